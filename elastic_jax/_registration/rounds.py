"""Phase 3, the registration rounds with the whole path (paper Algorithms 2 and 3) until
the energy stops changing.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

from .._geodesics.solvers import identity_inverse, minimize
from .._geometry.metric import SplitMetric
from .._options import ShapeOptions
from .problem import (
    Problem,
    State,
    geodesic_at,
    identity_frames,
    iterate,
    joint_objective,
    make_problem,
    path_energy_at,
    registration_variables,
    safe_update,
    scaling_at,
    straight_line_energy,
    zero_registration,
)


class _Warm(NamedTuple):
    """A round's state (:class:`State`'s fields) with the joint BFGS's inverse Hessian
    approximation at the end of the last round (None for the coordinate method and for
    lbfgs)."""

    gamma: Array
    rotation: Array
    coefficients: Array
    energy: Array
    steps: Array
    shrunk: Array
    inverse: object


def _round(prob: Problem, options: ShapeOptions, rigid: bool, state: _Warm) -> _Warm:
    """One registration round.

    joint (Algorithm 2): BFGS over the path coefficients and the next Diff step (and a
    rotation of f2) together; the path is not solved again for a shrunk step (the next
    round or the final solve does it). coordinate: BFGS over the Diff step (and
    rotation) with the path's perturbation held, then the geodesic. The paper's
    Algorithm 3 holds the path's interior frames instead, which pins the start to its
    neighbour: it moved the energy by 7-8 % per round on the cats where this reaches
    1 % of its limit in 4 rounds.

    The joint BFGS starts from the path's block of the inverse Hessian the last round
    ended with (:func:`_path_block_only`): the path's whitened coefficients are the same
    functions at a nearby point, so their curvature carries over instead of being
    learned again from the identity each round. The cats' 97 x 193 level continuing
    49 x 97: 4 rounds and 2263 solver steps instead of 6 and 3415, the same distance to
    5e-6 (the whole inverse carried, the Diff step's block too: 4 rounds, a distance 1.3 %
    higher, in a shallower minimum).
    """
    dtype = state.energy.dtype
    scaling = scaling_at(prob, options, state.gamma, state.rotation)
    objective = joint_objective(prob, options, rigid, state.gamma, state.rotation, scaling)
    y0 = zero_registration(prob, rigid, dtype)
    z0 = scaling.whitened(state.coefficients)
    solver_kwargs = {"solver": options.solver, "max_steps": options.max_steps, "tol": options.tol}
    if options.method == "joint":
        found = minimize(
            objective,
            (z0, y0),
            **solver_kwargs,
            inverse0=_path_block_only(state.inverse),
            keep_inverse=True,
        )
        z, y = found.x
    else:
        found = minimize(lambda y: objective((z0, y)), y0, **solver_kwargs)
        z, y = z0, found.x
    x, r_step = registration_variables(prob, y, rigid)
    gamma, shrunk = safe_update(prob, options, state.gamma, x)
    rotation = r_step @ state.rotation
    coefficients = scaling.coefficients(z)
    steps = state.steps + found.num_steps
    if options.method == "joint":
        energy = path_energy_at(prob, options, gamma, rotation, coefficients)
    else:
        res = geodesic_at(prob, options, gamma, rotation, coefficients)
        coefficients, energy, steps = res.coefficients, res.energy, steps + res.num_steps
    inverse = found.inverse if options.method == "joint" else None
    return _Warm(gamma, rotation, coefficients, energy, steps, shrunk, inverse)


def _with_path_block(inverse, block):
    """``inverse`` (the joint BFGS's operator over (path, Diff step)) with the path's
    block set to ``block`` and the Diff step's rows and columns those of the identity."""
    leaves, treedef = jax.tree_util.tree_flatten(inverse)
    _, path_step, step_path, step_step = leaves
    eye = jnp.eye(step_step.shape[0], dtype=step_step.dtype)
    return treedef.unflatten([block, jnp.zeros_like(path_step), jnp.zeros_like(step_path), eye])


def _path_block_only(inverse):
    """The carried inverse Hessian with its Diff step's rows and columns reset to the
    identity's: the path's coefficients are the same functions round after round, but a
    Diff step is taken at the newly composed gamma, a new variable."""
    if inverse is None:
        return None
    return _with_path_block(inverse, jax.tree_util.tree_leaves(inverse)[0])


def _first_inverse(prob: Problem, options: ShapeOptions, rigid: bool, state: State):
    """The identity operator the joint BFGS starts its first round from (its own
    init's), so that the rounds' loop carries one operator structure; None when nothing
    is carried (the coordinate method, lbfgs)."""
    if options.method != "joint" or options.solver != "bfgs":
        return None
    dtype = state.energy.dtype
    return identity_inverse((state.coefficients, zero_registration(prob, rigid, dtype)))


class Rounds(NamedTuple):
    """Where the registration rounds stand between the phases of a solve."""

    state: State
    history: Array  # (outer_steps + 2,) as ShapeGeodesicResult.energy_history, [0] unset
    rounds: Array  # () rounds with the whole path taken
    done: Array  # () bool: the last round met outer_tol or was refused
    # (N - 2, L) where the parametrized geodesic starts: the level below's solution when
    # carried (continuation_phase), else the straight line (zeros).
    parametrized: Array


def rest_of_rounds(earlier: ArrayLike, before: ArrayLike, after: ArrayLike) -> Array:
    """What the rounds after this one would still lower the energy by, were their
    changes to fall as the last two did: d r / (1 - r) with d = before - after and
    r = d / (earlier - before), the tail of a geometric series; inf where the changes
    do not fall (r >= 1) or there is no round before (``earlier`` inf).

    The rounds' energies fall about geometrically: continuing a lower level, the cats'
    49 x 97 rounds changed it by 11.6, 2.1, 0.41 and 0.15 % (ratios 0.18, 0.20, 0.37),
    cat1 -> horse0's by 17.5, 4.5, 0.31 and 0.12 % (0.26, 0.07, 0.39), and the cats'
    97 x 193 rounds by 15.3, 5.8, 1.3 and 0.02 % (0.38, 0.23, 0.02). The tail after the
    second of the cats' 49 x 97 rounds is 0.46 %, where the rounds that followed took
    0.57 %.
    """
    earlier, before, after = (jnp.asarray(e) for e in (earlier, before, after))
    d = before - after
    r = d / (earlier - before)
    falling = jnp.isfinite(earlier) & (r >= 0) & (r < 1)
    return jnp.where(falling, d * r / (1 - r), jnp.inf)


def rounds_phase(
    metric: SplitMetric,
    f1: ArrayLike,
    f2: ArrayLike,
    bases,
    coarse: tuple,
    options: ShapeOptions,
    rigid: bool,
) -> Rounds:
    """Phase 3: the registration rounds with the whole path."""
    prob = make_problem(metric, f1, f2, bases, rigid, options.interpolation)
    straight0 = straight_line_energy(prob, options, *identity_frames(prob, options))

    def small_change(before: ArrayLike, after: ArrayLike, earlier: ArrayLike):
        # Relative to the current energy, with a floor at the tolerance times the
        # straight line's: near a perfect match the energy is interpolation noise.
        stop = options.round_stop
        within = stop * (after + stop * straight0)
        return (jnp.abs(before - after) <= within) | (
            rest_of_rounds(earlier, before, after) <= within
        )

    state, history, *carried = coarse
    parametrized = carried[0] if carried else jnp.zeros_like(state.coefficients)
    warm = _Warm(*state, _first_inverse(prob, options, rigid, state))
    warm, history, rounds, done = iterate(
        lambda s: _round(prob, options, rigid, s),
        warm,
        options.outer_steps,
        small_change,
        history,
    )
    return Rounds(State(*warm[:6]), history, rounds, done, parametrized)


def continuation_phase(
    metric: SplitMetric,
    f1: ArrayLike,
    f2: ArrayLike,
    bases,
    carried: tuple,
    options: ShapeOptions,
    rigid: bool,
) -> tuple[State, Array, Array]:
    """Phase 3's start from a registration carried from a coarser working grid (gamma
    and R read at this grid's points, the path's coefficients as they were): the state
    and the energy history coarse_phase would give, without its rounds, and where the
    parametrized geodesic starts (the coarser grid's solution, when carried: fine levels
    solve it from there instead of from the straight line).

    A pure continuation. The coarse rounds re-register on the L2 mismatch and the straight
    line, away from the carried registration and by a route that turns on rounding: on
    the cats at 97 x 193 from one 49 x 97 registration, three solves whose inputs differ
    by 1e-10 began their path rounds at energies 5.39, 5.31 and 5.57. It is also the
    symmetric solve's third solve, from the other order's registration inverted: there
    the coarse rounds left the inverted basin (a stretched bumpy pair, 0.587 against
    0.547; continued, 0.5475). The path's coefficients are those of spherical harmonics,
    the same functions on every grid.
    """
    prob = make_problem(metric, f1, f2, bases, rigid, options.interpolation)
    gamma, rotation, coefficients, parametrized = carried
    energy = path_energy_at(prob, options, gamma, rotation, coefficients)
    dtype = energy.dtype
    state = State(
        gamma, rotation, coefficients, energy, jnp.zeros((), jnp.int32), jnp.zeros((), bool)
    )
    history = jnp.full((options.outer_steps + 2,), jnp.nan, dtype).at[1].set(energy)
    return state, history, parametrized
