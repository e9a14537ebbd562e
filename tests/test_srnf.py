import jax
import jax.numpy as jnp
import numpy as np
import pytest

import elastic_jax as ej
from elastic_jax import shapes

from .conftest import relerr

SRNF = ej.SplitMetric(0.0, 0.5, 1.0, 0.0)


def _q(alpha):
    """Pointwise SRNF of a 3 x 2 matrix: (a2 x a1) / |a1 x a2|^(1/2)."""
    normal = jnp.cross(alpha[..., 1], alpha[..., 0])
    return normal / jnp.linalg.norm(normal, axis=-1, keepdims=True) ** 0.5


def test_srnf_pulls_back_to_the_split_metric_pointwise():
    rng = np.random.default_rng(3)
    alpha = rng.standard_normal((400, 3, 2))
    xi = rng.standard_normal((400, 3, 2))
    _, dq = jax.jvp(_q, (alpha,), (xi,))
    lhs = jnp.sum(dq**2, axis=-1)
    rhs = ej.split_inner(SRNF, alpha, xi, xi)
    assert float(jnp.max(jnp.abs(lhs - rhs) / rhs)) < 1e-10


def test_srnf_of_spheres():
    m, n = 25, 49
    for r in (0.5, 2.0):
        q = ej.srnf(shapes.sample(shapes.sphere, m, n, radius=r))
        exact = r * ej.sphere_points(m, n)
        # Central differences shrink the sphere's differential by sin(h)/h in each direction.
        assert relerr(q, exact) < 3e-3
    q1 = shapes.sample(shapes.sphere, m, n, radius=0.5)
    q2 = shapes.sample(shapes.sphere, m, n, radius=2.0)
    assert float(ej.srnf_distance(q1, q2)) == pytest.approx(np.sqrt(4 * np.pi) * 1.5, rel=1e-2)


def test_table1_on_a_smooth_path():
    """(0, 1/2, 1, 0) length of a path against the L2 length of its SRNF image (paper, Table 1).

    The SRNF polyline sum ||q_{k+1} - q_k|| is a midpoint rule in time; the forward length
    evaluates each speed at the left end, so their gap is first order with the known
    constant (s_0 - s_1) / (2 T L). The central and midpoint schemes remove it.
    """
    f1, f2 = shapes.sample(shapes.ellipsoid, 25, 49), shapes.sample(shapes.bumpy, 25, 49)
    v = f2 - f1
    s0 = float(jnp.sqrt(ej.metric_inner(SRNF, f1, v, v)))
    s1 = float(jnp.sqrt(ej.metric_inner(SRNF, f2, v, v)))
    gaps, central_gaps, midpoint_gaps, residuals = [], [], [], []
    for n_times in (13, 20, 99):
        path = ej.straight_path(f1, f2, n_times)
        srnf_length = float(ej.srnf_path_length(path))
        forward = float(ej.path_length(SRNF, path, scheme="forward"))
        central = float(ej.path_length(SRNF, path, scheme="central"))
        midpoint = float(ej.path_length(SRNF, path, scheme="midpoint"))
        gap = (forward - srnf_length) / srnf_length
        first_order = (s0 - s1) / (2 * (n_times - 1) * srnf_length)
        gaps.append(abs(gap))
        central_gaps.append(abs(central - srnf_length) / srnf_length)
        midpoint_gaps.append(abs(midpoint - srnf_length) / srnf_length)
        residuals.append(abs(gap - first_order))
    assert gaps[0] > gaps[1] > gaps[2]
    assert central_gaps[0] > central_gaps[1] > central_gaps[2]
    assert central_gaps[2] < 1e-4
    assert residuals[2] < 1e-4 and residuals[2] < 0.01 * gaps[2]
    # Midpoint: second order, 2.6e-5, 1.0e-5, 3.9e-7 (ratios (19/12)^2 and (98/19)^2).
    for (t0, g0), (t1, g1) in zip(
        ((12, midpoint_gaps[0]), (19, midpoint_gaps[1])),
        ((19, midpoint_gaps[1]), (98, midpoint_gaps[2])),
        strict=True,
    ):
        assert g0 / g1 == pytest.approx((t1 / t0) ** 2, rel=0.05)


@pytest.mark.data
def test_table1_on_the_cats(cats, capsys):
    rows = []
    for n_times in (13, 20, 99):
        path = ej.straight_path(*cats, n_times)
        srnf_length = float(ej.srnf_path_length(path))
        length = float(ej.path_length(SRNF, path, scheme="forward"))
        rows.append((n_times, length, srnf_length, abs(length - srnf_length) / srnf_length))
    with capsys.disabled():
        print("\nTable 1, cat1 -> cat2 (50 x 99): N, (0,1/2,1,0) length, SRNF L2 length, rel. gap")
        for row in rows:
            print(f"  {row[0]:3d}  {row[1]:.8f}  {row[2]:.8f}  {row[3]:.2e}")
    # docs/math.md §3: such lines pass near non-immersed surfaces, so the gap need not shrink;
    # the authors' code gives 6.4e-3, 2.4e-2, 6.6e-3.
    assert all(row[3] < 3e-2 for row in rows)
    assert rows[0][1] == pytest.approx(1.6251290345, rel=1e-8)


@pytest.mark.data
def test_srnf_distance_is_below_the_straight_line_length(cats):
    lower = float(ej.srnf_distance(*cats))
    length = float(ej.path_length(SRNF, ej.straight_path(*cats, 99)))
    assert lower < length
    # q is homogeneous of degree 1 in f.
    assert float(ej.srnf_distance(2 * cats[0], 2 * cats[1])) == pytest.approx(2 * lower, rel=1e-12)


def test_surface_area_and_center():
    m, n = 50, 99
    r = 1.7
    shift = jnp.asarray([[[0.3]], [[-2.0]], [[1.1]]])
    f = shapes.sample(shapes.sphere, m, n, radius=r) + shift
    assert float(ej.surface_area(f)) == pytest.approx(4 * np.pi * r**2, rel=2e-3)
    centered = ej.center(f)
    np.testing.assert_allclose(np.asarray(centered - (f - shift)), 0.0, atol=1e-13)
    g = shapes.sample(shapes.bumpy, m, n)
    weights = ej.integrate(jnp.ones((m, n)))
    moved = ej.center(g + shift)
    assert relerr(ej.center(moved), moved) < 1e-14
    assert float(weights) > 0
