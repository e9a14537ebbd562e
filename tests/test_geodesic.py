import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import elastic_jax as ej
from elastic_jax import shapes
from elastic_jax._geodesics.geodesic import _straight_frames, solver_scaling
from elastic_jax._geometry.bases import basis_np, perturbed_frames
from elastic_jax._geometry.energy import frame_energy

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
    # docs/math.md §3: the discretization error of the straight line is 7.1e-3 in energy at 25 x 49.
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
    # (2.2, 1.5, 1.1 percent at N = 7, 10, 13 here); midpoint and central are symmetric.
    there = ej.geodesic(f1, f2, METRIC, degree=5, n_times=10, scheme="forward")
    back = ej.geodesic(f2, f1, METRIC, degree=5, n_times=10, scheme="forward")
    assert abs(float(back.distance) - float(there.distance)) / float(there.distance) < 0.02
    there = ej.geodesic(f1, f2, METRIC, **SETTINGS)
    back = ej.geodesic(f2, f1, METRIC, **SETTINGS)
    assert relerr(back.distance, there.distance) < 1e-6
    there = ej.geodesic(f1, f2, METRIC, scheme="central", **SETTINGS)
    back = ej.geodesic(f2, f1, METRIC, scheme="central", **SETTINGS)
    assert relerr(back.distance, there.distance) < 1e-9
    same = ej.geodesic(f1, f1, METRIC, **SETTINGS)
    assert float(same.distance) == 0.0 and bool(same.converged)


@pytest.mark.slow
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


@pytest.mark.slow
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


# Mirror-symmetric pair: BFGS from the straight line stays in the symmetric subspace and,
# under the forward scheme, stops at a saddle of the discrete energy (docs/math.md §9).
SADDLE = {"degree": 3, "n_times": 5}


@pytest.fixture(scope="module")
def saddle_pair():
    return shapes.sample(shapes.sphere, 13, 25), shapes.sample(shapes.bent_cylinder, 13, 25)


@pytest.fixture(scope="module")
def saddle(saddle_pair):
    return ej.geodesic(*saddle_pair, METRIC, scheme="forward", saddle_checks=0, **SADDLE)


@pytest.fixture(scope="module")
def escaped(saddle_pair):
    return ej.geodesic(*saddle_pair, METRIC, scheme="forward", saddle_checks=2, **SADDLE)


@pytest.fixture(scope="module")
def midpoint(saddle_pair):
    return ej.geodesic(*saddle_pair, METRIC, **SADDLE)  # the defaults: midpoint, one check


def _scaled_objective(f1, f2, degree, n_times, scheme):
    """The whitened objective the solver minimizes, and the map coefficients -> its z."""
    m, n = f1.shape[-2:]
    dframe = jnp.asarray(basis_np(m, n, degree)[1], f1.dtype)
    scaling = solver_scaling(METRIC, f1, f2, dframe, n_times, scheme)
    straight = _straight_frames(f1, f2, n_times)

    def objective(z):
        frames = perturbed_frames(straight, scaling.coefficients(z), dframe)
        return frame_energy(METRIC, *frames, scheme) / scaling.energy_scale

    return objective, scaling.whitened


def _refined_in_time(path, times):
    """The path with each time step halved `times` times (linear interpolation)."""
    for _ in range(times):
        steps = jnp.stack([path[:-1], 0.5 * (path[:-1] + path[1:])], axis=1)
        path = jnp.concatenate([steps.reshape(-1, *path.shape[1:]), path[-1:]])
    return path


@pytest.mark.slow
def test_the_forward_scheme_stops_at_a_saddle_and_its_escape_is_an_artifact(
    saddle_pair, saddle, escaped
):
    # The old answer: a stationary point with a direction of strongly negative curvature.
    assert float(saddle.energy) == pytest.approx(27.8115, rel=1e-5)
    assert float(saddle.min_curvature) < -1.0
    assert bool(saddle.converged)  # 0 reports the estimate only
    unchecked = ej.geodesic(*saddle_pair, METRIC, scheme="forward", saddle_checks=None, **SADDLE)
    # The same minimization: the same steps, and the same energy up to the last bits
    # (two programs, fused differently: measured 1 ulp apart).
    assert relerr(unchecked.energy, saddle.energy) < 1e-14
    assert int(unchecked.num_steps) == int(saddle.num_steps)
    assert bool(jnp.isnan(unchecked.min_curvature))
    # The escape reaches the forward energy's minimum 26.50, in float64 and float32 alike...
    assert float(escaped.energy) == pytest.approx(26.5019, rel=1e-3)
    assert bool(escaped.converged) and float(escaped.min_curvature) > 0
    assert int(escaped.num_steps) > int(saddle.num_steps)  # every minimization counted
    f1, f2 = (f.astype(jnp.float32) for f in saddle_pair)
    single = ej.geodesic(f1, f2, METRIC, scheme="forward", saddle_checks=2, **SADDLE)
    assert single.energy.dtype == jnp.float32 and bool(single.converged)
    assert relerr(single.distance, escaped.distance) < 1e-3
    # ... but that minimum exploits the coarse time steps: the same path refined to 2 and 4
    # times the time points (the continuum's side) has 28.83 and 28.85, 9 % above.
    for times, energy in ((1, 28.825), (2, 28.854)):
        refined = _refined_in_time(escaped.path, times)
        assert float(ej.path_energy(METRIC, refined)) == pytest.approx(energy, rel=1e-3)


@pytest.mark.slow
def test_the_midpoint_solution_is_a_minimum_that_refinement_keeps(saddle_pair, midpoint):
    # The default scheme: a minimum (positive curvature) from the same symmetric start.
    assert bool(midpoint.converged)
    assert float(midpoint.min_curvature) > 0.1
    assert float(midpoint.energy) == pytest.approx(23.2711, rel=1e-4)
    # Refined in time it moves by 1.3 and 1.6 %; solved at N = 9 by 1e-4.
    for times in (1, 2):
        refined = float(ej.path_energy(METRIC, _refined_in_time(midpoint.path, times)))
        assert 0 < refined / float(midpoint.energy) - 1 < 0.02
    finer = ej.geodesic(*saddle_pair, METRIC, degree=3, n_times=9)
    assert relerr(finer.energy, midpoint.energy) < 1e-3
    # float32 and float64 agree.
    f1, f2 = (f.astype(jnp.float32) for f in saddle_pair)
    single = ej.geodesic(f1, f2, METRIC, **SADDLE)
    assert single.energy.dtype == jnp.float32 and bool(single.converged)
    assert relerr(single.distance, midpoint.distance) < 1e-3
    # Batched: every item checks its own curvature; f1 = f2 stays exactly 0.
    f1, f2 = saddle_pair
    batched = jax.vmap(lambda g: ej.geodesic(f1, g, METRIC, **SADDLE))(jnp.stack([f2, f1]))
    assert relerr(batched.energy[0], midpoint.energy) < 1e-9
    assert float(batched.distance[1]) == 0.0 and bool(batched.converged.all())
    same = ej.geodesic(f1, f1, METRIC, **SADDLE)
    assert float(same.distance) == 0.0 and bool(same.converged)


def test_a_saddle_left_after_the_checks_is_not_converged(saddle_pair, monkeypatch):
    # Without trial lengths an escape cannot move: the saddle stays after every check.
    monkeypatch.setattr("elastic_jax._geodesics.geodesic._ESCAPE_LENGTHS", ())
    # The lengths are read when the solve is traced: drop the compiled solves before (one
    # compiled with the real lengths would be reused) and after (so is this one).
    jax.clear_caches()
    try:
        with pytest.warns(
            ej.ConvergenceWarning,
            match="2 saddle escapes: The solver met its tolerance at a saddle point",
        ):
            res = ej.geodesic(*saddle_pair, METRIC, scheme="forward", saddle_checks=2, **SADDLE)
    finally:
        jax.clear_caches()
    assert not bool(res.converged) and res.result == ej.RESULTS.saddle_point
    assert float(res.energy) == pytest.approx(27.8115, rel=1e-5)
    assert float(res.min_curvature) < -1.0


def test_min_curvature_matches_the_dense_hessian(saddle_pair, saddle, escaped, midpoint):
    for res, scheme in ((saddle, "forward"), (escaped, "forward"), (midpoint, "midpoint")):

        @jax.jit
        def dense_hessian(coefficients, scheme=scheme):
            objective, whitened = _scaled_objective(*saddle_pair, **SADDLE, scheme=scheme)
            z = whitened(coefficients)
            return jax.hessian(objective)(z).reshape(z.size, z.size)

        lowest = float(np.linalg.eigvalsh(np.asarray(dense_hessian(res.coefficients)))[0])
        error = float(res.min_curvature) - lowest
        # A Ritz value bounds the smallest eigenvalue from above (up to rounding).
        assert error > -1e-9
        if lowest < 0:
            # -2.108, separated from the next (-1.506): 24 steps resolve it to rounding.
            assert error < 1e-8
        else:
            # Minima sit at the low end of a cluster of a spectrum reaching ~28 (135
            # variables): 24 steps leave at most 1e-2, 0.5 % of the Hessian's scale ~2.
            assert error < 1e-2


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
    with pytest.warns(ej.ConvergenceWarning, match="stopped after 3 steps") as caught:
        res = ej.geodesic(*cylinders, METRIC, max_steps=3, **SETTINGS)
    # Attributed to this line, past the package's own frames (the public functions'
    # precision wrapper among them).
    assert caught[0].filename == __file__
    assert not bool(res.converged)
    assert "maximum number of steps" in res.message
    assert float(res.energy) < float(res.straight_energy)
    # The package's own callers use the same solve without the warning (they report
    # each solve's status in their records): the same numbers to the last bit.
    from elastic_jax._geodesics.geodesic import solve_geodesic

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        quiet = solve_geodesic(*cylinders, METRIC, max_steps=3, **SETTINGS)
    assert not bool(quiet.converged) and float(quiet.energy) == float(res.energy)


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
    for bad in (-1, 1.5, True):
        with pytest.raises(ValueError, match="saddle_checks must be an integer >= 0"):
            ej.geodesic(f1, f2, METRIC, saddle_checks=bad)
    with pytest.raises(ValueError, match="one surface"):
        ej.geodesic(jnp.stack([f1, f1]), jnp.stack([f2, f2]), METRIC)
