"""``elastic-jax distances``: the matrix of pairwise shape distances, chunk by chunk."""

from __future__ import annotations

import argparse
import json
import pathlib
import time

import numpy as np

from .. import distance_matrix, io
from .arguments import Command, batch_options, input_options, rtol_option, shape_options
from .common import (
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


def run_distances(args, progress: Progress) -> dict:
    from .. import plot

    shapes, metric, options = prepare(args, progress, args.files, shape_geodesic_options)
    k, m, n = shapes.shape[0], *shapes.shape[2:]
    settings = collection_settings(args, m, n, options)
    checkpoint = args.out / "distances_checkpoint.npz"

    def report(info):
        eta = "" if info["eta_s"] is None else f", about {info['eta_s']:.0f} s left"
        progress(
            f"pairs done {info['pairs_done']}/{info['pairs']}{eta} (checkpoint {checkpoint.name})"
        )

    where = f"on {m} x {n}"
    if options.resolves and args.modulo != "none":
        where = f"by levels until two agree within {options.rtol:g}"
    progress(
        f"{k * (k - 1) // 2} shape geodesics modulo {args.modulo} {where} (the first compiles)"
    )
    start = time.perf_counter()
    res = distance_matrix(
        shapes,
        metric,
        modulo=args.modulo,
        options=options,
        job=job_options(args, checkpoint, report),
    )
    seconds = time.perf_counter() - start
    matrix = np.asarray(res.distances)
    converged = np.asarray(res.pairs_converged)
    if not converged.all():
        progress(f"{int((~converged).sum()) // 2} pairs did not converge (summary: converged)")
    names = [pathlib.Path(f).stem for f in args.files]
    files = [
        str(
            io.save_npz_atomic(
                args.out / "distances.npz",
                distances=matrix,
                converged=converged,
                refinement_change=np.asarray(res.refinement_change),
                estimate=np.asarray(res.estimate),
                grids=np.asarray(res.grids),
                spread=np.asarray(res.spread),
                files=np.asarray(args.files),
                settings=json.dumps(settings),
            )
        )
    ]
    rows = [",".join(["", *names])]
    rows += [
        ",".join([name, *(f"{v:.10g}" for v in row)])
        for name, row in zip(names, matrix, strict=True)
    ]
    files.append(str(io.write_text_atomic(args.out / "distances.csv", "\n".join(rows) + "\n")))
    files += write_figure(
        args.out / "distances.png",
        lambda: plot.plot_distance_matrix(
            matrix, labels=names, title=f"distances modulo {args.modulo}", annotate=len(names) <= 12
        ),
        progress,
    )
    return {
        "command": args.command,
        "inputs": list(args.files),
        "settings": settings,
        "distances": matrix.tolist(),
        **result_fields(res),
        "pairs_converged": converged.tolist(),
        # Each pair's relative change under refinement (null: not computed).
        "refinement_change": json_floats(res.refinement_change),
        # Each pair's levels estimate and finest grid (null: one working grid).
        "estimate": json_floats(res.estimate),
        "grids": np.asarray(res.grids).tolist(),
        # Each pair's candidates' spread (0: one candidate; null: one working grid).
        "spread": json_floats(res.spread),
        "seconds": seconds,
        "files": files,
        "environment": environment_record(),
    }


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``distances`` command's arguments."""
    p.add_argument("files", nargs="+", help=SURFACE_FILES)
    shape_options(p, modulo="rigid")
    input_options(p)
    rtol_option(p, "each pair's resolved distance")
    batch_options(p)


COMMAND = Command(
    name="distances",
    run=run_distances,
    add_arguments=add_arguments,
    help="matrix of pairwise shape distances",
)
