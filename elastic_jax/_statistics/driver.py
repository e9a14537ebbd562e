"""One driver for the collection jobs: Karcher means, distance matrices and metric fits.

Each job is an iteration in the shape of an optimistix solver: ``init`` makes the first
state, ``step`` makes the next, ``terminate`` says why the iteration stops there (a
``RESULTS`` member) or None, and ``result`` turns the last state into the job's record.
:func:`run` is the one loop around them: it opens the cluster pool, reads and writes the
checkpoint, reports progress, stops a job whose value is not finite or whose steps reach
``max_steps``, and warns when the record did not converge. What a job does between two
checkpoints is the job's; when it is kept on disk, when it has run long enough and what
the user is told is the driver's, the same for all three.

:class:`JobOptions` is the one record of how a job runs (batching, checkpoint, progress,
cluster), beside :class:`ShapeOptions`, the record of what each solve does.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import pathlib
import time
from collections.abc import Callable
from typing import Any, NamedTuple, Protocol, runtime_checkable

import numpy as np

from .._checks import check_bool, check_choice, check_int, check_progress
from .._errors import ConvergenceWarning, InputError, warn_user
from .._results import RESULTS
from .._runtime.atomic import save_npz_atomic
from .batching import STRATEGIES, default_strategy
from .checkpoints import load_checkpoint


@dataclasses.dataclass(frozen=True)
class JobOptions:
    """How a collection job runs: batching, checkpoint, progress and cluster.

    One record for :func:`karcher_mean`, :func:`distance_matrix` and :func:`fit_metric`
    (``job=``); what each geodesic does is their ``options=`` (:class:`ShapeOptions`).
    Every field is checked when the record is made (an InputError names it); change
    fields with ``job.replace(...)``.

    Fields:
        batch_size: items per batched call and per task on a cluster (bounds memory):
            shapes for a Karcher step, pairs for a distance matrix or a fit. None: all
            for ``"vmap"``, 8 for ``"map"``, 1 for ``"loop"`` (each gains nothing from
            bigger chunks), and for a Karcher step in process all shapes.
        strategy: ``"vmap"`` (one batched program), ``"map"`` (``lax.map`` in one jit),
            ``"loop"`` (a Python loop of jitted solves) or ``"auto"``
            (``default_strategy()``: this backend's).
        checkpoint: path of an .npz the job writes atomically after every finished
            step (a Karcher step, a chunk of pairs, a trust region step); None: none.
        resume: continue from ``checkpoint``; refused if the file was written for other
            inputs or settings.
        progress: called with a dict after each finished step (each job's keys are in
            its docstring; every dict has ``seconds`` since the call began).
        client: a ``dask.distributed.Client`` or a scheduler address: the chunks run as
            tasks on its workers (the ``dask`` extra); the numbers equal the in-process
            ones. None: this process.

    Example:
        >>> import elastic_jax as ej
        >>> ej.JobOptions(strategy="loop", checkpoint="mean.npz", resume=True).batch_size is None
        True
    """

    batch_size: int | None = None
    strategy: str = "auto"
    checkpoint: str | os.PathLike | None = None
    resume: bool = False
    progress: Callable[[dict], None] | None = None
    client: Any = None

    def __post_init__(self):
        if self.batch_size is not None:
            object.__setattr__(self, "batch_size", check_int("batch_size", self.batch_size, 1))
        check_choice("strategy", self.strategy, STRATEGIES)
        if self.checkpoint is not None and not isinstance(self.checkpoint, str | os.PathLike):
            raise InputError(
                f"checkpoint must be a path (str or os.PathLike) or None; "
                f"got {type(self.checkpoint).__name__}"
            )
        object.__setattr__(self, "resume", check_bool("resume", self.resume))
        check_progress(self.progress)

    def replace(self, **changes) -> JobOptions:
        """A copy with some fields changed (validated again)."""
        unknown = sorted(set(changes) - {f.name for f in dataclasses.fields(self)})
        if unknown:
            raise TypeError(f"JobOptions has no field(s) {unknown}")
        return dataclasses.replace(self, **changes)

    @property
    def resolved_strategy(self) -> str:
        """``strategy`` with ``"auto"`` resolved to this backend's."""
        return default_strategy() if self.strategy == "auto" else self.strategy


def check_job(job) -> JobOptions:
    """``job`` as a :class:`JobOptions` (its defaults when None)."""
    if job is None:
        return JobOptions()
    if not isinstance(job, JobOptions):
        raise InputError(f"job must be an elastic_jax.JobOptions or None; got {type(job).__name__}")
    return job


class Sink(NamedTuple):
    """What a job may hand the driver while it works inside ``init``: arrays to keep in
    the checkpoint (``save``; None without a checkpoint) and a progress dict (``report``,
    ``seconds`` added; None without a listener)."""

    save: Callable[[dict], None] | None
    report: Callable[[dict], None] | None


@runtime_checkable
class Job(Protocol):
    """The iteration a collection job is: an immutable record (a NamedTuple) whose
    ``pool`` :func:`run` fills through ``_replace``. States are the job's own records.
    :func:`run` refuses a job that lacks any of these."""

    fingerprint: str  # the inputs and settings a checkpoint must have been written for
    pool: Any  # the cluster link (None in this process); run sets it

    def _replace(self, **fields) -> Job:
        """A copy with ``fields`` changed (a NamedTuple's own)."""

    def pool_inputs(self) -> tuple:
        """What a cluster pool's workers hold: (shapes, metric, modulo, options, strategy)."""

    def restore(self, saved: dict) -> Any | None:
        """The state a checkpoint holds, or None when it holds none (unfinished init)."""

    def init(self, saved: dict | None, sink: Sink) -> Any:
        """The first state; ``saved`` the checkpoint of an unfinished init (or None)."""

    def step(self, state) -> tuple[Any, bool]:
        """The next state, and whether it is kept (checkpointed and reported)."""

    def steps(self, state) -> int:
        """The steps ``state`` has taken, counted against ``run``'s ``max_steps``."""

    def value(self, state) -> float | None:
        """The number the job lowers or gathers at ``state`` (None: none); ``run`` stops
        the job ``nonfinite`` when it is NaN or infinite."""

    def terminate(self, state) -> RESULTS | None:
        """Why the iteration stops at ``state`` (a ``RESULTS`` member), or None."""

    def arrays(self, state) -> dict | None:
        """What the checkpoint holds of ``state`` (arrays and numbers); None: nothing
        worth a write (no work done since the run began)."""

    def report(self, state, seconds: float) -> dict | None:
        """What progress is told of ``state`` (None: nothing)."""

    def result(self, state, code: RESULTS):
        """The job's record at the last state; ``code`` from terminate or ``run``."""

    def warning(self, record) -> str:
        """The ConvergenceWarning's text for a record that did not converge."""


# What run uses of a job, read from the protocol itself (named when a job lacks some).
_JOB_MEMBERS = tuple(
    sorted(
        {
            *Job.__annotations__,
            *(name for name, value in vars(Job).items() if callable(value) and name[:2] != "__"),
        }
    )
)


def open_pool(client, job: Job):
    """A context holding the cluster link for ``client`` to the workers that hold
    ``job.pool_inputs()`` (None: no pool, this process)."""
    if client is None:
        return contextlib.nullcontext(None)
    from .._runtime.distributed import Pool

    return Pool(client, *job.pool_inputs())


def run(job: Job, options: JobOptions | None = None, max_steps: int | None = None):
    """Iterate ``job`` from its first (or checkpointed) state until it terminates.

    ``options`` (:class:`JobOptions`, defaults when None) says how: its ``client`` opens
    the pool the job's chunks run on (``job.pool_inputs()``, closed when the job ends);
    its ``checkpoint`` is read when ``resume`` is set (refused if its fingerprint is not
    the job's) and written atomically after the first state and after every kept step, so
    that a killed job loses at most the step it was in; ``progress`` hears of the same
    states. Before each step the job stops ``nonfinite`` when ``job.value`` is not
    finite, with ``job.terminate``'s code when it gives one, and
    ``nonlinear_max_steps_reached`` once ``job.steps`` reaches ``max_steps`` (None: no
    limit). The record that does not converge warns (:class:`ConvergenceWarning`) with
    the job's text, attributed to the caller of the public function.
    """
    if not isinstance(job, Job):
        missing = [name for name in _JOB_MEMBERS if not hasattr(job, name)]
        raise TypeError(f"run: {type(job).__name__} is not a Job (it lacks {missing})")
    options = check_job(options)
    path = None if options.checkpoint is None else pathlib.Path(options.checkpoint)
    progress = options.progress
    started = time.perf_counter()

    def save(arrays: dict | None) -> None:
        if path is not None and arrays is not None:
            save_npz_atomic(path, fingerprint=job.fingerprint, **arrays)

    def report(info: dict | None) -> None:
        if progress is not None and info is not None:
            progress({**info, "seconds": time.perf_counter() - started})

    def stop(state) -> RESULTS | None:
        value = job.value(state)
        if value is not None and not np.isfinite(value):
            return RESULTS.nonfinite
        code = job.terminate(state)
        if code is None and max_steps is not None and job.steps(state) >= max_steps:
            return RESULTS.nonlinear_max_steps_reached
        return code

    with open_pool(options.client, job) as pool:
        if pool is not None:
            job = job._replace(pool=pool)
        resume = path is not None and options.resume
        saved = load_checkpoint(path, job.fingerprint) if resume else None
        state = None if saved is None else job.restore(saved)
        if state is None:
            # No checkpoint or no listener: None, so that init spends nothing on them.
            sink = Sink(save if path is not None else None, report if progress else None)
            state = job.init(saved, sink)
            save(job.arrays(state))
            report(job.report(state, time.perf_counter() - started))
        while (code := stop(state)) is None:
            state, kept = job.step(state)
            if kept:
                save(job.arrays(state))
                report(job.report(state, time.perf_counter() - started))
        record = job.result(state, code)
    if not bool(record.converged):
        warn_user(job.warning(record), ConvergenceWarning)
    return record
