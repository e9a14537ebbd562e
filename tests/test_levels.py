"""Inputs on grids of their own and resolved distances by levels of working grids
(docs/math.md §10)."""

import inspect
import warnings

import jax.numpy as jnp
import numpy as np
import pytest

import elastic_jax as ej
from elastic_jax import shapes
from elastic_jax._registration.levels import level_change, noise_distance, refinement_gap
from elastic_jax._registration.one_grid import working_grid_of

from .conftest import assert_area_bound

METRIC = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)
# One working grid unless a test asks for levels (rtol).
OPTIONS = ej.ShapeOptions(degree=4, vf_degree=4, n_times=5, rtol=None)


@pytest.mark.slow
def test_an_input_on_a_finer_grid_is_read_through_its_interpolant():
    """f2 given at 25 x 49 and solved on a 13 x 25 working grid: its interpolant is read
    at the working grid's points, which are points of the finer grid. With grid
    differences the pair is then the one given at 13 x 25 (parametrized distance to
    rounding); with the chain rule and spline reads f2's differential is its finer
    interpolant's, which the 13 x 25 one approximates (measured 0.08 % apart)."""
    rotation = shapes.random_rotation(1)
    f1 = shapes.sample(shapes.bumpy, 13, 25)
    coarse = shapes.sample(shapes.bumpy, 13, 25, rotation=rotation)
    fine = shapes.sample(shapes.bumpy, 25, 49, rotation=rotation)
    for differential, interpolation, rtol in (
        ("grid", "bicubic", 1e-12),
        ("chain", "spline", 5e-3),
    ):
        options = OPTIONS.replace(differential=differential, interpolation=interpolation)
        same = ej.shape_geodesic(f1, coarse, METRIC, modulo="rigid", options=options)
        mixed = ej.shape_geodesic(
            f1, fine, METRIC, modulo="rigid", options=options.replace(grid=(13, 25))
        )
        assert mixed.path.shape == same.path.shape == (5, 3, 13, 25)
        np.testing.assert_allclose(
            mixed.parametrized_distance, same.parametrized_distance, rtol=rtol
        )
        assert float(mixed.distance) < 0.05 * float(mixed.parametrized_distance)
        assert float(same.distance) < 0.05 * float(same.parametrized_distance)
        if differential == "grid":
            np.testing.assert_allclose(mixed.distance, same.distance, rtol=1e-3)


def test_the_default_working_grid_is_the_finer_input():
    f, g = jnp.zeros((3, 13, 25)), jnp.zeros((3, 25, 49))
    assert working_grid_of(OPTIONS, f, g) == working_grid_of(OPTIONS, g, f) == (25, 49)
    assert working_grid_of(OPTIONS.replace(grid=(9, 17)), f, g) == (9, 17)
    assert working_grid_of(OPTIONS, f, f) == (13, 25)


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"grid": (13, 24)}, "even number of columns"),
        ({"grid": 13}, "grid must hold grids"),
        ({"levels": ((25, 49), (13, 25))}, "from coarse to fine"),
        ({"levels": ()}, "from coarse to fine"),
        ({"rtol": -1.0}, "rtol must be"),
    ],
)
def test_grid_options_are_checked(changes, message):
    with pytest.raises(ej.InputError, match=message):
        OPTIONS.replace(**changes)


@pytest.mark.slow  # about 50 s on 2 cores (the default tier: the spheres' resolved matrix)
def test_spline_reads_make_the_chain_rule_meet_the_spheres_closed_form():
    """docs/math.md §9: a sphere of radius 2 read through a Moebius map (abs(a) = 0.3) and
    one of radius 3, rotated and translated, modulo rigid at 13 x 25: sqrt(8 pi) (3 - 2).
    With the chain rule, bicubic reads are 3.8 % low, below the area bound (the optimizer
    reads f1 where the interpolant's derivative is shortest), and spline reads about
    0.3 % low, the trapezoid rule's h^2 / 24 in phi (0.29 %)."""
    from elastic_jax._geometry.reparam import moebius

    e1 = ej.sphere_points(13, 25)
    f1 = 2.0 * moebius(e1, jnp.asarray([0.1, -0.2, 0.2]))
    f2 = (
        3.0 * jnp.einsum("ij,jmn->imn", shapes.random_rotation(22), e1)
        + jnp.asarray([1.0, -0.3, 0.4])[:, None, None]
    )
    exact = np.sqrt(8.0 * np.pi)
    errors = {}
    for interpolation in ("bicubic", "spline"):
        options = OPTIONS.replace(differential="chain", interpolation=interpolation)
        res = ej.shape_geodesic(f1, f2, METRIC, modulo="rigid", options=options)
        errors[interpolation] = abs(float(res.distance) / exact - 1.0)
        if interpolation == "spline":  # bicubic reads fall below the area bound
            assert_area_bound(res.distance, f1, f2, METRIC)
    assert errors["spline"] < 5e-3
    assert errors["spline"] < 0.2 * errors["bicubic"]


@pytest.mark.slow  # about 140 s on 2 cores (the default tier keeps the resolved matrix)
def test_levels_resolve_the_concentric_spheres():
    """Spheres of radii 1 and 2 (the second rotated, on a finer grid than the first) at
    the default rtol, levels from 13 x 25: the levels' distances approach the closed
    form sqrt(8 pi) (metric a = b = 1) and stop where two agree within rtol (the second,
    25 x 49); the estimate is their relative change."""
    f1 = shapes.sample(shapes.sphere, 13, 25, radius=1.0)
    f2 = shapes.sample(shapes.sphere, 25, 49, radius=2.0, rotation=shapes.random_rotation(3))
    levels = ((13, 25), *ej.ShapeOptions().levels)
    options = ej.ShapeOptions(degree=4, vf_degree=4, n_times=5, levels=levels)  # rtol 0.03
    with warnings.catch_warnings():
        warnings.simplefilter("error", ej.ConvergenceWarning)
        res = ej.shape_geodesic(f1, f2, METRIC, modulo="rigid", options=options)
    levels = res.levels
    d = np.asarray(levels.distances)
    assert np.asarray(levels.grids).tolist() == [[13, 25], [25, 49]]  # met at the second
    # The change less the energy comparison's rounding (a distance of eps^(1/4) x the
    # surfaces' scale, 4.9e-4 here).
    noise = noise_distance(f1, f2)
    assert 1e-4 < noise < 1e-3
    np.testing.assert_allclose(levels.estimate, (abs(d[1] - d[0]) - noise) / d[1], rtol=1e-12)
    # The last level's registration and path read on the 97 x 193 nodes (twice finer than
    # its rule): a smooth pair's refinement moves it far less than the levels' change
    # (measured 1.3e-4 against 5.3e-4 relative), and the record keeps each level's read.
    gap = refinement_gap(res)
    assert float(levels.refined[-1]) == float(res.refinement.distance_grid)
    assert 0.0 < gap < 0.5 * abs(d[1] - d[0])
    assert float(levels.estimate) == level_change(d, res.parametrized_distance, noise, gap)
    assert float(levels.estimate) <= 0.03 and bool(res.converged)
    assert res.result == ej.RESULTS.successful and res.path.shape[-2:] == (25, 49)
    assert float(res.distance) == d[-1]
    closed = np.sqrt(8 * np.pi)
    assert abs(d[-1] - closed) < 0.03 * closed and d[0] < d[1] < closed  # from below
    # Within the tolerance asked for: the 13 x 25 level is 1.5 % below the area bound.
    assert_area_bound(res.distance, f1, f2, METRIC, slack=0.03)
    assert float(res.distance) <= float(res.parametrized_distance)
    assert "levels=Levels(" in repr(res) and len(repr(res)) <= 2000


@pytest.mark.slow
def test_levels_that_run_out_say_so():
    """rtol tighter than the levels reach: the finest level's distance, not converged,
    RESULTS.not_resolved, and a warning that lists the levels."""
    f1 = shapes.sample(shapes.sphere, 13, 25, radius=1.0)
    f2 = shapes.sample(shapes.sphere, 13, 25, radius=2.0)
    options = OPTIONS.replace(rtol=1e-4, levels=((9, 17), (13, 25)))
    with pytest.warns(ej.ConvergenceWarning, match=r"levels 9 x 17: [\d.]+, 13 x 25") as caught:
        line = inspect.currentframe().f_lineno + 1
        res = ej.shape_geodesic(f1, f2, METRIC, modulo="rigid", options=options)
    assert (caught[0].filename, caught[0].lineno) == (__file__, line)
    assert res.result == ej.RESULTS.not_resolved and not bool(res.converged)
    assert float(res.levels.estimate) > 1e-4
    assert "levels ran out" in res.message
    # The package's own callers solve without the warning, to the same numbers.
    from elastic_jax._registration.shape import solve_shapes

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        quiet = solve_shapes(f1, f2, METRIC, "rigid", options)
    assert quiet.result == res.result and float(quiet.distance) == float(res.distance)


def test_levels_check_a_start_before_solving():
    f = shapes.sample(shapes.sphere, 13, 25)
    options = OPTIONS.replace(rtol=0.03, levels=((9, 17), (13, 25)))
    with pytest.raises(ej.InputError, match="start must be a ShapeGeodesicResult or a pair"):
        ej.shape_geodesic(f, f, METRIC, options=options, start=3.0)
    folded = -ej.sphere_points(13, 25)  # a reflection: J < 0 everywhere
    with pytest.raises(ej.InputError, match="not a diffeomorphism on the 13 x 25 grid"):
        ej.shape_geodesic(f, f, METRIC, options=options, start=(folded, jnp.eye(3)))


def test_collections_refuse_another_working_grid():
    f = jnp.stack([shapes.sample(shapes.sphere, 13, 25, radius=r) for r in (1.0, 2.0, 3.0)])
    options = OPTIONS.replace(grid=(9, 17))
    with pytest.raises(ej.InputError, match="grid=None"):
        ej.distance_matrix(f, METRIC, options=options)
    with pytest.raises(ej.InputError, match="grid=None"):
        ej.karcher_mean(f, METRIC, options=options)
    with pytest.raises(ej.InputError, match="grid=None"):
        ej.fit_metric(f, [0, 0, 1], options=options)


def test_levels_are_the_default_and_grid_or_tracers_mean_one_grid():
    """The defaults resolve (rtol 0.03 by levels); grid= forces one working grid, and
    under jax.jit levels (which compare concrete distances) are refused by name."""
    import jax

    assert ej.ShapeOptions().resolves and ej.ShapeOptions().rtol == 0.03
    assert not ej.ShapeOptions(grid=(13, 25)).resolves
    assert not ej.ShapeOptions(rtol=None).resolves
    # Near-equal shapes (a distance under 5 % of the parametrized one) are resolved to
    # that absolute size; others relative to their distance.
    from elastic_jax._registration.levels import level_change

    assert level_change([0.010, 0.012], parametrized=1.0) == pytest.approx(0.002 / 0.05)
    assert level_change([2.0, 2.1], parametrized=1.0) == pytest.approx(0.1 / 2.1)
    assert np.isnan(level_change([2.0], parametrized=1.0))
    # Identical shapes: zero on one level, the carried identity's interpolation on the
    # next; differences within the rounding distance are no change.
    assert level_change([1e-14, 3.4e-5], parametrized=0.0, noise=4.9e-4) == 0.0
    assert level_change([2.0, 2.1], parametrized=1.0, noise=0.01) == pytest.approx(0.09 / 2.1)
    f = shapes.sample(shapes.sphere, 13, 25)
    options = OPTIONS.replace(rtol=0.03)
    with pytest.raises(ej.InputError, match=r"grid=\(m, n\), or rtol=None"):
        jax.jit(lambda g: ej.shape_geodesic(f, g, METRIC, options=options).distance)(2.0 * f)


def test_the_rounds_stop_where_a_geometric_decrease_leaves_at_most_their_stop():
    """The registration rounds' stop (rounds.rest_of_rounds): a round whose energy change
    and the one before, continued as a geometric series, leave at most the stop ends the
    rounds. On E_k = 1 + c q^k the tail after a round is exactly E_k - 1; with q = 0.1
    and a stop of 1e-3 E the tail stops the rounds after 3 rounds, where the change alone
    would take 4."""
    from elastic_jax._registration.problem import State, iterate
    from elastic_jax._registration.rounds import rest_of_rounds

    c, q, stop = 0.5, 0.1, 1e-3

    def energy(k):
        return 1.0 + c * q**k

    tail = float(rest_of_rounds(energy(0), energy(1), energy(2)))
    assert tail == pytest.approx(energy(2) - 1.0, rel=1e-12)
    assert float(rest_of_rounds(np.inf, energy(0), energy(1))) == np.inf  # the first round
    assert float(rest_of_rounds(2.0, 1.5, 0.9)) == np.inf  # changes that do not fall

    def small(before, after, earlier):
        within = stop * after
        return (before - after <= within) | (rest_of_rounds(earlier, before, after) <= within)

    def one_round(state):
        return state._replace(energy=1.0 + (state.energy - 1.0) * q)

    zero = jnp.zeros(())
    state = State(zero, zero, zero, jnp.asarray(energy(0)), jnp.asarray(0), jnp.asarray(False))
    end, history, rounds, done = iterate(one_round, state, 20, small)
    by_change = next(k for k in range(1, 20) if energy(k - 1) - energy(k) <= stop * energy(k))
    assert (int(rounds), by_change) == (3, 4) and bool(done)
    assert float(end.energy) == pytest.approx(energy(3), rel=1e-14)


@pytest.mark.slow  # about 100 s on 2 cores: three solves on two grids compile
def test_a_level_continues_the_registration_and_path_of_the_one_below():
    """Each level after the first starts its rounds where the level below ended: that
    level's gamma read at its points, its rotation and its path's coefficients (the
    same spherical harmonics on every grid), with no new start search or coarse rounds.
    Its first energy is then that path's energy on the finer grid, computed here
    independently from the coarser level's result; its rounds only lower it."""
    from elastic_jax._geometry.bases import make_bases
    from elastic_jax._geometry.units import in_units
    from elastic_jax._registration.problem import make_problem, path_energy_at
    from elastic_jax._registration.starts import given_start

    f1 = shapes.sample(shapes.bumpy, 13, 25)
    f2 = shapes.sample(shapes.bumpy, 13, 25, rotation=shapes.random_rotation(5))
    f2 = jnp.einsum("i,imn->imn", jnp.asarray([1.2, 1.0, 0.9]), f2)
    levels = ((9, 17), (13, 25))
    options = OPTIONS.replace(rtol=1e-6, levels=levels)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ej.ConvergenceWarning)
        res = ej.shape_geodesic(f1, f2, METRIC, modulo="rigid", options=options)
        # A level integrates as the levels do (at the finer nodes): on_level's options.
        below = ej.shape_geodesic(f1, f2, METRIC, modulo="rigid", options=options.on_level((9, 17)))
    # As first solved (``ascent``): the two levels disagree beyond rtol, so ``distances``
    # holds the 13 x 25 minimum solved again on 9 x 17.
    np.testing.assert_allclose(res.levels.ascent[0], below.distance, rtol=1e-12)

    cfg = options.on_level((13, 25))
    units, (g1, g2) = in_units(f1, f2)
    prob = make_problem(METRIC, g1, g2, make_bases(13, 25, cfg, g1.dtype), True, cfg.interpolation)
    gamma = given_start(below, 13, 25, g1.dtype, True)[0][0]
    carried = (
        path_energy_at(prob, cfg, gamma, below.rotation, below.coefficients / units.scale)
        * units.scale**2
    )
    history = np.asarray(res.energy_history)
    np.testing.assert_allclose(history[1], carried, rtol=1e-10)
    # The rounds stopped at the first round that changed the energy by at most the
    # level's stop, or whose change and the one before, continued geometrically, leave
    # at most that (the floor's tol^2 E_0 term is below 1e-6 E here).
    taken = history[1 : int(res.rounds) + 2]
    drops = -np.diff(taken)
    ratios = np.concatenate([[np.inf], drops[1:] / drops[:-1]])
    falling = (ratios >= 0) & (ratios < 1)
    tails = np.where(falling, drops * ratios / np.where(falling, 1 - ratios, 1), np.inf)
    within = cfg.round_stop * taken[1:] * (1 + 1e-3)
    met = (drops <= within) | (tails <= within)
    assert not met[:-1].any() and met[-1]
    assert float(res.energy) <= history[1] * (1 + 1e-12)
    assert abs(float(carried) - float(below.energy)) > 1e-4 * float(below.energy)  # another grid
    # The level's parametrized geodesic starts from the level below's: the same minimum
    # as a solve on 13 x 25 alone finds from the straight line.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ej.ConvergenceWarning)
        alone = ej.shape_geodesic(f1, f2, METRIC, modulo="rigid", options=cfg)
    np.testing.assert_allclose(res.parametrized_distance, alone.parametrized_distance, rtol=1e-6)


@pytest.mark.slow
def test_identical_shapes_resolve_at_the_second_level():
    """A shape and itself (a Karcher mean's first member against the starting mean): the
    distance is 0 on the first level; the next level continues the carried identity, read
    at its points by interpolation, and ends at the pair as given. Before, that level
    ended not_registered and later ones at 3.4e-5 and 3.1e-4, changes of a number that
    is zero in the continuum: the levels ran to 97 x 193 and stopped not_resolved."""
    e1 = ej.sphere_points(13, 25, dtype=jnp.float64)
    gamma = ej.moebius(e1, jnp.asarray([-0.1, 0.2, -0.2]))
    f = 2.0 * gamma
    options = ej.ShapeOptions(degree=4, vf_degree=4, n_times=5, levels=((13, 25), (25, 49)))
    with warnings.catch_warnings():
        warnings.simplefilter("error", ej.ConvergenceWarning)
        res = ej.shape_geodesic(f, f, METRIC, modulo="rigid", options=options)
    assert np.asarray(res.levels.grids).tolist() == [[13, 25], [25, 49]]
    assert res.result == ej.RESULTS.successful and float(res.levels.estimate) == 0.0
    assert float(res.distance) < 1e-10 and float(res.parametrized_distance) == 0.0


def test_a_level_is_resolved_only_where_its_own_refinement_moves_it_within_rtol():
    """Two levels that agree can agree in a minimum that hides content between both
    grids' points (the fsaverage5 pial pair: 3.799 and 3.731 at 13 x 25 and 25 x 49, then
    3.619 at 49 x 97): the estimate is the larger of the levels' change and how far the
    last level's refinement moves it, both less the noise, relative to the distance."""
    changes = [2.0, 2.02]
    assert level_change(changes) == pytest.approx(0.02 / 2.02, rel=1e-14)
    assert level_change(changes, 0.0, 0.0, 0.101) == pytest.approx(0.05, rel=1e-14)
    assert level_change(changes, 0.0, 0.0, 0.001) == pytest.approx(0.02 / 2.02, rel=1e-14)
    assert level_change(changes, 0.0, 0.001, 0.101) == pytest.approx(0.1 / 2.02, rel=1e-12)
    assert level_change(changes, 0.0, 0.0, np.nan) == level_change(changes)


def _spheres_by_rotation(radii, m=13, n=25):
    """Concentric spheres, each read through a rotation of its parameter sphere, rotated
    and translated in space."""
    e1 = ej.sphere_points(m, n, dtype=jnp.float64)
    out = []
    for i, r in enumerate(radii):
        gamma = jnp.einsum("ij,jmn->imn", shapes.random_rotation(30 + i), e1)
        f = jnp.einsum("ij,jmn->imn", shapes.random_rotation(40 + i), r * gamma)
        out.append(f + jnp.asarray([0.5 * i, -0.3, 0.2 * i])[:, None, None])
    return jnp.stack(out)


@pytest.mark.slow  # about 75 s on 2 cores (the default tier: the candidates' matrix, below)
def test_a_resolved_matrix_is_its_pairs_resolved_distances():
    """distance_matrix at the default rtol: the pairs go through the levels together and
    each entry is shape_geodesic's resolved distance of that pair (same levels, same
    estimate), its levels within rtol, on the grid where two levels agreed, and within
    1 % of the concentric spheres' closed form sqrt(8 pi) |r_i - r_j| (measured: each
    0.073 % under it at 25 x 49, levels estimate 0.21 %)."""
    radii = (1.0, 2.0, 3.0)
    spheres = _spheres_by_rotation(radii)
    # rtol 0.03; levels from 13 x 25, where smooth shapes resolve cheaply
    options = ej.ShapeOptions(degree=4, vf_degree=4, n_times=5, levels=((13, 25), (25, 49)))
    with warnings.catch_warnings():
        warnings.simplefilter("error", ej.ConvergenceWarning)
        res = ej.distance_matrix(
            spheres, METRIC, modulo="rigid", options=options, job=ej.JobOptions(strategy="loop")
        )
    d, estimate = np.asarray(res.distances), np.asarray(res.estimate)
    assert bool(res.converged) and res.result == ej.RESULTS.successful
    assert np.isnan(np.diag(estimate)).all() and np.asarray(res.grids)[0, 0].tolist() == [0, 0]
    upper = np.triu_indices(3, 1)
    assert (estimate[upper] <= 0.03).all()
    assert (np.asarray(res.grids)[upper] == [25, 49]).all()
    closed = np.sqrt(8 * np.pi) * np.abs(np.subtract.outer(radii, radii))
    assert (np.abs(d[upper] / closed[upper] - 1) < 0.01).all() and (d[upper] < closed[upper]).all()
    single = ej.shape_geodesic(spheres[0], spheres[2], METRIC, modulo="rigid", options=options)
    assert d[0, 2] == pytest.approx(float(single.distance), rel=1e-8)
    assert estimate[0, 2] == pytest.approx(float(single.levels.estimate), rel=1e-8)
    np.testing.assert_array_equal(single.levels.grids[-1], res.grids[0, 2])
    # The estimate is the levels' change less the energy comparison's rounding (a
    # distance of eps^(1/4) x the surfaces' scale), relative to the last level.
    levels = np.asarray(single.levels.distances)
    noise = noise_distance(spheres[0], spheres[2])
    assert levels[0] < levels[1] < closed[0, 2]  # from below
    np.testing.assert_allclose(
        single.levels.estimate, (abs(levels[1] - levels[0]) - noise) / levels[1], rtol=1e-12
    )
    assert single.result == ej.RESULTS.successful and float(single.distance) == levels[-1]
    assert_area_bound(single.distance, spheres[0], spheres[2], METRIC, slack=0.03)
    assert float(single.distance) <= float(single.parametrized_distance)
    assert "levels=Levels(" in repr(single) and len(repr(single)) <= 2000


def test_a_matrix_on_one_grid_has_no_estimate():
    """rtol=None: every pair on the collection's grid, estimate NaN, grids that grid."""
    spheres = _spheres_by_rotation((1.0, 2.0, 3.0))
    res = ej.distance_matrix(spheres, METRIC, modulo="none", options=OPTIONS)
    assert np.isnan(np.asarray(res.estimate)).all()
    grids = np.asarray(res.grids)
    assert (grids[np.triu_indices(3, 1)] == [13, 25]).all() and (grids[0, 0] == 0).all()


@pytest.mark.slow  # about 160 s on 2 cores: each level's batched programs compile
def test_a_resolved_matrix_is_the_same_side_by_side_and_one_after_another():
    """The levelled pairs vmapped side by side (an accelerator's strategy, padded to the
    chunk) and one after another through shape_geodesic's programs: the same levels, the
    same distances (measured equal to the last digit on a bumpy surface, an ellipsoid and a
    rotated bumpy surface; the levels at the finer nodes: the pair (0, 2) not resolved at
    17 x 33, estimate 0.047, the others 1.7e-4 and 1.7e-3)."""
    m, n = 13, 25
    collection = np.stack(
        [
            shapes.sample(shapes.bumpy, m, n),
            shapes.sample(shapes.ellipsoid, m, n),
            shapes.sample(shapes.bumpy, m, n, rotation=shapes.random_rotation(3)),
        ]
    )
    options = ej.ShapeOptions(
        degree=4, vf_degree=4, n_times=5, levels=((9, 17), (13, 25), (17, 33))
    )
    runs = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ej.ConvergenceWarning)
        for strategy in ("loop", "vmap"):
            runs[strategy] = ej.distance_matrix(
                collection,
                METRIC,
                modulo="rigid",
                options=options,
                job=ej.JobOptions(strategy=strategy),
            )
    loop, vmap = runs["loop"], runs["vmap"]
    np.testing.assert_allclose(vmap.distances, loop.distances, rtol=1e-8)
    # An estimate is a difference of two levels' distances over one: it inherits their
    # rounding absolutely: a pair resolved to 1.7e-4 differs by 2.6e-10 between them; the
    # pair (0, 2) (levels 0.009399, 0.025107, 0.030364; its changes more than halve, so
    # no level is solved again) by 1.7e-7 at 0.046586 under the levels' stretched cells.
    np.testing.assert_allclose(vmap.estimate, loop.estimate, rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(vmap.grids, loop.grids)
    np.testing.assert_array_equal(vmap.pairs_converged, loop.pairs_converged)
    # The pair that missed rtol on the finest level says so, as shape_geodesic would.
    assert not bool(loop.converged) and loop.result == ej.RESULTS.not_resolved
    assert np.asarray(loop.estimate)[0, 2] > 0.03 and loop.grids[0, 2].tolist() == [17, 33]


def test_one_levels_loop_lets_each_pair_leave_when_it_resolves():
    """run_levels, the loop shape_geodesic's levels and the collections' levelled solves
    share: a pair leaves once two successive levels agree within rtol at a converged
    solve; a non-finite distance ends its levels; the others go on to the next grid,
    each continuing its own solution from the level below. Where two levels disagree, or
    three levels' changes turn back or stop halving, the levels below are solved again
    from the last level's solution, and the change of that minimum decides."""
    from elastic_jax._registration.levels import LevelOutcome, run_levels

    levels = ((9, 17), (13, 25), (17, 33), (25, 49))
    # Per pair, per level: (distance, converged). Pair 0 agrees within 3 % at level 2;
    # pair 1 agrees at level 3 but that solve did not converge, so it goes on; pair 2
    # turns non-finite at level 2; pair 3 never agrees (changes 1, 1, 1: solved again
    # below at levels 3 and 4, no closer); pair 4 turns back at level 3 (0.2, -0.2) and
    # its minimum agrees one level down (0.99 against 1.0); pair 5 turns back too, but
    # its last gamma folds on the level below: the change stands, and level 4 agrees;
    # pair 6's two levels disagree (1.0, 1.2), and its second level's minimum agrees one
    # level down (1.19). Pairs 1, 3, 4 and 5 miss at level 2 too, each second level's
    # minimum one level down at 1.0.
    table = {
        0: [(1.0, True), (1.02, True)],
        1: [(1.0, True), (1.5, True), (1.51, False), (1.52, True)],
        2: [(2.0, True), (np.nan, False)],
        3: [(1.0, True), (2.0, True), (3.0, True), (4.0, True)],
        4: [(1.0, True), (1.2, True), (1.0, True)],
        5: [(1.0, True), (1.2, True), (1.0, True), (1.01, True)],
        6: [(1.0, True), (1.2, True)],
    }
    # (pair, finer level, level below) -> (distance, converged), or None: cannot continue.
    again = {
        **{(i, 1, 0): (1.0, True) for i in (1, 3, 4, 5)},
        (6, 1, 0): (1.19, True),
        (3, 2, 1): (2.0, True),
        (3, 2, 0): (1.0, True),
        (3, 3, 2): (3.0, True),
        (3, 3, 1): (2.0, True),
        (3, 3, 0): (1.0, True),
        (4, 2, 1): (0.99, True),
        (4, 2, 0): (0.9, True),
        (5, 2, 1): None,
        (5, 2, 0): (0.5, True),
    }
    calls = []

    def solve(index, grid, going, below, again_=False):
        calls.append((index, grid, list(going), again_))
        out = []
        for i, sol in zip(going, below, strict=True):
            if again_:  # each from its own finer solution
                entry = again[(i, sol[1], index)]
                out.append(None if entry is None else LevelOutcome(*entry, 10.0, "below"))
            else:  # each continues its own solution
                assert sol == (None if index == 0 else (i, index - 1))
                out.append(LevelOutcome(*table[i][index], 10.0, (i, index)))
        return out

    tracks = run_levels(7, levels, 0.03, [0.0] * 7, lambda *a, again=False: solve(*a, again))
    assert calls == [
        (0, (9, 17), [0, 1, 2, 3, 4, 5, 6], False),
        (1, (13, 25), [0, 1, 2, 3, 4, 5, 6], False),
        (0, (9, 17), [1, 3, 4, 5, 6], True),
        (2, (17, 33), [1, 3, 4, 5], False),
        (1, (13, 25), [3, 4, 5], True),
        (0, (9, 17), [3, 4, 5], True),
        (3, (25, 49), [1, 3, 5], False),
        (2, (17, 33), [3], True),
        (1, (13, 25), [3], True),
        (0, (9, 17), [3], True),
    ]
    assert [len(t.distances) for t in tracks] == [2, 4, 2, 4, 3, 4, 2]
    assert tracks[0].estimate == pytest.approx(0.02 / 1.02)
    assert tracks[1].estimate == pytest.approx(0.01 / 1.52)
    assert np.isnan(tracks[2].distances[-1]) and tracks[2].grids[-1] == (13, 25)
    assert tracks[3].estimate == pytest.approx(0.25) and tracks[3].solution == (3, 3)
    assert tracks[4].distances == [0.9, 0.99, 1.0] and tracks[4].ascent == [1.0, 1.2, 1.0]
    assert tracks[4].estimate == pytest.approx(0.01) and tracks[4].solution == (4, 2)
    assert tracks[5].distances == tracks[5].ascent == [1.0, 1.2, 1.0, 1.01]
    assert tracks[5].estimate == pytest.approx(0.01 / 1.01)
    assert tracks[6].distances == [1.19, 1.2] and tracks[6].ascent == [1.0, 1.2]
    assert tracks[6].estimate == pytest.approx(0.01 / 1.2) and tracks[6].solution == (6, 1)


@pytest.mark.slow  # about a minute on 2 cores: two degrees compile
def test_a_level_solves_with_its_own_diff_step_degree():
    """level_vf_degrees gives each level its Diff step: a level of a resolved distance
    is the one-grid solve at that level's degree (to rounding), not at vf_degree's."""
    f1 = shapes.sample(shapes.bumpy, 9, 17)
    f2 = shapes.sample(shapes.ellipsoid, 9, 17, rotation=shapes.random_rotation(3))
    levels = ((9, 17),)
    resolved = OPTIONS.replace(rtol=1e-9, levels=levels, init="none", refinement=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ej.ConvergenceWarning)
        solves = [
            ej.shape_geodesic(f1, f2, METRIC, modulo="rigid", options=options)
            for options in (
                resolved.replace(level_vf_degrees=(2,)),
                resolved.replace(vf_degree=2).on_level((9, 17)),
                resolved.on_level((9, 17)),
            )
        ]
    levelled, own, other = (float(res.distance) for res in solves)
    np.testing.assert_allclose(levelled, own, rtol=1e-12)
    assert abs(other - own) > 1e-4 * own  # vf_degree's (4) is another solve


@pytest.mark.slow  # about 85 s on 2 cores (the default tier: the spread's rule, below)
def test_candidates_carried_through_the_levels_keep_the_lowest():
    """``level_candidates=3``: three of the first level's starts each go through coarse
    rounds, rounds and levels of their own. The result is the lowest candidate's, its
    spread the candidates' range relative to the lowest, both computed here from the
    recorded distances; a candidate is the levelled solve from its start alone; one
    candidate records its own distance and no spread."""
    from elastic_jax._registration.levels import first_level_starts

    f1 = shapes.sample(shapes.bumpy, 13, 25)
    f2 = shapes.sample(shapes.bumpy, 13, 25, rotation=shapes.random_rotation(5))
    f2 = jnp.einsum("i,imn->imn", jnp.asarray([1.2, 1.0, 0.9]), f2)
    options = OPTIONS.replace(rtol=0.03, levels=((9, 17), (13, 25)), level_candidates=3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ej.ConvergenceWarning)
        res = ej.shape_geodesic(f1, f2, METRIC, modulo="rigid", options=options)
        starts = first_level_starts(f1, f2, METRIC, "rigid", options)
        last = ej.shape_geodesic(
            f1,
            f2,
            METRIC,
            modulo="rigid",
            options=options.replace(level_candidates=1),
            start=starts[-1],
        )
    found = np.asarray(res.levels.candidates)
    assert found.shape == (3,) and len(starts) == 3
    assert float(res.distance) == found.min()
    scale = max(found.min(), 0.05 * float(res.parametrized_distance))
    np.testing.assert_allclose(res.spread, (found.max() - found.min()) / scale, rtol=1e-12)
    np.testing.assert_allclose(found[-1], last.distance, rtol=1e-12)
    np.testing.assert_allclose(last.levels.candidates, [last.distance], rtol=0)
    assert float(last.spread) == 0.0
    assert_area_bound(res.distance, f1, f2, METRIC)


@pytest.mark.slow  # about 60 s on 2 cores (the default tier: the inverted starts, below)
def test_both_orders_add_the_other_orders_starts_as_candidates():
    """``both_orders=True`` with one candidate an order: the first candidate is the
    default solve itself, the second the levelled solve from the other order's best
    start inverted, and the result the lower; it is never above the default's."""
    from elastic_jax._registration.levels import other_order_starts

    f1 = shapes.sample(shapes.bumpy, 13, 25)
    f2 = shapes.sample(shapes.bumpy, 13, 25, rotation=shapes.random_rotation(5))
    f2 = jnp.einsum("i,imn->imn", jnp.asarray([1.2, 1.0, 0.9]), f2)
    options = OPTIONS.replace(rtol=0.03, levels=((9, 17), (13, 25)), both_orders=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ej.ConvergenceWarning)
        res = ej.shape_geodesic(f1, f2, METRIC, modulo="rigid", options=options)
        one = options.replace(both_orders=False)
        default = ej.shape_geodesic(f1, f2, METRIC, modulo="rigid", options=one)
        (start,) = other_order_starts(f1, f2, METRIC, "rigid", options)
        other = ej.shape_geodesic(f1, f2, METRIC, modulo="rigid", options=one, start=start)
    found = np.asarray(res.levels.candidates)
    assert found.shape == (2,)
    np.testing.assert_allclose(found, [default.distance, other.distance], rtol=1e-12)
    assert float(res.distance) == found.min() <= float(default.distance)
    assert_area_bound(res.distance, f1, f2, METRIC)


def test_the_other_orders_starts_are_inverted():
    """other_order_starts: each of f2 -> f1's starts (gamma, R) becomes (gamma^-1, R^T):
    gamma o gamma^-1 is the identity at the grid's points (to Newton's rounding), and
    the rotations are transposed."""
    from elastic_jax._registration.levels import first_level_starts, other_order_starts

    f1 = shapes.sample(shapes.bumpy, 9, 17)
    f2 = shapes.sample(shapes.bumpy, 9, 17, rotation=shapes.random_rotation(3))
    options = OPTIONS.replace(rtol=0.03, levels=((9, 17),), level_candidates=2)
    found = first_level_starts(f2, f1, METRIC, "rigid", options)
    inverted = other_order_starts(f1, f2, METRIC, "rigid", options)
    assert len(found) == len(inverted) == 2
    points = ej.sphere_points(9, 17, dtype=jnp.float64)
    for (gamma, rotation), (inverse, transposed) in zip(found, inverted, strict=True):
        back = ej.reparametrize(gamma, inverse, method="bicubic")
        back = back / jnp.linalg.norm(back, axis=0, keepdims=True)
        assert float(jnp.max(jnp.abs(back - points))) < 1e-9
        np.testing.assert_allclose(transposed, np.asarray(rotation).T, rtol=0, atol=0)


def test_candidates_apart_by_more_than_rtol_are_not_resolved():
    """A converged, resolved result whose candidates ended further apart than rtol is
    not converged (``not_resolved``): the minima found differ by more than the answer's
    stated resolution. Within rtol it stays converged. The spread's closed forms:
    (max - min) / max(min, floor) over the finite distances."""
    from elastic_jax._registration.levels import candidate_spread, with_levels

    assert candidate_spread([2.0, 2.2, np.nan]) == pytest.approx(0.1, rel=1e-14)
    assert candidate_spread([1.5]) == 0.0 and np.isnan(candidate_spread([np.nan]))
    assert candidate_spread([0.001, 0.002], floor=0.1) == pytest.approx(0.01, rel=1e-12)
    e1 = ej.sphere_points(9, 17, dtype=jnp.float64)
    options = ej.ShapeOptions(degree=3, vf_degree=3, n_times=5, grid=(9, 17))
    res = ej.shape_geodesic(e1, 1.5 * e1, METRIC, modulo="rigid", options=options)
    d = float(res.distance)
    assert bool(res.converged) and d > 0
    grids, seconds = [[9, 17], [9, 17]], [1.0, 1.0]
    apart = with_levels(res, grids, [d, d], seconds, 0.03, candidates=[d, 1.05 * d])
    near = with_levels(res, grids, [d, d], seconds, 0.03, candidates=[1.01 * d, d])
    assert not bool(apart.converged) and apart.result == ej.RESULTS.not_resolved
    assert float(apart.spread) == pytest.approx(0.05, rel=1e-12)
    assert bool(near.converged) and near.result == res.result
    assert float(near.spread) == pytest.approx(0.01, rel=1e-12)


def test_a_matrix_carries_each_pairs_candidates_as_shape_geodesic_does():
    """distance_matrix with level_candidates=2 and both_orders: each pair carries the
    candidates a resolved shape_geodesic carries (the first level's two best starts and
    the other order's two, inverted), each one more item of the levels' batch; the
    pair's distance, estimate, spread and status are shape_geodesic's with the same
    options, the spread the candidates' range (closed form of their recorded finals),
    and the distance the lowest candidate's. Option values are checked by name."""
    with pytest.raises(ej.InputError, match="level_candidates .* without search_smoothing"):
        ej.ShapeOptions(level_candidates=0)
    with pytest.raises(ej.InputError, match="level_candidates"):
        ej.ShapeOptions(level_candidates=-1, search_smoothing=(1.0,))
    with pytest.raises(ej.InputError, match="both_orders"):
        ej.ShapeOptions(both_orders=1)
    f1 = shapes.sample(shapes.bumpy, 9, 17)
    f2 = shapes.sample(shapes.bumpy, 9, 17, rotation=shapes.random_rotation(5))
    f2 = jnp.einsum("i,imn->imn", jnp.asarray([1.2, 1.0, 0.9]), f2)
    options = OPTIONS.replace(rtol=0.03, levels=((9, 17),), level_candidates=2, both_orders=True)
    job = ej.JobOptions(strategy="loop")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ej.ConvergenceWarning)
        res = ej.distance_matrix(jnp.stack([f1, f2]), METRIC, options=options, job=job)
        single = ej.shape_geodesic(f1, f2, METRIC, modulo="rigid", options=options)
    found = np.asarray(single.levels.candidates)
    assert found.shape == (4,)
    assert float(single.distance) == found.min()
    scale = max(found.min(), 0.05 * float(single.parametrized_distance))
    np.testing.assert_allclose(single.spread, np.ptp(found) / scale, rtol=1e-12)
    assert float(res.distances[0, 1]) == pytest.approx(float(single.distance), rel=1e-10)
    assert float(res.spread[0, 1]) == pytest.approx(float(single.spread), rel=1e-8, abs=1e-12)
    np.testing.assert_allclose(res.estimate[0, 1], single.levels.estimate, rtol=1e-8)
    assert bool(res.pairs_converged[0, 1]) == bool(single.converged)
    assert np.isnan(np.diag(np.asarray(res.spread))).all()
    assert res.spread[1, 0] == res.spread[0, 1]
    assert_area_bound(res.distances[0, 1], f1, f2, METRIC)
    for widths, problem in (((0.5, 1.0),), "wide to narrow"), (((1.0, -1.0),), "positive"):
        with pytest.raises(ej.InputError, match=problem):
            ej.ShapeOptions(search_smoothing=widths[0])
    with pytest.raises(ej.InputError, match="smoothing_kernel"):
        ej.ShapeOptions(smoothing_kernel="gaussian")
    with pytest.raises(ej.InputError, match="search_smoothing"):
        ej.ShapeOptions(search_smoothing=1.0)


def test_the_orders_in_turn_lower_a_level_and_a_matrix_carries_them():
    """``alternations``: after a level's solve, its registration inverted is continued in
    the other order and that one's inverted in this order (recomputed here from the
    level without alternations); the round trip is kept where it ends lower, and stops
    once it gained less than the rounds' stop. A matrix's entry is the same. Values
    are checked by name."""
    from elastic_jax._registration.one_grid import one_grid_solve
    from elastic_jax._registration.starts import usable_inverse

    with pytest.raises(ej.InputError, match="alternations"):
        ej.ShapeOptions(alternations=-1)
    f1 = shapes.sample(shapes.ellipsoid, 9, 17, axes=(1.2, 0.8, 0.6))
    f2 = shapes.sample(shapes.bumpy, 9, 17, rotation=shapes.random_rotation(2))
    options = OPTIONS.replace(rtol=0.03, levels=((9, 17),), alternations=3)
    level = options.on_level((9, 17))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ej.ConvergenceWarning)
        res = ej.shape_geodesic(f1, f2, METRIC, modulo="rigid", options=options)
        plain = ej.shape_geodesic(
            f1, f2, METRIC, modulo="rigid", options=options.replace(alternations=0)
        )
        inverse = usable_inverse(plain.gamma)
        other = one_grid_solve(
            f2, f1, METRIC, "rigid", level, None, carry=(inverse, plain.rotation.T, None)
        )
        back = usable_inverse(other.gamma)
        trip = one_grid_solve(
            f1, f2, METRIC, "rigid", level, None, carry=(back, other.rotation.T, None)
        )
        job = ej.JobOptions(strategy="loop")
        matrix = ej.distance_matrix(jnp.stack([f1, f2]), METRIC, options=options, job=job)
    d, d0 = float(trip.distance), float(plain.distance)
    # The other order's moves lower this pair's level (0.23 %), by less than the
    # rounds' stop: one round trip is kept and the next is not tried.
    assert d < d0 and (d0 - d) / d0 < options.level_rounds_tol
    assert float(res.distance) == pytest.approx(d, rel=1e-10)
    assert float(matrix.distances[0, 1]) == pytest.approx(d, rel=1e-10)
    assert_area_bound(res.distance, f1, f2, METRIC)


@pytest.mark.slow  # about 240 s on 2 cores: the candidates' batched programs compile
def test_a_matrix_carries_candidates_side_by_side_as_one_after_another():
    """Three pairs, each with six candidates (two starts an order and each order's
    graduated one), through two levels: vmapped side by side (each level's groups solved three
    at a time, the chunk's compiled shape) and one after another give the same matrix
    and spreads, each entry that pair's shape_geodesic (measured with five candidates
    a pair: 7e-12 relative)."""
    f1 = shapes.sample(shapes.bumpy, 9, 17)
    f2 = shapes.sample(shapes.bumpy, 9, 17, rotation=shapes.random_rotation(5))
    f2 = jnp.einsum("i,imn->imn", jnp.asarray([1.2, 1.0, 0.9]), f2)
    f3 = shapes.sample(shapes.ellipsoid, 9, 17)
    stack = jnp.stack([f1, f2, f3])
    options = OPTIONS.replace(
        rtol=0.03,
        levels=((9, 17), (13, 25)),
        level_candidates=2,
        both_orders=True,
        search_smoothing=(1.0,),
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ej.ConvergenceWarning)
        side = ej.distance_matrix(
            stack, METRIC, options=options, job=ej.JobOptions(strategy="vmap")
        )
        loop = ej.distance_matrix(
            stack, METRIC, options=options, job=ej.JobOptions(strategy="loop")
        )
        single = ej.shape_geodesic(f2, f3, METRIC, modulo="rigid", options=options)
    np.testing.assert_allclose(side.distances, loop.distances, rtol=1e-9)
    np.testing.assert_allclose(side.spread, loop.spread, rtol=0, atol=1e-6)
    assert np.asarray(single.levels.candidates).shape == (6,)
    assert float(loop.distances[1, 2]) == pytest.approx(float(single.distance), rel=1e-10)
    assert float(loop.spread[1, 2]) == pytest.approx(float(single.spread), abs=1e-10)
    upper = np.triu_indices(3, 1)
    assert (np.asarray(loop.spread)[upper] > 0).all()


@pytest.mark.slow  # about 150 s on 2 cores (the default tier: tests/test_smoothing.py)
def test_the_graduated_candidate_continues_its_solves_of_the_inputs_low_passed():
    """search_smoothing=(c,) adds one candidate to the default's: its first level is the
    solve of f1 and f2 averaged by the kernel of width c pi / (m - 1), then the solve on
    the data continuing it (continued_geodesic from its registration and path), to
    rounding; the default's candidate is the solve without the option; the result is
    the lower, and the spread their range. level_candidates=0 carries the graduated
    candidate alone: the same final, a spread of 0."""
    f1 = shapes.sample(shapes.bumpy, 9, 17)
    f2 = shapes.sample(shapes.bumpy, 9, 17, rotation=shapes.random_rotation(5))
    f2 = jnp.einsum("i,imn->imn", jnp.asarray([1.2, 1.0, 0.9]), f2)
    plain = OPTIONS.replace(rtol=0.03, levels=((9, 17),))
    options = plain.replace(search_smoothing=(1.0,), smoothing_kernel="surface")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ej.ConvergenceWarning)
        res = ej.shape_geodesic(f1, f2, METRIC, modulo="rigid", options=options)
        default = ej.shape_geodesic(f1, f2, METRIC, modulo="rigid", options=plain)
        alone = ej.shape_geodesic(
            f1, f2, METRIC, modulo="rigid", options=options.replace(level_candidates=0)
        )
        level = plain.on_level((9, 17))
        width = np.pi / 8
        blurred = ej.shape_geodesic(
            ej.smooth_surface(f1, width, kernel="surface"),
            ej.smooth_surface(f2, width, kernel="surface"),
            METRIC,
            modulo="rigid",
            options=level,
        )
        again = _continued(f1, f2, level, blurred)
    assert float(blurred.distance) < float(again.distance)  # the blur lowers it
    candidates = np.asarray(res.levels.candidates)
    np.testing.assert_allclose(candidates, [default.distance, again.distance], rtol=1e-10)
    assert float(res.distance) == candidates.min()
    spread = (candidates.max() - candidates.min()) / candidates.min()
    np.testing.assert_allclose(res.spread, spread, rtol=1e-12)
    np.testing.assert_allclose(alone.levels.candidates, [again.distance], rtol=1e-10)
    assert float(alone.spread) == 0.0
    assert_area_bound(res.distance, f1, f2, METRIC)
    assert float(res.distance) <= float(res.parametrized_distance)


@pytest.mark.slow  # about 100 s on 2 cores
def test_both_orders_carry_the_other_orders_graduated_solve_inverted():
    """search_smoothing with both_orders: four candidates, the default's, the other
    order's start, the graduated one and the other order's graduated one. The last is
    f2 -> f1 solved on the low-passed inputs and then on the data, its registration
    inverted (gamma^-1, R^T) and continued in this order from the straight line, to
    rounding; the result is the lowest of the four."""
    from elastic_jax._registration.one_grid import continued_geodesic
    from elastic_jax._registration.starts import usable_inverse

    f1 = shapes.sample(shapes.bumpy, 9, 17)
    f2 = shapes.sample(shapes.bumpy, 9, 17, rotation=shapes.random_rotation(5))
    f2 = jnp.einsum("i,imn->imn", jnp.asarray([1.2, 1.0, 0.9]), f2)
    plain = OPTIONS.replace(rtol=0.03, levels=((9, 17),))
    options = plain.replace(search_smoothing=(1.0,), both_orders=True)
    level = plain.on_level((9, 17))
    width = np.pi / 8
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ej.ConvergenceWarning)
        res = ej.shape_geodesic(f1, f2, METRIC, modulo="rigid", options=options)
        blurred = ej.shape_geodesic(
            ej.smooth_surface(f2, width),
            ej.smooth_surface(f1, width),
            METRIC,
            modulo="rigid",
            options=level,
        )
        data = _continued(f2, f1, level, blurred)
        inverse = usable_inverse(data.gamma)
        again = continued_geodesic(
            f1, f2, METRIC, "rigid", level, inverse, data.rotation.T, None, None
        )
    back = ej.reparametrize(data.gamma, inverse, method="bicubic")
    back = back / jnp.linalg.norm(back, axis=0, keepdims=True)
    assert float(jnp.max(jnp.abs(back - ej.sphere_points(9, 17, dtype=jnp.float64)))) < 1e-9
    candidates = np.asarray(res.levels.candidates)
    assert candidates.shape == (4,)
    np.testing.assert_allclose(candidates[3], again.distance, rtol=1e-10)
    assert float(res.distance) == candidates.min()
    assert_area_bound(res.distance, f1, f2, METRIC)
    assert float(res.distance) <= float(res.parametrized_distance)


def _continued(f1, f2, level: ej.ShapeOptions, res: ej.ShapeGeodesicResult):
    """continued_geodesic of (f1, f2) on ``level`` from a result's registration, path and
    parametrized path."""
    from elastic_jax._registration.one_grid import continued_geodesic

    return continued_geodesic(
        f1,
        f2,
        METRIC,
        "rigid",
        level,
        res.gamma,
        res.rotation,
        res.coefficients,
        res.parametrized_coefficients,
    )
