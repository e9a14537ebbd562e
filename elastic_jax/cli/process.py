"""Process handling: exit codes, preflight checks of the inputs and the output directory,
the lock on --out, signals, and the Dask client.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import pathlib

import numpy as np

from .. import InputError, ShapeOptions, enable_compilation_cache, io
from .common import (
    CHECKPOINTS,
    KARCHER_OUTPUT_KEYS,
    KARCHER_OWN_FLAGS,
    SHAPE_COMMANDS,
    BadInput,
    Progress,
    at_least,
    check_spheres,
    is_grid_file,
    metric_from,
    positive,
    shape_options_from,
)
from .parser import build_parser
from .warmup import check_warmup

EXIT_OK, EXIT_FAILURE, EXIT_BAD_INPUT, EXIT_NOT_CONVERGED = 0, 1, 2, 3


EXIT_INTERRUPTED, EXIT_TERMINATED = 130, 143  # 128 + SIGINT, 128 + SIGTERM


LOCK_NAME = ".elastic-jax.lock"
# Written (atomically) and removed at once: proves that --out takes new files.
PROBE_NAME = ".elastic-jax.probe"


def _expand_directories(args) -> None:
    """Each directory among the inputs stands for the surface files in it, sorted by name
    (:func:`io.surface_files`)."""
    files = getattr(args, "files", None)
    if files is None or not any(pathlib.Path(f).is_dir() for f in files):
        return

    expanded = []
    for name in files:
        if not pathlib.Path(name).is_dir():
            expanded.append(name)
            continue
        try:
            expanded += [str(p) for p in io.surface_files(name)]
        except ValueError as err:
            raise BadInput(str(err)) from err
    args.files = expanded


def _read_karcher_output(args) -> dict | None:
    """pca's only input as a karcher run's mean.npz (it holds ``velocities``): its arrays,
    with that run's metric, grid, dtype and options put into ``args``; else None."""

    if args.command != "pca" or len(args.files) != 1:
        return None
    name = args.files[0]
    if not (name.lower().endswith(".npz") and pathlib.Path(name).is_file()):
        return None
    try:
        with np.load(name) as data:
            if "velocities" not in data.files:
                return None
            missing = [k for k in KARCHER_OUTPUT_KEYS if k not in data.files]
            if missing:
                raise BadInput(f"{name}: a karcher output without {', '.join(missing)}")
            saved = {k: data[k] for k in KARCHER_OUTPUT_KEYS}
    except (OSError, ValueError) as err:
        raise BadInput(f"{name}: not a readable .npz ({err})") from err
    defaults = vars(build_parser().parse_args(["pca", name]))
    given = [
        flag for dest, flag in KARCHER_OWN_FLAGS.items() if getattr(args, dest) != defaults[dest]
    ]
    if given:
        raise BadInput(
            f"pca on a karcher output ({name}) uses that run's mean, metric and options; "
            f"leave out {', '.join(given)}"
        )
    settings = json.loads(str(saved["settings"]))
    fields = {f.name for f in dataclasses.fields(ShapeOptions)}
    args.shape_options = ShapeOptions(**{k: v for k, v in settings.items() if k in fields})
    args.metric, args.dtype = tuple(settings["metric"]), settings["dtype"]
    args.modulo, args.grid = settings["modulo"], tuple(settings["grid"])
    saved["settings"], saved["inputs"] = settings, json.loads(str(saved["inputs"]))
    return saved


def check_learn(learn: str) -> None:
    """--learn: at least two different letters of abcd (the coefficients' sum is fixed)."""
    if len(set(learn)) != len(learn) or not set(learn) <= set("abcd") or len(learn) < 2:
        raise BadInput(
            f"--learn {learn}: learn must name at least two different coefficients of "
            "'abcd' (their sum is fixed, so one alone cannot move)"
        )


def preflight(args) -> None:
    """Refuse bad options before reading any file or starting any work."""
    _expand_directories(args)
    args.karcher_output = _read_karcher_output(args)
    check_spheres(args)
    if getattr(args, "on_target_mesh", False) and is_grid_file(args.target):
        raise BadInput(
            f"--on-target-mesh: the target {args.target} is a grid file; the path's frames "
            "are painted on a target mesh's vertices"
        )
    metric_from(args)
    if args.grid is not None:
        try:  # the record checks a working grid as the solves will
            ShapeOptions(grid=tuple(args.grid))
        except InputError as err:
            raise BadInput(f"--grid {args.grid[0]} {args.grid[1]}: {err}") from err
    if args.command in SHAPE_COMMANDS and args.karcher_output is None:
        args.shape_options = shape_options_from(args)
    else:
        at_least("--degree", args.degree, 1)
        at_least("--times", args.times, 3)
        if getattr(args, "max_steps", None) is not None:
            at_least("--max-steps", args.max_steps, 1)
    if args.command == "warmup":
        check_warmup(args)
    if args.command in ("karcher", "pca", "distances") and args.karcher_output is None:
        if len(args.files) < 2:
            also = " (or one karcher run's mean.npz)" if args.command == "pca" else ""
            raise BadInput(
                f"{args.command} needs at least 2 surface files{also}; got {len(args.files)}"
            )
    if args.command == "fit-metric":
        if len(args.files) < 3:
            raise BadInput(f"fit-metric needs at least 3 surface files; got {len(args.files)}")
        if (args.test is None) != (args.test_labels is None):
            raise BadInput("--test and --test-labels go together")
        if args.test is not None and args.labels is None:
            raise BadInput("--test scores a classification: it needs --labels")

        check_learn(args.learn)
        for flag in ("--labels", "--targets", "--test-labels"):
            name = getattr(args, flag[2:].replace("-", "_"))
            if name is not None and not pathlib.Path(name).is_file():
                raise BadInput(f"{flag} {name}: no such file")
        at_least("--fit-steps", args.fit_steps, 0)
        positive("--fit-tol", args.fit_tol)
        positive("--temperature", args.temperature)
    if args.command in ("karcher", "pca"):
        at_least("--karcher-steps", args.karcher_steps, 0)
        positive("--tol", args.tol)
        positive("--step-size", args.step_size)
    if args.command == "pca":
        at_least("--modes", args.modes, 1)
        positive("--sigmas", args.sigmas)
        at_least("--mode-times", args.mode_times, 3)
        if args.scheme == "central":
            raise BadInput(
                "--scheme central: the mode paths are shot, and the central scheme cannot be "
                "(its energy couples five nodes); use midpoint or forward"
            )
    if args.command == "shoot":
        if not math.isfinite(args.scale):
            raise BadInput(f"--scale {args.scale}: must be a finite number")
        if args.tol is not None:
            positive("--tol", args.tol)
        at_least("--max-newton", args.max_newton, 1)
        if not pathlib.Path(args.velocity).is_file():
            raise BadInput(f"{args.velocity}: no such file (the velocity .npz)")
    if getattr(args, "batch_size", None) is not None:
        at_least("--batch-size", args.batch_size, 1)
    if getattr(args, "workers", None) is not None:
        at_least("--workers", args.workers, 1)
    if args.command == "bench":
        at_least("--repeat", args.repeat, 1)


def claim_out(args, stack: contextlib.ExitStack) -> None:
    """Make --out, prove it writable, lock it for this run, and sweep what killed runs left.

    All before any file is read or any solve starts, so that a bad --out never costs a
    solve. The lock is advisory (flock on ``.elastic-jax.lock``): a second run on the
    same directory is refused (BadInput) instead of overwriting the first one's
    checkpoint. A checkpoint already there is continued with --resume or discarded with
    --overwrite, never silently.
    """
    out = args.out
    if out.exists() and not out.is_dir():
        raise BadInput(f"--out {out}: exists and is not a directory")
    if not out.exists():
        # A run refused before writing anything leaves no empty directory behind
        # (rmdir fails, harmlessly, once the directory holds files).
        stack.callback(_remove_if_empty, out)
    try:
        out.mkdir(parents=True, exist_ok=True)
        stack.enter_context(_locked(out / LOCK_NAME))
        io.write_text_atomic(out / PROBE_NAME, "").unlink()
    except BlockingIOError:
        raise BadInput(
            f"--out {out}: another elastic-jax run is writing there (it holds {LOCK_NAME}); "
            "wait for it or choose another --out"
        ) from None
    except OSError as err:
        raise BadInput(f"--out {out}: not a writable directory ({err.strerror or err})") from err
    # Temporaries of atomic writes that a killed run left behind: nobody else writes here
    # while we hold the lock.
    for stale in io.stale_temporaries(out):
        stale.unlink(missing_ok=True)
    checkpoint = CHECKPOINTS.get(args.command)
    if checkpoint and (out / checkpoint).exists() and not (args.resume or args.overwrite):
        raise BadInput(
            f"--out {out} holds the checkpoint {checkpoint} of an earlier run; continue it "
            "with --resume or discard it with --overwrite"
        )


def dask_client(args, stack: contextlib.ExitStack, progress: Progress):
    """The Dask client of --workers or --scheduler (None without them), closed with the
    stack; its workers share the compilation cache unless --no-cache."""
    workers, address = getattr(args, "workers", None), getattr(args, "scheduler", None)
    if workers is None and address is None:
        return None
    try:
        import distributed
    except ImportError:
        raise BadInput(
            '--workers and --scheduler need Dask distributed: pip install "elastic-jax[dask]"'
        ) from None
    if workers is not None:
        progress(f"starting a local Dask cluster of {workers} worker processes")
        cluster = stack.enter_context(
            distributed.LocalCluster(
                n_workers=workers,
                threads_per_worker=1,
                processes=True,
                # The scheduler's web server on a free local port: with dashboard_address
                # None it still tries 8787, and warns when another cluster holds it.
                dashboard_address="127.0.0.1:0",
            )
        )
        client = stack.enter_context(distributed.Client(cluster))
    else:
        progress(f"connecting to the Dask scheduler at {address}")
        try:
            client = stack.enter_context(distributed.Client(address, timeout="30s"))
        except OSError as err:
            raise BadInput(f"--scheduler {address}: cannot connect ({err})") from err
    if not args.no_cache:
        enable_compilation_cache(args.cache_dir, client=client, exported=not args.no_export)
    return client


def _remove_if_empty(directory: pathlib.Path) -> None:
    with contextlib.suppress(OSError):
        directory.rmdir()


@contextlib.contextmanager
def _locked(path: pathlib.Path):
    """Hold an exclusive advisory lock on ``path`` (BlockingIOError if another holds it)."""
    import fcntl

    while True:
        fh = open(path, "a+")  # noqa: SIM115 (held for the whole run)
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BaseException:
            fh.close()
            raise
        # The previous holder may have removed the file between our open and our lock:
        # then we hold a lock on a file nobody else can find; take the new one.
        try:
            same = os.fstat(fh.fileno()).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        fh.close()
    try:
        fh.write(f"{os.getpid()}\n")
        fh.flush()
        yield
    finally:
        path.unlink(missing_ok=True)
        fh.close()
