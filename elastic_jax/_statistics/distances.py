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

from .._errors import ConvergenceWarning, InputError
from .._geometry.metric import SplitMetric
from .._options import ShapeOptions
from .._results import RESULTS, result_message
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
    strategy = check_batch(modulo, strategy, batch_size)
    shapes, options = check_collection(shapes, options)
    k = shapes.shape[0]
    rows, cols = np.triu_indices(k, 1)
    settings = job_settings(metric, modulo, options, batch_size=batch_size)
    fingerprint = fingerprint_of(shapes, **settings)
    path = None if checkpoint is None else pathlib.Path(checkpoint)
    values = np.full(rows.size, np.nan)
    converged = np.zeros(rows.size, bool)
    change = np.full(rows.size, np.nan)
    codes = np.zeros(rows.size, np.int32)
    steps = np.zeros(rows.size, np.int64)
    done = np.zeros(rows.size, bool)
    saved = load_checkpoint(path, fingerprint) if path is not None and resume else None
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

    chunk_size = default_chunk(strategy) if batch_size is None else batch_size
    size = min(chunk_size or rows.size, rows.size)
    todo = [(a, b) for a, b in chunk_bounds(rows.size, chunk_size) if not done[a:b].all()]
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
