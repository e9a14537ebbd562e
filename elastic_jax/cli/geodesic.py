"""``elastic-jax geodesic``: the geodesic between two parametrized surfaces."""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np

from .. import geodesic
from .arguments import Command, common_options, input_options
from .common import (
    SURFACE_FILE,
    Progress,
    environment_record,
    geodesic_options_from,
    input_settings,
    prepare,
    result_fields,
    write_path,
)


def run_geodesic(args, progress: Progress, surfaces=None, label=None) -> dict:
    files = [args.source, args.target] if surfaces is None else []
    (f1, f2), metric, options = prepare(args, progress, files, geodesic_options_from, surfaces)
    m, n = f1.shape[1:]
    progress(
        f"solving the geodesic on {m} x {n}, degree {args.degree}, N = {args.times} "
        "(the first call compiles)"
    )
    start = time.perf_counter()
    res = jax.block_until_ready(geodesic(f1, f2, metric, **options))
    seconds = time.perf_counter() - start
    progress(f"distance {float(res.distance):.6g} after {int(res.num_steps)} steps")
    settings = {
        "metric": list(args.metric),
        "grid": [m, n],
        **options,
        "dtype": args.dtype,
        **input_settings(args),
    }
    summary = {
        "command": args.command,
        "inputs": label or [args.source, args.target],
        "settings": settings,
        "distance": float(res.distance),
        "energy": float(res.energy),
        "straight_energy": float(res.straight_energy),
        **result_fields(res),
        "grad_norm": float(res.grad_norm),
        "seconds": seconds,
        "environment": environment_record(),
    }
    summary["files"] = write_path(args.out, np.asarray(res.path), settings, progress)
    return summary


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``geodesic`` command's arguments."""
    p.add_argument("source", help=SURFACE_FILE)
    p.add_argument("target", help=SURFACE_FILE)
    common_options(p, degree=7, times=13)
    input_options(p)


COMMAND = Command(
    name="geodesic",
    run=run_geodesic,
    add_arguments=add_arguments,
    help="geodesic between two parametrized surfaces",
)
