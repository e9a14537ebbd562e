"""A shape solve's phases: one compiled program each, chained over one problem record.

The starts (icosahedral rotations ranked, the best refined over rotations and over the
Moebius group); coarse-to-fine registration rounds (every start on the L2 mismatch, the
best on the straight line's energy, then with the whole path) until the energy stops
changing; the parametrized and the final geodesics; and the refinement check (the result
re-evaluated with halved time steps and on a finer grid). Every phase is traceable: a
single solve compiles one program per phase (smaller programs, less compiler memory),
and under a caller's jit or vmap the whole solve is one program, vmappable over f2.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from jaxtyping import ArrayLike

from .._geodesics.geodesic import GeodesicResult
from .._geometry.metric import SplitMetric
from .._options import ShapeOptions
from .._results import RESULTS
from .._runtime.cache import phase_chain, solver_jit
from .coarse import coarse_phase
from .final import end_phase, geodesics_phase
from .problem import State
from .records import Refinement, ShapeGeodesicResult
from .rounds import Rounds, continuation_phase, rounds_phase
from .starts import starts_phase

# The structures of the phases' results (leaves are placeholders), to rebuild them from
# an exported program's flat outputs (see _runtime/cache.py.exported_call).
_STATE_SKELETON = State(*([0] * 6))


_ROUNDS_SKELETON = Rounds(_STATE_SKELETON, 0, 0, 0, 0)


_RESULT_SKELETON = ShapeGeodesicResult(
    **dict.fromkeys(ShapeGeodesicResult._fields, 0),
)._replace(result=RESULTS.successful, refinement=Refinement(0, 0, 0), levels=None)


_GEODESIC_SKELETON = GeodesicResult(**dict.fromkeys(GeodesicResult._fields, 0))._replace(
    result=RESULTS.successful
)


# (name, function, skeleton) per phase, in order; each takes the previous one's result.
PHASES = (
    ("shape_starts", starts_phase, (0, 0, 0)),
    ("shape_coarse", coarse_phase, (_STATE_SKELETON, 0)),
    ("shape_rounds", rounds_phase, _ROUNDS_SKELETON),
    ("shape_geodesics", geodesics_phase, (_ROUNDS_SKELETON, _GEODESIC_SKELETON)),
    ("shape_end", end_phase, _RESULT_SKELETON),
)


# A level's start carried from the level below (levels_solve): in place of the start
# search and the coarse rounds.
CONTINUATION = ("shape_continue", continuation_phase, (_STATE_SKELETON, 0, 0))


# The last phase runs for milliseconds and decides nothing the result reports as found
# (its gradient norm and refinement are diagnostics): compiled for compile speed.
PHASE_JITS = {
    name: solver_jit(f, static_argnames=("options", "rigid"), quick=name == "shape_end")
    for name, f, _ in (*PHASES, CONTINUATION)
}


def _phases(starts: tuple | None, carried: tuple | None) -> tuple[list[tuple], tuple]:
    """The phases a solve runs, each as (name, function, jitted, skeleton), and what the
    first of them is given besides the arguments: all five phases from nothing, the
    coarse rounds on from ``starts``, or the continuation and the last three from
    ``carried``."""
    if carried is not None:
        phases, given = (CONTINUATION, *PHASES[2:]), (carried,)
    elif starts is not None:
        phases, given = PHASES[1:], (starts,)
    else:
        phases, given = PHASES, ()
    return [(name, f, PHASE_JITS[name], skeleton) for name, f, skeleton in phases], given


def solve_in_phases(
    args: tuple,
    options: ShapeOptions,
    rigid: bool,
    starts: tuple | None = None,
    carried: tuple | None = None,
    after: Callable | None = None,
) -> ShapeGeodesicResult:
    """shape_solve(*args, options, rigid), one compiled program per phase; ``starts`` (the
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


class Reporter:
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


def shape_solve(
    metric: SplitMetric,
    f1: ArrayLike,
    f2: ArrayLike,
    bases,
    options: ShapeOptions,
    rigid: bool,
) -> ShapeGeodesicResult:
    """The whole solve (solve_in_phases); traced inside a jit, one program."""
    return solve_in_phases((metric, f1, f2, bases), options, rigid)
