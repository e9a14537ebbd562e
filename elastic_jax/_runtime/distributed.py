"""Distance matrices and Karcher steps on a Dask cluster (``pip install "elastic-jax[dask]"``).

Dask distributed is the scientific Python stack's engine for independent tasks of unequal
length on many machines (LocalCluster on a laptop, dask-jobqueue on Slurm or PBS,
dask-kubernetes): it moves the data, balances the load by work stealing and reruns the
task of a worker that died. This module only cuts a job into tasks and collects them:

- A task is one chunk of pairs (or of shapes, for a Karcher step), padded to the job's
  chunk size like an in-process chunk, and computed by the same function, which the
  caller passes in (``_karcher.distance_chunk`` / ``velocity_chunk``; this module imports
  no solver): each worker compiles one program
  for the whole job, and each pair's numbers do not depend on where it ran (lax.map and
  the loop solve every item on its own; vmap runs a chunk in lockstep, as in process).
- The collection is scattered to the workers once; a task carries only its indices.
- A task runs under the caller's 64-bit setting and matmul precision (``jax.enable_x64``
  and ``jax.default_matmul_precision`` as contexts, so the worker's global configuration
  is left alone): float64 stays float64, and float32 products stay at float32's
  precision (_runtime/precision.py), on every worker.
- Results are handed back as they finish (``as_completed``): the caller checkpoints
  each one, so a job stopped at any point resumes with what had arrived.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Iterable, Iterator, Sequence

import jax
import numpy as np
from jaxtyping import ArrayLike

from .._errors import InputError
from .._options import ShapeOptions
from .precision import chosen

try:
    import distributed
    from distributed.diagnostics.plugin import WorkerPlugin
except ImportError as err:  # pragma: no cover - the extra is part of the test install
    raise ImportError(
        'a Dask client needs Dask distributed: pip install "elastic-jax[dask]"'
    ) from err


class CompilationCache(WorkerPlugin):
    """Turns JAX's persistent compilation cache on in every worker, those that join or
    restart later included (a worker is a process of its own): ``enable(*args)`` runs in
    each (a module-level function, pickled by reference)."""

    def __init__(self, enable: Callable, *args):
        self.enable, self.args = enable, args

    def setup(self, worker: distributed.Worker) -> None:
        self.enable(*self.args)


def connect(client: object):
    """``(client, owned)``: a ``distributed.Client`` as given, or a new one for a scheduler
    address (owned: the caller closes it when the job ends)."""
    if isinstance(client, distributed.Client):
        return client, False
    if isinstance(client, str | os.PathLike):
        try:
            return distributed.Client(os.fspath(client)), True
        except OSError as err:  # unreachable, refused or timed out
            raise InputError(f"client {os.fspath(client)!r}: cannot connect ({err})") from err
    raise InputError(
        "client must be a dask.distributed.Client or a scheduler address such as "
        f"'tcp://host:8786'; got {type(client).__name__}"
    )


@contextlib.contextmanager
def _as_caller(modes: tuple):
    """The caller's 64-bit setting and matmul precision (Pool._modes) in a worker."""
    x64, precision = modes
    with jax.enable_x64(x64), jax.default_matmul_precision(precision):
        yield


def _pairs_task(
    chunk: Callable,
    shapes: ArrayLike,
    rows: ArrayLike,
    cols: ArrayLike,
    settings: tuple,
    size: int,
    modes: tuple,
):
    with _as_caller(modes):
        out = chunk(shapes[rows], shapes[cols], *settings, size)
        return tuple(np.asarray(x) for x in out)


def _shapes_task(
    chunk: Callable,
    shapes: ArrayLike,
    index: ArrayLike,
    mean: ArrayLike,
    starts: tuple | None,
    settings: tuple,
    size: int,
    modes: tuple,
):
    with _as_caller(modes):
        out = chunk(mean, shapes[index], *settings, size, starts)
        return tuple(np.asarray(x) for x in out)


def _solved_pairs_task(
    chunk: Callable,
    shapes: ArrayLike,
    rows: ArrayLike,
    cols: ArrayLike,
    starts: tuple | None,
    settings: tuple,
    size: int,
    modes: tuple,
):
    with _as_caller(modes):
        out = chunk(shapes[rows], shapes[cols], *settings, size, starts)
        return tuple(np.asarray(x) for x in out)


class Pool:
    """One job's link to a cluster: the scattered collection and the solve's settings.

    Use as a context manager: a client made from an address is closed at the end, and the
    collection is released from the workers' memory.
    """

    def __init__(
        self,
        client: object,
        shapes: ArrayLike,
        metric: object,
        modulo: str,
        options: ShapeOptions,
        strategy: str,
    ):
        self.client, self._owned = connect(client)
        self._modes = (bool(jax.config.read("jax_enable_x64")), chosen())
        self._dtype = np.asarray(shapes).dtype
        # Every worker gets the collection once (broadcast): tasks carry indices only.
        self._shapes = self.client.scatter(np.asarray(shapes), broadcast=True, hash=False)
        self._settings = (metric, modulo, options, strategy)
        self._running: set = set()  # the futures submitted and not yet collected

    def __enter__(self) -> Pool:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        # A job stopped between two steps leaves no task of its behind.
        self._cancel(list(self._running))
        self._shapes.release()
        if self._owned:
            self.client.close()

    def _as_completed(self, futures: dict) -> Iterator:
        """``(key, result)`` as each task of ``futures`` (future -> key) ends, in the order
        they end."""
        self._running.update(futures)
        try:
            for future in distributed.as_completed(list(futures)):
                yield futures[future], future.result()
        finally:
            # On an error or Ctrl-C, the tasks not collected are not left running.
            self._cancel(futures)

    def _cancel(self, futures: Iterable) -> None:
        self.client.cancel([f for f in futures if not f.done()])
        self._running.difference_update(futures)

    def _in_order(self, futures: dict) -> list:
        """The results of ``futures`` (future -> its index 0..n-1), in index order."""
        parts = [None] * len(futures)
        for i, result in self._as_completed(futures):
            parts[i] = result
        return parts

    def _submit(
        self, task: Callable, chunk: Callable, *args, size: int, settings: tuple | None = None
    ):
        """One task on the scattered collection with this job's settings (or
        ``settings``); never cached by Dask (pure=False): a rerun after a resume solves
        again."""
        return self.client.submit(
            task,
            chunk,
            self._shapes,
            *args,
            self._settings if settings is None else settings,
            size,
            self._modes,
            pure=False,
        )

    def distances(
        self,
        chunk: Callable,
        rows: ArrayLike,
        cols: ArrayLike,
        chunks: Sequence[tuple[int, int]],
        size: int,
    ) -> Iterator:
        """Solve the pairs (rows[a:b], cols[a:b]) of every chunk (a, b) with
        ``chunk(first, second, *settings, size)``: ``((a, b), result)`` as each ends
        (all are submitted now, collected as they end)."""
        futures = {
            self._submit(_pairs_task, chunk, rows[a:b], cols[a:b], size=size): (a, b)
            for a, b in chunks
        }
        return self._as_completed(futures)

    def solved_pairs(
        self,
        chunk: Callable,
        rows: ArrayLike,
        cols: ArrayLike,
        chunks: Sequence[tuple[int, int]],
        size: int,
        metric: object,
        starts: tuple | None = None,
    ) -> list:
        """The pairs (rows[a:b], cols[a:b]) of every chunk (a, b) solved under ``metric``
        (not the pool's) by ``chunk(first, second, metric, modulo, options, strategy, size,
        starts[a:b])``; each chunk's result, in the chunks' order. ``starts``: None or a
        tuple of arrays with the pairs' leading axis (each pair's warm start)."""
        settings = (metric, *self._settings[1:])
        futures = {
            self._submit(
                _solved_pairs_task,
                chunk,
                rows[a:b],
                cols[a:b],
                None if starts is None else tuple(np.asarray(x[a:b]) for x in starts),
                size=size,
                settings=settings,
            ): i
            for i, (a, b) in enumerate(chunks)
        }
        return self._in_order(futures)

    def velocities(
        self,
        chunk: Callable,
        mean: ArrayLike,
        chunks: Sequence[tuple[int, int]],
        size: int,
        starts: tuple | None = None,
        options: ShapeOptions | None = None,
    ) -> tuple:
        """The geodesics from every shape to ``mean``, chunk by chunk, each by
        ``chunk(mean, shapes, *settings, size, starts)``: the fields of its result, each
        with the shapes' leading axis concatenated. ``starts``: None or (gammas,
        rotations) with that axis, each shape's warm start. ``options``: the solves'
        (a resolved mean's working grid) instead of the pool's."""
        settings = self._settings
        if options is not None:
            settings = (settings[0], settings[1], options, settings[3])
        mean = np.asarray(mean, self._dtype)
        starts = None if starts is None else tuple(np.asarray(x, self._dtype) for x in starts)

        def chunk_starts(a: int, b: int):
            return None if starts is None else tuple(x[a:b] for x in starts)

        futures = {
            self._submit(
                _shapes_task,
                chunk,
                np.arange(a, b),
                mean,
                chunk_starts(a, b),
                size=size,
                settings=settings,
            ): i
            for i, (a, b) in enumerate(chunks)
        }
        return tuple(np.concatenate(p) for p in zip(*self._in_order(futures), strict=True))
