"""``elastic-jax demo``: a shape geodesic between two built-in surfaces."""

from __future__ import annotations

import argparse

import numpy as np

from .. import io, shapes
from .arguments import Command, common_options
from .common import Progress
from .geodesic import run_geodesic


def builtin_pair(m: int, n: int, dtype: str):
    """The demo's and bench's surfaces ``(2, 3, m, n)``: a straight and a bent cylinder."""

    straight = shapes.sample(shapes.bent_cylinder, m, n, curvature=0.0)
    bent = shapes.sample(shapes.bent_cylinder, m, n, curvature=0.6, half_length=1.2)
    return np.stack([straight, bent]).astype(dtype)


def run_demo(args, progress: Progress) -> dict:

    f1, f2 = pair = builtin_pair(*(args.grid or (25, 49)), args.dtype)
    args.out.mkdir(parents=True, exist_ok=True)
    inputs = [
        str(io.save_surface(f1, args.out / "straight_cylinder.npz")),
        str(io.save_surface(f2, args.out / "bent_cylinder.npz")),
    ]
    summary = run_geodesic(args, progress, pair, label=inputs)
    summary["files"] = inputs + summary["files"]
    return summary


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``demo`` command's arguments."""
    common_options(p, degree=7, times=10)


COMMAND = Command(
    name="demo",
    run=run_demo,
    add_arguments=add_arguments,
    help="a geodesic between two built-in surfaces, with figures",
)
