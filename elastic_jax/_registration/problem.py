"""The registration problem and the arithmetic its phases share.

One record holds the metric, the two surfaces and the bases; the functions here step a
reparametrization gamma (math §6), turn f2 by R, take the frames of f1 o gamma and R f2,
and evaluate the matching criteria and the path energy (math §4) the phases minimize.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import DTypeLike
from jaxtyping import Array, ArrayLike

from .._geodesics.geodesic import solve_path, solver_scaling
from .._geometry.bases import Bases, frames_between, perturbed_frames
from .._geometry.composition import chain_frame, compose, on_grid, rotate_surface
from .._geometry.differential import interior_frame
from .._geometry.energy import frame_energy
from .._geometry.grid import (
    interior_weights,
    sphere_points,
)
from .._geometry.metric import SplitMetric
from .._geometry.reparam import (
    jacobian_determinant_unchecked,
    reparametrize_unchecked,
    spline_coefficients,
    spline_upsample,
)
from .._geometry.so3 import so3_exp_unchecked
from .._geometry.srnf import center_unchecked
from .._options import ShapeOptions
from .stretch import chosen_cells, stretch_correction

# Shrink factors tried for a reparametrization step, largest first; 0 keeps gamma.
_STEP_SCALES = (1.0, 0.5, 0.25, 0.125, 0.0625, 0.0)


def into_ball(b: Array, radius: Array) -> Array:
    """b -> radius tanh(|b|) b / |b|: R^3 onto the open ball of that radius, smooth at 0."""
    t2 = jnp.sum(b * b)
    small = t2 < np.sqrt(np.finfo(b.dtype).eps)
    # Safe where: tanh(t)/t's series below sqrt(eps), so no 0/0 reaches the gradient.
    t = jnp.sqrt(jnp.where(small, 1.0, t2))
    return radius * b * jnp.where(small, 1.0 - t2 / 3.0, jnp.tanh(t) / t)


# BFGS steps per round of the L2 matching of every start.
MATCH_STEPS = 30


def _step_field(y: ArrayLike, bases: Bases, e1: ArrayLike):
    """Proj(Id + sum_k y_k s_k v_k) (math §6), s_k = 1 / sqrt(l(l+1)).

    The sum in the fields' separable form (harmonics.FieldTables): value and gradient of
    the step at degree 8 took 0.56, 4.8 and 40 ms at 25 x 49, 49 x 97 and 97 x 193 with the
    dense (Lbar, 3, m, n) fields (2 cores), memory-bound on reading them."""
    y = y * bases.field_scale
    along = jnp.einsum("aik,k,akg->aig", bases.field_rows, y, bases.field_select)
    along = jnp.einsum("aig,gj->aij", along, bases.field_trig)
    w = e1 + jnp.einsum("aij,acij->cij", along, bases.field_frames)
    poles = jnp.einsum("k,kcpj->cpj", y, bases.field_poles)
    w = w.at[:, 0].add(poles[:, 0]).at[:, -1].add(poles[:, 1])
    return w / jnp.linalg.norm(w, axis=-3, keepdims=True)


def are_resolved(gammas: ArrayLike, floor: ArrayLike):
    """Whether each of ``gammas (..., 3, m, n)`` is a diffeomorphism the grid resolves.

    J > 0 at every grid point, and the discrete area of the reparametrized unit sphere
    (the integral of J) at least ``floor`` (:func:`~elastic_jax._geometry.bases.resolution_np`).
    """
    jac = jacobian_determinant_unchecked(gammas)
    m, n = gammas.shape[-2:]
    area = jnp.einsum("...ij,ij->...", jac[..., 1:-1, :-1], interior_weights(m, n, jac.dtype))
    return (jnp.min(jac, axis=(-2, -1)) > 0) & (area >= floor)


def safe_update(prob: Problem, options: ShapeOptions, gamma: ArrayLike, y: ArrayLike):
    """The largest shrink of the step whose composition with gamma stays resolved, and
    whether the step had to shrink.

    The shrinks are tried one after the other (a loop, not one candidate per shrink in
    the program): the first usually passes, and each candidate is a bicubic composition
    whose kernels would otherwise be compiled six times over at each of three call sites.
    """
    bases = prob.bases
    scales = jnp.asarray(_STEP_SCALES, y.dtype)
    last = len(_STEP_SCALES) - 1

    def candidate(i: ArrayLike):
        step = _step_field(scales[i] * y, bases, prob.e1)
        return compose(gamma, step, options.interpolation)

    def usable(i: ArrayLike, g: ArrayLike):
        # The last shrink (scale 0) is gamma itself, which is valid.
        return are_resolved(g, bases.area_floor) | (i == last)

    def next_shrink(carry: tuple):
        i, _, _ = carry
        g = candidate(i + 1)
        return i + 1, g, usable(i + 1, g)

    first = candidate(0)
    start = (jnp.zeros((), jnp.int32), first, usable(0, first))
    index, chosen, _ = jax.lax.while_loop(lambda c: ~c[2], next_shrink, start)
    return chosen, index > 0


class Problem(NamedTuple):
    """The traced data of one solve: metric, surfaces (centered when rigid), bases.

    ``f1``, ``f2`` are the surfaces on the working grid (the bases' grid, whose points
    are ``e1``); ``source1``, ``source2`` are the inputs on their own grids, whose
    interpolants f1 o gamma and the chain rule's differentials read (math §10: an input
    stands for its interpolant, the working grid discretizes the path). On one grid they
    are the same arrays (with ``interpolation="spline"`` the sources hold their spline's
    coefficients: read them with source_method).
    """

    metric: SplitMetric
    f1: Array
    f2: Array
    e1: Array
    bases: Bases
    source1: Array
    source2: Array


class State(NamedTuple):
    gamma: Array
    rotation: Array
    coefficients: Array
    energy: Array
    steps: Array
    shrunk: Array  # () bool: the (last) round's step had to shrink to stay resolved


def source_method(interpolation: str) -> str:
    """How a Problem's sources are read: a spline's coefficients are computed once, in
    make_problem, not in every evaluation of an objective."""
    return "coefficients" if interpolation == "spline" else interpolation


def registered_f1(prob: Problem, options: ShapeOptions, gamma: ArrayLike):
    return reparametrize_unchecked(prob.source1, gamma, method=source_method(options.interpolation))


def gamma_source(options: ShapeOptions, gamma: ArrayLike):
    """gamma as a round's objective reads it, for :func:`stepped_gamma`: with spline
    reads its spline's coefficients, computed once per round instead of in each
    evaluation (the same numbers; 25 x 49, degree 7 / 8: the step's value and gradient
    0.97 -> 0.80 ms)."""
    return spline_coefficients(gamma) if options.interpolation == "spline" else gamma


def stepped_gamma(prob: Problem, options: ShapeOptions, source: ArrayLike, x: ArrayLike):
    """gamma o Proj(Id + sum x_k v_k): the reparametrization after one more Diff step,
    gamma given by ``source = gamma_source(options, gamma)``."""
    step = _step_field(x, prob.bases, prob.e1)
    return compose(source, step, source_method(options.interpolation))


def frame_of(f: ArrayLike, gamma: ArrayLike, options: ShapeOptions):
    """The differential of f o gamma on gamma's interior points (options.differential), for a
    Problem's source f (read by source_method)."""
    read = source_method(options.interpolation)
    if options.differential == "grid":
        return interior_frame(reparametrize_unchecked(f, gamma, method=read))
    return chain_frame(f, gamma, options.interpolation, read)


def quadrature_gamma(prob: Problem, options: ShapeOptions, gamma: ArrayLike):
    """gamma at the nodes of the energy's quadrature: itself with ``options.quadrature``
    1, else read through its interpolant at the finer grid's points (bases.quad_points):
    gamma stays a function of the working grid, the energy sees it between the nodes."""
    if options.quadrature_factor == 1:
        return gamma
    if options.interpolation == "spline":
        g = spline_upsample(gamma, options.quadrature_factor)
        return g / jnp.linalg.norm(g, axis=-3, keepdims=True)
    return compose(gamma, prob.bases.quad_points, options.interpolation)


def refined_frames(straight: Sequence[Array], prob: Problem, coefficients: ArrayLike):
    """The frames of the straight line ``straight`` (on the refinement grid) plus the
    path's perturbation sum_j C[k, j] S_j, the harmonics' differentials taken on that
    grid by math §2's differences of their separable samples (no (K, 2 P) table).

    One interior time at a time (lax.map): at 97 x 193 levels the grid is 385 x 769.
    """
    rows, columns = prob.bases.fine_rows, prob.bases.fine_columns
    n_inner = straight[0].shape[0] - 2
    c = jnp.reshape(coefficients, (n_inner, 3, rows.shape[0]))

    def perturbation(ck):
        surface = jnp.einsum("ck,ki->cik", ck, rows) @ columns  # never (3, K, M', N')
        return interior_frame(surface)

    p1, p2 = jax.lax.map(perturbation, c)
    s1, s2 = straight
    return s1.at[1:-1].add(p1), s2.at[1:-1].add(p2)


def path_dframe(prob: Problem, options: ShapeOptions):
    """The path harmonics' differentials ``(K, 2 P)`` on the quadrature's interior nodes."""
    return prob.bases.dframe if options.quadrature_factor == 1 else prob.bases.quad_dframe


def registered_frame(prob: Problem, options: ShapeOptions, gamma: ArrayLike):
    """The differential of f1 o gamma on the quadrature's interior nodes."""
    return frame_of(prob.source1, quadrature_gamma(prob, options, gamma), options)


def rotated_end_frame(prob: Problem, options: ShapeOptions, rotation: ArrayLike):
    """The differential of R f2 (interior points), taken as f1 o gamma's at the identity:
    identical inputs then have identical frames."""
    if options.differential == "grid":
        frame = interior_frame(prob.f2)
    else:
        # At the identity read as f1 o gamma's are: the same points, the same frames.
        frame = frame_of(prob.source2, quadrature_gamma(prob, options, prob.e1), options)
    return tuple(rotate_surface(rotation, a) for a in frame)


def identity_frames(prob: Problem, options: ShapeOptions):
    """(f1's frame, f2's frame): the straight line without registration."""
    if options.differential == "grid":  # the surfaces themselves, not read back at their points
        return interior_frame(prob.f1), interior_frame(prob.f2)
    eye = jnp.eye(3, dtype=prob.f1.dtype)
    return registered_frame(prob, options, prob.e1), rotated_end_frame(prob, options, eye)


def geodesic_options(options: ShapeOptions):
    return {
        "n_times": options.n_times,
        "solver": options.solver,
        "max_steps": options.max_steps,
        "tol": options.tol,
        "scheme": options.scheme,
    }


def geodesic_at(
    prob: Problem, options: ShapeOptions, gamma: ArrayLike, rotation: ArrayLike, init: ArrayLike
):
    """The parametrized geodesic from f1 o gamma to R f2, warm-started at ``init``."""
    return solve_path(
        prob.metric,
        registered_f1(prob, options, gamma),
        rotate_surface(rotation, prob.f2),
        init,
        prob.bases.values,
        path_dframe(prob, options),
        **geodesic_options(options),
        frames=(registered_frame(prob, options, gamma), rotated_end_frame(prob, options, rotation)),
    )


def straight_line_energy(
    prob: Problem,
    options: ShapeOptions,
    start_frame: Sequence[ArrayLike],
    end_frame: Sequence[ArrayLike],
):
    """The straight line's energy between two ends given by their frames."""
    # Ranking and refining straight lines needs no time resolution: 3 time points
    # (4.5x cheaper than N = 10) order the candidates the same way.
    frames = frames_between(start_frame, end_frame, 3)
    return frame_energy(prob.metric, *frames, options.scheme)


def l2_mismatch(start: ArrayLike, end: ArrayLike):
    """int |start - end|^2 dsigma over the round sphere, for ``(3, m, n)`` surfaces."""
    m, n = start.shape[-2:]
    gap = jnp.sum((start - end)[:, 1:-1, :-1] ** 2, axis=0)
    return jnp.sum(gap * interior_weights(m, n, start.dtype))


def registration_variables(prob: Problem, y: ArrayLike, rigid: bool):
    """Split the registration variables into the Diff step's x and R^3's rotation step."""
    n_fields = prob.bases.field_scale.shape[0]
    x = y[:n_fields]
    r_step = so3_exp_unchecked(y[n_fields:]) if rigid else jnp.eye(3, dtype=y.dtype)
    return x, r_step


def joint_objective(
    prob: Problem,
    options: ShapeOptions,
    rigid: bool,
    gamma: ArrayLike,
    rotation: ArrayLike,
    scaling,
):
    """Energy / scale as a function of (whitened path coefficients z, registration step y)."""
    frames_of_variables = joint_frames(prob, options, rigid, gamma, rotation, scaling)
    # The cells integrated finer are those of the round's gamma: fixed within a round,
    # as a quadrature's nodes are.
    cells = stretched_cells_of(prob, options, gamma)

    def objective(variables: tuple):
        frames, stepped, turned = frames_of_variables(variables)
        energy = frames_energy_by_rule(prob, options, frames, stepped, turned, cells)
        return energy / scaling.energy_scale

    return objective


def joint_frames(
    prob: Problem,
    options: ShapeOptions,
    rigid: bool,
    gamma: ArrayLike,
    rotation: ArrayLike,
    scaling,
):
    """The rounds' variables (whitened path coefficients z, registration step y) ->
    (the path's interior frames on the quadrature's nodes, the stepped gamma, the turned
    R): what :func:`joint_objective` integrates."""
    end_frame = rotated_end_frame(prob, options, rotation)
    source = gamma_source(options, gamma)

    def frames_of_variables(variables: tuple):
        z, y = variables
        x, r_step = registration_variables(prob, y, rigid)
        stepped = stepped_gamma(prob, options, source, x)
        start = registered_frame(prob, options, stepped)
        end = [rotate_surface(r_step, a) for a in end_frame]
        straight = frames_between(start, end, options.n_times)
        coefficients = scaling.coefficients(z)
        frames = perturbed_frames(straight, coefficients, path_dframe(prob, options))
        return frames, stepped, r_step @ rotation

    return frames_of_variables


def stretched_cells_of(prob: Problem, options: ShapeOptions, gamma: ArrayLike):
    """The quadrature grid's cells where gamma stretches most, with R f2's sub-frames
    there (stretch.chosen_cells), None without ``options.stretch_quadrature``: chosen
    from gamma at the quadrature's nodes, so that with ``options.quadrature`` q > 1 the
    finer cells are those of the finer grid."""
    if options.stretch_fraction == 0.0:
        return None
    return chosen_cells(
        quadrature_gamma(prob, options, gamma),
        options.stretch_fraction,
        prob.source2,
        source_method(options.interpolation),
        options.interpolation,
        working_grid(prob.bases),
        options.stretch_subdivision,
    )


def frames_energy_by_rule(
    prob: Problem,
    options: ShapeOptions,
    frames: tuple,
    gamma: ArrayLike,
    rotation: ArrayLike,
    cells: tuple | None,
):
    """The energy of the path with these frames: the node rule, plus the stretched
    cells' finer quadrature less their node-rule share when ``cells`` (stretch.py)."""
    energy = frame_energy(prob.metric, *frames, options.scheme)
    if cells is None:
        return energy
    return energy + stretch_correction(
        prob.metric,
        prob.source1,
        source_method(options.interpolation),
        options.interpolation,
        gamma,
        rotation,
        frames,
        cells,
        options.stretch_subdivision,
    )


def scaling_at(prob: Problem, options: ShapeOptions, gamma: ArrayLike, rotation: ArrayLike):
    return solver_scaling(
        prob.metric,
        registered_f1(prob, options, gamma),
        rotate_surface(rotation, prob.f2),
        path_dframe(prob, options),
        options.n_times,
        options.scheme,
        (registered_frame(prob, options, gamma), rotated_end_frame(prob, options, rotation)),
    )


def zero_registration(prob: Problem, rigid: bool, dtype: DTypeLike):
    return jnp.zeros(prob.bases.field_scale.shape[0] + (3 if rigid else 0), dtype)


def path_frames_at(
    prob: Problem,
    options: ShapeOptions,
    gamma: ArrayLike,
    rotation: ArrayLike,
    coefficients: ArrayLike,
):
    """The frames (a1, a2), each ``(N, 3, M - 2, N' - 1)`` on the quadrature's grid
    (the working grid with ``options.quadrature`` 1), of the straight line from
    f1 o gamma to R f2 plus the perturbation: the path as the solve sees it."""
    start, end = registered_frame(prob, options, gamma), rotated_end_frame(prob, options, rotation)
    straight = frames_between(start, end, options.n_times)
    return perturbed_frames(straight, coefficients, path_dframe(prob, options))


def path_energy_at(
    prob: Problem,
    options: ShapeOptions,
    gamma: ArrayLike,
    rotation: ArrayLike,
    coefficients: ArrayLike,
):
    """Energy of the straight line from f1 o gamma to R f2 plus the perturbation; with
    ``options.stretch_quadrature``, the cells where gamma stretches most integrated
    ``options.stretch_subdivision`` times finer (stretch.py)."""
    frames = path_frames_at(prob, options, gamma, rotation, coefficients)
    cells = stretched_cells_of(prob, options, gamma)
    return frames_energy_by_rule(prob, options, frames, gamma, rotation, cells)


def matching_criterion(prob: Problem, options: ShapeOptions, weight: ArrayLike):
    """weight * L2 position mismatch + (1 - weight) * straight-line energy (3 time points).

    The L2 mismatch int |f1 o gamma - R f2|^2 dsigma has no derivatives of the surfaces
    in it, so its landscape over gamma is far smoother than the elastic energy's: from a
    wrong basin it finds the right correspondence where the energy cannot (cat1 against
    itself under two large Diff steps: the energy stalled at 0.63, the L2 rounds found the
    map to 0.017 rad). It only initializes: the rounds that follow minimize the energy.
    """

    def criterion(gamma: ArrayLike, rotation: ArrayLike):
        l2 = l2_mismatch(registered_f1(prob, options, gamma), rotate_surface(rotation, prob.f2))
        frames = registered_frame(prob, options, gamma), rotated_end_frame(prob, options, rotation)
        return weight * l2 + (1.0 - weight) * straight_line_energy(prob, options, *frames)

    return criterion


def iterate(
    round_fn: Callable,
    state: tuple,  # a State, or a record with its fields and more (rounds' _Warm)
    max_rounds: int,
    small_change: Callable,
    history: Array | None = None,
):
    """Rounds until one changes the energy little, or max_rounds; never a rising energy.

    ``small_change(before, after, earlier)`` is given the energies before and after the
    round and the one before the round before (inf in the first round).

    Returns (state, history, rounds taken, whether the last round met small_change or
    was refused); ``state.shrunk`` says whether the last round's step had to shrink.
    ``history`` (optional) gets each round's energy at index 2 + round.
    """
    if history is None:
        history = jnp.zeros((max_rounds + 2,), state.energy.dtype)

    def keep_going(carry: tuple):
        _, _, k, done, _ = carry
        return (k < max_rounds) & ~done

    def body(carry: tuple):
        state, history, k, _, earlier = carry
        new = round_fn(state)
        # A round whose step had to shrink can end higher: keep the better registration
        # (no round may raise the energy), and stop there.
        better = new.energy <= state.energy
        kept = jax.tree_util.tree_map(lambda a, b: jnp.where(better, a, b), new, state)
        # The last round's shrink is kept whether or not the round was: rounds that end
        # shrunk ended at the edge of what the grid resolves, not at a minimum.
        kept = kept._replace(steps=new.steps, shrunk=new.shrunk)
        done = ~better | small_change(state.energy, kept.energy, earlier)
        return kept, history.at[k + 2].set(kept.energy), k + 1, done, state.energy

    inf = jnp.full((), jnp.inf, state.energy.dtype)
    start = (state, history, jnp.zeros((), jnp.int32), jnp.asarray(max_rounds == 0), inf)
    return jax.lax.while_loop(keep_going, body, start)[:4]


def zero_coefficients(prob: Problem, options: ShapeOptions):
    return jnp.zeros((options.n_times - 2, prob.bases.dframe.shape[0] * 3), prob.f1.dtype)


def working_grid(bases: Bases) -> tuple[int, int]:
    """The working grid (m, n) of a solve: the grid of its bases."""
    return tuple(bases.field_frames.shape[-2:])


def make_problem(
    metric: SplitMetric,
    f1: ArrayLike,
    f2: ArrayLike,
    bases: Bases,
    rigid: bool,
    interpolation: str = "bicubic",
) -> Problem:
    """The problem on the bases' working grid; f1, f2 on their own grids (math §10)."""
    m, n = working_grid(bases)
    if rigid:
        f1, f2 = center_unchecked(f1), center_unchecked(f2)
    e1 = sphere_points(m, n, f1.dtype)
    w1, w2 = on_grid(f1, e1, interpolation), on_grid(f2, e1, interpolation)
    if interpolation == "spline":
        f1, f2 = spline_coefficients(f1), spline_coefficients(f2)
    return Problem(metric, w1, w2, e1, bases, f1, f2)
