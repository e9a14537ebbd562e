import jax
import jax.numpy as jnp
import numpy as np
import pytest

import elastic_jax as ej
from elastic_jax import shapes

from .conftest import relerr

M, N = 25, 49
METRIC = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)
SETTINGS = {"degree": 5, "n_times": 7}


@pytest.fixture(scope="module")
def cylinders():
    return (
        shapes.sample(shapes.bent_cylinder, M, N, curvature=0.0),
        shapes.sample(shapes.bent_cylinder, M, N, curvature=0.6, half_length=1.2),
    )


@pytest.fixture(scope="module")
def forward(cylinders):
    return ej.geodesic(*cylinders, METRIC, **SETTINGS)


def test_concentric_spheres():
    r1, r2, b = 0.7, 1.6, 1.0
    f1 = shapes.sample(shapes.sphere, M, N, radius=r1)
    f2 = shapes.sample(shapes.sphere, M, N, radius=r2)
    res = ej.geodesic(f1, f2, METRIC, **SETTINGS)
    exact = np.sqrt(8 * np.pi * b) * (r2 - r1)
    assert bool(res.converged)
    # MATH.md 3: the discretization error of the straight line is 7.1e-3 in energy at 25 x 49.
    assert abs(float(res.distance) - exact) / exact < 5e-3
    assert float(res.energy) <= float(res.straight_energy) * (1 + 1e-12)
    assert float(jnp.abs(res.coefficients).max()) < 1e-3 * r2


def test_energy_drops_below_the_straight_line(forward):
    assert bool(forward.converged)
    assert float(forward.energy) < 0.9 * float(forward.straight_energy)
    assert float(forward.distance) ** 2 == pytest.approx(float(forward.energy), rel=1e-14)
    # The returned path carries exactly the energy the solver minimized.
    assert float(ej.path_energy(METRIC, forward.path)) == pytest.approx(
        float(forward.energy), rel=1e-12
    )
    assert forward.path.shape == (7, 3, M, N)
    assert forward.coefficients.shape == (5, 3 * 35)


def test_symmetry_and_zero_distance(cylinders):
    f1, f2 = cylinders
    # The forward scheme weighs each step at its start: its asymmetry is O(1/T)
    # (2.2, 1.5, 1.1 percent at N = 7, 10, 13 here); the central scheme is symmetric.
    there = ej.geodesic(f1, f2, METRIC, degree=5, n_times=10)
    back = ej.geodesic(f2, f1, METRIC, degree=5, n_times=10)
    assert abs(float(back.distance) - float(there.distance)) / float(there.distance) < 0.02
    there = ej.geodesic(f1, f2, METRIC, scheme="central", **SETTINGS)
    back = ej.geodesic(f2, f1, METRIC, scheme="central", **SETTINGS)
    assert relerr(back.distance, there.distance) < 1e-9
    same = ej.geodesic(f1, f1, METRIC, **SETTINGS)
    assert float(same.distance) == 0.0 and bool(same.converged)


def test_bfgs_and_lbfgs_agree(cylinders, forward):
    other = ej.geodesic(*cylinders, METRIC, solver="lbfgs", **SETTINGS)
    assert bool(other.converged)
    assert relerr(other.energy, forward.energy) < 1e-3


def test_srnf_lower_bound_and_straight_line_upper_bound():
    srnf = ej.SplitMetric(0.0, 0.5, 1.0, 0.0)
    f1, f2 = shapes.sample(shapes.ellipsoid, M, N), shapes.sample(shapes.bumpy, M, N)
    res = ej.geodesic(f1, f2, srnf, **SETTINGS)
    straight_length = float(ej.path_length(srnf, ej.straight_path(f1, f2, SETTINGS["n_times"])))
    lower = float(ej.srnf_distance(f1, f2))
    assert lower <= float(res.distance) <= straight_length
    assert float(res.distance) < straight_length * 0.999


def test_vmap_over_targets_equals_a_loop(cylinders):
    f1, f2 = cylinders
    targets = jnp.stack(
        [
            f2,
            shapes.sample(shapes.bent_cylinder, M, N, curvature=0.3, radius=0.6),
            shapes.sample(shapes.bent_cylinder, M, N, curvature=-0.5, half_length=1.8),
        ]
    )
    solve = lambda g: ej.geodesic(f1, g, METRIC, **SETTINGS)  # noqa: E731
    batched = jax.vmap(solve)(targets)
    looped = [solve(g) for g in targets]
    assert batched.path.shape == (3, 7, 3, M, N)
    for i, res in enumerate(looped):
        assert relerr(batched.energy[i], res.energy) < 1e-9
        assert relerr(batched.path[i], res.path) < 1e-6
        assert bool(batched.converged[i]) == bool(res.converged)


def test_warm_start_and_multiresolution(cylinders, forward):
    warm = ej.geodesic(*cylinders, METRIC, init=forward.coefficients, **SETTINGS)
    assert int(warm.num_steps) < int(forward.num_steps) // 2
    assert relerr(warm.energy, forward.energy) < 1e-8
    multi = ej.geodesic(*cylinders, METRIC, schedule=[(3, 4)], **SETTINGS)
    assert bool(multi.converged)
    assert relerr(multi.energy, forward.energy) < 1e-5
    coarse_grid = ej.geodesic(*cylinders, METRIC, schedule=[(3, 4, 13, 25)], **SETTINGS)
    assert bool(coarse_grid.converged)
    assert relerr(coarse_grid.energy, forward.energy) < 1e-5


def test_upsampling_keeps_the_perturbation():
    rng = np.random.default_rng(0)
    coarse = jnp.asarray(rng.standard_normal((3, 3 * 15)))  # degree 3, N = 5
    fine = ej.upsample_coefficients(coarse, 3, 5, 9)
    assert fine.shape == (7, 3 * 35)
    basis3, basis5 = ej.surface_basis(M, N, 3), ej.surface_basis(M, N, 5)
    # Time points of N = 5 are every other point of N = 9.
    for k_old, k_new in [(0, 1), (1, 3), (2, 5)]:
        old = jnp.einsum("j,jimn->imn", coarse[k_old], basis3)
        new = jnp.einsum("j,jimn->imn", fine[k_new], basis5)
        np.testing.assert_allclose(new, old, atol=1e-12)
    np.testing.assert_allclose(fine[0], 0.5 * fine[1], atol=1e-12)  # halfway from the zero end


def test_max_steps_gives_converged_false_and_a_warning(cylinders):
    with pytest.warns(ej.ConvergenceWarning, match="stopped after 3 steps"):
        res = ej.geodesic(*cylinders, METRIC, max_steps=3, **SETTINGS)
    assert not bool(res.converged)
    assert "maximum number of steps" in res.message
    assert float(res.energy) < float(res.straight_energy)


def test_float32(cylinders, forward):
    f1, f2 = (f.astype(jnp.float32) for f in cylinders)
    res = ej.geodesic(f1, f2, METRIC, **SETTINGS)
    assert res.path.dtype == jnp.float32 and bool(res.converged)
    assert relerr(res.energy, forward.energy) < 1e-3


def test_errors(cylinders):
    f1, f2 = cylinders
    with pytest.raises(ValueError, match="same grid"):
        ej.geodesic(f1, shapes.sample(shapes.bumpy, 13, 25), METRIC)
    with pytest.raises(ValueError, match="too high for the 25 x 49 grid: the limit is 22"):
        ej.geodesic(f1, f2, METRIC, degree=30)
    with pytest.raises(ValueError, match="n_times must be an integer >= 3"):
        ej.geodesic(f1, f2, METRIC, n_times=2)
    with pytest.raises(ValueError, match="solver must be one of"):
        ej.geodesic(f1, f2, METRIC, solver="newton")
    with pytest.raises(ValueError, match=r"init must have shape \(n_times - 2, L\) = \(11, 189\)"):
        ej.geodesic(f1, f2, METRIC, init=jnp.zeros((3, 3)))
    with pytest.raises(ValueError, match="one surface"):
        ej.geodesic(jnp.stack([f1, f1]), jnp.stack([f2, f2]), METRIC)
