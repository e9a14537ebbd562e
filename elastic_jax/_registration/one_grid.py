"""A shape solve on one working grid: from a start search, a given start, or a carried
registration and path (a level continuing the one below).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import ArrayLike

from .._checks import is_concrete
from .._geometry.bases import make_bases
from .._geometry.metric import SplitMetric
from .._geometry.numerics import constant, default_tol
from .._geometry.units import in_units
from .._geometry.validation import check_grid_options
from .._options import ShapeOptions
from .._results import RESULTS
from .coarse import given_only_starts
from .final import shape_finish
from .phases import Reporter, solve_in_phases
from .records import ShapeGeodesicResult
from .starts import given_start

# What a solve on one grid records as its levels: it uses none (the default list).
_ONE_GRID_LEVELS = ShapeOptions().levels


def working_grid_of(options: ShapeOptions, f1: ArrayLike, f2: ArrayLike) -> tuple[int, int]:
    """The grid a shape solve discretizes its path on: ``options.grid``, else the inputs'
    grid, else the finer of the two (more points; f1's on a tie)."""
    if options.grid is not None:
        return options.grid
    grids = [tuple(f.shape[-2:]) for f in (f1, f2)]
    return max(grids, key=lambda grid: grid[0] * grid[1])


def grid_setup(f1: ArrayLike, f2: ArrayLike, metric: SplitMetric, options: ShapeOptions):
    """(options, units, g1, g2, args) of a solve on options's working grid: the static record,
    f1 and f2 in the solve's units, and the phases' arguments (the metric, g1, g2 and the
    bases) as constants: the solve runs on constants and shape_finish differentiates."""
    m, n = working_grid_of(options, f1, f2)
    check_grid_options(options, m, n)
    # One static record per grid and settings, however the grid was asked for (grid=,
    # the inputs' grid, a level of any list of levels): one compiled program for each.
    options = options.replace(
        grid=(m, n),
        rtol=None,
        levels=_ONE_GRID_LEVELS,
        level_vf_degrees=None,
        level_candidates=1,
        both_orders=False,
        search_smoothing=(),
        smoothing_kernel="sphere",
        alternations=0,
        quadrature=options.quadrature_factor,
        stretch_quadrature=options.stretch_fraction,
    )
    if options.tol is None:
        options = options.replace(tol=default_tol(f1.dtype))
    # Solve in units of the surfaces' size (see _geometry/units.py): float32 works at any scale.
    units, (g1, g2) = in_units(f1, f2)
    bases = make_bases(m, n, options, f1.dtype)
    args = (constant(metric), jax.lax.stop_gradient(g1), jax.lax.stop_gradient(g2), bases)
    return options, units, g1, g2, args


def one_grid_solve(
    f1: ArrayLike,
    f2: ArrayLike,
    metric: SplitMetric,
    modulo: str,
    options: ShapeOptions,
    start: object,
    carry: tuple | None = None,
    reporter: Reporter | None = None,
) -> ShapeGeodesicResult:
    """shape_geodesic on one working grid; ``carry`` = (gamma, R, coefficients or None
    [, the parametrized geodesic's coefficients or None]) continues a registration
    instead of searching starts (``start`` is then not used): the level below's
    registration, path and parametrized path in the user's units (levels_solve), or an
    inverted registration from its straight line (None; _symmetric_solve)."""
    options, units, g1, g2, args = grid_setup(f1, f2, metric, options)
    m, n = options.grid
    dtype = f1.dtype
    rigid = modulo == "rigid"
    *_, bases = args  # the phases' arguments end with the bases
    starts = None if start is None else given_start(start, m, n, dtype, rigid)
    carried = None
    if carry is not None:
        gamma, rotation, *paths = carry
        gammas, rotations, _ = given_start((gamma, rotation), m, n, dtype, rigid)
        shape = (options.n_times - 2, bases.dframe.shape[0] * 3)

        def solve_units(c):  # the straight line for None; the user's units to the solve's
            return jnp.zeros(shape, dtype) if c is None else jnp.asarray(c, dtype) / units.scale

        coefficients, parametrized = (solve_units(c) for c in (*paths, None)[:2])
        carried = (gammas[0], rotations[0], coefficients, parametrized)

    # As in geodesic: the solve runs on constants and the energy is evaluated again,
    # differentiably, at the solution (envelope theorem: the derivative of the minimal
    # energy in f1, f2 and the metric, with gamma, R and C held).
    after = None
    if reporter is not None and is_concrete(units.scale):
        after = reporter.phases(options.grid, float(units.scale))

    def solve(starts: tuple | None, carried: tuple | None = None):
        solved = solve_in_phases(args, options, rigid, starts, carried, after)
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
    parametrized: ArrayLike | None = None,
):
    """shape_geodesic on ``options``'s one working grid (``options.grid``, else the inputs'),
    continuing a registration and path: the registration rounds with the whole path start
    from gamma ``(3, p, q)`` (read at the working grid's points when on another grid), R
    ``(3, 3)`` and the path's coefficients ``(N - 2, L)`` in f1's and f2's units (a
    result's ``coefficients``); no start search and no coarse rounds (continuation_phase).
    ``parametrized``: where the parametrized geodesic starts (a coarser level's
    ``parametrized_coefficients``; None: the straight line).

    A solve that follows the basin it starts in: its distance is continuous in f1 and f2
    where the rounds' local minimum is (the resolved Karcher mean's steps; a level above
    the first). Traceable (jit, vmap); no ConvergenceWarning (the result's status says).
    """
    m, n = working_grid_of(options, f1, f2)
    options = options.replace(grid=(m, n), rtol=None)
    carry = (gamma, rotation, coefficients, parametrized)
    return one_grid_solve(f1, f2, metric, modulo, options, None, carry=carry)
