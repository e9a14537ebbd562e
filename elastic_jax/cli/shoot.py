"""``elastic-jax shoot``: the geodesic from a surface along an initial velocity."""

from __future__ import annotations

import argparse
import json
import time

import jax
import numpy as np

from .. import ShapeOptions, io, shoot
from .arguments import Command, input_options, io_options
from .common import (
    SURFACE_FILE,
    BadInput,
    Progress,
    environment_record,
    input_settings,
    json_float,
    json_floats,
    prepare,
    result_fields,
    write_path,
)

# The schemes a path can be shot with: those whose energy couples each node to its two
# neighbours only (shoot refuses "central", whose energy couples five nodes).
SHOOTING_SCHEMES = tuple(s for s in ShapeOptions.CHOICES["scheme"] if s != "central")


def _load_velocity(name: str, shape: tuple, dtype: str):
    """The array ``v`` (or ``velocity``) of an .npz, checked against the surface's shape."""

    try:
        with np.load(name) as data:
            arrays = {k: np.asarray(data[k]) for k in ("v", "velocity") if k in data.files}
            found = ", ".join(data.files) or "none"
    except (OSError, ValueError) as err:
        raise BadInput(f"{name}: not a readable .npz ({err})") from err
    if not arrays:
        raise BadInput(f"{name}: no array v or velocity in it (it has {found})")
    v = arrays.get("v", arrays.get("velocity"))
    if v.shape != shape:
        raise BadInput(
            f"{name}: the velocity has shape {v.shape}, the surface {shape}; a velocity "
            "lives on its surface's grid (resampling one would change what it means)"
        )
    if not np.issubdtype(v.dtype, np.floating) or not np.isfinite(v).all():
        raise BadInput(f"{name}: the velocity must be finite real numbers")
    return v.astype(dtype)


def run_shoot(args, progress: Progress) -> dict:
    (f,), metric, _ = prepare(args, progress, [args.source], lambda a: None)
    m, n = f.shape[1:]
    v = args.scale * _load_velocity(args.velocity, f.shape, args.dtype)
    options = {"n_times": args.times, "degree": args.degree, "scheme": args.scheme}
    options.update(tol=args.tol, max_newton=args.max_newton)
    progress(
        f"shooting on {m} x {n}, degree {args.degree}, N = {args.times} "
        "(one Newton solve per step; the first call compiles)"
    )
    start = time.perf_counter()
    res = jax.block_until_ready(shoot(f, v, metric, **options))
    seconds = time.perf_counter() - start
    speeds = np.asarray(res.speeds)
    residuals = np.asarray(res.residuals)
    n_valid = int(res.n_valid)
    progress(
        f"speed {speeds[0]:.6g} -> {speeds[-1]:.6g}, largest step residual "
        f"{np.nanmax(residuals):.3g}, converged {bool(res.converged)}"
    )
    settings = {
        "metric": list(args.metric),
        "grid": [m, n],
        "scale": args.scale,
        **options,
        "dtype": args.dtype,
        **input_settings(args),
    }
    path = np.asarray(res.path)
    if n_valid < path.shape[0]:
        last = path.shape[0] - 1
        progress(f"nodes {n_valid}..{last} did not solve: writing nodes 0..{n_valid - 1}")
    files = write_path(args.out, path[:n_valid], settings, progress)
    files.append(
        str(
            io.save_npz_atomic(
                args.out / "shoot.npz",
                n_valid=n_valid,
                endpoint=path[-1],
                velocity=np.asarray(res.velocity),
                speeds=speeds,
                residuals=residuals,
                newton_steps=np.asarray(res.newton_steps),
                settings=json.dumps(settings),
            )
        )
    )
    return {
        "command": args.command,
        "inputs": [args.source, args.velocity],
        "settings": settings,
        # The path's length: the sum of its steps' speeds over T (constant on a geodesic).
        "length": json_float(np.mean(speeds)),
        "n_valid": n_valid,
        "speeds": json_floats(speeds),
        "speed_drift": json_float(speeds[-1] / speeds[0] - 1) if speeds[0] > 0 else None,
        "residuals": json_floats(residuals),
        "newton_steps": [int(x) for x in np.asarray(res.newton_steps)],
        **result_fields(res),
        "seconds": seconds,
        "files": files,
        "environment": environment_record(),
    }


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``shoot`` command's arguments."""
    p.add_argument("source", help=SURFACE_FILE)
    p.add_argument(
        "velocity",
        help="the initial velocity: .npz with array v (or velocity) of the surface's shape "
        "(3, m, n), e.g. the pca command's modeK_velocity.npz",
    )
    io_options(p)
    input_options(p)
    p.add_argument(
        "--degree", type=int, default=7, help="spherical-harmonic degree of each step's solve"
    )
    p.add_argument("--times", type=int, default=13, help="time points N, ends included")
    p.add_argument("--scale", type=float, default=1.0, help="multiplies the velocity")
    p.add_argument(
        "--scheme",
        choices=SHOOTING_SCHEMES,
        default="midpoint",
        help="time discretization of the path energy (central cannot be shot)",
    )
    p.add_argument(
        "--tol",
        type=float,
        default=None,
        help="each step's Newton tolerance (default: 1e-10 in float64, 1e-4 in float32)",
    )
    p.add_argument("--max-newton", type=int, default=20, help="Newton iterations per step")


COMMAND = Command(
    name="shoot",
    run=run_shoot,
    add_arguments=add_arguments,
    help="geodesic from a surface with an initial velocity (exponential map)",
    description="Shoot the discrete geodesic from the source surface with initial "
    "velocity --scale times the velocity file's (elastic_jax.shoot). Writes the path "
    "(path/: a mesh per time point and path.npz), shoot.npz (endpoint, final "
    "velocity, speeds, residuals) and a figure.",
)
