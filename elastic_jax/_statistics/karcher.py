"""Karcher means and distance matrices of shape collections (paper section 4.1, MATH.md 7).

Batch jobs: every step solves K independent geodesics, batched by one of three
strategies ("vmap", "map": lax.map in one jit, "loop": a Python loop of jitted solves),
sharded across devices when there are several, and checkpointed atomically after each
finished step or chunk so that a killed job resumes where it stopped. The inner solves'
options travel as one :class:`ShapeOptions` record; the Karcher iteration's own limits
(max_steps, tol, step_size) are separate arguments.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import os
import pathlib
import time
import warnings
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._checks import check_bool
from .._errors import ConvergenceWarning, InputError
from .._geodesics.geodesic import default_tol, geodesic
from .._geometry.grid import sphere_points
from .._geometry.harmonics import vector_fields_np
from .._geometry.metric import SplitMetric, metric_inner_unchecked
from .._geometry.reparam import reparametrize_unchecked
from .._geometry.srnf import center_unchecked
from .._geometry.validation import as_surface
from .._options import ShapeOptions, check_choice, check_int, check_positive
from .._registration.records import turned_back
from .._registration.shape import check_grid_options, resolve_options, shape_geodesic
from .._results import RESULTS, result_message
from .._runtime.atomic import save_npz_atomic
from .._runtime.cache import solver_jit

MODULI = ("rigid", "diff", "none")
STRATEGIES = ("auto", "vmap", "map", "loop")
# Halvings of a Karcher step that raised the sum of squared distances before giving up.
_HALVINGS = 4

# Why a Karcher iteration stopped: result code -> words (KarcherResult.message).
_MESSAGES = {
    "distances_at_rounding": "converged: every distance is at rounding level (at most "
    "sqrt(eps) x the mean's size): the shapes are one orbit of the registration's group",
    "mean_velocity_small": "converged: the mean velocity's norm is at most tol x RMS distance",
    "sum_sq_stalled": "converged: a full step changed the sum of squared distances by less "
    "than tol (relative)",
    "line_search_failed": "stopped: line search failed: no step along the mean velocity "
    f"(halved up to {_HALVINGS} times) gave a finite sum of squared distances that was not larger",
    "resolution_limited": "stopped: line search failed (no step along the mean velocity, "
    f"halved up to {_HALVINGS} times, gave a sum of squared distances that was not larger) "
    "while some of the geodesics at the mean ended resolution_limited (their registration "
    "stopped at the stretch the grid resolves; geodesics_converged is False for them): the "
    "sum has kinks there that no step resolves; a finer grid may go further",
    "max_steps_reached": "stopped: max_steps Karcher steps taken",
    "nonfinite": "stopped: the distances at the mean are not finite",
}
_CONVERGED = ("distances_at_rounding", "mean_velocity_small", "sum_sq_stalled")


class KarcherResult(NamedTuple):
    """A Karcher mean, the registered collection and how the iteration went.

    Attributes:
        mean: ``(3, m, n)`` the mean shape (keeps its parametrization).
        distances: ``(K,)`` distances from the mean to each shape.
        registered: ``(K, 3, m, n)`` each shape reparametrized (and rotated) onto the mean.
        velocities: ``(K, 3, m, n)`` initial velocities of the geodesics at the mean
            (second-order one-sided differences, :func:`initial_velocity`).
        geodesics_converged: ``(K,)`` whether each inner solve at the mean converged.
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
            ``max_steps_reached`` or ``nonfinite``; ``RESULTS.name(result)`` is its name.
    """

    mean: Array
    distances: Array
    registered: Array
    velocities: Array
    geodesics_converged: Array
    history: np.ndarray
    converged: bool
    num_steps: int
    num_solves: int
    result: RESULTS

    @property
    def message(self) -> str:
        """Why the iteration stopped, in words (also when it converged: which criterion)."""
        return _MESSAGES[RESULTS.name(self.result)]


class DistanceMatrixResult(NamedTuple):
    """Pairwise shape distances and the status of each pair's solve.

    Attributes:
        distances: ``(K, K)`` symmetric, zero diagonal.
        pairs_converged: ``(K, K)`` bool: whether the pair's solve converged (diagonal
            True).
        refinement_change: ``(K, K)`` each pair's
            ``ShapeGeodesicResult.refinement.relative_change`` (how far the distance moves
            with halved time steps or on the finer grid); 0 on the diagonal, NaN for
            modulo="none" or ``options.refinement=False``.
        converged: ``()`` every pair converged.
        result: ``successful``, or the result code of the first pair (in row-major order
            of the upper triangle) that did not converge (``elastic_jax.RESULTS``).
        num_steps: ``()`` solver steps over all pairs.
    """

    distances: Float[Array, "K K"]
    pairs_converged: Bool[Array, "K K"]
    refinement_change: Float[Array, "K K"]
    converged: Bool[Array, ""]
    result: RESULTS
    num_steps: Int[Array, ""]

    @property
    def message(self) -> str:
        """How many pairs did not converge, the first of them and why ('' when all did)."""
        if bool(self.converged):
            return ""
        upper = np.triu(~np.asarray(self.pairs_converged), 1)
        first = tuple(int(i) for i in np.argwhere(upper)[0])
        return (
            f"{int(upper.sum())} of {upper.shape[0] * (upper.shape[0] - 1) // 2} pairs did not "
            f"converge; the first, {first}: {result_message(self.result)}"
        )


def default_strategy() -> str:
    """The batching strategy "auto" resolves to on this backend.

    CPU: "map" (lax.map in one jit). Measured by benchmarks/bench_karcher.py on 2 cores
    (8 surfaces at 25 x 49, rigid, one Karcher step after compilation): map 17.7 s, a
    Python loop 19.8 s, vmap 52.8 s; a vmapped BFGS runs in lockstep until its slowest
    member converges and its dense per-item updates do not vectorize on a CPU.
    Accelerators: "vmap", where batching is what pays.
    """
    return "map" if jax.default_backend() == "cpu" else "vmap"


def initial_velocity(path: Float[ArrayLike, "N 3 m n"]) -> Float[Array, "3 m n"]:
    """Initial velocity of a discrete path: T (-3 f_0 + 4 f_1 - f_2) / 2, T = N - 1.

    The second-order one-sided difference. The forward difference T (f_1 - f_0) is the
    velocity at t = 1 / (2T), off by f''(0) / (2T); the Karcher iteration's fixed point
    moves with it, away from the minimum of the (second-order, midpoint) discrete sum of
    squared distances, and the line search stalls there (README, "Karcher means").
    """
    t = path.shape[0] - 1
    return t * (-3.0 * path[0] + 4.0 * path[1] - path[2]) / 2.0


def _one_geodesic(mean, shape, metric, modulo, options, start=None):
    """Distance, registered shape, initial velocity at the mean, status and registration
    (gamma, R) for one shape.

    Every geodesic runs from the shape to the mean, as shape_geodesic must (it
    reparametrizes its first surface and rotates its second), also for modulo="none", so
    that a one-sided scheme ("forward") treats the mean alike for every modulo.

    ``start`` (gamma, R): a second solve whose registration rounds start there (the
    shape's registration at the previous mean) instead of the start search; the lower of
    the two distances is kept. The search alone may land in another basin at a mean
    moved a little and make the sum of squared distances jump; the warm solve follows its
    basin continuously, so the sum is continuous in the mean, while the search still
    finds a lower basin when there is one.
    """
    if modulo == "none":
        res = geodesic(shape, mean, metric, **options.geodesic_kwargs())
        m, n = mean.shape[-2:]
        gamma, rotation = sphere_points(m, n, mean.dtype), jnp.eye(3, dtype=mean.dtype)
        back = res.path
        limited = jnp.zeros((), bool)
    else:
        res = shape_geodesic(shape, mean, metric, modulo=modulo, options=options)
        if start is not None:
            warm = shape_geodesic(shape, mean, metric, modulo=modulo, options=options, start=start)
            lower = warm.distance < res.distance
            res = jax.tree_util.tree_map(lambda a, b: jnp.where(lower, a, b), warm, res)
        gamma, rotation = res.gamma, res.rotation
        back = turned_back(res, mean)
        limited = res.result == RESULTS.resolution_limited
    velocity = initial_velocity(back[::-1])
    return res.distance, back[0], velocity, res.converged, gamma, rotation, limited


def _one_item(mean, item, metric, modulo, options):
    """:func:`_one_geodesic` for a batch item: a shape, or (shape, gamma, R) to warm-start."""
    if isinstance(item, tuple):
        return _one_geodesic(mean, item[0], metric, modulo, options, item[1:])
    return _one_geodesic(mean, item, metric, modulo, options)


def _pair_distance(a, b, metric, modulo, options):
    """Distance, status, refinement change, result code and solver steps of one pair."""
    if modulo == "none":
        res = geodesic(a, b, metric, **options.geodesic_kwargs())
        change = jnp.full_like(res.distance, jnp.nan)
    else:
        res = shape_geodesic(a, b, metric, modulo=modulo, options=options)
        change = res.refinement.relative_change
    # The code as an integer: the chunk's outputs are plain arrays (checkpoints, Dask).
    code = jnp.asarray(res.result._value, jnp.int32)
    return res.distance, res.converged, change, code, jnp.asarray(res.num_steps, jnp.int32)


# Module-level jitted batch solves: the mean and the metric are arguments and the options
# (a frozen ShapeOptions) a static key, so consecutive Karcher steps reuse one compilation.
@functools.partial(solver_jit, static_argnames=("modulo", "options", "mode"))
def _velocities_batch(mean, batch, metric, *, modulo, options, mode):
    """batch: shapes ``(b, 3, m, n)``, or (shapes, gammas, rotations) for warm starts."""

    def one(item):
        return _one_item(mean, item, metric, modulo, options)

    return jax.lax.map(one, batch) if mode == "map" else jax.vmap(one)(batch)


@functools.partial(solver_jit, static_argnames=("modulo", "options", "mode"))
def _distances_batch(pairs, metric, *, modulo, options, mode):
    def one(pair):
        return _pair_distance(pair[0], pair[1], metric, modulo, options)

    return jax.lax.map(one, pairs) if mode == "map" else jax.vmap(one)(pairs)


def _batched(batch_call: Callable, single_call: Callable, batch, strategy: str) -> tuple:
    """Run ``single_call`` over the leading axis of ``batch`` (a pytree) by ``strategy``.

    ``batch_call(batch, mode)`` is the jitted lax.map / vmap form. With several devices
    the vmap batch is sharded over a one-axis mesh (optimistix solves break under
    shard_map; jit partitions a NamedSharding-placed input instead).
    """
    size = jax.tree_util.tree_leaves(batch)[0].shape[0]
    if strategy == "loop":
        items = [jax.tree_util.tree_map(lambda x, i=i: x[i], batch) for i in range(size)]
        outs = [single_call(item) for item in items]
        return tuple(jnp.stack(parts) for parts in zip(*outs, strict=True))
    devices = jax.devices()
    if strategy == "vmap" and len(devices) > 1:
        padded = _padded(batch, size + (-size) % len(devices))
        sharding = NamedSharding(Mesh(np.asarray(devices), ("batch",)), PartitionSpec("batch"))
        batch = jax.tree_util.tree_map(lambda x: jax.device_put(x, sharding), padded)
        return tuple(o[:size] for o in batch_call(batch, strategy))
    return batch_call(batch, strategy)


def _solve_chunk(batch_call: Callable, single_call: Callable, batch, strategy: str, size: int):
    """``_batched`` over a chunk (a pytree, leading axis b) padded to ``size`` items, the
    compiled batch shape (the padding is dropped): every chunk of a job runs one compiled
    program, here or on a Dask worker. The loop strategy solves one item at a time and is
    not padded. The solves' ConvergenceWarnings are silenced: callers report each item's
    status."""
    b = jax.tree_util.tree_leaves(batch)[0].shape[0]
    padded = batch if strategy == "loop" else _padded(batch, size)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        return tuple(out[:b] for out in _batched(batch_call, single_call, padded, strategy))


def velocity_chunk(mean, chunk, metric, modulo, options, strategy, size, starts=None) -> tuple:
    """The geodesics from ``chunk`` (b, 3, m, n) to ``mean``: the _Solved fields.

    starts: None, or (gammas (b, 3, m, n), rotations (b, 3, 3)), each shape's registration
    at the previous mean: every shape is then solved twice and the lower kept
    (:func:`_one_geodesic`)."""
    batch = chunk if starts is None or modulo == "none" else (chunk, *starts)

    def batch_call(batch, mode):
        return _velocities_batch(mean, batch, metric, modulo=modulo, options=options, mode=mode)

    def single_call(item):
        return _one_item(mean, item, metric, modulo, options)

    return _solve_chunk(batch_call, single_call, batch, strategy, size)


def distance_chunk(first, second, metric, modulo, options, strategy, size) -> tuple:
    """Distance, status, refinement change, result code and solver steps of the pairs
    (first[i], second[i])."""

    def batch_call(batch, mode):
        return _distances_batch(batch, metric, modulo=modulo, options=options, mode=mode)

    def single_call(pair):
        return _pair_distance(pair[0], pair[1], metric, modulo, options)

    return _solve_chunk(batch_call, single_call, (first, second), strategy, size)


def _chunks(n: int, size: int | None):
    size = n if size is None else size
    return [(start, min(start + size, n)) for start in range(0, n, size)]


def _default_chunk(strategy: str) -> int | None:
    """Pairs per chunk when batch_size is None: the sequential strategies gain nothing from
    big chunks, so they checkpoint every pair (loop) or every 8 pairs (map); vmap takes all."""
    return {"loop": 1, "map": 8}.get(strategy)


def _fingerprint(*arrays, **settings) -> str:
    digest = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(np.asarray(a))
        digest.update(str((a.shape, a.dtype.str)).encode())
        digest.update(a.tobytes())
    digest.update(json.dumps(settings, sort_keys=True, default=str).encode())
    return digest.hexdigest()


def _load_checkpoint(path: pathlib.Path, fingerprint: str) -> dict | None:
    """The arrays of the checkpoint at ``path`` (None if there is none); an InputError
    naming the file if it cannot be read or was written for other inputs."""
    if not path.exists():
        return None
    try:
        # Our own handle: np.load leaves the file open when the archive is truncated.
        with open(path, "rb") as fh, np.load(fh, allow_pickle=False) as data:
            saved = {k: data[k] for k in data.files}
        saved_fingerprint = str(saved["fingerprint"])
    except Exception as err:  # a truncated or foreign file: zipfile, numpy or KeyError
        raise InputError(
            f"checkpoint {str(path)!r} cannot be read ({type(err).__name__}: {err}); "
            "remove it to start over"
        ) from err
    if saved_fingerprint != fingerprint:
        raise InputError(
            f"checkpoint {str(path)!r} was written for other shapes or settings "
            f"(fingerprint {saved_fingerprint[:12]} != {fingerprint[:12]}); resume it with "
            "the inputs that wrote it, or start over without resuming"
        )
    return saved


def _padded(batch, size: int):
    """``batch`` (a pytree, leading axis b <= size) padded to ``size`` by repeating its last
    item, so that every chunk has the compiled batch shape (a smaller last chunk would
    compile the whole solve again)."""

    def pad(x):
        extra = max(size - x.shape[0], 0)
        return jnp.concatenate([x, jnp.repeat(x[-1:], extra, axis=0)]) if extra else x

    return jax.tree_util.tree_map(pad, batch)


def _check_batch(modulo: str, strategy: str, batch_size) -> str:
    """Validate modulo, strategy and batch_size; resolve "auto" to this backend's strategy."""
    check_choice("modulo", modulo, MODULI)
    check_choice("strategy", strategy, STRATEGIES)
    if batch_size is not None:
        check_int("batch_size", batch_size, 1)
    return default_strategy() if strategy == "auto" else strategy


def _check_collection(shapes, options: ShapeOptions | None, name="shapes"):
    """The collection ``(K, 3, m, n)`` and its options, checked on its grid, tol resolved."""
    shapes = as_surface(shapes, name)
    if shapes.ndim != 4 or shapes.shape[0] < 2:
        raise InputError(f"{name} must have shape (K, 3, m, n) with K >= 2; got {shapes.shape}")
    options = resolve_options(options, {})
    check_grid_options(options, *shapes.shape[-2:])
    if options.tol is None:
        # Resolved here, as the solves would: one static key for every call, and a
        # fingerprint that names the tolerance used.
        options = options.replace(tol=default_tol(shapes.dtype))
    return shapes, options


def _settings(metric, modulo, options: ShapeOptions, **more) -> dict:
    return {
        "metric": [float(x) for x in jax.tree_util.tree_leaves(metric)],
        "modulo": modulo,
        "options": options.as_dict(),
        **more,
    }


class _Solved(NamedTuple):
    """The K geodesics from one mean."""

    distances: Array
    registered: Array
    velocities: Array
    converged: Array
    gammas: Array  # each shape's reparametrization onto the mean (its warm start next)
    rotations: Array
    limited: Array  # each solve ended resolution_limited (shape_geodesic's result)


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
    batch_size: int | None = None,
    strategy: str = "auto",
    checkpoint: str | os.PathLike | None = None,
    resume: bool = False,
    progress: Callable[[dict], None] | None = None,
    client=None,
    warm_start: bool = False,
) -> KarcherResult:
    """Karcher (Frechet) mean of a collection of surfaces (paper section 4.1, MATH.md 7).

    Minimizes the sum of squared distances SSD(mu) = sum_k d(mu, f_k)^2 by gradient
    steps with backtracking. At the current mean every shape is registered to it (the
    shape is reparametrized and, for modulo="rigid", rotated; the mean keeps its
    parametrization) and the K geodesics from the shapes to the mean are solved. Their
    initial velocities at the mean, v_k = T (-3 f_0 + 4 f_1 - f_2) / 2 read from the mean
    (second order, :func:`initial_velocity`), average to v = -grad SSD / (2K); modulo
    "rigid" or "diff" v loses its vertical part (G_mu-orthogonal projection off the
    directions that only reparametrize or rotate the mean, :func:`_horizontal_part`).
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

    Stops converged when the RMS distance is at most sqrt(eps) x the mean's size
    sqrt(G_mu(c, c)), c the centered mean (the distance to a dilation (1 + t) mu is about
    t times it): the shapes are one orbit ("distances_at_rounding", at step 0 for copies
    of one shape under the group; tol x RMS below would only test rounding); when
    sqrt(G_mu(v, v)) <= tol x RMS distance ("mean_velocity_small")
    or when a full step changes the SSD by less than tol relative ("sum_sq_stalled": a
    step that lowers it is taken, one that raises it is not); stops
    not converged when no halving lowers the SSD ("line_search_failed"; "resolution_limited"
    when some of the geodesics at the mean ended resolution_limited, their registration
    held at the stretch the grid resolves, so that the SSD has kinks there), after
    max_steps steps ("max_steps_reached"), or when the distances at the mean are not
    finite ("not_finite"). ``result`` and ``message`` say which.

    Args:
        shapes: ``(K, 3, m, n)`` surfaces on one grid.
        metric: split metric coefficients.
        modulo: ``"rigid"``, ``"diff"`` (:func:`shape_geodesic`) or ``"none"``
            (:func:`geodesic` with the options' degree, n_times, solver, max_steps, tol
            and scheme).
        options: :class:`ShapeOptions` of the inner solves (its defaults when None).
        init: starting mean (default: the first shape).
        max_steps: most Karcher steps (accepted updates of the mean); 0 only evaluates.
        tol: the two convergence tests above.
        step_size: the first trial step, in units of the mean velocity.
        batch_size: shapes per batched call (bounds memory); default all.
        strategy: ``"vmap"``, ``"map"``, ``"loop"`` or ``"auto"`` (:func:`default_strategy`).
        checkpoint: path of an .npz written atomically after the first solves and after
            every accepted step (the mean and its geodesics).
        resume: continue from ``checkpoint`` (refused if it belongs to other inputs).
        progress: called after the first solves (step 0) and after each accepted step
            with a dict (step, sum_sq_distances, mean_velocity_norm, step_size, num_solves,
            seconds since the call began).
        warm_start: the second, warm-started solve per shape described above (modulo
            "rigid" / "diff"; twice the solves per step, the warm one without a search).
        client: a ``dask.distributed.Client`` or a scheduler address: each step's
            chunks of shapes (``batch_size``; default one shape per chunk for "loop",
            all for "vmap", 8 for "map") run as tasks on its workers (the ``dask``
            extra). The numbers equal the in-process ones. None: this process.

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
        >>> res.converged, round(float(res.mean[2, 0, 0]), 6)  # the sphere of radius 1.5
        (True, 1.5)
    """
    strategy = _check_batch(modulo, strategy, batch_size)
    shapes, options = _check_collection(shapes, options)
    max_steps = check_int("max_steps", max_steps, 0)
    tol = check_positive("tol", tol)
    step_size = check_positive("step_size", step_size)
    mean = shapes[0] if init is None else as_surface(init, "init")
    if mean.shape != shapes.shape[1:] or mean.dtype != shapes.dtype:
        raise InputError(
            f"init must be one surface {shapes.shape[1:]} {shapes.dtype} like the shapes; "
            f"got {mean.shape} {mean.dtype}"
        )
    if modulo == "rigid":
        mean = center_unchecked(mean)
    warm_start = check_bool("warm_start", warm_start) and modulo != "none"
    settings = _settings(metric, modulo, options, step_size=step_size, tol=tol, warm=warm_start)
    fingerprint = _fingerprint(shapes, mean, **settings)
    path = None if checkpoint is None else pathlib.Path(checkpoint)

    if batch_size is None and client is not None:
        batch_size = _default_chunk(strategy)
    chunks = _chunks(shapes.shape[0], batch_size)
    size = chunks[0][1] - chunks[0][0]

    def solve_at(at, previous: _Solved | None) -> _Solved:
        starts = None
        if warm_start:
            if previous is None:  # the identity registration
                k, m, n = shapes.shape[0], *shapes.shape[-2:]
                e1 = sphere_points(m, n, shapes.dtype)
                eye = jnp.eye(3, dtype=shapes.dtype)
                starts = (jnp.broadcast_to(e1, (k, *e1.shape)), jnp.broadcast_to(eye, (k, 3, 3)))
            else:
                starts = (previous.gammas, previous.rotations)
        if pool is not None:
            return _Solved(
                *(jnp.asarray(x) for x in pool.velocities(velocity_chunk, at, chunks, size, starts))
            )
        parts = [
            velocity_chunk(
                at,
                shapes[a:b],
                metric,
                modulo,
                options,
                strategy,
                size,
                None if starts is None else tuple(x[a:b] for x in starts),
            )
            for a, b in chunks
        ]
        return _Solved(*(jnp.concatenate(p) for p in zip(*parts, strict=True)))

    def save(step):
        if path is not None:
            save_npz_atomic(
                path,
                mean=np.asarray(mean),
                step=step,
                history=np.asarray(history),
                num_solves=num_solves,
                fingerprint=fingerprint,
                **{f"solved_{k}": np.asarray(v) for k, v in solved._asdict().items()},
            )

    def report(step):
        if progress is not None:
            progress(
                {
                    "step": step,
                    "sum_sq_distances": history[-1][0],
                    "mean_velocity_norm": history[-1][1],
                    "step_size": history[-1][2],
                    "num_solves": num_solves,
                    "seconds": time.perf_counter() - started,
                }
            )

    started = time.perf_counter()
    with contextlib.ExitStack() as stack:
        pool = None
        if client is not None:
            from .._runtime.distributed import Pool

            pool = stack.enter_context(Pool(client, shapes, metric, modulo, options, strategy))
        saved = _load_checkpoint(path, fingerprint) if path is not None and resume else None
        if saved is not None:
            mean, step = jnp.asarray(saved["mean"]), int(saved["step"])
            history = [tuple(row) for row in saved["history"].tolist()]
            num_solves = int(saved["num_solves"])
            solved = _Solved(*(jnp.asarray(saved[f"solved_{k}"]) for k in _Solved._fields))
            direction = _direction(metric, mean, solved, modulo, options)
        else:
            step, num_solves = 0, 1
            solved = solve_at(mean, None)
            direction = _direction(metric, mean, solved, modulo, options)
            history = [(direction.sum_sq, direction.norm, 0.0)]
            save(step)
            report(step)

        while True:
            sum_sq, norm = direction.sum_sq, direction.norm
            rms = np.sqrt(sum_sq / shapes.shape[0])
            if not np.isfinite(sum_sq):
                result = "nonfinite"
                break
            if rms <= np.sqrt(np.finfo(np.dtype(mean.dtype)).eps) * direction.size:
                result = "distances_at_rounding"
                break
            if norm <= tol * max(rms, np.finfo(np.float64).tiny):
                result = "mean_velocity_small"
                break
            if step >= max_steps:
                result = "max_steps_reached"
                break
            s = step_size
            risen_little = False
            for _ in range(_HALVINGS + 1):
                trial_mean = mean + s * direction.velocity
                trial = solve_at(trial_mean, solved)
                num_solves += 1
                trial_sum_sq = float(jnp.sum(trial.distances**2))
                # NaN compares False: a non-finite trial is never accepted.
                if trial_sum_sq <= sum_sq:
                    break
                # A full step that raises the SSD by less than tol changed it as little as
                # one that lowers it by less than tol: the mean is stationary to within the
                # registrations' own scatter (each is a nonconvex search), and halving a
                # step the SSD cannot resolve only looks for a lower draw of that scatter.
                if s == step_size and trial_sum_sq - sum_sq <= tol * sum_sq:
                    risen_little = True
                    break
                s *= 0.5
            else:
                limited = bool(np.any(np.asarray(solved.limited)))
                result = "resolution_limited" if limited else "line_search_failed"
                break
            if risen_little:  # the mean stays where it is
                result = "sum_sq_stalled"
                break
            mean, solved, step = trial_mean, trial, step + 1
            direction = _direction(metric, mean, solved, modulo, options)
            history.append((direction.sum_sq, direction.norm, s))
            save(step)
            report(step)
            if s == step_size and sum_sq - trial_sum_sq <= tol * sum_sq:
                result = "sum_sq_stalled"
                break

    res = KarcherResult(
        mean=mean,
        distances=solved.distances,
        registered=solved.registered,
        velocities=solved.velocities,
        geodesics_converged=solved.converged,
        history=np.asarray(history),
        converged=result in _CONVERGED,
        num_steps=step,
        num_solves=num_solves,
        result=getattr(RESULTS, result),
    )
    if not res.converged:
        warnings.warn(
            f"karcher_mean: {res.message} (sum of squared distances "
            f"{res.history[:, 0].round(6).tolist()})",
            ConvergenceWarning,
            stacklevel=2,
        )
    return res


def distance_matrix(
    shapes: Float[ArrayLike, "K 3 m n"],
    metric: SplitMetric,
    *,
    modulo: str = "rigid",
    options: ShapeOptions | None = None,
    batch_size: int | None = None,
    strategy: str = "auto",
    checkpoint: str | os.PathLike | None = None,
    resume: bool = False,
    progress: Callable[[dict], None] | None = None,
    client=None,
) -> DistanceMatrixResult:
    """Pairwise shape distances: K(K-1)/2 geodesics, batched (MATH.md 7).

    Pair (i, j), i < j, uses shape_geodesic(shapes[i], shapes[j]) (or geodesic for
    modulo="none"); the record is symmetrized from the upper triangle. With
    ``checkpoint`` every finished chunk of pairs is saved atomically; ``resume=True``
    skips the chunks already done.

    Args:
        shapes: ``(K, 3, m, n)`` surfaces on one grid; metric: split metric coefficients.
        modulo, options, strategy, checkpoint, resume: as in :func:`karcher_mean`.
        progress: called after each chunk with a dict: pairs_done, pairs (in all),
            seconds (since the call began) and eta_s (the time left at this run's rate).
        batch_size: pairs per chunk (one batched call, one checkpoint); default all pairs
            for "vmap", 8 for "map" and 1 for "loop", which gain nothing from big chunks.
        client: a ``dask.distributed.Client`` or a scheduler address: the chunks run as
            tasks on its workers, checkpointed as they arrive (in any order); a worker
            lost mid-task has its task rerun by Dask. The numbers equal the in-process
            ones (each pair is solved on its own). None: this process.

    Returns:
        :class:`DistanceMatrixResult`. If some pair did not converge it also warns
        (:class:`ConvergenceWarning`) once, naming the pairs.
    """
    strategy = _check_batch(modulo, strategy, batch_size)
    shapes, options = _check_collection(shapes, options)
    k = shapes.shape[0]
    rows, cols = np.triu_indices(k, 1)
    settings = _settings(metric, modulo, options, batch_size=batch_size)
    fingerprint = _fingerprint(shapes, **settings)
    path = None if checkpoint is None else pathlib.Path(checkpoint)
    values = np.full(rows.size, np.nan)
    converged = np.zeros(rows.size, bool)
    change = np.full(rows.size, np.nan)
    codes = np.zeros(rows.size, np.int32)
    steps = np.zeros(rows.size, np.int64)
    done = np.zeros(rows.size, bool)
    saved = _load_checkpoint(path, fingerprint) if path is not None and resume else None
    if saved is not None:
        missing = {"result_codes", "num_steps"} - set(saved)
        if missing:
            raise InputError(
                f"checkpoint {str(path)!r} has no {sorted(missing)}: an earlier release wrote "
                "it; start over without resuming"
            )
        values, converged, change, codes, steps, done = (
            saved[key]
            for key in (
                "values",
                "converged",
                "refinement_change",
                "result_codes",
                "num_steps",
                "done",
            )
        )

    chunk_size = _default_chunk(strategy) if batch_size is None else batch_size
    size = min(chunk_size or rows.size, rows.size)
    todo = [(a, b) for a, b in _chunks(rows.size, chunk_size) if not done[a:b].all()]
    started, done_before = time.perf_counter(), int(done.sum())

    def finished(chunk, out):
        a, b = chunk
        values[a:b], converged[a:b], change[a:b], codes[a:b], steps[a:b] = (
            np.asarray(c)[: b - a] for c in out
        )
        done[a:b] = True
        if path is not None:
            save_npz_atomic(
                path,
                values=values,
                converged=converged,
                refinement_change=change,
                result_codes=codes,
                num_steps=steps,
                done=done,
                fingerprint=fingerprint,
            )
        if progress is not None:
            seconds = time.perf_counter() - started
            now, left = int(done.sum()), int((~done).sum())
            rate = (now - done_before) / seconds if seconds > 0 else 0.0
            progress(
                {
                    "pairs_done": now,
                    "pairs": int(rows.size),
                    "seconds": seconds,
                    "eta_s": left / rate if rate > 0 else None,
                }
            )

    if client is not None:
        from .._runtime.distributed import Pool

        with Pool(client, shapes, metric, modulo, options, strategy) as pool:
            pool.distances(distance_chunk, rows, cols, todo, size, finished)
    else:
        for a, b in todo:
            # Index per chunk: all K(K-1)/2 pairs at once would copy every surface K - 1 times.
            first, second = shapes[rows[a:b]], shapes[cols[a:b]]
            finished((a, b), distance_chunk(first, second, metric, modulo, options, strategy, size))

    def symmetric(upper, diagonal, dtype):
        matrix = np.zeros((k, k), dtype)
        matrix[rows, cols] = upper
        matrix = matrix + matrix.T if dtype is not bool else matrix | matrix.T
        np.fill_diagonal(matrix, diagonal)
        return matrix

    unconverged = np.flatnonzero(~converged)
    result = DistanceMatrixResult(
        distances=jnp.asarray(symmetric(values, 0.0, np.float64), dtype=shapes.dtype),
        pairs_converged=jnp.asarray(symmetric(converged, True, bool)),
        refinement_change=jnp.asarray(symmetric(change, 0.0, np.float64), dtype=shapes.dtype),
        converged=jnp.asarray(converged.all()),
        result=RESULTS.from_code(codes[unconverged[0]]) if unconverged.size else RESULTS.successful,
        num_steps=jnp.asarray(steps.sum()),
    )
    if not converged.all():
        failed = [
            (int(i), int(j)) for i, j, ok in zip(rows, cols, converged, strict=True) if not ok
        ]
        warnings.warn(
            f"distance_matrix: {len(failed)} of {rows.size} pairs did not converge: {failed}",
            ConvergenceWarning,
            stacklevel=2,
        )
    return result
