import json
import os
import subprocess
import sys
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import elastic_jax as ej
from elastic_jax import moebius, shapes

from .conftest import load_shape, traced_functions

M, N = 13, 25
METRIC = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)
# Parametrized geodesics (modulo="none"): the inner options of the "none" tests.
FAST = ej.ShapeOptions(degree=3, n_times=5)
# Shape geodesics: one configuration for every test below (and tests/test_cli.py), with
# strategy="loop", so that they all share one compilation per modulo.
SHAPE = ej.ShapeOptions(degree=4, vf_degree=4, n_times=5, rtol=None)
RADII = (1.0, 2.0, 3.0)


def _collection():
    return jnp.stack(
        [
            shapes.sample(shapes.bumpy, M, N),
            shapes.sample(shapes.ellipsoid, M, N, axes=(1.1, 0.9, 0.7)),
            shapes.sample(shapes.bumpy, M, N, scale=1.3),
        ]
    )


def _moved_spheres():
    """Concentric spheres, each reparametrized (a rotation or a Moebius map of the
    parameter sphere), rotated and translated."""
    e1 = ej.sphere_points(M, N, dtype=jnp.float64)
    out = []
    for i, r in enumerate(RADII):
        if i == 1:
            gamma = moebius(e1, jnp.asarray([0.1, -0.2, 0.2]))  # |a| = 0.3
        else:
            gamma = jnp.einsum("ij,jmn->imn", shapes.random_rotation(10 + i), e1)
        f = jnp.einsum("ij,jmn->imn", shapes.random_rotation(20 + i), r * gamma)
        out.append(f + jnp.asarray([0.5 * i, -0.3, 0.2 * i])[:, None, None])
    return jnp.stack(out)


def _area_bound(f, g):
    """98 % of sqrt(2 b) |sqrt(A(g)) - sqrt(A(f))| (docs/math.md §9): no shape distance lies
    below the bound; at 13 x 25 the discrete distance of concentric spheres is 1.4 % under
    it, registration that exploits the grid goes tens of percent under (issue 10)."""
    areas = np.sqrt(np.asarray(ej.surface_area(jnp.stack([f, g]))))
    return 0.98 * np.sqrt(2 * METRIC.b) * abs(areas[1] - areas[0])


def test_concentric_spheres_mean_is_the_mean_radius():
    radii = [1.0, 1.5, 2.2]
    spheres = jnp.stack([shapes.sample(shapes.sphere, M, N, radius=r) for r in radii])
    res = ej.karcher_mean(spheres, METRIC, modulo="none", options=FAST)
    assert res.converged and ej.RESULTS.name(res.result) == "mean_velocity_small"
    expected = shapes.sample(shapes.sphere, M, N, radius=float(np.mean(radii)))
    assert float(jnp.abs(res.mean - expected).max()) < 1e-6
    # Distances from the mean: sqrt(8 pi b) |r_i - r|, to the 13 x 25 discretization error.
    exact = np.sqrt(8 * np.pi) * np.abs(np.asarray(radii) - np.mean(radii))
    np.testing.assert_allclose(res.distances, exact, rtol=3e-2)
    assert res.num_steps == 1 and res.num_solves == 2  # one step, accepted at once


@pytest.mark.slow
def test_karcher_mean_of_moved_concentric_spheres_modulo_rigid():
    spheres = _moved_spheres()
    res = ej.karcher_mean(
        spheres, METRIC, modulo="rigid", options=SHAPE, job=ej.JobOptions(strategy="loop")
    )
    assert res.converged, res.message
    sum_sq = res.history[:, 0]
    assert np.all(np.diff(sum_sq) <= 0)
    # A sphere of the mean radius: its points' distance from their centroid.
    radius = np.linalg.norm(np.asarray(ej.center(res.mean)), axis=0)
    assert abs(radius.mean() / np.mean(RADII) - 1) < 1e-2
    assert (radius.max() - radius.min()) / radius.mean() < 2e-2
    # The distances: sqrt(8 pi b) |r_k - r|, 1.5 % below it at 13 x 25, as is the area
    # bound's margin (_area_bound).
    exact = np.sqrt(8 * np.pi) * np.abs(np.asarray(RADII) - np.mean(RADII))
    distances = np.asarray(res.distances)
    np.testing.assert_allclose(distances[[0, 2]], exact[[0, 2]], rtol=3e-2)
    assert distances[1] < 0.02 * exact[0]
    for f, d in zip(res.registered, res.distances, strict=True):
        assert float(d) >= _area_bound(f, res.mean)
    assert bool(jnp.all(res.geodesics_converged))
    # The registered shapes are the inputs moved onto the mean: spheres about its centre.
    centred = np.asarray(ej.center(res.registered))
    radii = np.linalg.norm(centred, axis=1).mean(axis=(1, 2))
    np.testing.assert_allclose(radii, RADII, rtol=1e-2)


def _moebius_spheres(m, n, radii):
    """Concentric spheres, each read through a rotation and a Moebius map of the
    parameter sphere (boosts |a| = 0.3, 0 and 0.3), rotated and translated in R^3."""
    e1 = ej.sphere_points(m, n, dtype=jnp.float64)
    out = []
    for i, r in enumerate(radii):
        turned = jnp.einsum("ij,jmn->imn", shapes.random_rotation(10 + i), e1)
        gamma = moebius(turned, (i - 1) * jnp.asarray([0.1, -0.2, 0.2]))
        f = jnp.einsum("ij,jmn->imn", shapes.random_rotation(20 + i), r * gamma)
        out.append(f + jnp.asarray([0.5 * i, -0.3, 0.2 * i])[:, None, None])
    return jnp.stack(out)


@pytest.mark.slow  # 85-90 s each on 2 cores
@pytest.mark.parametrize("modulo", ["rigid", "diff"])
def test_resolved_mean_of_moebius_read_concentric_spheres(modulo, tmp_path, monkeypatch):
    """At the defaults (rtol) the first geodesics run by levels, and the mean is solved on
    the grid they needed, its steps continuing each registration. Measured (13 x 25
    inputs, levels stop at 25 x 49): rigid radius 2.995, spread 0.75 %, SSD 50.201; diff
    2.990, 0.95 %, 51.809. Before, modulo diff on the inputs' grid gave radius 2.638 and
    spread 25 % with an SSD below the continuum's."""
    radii = (2.0, 3.0, 4.0)
    options = ej.ShapeOptions(degree=4, vf_degree=4, n_times=5)  # rtol: the default
    spheres = _moebius_spheres(M, N, radii)
    path = tmp_path / "mean.npz"
    kwargs = {"modulo": modulo, "options": options}
    import elastic_jax._statistics.driver as driver
    import elastic_jax._statistics.karcher as karcher

    written, save = [], driver.save_npz_atomic
    monkeypatch.setattr(
        driver, "save_npz_atomic", lambda p, **arrays: written.append(arrays) or save(p, **arrays)
    )
    reports = []
    # One shape per chunk: the checkpoint is written after each chunk of step 0.
    job = ej.JobOptions(checkpoint=path, progress=reports.append, batch_size=1)
    res = ej.karcher_mean(spheres, METRIC, **kwargs, job=job)
    assert res.converged, res.message
    # Step 0's levelled solves report each level of each shape as it ends (chunk by
    # chunk, here shape by shape), with the distance the result records; then one
    # report per step.
    ends = [r for r in reports if r.get("stage") == "level"]
    assert [(r["shape"], r["shapes"]) for r in ends] == sorted((r["shape"], 3) for r in ends)
    for k in range(3):
        mine = [r["level"] for r in ends if r["shape"] == k]
        assert mine == list(range(1, len(mine) + 1))
    assert len(ends) == int(np.isfinite(res.level_distances).sum())
    for r in ends:
        assert r["distance"] == pytest.approx(res.level_distances[r["shape"], r["level"] - 1])
    steps = [r["step"] for r in reports if "shape" not in r]
    assert steps == list(range(int(res.num_steps) + 1))
    seconds = [r["seconds"] for r in reports]
    assert seconds == sorted(seconds)
    sum_sq = res.history[:, 0]
    assert np.all(np.diff(sum_sq) <= 0)
    # The levels: each row stops where two grids agree within rtol; the mean lives on
    # the finest grid any row reached.
    levels = res.level_distances
    reached = [max(np.flatnonzero(np.isfinite(row))) for row in levels]
    assert res.mean.shape[-2:] == options.levels[max(reached)]
    assert levels[0, 0] < 1e-8  # the first shape is the starting mean
    radius = np.linalg.norm(np.asarray(ej.center(res.mean)), axis=0)
    assert abs(radius.mean() / 3.0 - 1) < 1e-2
    assert (radius.max() - radius.min()) / radius.mean() < 2e-2
    # Never below what the grid allows: the distances of concentric spheres of radii 2
    # and 4 to 3 on the mean's grid, parametrized alike (the discrete closed form; the
    # continuum's 2 x 8 pi is 0.7 % above it at 25 x 49), nor far above the continuum.
    m, n = res.mean.shape[-2:]
    mean_sphere = shapes.sample(shapes.sphere, m, n, radius=3.0)
    discrete = sum(
        float(
            ej.geodesic(
                shapes.sample(shapes.sphere, m, n, radius=r),
                mean_sphere,
                METRIC,
                degree=4,
                n_times=5,
            ).distance
        )
        ** 2
        for r in (2.0, 4.0)
    )
    assert discrete * (1 - 1e-6) <= sum_sq[-1] <= 1.05 * 16 * np.pi
    for f, d in zip(res.registered, res.distances, strict=True):
        assert float(d) >= _area_bound(f, res.mean)
    if modulo == "diff":
        return
    # A kill during step 0 loses one chunk's levelled solves at most (here one shape's):
    # the checkpoint holds each chunk's as it ends. Resumed from the file as it was with
    # two of three, one is solved again, and step 0 is the same.
    assert [sorted(k for k in w if k.startswith("first_levels")) for w in written[:3]] == [
        [f"first_levels_{i}" for i in range(j + 1)] for j in range(3)
    ]
    np.savez(path, **written[1])
    levelled = []
    solve = karcher.levelled_chunk
    monkeypatch.setattr(
        karcher,
        "levelled_chunk",
        lambda first, *a, **k: levelled.append(len(first)) or solve(first, *a, **k),
    )
    with pytest.warns(ej.ConvergenceWarning, match="max_steps"):
        again = ej.karcher_mean(
            spheres,
            METRIC,
            max_steps=0,
            **kwargs,
            job=ej.JobOptions(checkpoint=path, resume=True, batch_size=1),
        )
    assert levelled == [1]  # the one shape the file lacked
    np.testing.assert_allclose(again.level_distances, res.level_distances, rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(again.history[0], res.history[0], rtol=1e-9)


@pytest.mark.slow  # about 5 minutes on 2 cores
def test_resolved_mean_of_the_shared_shapes_converges_below_every_member():
    """cat1, cat2, horse0 and hand4 as stored (50 x 99), modulo rigid, the levels capped
    at 25 x 49 for time (degree 4/4, N = 5): every step lowers the SSD, the iteration
    converges, and the mean is a better centre than any member (each member's SSD from
    the same levelled solves). Measured: SSD 14.02, 7.06, 6.70, 6.50, 6.44, 6.414,
    6.411, sum_sq_stalled, 260-310 s alone; at the full defaults (levels to 97 x 193)
    13.27 to 5.96 in 57 minutes (docs/guides/collections.md). With a start search per
    solve on one grid the same four stopped line_search_failed after one step."""
    names = ("cat1", "cat2", "horse0", "hand4")
    coll = np.stack([load_shape(name) for name in names])
    options = ej.ShapeOptions(degree=4, vf_degree=4, n_times=5, levels=((13, 25), (25, 49)))
    res = ej.karcher_mean(coll, METRIC, modulo="rigid", options=options)
    assert res.converged, res.message
    sum_sq = res.history[:, 0]
    assert np.all(np.diff(sum_sq) <= 0) and sum_sq[-1] < 0.5 * sum_sq[0]
    assert res.mean.shape[-2:] == (25, 49)
    # hand4's registration to a mean of cats and a horse asks to collapse a region, as
    # horse0 -> hand4's does at every area floor tried (docs/guides/registration_notes.md,
    # registration-edge): its solve may end resolution_limited (it did, 1.181), which
    # the record flags. Any other solve that did not converge failed.
    converged = np.asarray(res.geodesics_converged)
    assert np.all(converged | np.asarray(res.geodesics_resolution_limited))
    assert converged[:3].all()  # the cats and the horse
    # Members as centres: cat1's is the first row (the starting mean); the others from
    # the same levelled solves of the pairs.
    first = [row[np.isfinite(row)][-1] for row in res.level_distances]
    d = np.zeros((4, 4))
    d[0, 1:] = d[1:, 0] = first[1:]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ej.ConvergenceWarning)
        for i, j in ((1, 2), (1, 3), (2, 3)):
            pair = ej.shape_geodesic(coll[i], coll[j], METRIC, modulo="rigid", options=options)
            d[i, j] = d[j, i] = float(pair.distance)
    members = (d**2).sum(axis=1)
    assert sum_sq[-1] < members.min(), members


def _three_reparametrized():
    return jnp.stack(
        [
            shapes.sample(shapes.bumpy, M, N, rotation=shapes.random_rotation(1)),
            shapes.sample(
                shapes.ellipsoid, M, N, axes=(1.1, 0.9, 0.7), rotation=shapes.random_rotation(2)
            ),
            shapes.sample(shapes.bumpy, M, N, scale=1.3, rotation=shapes.random_rotation(3)),
        ]
    )


@pytest.mark.slow
def test_karcher_mean_modulo_diff_reaches_its_fixed_point():
    # Three shapes, each under a reparametrization; a small tol. Every step is accepted
    # at once and the mean velocity falls to 0.2 % of its first norm (0.339, 4.8e-3,
    # 7.8e-4, 6.0e-4). Its vertical part removed, it no longer drifts the mean's
    # parametrization (which kept it at 3.5 % of the first norm, lowering the SSD by
    # 0.04 % a step for ever). With warm_start=True the SSD ends lower (2.17540 against
    # 2.17626) but the mean velocity stays at 0.5 % of its first norm and the line search
    # fails at this tol: the warm solves keep finding lower registrations.
    coll = _three_reparametrized()
    res = ej.karcher_mean(
        coll,
        METRIC,
        modulo="diff",
        options=SHAPE,
        tol=1e-5,
        max_steps=6,
        job=ej.JobOptions(strategy="loop"),
    )
    assert res.converged, res.message
    sum_sq, norms = res.history[:, 0], res.history[:, 1]
    assert np.all(np.diff(sum_sq) <= 0)
    assert sum_sq[-1] < 0.9 * sum_sq[0]
    assert norms[-1] < 1e-2 * norms[0]
    assert res.num_solves == res.num_steps + 1  # no step had to backtrack
    for f, d in zip(res.registered, res.distances, strict=True):
        assert float(d) >= _area_bound(f, res.mean)


@pytest.mark.slow  # 83 s on 2 cores
def test_warm_start_keeps_the_lower_of_two_registrations():
    """warm_start adds, per shape, a solve started from its registration at the previous
    mean (the identity at the first) and keeps the lower distance: at the first mean both
    runs agree here (the search's minima), so both take the same first step; at that new
    mean no distance is above the search's, and the sum is lower (measured 2.17625
    against 2.17683: the search lands in a slightly worse minimum than the warm start's
    continuation of the previous one)."""
    coll = _three_reparametrized()
    kwargs = {"modulo": "diff", "options": SHAPE, "job": ej.JobOptions(strategy="loop")}
    kwargs["max_steps"] = 1
    with pytest.warns(ej.ConvergenceWarning, match="max_steps Karcher steps taken"):
        fresh = ej.karcher_mean(coll, METRIC, **kwargs)
    with pytest.warns(ej.ConvergenceWarning, match="max_steps Karcher steps taken"):
        warm = ej.karcher_mean(coll, METRIC, warm_start=True, **kwargs)
    np.testing.assert_allclose(warm.history[0], fresh.history[0], rtol=1e-10)
    np.testing.assert_allclose(warm.mean, fresh.mean, atol=1e-10)
    assert np.all(np.asarray(warm.distances) <= np.asarray(fresh.distances) * (1 + 1e-12))
    assert warm.history[1, 0] < (1 - 5e-5) * fresh.history[1, 0]
    with pytest.raises(ej.InputError, match="warm_start"):
        ej.karcher_mean(coll, METRIC, warm_start="yes")


@pytest.mark.slow
def test_karcher_mean_modulo_diff_forward_scheme_converges():
    coll = jnp.stack(
        [
            shapes.sample(shapes.bumpy, M, N, rotation=shapes.random_rotation(1)),
            shapes.sample(
                shapes.ellipsoid, M, N, axes=(1.1, 0.9, 0.7), rotation=shapes.random_rotation(2)
            ),
            shapes.sample(shapes.bumpy, M, N, scale=1.3, rotation=shapes.random_rotation(3)),
        ]
    )
    options = SHAPE.replace(scheme="forward")
    res = ej.karcher_mean(
        coll, METRIC, modulo="diff", options=options, job=ej.JobOptions(strategy="loop")
    )
    assert res.converged, res.message
    assert np.all(np.diff(res.history[:, 0]) <= 0)
    assert res.history[-1, 0] < 0.9 * res.history[0, 0]


def test_distance_matrix_record_equals_single_solves_and_resumes(tmp_path):
    spheres = _moved_spheres()
    kwargs = {"modulo": "rigid", "options": SHAPE}
    loop = ej.JobOptions(strategy="loop")
    res = ej.distance_matrix(spheres, METRIC, **kwargs, job=loop)
    assert isinstance(res, ej.DistanceMatrixResult)
    d, change = np.asarray(res.distances), np.asarray(res.refinement_change)
    assert np.asarray(res.pairs_converged).all() and bool(res.converged)
    assert res.result == ej.RESULTS.successful and res.message == ""
    np.testing.assert_array_equal(d, d.T)
    np.testing.assert_array_equal(np.diag(d), 0.0)
    np.testing.assert_array_equal(np.diag(change), 0.0)
    exact = np.sqrt(8 * np.pi) * np.abs(np.subtract.outer(RADII, RADII))
    np.testing.assert_allclose(d, exact, rtol=3e-2)
    steps = 0
    for i, j in [(0, 1), (0, 2), (1, 2)]:
        single = ej.shape_geodesic(spheres[i], spheres[j], METRIC, modulo="rigid", options=SHAPE)
        steps += int(single.num_steps)
        assert d[i, j] == pytest.approx(float(single.distance), rel=1e-6)
        assert change[i, j] == pytest.approx(float(single.refinement.relative_change), rel=1e-6)
        assert 0 < change[i, j] < 0.05  # the 13 x 25 grid moves a distance by about 1 %
        assert d[i, j] >= _area_bound(spheres[i], spheres[j])
    assert int(res.num_steps) == steps  # the record's steps are the pairs' own
    # Killed after the first pair, resumed: the same record, and the checkpoint holds it.
    path = tmp_path / "pairs.npz"

    def kill(info):
        if info["pairs_done"] == 1:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        ej.distance_matrix(
            spheres, METRIC, **kwargs, job=loop.replace(checkpoint=path, progress=kill)
        )
    saved = np.load(path)
    assert saved["done"].tolist() == [True, False, False] and bool(saved["converged"][0])
    resumed = ej.distance_matrix(
        spheres, METRIC, **kwargs, job=loop.replace(checkpoint=path, resume=True)
    )
    jax.tree_util.tree_map(np.testing.assert_array_equal, resumed, res)


def test_distance_matrix_modulo_none_matches_geodesics(tmp_path):
    coll = _collection()
    res = ej.distance_matrix(coll, METRIC, modulo="none", options=FAST)
    d = np.asarray(res.distances)
    np.testing.assert_array_equal(d, d.T)
    np.testing.assert_array_equal(np.diag(d), 0.0)
    assert np.asarray(res.pairs_converged).all()
    change = np.asarray(res.refinement_change)
    assert np.isnan(change[~np.eye(3, dtype=bool)]).all() and (np.diag(change) == 0).all()
    for i, j in [(0, 1), (0, 2), (1, 2)]:
        single = ej.geodesic(coll[i], coll[j], METRIC, degree=3, n_times=5, scheme="midpoint")
        assert d[i, j] == pytest.approx(float(single.distance), rel=1e-6)
    # Killed after the first chunk, resumed: the same matrix.
    path = tmp_path / "pairs.npz"

    def kill(info):
        if info["pairs_done"] == 1:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        ej.distance_matrix(
            coll,
            METRIC,
            modulo="none",
            options=FAST,
            job=ej.JobOptions(batch_size=1, checkpoint=path, progress=kill),
        )
    resumed = ej.distance_matrix(
        coll,
        METRIC,
        modulo="none",
        options=FAST,
        job=ej.JobOptions(batch_size=1, checkpoint=path, resume=True),
    )
    np.testing.assert_allclose(resumed.distances, d, rtol=1e-12)


@pytest.mark.slow
def test_strategies_agree_and_permutation_does_not_matter():
    coll = _collection()
    kwargs = {"modulo": "none", "options": FAST, "max_steps": 15}
    loop = ej.karcher_mean(coll, METRIC, **kwargs, job=ej.JobOptions(strategy="loop"))
    assert loop.converged
    for strategy in ("vmap", "map"):
        other = ej.karcher_mean(coll, METRIC, **kwargs, job=ej.JobOptions(strategy=strategy))
        assert float(jnp.abs(other.mean - loop.mean).max()) < 1e-6
    permuted = ej.karcher_mean(coll[::-1], METRIC, init=coll[0], **kwargs)
    assert float(jnp.abs(permuted.mean - loop.mean).max()) < 1e-5
    np.testing.assert_allclose(permuted.distances[::-1], loop.distances, rtol=1e-4)
    # Sum of squared distances decreases along the iteration.
    assert np.all(np.diff(loop.history[:, 0]) <= 0)


def test_resume_after_a_kill_equals_an_uninterrupted_run(tmp_path):
    coll = _collection()
    kwargs = {"modulo": "none", "options": FAST, "tol": 1e-9, "max_steps": 4}
    full = ej.karcher_mean(coll, METRIC, **kwargs)
    # Parametrized geodesics carry no registration noise: the mean velocity falls to
    # 1e-9 of its first norm in 4 steps, each accepted at once (the second-order initial
    # velocity; the forward difference stalls at 0.7 %, where its step raises the SSD).
    assert full.converged and full.num_steps == 4 and full.num_solves == 5
    assert np.all(np.diff(full.history[:, 0]) <= 0)
    assert full.history[-1, 1] < 1e-8 * full.history[0, 1]
    path = tmp_path / "karcher.npz"

    def kill_after_two(info):
        if info["step"] == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        ej.karcher_mean(
            coll, METRIC, **kwargs, job=ej.JobOptions(checkpoint=path, progress=kill_after_two)
        )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["karcher.npz"]  # nothing half-written
    resumed = ej.karcher_mean(
        coll, METRIC, **kwargs, job=ej.JobOptions(checkpoint=path, resume=True)
    )
    np.testing.assert_allclose(resumed.mean, full.mean, atol=1e-12)
    np.testing.assert_allclose(resumed.history, full.history, rtol=1e-12)
    np.testing.assert_allclose(resumed.distances, full.distances, rtol=1e-12)
    assert (resumed.num_steps, resumed.num_solves, resumed.result) == (
        full.num_steps,
        full.num_solves,
        full.result,
    )
    with pytest.raises(ValueError, match="other shapes or settings"):
        ej.karcher_mean(
            coll[::-1], METRIC, **kwargs, job=ej.JobOptions(checkpoint=path, resume=True)
        )


def test_one_orbit_converges_at_step_zero():
    # Copies of one shape under rigid motions (issue 30): every distance is at rounding
    # level, so the mean velocity is too and tol x RMS would only test rounding (this ended
    # line_search_failed). The orbit test stops at the start, after one batch of solves.
    f = shapes.sample(shapes.bumpy, M, N)
    shift = jnp.asarray([0.3, -0.1, 0.2])[:, None, None]
    moved = [jnp.einsum("ij,jmn->imn", shapes.random_rotation(k), f) + k * shift for k in (3, 5)]
    res = ej.karcher_mean(
        jnp.stack([f, *moved]),
        METRIC,
        modulo="rigid",
        options=SHAPE,
        job=ej.JobOptions(strategy="loop"),
    )
    assert res.converged and ej.RESULTS.name(res.result) == "distances_at_rounding", res.message
    assert (res.num_steps, res.num_solves) == (0, 1)
    assert float(jnp.max(res.distances)) < 1e-8
    same = ej.karcher_mean(jnp.stack([f, f]), METRIC, modulo="none", options=FAST)
    assert (
        ej.RESULTS.name(same.result) == "distances_at_rounding"
        and float(jnp.max(same.distances)) == 0.0
    )


@pytest.mark.filterwarnings("ignore::elastic_jax.ConvergenceWarning")  # max_steps=1
def test_line_search_rejects_steps_that_raise_the_sum_or_are_not_finite(monkeypatch):
    # A step 12 times too long overshoots: the line search halves it until the sum of
    # squared distances falls. A trial with a NaN distance is never accepted.
    coll = _collection()
    res = ej.karcher_mean(coll, METRIC, modulo="none", options=FAST, step_size=12.0, max_steps=1)
    assert res.history[1, 2] in (1.5, 0.75) and res.num_solves in (5, 6)
    assert res.history[1, 0] <= res.history[0, 0]

    from elastic_jax._statistics import batching as _batching

    real = _batching._one_geodesic
    calls = []

    def nan_after_first(mean, shape, *args):
        out = real(mean, shape, *args)
        calls.append(1)
        return (jnp.nan * out[0], *out[1:]) if len(calls) > 3 else out

    monkeypatch.setattr(_batching, "_one_geodesic", nan_after_first)
    with pytest.warns(ej.ConvergenceWarning, match="line search"):
        res = ej.karcher_mean(
            coll, METRIC, modulo="none", options=FAST, job=ej.JobOptions(strategy="loop")
        )
    assert ej.RESULTS.name(res.result) == "line_search_failed" and not res.converged
    assert res.num_steps == 0 and res.history.shape == (1, 3) and np.isfinite(res.distances).all()
    np.testing.assert_array_equal(res.mean, coll[0])

    # The same failure while a geodesic at the mean is held at the grid's resolution (its
    # registration's result) is reported as that: the SSD has a kink there.
    calls.clear()

    def limited_then_nan(mean, shape, *args):
        out = nan_after_first(mean, shape, *args)
        return (*out[:6], jnp.asarray(len(calls) == 2), out[7])  # the limited flag

    monkeypatch.setattr(_batching, "_one_geodesic", limited_then_nan)
    with pytest.warns(ej.ConvergenceWarning, match="resolution_limited"):
        res = ej.karcher_mean(
            coll, METRIC, modulo="none", options=FAST, job=ej.JobOptions(strategy="loop")
        )
    assert ej.RESULTS.name(res.result) == "resolution_limited" and not res.converged
    assert res.num_steps == 0 and res.num_solves == 6  # the first solves and 5 trials


SHARDED = """
import json, jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import elastic_jax as ej
from elastic_jax import shapes
m, n = 13, 25
coll = jnp.stack([shapes.sample(shapes.bumpy, m, n),
                  shapes.sample(shapes.ellipsoid, m, n, axes=(1.1, 0.9, 0.7)),
                  shapes.sample(shapes.bumpy, m, n, scale=1.3)])
res = ej.karcher_mean(coll, ej.SplitMetric(1.0, 1.0, 0.1, 0.0), modulo="none",
                      job=ej.JobOptions(strategy="vmap"),
                      options=ej.ShapeOptions(degree=3, n_times=5), max_steps=2)
print(json.dumps({"devices": jax.device_count(), "mean": res.mean.ravel().tolist()}))
"""


@pytest.mark.slow
def test_sharded_equals_unsharded():
    env = {
        **os.environ,
        "XLA_FLAGS": "--xla_force_host_platform_device_count=4",
        "JAX_PLATFORMS": "cpu",
    }
    out = subprocess.run(
        [sys.executable, "-c", SHARDED],
        env=env,
        capture_output=True,
        text=True,
        check=True,
        timeout=600,
    )
    sharded = json.loads(out.stdout.strip().splitlines()[-1])
    assert sharded["devices"] == 4
    coll = _collection()
    single = ej.karcher_mean(
        coll, METRIC, modulo="none", max_steps=2, options=FAST, job=ej.JobOptions(strategy="vmap")
    )
    np.testing.assert_allclose(np.asarray(sharded["mean"]).reshape(3, M, N), single.mean, atol=1e-9)


def test_errors():
    coll = _collection()
    with pytest.raises(ValueError, match="modulo must be one of"):
        ej.karcher_mean(coll, METRIC, modulo="affine")
    with pytest.raises(ValueError, match="strategy must be one of"):
        ej.distance_matrix(coll, METRIC, job=ej.JobOptions(strategy="threads"))
    with pytest.raises(ValueError, match=r"\(K, 3, m, n\) with K >= 2"):
        ej.karcher_mean(coll[:1], METRIC)
    # A wrong options record is an InputError, as in every function that takes one.
    for function in (ej.karcher_mean, ej.distance_matrix, ej.fit_metric):
        with pytest.raises(ej.InputError, match=f"{function.__name__}: options must be an"):
            function(coll, METRIC, options={"degree": 3})
    with pytest.raises(TypeError, match="degree"):
        ej.karcher_mean(coll, METRIC, degree=3)  # inner options travel in `options` only
    with pytest.raises(ValueError, match="vf_degree=30 is too high"):
        ej.distance_matrix(coll, METRIC, options=ej.ShapeOptions(vf_degree=30))
    for name, value in [("max_steps", -1), ("tol", 0.0), ("step_size", float("nan"))]:
        with pytest.raises(ValueError, match=name):
            ej.karcher_mean(coll, METRIC, **{name: value})
    with pytest.raises(ValueError, match="batch_size"):
        ej.distance_matrix(coll, METRIC, job=ej.JobOptions(batch_size=0))
    with pytest.raises(ValueError, match="init must be one surface"):
        ej.karcher_mean(coll, METRIC, init=coll)


# Inner shape geodesics at 13 x 25 stop at interpolation-noise energies and may warn.
@pytest.mark.filterwarnings("ignore::elastic_jax.ConvergenceWarning")
@pytest.mark.slow
def test_mean_is_invariant_to_reparametrization_and_rotation():
    f = shapes.sample(shapes.bumpy, M, N)
    moved = shapes.sample(shapes.bumpy, M, N, rotation=shapes.random_rotation(1))
    turned = jnp.einsum(
        "ij,jmn->imn",
        shapes.random_rotation(2),
        shapes.sample(shapes.bumpy, M, N, rotation=shapes.random_rotation(3)),
    )
    res = ej.karcher_mean(
        jnp.stack([f, moved, turned]),
        METRIC,
        modulo="rigid",
        options=SHAPE,
        max_steps=3,
        job=ej.JobOptions(strategy="loop"),
    )
    to_f = ej.shape_geodesic(res.mean, f, METRIC, modulo="rigid", options=SHAPE).distance
    reference = ej.shape_geodesic(
        shapes.sample(shapes.ellipsoid, M, N), f, METRIC, modulo="rigid", options=SHAPE
    )
    assert float(to_f) < 0.1 * float(reference.distance)
    assert float(jnp.max(res.distances)) < 0.1 * float(reference.distance)


def _top_level_traces(call) -> list[str]:
    """The functions JAX traced for a new compiled program while ``call()`` ran."""
    return traced_functions(call)[1]


@pytest.mark.filterwarnings("ignore::elastic_jax.ConvergenceWarning")  # max_steps=1
def test_new_surfaces_on_the_same_grid_trace_nothing_new():
    """Everything that changes a compiled program is static (grid, options, dtype): a
    second call with other surfaces reuses the first call's programs, for a geodesic, a
    shape geodesic and a Karcher step."""
    first = _collection()
    second = jnp.stack(
        [
            shapes.sample(shapes.ellipsoid, M, N, axes=(0.9, 1.2, 0.8)),
            shapes.sample(shapes.bumpy, M, N, scale=0.8, rotation=shapes.random_rotation(4)),
            shapes.sample(shapes.sphere, M, N, radius=1.4),
        ]
    )
    calls = {
        "geodesic": lambda c: ej.geodesic(c[0], c[1], METRIC, degree=3, n_times=5).distance,
        "shape_geodesic": lambda c: (
            ej.shape_geodesic(c[0], c[2], METRIC, modulo="rigid", options=SHAPE).distance
        ),
        "karcher step": lambda c: (
            ej.karcher_mean(
                c,
                METRIC,
                modulo="rigid",
                options=SHAPE,
                max_steps=1,
                job=ej.JobOptions(strategy="loop"),
            ).mean
        ),
    }
    import jax

    # The listener sees a new program's trace (and only the outermost one).
    assert _top_level_traces(lambda: jax.jit(lambda x: jnp.sin(x) + 1)(2.0)) == ["<lambda>"]
    for name, call in calls.items():
        _top_level_traces(lambda call=call: np.asarray(call(first)))
        again = _top_level_traces(lambda call=call: np.asarray(call(second)))
        assert again == [], (name, again)


@pytest.mark.parametrize("name", ["karcher_mean", "distance_matrix", "fit_metric"])
def test_a_progress_that_is_not_callable_is_named_before_any_solve(name):
    spheres = jnp.stack([shapes.sample(shapes.sphere, M, N, radius=r) for r in (1.0, 2.0)])
    args = (spheres, [0, 1]) if name == "fit_metric" else (spheres, METRIC)
    with pytest.raises(ej.InputError, match="progress must be a callable taking a dict; got 3"):
        getattr(ej, name)(*args, job=ej.JobOptions(progress=3))
