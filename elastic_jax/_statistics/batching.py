"""Batches of inner solves for Karcher means and distance matrices: one geodesic per
shape or pair, run by lax.map, vmap (sharded over devices) or a loop, chunk by chunk,
each chunk padded to the compiled batch shape (math §7).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from jaxtyping import Array, ArrayLike, Float

from .._errors import InputError
from .._geodesics.geodesic import solve_geodesic
from .._geometry.grid import sphere_points
from .._geometry.metric import SplitMetric
from .._geometry.numerics import default_tol
from .._geometry.validation import as_surface, check_grid_options, check_levels
from .._options import ShapeOptions, check_choice, options_with
from .._registration.levels import (
    LevelOutcome,
    alternated,
    candidate_starts,
    level_start,
    lowest,
    noise_distance,
    one_candidate,
    run_levels,
    spread_of,
)
from .._registration.one_grid import continued_geodesic
from .._registration.records import ShapeGeodesicResult, turned_back
from .._registration.shape import solve_shapes
from .._results import RESULTS
from .._runtime.cache import solver_jit

MODULI = ("rigid", "diff", "none")


STRATEGIES = ("auto", "vmap", "map", "loop")


def default_strategy() -> str:
    """The batching strategy "auto" resolves to on this backend.

    CPU: "map" (lax.map in one jit). Measured by benchmarks/bench_karcher.py on 2 cores
    (8 surfaces at 25 x 49, rigid, one Karcher step after compilation): map 17.7 s, a
    Python loop 19.8 s, vmap 52.8 s; a vmapped BFGS runs in lockstep until its slowest
    member converges and its dense per-item updates do not vectorize on a CPU.
    Accelerators: "vmap", where batching is what pays.
    """
    return "map" if jax.default_backend() == "cpu" else "vmap"


def initial_velocity(path: Float[ArrayLike, "N 3 m n"]) -> Float[Array, "3 m n"]:
    """Initial velocity of a discrete path: T (-3 f_0 + 4 f_1 - f_2) / 2, T = N - 1.

    The second-order one-sided difference. The forward difference T (f_1 - f_0) is the
    velocity at t = 1 / (2T), off by f''(0) / (2T); the Karcher iteration's fixed point
    moves with it, away from the minimum of the (second-order, midpoint) discrete sum of
    squared distances, and the line search stalls there (docs/guides/collections.md).
    """
    t = path.shape[0] - 1
    return t * (-3.0 * path[0] + 4.0 * path[1] - path[2]) / 2.0


def _one_geodesic(
    mean: ArrayLike,
    shape: ArrayLike,
    metric: SplitMetric,
    modulo: str,
    options: ShapeOptions,
    start: tuple | None = None,
):
    """Distance, registered shape, initial velocity at the mean, status, registration
    (gamma, R), resolution_limited flag and the path's coefficients, for one shape.

    Every geodesic runs from the shape to the mean, as shape_geodesic must (it
    reparametrizes its first surface and rotates its second), also for modulo="none", so
    that a one-sided scheme ("forward") treats the mean alike for every modulo.

    ``start``:

    - None: shape_geodesic's start search.
    - (gamma, R): a second solve whose registration rounds start there (the shape's
      registration at the previous mean) instead of the start search; the lower of the
      two distances is kept (``warm_start``). The search alone may land in another basin
      at a mean moved a little and make the sum of squared distances jump; the warm
      solve follows its basin, while the search still finds a lower basin when there
      is one.
    - (gamma, R, C): a pure continuation (the resolved Karcher mean): one solve whose
      registration rounds with the whole path start from that registration and path
      (no start search, no coarse rounds; :func:`continued_geodesic`). The distance is
      then a continuous function of the mean: no jump to another basin.
    """
    if modulo == "none":
        res = solve_geodesic(shape, mean, metric, **options.geodesic_kwargs())
        m, n = mean.shape[-2:]
        gamma, rotation = sphere_points(m, n, mean.dtype), jnp.eye(3, dtype=mean.dtype)
        back = res.path
        limited = jnp.zeros((), bool)
    else:
        if start is not None and len(start) == 3:
            res = continued_geodesic(shape, mean, metric, modulo, options, *start)
        else:
            res = solve_shapes(shape, mean, metric, modulo, options)
        if start is not None and len(start) == 2:
            warm = solve_shapes(shape, mean, metric, modulo, options, start=start)
            lower = warm.distance < res.distance
            res = jax.tree_util.tree_map(lambda a, b: jnp.where(lower, a, b), warm, res)
        gamma, rotation = res.gamma, res.rotation
        back = turned_back(res, mean)
        limited = res.result == RESULTS.resolution_limited
    velocity = initial_velocity(back[::-1])
    return (
        res.distance,
        back[0],
        velocity,
        res.converged,
        gamma,
        rotation,
        limited,
        res.coefficients,
    )


def _one_item(
    mean: ArrayLike,
    item: ArrayLike | tuple,
    metric: SplitMetric,
    modulo: str,
    options: ShapeOptions,
):
    """:func:`_one_geodesic` for a batch item: a shape, or (shape, gamma, R) to warm-start,
    or (shape, gamma, R, C) to continue."""
    if isinstance(item, tuple):
        return _one_geodesic(mean, item[0], metric, modulo, options, item[1:])
    return _one_geodesic(mean, item, metric, modulo, options)


def _pair_distance(
    a: ArrayLike, b: ArrayLike, metric: SplitMetric, modulo: str, options: ShapeOptions
):
    """Distance, status, refinement change, result code and solver steps of one pair."""
    if modulo == "none":
        res = solve_geodesic(a, b, metric, **options.geodesic_kwargs())
        change = jnp.full_like(res.distance, jnp.nan)
    else:
        res = solve_shapes(a, b, metric, modulo, options)
        change = res.refinement.relative_change
    # The code as an integer: the chunk's outputs are plain arrays (checkpoints, Dask).
    code = jnp.asarray(res.result._value, jnp.int32)
    return res.distance, res.converged, change, code, jnp.asarray(res.num_steps, jnp.int32)


def _registered_pair(
    a: ArrayLike,
    b: ArrayLike,
    metric: SplitMetric,
    modulo: str,
    options: ShapeOptions,
    start: tuple | None = None,
):
    """One pair's solve, warm-started at ``start`` (gamma, R, C) when given: distance,
    status, result code, solver steps, and the solution (gamma, R, C) that
    :func:`elastic_jax.fit_metric` holds when it differentiates the distance in the metric.

    modulo="none": the geodesic from the path coefficients C (gamma and R are the identity).
    Otherwise: shape_geodesic's start search, or with ``start`` a pure continuation of
    that registration and path (:func:`continued_geodesic`: no start search and no coarse
    rounds). The coarse rounds re-register on the L2 mismatch and leave the basin; with
    them the re-solved distances at a nearby metric moved by more than a fit's step
    gains, and the animals' fit stalled after 6 steps.
    """
    if modulo == "none":
        init = None if start is None else start[2]
        res = solve_geodesic(a, b, metric, init=init, **options.geodesic_kwargs())
        m, n = a.shape[-2:]
        gamma, rotation = sphere_points(m, n, a.dtype), jnp.eye(3, dtype=a.dtype)
    else:
        if start is None:
            res = solve_shapes(a, b, metric, modulo, options)
        else:
            res = continued_geodesic(a, b, metric, modulo, options, *start)
        gamma, rotation = res.gamma, res.rotation
    code = jnp.asarray(res.result._value, jnp.int32)
    steps = jnp.asarray(res.num_steps, jnp.int32)
    return res.distance, res.converged, code, steps, gamma, rotation, res.coefficients


# Module-level jitted batch solves: the mean and the metric are arguments and the options
# (a frozen ShapeOptions) a static key, so consecutive Karcher steps reuse one compilation.
@functools.partial(solver_jit, static_argnames=("modulo", "options", "mode"))
def _velocities_batch(
    mean: ArrayLike,
    batch: ArrayLike | tuple,
    metric: SplitMetric,
    *,
    modulo: str,
    options: ShapeOptions,
    mode: str,
):
    """batch: shapes ``(b, 3, m, n)``, or (shapes, gammas, rotations) for warm starts, or
    (shapes, gammas, rotations, coefficients) for continuations."""

    def one(item: ArrayLike | tuple):
        return _one_item(mean, item, metric, modulo, options)

    return jax.lax.map(one, batch) if mode == "map" else jax.vmap(one)(batch)


@functools.partial(solver_jit, static_argnames=("modulo", "options", "mode"))
def _distances_batch(
    pairs: tuple, metric: SplitMetric, *, modulo: str, options: ShapeOptions, mode: str
):
    def one(pair: tuple):
        return _pair_distance(pair[0], pair[1], metric, modulo, options)

    return jax.lax.map(one, pairs) if mode == "map" else jax.vmap(one)(pairs)


@functools.partial(solver_jit, static_argnames=("modulo", "options", "mode"))
def _registered_batch(
    batch: tuple, metric: SplitMetric, *, modulo: str, options: ShapeOptions, mode: str
):
    """batch: (firsts, seconds) or (firsts, seconds, gammas, rotations, coefficients)."""

    def one(item: tuple):
        return _registered_pair(item[0], item[1], metric, modulo, options, item[2:] or None)

    return jax.lax.map(one, batch) if mode == "map" else jax.vmap(one)(batch)


def _batched(
    batch_call: Callable, single_call: Callable, batch: ArrayLike | tuple, strategy: str
) -> tuple:
    """Run ``single_call`` over the leading axis of ``batch`` (a pytree) by ``strategy``.

    ``batch_call(batch, mode)`` is the jitted lax.map / vmap form. With several devices
    the vmap batch is sharded over a one-axis mesh (optimistix solves break under
    shard_map; jit partitions a NamedSharding-placed input instead).
    """
    size = jax.tree_util.tree_leaves(batch)[0].shape[0]
    if strategy == "loop":
        items = [jax.tree_util.tree_map(lambda x, i=i: x[i], batch) for i in range(size)]
        outs = [single_call(item) for item in items]
        return tuple(jnp.stack(parts) for parts in zip(*outs, strict=True))
    devices = jax.devices()
    if strategy == "vmap" and len(devices) > 1:
        padded = _padded(batch, size + (-size) % len(devices))
        sharding = NamedSharding(Mesh(np.asarray(devices), ("batch",)), PartitionSpec("batch"))
        batch = jax.tree_util.tree_map(lambda x: jax.device_put(x, sharding), padded)
        return tuple(o[:size] for o in batch_call(batch, strategy))
    return batch_call(batch, strategy)


def _solve_chunk(
    batch_call: Callable, single_call: Callable, batch: ArrayLike | tuple, strategy: str, size: int
):
    """``_batched`` over a chunk (a pytree, leading axis b) padded to ``size`` items, the
    compiled batch shape (the padding is dropped): every chunk of a job runs one compiled
    program, here or on a Dask worker. The loop strategy solves one item at a time and is
    not padded. The solves do not warn (solve_shapes, solve_geodesic): callers report each
    item's status."""
    b = jax.tree_util.tree_leaves(batch)[0].shape[0]
    padded = batch if strategy == "loop" else _padded(batch, size)
    return tuple(out[:b] for out in _batched(batch_call, single_call, padded, strategy))


def velocity_chunk(
    mean: ArrayLike,
    chunk: ArrayLike,
    metric: SplitMetric,
    modulo: str,
    options: ShapeOptions,
    strategy: str,
    size: int,
    starts: tuple | None = None,
) -> tuple:
    """The geodesics from ``chunk`` (b, 3, m, n) to ``mean``: the _Solved fields.

    starts: None, or (gammas (b, 3, m, n), rotations (b, 3, 3)), each shape's registration
    at the previous mean: every shape is then solved twice and the lower kept; or
    (gammas, rotations, coefficients (b, N - 2, L)): every shape's solve continues its
    registration and path at the previous mean (:func:`_one_geodesic`)."""
    batch = chunk if starts is None or modulo == "none" else (chunk, *starts)

    def batch_call(batch: ArrayLike | tuple, mode: str):
        return _velocities_batch(mean, batch, metric, modulo=modulo, options=options, mode=mode)

    def single_call(item: ArrayLike | tuple):
        return _one_item(mean, item, metric, modulo, options)

    return _solve_chunk(batch_call, single_call, batch, strategy, size)


def distance_chunk(
    first: ArrayLike,
    second: ArrayLike,
    metric: SplitMetric,
    modulo: str,
    options: ShapeOptions,
    strategy: str,
    size: int,
) -> tuple:
    """Distance, status, refinement change, result code, solver steps, levels estimate,
    finest grid and candidates' spread of the pairs (first[i], second[i]): by levels
    (:func:`levelled_chunk`) when ``options.resolves`` and modulo is not "none", else on
    ``options.grid`` or the pairs' own grid (estimate and spread NaN)."""
    if options.resolves and modulo != "none":
        return levelled_chunk(first, second, metric, modulo, options, strategy, size)[:8]
    b = np.shape(first)[0]
    grid = options.grid or tuple(np.shape(first)[-2:])
    extra = (np.full(b, np.nan), np.tile(np.asarray(grid, np.int32), (b, 1)), np.full(b, np.nan))

    def batch_call(batch: tuple, mode: str):
        return _distances_batch(batch, metric, modulo=modulo, options=options, mode=mode)

    def single_call(pair: tuple):
        return _pair_distance(pair[0], pair[1], metric, modulo, options)

    return (*_solve_chunk(batch_call, single_call, (first, second), strategy, size), *extra)


def registered_chunk(
    first: ArrayLike,
    second: ArrayLike,
    metric: SplitMetric,
    modulo: str,
    options: ShapeOptions,
    strategy: str,
    size: int,
    starts: tuple | None = None,
):
    """The pairs (first[i], second[i]) solved with their solutions: distance, status, result
    code, solver steps, gamma, R and the path coefficients C (:func:`_registered_pair`).

    starts: None (the start search, or the straight line for modulo="none"), or
    (gammas (b, 3, m, n), rotations (b, 3, 3), coefficients (b, N - 2, L)) to start from.

    Without starts and with ``options.resolves`` (modulo "diff" / "rigid") the pairs are
    resolved by levels (:func:`levelled_chunk`): gamma is then a list, each pair's on the
    finest grid it reached. With starts the pairs continue on the starts' grid (a
    resolved pair's finest level's, or the pairs' own).
    """
    if modulo != "none" and starts is None and options.resolves:
        out = levelled_chunk(first, second, metric, modulo, options, strategy, size)
        fields = (out.distance, out.converged, out.result, out.num_steps)
        return (*fields, list(out.gamma), out.rotation, out.coefficients)
    if modulo != "none" and starts is not None:
        grid = tuple(np.shape(starts[0])[-2:])
        if options.resolves or grid != tuple(np.shape(first)[-2:]):
            options = options.on_level(grid)
    batch = (first, second) if starts is None else (first, second, *starts)

    def batch_call(batch: tuple, mode: str):
        return _registered_batch(batch, metric, modulo=modulo, options=options, mode=mode)

    def single_call(item: tuple):
        return _registered_pair(item[0], item[1], metric, modulo, options, item[2:] or None)

    return _solve_chunk(batch_call, single_call, batch, strategy, size)


def _level_pair(
    a: ArrayLike,
    b: ArrayLike,
    metric: SplitMetric,
    modulo: str,
    options: ShapeOptions,
    start: tuple | None = None,
):
    """One pair's solve on one level (``options.grid``): :func:`_registered_pair`'s
    outputs, then the parametrized distance and the refinement change, which the levels'
    estimate and the matrix's record need, and the parametrized geodesic's coefficients
    (where the next level's starts). ``start``: None (a start search), (gamma, R) to
    start the rounds from (a candidate's first level), or (gamma, R, C, parametrized C)
    of the level below to continue."""
    if start is None or len(start) == 2:
        res = solve_shapes(a, b, metric, modulo, options, start)
    else:
        res = continued_geodesic(a, b, metric, modulo, options, *start)
    return _solution_of(res)


def _solution_of(res: ShapeGeodesicResult) -> _LevelSolution:
    """A one-grid result as a level's solution (:class:`_LevelSolution`)."""
    return _LevelSolution(
        res.distance,
        res.converged,
        jnp.asarray(res.result._value, jnp.int32),
        jnp.asarray(res.num_steps, jnp.int32),
        res.gamma,
        res.rotation,
        res.coefficients,
        res.parametrized_distance,
        res.refinement.relative_change,
        res.parametrized_coefficients,
    )


def _tiny(x: ArrayLike) -> float:
    return float(np.finfo(np.asarray(x).dtype).tiny)


class _LevelSolution(NamedTuple):
    """:func:`_level_pair`'s outputs by name (one pair's, or a group's stacked)."""

    distance: ArrayLike
    converged: ArrayLike
    result: ArrayLike
    num_steps: ArrayLike
    gamma: ArrayLike
    rotation: ArrayLike
    coefficients: ArrayLike
    parametrized_distance: ArrayLike
    refinement_change: ArrayLike
    parametrized_coefficients: ArrayLike


@functools.partial(solver_jit, static_argnames=("modulo", "options", "mode"))
def _level_batch(
    batch: tuple, metric: SplitMetric, *, modulo: str, options: ShapeOptions, mode: str
):
    """batch: (firsts, seconds), with (gammas, rotations) to start from or (gammas,
    rotations, coefficients, parametrized coefficients) to continue (:func:`_level_pair`)."""

    def one(item: tuple):
        return _level_pair(item[0], item[1], metric, modulo, options, item[2:] or None)

    return jax.lax.map(one, batch) if mode == "map" else jax.vmap(one)(batch)


class LevelledPairs(NamedTuple):
    """What :func:`levelled_chunk` returns for b pairs solved by levels (math §10).

    ``distance``, ``converged``, ``refinement_change``, ``result`` (int codes) and
    ``num_steps`` (over all levels and candidates) are ``(b,)``, the first five of a
    distance chunk;
    ``estimate`` ``(b,)`` the last two levels' relative change (NaN after one level);
    ``grid`` ``(b, 2)`` the finest grid each pair reached; ``spread`` ``(b,)`` its
    candidates' spread (:class:`Levels` ``spread``; 0 with one); ``level_distances`` ``(b, L)``
    each level's distance (of the last level's minimum, as :class:`Levels` ``distances``;
    NaN past the level where a pair resolved); ``gamma``
    ``(b, 3, m, n)`` on that finest grid when every pair reached the same one, else a
    list; ``rotation`` ``(b, 3, 3)``, ``coefficients`` ``(b, N - 2, L')``.
    """

    distance: np.ndarray
    converged: np.ndarray
    refinement_change: np.ndarray
    result: np.ndarray
    num_steps: np.ndarray
    estimate: np.ndarray
    grid: np.ndarray
    spread: np.ndarray
    level_distances: np.ndarray
    gamma: list
    rotation: np.ndarray
    coefficients: np.ndarray


def levelled_chunk(
    first: ArrayLike,
    second: ArrayLike,
    metric: SplitMetric,
    modulo: str,
    options: ShapeOptions,
    strategy: str,
    size: int,
    report: Callable[[int, dict], None] | None = None,
) -> LevelledPairs:
    """The pairs (first[i], second[i]) by levels of working grids, all at once: the
    first level of ``options.levels`` searches each pair's start, every later level
    continues the pairs still going from their registration and path on the level
    below (:func:`continued_geodesic`), and a pair leaves once two successive
    distances agree within ``options.rtol`` (as :func:`shape_geodesic` decides for one
    pair; its result code ``not_resolved`` when the last level converged but missed rtol).

    Each pair carries the candidates a resolved shape_geodesic carries
    (:func:`candidate_starts`: ``level_candidates``, ``both_orders``,
    ``search_smoothing``): every candidate is one more item of each level's batch, the
    lowest final distance is the pair's, and the pair is resolved only when its
    candidates' ``spread`` is within rtol too. A pair is therefore shape_geodesic's
    resolved distance of that pair, candidates and all.

    A carried registration whose interpolant folds between the next grid's points (the
    check of ``shape_geodesic(start=...)``) searches a start of its own on that level
    (graduated, for the graduated candidates: :func:`graduated_search`,
    :func:`other_order_graduated`).
    "vmap" solves each level's pairs side by side, padded to ``size`` (traced: a pair
    whose rounds end above the pair as given is not solved again from it, as a concrete
    shape_geodesic would); "map" and "loop" one after another through shape_geodesic's
    own compiled phases (a vmapped step costs the batch's size on a CPU, and a padded
    lax.map solves its padding). The graduated candidate's low-passed solves run one
    after another.

    The levels' loop is :func:`run_levels`, the one shape_geodesic's levels run (a
    single pair is a batch of one there); this function solves each level's pairs.

    ``report(i, info)``: after each level, for each pair i solved on it, as
    shape_geodesic's progress reports a level (``stage`` "level", ``level`` and
    ``levels`` counted from 1, ``grid``, ``distance``, ``converged``, and
    ``candidate`` counted from 1 where a pair carries several).
    """
    first, second = jnp.asarray(first), jnp.asarray(second)
    count = first.shape[0]
    levels = options.levels
    check_levels(options)
    # Every candidate of every pair is a track of the levels (owner: its pair). The
    # levels' solves share one static record whatever the candidates' options and
    # round trips (which run on the host).
    plain = one_candidate(options)
    owner, rank, starts = [], [], []
    for i in range(count):
        own = candidate_starts(first[i], second[i], metric, modulo, options)
        owner += [i] * len(own)
        rank += range(1, len(own) + 1)
        starts += own
    owner = np.asarray(owner)
    many = len(starts) > count
    noise = [noise_distance(first[i], second[i]) for i in range(count)]
    mode = "loop" if strategy == "map" else strategy
    steps = np.zeros(count, np.int64)

    def solve_group(tracks: list, level: ShapeOptions, given: tuple | None):
        def batch_call(batch: tuple, mode: str):
            return _level_batch(batch, metric, modulo=modulo, options=level, mode=mode)

        def single_call(item: tuple):
            return _level_pair(item[0], item[1], metric, modulo, level, item[2:] or None)

        pairs = jnp.asarray(owner[tracks])
        batch = (first[pairs], second[pairs])
        if given is not None:
            batch = (*batch, *given)
        # Candidates make a group longer than the chunk: solved ``size`` at a time, so
        # that every group runs the one compiled batch shape.
        parts = [
            _solve_chunk(batch_call, single_call, _part(batch, a, b), mode, size)
            for a, b in chunk_bounds(len(tracks), size)
        ]
        return tuple(
            np.concatenate([np.asarray(x) for x in out]) for out in zip(*parts, strict=True)
        )

    def solve(
        index: int, grid: tuple[int, int], going: list, below: list, again: bool = False
    ) -> list:
        # Each track begins as a lone shape_geodesic's candidate would (level_start);
        # the tracks that begin alike are solved as one group.
        level = plain.on_level(grid)
        searched, started, carried = [], [], []
        for t, sol in zip(going, below, strict=True):
            i = owner[t]
            plan = level_start(
                first[i], second[i], metric, modulo, options, grid, sol, starts[t], again
            )
            group = {"search": searched, "start": started, "carry": carried}.get(plan.kind)
            if group is not None:
                group.append((t, plan.given))
        groups = [] if not searched else [([t for t, _ in searched], None)]
        for group in (started, carried):
            if group:
                given = tuple(
                    jnp.stack([jnp.asarray(x) for x in parts])
                    for parts in zip(*[item for _, item in group], strict=True)
                )
                groups.append(([t for t, _ in group], given))
        outcomes = {}
        for tracks, given in groups:
            solved = _LevelSolution(*(np.asarray(x) for x in solve_group(tracks, level, given)))
            for k, t in enumerate(tracks):
                sol = _LevelSolution(*(x[k] for x in solved))
                i = owner[t]
                # As a lone shape_geodesic's level does (level_solve), on the host.
                better = alternated(first[i], second[i], metric, modulo, options, grid, sol)
                if better is not sol:
                    sol = _LevelSolution(*(np.asarray(x) for x in _solution_of(better)))
                d, ok = float(sol.distance), bool(sol.converged)
                steps[owner[t]] += sol.num_steps
                outcomes[t] = LevelOutcome(
                    d,
                    ok,
                    float(sol.parametrized_distance),
                    sol,
                    # Refinement.relative_change is relative to max(d, tiny).
                    refined_gap=float(sol.refinement_change) * max(d, _tiny(sol.distance)),
                )
                if report is not None:
                    info = {"level": index + 1, "levels": len(levels), "grid": tuple(grid)}
                    info.update({"again": True} if again else {})
                    info.update({"candidate": rank[t]} if many else {})
                    report(
                        int(owner[t]), {"stage": "level", **info, "distance": d, "converged": ok}
                    )
        return [outcomes.get(t) for t in going]

    tracks = run_levels(len(starts), levels, options.rtol, [noise[i] for i in owner], solve)
    # Each pair's winner: its candidate with the lowest final distance.
    winners, spread = [], np.zeros(count)
    for i in range(count):
        own = np.flatnonzero(owner == i)
        finals = [float(tracks[t].solution.distance) for t in own]
        best = tracks[own[lowest(finals)]]
        winners.append(best)
        spread[i] = spread_of(finals, best.solution.parametrized_distance)
    solutions = [t.solution for t in winners]
    estimate = np.asarray([t.estimate for t in winners], np.float64)
    level_distances = np.full((count, len(levels)), np.nan)
    for i, t in enumerate(winners):
        level_distances[i, : len(t.distances)] = t.distances
    converged = np.asarray([bool(sol.converged) for sol in solutions])
    result = np.asarray([int(sol.result) for sol in solutions], np.int32)
    met = (estimate <= options.rtol) & (spread <= options.rtol)
    result[converged & ~met] = RESULTS.not_resolved._value
    gammas = [sol.gamma for sol in solutions]
    same = len({g.shape for g in gammas}) == 1
    return LevelledPairs(
        distance=np.asarray([float(sol.distance) for sol in solutions]),
        converged=converged & met,
        refinement_change=np.asarray([float(sol.refinement_change) for sol in solutions]),
        result=result,
        num_steps=steps,
        estimate=estimate,
        grid=np.asarray([t.grids[-1] for t in winners], np.int32),
        spread=spread,
        level_distances=level_distances,
        gamma=np.stack(gammas) if same else gammas,
        rotation=np.stack([np.asarray(sol.rotation) for sol in solutions]),
        coefficients=np.stack([np.asarray(sol.coefficients) for sol in solutions]),
    )


def _part(batch: tuple, a: int, b: int) -> tuple:
    return jax.tree_util.tree_map(lambda x: x[a:b], batch)


def chunk_bounds(n: int, size: int | None):
    size = n if size is None else size
    return [(start, min(start + size, n)) for start in range(0, n, size)]


def default_chunk(strategy: str) -> int | None:
    """Pairs per chunk when batch_size is None: the sequential strategies gain nothing from
    big chunks, so they checkpoint every pair (loop) or every 8 pairs (map); vmap takes all."""
    return {"loop": 1, "map": 8}.get(strategy)


def _padded(batch: ArrayLike | tuple, size: int):
    """``batch`` (a pytree, leading axis b <= size) padded to ``size`` by repeating its last
    item, so that every chunk has the compiled batch shape (a smaller last chunk would
    compile the whole solve again)."""

    def pad(x: ArrayLike):
        extra = max(size - x.shape[0], 0)
        return jnp.concatenate([x, jnp.repeat(x[-1:], extra, axis=0)]) if extra else x

    return jax.tree_util.tree_map(pad, batch)


def check_collection(
    shapes: ArrayLike,
    options: ShapeOptions | None,
    modulo: str,
    name: str = "shapes",
    levels: bool = False,
    function: str = "karcher_mean",
):
    """The collection ``(K, 3, m, n)`` and its options, checked on its grid, tol resolved;
    ``modulo`` checked first (one of MODULI); ``function`` names the caller in errors.

    ``levels``: keep ``options.rtol`` (a caller that resolves its working grid by levels,
    :func:`elastic_jax.karcher_mean`); otherwise rtol is dropped: the collection is
    solved on its own grid.
    """
    check_choice("modulo", modulo, MODULI)
    shapes = as_surface(shapes, name)
    if shapes.ndim != 4 or shapes.shape[0] < 2:
        raise InputError(f"{name} must have shape (K, 3, m, n) with K >= 2; got {shapes.shape}")
    options = options_with(function, options, {})
    check_grid_options(options, *shapes.shape[-2:])
    grid = tuple(shapes.shape[-2:])
    if options.grid not in (None, grid):
        # A collection's results (paths, velocities at the mean, registrations) live on
        # its grid: a working grid of another size has no place to put them.
        raise InputError(
            f"options.grid={options.grid} differs from the collection's grid {grid}: resample "
            "the shapes to the working grid (elastic_jax.resample), or leave grid=None"
        )
    if not levels:
        # Solved on the collection's own grid (its members' results live there), not
        # by levels.
        options = options.replace(rtol=None)
    if options.tol is None:
        # Resolved here, as the solves would: one static key for every call, and a
        # fingerprint that names the tolerance used.
        options = options.replace(tol=default_tol(shapes.dtype))
    return shapes, options


def job_settings(metric: SplitMetric, modulo: str, options: ShapeOptions, **more) -> dict:
    return {
        "metric": [float(x) for x in jax.tree_util.tree_leaves(metric)],
        "modulo": modulo,
        "options": options.as_dict(),
        **more,
    }
