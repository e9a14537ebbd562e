import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

import elastic_jax as ej
from elastic_jax import shapes

from .conftest import relerr

# Zero or at least 1e-100 in magnitude: XLA flushes subnormal results to zero on CPU, so an
# input near the smallest normal (hypothesis found xi = 2.2e-308) has parts whose products
# vanish, and no relative bound can hold there; the identities are tested at every scale
# that float64 arithmetic keeps.
entries = st.floats(-2.0, 2.0, allow_nan=False, allow_subnormal=False).filter(
    lambda x: x == 0.0 or abs(x) >= 1e-100
)
matrices = arrays(np.float64, (3, 2), elements=entries)


def _well_conditioned(alpha):
    s = np.linalg.svd(alpha, compute_uv=False)
    return s[1] > 0.05 * s[0] and s[0] > 1e-3


@settings(max_examples=60, deadline=None)
@given(alpha=matrices.filter(_well_conditioned), xi=matrices)
def test_split_parts_sum_to_xi_and_are_orthogonal(alpha, xi):
    parts = ej.split_parts(alpha, xi)
    scale = max(np.abs(xi).max(), 1e-300)
    assert np.abs(sum(parts) - xi).max() <= 1e-12 * scale
    total = float(ej.base_inner(alpha, xi, xi))
    for i in range(4):
        for j in range(i + 1, 4):
            assert abs(float(ej.base_inner(alpha, parts[i], parts[j]))) <= 1e-12 * max(
                total, 1e-300
            )
    # Pythagoras: the four squared norms add up to the whole.
    norms = sum(float(ej.base_inner(alpha, p, p)) for p in parts)
    assert norms == pytest.approx(total, rel=1e-12, abs=1e-300)


@settings(max_examples=60, deadline=None)
@given(
    alpha=matrices.filter(_well_conditioned),
    xi=matrices,
    eta=matrices,
    abcd=st.tuples(*[st.floats(0.0, 3.0)] * 4).filter(any),
)
def test_fast_kernel_equals_the_decomposition(alpha, xi, eta, abcd):
    metric = ej.SplitMetric(*abcd)
    parts_x, parts_y = ej.split_parts(alpha, xi), ej.split_parts(alpha, eta)
    # Order of the parts: (m, vol, perp, 0); coefficients (a, b, c, d).
    reference = sum(
        k * float(ej.base_inner(alpha, px, py))
        for k, px, py in zip(abcd, parts_x, parts_y, strict=True)
    )
    # Each norm taken of the unit-scaled matrix and scaled back: xi with entries ~1e-174
    # has a squared norm below float64's range, which made this tolerance 0 (a flaky
    # hypothesis example: 4.5e-190 apart on values 2.7e-174).
    sx, sy = (max(float(np.abs(m).max()), 1e-300) for m in (xi, eta))
    norms = [
        np.sqrt(float(ej.base_inner(alpha, m / s, m / s))) * s for m, s in ((xi, sx), (eta, sy))
    ]
    scale = max(abcd) * norms[0] * norms[1]
    assert abs(float(ej.split_inner(metric, alpha, xi, eta)) - reference) <= 1e-11 * scale + 1e-200


@settings(max_examples=60, deadline=None)
@given(
    alpha=matrices.filter(_well_conditioned),
    xi=matrices,
    abcd=st.tuples(*[st.floats(0.0, 3.0)] * 4).filter(any),
)
def test_the_residuals_square_to_each_part_of_the_decomposition(alpha, xi, abcd):
    from elastic_jax._geometry.metric import split_residuals

    metric = ej.SplitMetric(*abcd)
    columns = [jnp.asarray(m[:, k, None, None]) for m in (alpha, xi) for k in range(2)]
    r2 = [float(r[0, 0]) ** 2 for r in split_residuals(metric, *columns)]
    # Residuals: shear twice, volume, rotation, the normal part twice; the parts of
    # split_parts: (m, vol, perp, 0) with coefficients (a, b, c, d).
    by_part = [r2[0] + r2[1], r2[2], r2[4] + r2[5], r2[3]]
    scale = max(float(np.abs(xi).max()), 1e-300)
    norm2 = float(ej.base_inner(alpha, xi / scale, xi / scale)) * scale**2
    for k, part, squares in zip(abcd, ej.split_parts(alpha, xi), by_part, strict=True):
        reference = k * float(ej.base_inner(alpha, part, part))
        assert abs(squares - reference) <= 1e-11 * max(abcd) * norm2 + 1e-200


@pytest.mark.parametrize("sine", [1e-2, 1e-3, 1e-4])
def test_float32_kernel_on_nearly_degenerate_frames(sine):
    """G_alpha(xi, xi) in float32 where alpha's columns are nearly parallel (the sine of
    their angle ``sine``, as at the folds that real shapes' paths pass near): never
    negative, and within 60 eps / sine of the float64 value. The kernel written with
    g^-1's entries multiplied out (the package's earlier form) had 127 negative values in 20000 at
    sine 1e-3 and a relative error of 3.1 (330 at 1e-4): an optimizer in float32 drove
    such energies below zero."""
    rng = np.random.default_rng(0)
    count = 20000
    a1 = rng.normal(size=(count, 3))
    away = rng.normal(size=(count, 3))
    away -= np.sum(away * a1, -1, keepdims=True) / np.sum(a1 * a1, -1, keepdims=True) * a1
    away /= np.linalg.norm(away, axis=-1, keepdims=True)
    length = rng.uniform(0.3, 3.0, size=(count, 1))
    a2 = length * a1 / np.linalg.norm(a1, axis=-1, keepdims=True) + sine * length * away
    alpha = np.stack([a1, a2], axis=-1)
    xi = rng.normal(size=(count, 3, 2))
    values = {}
    for dtype in (np.float64, np.float32):
        metric = ej.SplitMetric(*(dtype(k) for k in (1.0, 1.0, 0.1, 0.3)))
        values[dtype] = np.asarray(
            ej.split_inner(metric, alpha.astype(dtype), xi.astype(dtype), xi.astype(dtype))
        )
    exact, low = values[np.float64], values[np.float32].astype(np.float64)
    assert np.all(low >= 0.0)
    error = float(np.max(np.abs(low - exact) / exact))
    assert error <= 60 * float(np.finfo(np.float32).eps) / sine, error


def test_split_parts_batch_shapes():
    rng = np.random.default_rng(0)
    for batch in [(), (1,), (3, 2)]:
        alpha = rng.standard_normal(batch + (3, 2))
        xi = rng.standard_normal(batch + (3, 2))
        parts = ej.split_parts(alpha, xi)
        assert all(p.shape == batch + (3, 2) for p in parts)
        assert ej.split_inner(ej.SplitMetric(1, 1, 1, 1), alpha, xi, xi).shape == batch
        np.testing.assert_allclose(sum(parts), xi, atol=1e-12)


def test_theorem2_pointwise():
    rng = np.random.default_rng(1)
    alpha = rng.standard_normal((500, 3, 2))
    xi, eta = rng.standard_normal((2, 500, 3, 2))
    from elastic_jax._geometry.metric import _elastic_pointwise

    for a, b, c in [(1.0, 1.0, 0.1), (0.0, 0.5, 1.0), (2.0, 0.3, 0.7)]:
        split = ej.split_inner(ej.SplitMetric(a, b, c, 0.0), alpha, xi, eta)
        elastic = _elastic_pointwise(a / 4, (b - a) / 8, c, alpha, xi, eta)
        scale = np.sqrt(
            np.abs(ej.split_inner(ej.SplitMetric(a, b, c, 0.0), alpha, xi, xi))
            * np.abs(ej.split_inner(ej.SplitMetric(a, b, c, 0.0), alpha, eta, eta))
        )
        assert np.max(np.abs(split - elastic) / scale) < 1e-10


def test_theorem2_integrated_on_real_shapes(cats):
    f1, f2 = cats
    u = f2 - f1
    v = ej.center(f2) - 0.5 * f1
    for a, b, c in [(1.0, 1.0, 0.1), (0.0, 0.5, 1.0)]:
        split = ej.metric_inner(ej.SplitMetric(a, b, c, 0.0), f1, u, v)
        elastic = ej.elastic_metric_inner(a / 4, (b - a) / 8, c, f1, u, v)
        assert relerr(split, elastic) < 1e-10
    # From Jermyn's coefficients back to the split ones.
    metric = ej.SplitMetric.from_elastic(0.25, 0.0, 0.1)
    assert (metric.a, metric.b, metric.c, metric.d) == (1.0, 1.0, 0.1, 0.0)


def _rotation(seed):
    return jnp.asarray(shapes.random_rotation(seed))


def test_invariance_under_rigid_motions(cats):
    f, g = cats
    u, v = g - f, ej.center(g) * 0.3 + f**2
    metric = ej.SplitMetric(1.0, 0.7, 0.3, 0.2)
    value = ej.metric_inner(metric, f, u, v)
    for seed in range(3):
        r = _rotation(seed)
        shift = jnp.asarray([[[0.7]], [[-1.3]], [[2.1]]])

        def rot(x, r=r):
            return jnp.einsum("ij,jmn->imn", r, x)

        moved = ej.metric_inner(metric, rot(f) + shift, rot(u), rot(v))
        assert relerr(moved, value) < 1e-10


@pytest.mark.parametrize("s", [5e-3, 1e3])
def test_scale_homogeneity(s):
    f = shapes.sample(shapes.bumpy, 25, 49)
    u = shapes.sample(shapes.ellipsoid, 25, 49) - f
    metric = ej.SplitMetric(1.0, 1.0, 0.1, 0.5)
    assert (
        relerr(
            ej.metric_inner(metric, s * f, s * u, s * u), s**2 * ej.metric_inner(metric, f, u, u)
        )
        < 1e-12
    )


def test_concentric_spheres_closed_form():
    # Energy of the straight line between concentric spheres: 8 pi b (r2 - r1)^2 (docs/math.md §3).
    r1, r2 = 0.8, 1.9
    errors = []
    for m, n in [(25, 49), (50, 99)]:
        f1 = shapes.sample(shapes.sphere, m, n, radius=r1)
        f2 = shapes.sample(shapes.sphere, m, n, radius=r2)
        path = ej.straight_path(f1, f2, 7)
        for b in (1.0, 0.3):
            metric = ej.SplitMetric(1.0, b, 0.1, 0.4)
            exact = 8 * np.pi * b * (r2 - r1) ** 2
            err = abs(float(ej.path_energy(metric, path)) - exact) / exact
            err_c = abs(float(ej.path_energy(metric, path, scheme="central")) - exact) / exact
            assert err_c == pytest.approx(err, rel=1e-9)  # constant speed: both schemes agree
        errors.append(err)
    assert errors[0] < 1e-2
    assert errors[1] < errors[0] / 3


def _field(x):
    return jnp.stack([x[0] * x[1] + 0.3, jnp.sin(2 * x[2]), x[0] ** 2 - 0.5 * x[1]])


def test_reparametrization_invariance_converges():
    r = _rotation(7)
    metric = ej.SplitMetric(1.0, 1.0, 0.2, 0.3)
    errors = []
    for m, n in [(13, 25), (25, 49), (50, 99)]:
        f, u = shapes.sample(shapes.bumpy, m, n), shapes.sample(_field, m, n)
        fh = shapes.sample(shapes.bumpy, m, n, rotation=r)
        uh = shapes.sample(_field, m, n, rotation=r)
        g, gh = ej.metric_inner(metric, f, u, u), ej.metric_inner(metric, fh, uh, uh)
        errors.append(abs(float(gh - g)) / float(g))
    assert errors[1] < errors[0] / 2 and errors[2] < errors[1] / 2
    assert errors[2] < 1e-2


def test_metric_inner_is_symmetric_and_bilinear():
    f = shapes.sample(shapes.bent_cylinder, 25, 49)
    u = shapes.sample(_field, 25, 49)
    v = u + shapes.sample(shapes.bumpy, 25, 49)
    metric = ej.SplitMetric(1.0, 2.0, 0.5, 0.25)
    uv, vu = ej.metric_inner(metric, f, u, v), ej.metric_inner(metric, f, v, u)
    assert abs(float(uv)) > 0.1 * float(
        jnp.sqrt(ej.metric_inner(metric, f, u, u) * ej.metric_inner(metric, f, v, v))
    )
    assert relerr(uv, vu) < 1e-13
    lhs = ej.metric_inner(metric, f, 2 * u + v, v)
    rhs = 2 * uv + ej.metric_inner(metric, f, v, v)
    assert relerr(lhs, rhs) < 1e-12
    batch = ej.metric_inner(metric, jnp.stack([f, f]), jnp.stack([u, v]), jnp.stack([v, v]))
    assert relerr(batch[0], uv) < 1e-14


@pytest.mark.parametrize(
    ("args", "message"),
    [
        ((-1.0, 1.0, 1.0, 0.0), "coefficient a=-1.0 is negative"),
        ((1.0, float("nan"), 1.0, 0.0), "coefficient b=nan is not finite"),
        ((1.0, 1.0, float("inf"), 0.0), "coefficient c=inf is not finite"),
        ((0, 0, 0, 0), "all four coefficients are zero"),
    ],
)
def test_split_metric_rejects_bad_coefficients(args, message):
    with pytest.raises(ValueError, match=message):
        ej.SplitMetric(*args)


def test_split_metric_is_a_pytree_with_traced_leaves():
    metric = ej.SplitMetric(1, 2, 3, 4)
    leaves, tree = jax.tree_util.tree_flatten(metric)
    assert leaves == [1.0, 2.0, 3.0, 4.0]
    doubled = jax.jit(lambda m: jax.tree_util.tree_map(lambda x: 2 * x, m))(metric)
    assert [float(x) for x in jax.tree_util.tree_leaves(doubled)] == [2.0, 4.0, 6.0, 8.0]
