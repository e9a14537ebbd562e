"""Geodesics between shapes: registration modulo reparametrization and rigid motion.

Paper sections 4.2-4.3 (Algorithms 2 and 3, Remark 4), math §6, 7 and 9. f1 is
reparametrized by gamma (f1 o gamma), f2 is rotated in R^3 by R for modulo="rigid";
translations cost nothing (the metric sees only df), so both surfaces are centered for
modulo="rigid".

The solve runs in phases over one problem record: the starts (icosahedral rotations
ranked, the best refined over rotations and over the Moebius group); coarse-to-fine
registration rounds (every start on the L2 mismatch, the best on the straight line's
energy, then with the whole path) until the energy stops changing; the parametrized and
the final geodesics; and the refinement check (the result re-evaluated with halved time
steps and on a finer grid). Every phase is traceable: a single solve compiles one
program per phase (smaller programs, less compiler memory), and under a caller's jit or
vmap the whole solve is one program, vmappable over f2.
"""

from __future__ import annotations

import functools
import time
import warnings
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import DTypeLike
from jaxtyping import Array, ArrayLike, Float

from .._checks import check_progress, is_concrete
from .._errors import ConvergenceWarning, InputError
from .._geodesics.geodesic import GeodesicResult
from .._geodesics.solvers import default_tol
from .._geometry.harmonics import check_degree
from .._geometry.metric import SplitMetric
from .._geometry.numerics import constant
from .._geometry.reparam import (
    jacobian_determinant_unchecked,
)
from .._geometry.units import in_units
from .._geometry.validation import check_pair
from .._options import ShapeOptions, check_choice, options_with
from .._results import RESULTS
from .._runtime.cache import phase_chain, solver_jit
from .coarse import coarse_phase, given_only_starts
from .final import end_phase, geodesics_phase, shape_finish
from .problem import State, make_bases
from .records import MODULI, Levels, Refinement, ShapeGeodesicResult
from .rounds import Rounds, continuation_phase, rounds_phase
from .starts import given_start, inverse_gamma, starts_phase

# The structures of the phases' results (leaves are placeholders), to rebuild them from
# an exported program's flat outputs (see _runtime/cache.py.exported_call).
_STATE_SKELETON = State(*([0] * 6))


_ROUNDS_SKELETON = Rounds(_STATE_SKELETON, 0, 0, 0)


_RESULT_SKELETON = ShapeGeodesicResult(*([0] * 12), RESULTS.successful, 0, 0, Refinement(0, 0, 0))


_GEODESIC_SKELETON = GeodesicResult(*([0] * 7), RESULTS.successful, 0, 0)


# (name, function, skeleton) per phase, in order; each takes the previous one's result.
_PHASES = (
    ("shape_starts", starts_phase, (0, 0, 0)),
    ("shape_coarse", coarse_phase, (_STATE_SKELETON, 0)),
    ("shape_rounds", rounds_phase, _ROUNDS_SKELETON),
    ("shape_geodesics", geodesics_phase, (_ROUNDS_SKELETON, _GEODESIC_SKELETON)),
    ("shape_end", end_phase, _RESULT_SKELETON),
)


# A level's start carried from the level below (_levels_solve): in place of the start
# search and the coarse rounds.
_CONTINUATION = ("shape_continue", continuation_phase, (_STATE_SKELETON, 0))


# The last phase runs for milliseconds and decides nothing the result reports as found
# (its gradient norm and refinement are diagnostics): compiled for compile speed.
_PHASE_JITS = {
    name: solver_jit(f, static_argnames=("options", "rigid"), quick=name == "shape_end")
    for name, f, _ in (*_PHASES, _CONTINUATION)
}


def _phases(starts: tuple | None, carried: tuple | None) -> tuple[list[tuple], tuple]:
    """The phases a solve runs, each as (name, function, jitted, skeleton), and what the
    first of them is given besides the arguments: all five phases from nothing, the
    coarse rounds on from ``starts``, or the continuation and the last three from
    ``carried``."""
    if carried is not None:
        phases, given = (_CONTINUATION, *_PHASES[2:]), (carried,)
    elif starts is not None:
        phases, given = _PHASES[1:], (starts,)
    else:
        phases, given = _PHASES, ()
    return [(name, f, _PHASE_JITS[name], skeleton) for name, f, skeleton in phases], given


def _solve_in_phases(
    args: tuple,
    options: ShapeOptions,
    rigid: bool,
    starts: tuple | None = None,
    carried: tuple | None = None,
    after: Callable | None = None,
) -> ShapeGeodesicResult:
    """_shape_solve(*args, options, rigid), one compiled program per phase; ``starts`` (the
    first phase's result, given) skips the start search; ``carried`` (gamma, R and the
    path's coefficients, in the solve's units) skips the coarse rounds as well
    (continuation_phase).

    XLA:CPU's compile time and memory grow with a program, and the phases share no
    compiled code: as five programs a solve held less memory than as one (25 x 49 at the
    defaults, peak RSS 600 MB against 789 MB). phase_chain compiles them concurrently,
    which costs some of that back (the cats' peak RSS, the paper's low row 627 -> 727
    MB, middle row 727 -> 822 MB) and saves a quarter of the first call's compiling.
    The arithmetic is that of one program, except the last
    phase's diagnostics (solver_jit's quick compilation: grad_norm rounds differently,
    about 1e-11 relative). Inside a caller's trace (karcher_mean, distance_matrix) the
    phases are part of the caller's one program.
    """
    phases, given = _phases(starts, carried)
    return phase_chain(phases, args, given, {"options": options, "rigid": rigid}, after)


# What each phase has done when it reports (shape_geodesic's progress).
_STAGES = {
    "shape_starts": "start search",
    "shape_coarse": "coarse registration",
    "shape_continue": "registration carried from the level below",
    "shape_rounds": "registration rounds",
    "shape_geodesics": "geodesics",
    "shape_end": "checks",
}


def _phase_energy(out: object):
    """The path energy a phase's result holds (the solve's units), None for the starts."""
    if isinstance(out, ShapeGeodesicResult):
        return out.energy
    head = out[0] if type(out) is tuple else out
    if isinstance(head, Rounds):
        head = head.state
    return head.energy if isinstance(head, State) else None


class _Reporter:
    """shape_geodesic's ``progress``: one dict per phase of each solve and per level,
    with the time since the call began."""

    def __init__(self, progress: Callable, **fixed):
        self.progress, self.fixed = progress, fixed
        self.begin = time.perf_counter()
        self.level: dict = {}

    def send(self, **record):
        seconds = time.perf_counter() - self.begin
        self.progress({**self.fixed, **self.level, **record, "seconds": seconds})

    def phases(self, grid: tuple[int, int], scale: float):
        """phase_chain's ``after`` for a solve on ``grid`` in units of size ``scale``."""

        def after(name: str, out: object):
            energy = _phase_energy(out)
            energy = None if energy is None else float(energy) * scale**2
            self.send(stage=_STAGES[name], grid=tuple(grid), energy=energy)

        return after


def _shape_solve(
    metric: SplitMetric,
    f1: ArrayLike,
    f2: ArrayLike,
    bases,
    options: ShapeOptions,
    rigid: bool,
) -> ShapeGeodesicResult:
    """The whole solve (_solve_in_phases); traced inside a jit, one program."""
    return _solve_in_phases((metric, f1, f2, bases), options, rigid)


def resolve_options(
    options: ShapeOptions | None, changes: dict, function: str = "shape_geodesic"
) -> ShapeOptions:
    """``options`` (default ShapeOptions()) with the keywords ``changes`` under the one
    rule of :func:`elastic_jax._options.options_with`: beside a record a keyword must
    agree with it (an InputError otherwise); without one it sets that field."""
    if options is not None and not isinstance(options, ShapeOptions):
        raise TypeError(f"options must be a ShapeOptions; got {type(options).__name__}")
    return options_with(function, options, changes)


def working_grid_of(options: ShapeOptions, f1: ArrayLike, f2: ArrayLike) -> tuple[int, int]:
    """The grid a shape solve discretizes its path on: ``options.grid``, else the inputs'
    grid, else the finer of the two (more points; f1's on a tie)."""
    if options.grid is not None:
        return options.grid
    grids = [tuple(f.shape[-2:]) for f in (f1, f2)]
    return max(grids, key=lambda grid: grid[0] * grid[1])


def check_grid_options(options: ShapeOptions, m: int, n: int) -> None:
    """The grid-dependent limits of ``options`` (degrees) on an m x n grid."""
    check_degree(options.degree, m, n)
    check_degree(options.vf_degree, m, n, "vf_degree")


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
       never raise the energy and stop when one changes it by at most outer_tol, or after
       outer_steps.
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

    Each phase is one compiled program (five in all, see _solve_in_phases); under
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
            call began, and during levels ``level`` and ``levels``; with ``symmetric``,
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
    check_choice("modulo", modulo, MODULI)
    check_progress(progress)
    resolved = resolve_options(options, changes)
    f1, f2 = check_pair(f1, f2, same_grid=False)
    if symmetric:
        return _symmetric_solve(f1, f2, metric, modulo, resolved, start, progress)
    reporter = None if progress is None else _Reporter(progress)
    if resolved.resolves:
        return _levels_solve(f1, f2, metric, modulo, resolved, start, reporter)
    result = _one_grid_solve(f1, f2, metric, modulo, resolved, start, reporter=reporter)
    _warn_unless_converged(result)
    return result


def _grid_setup(f1: ArrayLike, f2: ArrayLike, metric: SplitMetric, options: ShapeOptions):
    """(options, units, g1, g2, args) of a solve on options's working grid: the static record,
    f1 and f2 in the solve's units, and the phases' arguments (the metric, g1, g2 and the
    bases) as constants: the solve runs on constants and shape_finish differentiates."""
    m, n = working_grid_of(options, f1, f2)
    check_grid_options(options, m, n)
    # One static record per grid and settings, however the grid was asked for (grid=,
    # the inputs' grid, a level): one compiled program for each.
    options = options.replace(grid=(m, n), rtol=None)
    if options.tol is None:
        options = options.replace(tol=default_tol(f1.dtype))
    # Solve in units of the surfaces' size (see _geometry/units.py): float32 works at any scale.
    units, (g1, g2) = in_units(f1, f2)
    bases = make_bases(m, n, options, f1.dtype)
    args = (constant(metric), jax.lax.stop_gradient(g1), jax.lax.stop_gradient(g2), bases)
    return options, units, g1, g2, args


def _one_grid_solve(
    f1: ArrayLike,
    f2: ArrayLike,
    metric: SplitMetric,
    modulo: str,
    options: ShapeOptions,
    start: object,
    carry: tuple | None = None,
    reporter: _Reporter | None = None,
) -> ShapeGeodesicResult:
    """shape_geodesic on one working grid; ``carry`` = (gamma, R, coefficients or None)
    continues a registration instead of searching starts (``start`` is then not used):
    the level below's registration and path in the user's units (_levels_solve), or an
    inverted registration from its straight line (None; _symmetric_solve)."""
    options, units, g1, g2, args = _grid_setup(f1, f2, metric, options)
    m, n = options.grid
    dtype = f1.dtype
    rigid = modulo == "rigid"
    *_, bases = args  # the phases' arguments end with the bases
    starts = None if start is None else given_start(start, m, n, dtype, rigid)
    carried = None
    if carry is not None:
        gamma, rotation, coefficients = carry
        gammas, rotations, _ = given_start((gamma, rotation), m, n, dtype, rigid)
        if coefficients is None:  # the straight line
            coefficients = jnp.zeros((options.n_times - 2, bases.dframe.shape[0] * 3), dtype)
        else:  # the user's units to the solve's
            coefficients = jnp.asarray(coefficients, dtype) / units.scale
        carried = (gammas[0], rotations[0], coefficients)

    # As in geodesic: the solve runs on constants and the energy is evaluated again,
    # differentiably, at the solution (envelope theorem: the derivative of the minimal
    # energy in f1, f2 and the metric, with gamma, R and C held).
    after = None
    if reporter is not None and is_concrete(units.scale):
        after = reporter.phases(options.grid, float(units.scale))

    def solve(starts: tuple | None, carried: tuple | None = None):
        solved = _solve_in_phases(args, options, rigid, starts, carried, after)
        return shape_finish(metric, g1, g2, bases, solved, units, options=options, rigid=rigid)

    result = solve(starts, carried)
    # By name: an eager == would compile a program of its own in each process.
    if is_concrete(result.result) and RESULTS.name(result.result) == "not_registered":
        # The rounds ended above the pair as given: carry the pair as given (and its best
        # rotation) through the rounds as well, and keep the lower of the two.
        again = solve(given_only_starts(m, n, dtype))
        # On a tie (identical inputs: both at the given pair's energy) the solve whose
        # rounds reached it, with their status, not not_registered.
        if float(again.energy) <= float(result.energy):
            result = again._replace(num_steps=again.num_steps + result.num_steps)
    return result


def continued_geodesic(
    f1: ArrayLike,
    f2: ArrayLike,
    metric: SplitMetric,
    modulo: str,
    options: ShapeOptions,
    gamma: ArrayLike,
    rotation: ArrayLike,
    coefficients: ArrayLike | None,
):
    """shape_geodesic on ``options``'s one working grid (``options.grid``, else the inputs'),
    continuing a registration and path: the registration rounds with the whole path start
    from gamma ``(3, p, q)`` (read at the working grid's points when on another grid), R
    ``(3, 3)`` and the path's coefficients ``(N - 2, L)`` in f1's and f2's units (a
    result's ``coefficients``); no start search and no coarse rounds (continuation_phase).

    A solve that follows the basin it starts in: its distance is continuous in f1 and f2
    where the rounds' local minimum is (the resolved Karcher mean's steps; a level above
    the first). Traceable (jit, vmap); no ConvergenceWarning (the result's status says).
    """
    m, n = working_grid_of(options, f1, f2)
    options = options.replace(grid=(m, n), rtol=None)
    carry = (gamma, rotation, coefficients)
    return _one_grid_solve(f1, f2, metric, modulo, options, None, carry=carry)


def level_solve(
    f1: ArrayLike,
    f2: ArrayLike,
    metric: SplitMetric,
    modulo: str,
    options: ShapeOptions,
    grid: tuple[int, int],
    below: ShapeGeodesicResult | None,
    start: object = None,
    reporter: _Reporter | None = None,
) -> ShapeGeodesicResult:
    """One level of a resolved distance: the solve on ``grid`` continuing the level
    ``below`` (its registration and path, without a new start search or coarse rounds:
    continuation_phase), or, for the first level, from ``start`` or a search of its own.

    The coarser gamma's interpolant can fold between its points (the cats at 13 x 25 read
    at 25 x 49, chain rule), and so can a fine start read on a coarse level: that level
    then searches its own start.
    """
    carried = registration_at(start if below is None else below, grid, f1.dtype, modulo)
    level = options.replace(rtol=None, grid=grid)
    if below is not None and carried is not None:
        carry = (*carried, below.coefficients)
        return _one_grid_solve(f1, f2, metric, modulo, level, None, carry=carry, reporter=reporter)
    return _one_grid_solve(f1, f2, metric, modulo, level, carried, reporter=reporter)


def _levels_solve(
    f1: ArrayLike,
    f2: ArrayLike,
    metric: SplitMetric,
    modulo: str,
    options: ShapeOptions,
    start: object,
    reporter: _Reporter | None = None,
) -> ShapeGeodesicResult:
    """shape_geodesic with ``options.rtol``: the working grids of ``options.levels`` coarse to
    fine, each level continuing the one below (its registration and path: no new start
    search, no coarse rounds; continuation_phase), until two successive distances agree
    within rtol (math §10). The first level starts from ``start`` or searches its own.

    The finest level's result, with ``levels`` recording every level; converged when
    that level converged and the tolerance was met, else ``RESULTS.not_resolved`` when
    only the tolerance was missed.
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
    for m, n in options.levels:
        try:
            check_grid_options(options, m, n)
        except InputError as error:
            raise InputError(f"levels: the {m} x {n} level: {error}") from None
    grids, distances, seconds = [], [], []
    result = None
    noise = _noise_distance(f1, f2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        for index, grid in enumerate(options.levels, 1):
            begin = time.perf_counter()
            if reporter is not None:
                reporter.level = {"level": index, "levels": len(options.levels)}
            result = level_solve(f1, f2, metric, modulo, options, grid, result, start, reporter)
            distances.append(float(jax.block_until_ready(result.distance)))
            seconds.append(time.perf_counter() - begin)
            grids.append(grid)
            if reporter is not None:
                reporter.send(
                    stage="level",
                    grid=tuple(grid),
                    energy=float(result.energy),
                    distance=distances[-1],
                    converged=bool(result.converged),
                )
            change = _change(distances, result.parametrized_distance, noise)
            if not np.isfinite(distances[-1]) or (
                change <= options.rtol and bool(result.converged)
            ):
                break  # a non-finite level (RESULTS.nonfinite) ends the levels too
    if reporter is not None:
        reporter.level = {}
    result = _with_levels(result, grids, distances, seconds, options.rtol, noise)
    _warn_unless_converged(result, stacklevel=4)
    return result


# A pair of near-equal shapes (a distance below this fraction of the pair's parametrized
# distance) is resolved to that absolute size, not relative to its own distance: d(f, R f)
# is zero in the continuum, and levels of a small number differ by more than 3 % of it
# however well each is solved (the target for such pairs is 0.05 d, absolute).
_NEAR_EQUAL = 0.05


def _noise_distance(f1: ArrayLike, f2: ArrayLike) -> float:
    """The distance whose energy is the rounding level at which the final phase compares
    the registered and the given pair (sqrt(eps) in the solve's unit-size units): two
    levels' distances that differ by less are the same minimum. Identical inputs end at
    0 on one level and at up to this on the next, from the carried identity's
    interpolation (a sphere of radius 2 at 13 x 25: 1e-14, 8e-15, 3.4e-5, 3.1e-4 up to
    97 x 193, all within 4.9e-4)."""
    units, _ = in_units(f1, f2)
    eps = float(np.finfo(np.dtype(f1.dtype)).eps)
    return eps**0.25 * float(units.scale)


def _change(distances: Sequence[float], parametrized: ArrayLike = 0.0, noise: float = 0.0) -> float:
    """The change of the last two levels' distances, less ``noise`` (_noise_distance),
    relative to the last, or to _NEAR_EQUAL times the parametrized distance when that is
    larger (NaN for one level)."""
    if len(distances) < 2:
        return np.nan
    d, before = float(distances[-1]), float(distances[-2])
    scale = max(d, _NEAR_EQUAL * float(parametrized), np.finfo(np.float64).tiny)
    return max(abs(d - before) - noise, 0.0) / scale


def _with_levels(
    result: ShapeGeodesicResult,
    grids: list | Array,
    distances: Sequence[float],
    seconds: Sequence[float],
    rtol: float,
    noise: float = 0.0,
) -> ShapeGeodesicResult:
    """``result`` (the finest level's) with its :class:`Levels` record; converged when it
    converged and the last change met rtol, ``RESULTS.not_resolved`` when only the
    tolerance was missed."""
    dtype = result.distance.dtype
    estimate = _change(distances, result.parametrized_distance, noise)
    met = bool(estimate <= rtol)
    levels = Levels(
        grids=jnp.asarray(grids, jnp.int32),
        distances=jnp.asarray(distances, dtype),
        seconds=jnp.asarray(seconds, dtype),
        estimate=jnp.asarray(estimate, dtype),
        rtol=jnp.asarray(rtol, dtype),
    )
    code = result.result
    if not met and bool(result.converged):
        code = RESULTS.not_resolved
    return result._replace(
        converged=jnp.asarray(bool(result.converged) and met), result=code, levels=levels
    )


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
    solve = functools.partial(shape_geodesic, metric=metric, modulo=modulo, options=resolved)
    begin = time.perf_counter()

    def order(name: str):  # the order's reports, timed from this call's beginning
        if progress is None:
            return None
        return lambda r: progress({**r, "order": name, "seconds": time.perf_counter() - begin})

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        best = solve(f1, f2, start=start, progress=order("f1 -> f2"))
        other = solve(f2, f1, progress=order("f2 -> f1"))
        if float(other.distance) < float(best.distance):
            inverse, residual = inverse_gamma(other.gamma)
            tol = 10.0 * float(np.sqrt(np.finfo(np.dtype(inverse.dtype)).eps))
            if (
                float(residual) <= tol
                and float(jnp.min(jacobian_determinant_unchecked(inverse))) > 0
            ):
                # A continuation: the coarse rounds would re-register on the L2
                # mismatch and leave the inverted registration's basin.
                grid = tuple(other.gamma.shape[-2:])
                begin = time.perf_counter()
                carry = (inverse, other.rotation.T, None)
                level = resolved.replace(rtol=None, grid=grid)
                third = order("f1 -> f2 from f2 -> f1")
                reporter = None if third is None else _Reporter(third)
                again = _one_grid_solve(
                    f1, f2, metric, modulo, level, None, carry=carry, reporter=reporter
                )
                if other.levels is not None:
                    # The levels that found this basin (the other order's), the last
                    # distance and time this solve's.
                    levels = other.levels
                    distances = np.asarray(levels.distances).tolist()[:-1] + [float(again.distance)]
                    seconds = np.asarray(levels.seconds).tolist()
                    seconds[-1] += time.perf_counter() - begin
                    noise = _noise_distance(f1, f2)
                    again = _with_levels(
                        again, levels.grids, distances, seconds, resolved.rtol, noise
                    )
                if float(again.distance) < float(best.distance):
                    best = again
    _warn_unless_converged(best)
    return best


def _warn_unless_converged(result: ShapeGeodesicResult, stacklevel: int = 3) -> None:
    """ConvergenceWarning for a concrete result that did not converge."""
    if is_concrete(result.converged, result.energy_history, result.rounds) and not bool(
        result.converged
    ):
        history = np.asarray(result.energy_history)
        # Every other ending's words (stalled, saddle, resolution-limited) say what to
        # change; running out of steps is the one that does not.
        ran_out = RESULTS.name(result.result) == "nonlinear_max_steps_reached"
        advice = "; raise outer_steps or max_steps" if ran_out else ""
        if result.levels is not None:
            steps = ", ".join(
                f"{m} x {n}: {d:.6g}"
                for (m, n), d in zip(
                    np.asarray(result.levels.grids).tolist(),
                    np.asarray(result.levels.distances).tolist(),
                    strict=True,
                )
            )
            advice += f"; levels {steps} (estimate {float(result.levels.estimate):.3g})"
        warnings.warn(
            f"shape_geodesic: not converged after {int(result.rounds)} registration rounds "
            f"({result.message}; energies {history[np.isfinite(history)].round(6).tolist()})"
            f"{advice}",
            ConvergenceWarning,
            stacklevel=stacklevel,
        )
