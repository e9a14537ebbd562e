"""``elastic-jax karcher``: the Karcher mean of a collection, checkpointed and resumable."""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from .. import RESULTS, io, karcher_mean
from .arguments import (
    Command,
    batch_options,
    input_options,
    karcher_options,
    rtol_option,
    shape_options,
)
from .common import (
    CHECKPOINTS,
    SURFACE_FILES,
    Progress,
    collection_settings,
    environment_record,
    job_options,
    json_floats,
    prepare,
    result_fields,
    shape_geodesic_options,
    write_figure,
)


def solve_karcher(args, progress: Progress):
    """The Karcher mean of ``args.files`` with its files and summary: (result, metric,
    options, summary), the summary holding ``files`` already written."""

    from .. import plot

    shapes, metric, options = prepare(args, progress, args.files, shape_geodesic_options)
    m, n = shapes.shape[2:]
    settings = collection_settings(args, m, n, options)
    settings.update(
        karcher_steps=args.karcher_steps,
        tol=args.tol,
        step_size=args.step_size,
        warm_start=args.warm_start,
    )
    checkpoint = args.out / CHECKPOINTS["karcher"]

    def report(info):
        if "shape" in info:
            # A resolved mean's first solves, one line per level of each shape's solve.
            if info["stage"] == "level":
                state = "converged" if info["converged"] else "not converged"
                progress(
                    f"first solves, shape {info['shape'] + 1}/{info['shapes']}: level "
                    f"{info['level']}/{info['levels']} ({info['grid'][0]} x {info['grid'][1]})"
                    f"{' again' if info.get('again') else ''} "
                    f"distance {info['distance']:.6g} ({state}), {info['seconds']:.0f} s"
                )
            return
        # The pace so far (step 0: the first solves, compilation included) times the
        # steps left: the most the run can still take at that pace; it stops earlier
        # when it converges.
        pace = info["seconds"] / max(info["step"], 1)
        left = args.karcher_steps - info["step"]
        eta = f"; at most ~{left * pace:.0f} s left ({left} steps at {pace:.0f} s)" if left else ""
        progress(
            f"Karcher step {info['step']}/{args.karcher_steps}: sum of squared distances "
            f"{info['sum_sq_distances']:.6g}, mean velocity {info['mean_velocity_norm']:.3g}, "
            f"step {info['step_size']:g}{eta} (checkpoint {checkpoint.name})"
        )

    where = (
        f"each shape's first geodesic by levels until two agree within {options.rtol:g}, "
        "then on the finest grid any shape needed"
        if options.resolves
        else f"on {m} x {n}"
    )
    progress(
        f"Karcher mean of {len(args.files)} shapes modulo {args.modulo}, {where} "
        f"(each step solves {len(args.files)} geodesics; the first compiles)"
    )
    start = time.perf_counter()
    res = karcher_mean(
        shapes,
        metric,
        modulo=args.modulo,
        options=options,
        max_steps=args.karcher_steps,
        tol=args.tol,
        step_size=args.step_size,
        warm_start=args.warm_start,
        job=job_options(args, checkpoint, report),
    )
    seconds = time.perf_counter() - start
    mean = np.asarray(res.mean)
    # The grid the mean, the registered shapes and the velocities are on: the finest
    # level's for a resolved mean, else the inputs'.
    settings.update(input_grid=[m, n], grid=list(mean.shape[-2:]))
    result = RESULTS.name(res.result)  # by name in the files: a code is this release's
    files = [
        str(
            io.save_npz_atomic(
                args.out / "mean.npz",
                f=mean,
                distances=np.asarray(res.distances),
                registered=np.asarray(res.registered),
                velocities=np.asarray(res.velocities),
                geodesics_converged=np.asarray(res.geodesics_converged),
                geodesics_resolution_limited=np.asarray(res.geodesics_resolution_limited),
                history=np.asarray(res.history),
                result=result,
                converged=bool(res.converged),
                inputs=json.dumps(list(args.files)),
                settings=json.dumps(settings),
            )
        )
    ]
    if np.isfinite(mean).all():
        files.append(str(io.save_surface(mean, args.out / "mean.ply")))
    files += write_figure(
        args.out / "mean.png",
        lambda: plot.plot_path(mean, titles=["Karcher mean"], view="fit"),
        progress,
    )
    history = np.asarray(res.history)
    columns = {"sum of squared distances": history[:, 0], "mean velocity norm": history[:, 1]}
    files += write_figure(args.out / "history.png", lambda: plot.plot_energy(columns), progress)
    summary = {
        "command": args.command,
        "inputs": list(args.files),
        "settings": settings,
        "distances": [float(d) for d in np.asarray(res.distances)],
        "sum_sq_distances": float(np.sum(np.asarray(res.distances) ** 2)),
        "history": {
            "sum_sq_distances": json_floats(history[:, 0]),
            "mean_velocity_norm": json_floats(history[:, 1]),
            "step_size": json_floats(history[:, 2]),
        },
        **result_fields(res),
        "num_solves": int(res.num_solves),
        "level_distances": None
        if res.level_distances is None
        else json_floats(res.level_distances),
        "geodesics_converged": [bool(c) for c in np.asarray(res.geodesics_converged)],
        "geodesics_resolution_limited": [
            bool(c) for c in np.asarray(res.geodesics_resolution_limited)
        ],
        "seconds": seconds,
        "files": files,
        "environment": environment_record(),
    }
    return res, metric, options, summary


def run_karcher(args, progress: Progress) -> dict:
    return solve_karcher(args, progress)[-1]


def add_arguments(p: argparse.ArgumentParser, files_help: str = SURFACE_FILES) -> None:
    """The ``karcher`` command's arguments (the ``pca`` command's too, which solves the
    same mean first)."""
    p.add_argument("files", nargs="+", help=files_help)
    shape_options(p, modulo="rigid", inner="; the Karcher steps are --karcher-steps")
    input_options(p)
    rtol_option(
        p,
        "a resolved mean: each shape's first geodesic by levels, the mean then kept on the "
        "finest grid any shape needed",
    )
    batch_options(p)
    karcher_options(p)


COMMAND = Command(
    name="karcher",
    run=run_karcher,
    add_arguments=add_arguments,
    help="Karcher mean of a collection of shapes",
    description="The Karcher mean of the shapes modulo rigid motions (or "
    "reparametrizations only), checkpointed after every step (--resume continues). "
    "Writes mean.npz (the mean, its distances, the velocities at the mean and the "
    "settings: the pca command's input), mean.ply, mean.png and history.png.",
)
