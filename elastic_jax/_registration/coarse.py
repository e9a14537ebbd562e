"""Phase 2, the coarse registration: every start gets rounds on the L2 mismatch, the best
then rounds on the straight line's energy, before the path has to be solved.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.typing import DTypeLike
from jaxtyping import Array, ArrayLike

from .._geodesics.solvers import minimize
from .._geometry.composition import kabsch
from .._geometry.metric import SplitMetric
from .._options import ShapeOptions
from .problem import (
    MATCH_STEPS,
    Problem,
    State,
    gamma_source,
    iterate,
    make_problem,
    matching_criterion,
    path_energy_at,
    registered_frame,
    registration_variables,
    rotated_end_frame,
    safe_update,
    stepped_gamma,
    straight_line_energy,
    zero_coefficients,
    zero_registration,
)


def _straight_round(
    prob: Problem, options: ShapeOptions, rigid: bool, weight: ArrayLike, cap: Array, state: State
) -> State:
    """One registration round on the matching criterion from f1 o gamma to R f2.

    Coarse in time before the rounds with the whole path: the straight line cannot bend
    around a wrong correspondence, so its energy keeps a clear pull towards the right
    one. Measured on a bumpy surface against itself under two large degree-3 Diff steps
    (J from 0.13 to 3.0): joint rounds straight from the Moebius start stalled at a
    distance of 0.17; these rounds first brought it to 0.05. ``weight`` and the BFGS's
    step limit ``cap`` are traced (see _coarse_registration).
    """
    dtype = state.energy.dtype
    criterion = matching_criterion(prob, options, weight)
    reference = jnp.maximum(state.energy, jnp.finfo(dtype).tiny)
    source = gamma_source(options, state.gamma)

    def objective(y: ArrayLike):
        x, r_step = registration_variables(prob, y, rigid)
        gamma = stepped_gamma(prob, options, source, x)
        return criterion(gamma, r_step @ state.rotation) / reference

    y0 = zero_registration(prob, rigid, dtype)
    found = minimize(
        objective,
        y0,
        solver=options.solver,
        max_steps=max(options.max_steps, MATCH_STEPS),
        tol=options.tol,
        step_cap=cap,
    )
    x, r_step = registration_variables(prob, found.x, rigid)
    gamma, shrunk = safe_update(prob, options, state.gamma, x)
    rotation = r_step @ state.rotation
    energy = criterion(gamma, rotation)
    steps = state.steps + found.num_steps
    return State(gamma, rotation, state.coefficients, energy, steps, shrunk)


def _straight_rounds(
    prob: Problem, options: ShapeOptions, rigid: bool, state: State, weight: ArrayLike, cap: Array
) -> State:
    """Rounds on the matching criterion (weight 1: L2, 0: the straight line's energy),
    each round's BFGS cut at ``cap`` steps."""
    criterion = matching_criterion(prob, options, weight)
    current = criterion(state.gamma, state.rotation)
    floor = criterion(prob.e1, jnp.eye(3, dtype=prob.f1.dtype))

    def small(before: ArrayLike, after: ArrayLike, _earlier: ArrayLike):
        return jnp.abs(before - after) <= options.outer_tol * (after + options.outer_tol * floor)

    state, _, _, _ = iterate(
        lambda s: _straight_round(prob, options, rigid, weight, cap, s),
        state._replace(energy=current),
        options.outer_steps,
        small,
    )
    return state


def _ranked_rounds(
    prob: Problem, options: ShapeOptions, rigid: bool, state: State, weight: ArrayLike, cap: Array
):
    """_straight_rounds from ``state``, and the straight line's energy where they end: a
    matched start is ranked by it."""
    state = _straight_rounds(prob, options, rigid, state, weight, cap)
    frames = (
        registered_frame(prob, options, state.gamma),
        rotated_end_frame(prob, options, state.rotation),
    )
    return state, straight_line_energy(prob, options, *frames)


def batch_candidates() -> bool:
    """Whether the candidates' L2 rounds run side by side (vmap) rather than one after
    another (a scan): on accelerators. Side by side they step in lockstep, so a batch
    takes the longest candidate's steps, each step costing about one candidate's on a
    GPU at these grids (its kernels are far from filling it); on CPU a step costs the
    batch's size, and the scan's sum of steps is cheaper."""
    return jax.default_backend() != "cpu"


def _coarse_registration(
    prob: Problem, options: ShapeOptions, rigid: bool, starts: tuple, batched: bool | None = None
) -> State:
    """From the starts (_initialize's result) to the registration the rounds with the
    whole path begin from.

    Coarse to fine in the criterion and in time. Every start gets rounds on the L2
    mismatch, each round's BFGS cut at MATCH_STEPS (a round only has to move towards the
    basin: the next round linearizes again); the start whose straight line then has the
    lowest energy gets rounds on that energy. With no starts (given_only_starts) the
    candidates are the pair as given, unmatched: the identity gamma with the identity
    rotation and, modulo rigid, with R^3's Procrustes rotation, the lower straight line's
    energy first (shape_geodesic's second solve when the first ended above the pair as
    given: the L2 rounds can carry every searched start into a worse basin, as on
    fsaverage5's pial hemispheres at 11 x 19, modulo diff: 41,527 after matching against
    20,366 for the parametrized geodesic).
    """
    dtype = prob.f1.dtype
    gammas, rotations, steps = starts
    n_starts = gammas.shape[0]
    # The searched starts' slots are filled as they are matched. The pair as given is a
    # candidate only when no start is searched (given_only_starts): ranked beside the
    # matched starts it won on the elongated ellipsoids' pairs and then ended in a worse,
    # less stationary minimum (0.3738 against 0.3722, joint gradient 8e-3).
    energies = jnp.full((n_starts,), jnp.inf, dtype)
    if n_starts == 0:
        eye = jnp.eye(3, dtype=dtype)
        rotations = jnp.stack([eye, kabsch(prob.f2, prob.f1) if rigid else eye])
        gammas = jnp.broadcast_to(prob.e1, (2, *prob.e1.shape))
        start_frame = registered_frame(prob, options, prob.e1)
        energies = jax.vmap(
            lambda r: straight_line_energy(
                prob, options, start_frame, rotated_end_frame(prob, options, r)
            )
        )(rotations)
    zero = State(
        prob.e1,
        jnp.eye(3, dtype=dtype),
        zero_coefficients(prob, options),
        jnp.zeros((), dtype),
        jnp.zeros((), jnp.int32),
        jnp.zeros((), bool),
    )

    starts = jax.tree_util.tree_map(
        lambda x: jnp.broadcast_to(x, (gammas.shape[0], *x.shape)), zero
    )._replace(gamma=gammas, rotation=rotations, energy=energies)
    if batched is None:
        batched = batch_candidates()
    if batched and n_starts > 0:
        return _batched_candidates(prob, options, rigid, starts, steps)

    # Every start's L2 rounds and then the best start's energy rounds are jobs of one
    # scan, and so one compiled copy of the rounds (weight and step limit traced).

    def job(ends: State, j: ArrayLike):
        matching = j < n_starts
        best = jnp.argmin(jnp.where(jnp.isfinite(ends.energy), ends.energy, jnp.inf))
        i = jnp.where(matching, j, best.astype(jnp.int32))
        state = jax.tree_util.tree_map(lambda x: x[i], ends)
        weight = jnp.where(matching, 1.0, 0.0).astype(dtype)
        cap = jnp.where(matching, MATCH_STEPS, options.max_steps)
        state, straight = _ranked_rounds(prob, options, rigid, state, weight, cap)
        slot = jnp.minimum(j, n_starts - 1)
        ends = jax.tree_util.tree_map(
            lambda e, x: jnp.where(matching, e.at[slot].set(x), e),
            ends,
            state._replace(energy=straight),
        )
        return ends, state

    ends, states = jax.lax.scan(job, starts, jnp.arange(n_starts + 1, dtype=jnp.int32))
    state = jax.tree_util.tree_map(lambda x: x[-1], states)
    best = jnp.argmin(jnp.where(jnp.isfinite(ends.energy), ends.energy, jnp.inf))
    others = jnp.sum(ends.steps).astype(jnp.int32) - ends.steps[best]
    return state._replace(steps=state.steps + steps + others)


def _batched_candidates(
    prob: Problem, options: ShapeOptions, rigid: bool, starts: State, steps: ArrayLike
) -> State:
    """_coarse_registration with the searched starts' L2 rounds vmapped (batch_candidates):
    the same rounds, ranking and energy rounds as the scan's jobs."""
    dtype = prob.f1.dtype

    def match(state: State):
        weight, cap = jnp.ones((), dtype), jnp.asarray(MATCH_STEPS)
        state, straight = _ranked_rounds(prob, options, rigid, state, weight, cap)
        return state._replace(energy=straight)

    ends = jax.vmap(match)(starts)
    best = jnp.argmin(jnp.where(jnp.isfinite(ends.energy), ends.energy, jnp.inf))
    state = jax.tree_util.tree_map(lambda x: x[best], ends)
    state = _straight_rounds(
        prob, options, rigid, state, jnp.zeros((), dtype), jnp.asarray(options.max_steps)
    )
    others = jnp.sum(ends.steps).astype(jnp.int32) - ends.steps[best]
    return state._replace(steps=state.steps + steps + others)


def given_only_starts(m: int, n: int, dtype: DTypeLike):
    """Starts for a solve whose only candidates are the pair as given (see
    _coarse_registration): no searched start."""
    return (
        jnp.zeros((0, 3, m, n), dtype),
        jnp.zeros((0, 3, 3), dtype),
        jnp.zeros((), jnp.int32),
    )


def coarse_phase(
    metric: SplitMetric,
    f1: ArrayLike,
    f2: ArrayLike,
    bases,
    starts: tuple,
    options: ShapeOptions,
    rigid: bool,
) -> tuple[State, Array]:
    """Phase 2: the coarse registration from the starts, and the energy history with its
    energy at [1] (no rounds with the path yet)."""
    prob = make_problem(metric, f1, f2, bases, rigid, options.interpolation)
    state = _coarse_registration(prob, options, rigid, starts)
    energy = path_energy_at(prob, options, state.gamma, state.rotation, state.coefficients)
    state = state._replace(energy=energy, shrunk=jnp.zeros((), bool))
    history = jnp.full((options.outer_steps + 2,), jnp.nan, energy.dtype).at[1].set(energy)
    return state, history
