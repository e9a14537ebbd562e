"""The ``elastic-jax`` command line: geodesics, shape geodesics, Karcher means, distances,
fitting the metric.

Every command reads surfaces (``.npz`` with array ``f``, the authors' ``.mat``, or any mesh
trimesh reads, resampled by :func:`elastic_jax.io.mesh_to_grid`), computes, and writes into
``--out DIR``: the arrays (``.npz``), meshes (``.ply``), figures (``.png``) and
``summary.json``. The summary is also printed on stdout. All files are written atomically,
so Ctrl-C never leaves half a file; ``karcher``, ``distances`` and ``fit-metric``
checkpoint every finished step or chunk and continue with ``--resume``. A directory among
the inputs stands for the surface files in it. The statistics run in two commands:
``karcher`` writes ``mean.npz`` (the mean, the velocities at it, the settings) and ``pca``
on that file computes the modes and their figure without solving again.

Exit codes: 0 done and converged; 2 bad input (unreadable file, invalid surface or mesh,
bad option, an --out that is not a writable directory or that another run holds, a
checkpoint there without --resume or --overwrite), reported in one line before any work;
3 finished but the solver did not converge (results are still written); 130 interrupted
(Ctrl-C), 143 terminated (SIGTERM), both leaving only complete files; 1 anything else
(a bug: please report it).
"""

from __future__ import annotations

import contextlib
import sys
import warnings
from collections.abc import Sequence

import jax

from .. import ConvergenceWarning, InputError, enable_compilation_cache
from .arguments import join_negative_values
from .common import BadInput, Progress, one_line, write_summary
from .parser import COMMANDS as _COMMANDS
from .parser import build_parser
from .process import (
    EXIT_BAD_INPUT,
    EXIT_FAILURE,
    EXIT_INTERRUPTED,
    EXIT_NOT_CONVERGED,
    EXIT_OK,
    EXIT_TERMINATED,
    LOCK_NAME,
    claim_out,
    dask_client,
    preflight,
)
from .signals import Terminated, handled_signals, raise_if_signalled

__all__ = [
    "COMMANDS",
    "EXIT_BAD_INPUT",
    "EXIT_FAILURE",
    "EXIT_INTERRUPTED",
    "EXIT_NOT_CONVERGED",
    "EXIT_OK",
    "EXIT_TERMINATED",
    "LOCK_NAME",
    "BadInput",
    "build_parser",
    "main",
]

# Each command's run(args, progress) by name.
COMMANDS = {command.name: command.run for command in _COMMANDS}


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``elastic-jax`` (and ``python -m elastic_jax``); returns the exit code."""
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser().parse_args(join_negative_values(argv))

    if args.dtype == "float64":
        # The program chooses its precision (the library never changes JAX's global config);
        # float32 runs cast their inputs instead, so an in-process call changes nothing else.
        jax.config.update("jax_enable_x64", True)
    if not args.no_cache and jax.config.jax_compilation_cache_dir is None:
        # Solves compile for 5-60 s and a command runs once per process: keep the
        # executables (and the exported shape solve) on disk; a program's choice, the
        # library never sets this by itself. A caller that set a cache keeps its own.
        try:
            enable_compilation_cache(args.cache_dir, exported=not args.no_export)
        except OSError as err:  # e.g. a read-only home: the run goes on, compiling
            print(
                f"elastic-jax: --cache-dir {args.cache_dir}: cannot be created ({err}); "
                "compiling without a cache",
                file=sys.stderr,
            )

    progress = Progress(args.quiet)
    with handled_signals():
        return _run(args, progress)


def _run(args, progress: Progress) -> int:
    try:
        # Every function a command calls is public (the package's and io's), and each
        # traces its float32 products at full precision itself (_runtime/precision.py).
        with warnings.catch_warnings(), contextlib.ExitStack() as stack:
            # Non-convergence is reported in the summary and the exit code instead.
            warnings.simplefilter("ignore", ConvergenceWarning)
            preflight(args)
            claim_out(args, stack)
            args.client = dask_client(args, stack, progress)
            summary = COMMANDS[args.command](args, progress)
            raise_if_signalled()
            write_summary(args.out, summary)
            progress(f"done; summary in {args.out / 'summary.json'}")
    except (BadInput, InputError) as err:
        print(f"elastic-jax {args.command}: bad input: {one_line(err)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt as err:
        how = "terminated" if isinstance(err, Terminated) else "interrupted"
        print(
            f"elastic-jax {args.command}: {how}; every file in {args.out} is complete "
            "(karcher, pca, distances and fit-metric continue with --resume)",
            file=sys.stderr,
        )
        return EXIT_TERMINATED if isinstance(err, Terminated) else EXIT_INTERRUPTED
    return EXIT_NOT_CONVERGED if summary.get("converged") is not True else EXIT_OK
