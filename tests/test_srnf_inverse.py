import jax
import jax.numpy as jnp
import numpy as np
import pytest

import elastic_jax as ej
from elastic_jax import ConvergenceWarning, InputError, shapes, srnf_geodesic, srnf_invert

from .conftest import relerr

M, N = 13, 25
# One set of static options per grid, so that the tests share compiled solves.
GEODESIC = {"degrees": (2, 4)}


def _area_weighted_centroid(f):
    return np.asarray(f - ej.center(f))[:, 0, 0]


def test_in_span_target_is_recovered():
    """q = Q(f0 + sum_j c_j S_j) with a known c at degree 3: the inversion from f0 finds c."""
    f0 = ej.sphere_points(M, N)
    basis = ej.surface_basis(M, N, 3)
    c = 0.05 * np.random.default_rng(0).standard_normal(basis.shape[0])
    target = f0 + jnp.einsum("j,jimn->imn", jnp.asarray(c), basis)
    q = ej.srnf(target)
    res = srnf_invert(q, f0=f0, degrees=(2, 3), tol=1e-10)
    assert bool(res.converged)
    # Measured: surface 7.0e-11, coefficients 5.1e-11, relative residual 4.6e-11.
    assert relerr(res.surface, ej.center(target)) < 1e-8
    assert float(jnp.max(jnp.abs(res.coefficients - c))) < 1e-8
    assert float(res.relative_residual) < 1e-9
    assert res.coefficients.shape == (3 * 15,)
    assert res.level_residuals.shape == (2,)
    # Degree 2 cannot hold the degree-3 part (0.40 of ||q|| measured); degree 3 can.
    assert float(res.level_residuals[0]) > 1e3 * float(res.level_residuals[1])
    # The returned surface is centred, and its SRNF is the reported residual away from q.
    assert np.max(np.abs(_area_weighted_centroid(res.surface))) < 1e-14
    assert float(ej.srnf_distance(res.surface, target)) == pytest.approx(
        float(res.residual), rel=1e-6, abs=1e-14
    )
    # The default start, the area-matched sphere, reaches the same surface here.
    default = srnf_invert(q, degrees=(2, 3), tol=1e-10)
    assert relerr(default.surface, ej.center(target)) < 1e-8


def test_ellipsoid_from_the_area_matched_sphere():
    ellipsoid = shapes.sample(shapes.ellipsoid, M, N)
    q = ej.srnf(ellipsoid)
    res = srnf_invert(q)
    assert bool(res.converged)
    # Measured: relative residual 7.2e-10 (tol 1e-8), surface 6.1e-10 from the ellipsoid.
    assert float(res.relative_residual) < 1e-8
    assert relerr(res.surface, ej.center(ellipsoid)) < 1e-8
    assert float(res.residual) == pytest.approx(
        float(res.relative_residual) * np.sqrt(float(ej.integrate(jnp.sum(q * q, axis=0)))),
        rel=1e-12,
    )
    # Units: the solve runs on the size q encodes, so a 1000 times smaller q takes the
    # same steps to the same (scaled) surface.
    small = srnf_invert(1e-3 * q)
    assert int(small.num_steps) == int(res.num_steps)
    assert relerr(small.surface, 1e-3 * res.surface) < 1e-9  # measured 1.0e-13
    assert float(small.relative_residual) < 1e-8
    # Traced (under jit) the solve runs in the same units: the same steps, the same
    # surface (before issue 31 a traced q was solved at scale 1, 1000 times too large).
    traced = jax.jit(lambda q: srnf_invert(q))(1e-3 * q)
    assert int(traced.num_steps) == int(small.num_steps)
    assert relerr(traced.surface, small.surface) < 1e-9


def test_float32():
    ellipsoid = shapes.sample(shapes.ellipsoid, M, N, dtype=jnp.float32)
    res = srnf_invert(ej.srnf(ellipsoid), degrees=(2,))
    assert res.surface.dtype == jnp.float32
    assert bool(res.converged)
    # Default tol 1e-4 in float32: measured relative residual 1.7e-5, surface 1.7e-5.
    assert float(res.relative_residual) < 1e-4
    assert relerr(res.surface, ej.center(ellipsoid)) < 1e-4


def test_bumpy_shape_coarse_to_fine():
    q = ej.srnf(shapes.sample(shapes.bumpy, 25, 49))
    res = srnf_invert(q, degrees=(2, 4, 7, 12))
    assert bool(res.converged)
    levels = np.asarray(res.level_residuals) / np.sqrt(float(ej.integrate(jnp.sum(q * q, 0))))
    # Truncation-limited: measured 0.147, 0.064, 8.0e-3, 3.7e-5 relative (issue 13's
    # prototype: 6.4e-4 at degree 12).
    assert np.all(np.diff(levels) < 0)
    assert float(res.relative_residual) < 2e-4
    assert levels[-1] == pytest.approx(float(res.relative_residual), rel=1e-12)


def test_geodesic_relations():
    """The SRNF image of the path is a polyline from q1 to q2 whose vertices lie within the
    residuals of the straight line: ||q1 - q2|| <= L <= ||q1 - q2|| + 2 sum r_k."""
    f1 = shapes.sample(shapes.ellipsoid, M, N) + jnp.asarray([0.3, -0.2, 0.1])[:, None, None]
    f2 = 1.3 * shapes.sample(shapes.bumpy, M, N)
    res = srnf_geodesic(f1, f2, 5, **GEODESIC)
    assert res.path.shape == (5, 3, M, N)
    assert bool(jnp.all(res.path[0] == f1)) and bool(jnp.all(res.path[-1] == f2))
    assert bool(res.converged) and bool(np.all(res.nodes_converged))
    assert float(res.srnf_distance) == pytest.approx(float(ej.srnf_distance(f1, f2)), rel=1e-12)
    assert float(res.srnf_length) == pytest.approx(float(ej.srnf_path_length(res.path)), rel=1e-12)
    # Measured: d = 2.1121 <= L = 2.1519 <= d + 2 sum r = 2.8486 (degree 4 truncates the
    # bumps: relative residuals 0.021, 0.035, 0.045 at t = 1/4, 1/2, 3/4).
    assert float(res.srnf_distance) <= float(res.srnf_length)
    assert float(res.srnf_length) <= float(res.srnf_distance + 2.0 * jnp.sum(res.residuals))
    assert float(res.residuals[0]) == 0.0 and float(res.residuals[-1]) == 0.0
    assert 0.0 < float(jnp.max(res.relative_residuals)) < 0.1
    # Q fixes no translation: the centroids move on the segment between the ends'.
    c1, c2 = _area_weighted_centroid(f1), _area_weighted_centroid(f2)
    for k, t in enumerate(np.linspace(0.0, 1.0, 5)):
        centroid = _area_weighted_centroid(res.path[k])
        assert np.max(np.abs(centroid - ((1 - t) * c1 + t * c2))) < 1e-12


def test_geodesic_between_concentric_spheres():
    """Q(r e1) = r Q(e1): the straight line between the SRNFs of concentric spheres is the
    SRNF of the spheres of radius (1 - t) r1 + t r2, so its inversion is exact."""
    r1, r2 = 0.7, 1.6
    f1 = shapes.sample(shapes.sphere, M, N, radius=r1)
    f2 = shapes.sample(shapes.sphere, M, N, radius=r2)
    res = srnf_geodesic(f1, f2, 5, **GEODESIC)
    # Measured: nodes within 1e-15 of the spheres, relative residuals 7e-16.
    for k, t in enumerate(np.linspace(0.0, 1.0, 5)):
        assert relerr(res.path[k], ((1 - t) * r1 + t * r2) * ej.sphere_points(M, N)) < 1e-8
    assert float(jnp.max(res.relative_residuals)) < 1e-8
    assert float(res.srnf_length) == pytest.approx(float(res.srnf_distance), rel=1e-8)


def test_unconverged_solve_warns():
    q = ej.srnf(shapes.sample(shapes.bumpy, M, N))
    with pytest.warns(ConvergenceWarning, match="srnf_invert"):
        res = srnf_invert(q, degrees=(2,), max_steps=2)
    assert not bool(res.converged)
    assert "maximum number of steps" in res.message.lower()


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"degrees": (4, 2)}, "degrees must be strictly increasing"),
        ({"degrees": (2, 2)}, "degrees must be strictly increasing"),
        ({"degrees": ()}, "degrees must be a non-empty sequence"),
        ({"degrees": "247"}, "degrees must be a non-empty sequence"),
        ({"degrees": (2, 11)}, r"degrees\[1\]=11 is too high for the 13 x 25 grid"),
        ({"degrees": (0, 2)}, r"degrees\[0\] must be an integer >= 1"),
        ({"degrees": (2.0,)}, r"degrees\[0\] must be an integer"),
        ({"solver": "newton"}, "solver must be one of"),
        ({"max_steps": 0}, "max_steps must be an integer >= 1"),
        ({"tol": -1.0}, "tol must be a positive finite number"),
        ({"f0": shapes.sample(shapes.sphere, M, 27)}, "f0 must have the shape and dtype of q"),
        ({"f0": np.zeros((3, 13, 25))}, "f0 is a single point"),
    ],
)
def test_invert_refuses_bad_options(kwargs, match):
    q = ej.srnf(shapes.sample(shapes.sphere, M, N))
    with pytest.raises(InputError, match=match):
        srnf_invert(q, **kwargs)


def test_refuses_bad_targets():
    q = np.asarray(ej.srnf(shapes.sample(shapes.sphere, M, N)))
    with pytest.raises(InputError, match="q must have shape"):
        srnf_invert(q[:2])
    with pytest.raises(InputError, match="q has an even number of columns"):
        srnf_invert(q[..., :-1])
    with pytest.raises(InputError, match="q must be one SRNF"):
        srnf_invert(np.stack([q, q]))
    bad = q.copy()
    bad[1, 4, 6] = np.nan
    with pytest.raises(InputError, match=r"q contains 1 non-finite value.*\(1, 4, 6\)"):
        srnf_invert(bad)
    with pytest.raises(InputError, match="q is zero at every interior point"):
        srnf_invert(np.zeros_like(q))
    with pytest.raises(InputError, match="q is complex"):
        srnf_invert(q.astype(complex))


def test_geodesic_refuses_bad_input():
    f1 = shapes.sample(shapes.sphere, M, N)
    f2 = shapes.sample(shapes.ellipsoid, M, N)
    with pytest.raises(InputError, match="n_times must be an integer >= 2"):
        srnf_geodesic(f1, f2, 1)
    with pytest.raises(InputError, match="f1 and f2 must share grid"):
        srnf_geodesic(f1, shapes.sample(shapes.sphere, 25, 49))
    with pytest.raises(InputError, match="degrees must be strictly increasing"):
        srnf_geodesic(f1, f2, 3, degrees=(3, 3))
    with pytest.raises(InputError, match="f2 contains"):
        srnf_geodesic(f1, f2.at[0, 3, 3].set(jnp.inf))


def test_two_time_points_are_the_ends():
    f1 = shapes.sample(shapes.sphere, M, N)
    f2 = shapes.sample(shapes.ellipsoid, M, N)
    res = srnf_geodesic(f1, f2, 2)
    assert bool(jnp.all(res.path == jnp.stack([f1, f2])))
    assert float(res.srnf_length) == pytest.approx(float(res.srnf_distance), rel=1e-12)
    assert res.residuals.shape == res.node_steps.shape == res.nodes_converged.shape == (2,)
    # Nothing was solved: converged, successful, no steps.
    assert bool(res.converged) and bool(res.result == ej.RESULTS.successful)
    assert int(res.num_steps) == 0 and res.message == ""
