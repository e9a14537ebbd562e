"""``elastic-jax fit-metric``: learn the split metric's coefficients from labelled shapes
(or target dissimilarities), and score them on held-out shapes."""

from __future__ import annotations

import argparse
import pathlib
import time

import numpy as np

from .. import distance_matrix, fit_metric, io, retrieval_scores
from .arguments import Command, batch_options, input_options, rtol_option, shape_options
from .common import (
    CHECKPOINTS,
    SURFACE_FILES,
    BadInput,
    Progress,
    collection_settings,
    environment_record,
    job_options,
    json_floats,
    prepare,
    result_fields,
    shape_geodesic_options,
)


def read_labels(path: str, files: list[str]) -> list[str]:
    """Class labels, one per surface file: a text file with one label per line in the
    files' order, or lines ``name,label`` (name: the file's stem) in any order."""
    p = pathlib.Path(path)
    if not p.is_file():
        raise BadInput(f"{path}: no such file (the labels)")
    lines = [line.strip() for line in p.read_text().splitlines() if line.strip()]
    stems = [pathlib.Path(f).stem for f in files]
    if lines and all("," in line for line in lines):
        given = dict(tuple(x.strip() for x in line.split(",", 1)) for line in lines)
        missing = [s for s in stems if s not in given]
        if missing:
            raise BadInput(f"{path}: no label for {missing}")
        return [given[s] for s in stems]
    if len(lines) != len(files):
        raise BadInput(
            f"{path}: {len(lines)} labels for {len(files)} surface files (one per line, in "
            "the files' order, or lines name,label)"
        )
    return lines


def read_targets(path: str):
    """A (K, K) dissimilarity matrix from .npy, .npz (its first array) or a CSV/text file."""

    p = pathlib.Path(path)
    if not p.is_file():
        raise BadInput(f"{path}: no such file (the targets)")
    try:
        if p.suffix == ".npy":
            return np.load(p)
        if p.suffix == ".npz":
            with np.load(p) as data:
                return data[data.files[0]]
        return np.loadtxt(p, delimiter="," if p.suffix == ".csv" else None)
    except (OSError, ValueError, IndexError) as err:
        raise BadInput(f"{path}: cannot be read as a matrix ({err})") from err


def run_fit_metric(args, progress: Progress) -> dict:
    shapes, metric, options = prepare(args, progress, args.files, shape_geodesic_options)
    k, m, n = shapes.shape[0], *shapes.shape[2:]
    labels = None if args.labels is None else read_labels(args.labels, args.files)
    targets = None if args.targets is None else read_targets(args.targets)
    test_labels = None
    if args.test:
        test_labels = read_labels(args.test_labels, args.test)
        test_shapes = prepare(args, progress, args.test, shape_geodesic_options, main_inputs=False)[
            0
        ]
        if test_shapes.shape[2:] != shapes.shape[2:]:
            raise BadInput(
                f"--test surfaces are on a {test_shapes.shape[2]} x {test_shapes.shape[3]} "
                f"grid, the training ones on {m} x {n}: give --grid to resample both"
            )

    def report(info):
        state = "accepted" if info["accepted"] else "rejected"
        coefficients = ", ".join(f"{x:.4g}" for x in info["metric"])
        progress(
            f"step {info['step']} {state}: objective {info['objective']:.6g}, gradient "
            f"{info['grad_norm']:.3g}, metric ({coefficients})"
        )

    progress(f"fitting the metric to {k} shapes modulo {args.modulo} on {m} x {n}")
    start = time.perf_counter()
    fit = fit_metric(
        shapes,
        labels,
        targets=targets,
        modulo=args.modulo,
        options=options,
        init=metric,
        learn=args.learn,
        temperature=args.temperature,
        max_steps=args.fit_steps,
        tol=args.fit_tol,
        job=job_options(args, args.out / CHECKPOINTS["fit-metric"], report),
    )
    seconds = time.perf_counter() - start
    coefficients = {c: float(getattr(fit.metric, c)) for c in "abcd"}
    summary = {
        "command": args.command,
        "inputs": list(args.files),
        "settings": {
            **collection_settings(args, m, n, options),
            "learn": args.learn,
            "objective": "nca" if labels is not None else "stress",
            "temperature": args.temperature,
            "fit_steps": args.fit_steps,
            "fit_tol": args.fit_tol,
        },
        "metric": coefficients,
        "initial_metric": {c: float(getattr(fit.initial_metric, c)) for c in "abcd"},
        "objective_before": float(fit.objective_before),
        "objective_after": float(fit.objective_after),
        "grad_norm": float(fit.grad_norm),
        "history": json_floats(fit.history),
        "evaluations": int(fit.evaluations),
        **result_fields(fit),
        "seconds": seconds,
    }
    if labels is not None:
        summary["training_scores"] = {
            "before": retrieval_scores(fit.distances_before, labels)._asdict(),
            "after": retrieval_scores(fit.distances, labels)._asdict(),
        }
    arrays = {
        "metric": np.asarray(list(coefficients.values())),
        "distances": np.asarray(fit.distances),
        "distances_before": np.asarray(fit.distances_before),
        "history": np.asarray(fit.history),
        "files": np.asarray(args.files),
    }
    if test_labels is not None:
        progress(f"scoring on {len(args.test)} held-out shapes")
        held_out = {}
        for name, which in (("before", fit.initial_metric), ("after", fit.metric)):
            res = distance_matrix(
                test_shapes,
                which,
                modulo=args.modulo,
                options=options,
                job=job_options(args),
            )
            held_out[name] = retrieval_scores(res.distances, test_labels)._asdict()
            arrays[f"test_distances_{name}"] = np.asarray(res.distances)
        summary["held_out_scores"] = held_out
        summary["test_inputs"] = list(args.test)
    files = [str(io.save_npz_atomic(args.out / "fit_metric.npz", **arrays))]
    summary["files"] = files
    summary["environment"] = environment_record()
    return summary


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``fit-metric`` command's arguments."""
    p.add_argument("files", nargs="+", help=SURFACE_FILES)
    data = p.add_mutually_exclusive_group(required=True)
    data.add_argument(
        "--labels",
        default=None,
        help="text file: one class label per line in the files' order, or lines name,label",
    )
    data.add_argument(
        "--targets", default=None, help="(K, K) dissimilarities: .npy, .npz, .csv or text"
    )
    shape_options(p, modulo="rigid", moduli=("rigid", "diff", "none"))
    input_options(p)
    rtol_option(p, "each pair's resolved distance at the first solve (the steps continue it)")
    batch_options(p)
    p.add_argument("--learn", default="abc", help="the coefficients that move (of abcd)")
    p.add_argument(
        "--temperature",
        type=float,
        default=0.1,
        help="softness of the soft nearest neighbours (squared mean distances)",
    )
    p.add_argument(
        "--fit-steps",
        type=int,
        default=30,
        help="most trust region steps (each solves every pair once)",
    )
    p.add_argument(
        "--fit-tol",
        type=float,
        default=1e-3,
        help="the fit converges when its gradient norm is at most this",
    )
    p.add_argument(
        "--test",
        nargs="+",
        default=None,
        metavar="FILE",
        help="held-out surface files to score the metrics on",
    )
    p.add_argument("--test-labels", default=None, help="their labels (as --labels)")


COMMAND = Command(
    name="fit-metric",
    run=run_fit_metric,
    add_arguments=add_arguments,
    help="learn the metric's coefficients from labelled shapes (or target distances)",
    description="Fit the split metric's coefficients (a, b, c, d) to the shapes' class "
    "labels (soft nearest neighbours) or to a matrix of target dissimilarities "
    "(elastic_jax.fit_metric), starting from --metric; a + b + c + d = 1 in the result. "
    "With --test and --test-labels, also scores the start and the fitted metric on those "
    "held-out shapes (nearest neighbour, first and second tier). Writes summary.json "
    "and fit_metric.npz (the coefficients, the distance matrices, the history).",
)
