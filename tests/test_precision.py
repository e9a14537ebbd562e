"""float32: the same problem as float64 (issue 51's GPU rows).

On recent GPUs JAX computes float32 products with TensorFloat-32 inputs unless told
otherwise; the public functions trace under full precision instead (_runtime/precision.py).
CPU runs cannot see the difference in the numbers, so the traced programs are checked.
"""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import elastic_jax as ej
from elastic_jax import shapes
from elastic_jax._geometry.numerics import safe_sqrt

METRIC = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)


def _dot_precisions(fn, *args) -> list[str]:
    """The precision of every dot_general in fn's program, sub-programs included."""
    found = []

    def walk(jaxpr):
        for eqn in jaxpr.eqns:
            if eqn.primitive.name == "dot_general":
                found.append(str(eqn.params["precision"]))
            for value in eqn.params.values():
                for sub in value if isinstance(value, (list, tuple)) else (value,):
                    inner = getattr(sub, "jaxpr", sub)
                    if hasattr(inner, "eqns"):
                        walk(inner)

    walk(jax.make_jaxpr(fn)(*args).jaxpr)
    return found


@pytest.mark.caller_precision  # the caller's own products keep JAX's default
def test_public_functions_trace_float32_products_at_full_precision():
    f1 = shapes.sample(shapes.bumpy, 7, 13).astype(jnp.float32)
    f2 = shapes.sample(shapes.ellipsoid, 7, 13).astype(jnp.float32)
    path = ej.straight_path(f1, f2, 4)
    rotation = jnp.asarray(shapes.random_rotation(1), jnp.float32)

    def work(path, rotation):
        turned = jnp.einsum("ij,tjmn->timn", rotation, path)  # the caller's own product
        moved = ej.reparametrize(path[1], ej.sphere_points(7, 13), method="spline")
        return ej.path_energy(METRIC, turned) + ej.surface_area(moved)

    def public(path, rotation):
        return ej.path_energy(METRIC, path) + ej.surface_area(
            ej.reparametrize(path[1], ej.sphere_points(7, 13), method="spline")
        )

    inside = _dot_precisions(public, path, rotation)
    assert inside and all("HIGHEST" in p for p in inside), inside
    # The caller's product outside the package keeps JAX's default (None).
    assert "None" in _dot_precisions(work, path, rotation)
    # A precision the caller chose is kept, not overridden.
    with jax.default_matmul_precision("tensorfloat32"):
        chosen = _dot_precisions(public, path, rotation)
    assert chosen and not any("HIGHEST" in p for p in chosen), chosen
    # Every public function is wrapped (a new one added without it would trace at TF32).
    # io's too (its sphere map and grid reads are products; the commands call them).
    for module in (ej, ej.io):
        for name in module.__all__:
            obj = getattr(module, name)
            if callable(obj) and not isinstance(obj, type):
                assert hasattr(obj, "__wrapped__"), name


def test_float32_shape_geodesic_is_float64s_problem():
    # The spline's pole smoothing once came in as a numpy float64 scalar: float32 inputs
    # met it as a float64 tangent (TypeError under strict promotion, float64 otherwise).
    f1 = shapes.sample(shapes.bumpy, 9, 17)
    f2 = shapes.sample(
        shapes.ellipsoid, 9, 17, axes=(1.2, 0.9, 0.7), rotation=shapes.random_rotation(2)
    )
    options = ej.ShapeOptions(degree=2, vf_degree=2, n_times=3, rtol=None)
    d = {}
    for dtype in (jnp.float64, jnp.float32):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ej.ConvergenceWarning)
            res = ej.shape_geodesic(f1.astype(dtype), f2.astype(dtype), METRIC, options=options)
        assert res.distance.dtype == dtype and res.path.dtype == dtype
        d[dtype] = float(res.distance)
    # Measured 0.569328 against 0.569353 (4.4e-5): the same minimum, at float32's resolution.
    assert abs(d[jnp.float32] - d[jnp.float64]) <= 0.01 * d[jnp.float64]


def test_a_nonfinite_energy_is_not_a_zero_distance():
    x = jnp.asarray([4.0, 0.0, -1e-18, jnp.nan, jnp.inf])
    np.testing.assert_array_equal(np.asarray(safe_sqrt(x))[:3], [2.0, 0.0, 0.0])
    assert np.isnan(float(safe_sqrt(x)[3])) and float(safe_sqrt(x)[4]) == np.inf
    assert float(jax.grad(lambda t: safe_sqrt(t))(0.0)) == 0.0  # finite at 0
