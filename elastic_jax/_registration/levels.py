"""Resolved distances: levels of working grids, coarse to fine, each continuing the one
below, until two successive distances agree within rtol (math §10).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import DTypeLike
from jaxtyping import Array, ArrayLike

from .._checks import is_concrete
from .._errors import InputError
from .._geometry.metric import SplitMetric
from .._geometry.smoothing import smooth_surface
from .._geometry.units import in_units
from .._geometry.validation import check_levels
from .._options import ShapeOptions
from .._results import RESULTS
from .._runtime.cache import phase_chain
from .one_grid import grid_setup, one_grid_solve
from .phases import PHASE_JITS, PHASES, Reporter
from .records import Levels, ShapeGeodesicResult
from .starts import given_start, usable_inverse


class LevelStart(NamedTuple):
    """How one candidate's solve on a level begins (:func:`level_start`): ``kind``
    "search" (a start search of its own; ``given`` None), "start" (the rounds from
    ``given`` = (gamma ``(3, m, n)``, R ``(3, 3)``)), "carry" (a continuation of
    ``given`` = (gamma, R, the path's coefficients ``(N - 2, L)``, the parametrized
    path's)) or "none" (solved again from a finer level whose registration folds on
    this grid: no solve, since a search would find another minimum)."""

    kind: str
    given: tuple | None = None


def level_start(
    f1: ArrayLike,
    f2: ArrayLike,
    metric: SplitMetric,
    modulo: str,
    options: ShapeOptions,
    grid: tuple[int, int],
    below: object,
    start: object = None,
    again: bool = False,
    reporter: Reporter | None = None,
) -> LevelStart:
    """How a candidate's solve on ``grid`` begins, given the solution ``below`` it
    continues (a result, or any record with ``gamma``, ``rotation``, ``coefficients``
    and ``parametrized_coefficients``; None on the first level) and the candidate's
    first-level ``start`` (:func:`candidate_starts`). The one decision a resolved
    shape_geodesic (:func:`level_solve`) and a collection's levels make per candidate.

    A level continues the solution below where its registration reads at this grid's
    points without folding (the coarser gamma's interpolant can fold between its points:
    the cats at 13 x 25 read at 25 x 49, chain rule). The first level starts from a
    (gamma, R) start where it reads, else searches. Where a graduated candidate would
    search (its first level, or a carry that folds), it continues instead the solves of
    the inputs low-passed (:data:`GRADUATED`: :func:`graduated_search` with ``options``'
    widths), or the other order's graduated solve, inverted (:class:`OtherGraduated`:
    its own carry on the first level, :func:`other_order_graduated` above it), and
    searches only where that carry is not usable."""
    dtype = jnp.asarray(f1).dtype
    if below is None and not graduates(start):
        read = registration_at(start, grid, dtype, modulo)
        return LevelStart("search") if read is None else LevelStart("start", read)
    carry = None if below is None else carried(below, grid, dtype, modulo)
    if below is None and isinstance(start, OtherGraduated):
        carry = start.carry
    elif carry is None and not again and start is GRADUATED:
        searched = graduated_search(f1, f2, metric, modulo, options, grid, reporter)
        carry = carried(searched, grid, dtype, modulo)
    elif carry is None and not again and isinstance(start, OtherGraduated):
        carry = other_order_graduated(f1, f2, metric, modulo, options, grid, reporter)
    if carry is not None:
        return LevelStart("carry", carry)
    return LevelStart("none" if again else "search")


def carried(solution: object, grid: tuple[int, int], dtype: DTypeLike, modulo: str) -> tuple | None:
    """A level's solution as the carry of a solve on ``grid``: its registration read at
    the grid's points (:func:`registration_at`), its path's and its parametrized path's
    coefficients; None where the registration folds there."""
    read = registration_at((solution.gamma, solution.rotation), grid, dtype, modulo)
    if read is None:
        return None
    return (*read, solution.coefficients, solution.parametrized_coefficients)


def level_solve(
    f1: ArrayLike,
    f2: ArrayLike,
    metric: SplitMetric,
    modulo: str,
    options: ShapeOptions,
    grid: tuple[int, int],
    below: ShapeGeodesicResult | None,
    start: object = None,
    reporter: Reporter | None = None,
    again: bool = False,
) -> ShapeGeodesicResult | None:
    """One level of a resolved distance: the solve on ``grid`` continuing the level
    ``below`` (its registration, path and parametrized path, without a new start search
    or coarse rounds: continuation_phase), or, for the first level, from the
    candidate's ``start`` (:func:`candidate_starts`) or a search of its own, as
    :func:`level_start` decides. None when solved ``again`` from a finer level whose
    registration folds on this grid."""
    plan = level_start(f1, f2, metric, modulo, options, grid, below, start, again, reporter)
    if plan.kind == "none":
        return None
    start, carry = (None, plan.given) if plan.kind == "carry" else (plan.given, None)
    level = options.on_level(grid)
    result = one_grid_solve(f1, f2, metric, modulo, level, start, carry=carry, reporter=reporter)
    return alternated(f1, f2, metric, modulo, options, grid, result, reporter)


def alternated(
    f1: ArrayLike,
    f2: ArrayLike,
    metric: SplitMetric,
    modulo: str,
    options: ShapeOptions,
    grid: tuple[int, int],
    result: object,
    reporter: Reporter | None = None,
) -> object:
    """``result`` (a level's solve on ``grid``, f1 -> f2: a result or any record with
    ``distance``, ``converged``, ``gamma`` and ``rotation``) after at most
    ``options.alternations`` round trips between the orders: its registration inverted
    (gamma^-1 by Newton's method on gamma's interpolant, R^T) continued in the order
    f2 -> f1 from the straight line, and that one's inverted continued in this order
    likewise. A round trip is kept where it ends lower (and converged, where the result
    did); they stop at one that is not kept, at an inverse that folds or misses
    rounding's tolerance, or once one lowered the distance by less than
    ``options.level_rounds_tol`` (relative). ``result`` itself without alternations.

    gamma o phi (this order's steps) and phi o gamma (the other order's, seen from this
    one) are different families of moves of the degree-``vf_degree`` basis, and each
    order's rounds end where their own family no longer lowers the energy."""
    if not options.alternations:
        return result
    level = options.on_level(grid)
    saved = None if reporter is None else reporter.level
    best = result
    for trip in range(1, options.alternations + 1):
        if reporter is not None:
            reporter.level = {**saved, "alternation": trip, "order": "f2 -> f1"}
        other = turned(f2, f1, metric, modulo, level, best, reporter)
        if other is None:
            break
        if reporter is not None:
            reporter.level = {**saved, "alternation": trip, "order": "f1 -> f2"}
        trial = turned(f1, f2, metric, modulo, level, other, reporter)
        if trial is None:
            break
        d, lower = float(trial.distance), float(best.distance)
        if not d < lower or (bool(best.converged) and not bool(trial.converged)):
            break
        best = trial
        if (lower - d) / max(lower, np.finfo(np.float64).tiny) < options.level_rounds_tol:
            break
    if reporter is not None:
        reporter.level = saved
    return best


def inverted(gamma: ArrayLike, rotation: ArrayLike) -> tuple | None:
    """A registration of the other order, (gamma, R) with f2 o gamma ~ R f1, as one of
    this order: (gamma^-1, R^T), since then f1 o gamma^-1 ~ R^T f2 (modulo "diff" R is
    the identity). gamma^-1 is solved on gamma's interpolant (:func:`usable_inverse`);
    None where it misses rounding's tolerance or folds on the grid."""
    inverse = usable_inverse(jnp.asarray(gamma))
    return None if inverse is None else (inverse, jnp.asarray(rotation).T)


def turned(
    f1: ArrayLike,
    f2: ArrayLike,
    metric: SplitMetric,
    modulo: str,
    level: ShapeOptions,
    other: object,
    reporter: Reporter | None = None,
) -> ShapeGeodesicResult | None:
    """The solve f1 -> f2 on ``level``'s one grid continuing ``other``, a solve of f2 ->
    f1 (any record with ``gamma`` and ``rotation``), with its registration inverted
    (:func:`inverted`) and the straight line as the path: a continuation, since coarse
    rounds would re-register on the L2 mismatch and leave the inverted registration's
    basin. None where the inverse is not usable."""
    registration = inverted(other.gamma, other.rotation)
    if registration is None:
        return None
    carry = (*registration, None)
    return one_grid_solve(f1, f2, metric, modulo, level, None, carry=carry, reporter=reporter)


# The start of the candidate whose levels graduate their own start searches.
GRADUATED = object()


class OtherGraduated(NamedTuple):
    """The start of the candidate whose levels continue the other order's graduated
    solve, inverted: its first level's carry (:func:`other_order_graduated`), where it
    was usable."""

    carry: tuple


def graduates(start: object) -> bool:
    """Whether a candidate's start is a graduated one (GRADUATED or OtherGraduated)."""
    return start is GRADUATED or isinstance(start, OtherGraduated)


def one_candidate(options: ShapeOptions) -> ShapeOptions:
    """``options`` for one candidate's own solves: no more candidates of its own (one
    start search's, no graduated one) and no round trips between the orders."""
    return options.replace(search_smoothing=(), alternations=0, level_candidates=1)


def graduated_search(
    f1: ArrayLike,
    f2: ArrayLike,
    metric: SplitMetric,
    modulo: str,
    options: ShapeOptions,
    grid: tuple[int, int],
    reporter: Reporter | None = None,
) -> ShapeGeodesicResult:
    """A level's own start search, graduated: for each width c of
    ``options.search_smoothing`` (wide to narrow), f1 and f2 averaged by
    :func:`smooth_surface` with the kernel width c pi / (m - 1) on the m x n level and
    solved there, each solve continuing the one before (the widest searches its start).
    The level then continues the last (:func:`level_solve`), on the data.

    A blurred pair has fewer local minima, and one that moves continuously with the
    data is followed as the blur narrows, where a start search on the data lands in
    whichever basin rounding picks (:doc:`/guides/registration_notes`, "Graduated
    start searches")."""
    plain = one_candidate(options)
    spacing = np.pi / (grid[0] - 1)
    saved = None if reporter is None else reporter.level
    below = None
    for width in options.search_smoothing:
        if reporter is not None:
            reporter.level = {**saved, "smoothing": width}
        g1, g2 = (smooth_surface(f, width * spacing, options.smoothing_kernel) for f in (f1, f2))
        # level_solve's own continuation: the widest (below None) searches its start.
        below = level_solve(g1, g2, metric, modulo, plain, grid, below, reporter=reporter)
    if reporter is not None:
        reporter.level = saved
    return below


def other_order_graduated(
    f1: ArrayLike,
    f2: ArrayLike,
    metric: SplitMetric,
    modulo: str,
    options: ShapeOptions,
    grid: tuple[int, int],
    reporter: Reporter | None = None,
) -> tuple | None:
    """The other order's graduated level as a carry of this order: f2 -> f1 solved on
    ``grid`` through the low-passed inputs (:func:`graduated_search`) and then on the
    data; its registration (gamma, R), f2 o gamma ~ R f1, inverted into (gamma^-1, R^T),
    since then f1 o gamma^-1 ~ R^T f2, with the straight line as the path (zero
    coefficients ``(N - 2, L)``, as ``shape_geodesic(symmetric=True)`` continues an
    inverted registration). None where gamma^-1 misses rounding's tolerance or folds on
    the grid.

    The sphere kernel blurs the parametrization, so the two orders blur different pairs
    of functions and their graduated searches follow different minima; carrying both
    makes the answer the lower of the two in either order."""
    plain = one_candidate(options)
    saved = None if reporter is None else reporter.level
    if reporter is not None:
        reporter.level = {**saved, "order": "f2 -> f1"}
    blurred = graduated_search(f2, f1, metric, modulo, options, grid, reporter)
    data = level_solve(f2, f1, metric, modulo, plain, grid, blurred, reporter=reporter)
    if reporter is not None:
        reporter.level = saved
    registration = inverted(data.gamma, data.rotation)
    if registration is None:
        return None
    # Zeros, not None, for the straight line: a collection stacks its candidates' carries.
    zero = jnp.zeros_like
    return *registration, zero(data.coefficients), zero(data.parametrized_coefficients)


class LevelOutcome(NamedTuple):
    """One pair's solve on one level, as :func:`run_levels` needs it: its distance,
    whether that solve converged, its parametrized distance (the near-equal scale of
    :func:`level_change`) and the solution the next level continues (opaque here)."""

    distance: float
    converged: bool
    parametrized: ArrayLike
    solution: object
    refined: float = np.nan  # the solve read on the grid twice finer than its rule
    refined_gap: float = np.nan  # how far its refinement moves the distance (absolute)


@dataclasses.dataclass
class LevelTrack:
    """One pair's levels so far: the grids solved, the distances of the last level's
    minimum on each (``distances``: the levels below solved again from it where
    :func:`run_levels` did so, else as first solved), the distances as first solved
    going up (``ascent``), each level's seconds, the last level's solution, and the
    levels estimate (:func:`level_change` of ``distances``)."""

    grids: list = dataclasses.field(default_factory=list)
    distances: list = dataclasses.field(default_factory=list)
    ascent: list = dataclasses.field(default_factory=list)
    refined: list = dataclasses.field(default_factory=list)
    seconds: list = dataclasses.field(default_factory=list)
    solution: object = None
    estimate: float = np.nan
    refined_gap: float = np.nan


def turns(distances: Sequence[float]) -> bool:
    """Whether the last levels' distances may not be one minimum refined: two levels
    cannot tell (their change is a grid's error or two minima's), and of three, the
    last change reverses the one before or is more than half its size (an observed
    order below 1). Levels that continue one another can still end in different minima
    (the fsaverage5 pial pair: 3.746, 3.832, 3.628 on 13 x 25, 25 x 49, 49 x 97, the
    finest level's minimum 3.223, 3.568, 3.628 on the same grids), and then their change
    is the minima's difference, not the discretization's."""
    if len(distances) < 3:
        return len(distances) == 2
    before, last = distances[-2] - distances[-3], distances[-1] - distances[-2]
    return bool(before * last < 0 or abs(last) > 0.5 * abs(before))


def run_levels(
    count: int,
    levels: Sequence[tuple[int, int]],
    rtol: float,
    noise: Sequence[float],
    solve: Callable[..., list],
) -> list[LevelTrack]:
    """The levels of working grids for ``count`` pairs at once (math §10): the one loop
    every resolved solve runs, a single pair as a batch of one (:func:`levels_solve`)
    and a collection's pairs (``levelled_chunk`` of distance_matrix, fit_metric, log and
    karcher_mean).

    ``solve(index, grid, going, below, again=False)`` solves the pairs ``going``
    (indices) on ``levels[index]``, each continuing its solution ``below`` from the
    level before (None on the first level), and returns one :class:`LevelOutcome` per
    pair. A pair leaves once two successive levels agree within ``rtol`` at a converged
    solve, or when its distance is not finite (RESULTS.nonfinite ends its levels too);
    the others go on to the next grid. ``noise[i]``: pair i's :func:`noise_distance`.

    Where the levels' distances :func:`turns` (two levels, or three whose changes do not
    halve) and the last change misses rtol at a converged solve, the change may be two
    minima's: every level below is solved again from the last level's solution
    (``again=True``: ``below`` holds that finer solution; an outcome of None where it
    cannot be continued on that grid, whose distance is then NaN), those distances
    replace the track's first ones, and the estimate is the change between the last two
    of the last level's own minimum. The next level continues the last level's solution
    either way. Each pair's seconds are its level's wall time (the whole group's, when
    several share it), the levels solved again included.
    """
    tracks = [LevelTrack() for _ in range(count)]
    going = list(range(count))
    for index, grid in enumerate(levels):
        if not going:
            break
        begin = time.perf_counter()
        outcomes = solve(index, tuple(grid), going, [tracks[i].solution for i in going])
        seconds = time.perf_counter() - begin
        still, turned, parametrized = [], [], {}
        for i, outcome in zip(going, outcomes, strict=True):
            track = tracks[i]
            track.grids.append(tuple(grid))
            track.distances.append(float(outcome.distance))
            track.ascent.append(float(outcome.distance))
            track.refined.append(float(outcome.refined))
            track.seconds.append(seconds)
            track.solution = outcome.solution
            track.refined_gap = float(outcome.refined_gap)
            track.estimate = level_change(
                track.distances, outcome.parametrized, noise[i], track.refined_gap
            )
            parametrized[i] = outcome.parametrized
            resolved = track.estimate <= rtol and bool(outcome.converged)
            if np.isfinite(track.distances[-1]) and not resolved:
                still.append(i)
                if bool(outcome.converged) and turns(track.distances):
                    turned.append(i)
        if turned:
            begin = time.perf_counter()
            again = {i: [] for i in turned}
            finer = [tracks[i].solution for i in turned]
            for lower in range(index - 1, -1, -1):
                outs = solve(lower, tuple(levels[lower]), turned, finer, again=True)
                for i, out in zip(turned, outs, strict=True):
                    again[i].insert(0, out)
            seconds = time.perf_counter() - begin
            for i in turned:
                track, below = tracks[i], again[i][-1]
                track.seconds[-1] += seconds
                if below is None or not bool(below.converged):
                    continue  # no minimum of its own one level down: the change stands
                track.distances[:-1] = [
                    np.nan if out is None else float(out.distance) for out in again[i]
                ]
                track.estimate = level_change(
                    track.distances, parametrized[i], noise[i], track.refined_gap
                )
                if track.estimate <= rtol:
                    still.remove(i)
        going = still
    return tracks


def levels_solve(
    f1: ArrayLike,
    f2: ArrayLike,
    metric: SplitMetric,
    modulo: str,
    options: ShapeOptions,
    start: object,
    reporter: Reporter | None = None,
) -> ShapeGeodesicResult:
    """shape_geodesic with ``options.rtol``: the working grids of ``options.levels`` coarse to
    fine, each level continuing the one below (its registration and path: no new start
    search, no coarse rounds; continuation_phase), until two successive distances agree
    within rtol (math §10). The first level starts from ``start`` or searches its own.

    With ``options.level_candidates`` K > 1 (and no ``start``), the first level's start
    search gives up to K starts (:func:`first_level_starts`) and each is a pair of
    run_levels' batch: its own coarse rounds, rounds and levels. With
    ``options.both_orders`` the other order's K best-ranked starts, inverted, follow them
    (:func:`other_order_starts`). With ``options.search_smoothing`` (and no ``start``)
    one more candidate follows, whose levels graduate their own start searches
    (:func:`graduated_search`), and with both_orders one whose levels continue the
    other order's graduated solve, inverted (:func:`other_order_graduated`); the others
    search as without it. The candidate with the
    lowest final distance is the result; ``levels.candidates`` holds every candidate's
    final distance and ``levels.spread`` their range (:func:`candidate_spread`).

    The finest level's result, with ``levels`` recording every level; converged when
    that level converged and the tolerance was met (the levels' change and the
    candidates' spread), else ``RESULTS.not_resolved`` when only a tolerance was missed.
    """
    if not is_concrete(f1, f2, metric):
        raise InputError(
            "rtol (the default) refines the working grid until two levels agree: it needs "
            "concrete inputs, not tracers; under jax.jit or jax.vmap give one working grid "
            "(options grid=(m, n), or rtol=None for the inputs' grid)"
        )
    if start is not None:  # a start must be a registration on its own grid
        try:
            gamma = start.gamma if isinstance(start, ShapeGeodesicResult) else start[0]
            own = tuple(np.shape(gamma)[-2:])
        except (TypeError, IndexError, KeyError):
            own = ()
        if len(own) != 2:
            own = options.levels[0]  # malformed: given_start names the problem
        given_start(start, *own, f1.dtype, modulo == "rigid")
    check_levels(options)
    noise = noise_distance(f1, f2)
    # Only the graduated candidates' levels graduate their own start searches
    # (level_start): the others search as the default does, so the lowest final is
    # never above its.
    starts = candidate_starts(f1, f2, metric, modulo, options, start, reporter)
    many = len(starts) > 1

    def solve(
        index: int, grid: tuple[int, int], going: list, below: list, again: bool = False
    ) -> list:
        outcomes = []
        for i, lower in zip(going, below, strict=True):
            if reporter is not None:
                reporter.level = {"level": index + 1, "levels": len(options.levels)}
                if many:
                    reporter.level["candidate"] = i + 1
                if again:
                    reporter.level["again"] = True
            result = level_solve(
                f1, f2, metric, modulo, options, grid, lower, starts[i], reporter, again
            )
            if result is None:
                outcomes.append(None)  # the finer gamma folds between this grid's points
                continue
            distance = float(jax.block_until_ready(result.distance))
            converged = bool(result.converged)
            if reporter is not None:
                reporter.send(
                    stage="level",
                    grid=tuple(grid),
                    energy=float(result.energy),
                    distance=distance,
                    converged=converged,
                )
            outcomes.append(
                LevelOutcome(
                    distance,
                    converged,
                    result.parametrized_distance,
                    result,
                    float(result.refinement.distance_grid),
                    refinement_gap(result),
                )
            )
        return outcomes

    tracks = run_levels(len(starts), options.levels, options.rtol, [noise] * len(starts), solve)
    if reporter is not None:
        reporter.level = {}
    finals = [float(track.solution.distance) for track in tracks]
    track = tracks[lowest(finals)]
    return with_levels(
        track.solution,
        track.grids,
        track.distances,
        track.seconds,
        options.rtol,
        noise,
        ascent=track.ascent,
        refined=track.refined,
        refined_gap=track.refined_gap,
        candidates=finals,
    )


def candidate_starts(
    f1: ArrayLike,
    f2: ArrayLike,
    metric: SplitMetric,
    modulo: str,
    options: ShapeOptions,
    start: object = None,
    reporter: Reporter | None = None,
) -> list:
    """The first-level starts of a resolved solve's candidates, one per candidate: None
    (a start search of its own), a (gamma ``(3, m, n)``, R ``(3, 3)``) pair,
    :data:`GRADUATED` or an :class:`OtherGraduated`. A given ``start``: that one alone.
    Else ``[None]`` by default (``[]`` with ``options.level_candidates`` 0);
    ``level_candidates`` K > 1: the first level's K best-ranked starts
    (:func:`first_level_starts`); ``options.both_orders``: then the
    other order's, inverted (:func:`other_order_starts`); ``options.search_smoothing``:
    then GRADUATED, and with ``both_orders`` an OtherGraduated where the other order's
    graduated first level inverts (:func:`other_order_graduated`, whose solves
    ``reporter`` hears, marked ``order``). The one list a resolved shape_geodesic and a
    collection's pairs carry."""
    if start is not None:
        return [start]
    starts = [None] if options.level_candidates else []
    if options.level_candidates > 1:
        starts = first_level_starts(f1, f2, metric, modulo, options)
    if options.both_orders and options.level_candidates:
        starts = starts + other_order_starts(f1, f2, metric, modulo, options)
    if options.search_smoothing:
        starts = starts + [GRADUATED]
        if options.both_orders:
            first = tuple(options.levels[0])
            carry = other_order_graduated(f1, f2, metric, modulo, options, first, reporter)
            starts = starts + ([] if carry is None else [OtherGraduated(carry)])
    return starts


def lowest(finals: Sequence[float]) -> int:
    """The index of the candidate that wins: the lowest final distance (NaN never does;
    all NaN: the first)."""
    ranked = np.where(np.isfinite(finals), np.asarray(finals, np.float64), np.inf)
    return int(np.argmin(ranked))


def first_level_starts(
    f1: ArrayLike, f2: ArrayLike, metric: SplitMetric, modulo: str, options: ShapeOptions
) -> list[tuple]:
    """The first level's start search (phase 1 on ``options.levels[0]``): its first
    ``options.level_candidates`` starts (at most as many as it gives) as (gamma
    ``(3, m, n)``, R ``(3, 3)``) pairs, in its ranking's order."""
    grid = tuple(options.levels[0])
    level, _, _, _, args = grid_setup(f1, f2, metric, options.on_level(grid))
    name, function, skeleton = PHASES[0]
    static = {"options": level, "rigid": modulo == "rigid"}
    gammas, rotations, _ = phase_chain(
        [(name, function, PHASE_JITS[name], skeleton)], args, (), static
    )
    count = min(options.level_candidates, int(gammas.shape[0]))
    return [(gammas[i], rotations[i]) for i in range(count)]


def other_order_starts(
    f1: ArrayLike, f2: ArrayLike, metric: SplitMetric, modulo: str, options: ShapeOptions
) -> list[tuple]:
    """The other order's first-level starts as starts of this order: the start search
    of f2 to f1 on ``options.levels[0]`` (:func:`first_level_starts`, its first
    ``level_candidates``), each (gamma, R) with f2 o gamma ~ R f1 turned into
    (gamma^-1, R^T), since then f1 o gamma^-1 ~ R^T f2 (modulo "diff" R is the identity).
    gamma^-1 is solved on gamma's interpolant (:func:`inverse_gamma`); a start whose
    inverse misses rounding's tolerance or folds on the grid is left out."""
    starts = (inverted(*start) for start in first_level_starts(f2, f1, metric, modulo, options))
    return [start for start in starts if start is not None]


# A pair of near-equal shapes (a distance below this fraction of the pair's parametrized
# distance) is resolved to that absolute size, not relative to its own distance: d(f, R f)
# is zero in the continuum, and levels of a small number differ by more than 3 % of it
# however well each is solved: such a pair is resolved to 0.05 d, absolute.
_NEAR_EQUAL = 0.05


def noise_distance(f1: ArrayLike, f2: ArrayLike) -> float:
    """The distance whose energy is the rounding level at which the final phase compares
    the registered and the given pair (sqrt(eps) in the solve's unit-size units): two
    levels' distances that differ by less are the same minimum. Identical inputs end at
    0 on one level and at up to this on the next, from the carried identity's
    interpolation (a sphere of radius 2 at 13 x 25: 1e-14, 8e-15, 3.4e-5, 3.1e-4 up to
    97 x 193, all within 4.9e-4)."""
    units, _ = in_units(f1, f2)
    eps = float(np.finfo(np.dtype(f1.dtype)).eps)
    return eps**0.25 * float(units.scale)


def level_change(
    distances: Sequence[float],
    parametrized: ArrayLike = 0.0,
    noise: float = 0.0,
    refined_gap: float = np.nan,
) -> float:
    """The change of the last two levels' distances, less ``noise`` (noise_distance),
    relative to the last, or to _NEAR_EQUAL times the parametrized distance when that is
    larger (NaN for one level); at least the last level's ``refined_gap`` (how far its
    refinement moves its distance, :func:`refinement_gap`, where finite), less noise,
    in the same scale.

    A level agreeing with the one below does not show that either resolved the data:
    two levels can agree in a minimum whose registration hides content between both
    grids' points, and the next grid leaves it (the fsaverage5 pial pair: 3.799 and
    3.731 at 13 x 25 and 25 x 49, then 3.619 at 49 x 97). The refinement reads the last
    level's own registration and path on the grid twice finer than its rule, so a level
    is resolved only where that read moves it by at most rtol too."""
    if len(distances) < 2:
        return np.nan
    d, before = float(distances[-1]), float(distances[-2])
    scale = max(d, _NEAR_EQUAL * float(parametrized), np.finfo(np.float64).tiny)
    change = max(abs(d - before) - noise, 0.0) / scale
    if np.isfinite(refined_gap):
        change = max(change, max(float(refined_gap) - noise, 0.0) / scale)
    return change


def refinement_gap(result: ShapeGeodesicResult) -> float:
    """How far a result's refinement moves its distance: max(abs(distance_time - d),
    abs(distance_grid - d)) (NaN without the refinement check)."""
    ref, d = result.refinement, float(result.distance)
    return max(abs(float(ref.distance_time) - d), abs(float(ref.distance_grid) - d))


def with_levels(
    result: ShapeGeodesicResult,
    grids: list | Array,
    distances: Sequence[float],
    seconds: Sequence[float],
    rtol: float,
    noise: float = 0.0,
    ascent: Sequence[float] | None = None,
    refined: Sequence[float] | None = None,
    refined_gap: float = np.nan,
    candidates: Sequence[float] | None = None,
) -> ShapeGeodesicResult:
    """``result`` (the finest level's) with its :class:`Levels` record; converged when it
    converged, the last change met rtol and the candidates' spread is within rtol,
    ``RESULTS.not_resolved`` when only a tolerance was missed. ``ascent``: the
    distances as first solved (``distances`` when None); ``refined``: each of those
    read on the grid twice finer than its rule (NaN when None); ``refined_gap``: the
    last level's refinement gap (level_change); ``candidates``: every candidate's final
    distance (None: this result's alone)."""
    dtype = result.distance.dtype
    estimate = level_change(distances, result.parametrized_distance, noise, refined_gap)
    if candidates is None:
        candidates = [float(result.distance)]
    spread = spread_of(candidates, result.parametrized_distance)
    met = bool(estimate <= rtol) and bool(spread <= rtol)
    levels = Levels(
        grids=jnp.asarray(grids, jnp.int32),
        distances=jnp.asarray(distances, dtype),
        ascent=jnp.asarray(distances if ascent is None else ascent, dtype),
        refined=jnp.asarray(np.full(len(distances), np.nan) if refined is None else refined, dtype),
        seconds=jnp.asarray(seconds, dtype),
        estimate=jnp.asarray(estimate, dtype),
        rtol=jnp.asarray(rtol, dtype),
        candidates=jnp.asarray(candidates, dtype),
        spread=jnp.asarray(spread, dtype),
    )
    code = result.result
    if not met and bool(result.converged):
        code = RESULTS.not_resolved
    return result._replace(
        converged=jnp.asarray(bool(result.converged) and met), result=code, levels=levels
    )


def candidate_spread(distances: Sequence[float], floor: float = 0.0) -> float:
    """(max - min) / max(min, floor) of the finite ``distances`` (0 for fewer than two;
    NaN when none is finite): how far apart the candidates' minima are, relative to the
    lowest, or to ``floor`` where that is larger (level_change's scale for near-equal
    shapes, whose distance is near zero)."""
    finite = np.asarray(distances, np.float64)
    finite = finite[np.isfinite(finite)]
    if finite.size == 0:
        return np.nan
    if finite.size == 1:
        return 0.0
    low = max(float(finite.min()), float(floor), np.finfo(np.float64).tiny)
    return float(finite.max() - finite.min()) / low


def spread_of(finals: Sequence[float], parametrized: ArrayLike) -> float:
    """The candidates' spread as a resolved result records it (:class:`Levels`
    ``spread``): :func:`candidate_spread` of their ``finals``, with the near-equal floor
    of the winner's ``parametrized`` distance."""
    return candidate_spread(finals, _NEAR_EQUAL * float(parametrized))


def registration_at(start: object, grid: tuple[int, int], dtype: DTypeLike, modulo: str):
    """A registration (a result, or gamma and R; or None) read at ``grid``'s points as
    (gamma, R), or None where it is not a diffeomorphism there (given_start's checks)."""
    if start is None:
        return None
    try:
        gammas, rotations, _ = given_start(start, *grid, dtype, modulo == "rigid")
    except InputError:
        return None
    return gammas[0], rotations[0]
