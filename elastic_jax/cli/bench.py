"""``elastic-jax bench``: time a shape geodesic on the built-in pair."""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import jax
import numpy as np

from .. import geodesic, path_energy, straight_path
from .arguments import Command, common_options
from .common import Progress, environment_record, geodesic_options_from, prepare, result_fields
from .demo import builtin_pair


def run_bench(args, progress: Progress) -> dict:
    m, n = args.grid or (50, 99)
    pair = builtin_pair(m, n, args.dtype)
    (f1, f2), metric, options = prepare(args, progress, [], geodesic_options_from, pair)
    path = straight_path(f1, f2, args.times)
    grad = jax.jit(jax.value_and_grad(lambda p: path_energy(metric, p)))

    def timed(call: Callable) -> tuple[dict, object]:
        """Times of the first call and of ``repeat`` more; and the last call's output."""
        runs = []
        for _ in range(args.repeat + 1):
            start = time.perf_counter()
            out = jax.block_until_ready(call())
            runs.append(time.perf_counter() - start)
        stats = {
            "first_call_s": runs[0],
            "median_s": float(np.median(runs[1:])),
            "runs_s": runs[1:],
        }
        return stats, out

    progress(f"energy value and gradient, {m} x {n}, N = {args.times}")
    energy, _ = timed(lambda: grad(path))
    progress(f"geodesic solve, degree {args.degree}")
    solve, res = timed(lambda: geodesic(f1, f2, metric, **options))
    return {
        "command": "bench",
        "settings": {
            "grid": [m, n],
            "metric": list(args.metric),
            **options,
            "dtype": args.dtype,
            "repeat": args.repeat,
            "shapes": "straight -> bent cylinder (built-in)",
        },
        "energy_value_and_grad": energy,
        "geodesic_solve": {
            **solve,
            "num_steps": int(res.num_steps),
            "distance": float(res.distance),
        },
        **result_fields(res),
        "environment": environment_record(),
    }


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``bench`` command's arguments."""
    common_options(p, degree=7, times=13)
    p.add_argument("--repeat", type=int, default=3, help="timed calls after the first")


COMMAND = Command(
    name="bench",
    run=run_bench,
    add_arguments=add_arguments,
    help="time the energy gradient and a geodesic solve (JSON)",
)
