"""Pairwise shape distances: K(K-1)/2 geodesics, batched, checkpointed chunk by chunk,
optionally on a Dask cluster.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._errors import InputError
from .._geometry.metric import SplitMetric
from .._options import ShapeOptions
from .._results import RESULTS, status_record
from .batching import (
    check_collection,
    chunk_bounds,
    default_chunk,
    distance_chunk,
    job_settings,
)
from .checkpoints import fingerprint_of
from .driver import JobOptions, check_job, run


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
        estimate: ``(K, K)`` each pair's levels estimate (``ShapeGeodesicResult.levels``:
            the relative change of its last two levels; NaN on the diagonal, after one
            level, and on one working grid).
        grids: ``(K, K, 2)`` the finest working grid each pair was solved on (its last
            level; the collection's grid without levels); 0 on the diagonal.
        spread: ``(K, K)`` each pair's candidates' spread (``ShapeGeodesicResult.spread``:
            how far apart the final distances of the candidates it carried through the
            levels are, relative to the lowest; 0 with one candidate, NaN on the diagonal
            and on one working grid).
        converged: ``()`` every pair converged (resolved: the last level converged and
            its estimate and its candidates' spread met ``rtol``).
        result: ``successful``, or the result code of the first pair (in row-major order
            of the upper triangle) that did not converge (``elastic_jax.RESULTS``).
        num_steps: ``()`` solver steps over all pairs.
    """

    distances: Float[Array, "K K"]
    pairs_converged: Bool[Array, "K K"]
    refinement_change: Float[Array, "K K"]
    estimate: Float[Array, "K K"]
    grids: Int[Array, "K K 2"]
    spread: Float[Array, "K K"]
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
    finished one gave, and which are done (the checkpoint's arrays); the pairs done when
    this run began and the chunks still running (neither saved)."""

    values: np.ndarray
    converged: np.ndarray
    refinement_change: np.ndarray
    result_codes: np.ndarray
    num_steps: np.ndarray
    estimate: np.ndarray
    grids: np.ndarray
    spread: np.ndarray
    done: np.ndarray
    done_before: int = 0
    pending: Iterator | None = None


_SAVED = _PairsState._fields[:9]


class _PairsJob(NamedTuple):
    """A distance matrix as the driver's job (_statistics/driver.py): a step is one
    finished chunk of pairs; on a cluster the chunks finish in any order."""

    shapes: Array
    metric: SplitMetric
    modulo: str
    options: ShapeOptions
    strategy: str
    chunk: int | None  # pairs per chunk (None: all)
    fingerprint: str
    pool: object = None

    @property
    def count(self) -> int:
        return self.shapes.shape[0]

    @property
    def pairs(self) -> int:
        return self.count * (self.count - 1) // 2

    def _started(self, state: _PairsState) -> _PairsState:
        """The state with its chunks not done under way (solved lazily, one per step)."""
        rows, cols = np.triu_indices(self.count, 1)
        size = min(self.chunk or self.pairs, self.pairs)
        todo = [
            (a, b) for a, b in chunk_bounds(self.pairs, self.chunk) if not state.done[a:b].all()
        ]
        settings = (self.metric, self.modulo, self.options, self.strategy, size)
        if self.pool is not None:
            pending = self.pool.distances(distance_chunk, rows, cols, todo, size)
        else:
            # Index per chunk: all K(K-1)/2 pairs at once would copy every surface K - 1 times.
            pending = (
                ((a, b), distance_chunk(self.shapes[rows[a:b]], self.shapes[cols[a:b]], *settings))
                for a, b in todo
            )
        return state._replace(done_before=int(state.done.sum()), pending=iter(pending))

    def init(self, saved, sink) -> _PairsState:
        p = self.pairs
        nan = np.full(p, np.nan)
        zeros = np.zeros(p, bool)
        state = _PairsState(
            nan,
            zeros,
            nan.copy(),
            np.zeros(p, np.int32),
            np.zeros(p, np.int64),
            nan.copy(),
            np.zeros((p, 2), np.int32),
            nan.copy(),
            zeros.copy(),
        )
        return self._started(state)

    def restore(self, saved: dict) -> _PairsState:
        missing = set(_SAVED) - set(saved)
        if missing:
            raise InputError(
                f"the checkpoint has no {sorted(missing)}: an earlier release wrote it; start "
                "over without resuming"
            )
        return self._started(_PairsState(*(np.array(saved[key]) for key in _SAVED)))

    def step(self, state: _PairsState) -> tuple[_PairsState, bool]:
        """The state with the next finished chunk's pairs written in (in place: a copy per
        chunk would cost O(pairs) for every finished chunk)."""
        finished = next(state.pending, None)
        if finished is None:  # a failed chunk raises in next(): this is a bug if reached
            raise RuntimeError("distance_matrix: some chunks of pairs were never solved")
        (a, b), out = finished
        for field, part in zip(state[:8], out, strict=True):
            field[a:b] = np.asarray(part)[: b - a]
        state.done[a:b] = True
        return state, True

    def pool_inputs(self) -> tuple:
        return self.shapes, self.metric, self.modulo, self.options, self.strategy

    def steps(self, state: _PairsState) -> int:
        """The pairs solved (a matrix has no step limit: run is given none)."""
        return int(state.done.sum())

    def value(self, state: _PairsState) -> None:
        """None: a pair's non-finite distance is that pair's result, not the job's."""
        return None

    def terminate(self, state: _PairsState) -> RESULTS | None:
        return RESULTS.successful if state.done.all() else None

    def arrays(self, state: _PairsState) -> dict | None:
        if int(state.done.sum()) == state.done_before:  # no pair solved in this run yet
            return None
        return {key: getattr(state, key) for key in _SAVED}

    def report(self, state: _PairsState, seconds: float) -> dict | None:
        now = int(state.done.sum())
        if now == state.done_before:  # no chunk finished in this run yet
            return None
        rate = (now - state.done_before) / seconds if seconds > 0 else 0.0
        left = self.pairs - now
        return {"pairs_done": now, "pairs": self.pairs, "eta_s": left / rate if rate > 0 else None}

    def result(self, state: _PairsState, code: RESULTS) -> DistanceMatrixResult:
        """The symmetric record from the upper triangle."""
        rows, cols = np.triu_indices(self.count, 1)
        k = self.count

        def symmetric(upper, diagonal, kind):
            matrix = np.zeros((k, k, *np.shape(upper)[1:]), kind)
            matrix[rows, cols] = upper
            matrix[cols, rows] = upper
            matrix[np.arange(k), np.arange(k)] = diagonal
            return matrix

        unconverged = np.flatnonzero(~state.converged)
        first = state.result_codes[unconverged[0]] if unconverged.size else None
        dtype = self.shapes.dtype
        return DistanceMatrixResult(
            distances=jnp.asarray(symmetric(state.values, 0.0, np.float64), dtype=dtype),
            pairs_converged=jnp.asarray(symmetric(state.converged, True, bool)),
            refinement_change=jnp.asarray(
                symmetric(state.refinement_change, 0.0, np.float64), dtype=dtype
            ),
            estimate=jnp.asarray(symmetric(state.estimate, np.nan, np.float64), dtype=dtype),
            grids=jnp.asarray(symmetric(state.grids, 0, np.int32)),
            spread=jnp.asarray(symmetric(state.spread, np.nan, np.float64), dtype=dtype),
            converged=jnp.asarray(state.converged.all()),
            result=RESULTS.successful if first is None else RESULTS.from_code(first),
            num_steps=jnp.asarray(state.num_steps.sum()),
        )

    def warning(self, record: DistanceMatrixResult) -> str:
        ok = np.asarray(record.pairs_converged)
        failed = [(int(i), int(j)) for i, j in np.argwhere(np.triu(~ok, 1))]
        return f"distance_matrix: {len(failed)} of {self.pairs} pairs did not converge: {failed}"


def distance_matrix(
    shapes: Float[ArrayLike, "K 3 m n"],
    metric: SplitMetric,
    *,
    modulo: str = "rigid",
    options: ShapeOptions | None = None,
    job: JobOptions | None = None,
) -> DistanceMatrixResult:
    """Pairwise shape distances: K(K-1)/2 geodesics, batched (:ref:`math §7 <math-7>`).

    Pair (i, j), i < j, is shape_geodesic(shapes[i], shapes[j]) at ``options``: by
    default resolved by levels (``options.rtol`` with ``grid=None``; :ref:`math §10
    <math-10>`): a chunk's pairs go through the levels of working grids together, each
    level continuing every pair still going from its registration and path on the level
    below, and a pair leaves once two successive levels agree within rtol (``estimate``,
    ``grids``). ``rtol=None`` (or ``grid`` equal to the collection's grid) solves every
    pair on the collection's grid; modulo="none" is the parametrized geodesic on that
    grid. The record is symmetrized from the upper triangle. With
    ``job.checkpoint`` every finished chunk of pairs is saved atomically; ``job.resume``
    skips the chunks already done.

    Args:
        shapes: ``(K, 3, m, n)`` surfaces on one grid; metric: split metric coefficients.
        modulo, options: as in :func:`karcher_mean` (options without its levels: above).
        job: how the job runs (:class:`JobOptions`): a chunk is ``batch_size`` pairs (one
            batched call, one checkpoint, one task on a cluster; default all pairs for
            "vmap", 8 for "map" and 1 for "loop"). ``progress`` hears after each chunk:
            pairs_done, pairs (in all), seconds and eta_s (the time left at this run's
            rate). On a cluster the chunks are checkpointed as they arrive, in any order,
            and a worker lost mid-task has its task rerun by Dask; the numbers equal the
            in-process ones (each pair is solved on its own).

    Returns:
        :class:`DistanceMatrixResult`. If some pair did not converge it also warns
        (:class:`ConvergenceWarning`) once, naming the pairs.
    """
    job = check_job(job)
    shapes, options = check_collection(
        shapes, options, modulo, levels=modulo != "none", function="distance_matrix"
    )
    if modulo == "none":
        options = options.replace(rtol=None)
    strategy = job.resolved_strategy
    settings = job_settings(metric, modulo, options, batch_size=job.batch_size)
    pairs = _PairsJob(
        shapes,
        metric,
        modulo,
        options,
        strategy,
        default_chunk(strategy) if job.batch_size is None else job.batch_size,
        fingerprint_of(shapes, **settings),
    )
    return run(pairs, job)
