"""Phases 4 and 5: the unregistered and the registered geodesics, the result record and
the refinement check (halved time steps, the finer grid).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import ArrayLike

from .._geodesics.geodesic import solve_path, upsample_coefficients
from .._geometry.bases import frames_between, path_from_coefficients, perturbed_frames
from .._geometry.composition import compose, rotate_surface
from .._geometry.differential import area_element
from .._geometry.energy import frame_energy
from .._geometry.grid import integrate_interior, sphere_points
from .._geometry.metric import SplitMetric
from .._geometry.numerics import safe_sqrt
from .._geometry.units import Units
from .._options import ShapeOptions
from .._results import RESULTS
from .problem import (
    Problem,
    State,
    frame_of,
    frames_energy_by_rule,
    geodesic_options,
    identity_frames,
    joint_objective,
    make_problem,
    path_dframe,
    path_energy_at,
    refined_frames,
    registered_f1,
    registered_frame,
    rotated_end_frame,
    scaling_at,
    stretched_cells_of,
    zero_registration,
)
from .records import Refinement, ShapeGeodesicResult
from .rounds import Rounds


def _refinement(
    prob: Problem,
    options: ShapeOptions,
    gamma: ArrayLike,
    rotation: ArrayLike,
    coefficients: ArrayLike,
    energy: ArrayLike,
) -> Refinement:
    """The result re-evaluated with halved time steps, and on the grid twice finer than
    the one its energy was integrated on (bases.refinement_grid) by that grid's nodes."""
    metric, bases, degree = prob.metric, prob.bases, options.degree
    start, end = registered_frame(prob, options, gamma), rotated_end_frame(prob, options, rotation)
    n_fine = 2 * options.n_times - 1
    halved = upsample_coefficients(coefficients, degree, degree, n_fine)
    straight = frames_between(start, end, n_fine)
    frames = perturbed_frames(straight, halved, path_dframe(prob, options))
    # By the solve's own rule in space (its stretched cells included): only time changes.
    cells = stretched_cells_of(prob, options, gamma)
    time_energy = frames_energy_by_rule(prob, options, frames, gamma, rotation, cells)

    fine_gamma = compose(gamma, bases.fine_points, options.interpolation)
    fine_start = frame_of(prob.source1, fine_gamma, options)
    # R f2 read through the identity's interpolant, as f1 o gamma is through gamma's: a
    # surface against itself is then at distance 0 here too.
    fine_id = compose(prob.e1, bases.fine_points, options.interpolation)
    fine_end = [rotate_surface(rotation, a) for a in frame_of(prob.source2, fine_id, options)]
    straight = frames_between(fine_start, fine_end, options.n_times)
    frames = refined_frames(straight, prob, coefficients)
    grid_energy = frame_energy(metric, *frames, options.scheme)

    d = jnp.sqrt(energy)
    d_time, d_grid = jnp.sqrt(time_energy), jnp.sqrt(grid_energy)
    change = jnp.maximum(jnp.abs(d_time - d), jnp.abs(d_grid - d))
    return Refinement(d_time, d_grid, change / jnp.maximum(d, jnp.finfo(d.dtype).tiny))


def _final_solves(prob: Problem, options: ShapeOptions, state: State, parametrized):
    """The unregistered and the registered geodesics, saddle-checked; the first starts
    from ``parametrized`` (a coarser level's solution, or zeros), the second from the
    rounds' path.

    One traced solve for both (lax.map runs them one after the other): half the
    compilation of two call sites.
    """
    f1, f2, bases = prob.f1, prob.f2, prob.bases
    starts = jnp.stack([f1, registered_f1(prob, options, state.gamma)])
    ends = jnp.stack([f2, rotate_surface(state.rotation, f2)])
    inits = jnp.stack([parametrized, state.coefficients])
    identity = identity_frames(prob, options)
    registered = (
        registered_frame(prob, options, state.gamma),
        rotated_end_frame(prob, options, state.rotation),
    )
    frames = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), identity, registered)

    def solve(problem: tuple):
        start, end, init, (start_frame, end_frame) = problem
        return solve_path(
            prob.metric,
            start,
            end,
            init,
            bases.values,
            path_dframe(prob, options),
            **geodesic_options(options),
            saddle_checks=options.saddle_checks,
            frames=(start_frame, end_frame),
        )

    return jax.lax.map(solve, (starts, ends, inits, frames))


def geodesics_phase(
    metric: SplitMetric,
    f1: ArrayLike,
    f2: ArrayLike,
    bases,
    rounds: Rounds,
    options: ShapeOptions,
    rigid: bool,
):
    """Phase 4: the parametrized and the final geodesic (``rounds`` passed on)."""
    prob = make_problem(metric, f1, f2, bases, rigid, options.interpolation)
    return rounds, _final_solves(prob, options, rounds.state, rounds.parametrized)


# A distance below this fraction of the area bound is lost precision (end_phase).
_AREA_BOUND_SLACK = 0.9


def end_phase(
    metric: SplitMetric,
    f1: ArrayLike,
    f2: ArrayLike,
    bases,
    solved: tuple,
    options: ShapeOptions,
    rigid: bool,
) -> ShapeGeodesicResult:
    """Phase 5: the result from the rounds and the geodesics (status, refinement).

    The shape distance is an infimum over reparametrizations (and rotations), so the
    pair as given is always a candidate: when the registered geodesic ends above the
    parametrized one, the result is the parametrized geodesic (identity gamma and
    rotation), with ``RESULTS.not_registered`` when the gap exceeds outer_tol relative
    (and sqrt(eps) absolute, in the solve's unit-size units): a gap within it is the same
    minimum reached two ways, and keeps the rounds' status.
    """
    prob = make_problem(metric, f1, f2, bases, rigid, options.interpolation)
    dtype = prob.f1.dtype
    rounds, both = solved
    parametrized, registered = (jax.tree_util.tree_map(lambda x, i=i: x[i], both) for i in (0, 1))
    state, history = rounds.state, rounds.history
    history = history.at[0].set(parametrized.energy)
    steps = state.steps + jnp.sum(both.num_steps).astype(jnp.int32)

    # The surfaces are of unit size here (_geometry/units.py): a gap below sqrt(eps),
    # relative or absolute, is rounding (identical inputs: the registered energy ~1e-30
    # against the given 0). Within it the registration is kept: a registration that
    # converged to (nearly) the identity is the pair as given, and a choice made by
    # rounding would differ between programs (fit_metric's batched solves against
    # distance_matrix's: 3e-9 apart, and kinks in the distance as a function of the metric).
    noise = jnp.sqrt(jnp.finfo(dtype).eps)
    registered_energy, parametrized_energy = registered.energy, parametrized.energy
    if options.stretch_fraction > 0.0:
        # The geodesics are solved by the nodes, and the reported distances add the
        # stretched cells' finer rule (shape_finish): the two are compared by the rule
        # they are reported by. By the nodes alone, horse0 -> hand4's 97 x 193 level kept
        # a registration reported 0.05 % above the pair as given.
        registered_energy = path_energy_at(
            prob, options, state.gamma, state.rotation, registered.coefficients
        )
        parametrized_energy = path_energy_at(
            prob, options, prob.e1, jnp.eye(3, dtype=dtype), parametrized.coefficients
        )
    given_lower = jnp.isfinite(parametrized_energy) & ~(
        registered_energy <= parametrized_energy * (1.0 + noise) + noise
    )
    not_registered = given_lower & ~(
        registered_energy - parametrized_energy <= options.outer_tol * parametrized_energy + noise
    )
    final = jax.tree_util.tree_map(
        lambda a, b: jnp.where(given_lower, a, b), parametrized, registered
    )
    gamma = jnp.where(given_lower, prob.e1, state.gamma)
    rotation = jnp.where(given_lower, jnp.eye(3, dtype=dtype), state.rotation)

    scaling = scaling_at(prob, options, gamma, rotation)
    joint = joint_objective(prob, options, rigid, gamma, rotation, scaling)
    zero_step = zero_registration(prob, rigid, dtype)
    grad_norm = optx.two_norm(jax.grad(joint)((scaling.whitened(final.coefficients), zero_step)))
    rounds_result = RESULTS.where(
        state.shrunk,
        RESULTS.resolution_limited,
        RESULTS.where(rounds.done, RESULTS.successful, RESULTS.nonlinear_max_steps_reached),
    )
    result = RESULTS.where(final.converged, rounds_result, final.result)
    result = RESULTS.where(not_registered, RESULTS.not_registered, result)
    finite = jnp.isfinite(final.energy)
    result = RESULTS.where(finite, result, RESULTS.nonfinite)
    # Math §9's area bound holds for every path between the two surfaces, here with the
    # areas of the path's own end frames (as the energy reads them: a registration that
    # compresses f1 between the grid's points reads less of its area); a distance far
    # below it is lost precision, not a shorter path (float32 with the kernel's earlier,
    # cancelling form ended at 0.0 on a GPU). The slack is well above the quadrature's:
    # concentric spheres, which attain the bound, are within 1 % of it.
    ends = (registered_frame(prob, options, gamma), rotated_end_frame(prob, options, rotation))
    areas = [integrate_interior(area_element(*frame)) for frame in ends]
    bound = jnp.sqrt(2.0 * prob.metric.b) * jnp.abs(jnp.sqrt(areas[1]) - jnp.sqrt(areas[0]))
    lost = finite & (final.distance < _AREA_BOUND_SLACK * bound)
    result = RESULTS.where(lost, RESULTS.below_area_bound, result)
    if options.refinement:
        refinement = _refinement(prob, options, gamma, rotation, final.coefficients, final.energy)
    else:
        nan = jnp.asarray(jnp.nan, dtype)
        refinement = Refinement(nan, nan, nan)
    return ShapeGeodesicResult(
        path=final.path,
        distance=final.distance,
        energy=final.energy,
        parametrized_distance=parametrized.distance,
        f1_registered=final.path[0],
        gamma=gamma,
        rotation=rotation,
        coefficients=final.coefficients,
        parametrized_coefficients=parametrized.coefficients,
        energy_history=history,
        rounds=rounds.rounds,
        num_steps=steps,
        converged=final.converged & rounds.done & ~state.shrunk & ~not_registered & finite & ~lost,
        result=result,
        grad_norm=grad_norm,
        min_curvature=final.min_curvature,
        refinement=refinement,
        levels=None,
    )


@functools.partial(jax.jit, static_argnames=("options", "rigid"))
def _shape_evaluate(
    metric: SplitMetric,
    f1: ArrayLike,
    f2: ArrayLike,
    bases,
    gamma: ArrayLike,
    rotation: ArrayLike,
    coefficients: ArrayLike,
    *,
    options: ShapeOptions,
    rigid: bool,
):
    """The path from f1 o gamma to R f2 with the perturbation C, and its energy."""
    prob = make_problem(metric, f1, f2, bases, rigid, options.interpolation)
    start, end = registered_f1(prob, options, gamma), rotate_surface(rotation, prob.f2)
    path = path_from_coefficients(start, end, coefficients, bases.values, options.n_times)
    return path, path_energy_at(prob, options, gamma, rotation, coefficients)


@functools.partial(jax.jit, static_argnames=("options", "rigid"))
def shape_finish(
    metric: SplitMetric,
    g1: ArrayLike,
    g2: ArrayLike,
    bases,
    solved: ShapeGeodesicResult,
    units: Units,
    *,
    options: ShapeOptions,
    rigid: bool,
) -> ShapeGeodesicResult:
    """The result in the user's units from the solve's: the path and its energy evaluated
    again at the solution (differentiably, see shape_geodesic), then the units restored.
    One compiled program: op by op, a first call would compile each operation alone."""
    gamma, rotation, coefficients = (
        jax.lax.stop_gradient(x) for x in (solved.gamma, solved.rotation, solved.coefficients)
    )
    path, energy = _shape_evaluate(
        metric, g1, g2, bases, gamma, rotation, coefficients, options=options, rigid=rigid
    )
    # A distance that lost its precision (end_phase) is not reported as a number.
    energy = jnp.where(solved.result == RESULTS.below_area_bound, jnp.nan, energy)
    parametrized_distance = solved.parametrized_distance
    if options.stretch_fraction > 0.0:
        # The geodesics' solves integrate by the nodes; the reported distance adds the
        # stretched cells' finer rule, and so does the parametrized distance it is
        # bounded by (the pair as given, gamma = id and R = I).
        e1 = sphere_points(*solved.gamma.shape[-2:], solved.gamma.dtype)
        _, parametrized_energy = _shape_evaluate(
            metric,
            g1,
            g2,
            bases,
            e1,
            jnp.eye(3, dtype=e1.dtype),
            jax.lax.stop_gradient(solved.parametrized_coefficients),
            options=options,
            rigid=rigid,
        )
        parametrized_distance = safe_sqrt(parametrized_energy)
    unit_result = solved._replace(
        path=path,
        f1_registered=path[0],
        energy=energy,
        distance=safe_sqrt(energy),
        parametrized_distance=parametrized_distance,
    )
    return _restore_shape_units(unit_result, units, rigid)


def _restore_shape_units(
    result: ShapeGeodesicResult, units: Units, rigid: bool
) -> ShapeGeodesicResult:
    """A result solved in ``units`` in the user's units again. Modulo "rigid" the solve
    centres both surfaces, so the path is only scaled back; modulo "diff" it is also
    moved back to the inputs' place."""
    s = units.scale

    def surfaces(x: ArrayLike):
        return x * s if rigid else units.restore(x)

    return result._replace(
        path=surfaces(result.path),
        distance=result.distance * s,
        energy=result.energy * s**2,
        parametrized_distance=result.parametrized_distance * s,
        f1_registered=surfaces(result.f1_registered),
        coefficients=result.coefficients * s,
        parametrized_coefficients=result.parametrized_coefficients * s,
        energy_history=result.energy_history * s**2,
        refinement=result.refinement._replace(
            distance_time=result.refinement.distance_time * s,
            distance_grid=result.refinement.distance_grid * s,
        ),
    )
