"""Learning the split metric's coefficients from data (the paper's introduction: "choose
the constants of the metric in a data driven way").

The distances d_ij(a, b, c, d) of a collection are minima over paths (and
registrations) of an energy that is linear in the coefficients (math §3, 4):
E_ij(w) = sum_k w_k E_ij^k at the optimal path, where E_ij^k is the energy of that path
under the k-th coefficient alone. By the envelope theorem the derivative of d_ij in w is
that of sqrt(E_ij(w)) with the path and registration held, so one batched solve of all
pairs gives an objective's value and exact gradient, and a model of it around the current
coefficients (the held paths' energies, cheap to evaluate for any w). The fit is a trust
region method on that model: minimize the model within a box around the coefficients,
solve the pairs again there (warm-started from the held solutions), accept the step if the
objective went down, and adjust the box by how well the model predicted it.

Resolved distances (the solves' ``rtol``, math §10): the first solve resolves each pair by
levels of working grids; the held registration and path of a pair are those of its finest
level, and every later solve continues them on that grid. So the gradient is the envelope
derivative of the resolved distances, each at its own finest level.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._checks import check_choice, check_int, check_positive
from .._errors import InputError
from .._geodesics.solvers import minimize
from .._geometry.bases import basis_np, frames_between, make_bases, perturbed_frames
from .._geometry.differential import interior_frame
from .._geometry.energy import frame_energy
from .._geometry.metric import SplitMetric
from .._geometry.numerics import safe_sqrt
from .._options import ShapeOptions
from .._registration.problem import make_problem, path_energy_at
from .._results import RESULTS, status_record
from .batching import (
    check_collection,
    chunk_bounds,
    default_chunk,
    job_settings,
    registered_chunk,
)
from .checkpoints import fingerprint_of
from .driver import JobOptions, check_job, run
from .retrieval import check_distances, check_labels

# The least share of a learned coefficient in a + b + c + d = 1 (times the learned
# coefficients' total share): a, b, c stay positive, as the metric needs, and a
# coefficient the data do not want ends at this floor instead of running off to zero.
FLOOR = 1e-3

# Trust region radius (in the log of the coefficients): start, largest, and the one below
# which a step that still does not lower the objective ends the fit as stalled.
_RADIUS = (0.5, 4.0, 1e-3)

OBJECTIVES = ("nca", "stress")
COEFFICIENTS = "abcd"


@status_record
class MetricFit(NamedTuple):
    """A split metric fitted to a collection (:func:`fit_metric`).

    Attributes:
        metric: the fitted :class:`SplitMetric`, normalized to a + b + c + d = 1.
        initial_metric: the metric the fit started from, normalized the same way.
        objective_before: ``()`` the objective at ``initial_metric``.
        objective_after: ``()`` the objective at ``metric``.
        history: ``(max(max_steps, num_steps) + 1,)`` the objective at the start and after
            each step (a rejected step repeats the value; NaN for steps not taken).
        grad_norm: ``()`` 2-norm of the objective's gradient in the log of the learned
            coefficients at ``metric`` (envelope derivative, paths and registrations held).
        gradient: ``(4,)`` the objective's derivatives in (a, b, c, d) at ``metric``
            (envelope derivative); orthogonal to (a, b, c, d), as the objective is
            invariant under scaling the metric.
        distances: ``(K, K)`` the distance matrix at ``metric``.
        distances_before: ``(K, K)`` the distance matrix at ``initial_metric``.
        pairs_converged: ``(K, K)`` bool, each pair's solve at ``metric`` (diagonal True).
        grids: ``(K, K, 2)`` the working grid each pair is solved on (its finest level's
            when resolved, else the collection's; 0 on the diagonal).
        converged: ``()`` grad_norm <= tol.
        result: ``successful``, ``nonlinear_max_steps_reached`` (max_steps ran out),
            ``stalled`` (the trust region shrank below 1e-3 without a lower objective) or
            ``nonfinite`` (the objective at the metric is not finite).
        num_steps: ``()`` trust region steps taken (accepted or not).
        evaluations: ``()`` batched solves of all pairs (one per step, plus the first).
    """

    metric: SplitMetric
    initial_metric: SplitMetric
    objective_before: Float[Array, ""]
    objective_after: Float[Array, ""]
    history: Float[Array, " S"]
    grad_norm: Float[Array, ""]
    gradient: Float[Array, " 4"]
    distances: Float[Array, "K K"]
    distances_before: Float[Array, "K K"]
    pairs_converged: Bool[Array, "K K"]
    grids: Int[Array, "K K 2"]
    evaluations: Int[Array, ""]
    converged: Bool[Array, ""]
    result: RESULTS
    num_steps: Int[Array, ""]


def normalized(metric: SplitMetric) -> np.ndarray:
    """The coefficients (a, b, c, d) of a metric with concrete float leaves, over their sum."""
    values = np.asarray([float(getattr(metric, k)) for k in COEFFICIENTS])
    return values / values.sum()


def weights_of(theta: Array, fixed: Array, free: tuple[int, ...]) -> Array:
    """The coefficients (a, b, c, d), summing to 1, from the learned ones' parameters.

    ``fixed (4,)``: the held coefficients' shares (zero at the learned positions);
    ``theta (F,)``: the learned ones are (1 - sum fixed) (FLOOR + (1 - F FLOOR) softmax(theta)).
    """
    share = 1.0 - jnp.sum(fixed)
    learned = share * (FLOOR + (1.0 - len(free) * FLOOR) * jax.nn.softmax(theta))
    return fixed.at[jnp.asarray(free)].set(learned)


def initial_theta(start: np.ndarray, free: tuple[int, ...]) -> np.ndarray:
    """theta with weights_of(theta) = the start's learned shares, each raised to 2 FLOOR."""
    share = np.asarray(start)[list(free)]
    share = np.maximum(share / share.sum(), 2.0 * FLOOR)
    share = share / share.sum()
    return np.log((share - FLOOR) / (1.0 - len(free) * FLOOR))


def _pair_matrix(values: Array, rows, cols, k: int) -> Array:
    matrix = jnp.zeros((k, k), values.dtype).at[rows, cols].set(values)
    return matrix + matrix.T


def nca_loss(d: Array, same: Array, rows, cols, temperature) -> Array:
    """Soft nearest neighbours' loss (NCA, Goldberger et al. 2004, in its log form).

    The distances ``d (P,)`` (the upper triangle's pairs ``rows, cols``) over their mean,
    p_ij = softmax_j (-D_ij^2 / temperature) over j != i, and the loss
    -(1/K) sum_i log sum_{j in i's class, j != i} p_ij: the mean log-probability that a
    shape's soft nearest neighbour is a classmate. Invariant under scaling every distance.
    """
    k = same.shape[0]
    scaled = _pair_matrix(d / jnp.mean(d), rows, cols, k)
    eye = jnp.eye(k, dtype=bool)
    logits = jnp.where(eye, -jnp.inf, -(scaled**2) / temperature)
    log_p = jax.nn.log_softmax(logits, axis=1)
    classmates = jnp.where(same & ~eye, log_p, -jnp.inf)
    return -jnp.mean(jax.nn.logsumexp(classmates, axis=1))


def stress_loss(d: Array, targets: Array) -> Array:
    """1 - cos^2 between the distances ``d (P,)`` and the targets ``(P,)``: the residual
    min_s |d - s t|^2 / |d|^2 of the best scale s. 0 exactly when d is proportional to t;
    invariant under scaling either."""
    return 1.0 - jnp.dot(d, targets) ** 2 / (jnp.dot(d, d) * jnp.dot(targets, targets))


def _loss_at(parts, w, data, *, objective, k):
    """The objective at the held paths: parts ``(P, 4)`` (E_ij^k), coefficients ``w (4,)``."""
    d = safe_sqrt(parts @ w)
    rows, cols = np.triu_indices(k, 1)
    if objective == "nca":
        same, temperature = data
        return nca_loss(d, same, rows, cols, temperature)
    return stress_loss(d, data)


def _loss(parts, theta, data, fixed, *, objective, free, k):
    return _loss_at(parts, weights_of(theta, fixed, free), data, objective=objective, k=k)


@functools.partial(jax.jit, static_argnames=("objective", "free", "k"))
def _value_and_grad(parts, theta, data, fixed, *, objective, free, k):
    return jax.value_and_grad(_loss, argnums=1)(
        parts, theta, data, fixed, objective=objective, free=free, k=k
    )


@functools.partial(jax.jit, static_argnames=("objective", "k"))
def _coefficient_gradient(parts, w, data, *, objective, k):
    return jax.grad(_loss_at, argnums=1)(parts, w, data, objective=objective, k=k)


@functools.partial(jax.jit, static_argnames=("objective", "free", "k"))
def _model_step(parts, theta, radius, data, fixed, tol, *, objective, free, k):
    """The minimum of the model (the objective at the held paths) over the box
    |theta' - theta| <= radius (componentwise; theta' = theta + radius tanh(u)): the new
    theta, the model's predicted decrease, and whether the step reached the box's edge."""

    def model(u):
        return _loss(
            parts, theta + radius * jnp.tanh(u), data, fixed, objective=objective, free=free, k=k
        )

    found = minimize(model, jnp.zeros_like(theta), solver="bfgs", max_steps=200, tol=tol)
    step = radius * jnp.tanh(found.x)
    edge = jnp.max(jnp.abs(step)) >= 0.9 * radius
    return theta + step, model(jnp.zeros_like(theta)) - model(found.x), edge


@functools.partial(jax.jit, static_argnames=("options", "modulo"))
def energy_parts(first, second, gammas, rotations, coefficients, bases, *, options, modulo):
    """E_ij^k: the energies of the held paths under each coefficient alone, ``(b, 4)``.

    first, second ``(b, 3, m, n)``; gammas ``(b, 3, m, n)``, rotations ``(b, 3, 3)``,
    coefficients ``(b, N - 2, L)`` the solutions (in the surfaces' own units). modulo
    "none": the path from first to second perturbed by C (as geodesic evaluates it);
    else the path from first o gamma to R second (as shape_geodesic does, math §4).
    The energy is linear in the metric, so E(w) = parts @ w for every w.
    """
    units = SplitMetric(*jnp.eye(4, dtype=first.dtype))

    def one(a, b, gamma, rotation, c):
        def energy(metric):
            if modulo == "none":
                frames = frames_between(interior_frame(a), interior_frame(b), options.n_times)
                return frame_energy(metric, *perturbed_frames(frames, c, bases), options.scheme)
            prob = make_problem(metric, a, b, bases, modulo == "rigid", options.interpolation)
            return path_energy_at(prob, options, gamma, rotation, c)

        return jax.vmap(energy)(units)

    return jax.vmap(one)(first, second, gammas, rotations, coefficients)


class _Held(NamedTuple):
    """One batched solve of all pairs at a metric: what the model holds."""

    parts: np.ndarray  # (P, 4)
    # (gammas, rotations, coefficients), each a list of P arrays: a resolved pair's
    # gamma is on the grid of its finest level, which differs between pairs.
    starts: tuple
    converged: np.ndarray  # (P,)


def fit_metric(
    shapes: Float[ArrayLike, "K 3 m n"],
    labels: ArrayLike | None = None,
    *,
    targets: Float[ArrayLike, "K K"] | None = None,
    modulo: str = "rigid",
    options: ShapeOptions | None = None,
    init: SplitMetric | None = None,
    objective: str | None = None,
    learn: str = "abc",
    temperature: float = 0.1,
    max_steps: int = 30,
    tol: float = 1e-3,
    job: JobOptions | None = None,
) -> MetricFit:
    """Fit the split metric's coefficients to labels or to target dissimilarities.

    Objectives (both invariant under scaling the distances, so under scaling the shapes
    and the metric):

    - ``"nca"`` (with ``labels``): soft nearest neighbours (``nca_loss()``): makes each
      shape's nearest shapes its classmates, the differentiable surrogate of
      leave-one-out nearest-neighbour classification.
    - ``"stress"`` (with ``targets``, e.g. expert ratings): 1 - cos^2 between the
      distances and the targets over the pairs i < j (``stress_loss()``).

    Normalization: distances scale with the square root of the metric, so only the
    coefficients' ratios are learned; the result has a + b + c + d = 1. The coefficients
    in ``learn`` move (each keeps at least FLOOR = 1e-3 of their total share, so a, b, c
    stay positive); the others keep their share of ``init``.

    Method: the envelope theorem gives the exact gradient of every distance in the
    coefficients with the solved paths and registrations held, and the held paths'
    energies are linear in the coefficients (module docstring). Each step minimizes that
    model over a box of radius r in log-coefficients (BFGS), solves all K(K-1)/2 pairs at
    the new coefficients, warm-started from the held solutions (for modulo "diff" and
    "rigid" the registrations: the start search runs at the first solve only; for
    "none" the path coefficients), and accepts the step when the objective went down. r
    starts at 0.5, doubles after a well-predicted step to the box's edge, and shrinks by 4
    after a poor one. Converged: the gradient's 2-norm in the log-coefficients <= tol.

    Args:
        shapes: ``(K, 3, m, n)`` on one grid, K >= 3.
        labels: ``(K,)`` class ids (at least two classes, two shapes in each); or
        targets: ``(K, K)`` symmetric, non-negative dissimilarities (diagonal unused).
        modulo: ``"rigid"``, ``"diff"`` or ``"none"`` (parametrized geodesics).
        options: the solves' :class:`ShapeOptions` (its defaults when None). As in
            :func:`distance_matrix`: modulo "diff" / "rigid" with ``rtol`` (the default)
            resolves each pair by levels at the first solve, and the steps continue each
            pair on its finest level's grid; ``rtol=None`` (or ``grid`` the collection's)
            solves on the collection's grid, as modulo "none" always does.
        init: the metric to start from (default ``SplitMetric(1, 1, 0.1, 0)``).
        objective: ``"nca"`` or ``"stress"``; default: the one the data given calls for.
        learn: which coefficients move, a string of at least two of ``"abcd"``.
        temperature: NCA's softness, in units of the squared mean distance.
        max_steps: trust region steps at most (each one batched solve of all pairs).
        tol: the gradient norm that ends the fit.
        job: how the job runs (:class:`JobOptions`): the pairs are batched as in
            :func:`distance_matrix` (``batch_size``, ``strategy``; on a cluster every
            step's pairs are tasks on its workers, the numbers equal the in-process
            ones). The checkpoint is written after the first solve of all pairs and after
            every step (the coefficients, the trust region, the held solutions); a resume
            is refused if it belongs to other shapes, labels, targets or settings
            (``max_steps`` may differ), and a fit killed during a step loses that step's
            solves only. ``progress`` hears after each step: step, objective, grad_norm,
            metric (a, b, c, d), radius, accepted, seconds.

    Returns:
        :class:`MetricFit`. A fit that did not converge also warns
        (:class:`ConvergenceWarning`).

    Raises:
        InputError: labels and targets both or neither given, labels of the wrong length,
            with NaN or a class of one shape or one class only, targets not square,
            symmetric, finite and non-negative, ``learn`` not two or more of "abcd".
    """
    job = check_job(job)
    shapes, options = check_collection(
        shapes, options, modulo, levels=modulo != "none", function="fit_metric"
    )
    if modulo == "none":
        options = options.replace(rtol=None)
    k = shapes.shape[0]
    if k < 3:
        raise InputError(f"fit_metric needs at least 3 shapes; got {k}")
    if (labels is None) == (targets is None):
        raise InputError("fit_metric: give labels (classes) or targets (dissimilarities), one")
    if objective is None:
        objective = "nca" if labels is not None else "stress"
    check_choice("objective", objective, OBJECTIVES)
    if (objective == "nca") != (labels is not None):
        needs = "labels" if objective == "nca" else "targets"
        raise InputError(f"objective={objective!r} needs {needs}")
    free = check_learn(learn)
    max_steps = check_int("max_steps", max_steps, 0)
    tol = check_positive("tol", tol)
    dtype = shapes.dtype
    rows = np.triu_indices(k, 1)[0]
    data = _objective_data(objective, labels, targets, temperature, k, dtype)

    if init is not None and not isinstance(init, SplitMetric):
        raise InputError(f"init must be a SplitMetric; got {type(init).__name__}")
    start = normalized(SplitMetric(1.0, 1.0, 0.1, 0.0) if init is None else init)
    fixed = np.where(np.isin(np.arange(4), free), 0.0, start)
    if fixed.sum() >= 1.0:
        raise InputError(
            "fit_metric: the coefficients in learn are all zero in init and "
            "the others hold the whole metric"
        )
    theta0 = jnp.asarray(initial_theta(start, free), dtype)
    fingerprint = fingerprint_of(
        shapes,
        np.asarray(data[0] if objective == "nca" else data),
        # max_steps is left out: a resumed fit may be given more steps.
        **job_settings(
            SplitMetric(*(float(x) for x in start)),
            modulo,
            options,
            objective=objective,
            learn=learn,
            temperature=temperature,
            tol=tol,
            batch_size=job.batch_size,
        ),
    )
    strategy = job.resolved_strategy
    chunk = default_chunk(strategy) if job.batch_size is None else job.batch_size
    solves = _Solves(
        shapes,
        modulo,
        options,
        strategy,
        chunk,
        min(chunk or rows.size, rows.size),
        {},
    )
    fit = _FitJob(
        data,
        jnp.asarray(fixed, dtype),
        free,
        objective,
        k,
        tol,
        max_steps,
        theta0,
        solves,
        fingerprint,
    )
    return run(fit, job, max_steps)


class _Solves(NamedTuple):
    """How the pairs are solved: the collection, the solves' settings, the pool."""

    shapes: Array
    modulo: str
    options: ShapeOptions
    strategy: str
    chunk: int | None
    size: int
    bases: dict  # energy_parts' bases by working grid, filled as grids come

    def options_at(self, grid: tuple[int, int]) -> ShapeOptions:
        """The options the pairs held on ``grid`` were solved with: a level's (its
        quadrature and stretched cells, :meth:`ShapeOptions.on_level`) when the solves
        register, so that the held energies are the solves' own."""
        return self.options if self.modulo == "none" else self.options.on_level(grid)

    def bases_at(self, grid: tuple[int, int]):
        if grid not in self.bases:
            dtype = self.shapes.dtype
            self.bases[grid] = _evaluation_bases(grid, self.options_at(grid), self.modulo, dtype)
        return self.bases[grid]


class _FitState(NamedTuple):
    """Where a fit stands after a step (what its checkpoint holds)."""

    theta: Array  # (F,) the learned coefficients' parameters
    held: _Held  # the pairs solved at theta
    before: _Held  # the pairs solved at the start
    radius: float
    steps: int
    evaluations: int
    history: list  # the objective at the start and after each step
    accepted: bool | None = None  # whether the last step was (None: no step yet)


class _FitJob(NamedTuple):
    """A fit as the driver's job (_statistics/driver.py) over a :class:`_FitState`."""

    data: object  # (classmates (K, K), temperature) for "nca"; targets (P,) for "stress"
    fixed: Array  # (4,) the held coefficients' shares
    free: tuple[int, ...]
    objective: str
    k: int
    tol: float
    max_steps: int
    theta0: Array  # (F,) where the fit started
    solves: _Solves
    fingerprint: str
    pool: object = None

    def metric_at(self, theta) -> SplitMetric:
        return SplitMetric(*(float(w) for w in np.asarray(self.weights(theta))))

    def weights(self, theta) -> Array:
        return weights_of(theta, self.fixed, self.free)

    def value_and_grad(self, parts, theta):
        return _value_and_grad(
            parts,
            theta,
            self.data,
            self.fixed,
            objective=self.objective,
            free=self.free,
            k=self.k,
        )

    def solve(self, theta, starts) -> _Held:
        return _solve_pairs(self.metric_at(theta), starts, self.solves, self.pool)

    def init(self, saved, sink) -> _FitState:
        held = self.solve(self.theta0, None)
        value = self.value_and_grad(held.parts, self.theta0)[0]
        return _FitState(self.theta0, held, held, _RADIUS[0], 0, 1, [float(value)])

    def restore(self, saved: dict) -> _FitState:
        dtype = self.theta0.dtype
        held = _Held(saved["parts"], _restored_starts(saved, dtype), saved["converged"])
        before = _Held(saved["before_parts"], (), saved["before_converged"])
        return _FitState(
            jnp.asarray(saved["theta"], dtype),
            held,
            before,
            float(saved["radius"]),
            int(saved["steps"]),
            int(saved["evaluations"]),
            list(saved["history"]),
        )

    def pool_inputs(self) -> tuple:
        solves = self.solves
        first = self.metric_at(self.theta0)
        return solves.shapes, first, solves.modulo, solves.options, solves.strategy

    def steps(self, state: _FitState) -> int:
        return state.steps

    def value(self, state: _FitState) -> float:
        """The objective at ``state.theta`` (the last entry of its history)."""
        return float(state.history[-1])

    def terminate(self, state: _FitState) -> RESULTS | None:
        """The result when the fit stops here, None while it goes on (the step limit
        and a non-finite objective are the driver's)."""
        grad = self.value_and_grad(state.held.parts, state.theta)[1]
        if float(jnp.linalg.norm(grad)) <= self.tol:
            return RESULTS.successful
        if state.radius < _RADIUS[2]:
            return RESULTS.stalled
        return None

    def step(self, state: _FitState) -> tuple[_FitState, bool]:
        """One trust region step: the model's minimum in the box, the pairs solved there
        (warm-started), accepted if the objective went down; the box adjusted."""
        dtype = state.theta.dtype
        value = self.value_and_grad(state.held.parts, state.theta)[0]
        trial, predicted, edge = _model_step(
            state.held.parts,
            state.theta,
            jnp.asarray(state.radius, dtype),
            self.data,
            self.fixed,
            jnp.asarray(0.01 * self.tol, dtype),
            objective=self.objective,
            free=self.free,
            k=self.k,
        )
        new = self.solve(trial, state.held.starts)
        new_value = self.value_and_grad(new.parts, trial)[0]
        ratio = float(value - new_value) / max(float(predicted), 1e-300)
        accepted = bool(new_value < value)
        radius = state.radius
        if accepted and ratio > 0.75 and bool(edge):
            radius = min(2.0 * radius, _RADIUS[1])
        elif not accepted or ratio < 0.25:
            radius = radius / 4.0
        theta, held = (trial, new) if accepted else (state.theta, state.held)
        history = [*state.history, float(new_value if accepted else value)]
        return state._replace(
            theta=theta,
            held=held,
            radius=radius,
            steps=state.steps + 1,
            evaluations=state.evaluations + 1,
            history=history,
            accepted=accepted,
        ), True

    def report(self, state: _FitState, seconds: float) -> dict | None:
        if state.accepted is None:  # the first solve: progress hears of steps only
            return None
        value, grad = self.value_and_grad(state.held.parts, state.theta)
        return {
            "step": state.steps,
            "objective": float(value),
            "grad_norm": float(jnp.linalg.norm(grad)),
            "metric": tuple(float(w) for w in self.weights(state.theta)),
            "radius": state.radius,
            "accepted": state.accepted,
        }

    def warning(self, fit: MetricFit) -> str:
        return (
            f"fit_metric: not converged after {int(fit.num_steps)} steps (gradient norm "
            f"{float(fit.grad_norm):.3g} > tol {self.tol:g}): {fit.message}"
        )

    def arrays(self, state: _FitState) -> dict:
        return {
            "theta": np.asarray(state.theta),
            "radius": state.radius,
            "steps": state.steps,
            "evaluations": state.evaluations,
            "history": np.asarray(state.history),
            "parts": state.held.parts,
            "converged": state.held.converged,
            "before_parts": state.before.parts,
            "before_converged": state.before.converged,
            **_saved_starts(state.held.starts),
        }

    def result(self, state: _FitState, code: RESULTS) -> MetricFit:
        theta0, max_steps, result = self.theta0, self.max_steps, code
        rows, cols = np.triu_indices(self.k, 1)
        value, grad = self.value_and_grad(state.held.parts, state.theta)
        dtype = state.theta.dtype

        def matrix(held: _Held, theta) -> Array:
            d = safe_sqrt(jnp.asarray(held.parts) @ self.weights(theta))
            return _pair_matrix(d, rows, cols, self.k)

        pairs_ok = np.ones((self.k, self.k), bool)
        pairs_ok[rows, cols] = pairs_ok[cols, rows] = state.held.converged
        grids = np.zeros((self.k, self.k, 2), np.int32)
        grids[rows, cols] = grids[cols, rows] = [g.shape[-2:] for g in state.held.starts[0]]
        history = np.full(max(max_steps, state.steps) + 1, np.nan)
        history[: len(state.history)] = state.history
        return MetricFit(
            metric=self.metric_at(state.theta),
            initial_metric=self.metric_at(theta0),
            objective_before=self.value_and_grad(state.before.parts, theta0)[0],
            objective_after=value,
            history=jnp.asarray(history, dtype),
            grad_norm=jnp.linalg.norm(grad),
            gradient=_coefficient_gradient(
                jnp.asarray(state.held.parts),
                self.weights(state.theta),
                self.data,
                objective=self.objective,
                k=self.k,
            ),
            distances=matrix(state.held, state.theta),
            distances_before=matrix(state.before, theta0),
            pairs_converged=jnp.asarray(pairs_ok),
            grids=jnp.asarray(grids),
            converged=jnp.asarray(result == RESULTS.successful),
            result=result,
            num_steps=jnp.asarray(state.steps),
            evaluations=jnp.asarray(state.evaluations),
        )


def _objective_data(objective, labels, targets, temperature, k: int, dtype):
    """What the objective compares with: (classmates (K, K) bool, temperature) for "nca",
    the targets' upper triangle (P,) for "stress"; checked."""
    if objective == "nca":
        classes = check_labels(labels, k)
        same = jnp.asarray(classes[:, None] == classes[None, :])
        return same, jnp.asarray(check_positive("temperature", temperature), dtype)
    t = check_distances(targets, "targets")
    if t.shape[0] != k:
        raise InputError(f"targets must have shape ({k}, {k}); got {t.shape}")
    rows, cols = np.triu_indices(k, 1)
    if not np.any(t[rows, cols] > 0):
        raise InputError("targets are all zero off the diagonal")
    return jnp.asarray(t[rows, cols], dtype)


def check_learn(learn) -> tuple[int, ...]:
    if (
        not isinstance(learn, str)
        or len(set(learn)) != len(learn)
        or not set(learn) <= set(COEFFICIENTS)
        or len(learn) < 2
    ):
        raise InputError(
            f"learn must name at least two different coefficients of 'abcd' (their sum is "
            f"fixed, so one alone cannot move); got {learn!r}"
        )
    return tuple(sorted(COEFFICIENTS.index(c) for c in learn))


def _evaluation_bases(grid, options: ShapeOptions, modulo: str, dtype):
    """What energy_parts needs besides the pairs: the path basis' differentials (modulo
    "none") or the registration problem's bases."""
    m, n = grid
    if modulo == "none":
        return jnp.asarray(basis_np(m, n, options.degree)[1], dtype)
    return make_bases(m, n, options, dtype)


def _saved_starts(starts: tuple) -> dict:
    """The held solutions as a checkpoint's arrays: the gammas (each on its pair's grid)
    raveled into one, with their grids beside them."""
    gammas, rotations, coefficients = starts
    return {
        "gammas": np.concatenate([np.asarray(g).ravel() for g in gammas]),
        "gamma_grids": np.asarray([g.shape[-2:] for g in gammas], np.int64),
        "rotations": np.stack([np.asarray(r) for r in rotations]),
        "coefficients": np.stack([np.asarray(c) for c in coefficients]),
    }


def _restored_starts(saved: dict, dtype) -> tuple:
    """:func:`_saved_starts` read back: three lists of per-pair arrays."""
    flat = np.asarray(saved["gammas"])
    if "gamma_grids" not in saved:  # written before resolved fits: all on one grid
        grids = np.tile(flat.shape[-2:], (flat.shape[0], 1))
    else:
        grids = np.asarray(saved["gamma_grids"])
    flat = flat.ravel()
    ends = np.cumsum([3 * m * n for m, n in grids])
    pieces = np.split(flat, ends[:-1])
    gammas = [
        jnp.asarray(x.reshape(3, m, n), dtype) for x, (m, n) in zip(pieces, grids, strict=True)
    ]
    return (
        gammas,
        [jnp.asarray(r, dtype) for r in saved["rotations"]],
        [jnp.asarray(c, dtype) for c in saved["coefficients"]],
    )


def _by_grid(gammas: list) -> list[np.ndarray]:
    """The pairs' indices grouped by the grid their gamma is on (coarse to fine)."""
    grids = [tuple(g.shape[-2:]) for g in gammas]
    return [np.flatnonzero([g == grid for g in grids]) for grid in sorted(set(grids))]


def _solve_pairs(metric, starts, solves: _Solves, pool=None) -> _Held:
    """All pairs solved at ``metric`` (from ``starts`` when given) and their energy parts;
    on the pool's workers when there is one (the parts are computed here).

    Without starts a resolved solve (``options.rtol``) takes each pair through the levels;
    with starts the pairs continue on their starts' grids, one group per grid."""
    shapes, modulo, options = solves.shapes, solves.modulo, solves.options
    rows, cols = np.triu_indices(shapes.shape[0], 1)
    count = rows.size
    groups = [np.arange(count)] if starts is None else _by_grid(starts[0])
    settings = (metric, modulo, options, solves.strategy, solves.size)
    gammas, rotations, coefficients = [None] * count, [None] * count, [None] * count
    converged = np.zeros(count, bool)
    for group in groups:
        given = None if starts is None else tuple(jnp.stack([x[i] for i in group]) for x in starts)
        chunks = chunk_bounds(group.size, solves.chunk)
        if pool is not None:
            outs = pool.solved_pairs(
                registered_chunk, rows[group], cols[group], chunks, solves.size, metric, given
            )
        else:
            outs = [
                registered_chunk(
                    shapes[rows[group[a:b]]],
                    shapes[cols[group[a:b]]],
                    *settings,
                    None if given is None else tuple(x[a:b] for x in given),
                )
                for a, b in chunks
            ]
        for (a, b), out in zip(chunks, outs, strict=True):
            _, ok, _, _, gamma, rotation, c = out
            for k, i in enumerate(group[a:b]):
                gammas[i], rotations[i] = jnp.asarray(gamma[k]), jnp.asarray(rotation[k])
                coefficients[i], converged[i] = jnp.asarray(c[k]), bool(ok[k])
    parts = np.zeros((count, 4))
    for group in _by_grid(gammas):
        grid = tuple(gammas[group[0]].shape[-2:])
        bases, at = solves.bases_at(grid), solves.options_at(grid)
        for a, b in chunk_bounds(group.size, solves.size):
            # Every chunk padded to the solves' batch size: one compiled energy_parts a grid.
            chosen = group[a:b][np.minimum(np.arange(solves.size), b - a - 1)]
            held = (
                shapes[rows[chosen]],
                shapes[cols[chosen]],
                *(jnp.stack([x[i] for i in chosen]) for x in (gammas, rotations, coefficients)),
            )
            energies = energy_parts(*held, bases, options=at, modulo=modulo)
            parts[group[a:b]] = np.asarray(energies)[: b - a]
    return _Held(parts, (gammas, rotations, coefficients), converged)
