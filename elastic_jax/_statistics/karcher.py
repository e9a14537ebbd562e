"""Karcher means and distance matrices of shape collections (paper section 4.1, math §7).

Batch jobs: every step solves K independent geodesics, batched by one of three
strategies ("vmap", "map": lax.map in one jit, "loop": a Python loop of jitted solves),
sharded across devices when there are several, and checkpointed atomically after each
finished step or chunk so that a killed job resumes where it stopped. The inner solves'
options travel as one :class:`ShapeOptions` record; the Karcher iteration's own limits
(max_steps, tol, step_size) are separate arguments.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._checks import check_bool
from .._errors import InputError
from .._geometry.composition import on_grid
from .._geometry.grid import sphere_points
from .._geometry.harmonics import vector_fields_np
from .._geometry.metric import SplitMetric, metric_inner_unchecked
from .._geometry.reparam import reparametrize_unchecked
from .._geometry.srnf import center_unchecked
from .._geometry.validation import as_surface
from .._options import ShapeOptions, check_int, check_positive
from .._registration.levels import registration_at
from .._registration.shape import solve_shapes
from .._results import RESULTS, status_record
from .batching import (
    check_collection,
    chunk_bounds,
    default_chunk,
    job_settings,
    levelled_chunk,
    velocity_chunk,
)
from .checkpoints import fingerprint_of
from .driver import JobOptions, check_job, run

# Halvings of a Karcher step that raised the sum of squared distances before giving up.
_HALVINGS = 4


_CONVERGED = ("distances_at_rounding", "mean_velocity_small", "sum_sq_stalled")


@status_record
class KarcherResult(NamedTuple):
    """A Karcher mean, the registered collection and how the iteration went.

    Attributes:
        mean: ``(3, m, n)`` the mean shape (keeps its parametrization).
        distances: ``(K,)`` distances from the mean to each shape.
        registered: ``(K, 3, m, n)`` each shape reparametrized (and rotated) onto the mean.
        velocities: ``(K, 3, m, n)`` initial velocities of the geodesics at the mean
            (second-order one-sided differences, ``initial_velocity()``).
        geodesics_converged: ``(K,)`` whether each inner solve at the mean converged.
        geodesics_resolution_limited: ``(K,)`` whether each inner solve at the mean ended
            ``resolution_limited`` (its registration stopped at the stretch the grid
            resolves, :class:`ShapeGeodesicResult`; not converged, its distance an upper
            bound), as a shape whose registration to the mean would collapse a region
            does on every grid. A False entry of ``geodesics_converged`` that is not
            flagged here is a solve that failed.
        history: ``(steps + 1, 3)`` per mean visited (the start first): sum of squared
            distances (non-increasing), norm of the mean velocity sqrt(G_mean(v, v)), and
            the step size that led there (0 for the start; step_size / 2^j after j halvings).
        converged: ``result`` is ``distances_at_rounding``, ``mean_velocity_small`` or
            ``sum_sq_stalled``.
        num_steps: Karcher steps taken (accepted updates of the mean).
        num_solves: batches of K geodesics solved, rejected line-search trials included.
        result: why the iteration stopped, an ``elastic_jax.RESULTS``:
            ``distances_at_rounding``, ``mean_velocity_small``, ``sum_sq_stalled`` (all three
            converged), ``line_search_failed``, ``resolution_limited`` (the line search
            failed while some geodesics at the mean are resolution_limited),
            ``nonlinear_max_steps_reached`` (max_steps Karcher steps) or ``nonfinite``;
            ``RESULTS.name(result)`` is its name.
        level_distances: ``(K, L)`` for a resolved mean (``options.rtol``): each shape's
            distance to the starting mean on each grid of ``options.levels`` (NaN on the
            grids past the one where its levels agreed within rtol); the mean, the
            registered shapes and the velocities are on the finest grid any shape needed.
            None on one grid.
    """

    mean: Array
    distances: Array
    registered: Array
    velocities: Array
    geodesics_converged: Array
    geodesics_resolution_limited: Array
    history: np.ndarray
    num_solves: int
    level_distances: np.ndarray | None
    converged: Bool[Array, ""]
    result: RESULTS
    num_steps: Int[Array, ""]

    def _explain(self, words: str) -> str:
        # A Karcher mean names its criterion also when it converged; a stop says what
        # stopped the iteration rather than an inner solve.
        name = RESULTS.name(self.result)
        if name in _CONVERGED:
            return words
        if name == "resolution_limited":
            words = (
                f"line search failed (no step along the mean velocity, halved up to {_HALVINGS} "
                "times, gave a sum of squared distances that was not larger) while some of the "
                "geodesics at the mean ended resolution_limited (their registration stopped at "
                "the stretch the grid resolves; geodesics_converged is False for them): the sum "
                "has kinks there that no step resolves; a finer grid may go further"
            )
        elif name == "nonlinear_max_steps_reached":
            words = f"max_steps Karcher steps taken ({int(self.num_steps)})"
        elif name == "nonfinite":
            words = "the distances at the mean are not finite"
        return f"stopped: {words}"


class _Solved(NamedTuple):
    """The K geodesics from one mean."""

    distances: Array
    registered: Array
    velocities: Array
    converged: Array
    gammas: Array  # each shape's reparametrization onto the mean (its warm start next)
    rotations: Array
    limited: Array  # each solve ended resolution_limited (shape_geodesic's result)
    coefficients: Array  # each path's coefficients (a continuation's start next)


@functools.partial(jax.jit, static_argnames=("interpolation", "rigid"))
def _horizontal_part(metric, mean, v, fields, *, interpolation, rigid):
    """v minus its G_mean-orthogonal projection on the vertical directions at the mean.

    The vertical directions are those the registration moves the mean along without
    changing its shape: df(X_j) for the Diff step's vector fields X_j (d/de of
    mean o Proj(Id + e X_j), through the same interpolation), and for rigid also the
    rotations w x mean. In the continuum the gradient of the sum of squared distances
    has no vertical part; in the discrete one it has a small one that drifts the mean's
    parametrization toward grids the discretization favours. An orthogonal projection
    never raises the norm: G(v_h, v_h) = G(v, v) - b^T c.
    """
    m, n = mean.shape[-2:]
    e1 = sphere_points(m, n, mean.dtype)

    def sampled(gamma):
        return reparametrize_unchecked(mean, gamma, method=interpolation)

    directions = jax.vmap(lambda x: jax.jvp(sampled, (e1,), (x,))[1])(fields)
    if rigid:
        centered = center_unchecked(mean)
        turns = [jnp.cross(jnp.eye(3, dtype=mean.dtype)[i], centered, axis=0) for i in range(3)]
        directions = jnp.concatenate([directions, jnp.stack(turns)])

    def combined(c):
        return jnp.einsum("k,kimn->imn", c, directions)

    zero = jnp.zeros(directions.shape[0], mean.dtype)
    gram = jax.hessian(
        lambda c: 0.5 * metric_inner_unchecked(metric, mean, combined(c), combined(c))
    )(zero)
    b = jax.grad(lambda c: metric_inner_unchecked(metric, mean, combined(c), v))(zero)
    values, vectors = jnp.linalg.eigh(gram)
    # Pseudo-inverse: directions the metric cannot tell apart carry no weight.
    keep = values > jnp.finfo(mean.dtype).eps ** 0.5 * jnp.max(values)
    inverse = jnp.where(keep, 1.0 / jnp.where(keep, values, 1.0), 0.0)
    c = vectors @ (inverse * (vectors.T @ b))
    return v - combined(c)


class _Direction(NamedTuple):
    """The step direction at one mean and the numbers the iteration tests."""

    velocity: Array  # the mean velocity (its horizontal part, modulo "rigid" / "diff")
    norm: float  # sqrt(G_mean(v, v))
    sum_sq: float  # sum of squared distances
    size: float  # sqrt(G_mean(c, c)), c the centered mean: d(mean, (1 + t) mean) ~ t size


def _direction(metric, mean, solved: _Solved, modulo: str, options: ShapeOptions) -> _Direction:
    average = solved.velocities.mean(axis=0)
    if modulo != "none":
        m, n = mean.shape[-2:]
        fields = jnp.asarray(vector_fields_np(m, n, options.vf_degree), mean.dtype)
        average = _horizontal_part(
            metric,
            mean,
            average,
            fields,
            interpolation=options.interpolation,
            rigid=modulo == "rigid",
        )
    norm = float(jnp.sqrt(metric_inner_unchecked(metric, mean, average, average)))
    centered = center_unchecked(mean)
    size = float(jnp.sqrt(metric_inner_unchecked(metric, mean, centered, centered)))
    return _Direction(average, norm, float(jnp.sum(solved.distances**2)), size)


class _KarcherState(NamedTuple):
    """Where a Karcher iteration stands: the mean, its K geodesics and step direction, the
    steps taken, the batches solved, the history rows (sum_sq, norm, step size), the
    options the solves use (a resolved mean's working grid), the first solves' level
    distances (a resolved mean's; else None) and, once a step has decided it, why the
    iteration stops (else None)."""

    mean: Array
    solved: _Solved
    direction: _Direction
    step: int
    num_solves: int
    history: tuple
    working: ShapeOptions
    level_distances: np.ndarray | None
    stop: RESULTS | None = None


class _KarcherJob(NamedTuple):
    """The Karcher iteration as the driver's job (_statistics/driver.py): the geodesics
    at the starting mean (by levels for a resolved mean), then line searches along the
    mean velocity."""

    shapes: Array
    start: Array  # the starting mean
    metric: SplitMetric
    modulo: str
    options: ShapeOptions  # the inner solves'; rtol set only for a resolved mean
    strategy: str
    chunks: tuple  # (a, b) bounds of the chunks of shapes
    tol: float
    step_size: float
    warm_start: bool
    fingerprint: str
    pool: object = None

    @property
    def count(self) -> int:  # K, the shapes
        return self.shapes.shape[0]

    def _solve(self, working: ShapeOptions, at, starts) -> _Solved:
        """The K geodesics at the mean ``at`` (a batch of solves, chunk by chunk)."""
        size = self.chunks[0][1] - self.chunks[0][0]
        if self.pool is not None:
            out = self.pool.velocities(velocity_chunk, at, self.chunks, size, starts, working)
            return _Solved(*(jnp.asarray(x) for x in out))
        parts = [
            velocity_chunk(
                at,
                self.shapes[a:b],
                self.metric,
                self.modulo,
                working,
                self.strategy,
                size,
                None if starts is None else tuple(x[a:b] for x in starts),
            )
            for a, b in self.chunks
        ]
        return _Solved(*(jnp.concatenate(p) for p in zip(*parts, strict=True)))

    def _continued(self, working: ShapeOptions, at, previous: _Solved) -> _Solved:
        """The geodesics at ``at``, each started where it was at the previous mean when
        the mean is resolved (continued) or warm-started; else a fresh search."""
        if self.options.resolves:
            starts = (previous.gammas, previous.rotations, previous.coefficients)
        elif self.warm_start:
            starts = (previous.gammas, previous.rotations)
        else:
            starts = None
        return self._solve(working, at, starts)

    def _direction(self, mean, solved: _Solved, working: ShapeOptions) -> _Direction:
        return _direction(self.metric, mean, solved, self.modulo, working)

    def init(self, saved: dict | None, sink) -> _KarcherState:
        """Step 0: the geodesics at the starting mean; for a resolved mean by levels, shape
        by shape (each kept in the checkpoint as it ends), then read on its working grid."""
        mean, working, starts, levels = self.start, self.options, None, None
        if self.options.resolves:
            report = None
            if sink.report is not None:

                def report(k, info):
                    sink.report({**info, "step": 0, "shape": k, "shapes": self.count})

            mean, working, starts, levels = _resolved_start(
                self.shapes,
                mean,
                self.metric,
                self.modulo,
                self.options,
                saved,
                sink.save,
                report,
                self.strategy,
                self.chunks,
            )
        elif self.warm_start:  # the identity registration
            m, n = self.shapes.shape[-2:]
            e1 = sphere_points(m, n, self.shapes.dtype)
            eye = jnp.eye(3, dtype=self.shapes.dtype)
            k = self.count
            starts = (jnp.broadcast_to(e1, (k, *e1.shape)), jnp.broadcast_to(eye, (k, 3, 3)))
        solved = self._solve(working, mean, starts)
        direction = self._direction(mean, solved, working)
        history = ((direction.sum_sq, direction.norm, 0.0),)
        return _KarcherState(mean, solved, direction, 0, 1, history, working, levels)

    def restore(self, saved: dict) -> _KarcherState | None:
        """The state a checkpoint holds (its direction evaluated again, no solve); None
        for one written during a resolved mean's first, levelled solves."""
        if "mean" not in saved:
            return None
        mean = jnp.asarray(saved["mean"])
        solved = _Solved(*(jnp.asarray(saved[f"solved_{k}"]) for k in _Solved._fields))
        history = tuple(tuple(row) for row in saved["history"].tolist())
        working, levels = self.options, None
        if self.options.resolves:
            levels = np.asarray(saved["level_distances"])
            working = self.options.replace(grid=tuple(mean.shape[-2:]), rtol=None)
        return _KarcherState(
            mean,
            solved,
            self._direction(mean, solved, working),
            int(saved["step"]),
            int(saved["num_solves"]),
            history,
            working,
            levels,
        )

    def pool_inputs(self) -> tuple:
        return self.shapes, self.metric, self.modulo, self.options, self.strategy

    def steps(self, state: _KarcherState) -> int:
        return state.step

    def value(self, state: _KarcherState) -> float:
        """The sum of squared distances at the mean."""
        return float(state.direction.sum_sq)

    def terminate(self, state: _KarcherState) -> RESULTS | None:
        """Why the iteration stops at ``state`` (a RESULTS member), or None to step on
        (the step limit and a non-finite sum are the driver's)."""
        if state.stop is not None:
            return state.stop
        sum_sq, norm = state.direction.sum_sq, state.direction.norm
        rms = np.sqrt(sum_sq / self.count)
        if rms <= np.sqrt(np.finfo(np.dtype(state.mean.dtype)).eps) * state.direction.size:
            return RESULTS.distances_at_rounding
        if norm <= self.tol * max(rms, np.finfo(np.float64).tiny):
            return RESULTS.mean_velocity_small
        return None

    def step(self, state: _KarcherState) -> tuple[_KarcherState, bool]:
        """One line search along the mean velocity: the accepted trial as the new state
        (kept), or the same mean with ``stop`` set (every trial solved is counted)."""
        sum_sq, num_solves = state.direction.sum_sq, state.num_solves
        s = self.step_size
        for _ in range(_HALVINGS + 1):
            trial_mean = state.mean + s * state.direction.velocity
            trial = self._continued(state.working, trial_mean, state.solved)
            num_solves += 1
            trial_sum_sq = float(jnp.sum(trial.distances**2))
            # NaN compares False: a non-finite trial is never accepted.
            if trial_sum_sq <= sum_sq:
                break
            # A full step that raises the SSD by less than tol changed it as little as
            # one that lowers it by less than tol: the mean is stationary to within the
            # registrations' own scatter (each is a nonconvex search), and halving a
            # step the SSD cannot resolve only looks for a lower draw of that scatter.
            if s == self.step_size and trial_sum_sq - sum_sq <= self.tol * sum_sq:
                return state._replace(num_solves=num_solves, stop=RESULTS.sum_sq_stalled), False
            s *= 0.5
        else:
            limited = bool(np.any(np.asarray(state.solved.limited)))
            stop = RESULTS.resolution_limited if limited else RESULTS.line_search_failed
            return state._replace(num_solves=num_solves, stop=stop), False
        direction = self._direction(trial_mean, trial, state.working)
        # A halved step counts too: the full step raised the SSD by more than tol, and
        # the best halving lowered it by less, so no step along this direction changes
        # it by more than tol. Counting full steps only, the shared animals' mean (levels
        # to 25 x 49, rigid) took four halved steps of 5e-4 to 3e-6 (relative) and then
        # ended line_search_failed at the same SSD to 1e-5, an outcome that flipped with
        # the registrations' rounding.
        stalled = sum_sq - trial_sum_sq <= self.tol * sum_sq
        return state._replace(
            mean=trial_mean,
            solved=trial,
            direction=direction,
            step=state.step + 1,
            num_solves=num_solves,
            history=(*state.history, (direction.sum_sq, direction.norm, s)),
            stop=RESULTS.sum_sq_stalled if stalled else None,
        ), True

    def arrays(self, state: _KarcherState) -> dict:
        """The mean and its geodesics (and a resolved mean's first level distances)."""
        extra = {} if state.level_distances is None else {"level_distances": state.level_distances}
        return {
            "mean": np.asarray(state.mean),
            "step": state.step,
            "history": np.asarray(state.history),
            "num_solves": state.num_solves,
            **{f"solved_{k}": np.asarray(v) for k, v in state.solved._asdict().items()},
            **extra,
        }

    def report(self, state: _KarcherState, seconds: float) -> dict:
        sum_sq, norm, step_size = state.history[-1]
        return {
            "step": state.step,
            "sum_sq_distances": sum_sq,
            "mean_velocity_norm": norm,
            "step_size": step_size,
            "num_solves": state.num_solves,
        }

    def result(self, state: _KarcherState, code: RESULTS) -> KarcherResult:
        solved = state.solved
        return KarcherResult(
            mean=state.mean,
            distances=solved.distances,
            registered=solved.registered,
            velocities=solved.velocities,
            geodesics_converged=solved.converged,
            geodesics_resolution_limited=solved.limited,
            history=np.asarray(state.history),
            converged=jnp.asarray(RESULTS.name(code) in _CONVERGED),
            num_steps=jnp.asarray(state.step, jnp.int32),
            num_solves=state.num_solves,
            result=code,
            level_distances=state.level_distances,
        )

    def warning(self, res: KarcherResult) -> str:
        return (
            f"karcher_mean: {res.message} (sum of squared distances "
            f"{res.history[:, 0].round(6).tolist()})"
        )


def _resolved_start(
    shapes,
    mean,
    metric,
    modulo,
    options: ShapeOptions,
    saved=None,
    keep=None,
    report=None,
    strategy: str = "loop",
    chunks: tuple = (),
):
    """Step 0 of a resolved mean: every shape's distance to the starting mean by levels
    (math §10: :func:`levelled_chunk`, chunk by chunk, the distances shape_geodesic with
    ``options.rtol`` gives), and the working grid the mean is then solved on, the finest
    grid any shape needed.

    Returns the starting mean read there (its interpolant at that grid's points, as the
    solves read it), the options of that one grid, each shape's registration and path
    there (gamma, R, C: the first continuations' starts) and the ``(K, L)`` level
    distances. A registration from a coarser level whose interpolant folds at that grid
    is replaced by a search there. ``saved``: the shapes finished before (a checkpoint's
    ``first_*`` arrays); ``keep(arrays)`` is called after each chunk with all so far;
    ``report(k, info)`` after each level of shape k (shape_geodesic's level report).
    ``chunks``: (a, b) bounds of the shapes' chunks (default: all at once).
    """
    finished = {} if saved is None else {k: v for k, v in saved.items() if k.startswith("first_")}
    count = len(shapes)
    for a, b in chunks or ((0, count),):
        todo = [k for k in range(a, b) if f"first_levels_{k}" not in finished]
        if not todo:
            continue
        told = None if report is None else (lambda i, info, todo=todo: report(todo[i], info))
        out = levelled_chunk(
            shapes[np.asarray(todo)],
            jnp.broadcast_to(mean, (len(todo), *mean.shape)),
            metric,
            modulo,
            options,
            strategy,
            b - a,
            report=told,
        )
        for i, k in enumerate(todo):
            finished.update(
                {
                    f"first_gamma_{k}": np.asarray(out.gamma[i]),
                    f"first_rotation_{k}": np.asarray(out.rotation[i]),
                    f"first_coefficients_{k}": np.asarray(out.coefficients[i]),
                    f"first_levels_{k}": np.asarray(out.level_distances[i]),
                }
            )
        if keep is not None:
            keep(finished)
    grid = max(
        (finished[f"first_gamma_{k}"].shape[-2:] for k in range(count)),
        key=lambda g: g[0] * g[1],
    )
    grid = (int(grid[0]), int(grid[1]))
    working = options.on_level(grid)
    at = on_grid(mean, sphere_points(*grid, mean.dtype), options.interpolation)
    if modulo == "rigid":
        at = center_unchecked(at)
    starts = []
    for k, shape in enumerate(shapes):
        gamma, rotation = finished[f"first_gamma_{k}"], finished[f"first_rotation_{k}"]
        coefficients = finished[f"first_coefficients_{k}"]
        carried = registration_at((gamma, rotation), grid, mean.dtype, modulo)
        if carried is None:
            r = solve_shapes(shape, at, metric, modulo, working)
            carried, coefficients = (r.gamma, r.rotation), r.coefficients
        starts.append((*carried, jnp.asarray(coefficients, mean.dtype)))
    stacked = tuple(jnp.stack(parts) for parts in zip(*starts, strict=True))
    distances = np.stack([finished[f"first_levels_{k}"] for k in range(count)])
    return at, working, stacked, distances


def karcher_mean(
    shapes: Float[ArrayLike, "K 3 m n"],
    metric: SplitMetric,
    *,
    modulo: str = "rigid",
    options: ShapeOptions | None = None,
    init: Float[ArrayLike, "3 m n"] | None = None,
    max_steps: int = 10,
    tol: float = 1e-3,
    step_size: float = 1.0,
    warm_start: bool = False,
    job: JobOptions | None = None,
) -> KarcherResult:
    """Karcher (Frechet) mean of a collection of surfaces (paper section 4.1,
    :ref:`math §7 <math-7>`).

    Minimizes the sum of squared distances SSD(mu) = sum_k d(mu, f_k)^2 by gradient
    steps with backtracking. At the current mean every shape is registered to it (the
    shape is reparametrized and, for modulo="rigid", rotated; the mean keeps its
    parametrization) and the K geodesics from the shapes to the mean are solved. Their
    initial velocities at the mean, v_k = T (-3 f_0 + 4 f_1 - f_2) / 2 read from the mean
    (second order, ``initial_velocity()``), average to v = -grad SSD / (2K); modulo
    "rigid" or "diff" v loses its vertical part (G_mu-orthogonal projection off the
    directions that only reparametrize or rotate the mean, ``_horizontal_part()``).
    A trial mean mu + s v (s = step_size first) is accepted only if its SSD, from K new
    solves, is finite and not larger; otherwise s is halved, at most 4 times. The
    accepted trial's geodesics serve the next step, so a step that does not backtrack
    costs K solves. With ``warm_start`` (modulo "rigid" / "diff") each of those solves is
    two: the registration search, and registration rounds started from the shape's
    registration at the current mean (at the first mean: the identity); the lower
    distance is kept. The search alone can land in another local minimum after a small
    move of the mean, and the SSD then jumps by more than a step gains (four real shapes
    at 25 x 49 stopped "line_search_failed" after one step, SSD 4.880 -> 3.286); the warm
    solve follows the minimum it started in. Measured: those four took three steps
    (4.870, 3.295, 2.919, 2.752) and then failed the line search too (two inner solves
    unconverged; 1.8 times the time per step); three synthetic shapes modulo "diff"
    end with a lower SSD (2.17540 against 2.17626) whose mean velocity stalls at 0.5 % of
    its first norm. Hence not the default.

    Resolved (the default: ``options.rtol`` given, ``grid`` None; modulo "rigid" or
    "diff"): the first geodesics, from each shape to the starting mean, are solved by
    levels of working grids until two agree within rtol (``shape_geodesic``,
    :ref:`math §10 <math-10>`); the mean is then read on the finest grid any shape
    needed (its interpolant at that grid's points) and stays there, and every later solve
    continues the shape's registration and path at the previous mean (no start search,
    no coarse rounds; ``continued_geodesic``). The shapes themselves keep their grid: each
    stands for its interpolant. The SSD is then a continuous function of the mean (each
    registration follows its basin), which is what a line search needs; with a search
    per solve it jumps between basins (cat1, cat2, horse0 and hand4 stopped
    ``line_search_failed`` after one step at 25 x 49). The result's mean, registered
    shapes and velocities are on that grid; ``level_distances`` records the levels.
    ``rtol=None`` (or ``grid`` equal to the shapes' grid) solves on the shapes' grid,
    a start search per solve, as before; modulo "none" always does.

    Stops converged when the RMS distance is at most sqrt(eps) x the mean's size
    sqrt(G_mu(c, c)), c the centered mean (the distance to a dilation (1 + t) mu is about
    t times it): the shapes are one orbit ("distances_at_rounding", at step 0 for copies
    of one shape under the group; tol x RMS below would only test rounding); when
    sqrt(G_mu(v, v)) <= tol x RMS distance ("mean_velocity_small")
    or when the line search's step (the full step, or the halving it took after the
    full step raised the SSD) changes the SSD by less than tol relative
    ("sum_sq_stalled": a step that lowers it is taken, one that raises it is not); stops
    not converged when no halving lowers the SSD ("line_search_failed"; "resolution_limited"
    when some of the geodesics at the mean ended resolution_limited, their registration
    held at the stretch the grid resolves, so that the SSD has kinks there), after
    max_steps steps ("nonlinear_max_steps_reached"), or when the distances at the mean are not
    finite ("nonfinite"). ``result`` (an ``elastic_jax.RESULTS``) and ``message`` say which.

    Args:
        shapes: ``(K, 3, m, n)`` surfaces on one grid.
        metric: split metric coefficients.
        modulo: ``"rigid"``, ``"diff"`` (:func:`shape_geodesic`) or ``"none"``
            (:func:`geodesic` with the options' degree, n_times, solver, max_steps, tol
            and scheme).
        options: :class:`ShapeOptions` of the inner solves (its defaults when None);
            its ``rtol`` and ``levels`` resolve the mean's grid (above). Modulo "none"
            solves on the shapes' grid: ``rtol`` and ``levels`` are not used there
            (rtol is set to None).
        init: starting mean (default: the first shape).
        max_steps: most Karcher steps (accepted updates of the mean); 0 only evaluates.
        tol: the two convergence tests above.
        step_size: the first trial step, in units of the mean velocity.
        warm_start: the second, warm-started solve per shape described above (modulo
            "rigid" / "diff" on one grid, ``rtol=None``; twice the solves per step, the
            warm one without a search). A resolved mean continues every solve already.
        job: how the job runs (:class:`JobOptions`). A chunk is ``batch_size`` shapes
            (default all in process; on a cluster one for "loop", all for "vmap", 8 for
            "map"). The checkpoint is written after the first solves and after every
            accepted step (the mean and its geodesics), for a resolved mean also after
            each chunk of first, levelled solves (a chunk's shapes go through the levels
            together); a resume is refused if it belongs to other inputs. ``progress``
            hears after the first solves (step 0) and after each accepted step: step,
            sum_sq_distances, mean_velocity_norm, step_size, num_solves, seconds; a
            resolved mean's first, levelled solves also report each shape's levels as
            they end (stage "level", level, levels, grid, distance, converged) with
            step 0, shape (its index), shapes (K) and seconds. On a cluster each step's
            chunks run as tasks on its workers (a resolved mean's first, levelled solves
            run in this process); the numbers equal the in-process ones.

    Returns:
        :class:`KarcherResult`. One that did not converge also warns
        (:class:`ConvergenceWarning`); the inner solves' own warnings are folded into
        ``geodesics_converged``.

    Example:
        >>> import numpy as np
        >>> import elastic_jax as ej
        >>> from elastic_jax import shapes
        >>> spheres = np.stack([shapes.sample(shapes.sphere, 13, 25, radius=r) for r in (1, 2)])
        >>> res = ej.karcher_mean(spheres, ej.SplitMetric(1.0, 1.0, 0.1, 0.0), modulo="none",
        ...                       options=ej.ShapeOptions(degree=3, n_times=5))
        >>> bool(res.converged), round(float(res.mean[2, 0, 0]), 6)  # the sphere of radius 1.5
        (True, 1.5)
    """
    job = check_job(job)
    shapes, options = check_collection(shapes, options, modulo, levels=True)
    max_steps = check_int("max_steps", max_steps, 0)
    tol = check_positive("tol", tol)
    step_size = check_positive("step_size", step_size)
    mean = _starting_mean(shapes, init, modulo)
    # Resolved (options.rtol, the default): step 0 by levels, then continuations on the
    # grid the distances needed. Modulo "none" has no registration to carry: one grid.
    if modulo == "none" or not options.resolves:
        options = options.replace(rtol=None)
    warm_start = check_bool("warm_start", warm_start) and modulo != "none" and not options.resolves
    strategy = job.resolved_strategy
    settings = job_settings(metric, modulo, options, step_size=step_size, tol=tol, warm=warm_start)
    batch_size = job.batch_size
    if batch_size is None and job.client is not None:
        batch_size = default_chunk(strategy)
    iteration = _KarcherJob(
        shapes,
        mean,
        metric,
        modulo,
        options,
        strategy,
        tuple(chunk_bounds(shapes.shape[0], batch_size)),
        tol,
        step_size,
        warm_start,
        fingerprint_of(shapes, mean, **settings),
    )
    return run(iteration, job, max_steps)


def _starting_mean(shapes, init, modulo: str):
    """The starting mean: ``init`` (checked against the shapes) or the first shape;
    centred for modulo "rigid"."""
    mean = shapes[0] if init is None else as_surface(init, "init")
    if mean.shape != shapes.shape[1:] or mean.dtype != shapes.dtype:
        raise InputError(
            f"init must be one surface {shapes.shape[1:]} {shapes.dtype} like the shapes; "
            f"got {mean.shape} {mean.dtype}"
        )
    return center_unchecked(mean) if modulo == "rigid" else mean
