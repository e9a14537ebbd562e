"""Pairwise shape distances: K(K-1)/2 geodesics, batched, checkpointed chunk by chunk,
optionally on a Dask cluster.
"""

from __future__ import annotations

import os
import pathlib
import time
import warnings
from collections.abc import Callable
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._checks import check_progress
from .._errors import ConvergenceWarning, InputError
from .._geometry.metric import SplitMetric
from .._options import ShapeOptions
from .._results import RESULTS, status_record
from .._runtime.atomic import save_npz_atomic
from .batching import (
    check_batch,
    check_collection,
    chunk_bounds,
    default_chunk,
    distance_chunk,
    job_settings,
)
from .checkpoints import fingerprint_of, load_checkpoint


@status_record
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

    def _explain(self, words: str) -> str:
        if bool(self.converged):
            return ""
        upper = np.triu(~np.asarray(self.pairs_converged), 1)
        first = tuple(int(i) for i in np.argwhere(upper)[0])
        return (
            f"{int(upper.sum())} of {upper.shape[0] * (upper.shape[0] - 1) // 2} pairs did not "
            f"converge; the first, {first}: {words}"
        )


class _PairsState(NamedTuple):
    """The pairs (i, j), i < j, in row-major order of the upper triangle: what each
    finished one gave, and which are done. Its fields are the checkpoint's arrays."""

    values: np.ndarray
    converged: np.ndarray
    refinement_change: np.ndarray
    result_codes: np.ndarray
    num_steps: np.ndarray
    done: np.ndarray


class _PairsJob(NamedTuple):
    """A distance matrix as init / step / terminate over a :class:`_PairsState`; a step is
    one finished chunk of pairs (chunks may finish in any order on a cluster).
    :func:`distance_matrix` is the driver: chunks, checkpoints, progress, the pool."""

    count: int  # K, the shapes

    @property
    def rows(self) -> np.ndarray:
        return np.triu_indices(self.count, 1)[0]

    @property
    def cols(self) -> np.ndarray:
        return np.triu_indices(self.count, 1)[1]

    @property
    def pairs(self) -> int:
        return self.count * (self.count - 1) // 2

    def init(self) -> _PairsState:
        p = self.pairs
        nan = np.full(p, np.nan)
        return _PairsState(
            nan,
            np.zeros(p, bool),
            nan.copy(),
            np.zeros(p, np.int32),
            np.zeros(p, np.int64),
            np.zeros(p, bool),
        )

    def restore(self, saved: dict, path) -> _PairsState:
        missing = set(_PairsState._fields) - set(saved)
        if missing:
            raise InputError(
                f"checkpoint {str(path)!r} has no {sorted(missing)}: an earlier release wrote "
                "it; start over without resuming"
            )
        return _PairsState(*(np.array(saved[key]) for key in _PairsState._fields))

    def step(self, state: _PairsState, chunk: tuple[int, int], out: tuple) -> _PairsState:
        """The state with chunk (a, b)'s pairs done: ``out`` is distance_chunk's output.
        Written in place: a copy per chunk would cost O(pairs) for every finished chunk."""
        a, b = chunk
        for field, part in zip(state[:-1], out, strict=True):
            field[a:b] = np.asarray(part)[: b - a]
        state.done[a:b] = True
        return state

    def terminate(self, state: _PairsState) -> bool:
        return bool(state.done.all())

    def result(self, state: _PairsState, dtype) -> DistanceMatrixResult:
        """The symmetric record from the upper triangle."""
        rows, cols, k = self.rows, self.cols, self.count

        def symmetric(upper, diagonal, kind):
            matrix = np.zeros((k, k), kind)
            matrix[rows, cols] = upper
            matrix = matrix + matrix.T if kind is not bool else matrix | matrix.T
            np.fill_diagonal(matrix, diagonal)
            return matrix

        unconverged = np.flatnonzero(~state.converged)
        first = state.result_codes[unconverged[0]] if unconverged.size else None
        return DistanceMatrixResult(
            distances=jnp.asarray(symmetric(state.values, 0.0, np.float64), dtype=dtype),
            pairs_converged=jnp.asarray(symmetric(state.converged, True, bool)),
            refinement_change=jnp.asarray(
                symmetric(state.refinement_change, 0.0, np.float64), dtype=dtype
            ),
            converged=jnp.asarray(state.converged.all()),
            result=RESULTS.successful if first is None else RESULTS.from_code(first),
            num_steps=jnp.asarray(state.num_steps.sum()),
        )


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
    """Pairwise shape distances: K(K-1)/2 geodesics, batched (:ref:`math §7 <math-7>`).

    Pair (i, j), i < j, uses shape_geodesic(shapes[i], shapes[j]) (or geodesic for
    modulo="none") on the collection's own grid: ``options.rtol`` and ``levels`` are not
    used here (rtol is set to None), so these distances are not resolved by levels as
    shape_geodesic's and a resolved karcher_mean's are (:ref:`math §10 <math-10>`). For
    resolved distances, resample the shapes to the grid their levels resolve at (a
    resolved mean's ``level_distances`` tells which) or solve the pairs with
    shape_geodesic. The record is symmetrized from the upper triangle. With
    ``checkpoint`` every finished chunk of pairs is saved atomically; ``resume=True``
    skips the chunks already done.

    Args:
        shapes: ``(K, 3, m, n)`` surfaces on one grid; metric: split metric coefficients.
        modulo, options, strategy, checkpoint, resume: as in :func:`karcher_mean`
            (options without its levels: above).
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
    strategy = check_batch(modulo, strategy, batch_size)
    check_progress(progress)
    shapes, options = check_collection(shapes, options)
    k = shapes.shape[0]
    settings = job_settings(metric, modulo, options, batch_size=batch_size)
    fingerprint = fingerprint_of(shapes, **settings)
    path = None if checkpoint is None else pathlib.Path(checkpoint)
    job = _PairsJob(k)
    state = job.init()
    saved = load_checkpoint(path, fingerprint) if path is not None and resume else None
    if saved is not None:
        state = job.restore(saved, path)

    chunk_size = default_chunk(strategy) if batch_size is None else batch_size
    size = min(chunk_size or job.pairs, job.pairs)
    todo = [(a, b) for a, b in chunk_bounds(job.pairs, chunk_size) if not state.done[a:b].all()]
    started, done_before = time.perf_counter(), int(state.done.sum())

    def finished(chunk, out):
        nonlocal state
        state = job.step(state, chunk, out)
        if path is not None:
            save_npz_atomic(path, fingerprint=fingerprint, **state._asdict())
        if progress is not None:
            seconds = time.perf_counter() - started
            now, left = int(state.done.sum()), int((~state.done).sum())
            rate = (now - done_before) / seconds if seconds > 0 else 0.0
            progress(
                {
                    "pairs_done": now,
                    "pairs": job.pairs,
                    "seconds": seconds,
                    "eta_s": left / rate if rate > 0 else None,
                }
            )

    rows, cols = job.rows, job.cols
    if client is not None:
        from .._runtime.distributed import Pool

        with Pool(client, shapes, metric, modulo, options, strategy) as pool:
            pool.distances(distance_chunk, rows, cols, todo, size, finished)
    else:
        for a, b in todo:
            # Index per chunk: all K(K-1)/2 pairs at once would copy every surface K - 1 times.
            first, second = shapes[rows[a:b]], shapes[cols[a:b]]
            finished((a, b), distance_chunk(first, second, metric, modulo, options, strategy, size))
    if not job.terminate(state):  # a failed chunk raises above: this is a bug if reached
        raise RuntimeError("distance_matrix: some chunks of pairs were never solved")

    result = job.result(state, shapes.dtype)
    converged = state.converged
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
