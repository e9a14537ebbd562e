"""Geodesics between shapes: registration modulo reparametrization and rigid motion.

Paper sections 4.2-4.3 (Algorithms 2 and 3, Remark 4), math §6, 7 and 9. f1 is
reparametrized by gamma (f1 o gamma), f2 is rotated in R^3 by R for modulo="rigid";
translations cost nothing (the metric sees only df), so both surfaces are centered for
modulo="rigid". The public driver: one working grid (one_grid.py), levels of grids
(levels.py), or both orders (symmetric); each solve runs in phases (phases.py).
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable

import numpy as np
from jaxtyping import ArrayLike, Float

from .._checks import check_progress, is_concrete
from .._errors import InputError
from .._geometry.metric import SplitMetric
from .._geometry.validation import check_pair
from .._options import ShapeOptions, check_choice, options_with
from .levels import levels_solve, noise_distance, refinement_gap, turned, with_levels
from .one_grid import one_grid_solve
from .phases import Reporter
from .records import MODULI, ShapeGeodesicResult, warn_unless_converged


def shape_geodesic(
    f1: Float[ArrayLike, "3 m n"],
    f2: Float[ArrayLike, "3 m n"],
    metric: SplitMetric,
    *,
    modulo: str = "diff",
    options: ShapeOptions | None = None,
    start: ShapeGeodesicResult | tuple[ArrayLike, ArrayLike] | None = None,
    symmetric: bool = False,
    progress: Callable[[dict], None] | None = None,
    **changes,
) -> ShapeGeodesicResult:
    """Geodesic between the shapes of f1 and f2, modulo reparametrization (and rigid motion).

    Minimizes the path energy (:ref:`math §4 <math-4>`; the options' scheme, midpoint by
    default) over paths from f1 o gamma to R f2 and over gamma in Diff+(S^2) (and R in SO(3) for
    modulo="rigid"); paper sections 4.2-4.3.

    1. The parametrized geodesic f1 -> f2 (``parametrized_distance``).
    2. Starts (``init="moebius"``): each of the 60 icosahedral rotations, as a
       reparametrization, starts a short search over the Moebius group of S^2 (rotations
       and conformal boosts; modulo "rigid" with R's Procrustes optimum for each) on the
       L2 mismatch int ‖f1 o gamma - R f2‖^2; the 60 are ranked by that mismatch, and the
       best ``init_candidates`` that lie apart are refined to the tolerance (other
       ``init`` values: :class:`ShapeOptions`). Every start gets registration rounds on
       the L2 mismatch; the one whose straight line then has the lowest energy gets
       rounds on that energy (coarse to fine in the criterion and in time).
    3. Registration rounds with the whole path (``method="joint"``: path and Diff step
       together, Algorithm 2; ``"coordinate"``: alternately). Each Diff step
       Proj(Id + sum x_k v_k) of degree vf_degree is composed onto gamma and shrunk (by
       halves, down to no step) until the composed gamma has a positive Jacobian at every
       grid point and keeps the area the grid can resolve (:ref:`math §9 <math-9>`); rounds
       never raise the energy and stop when one changes it by at most rounds_tol
       (outer_tol on one working grid, ``max(outer_tol, rtol / 5)`` on the levels), or
       when the last two rounds' changes, continued geometrically, leave at most that,
       or after outer_steps.
       Rounds whose last step had to shrink stopped at that edge, not at a minimum:
       ``RESULTS.resolution_limited``, not converged.
    4. The final geodesic, its status, and the refinement check (:class:`Refinement`).
       The pair as given is always a candidate (:ref:`math §10 <math-10>`): a registered
       geodesic that ends above the parametrized one by more than outer_tol is replaced
       by it, with ``RESULTS.not_registered``; on concrete inputs the pair as given (the
       identity gamma, and modulo "rigid" also its Procrustes-best rotation) then gets
       steps 3-4 of its own, and the lower of the two solves is the result.
       The result is never above the parametrized geodesic: when the registered
       geodesic ends above the pair as given, the result is the parametrized geodesic
       (identity gamma and rotation), with ``RESULTS.not_registered`` when the gap
       exceeds outer_tol.

    5. Levels (the default, ``options.rtol`` 0.03 with ``grid=None``): steps 2-4 on the
       coarsest grid of ``options.levels``, then on each finer grid steps 3-4 continuing
       the level below, until two successive distances agree within rtol (math §10);
       ``res.levels`` records them. ``grid=(m, n)`` (or ``rtol=None``, the inputs'
       grid) solves on one working grid instead.

    Each phase is one compiled program (five in all, see solve_in_phases); under
    ``jax.vmap`` or a caller's ``jax.jit`` the whole solve is one program, vmappable
    over f2, on one working grid (give ``grid`` or ``rtol=None``: levels compare
    concrete distances).

    Args:
        f1, f2: ``(3, m1, n1)`` and ``(3, m2, n2)`` immersions, each on a grid of its
            own: each stands for its interpolant (:ref:`math §10 <math-10>`), read at the
            working grid's points (each level's; ``options.grid``; with ``rtol=None`` the
            inputs' grid, or the finer of two).
            The result's path, gamma and f1_registered are on the working grid.
        metric: split metric coefficients.
        modulo: ``"diff"`` (reparametrizations) or ``"rigid"`` (also rotations; centers both).
        options: a :class:`ShapeOptions` (its defaults when None).
        start: a registration to start the rounds from instead of the start search (step
            2; ``init`` is then not used): a :class:`ShapeGeodesicResult`, e.g. of the same
            pair on a coarser grid (multiresolution in grid, the paper's section 5), or
            a pair (gamma ``(3, p, q)``, rotation ``(3, 3)``). gamma on another grid is
            read at this grid's points (bicubic); the rotation is ignored modulo "diff".
        symmetric: also solve the other order, f2 to f1; when it ends lower, solve this
            order again from its registration inverted (gamma^-1 by Newton's method on
            gamma's interpolant, R^T), and return the lower of this order's results. The
            two orders' rounds end in different local minima (the cats at 25 x 49: 0.751
            one way, 0.722 the other, and 0.7225 this way from the other's registration),
            so this finds the lower basin from either side. The third solve continues
            the inverted registration (its rounds with the whole path, no coarse rounds
            on the L2 mismatch, which leave that basin). With ``rtol`` both orders are
            solved by levels and the third solve continues on the finest level's grid;
            the result's ``levels`` are then those of the order that found its basin,
            the last distance its own. Two or three solves; concrete inputs only (not
            under jit or vmap).
        progress: called with a dict after each phase of a solve (``stage``: "start
            search", "coarse registration", "registration carried from the level below",
            "registration rounds", "geodesics", "checks"; ``grid``; ``energy``, the path
            energy the phase reached in the inputs' units, None after the start search)
            and after each level (``stage`` "level", ``level`` and ``levels`` counted
            from 1, ``distance``, ``converged``); every dict has ``seconds`` since the
            call began, and during levels ``level`` and ``levels`` (and ``candidate``,
            counted from 1, with ``ShapeOptions.level_candidates`` > 1,
            ``both_orders`` or ``search_smoothing``, and ``smoothing``, the kernel
            width, for the graduated candidate's solves of low-passed inputs); with
            ``symmetric``,
            ``order`` ("f1 -> f2", "f2 -> f1", "f1 -> f2 from f2 -> f1"). Concrete inputs
            only (no report inside a caller's trace). None (default): silent.
        **changes: fields of ShapeOptions as keywords, e.g. ``degree=5, n_times=9``:
            without ``options`` each sets that field of the default record; beside
            ``options`` each must equal the record's field (an equal one is accepted,
            another is an InputError: change the record with ``options.replace(...)``).

    Returns:
        :class:`ShapeGeodesicResult`. A result that did not converge also warns
        (:class:`ConvergenceWarning`); it never raises for that.

    Example:
        >>> import elastic_jax as ej
        >>> from elastic_jax import shapes
        >>> f1 = shapes.sample(shapes.bumpy, 13, 25)
        >>> f2 = shapes.sample(shapes.bumpy, 13, 25, rotation=shapes.random_rotation(1))
        >>> # One working grid (grid=): without it the default rtol solves levels of
        >>> # grids until two agree within 3 % (res.levels).
        >>> options = ej.ShapeOptions(degree=4, vf_degree=4, n_times=5, grid=(13, 25))
        >>> metric = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)
        >>> res = ej.shape_geodesic(f1, f2, metric, modulo="rigid", options=options)
        >>> bool(res.distance < 0.1 * res.parametrized_distance)
        True
    """
    resolved = options_with("shape_geodesic", options, changes)
    result = solve_shapes(f1, f2, metric, modulo, resolved, start, symmetric, progress)
    warn_unless_converged(result)
    return result


def solve_shapes(
    f1: ArrayLike,
    f2: ArrayLike,
    metric: SplitMetric,
    modulo: str,
    options: ShapeOptions,
    start: object = None,
    symmetric: bool = False,
    progress: Callable[[dict], None] | None = None,
) -> ShapeGeodesicResult:
    """:func:`shape_geodesic` at the record ``options``, without its ConvergenceWarning:
    the package's own callers (collections, logs, both orders, warmup) report each
    solve's status in their records instead. The same checks and the same result."""
    check_choice("modulo", modulo, MODULI)
    check_progress(progress)
    f1, f2 = check_pair(f1, f2, same_grid=False)
    if symmetric:
        return _symmetric_solve(f1, f2, metric, modulo, options, start, progress)
    reporter = None if progress is None else Reporter(progress)
    if options.resolves:
        return levels_solve(f1, f2, metric, modulo, options, start, reporter)
    return one_grid_solve(f1, f2, metric, modulo, options, start, reporter=reporter)


def _symmetric_solve(
    f1: ArrayLike,
    f2: ArrayLike,
    metric: SplitMetric,
    modulo: str,
    resolved: ShapeOptions,
    start: object,
    progress: Callable | None = None,
) -> ShapeGeodesicResult:
    """shape_geodesic(symmetric=True): the lower of this order's solve and its solve from
    the other order's registration inverted (when that one ends lower)."""
    if not is_concrete(f1, f2, metric):
        raise InputError(
            "symmetric=True compares whole solves: it needs concrete inputs, not tracers "
            "(call it outside jax.jit and jax.vmap)"
        )
    solve = functools.partial(solve_shapes, metric=metric, modulo=modulo, options=resolved)
    begin = time.perf_counter()

    def order(name: str):  # the order's reports, timed from this call's beginning
        if progress is None:
            return None
        return lambda r: progress({**r, "order": name, "seconds": time.perf_counter() - begin})

    best = solve(f1, f2, start=start, progress=order("f1 -> f2"))
    other = solve(f2, f1, progress=order("f2 -> f1"))
    if float(other.distance) < float(best.distance):
        grid = tuple(other.gamma.shape[-2:])
        begin = time.perf_counter()
        third = order("f1 -> f2 from f2 -> f1")
        reporter = None if third is None else Reporter(third)
        again = turned(f1, f2, metric, modulo, resolved.on_level(grid), other, reporter)
        if again is not None:
            if other.levels is not None:
                # The levels that found this basin (the other order's), the last
                # distance and time this solve's.
                levels = other.levels
                last = [float(again.distance)]
                distances = np.asarray(levels.distances).tolist()[:-1] + last
                ascent = np.asarray(levels.ascent).tolist()[:-1] + last
                refined = np.asarray(levels.refined).tolist()[:-1]
                refined += [float(again.refinement.distance_grid)]
                seconds = np.asarray(levels.seconds).tolist()
                seconds[-1] += time.perf_counter() - begin
                noise = noise_distance(f1, f2)
                again = with_levels(
                    again,
                    levels.grids,
                    distances,
                    seconds,
                    resolved.rtol,
                    noise,
                    ascent,
                    refined,
                    refinement_gap(again),
                )
            if float(again.distance) < float(best.distance):
                best = again
    return best
