"""``elastic-jax pca``: tangent PCA at a Karcher mean written by ``karcher``."""

from __future__ import annotations

import argparse
import json
import pathlib

import numpy as np

from .. import io, mode_path, sigmas_reached, tangent_pca
from .arguments import (
    Command,
)
from .common import (
    SURFACE_FILES,
    Progress,
    environment_record,
    json_floats,
    json_safe,
    metric_from,
    write_figure,
)
from .karcher import add_arguments as karcher_arguments
from .karcher import solve_karcher


def run_pca(args, progress: Progress) -> dict:
    from .. import plot

    if args.karcher_output is None:
        karcher, metric, options, summary = solve_karcher(args, progress)
        mean, velocities = np.asarray(karcher.mean), np.asarray(karcher.velocities)
        distances, karcher_converged = np.asarray(karcher.distances), bool(karcher.converged)
        inputs = list(args.files)
    else:
        saved = args.karcher_output
        metric, options = metric_from(args), args.shape_options
        mean, velocities = saved["f"].astype(args.dtype), saved["velocities"].astype(args.dtype)
        distances, inputs = saved["distances"], saved["inputs"]
        karcher_converged = bool(saved["converged"])
        progress(
            f"the Karcher mean of {len(inputs)} shapes from {args.files[0]} "
            f"({saved['result']}); its metric and options"
        )
        summary = {
            "command": args.command,
            "inputs": list(args.files),
            "karcher_inputs": inputs,
            "settings": dict(saved["settings"]),
            "karcher_result": str(saved["result"]),
            "converged": karcher_converged,
            "files": [],
            "environment": environment_record(),
        }
    files = summary["files"]
    if not np.isfinite(velocities).all():
        # Nothing to analyse; the Karcher part of the summary says what failed.
        progress("the velocities at the mean are not finite: no PCA")
        summary.update(converged=False, pca=None)
        return summary
    k = len(inputs)
    n_modes = min(args.modes, k - 1)
    if n_modes < args.modes:
        progress(f"{k} shapes span at most {k - 1} modes: keeping {n_modes}")
    # Modes whose variance is at round-off (tangent_pca's rtol) are not modes: fewer kept.
    # Asking tangent_pca for fewer keeps the leading ones of the same decomposition
    # (explained stays relative to the total variance).
    data = (mean, velocities)
    full = tangent_pca(data, metric)
    pca = full if n_modes >= full.modes.shape[0] else tangent_pca(data, metric, n_modes=n_modes)
    n_modes = int(pca.modes.shape[0])
    explained = np.asarray(pca.explained)
    progress("explained variance by mode: " + ", ".join(f"{100 * e:.1f} %" for e in explained))
    # Shot with the scheme of the mean's geodesics (central is refused by preflight).
    shoot_options = {"n_times": args.mode_times, "degree": options.degree, "scheme": options.scheme}
    paths, unconverged = [], []
    for mode in range(n_modes):
        progress(f"mode {mode + 1}: shooting +-{args.sigmas:g} sigma from the mean")
        path = np.asarray(mode_path(pca, mode, metric, sigmas=args.sigmas, **shoot_options))
        paths.append(path)
        # A shot whose Newton step failed leaves the nodes beyond it NaN: a finite path is
        # both shots converged.
        if not np.isfinite(path).all():
            progress(f"mode {mode + 1}: a shooting step did not converge")
            unconverged.append(mode + 1)
    paths = np.stack(paths)
    sigma = np.sqrt(np.asarray(pca.variances))
    reached = []
    for mode, path in enumerate(paths, start=1):
        files.append(
            str(
                io.save_npz_atomic(
                    args.out / f"mode{mode}_velocity.npz",
                    v=sigma[mode - 1] * np.asarray(pca.modes[mode - 1]),
                    f=mean,
                )
            )
        )
        reached.append(sigmas_reached(path, args.sigmas))
        if np.isfinite(path).all():
            for end, name in ((path[0], "minus"), (path[-1], "plus")):
                files.append(str(io.save_surface(end, args.out / f"mode{mode}_{name}.ply")))
        else:
            progress(
                f"mode {mode}: the shots reached {reached[-1][0]:+.3g} and {reached[-1][1]:+.3g} "
                "sigma (a Newton step failed beyond); no meshes written for it"
            )
    files.append(
        str(
            io.save_npz_atomic(
                args.out / "pca.npz",
                mean=mean,
                modes=np.asarray(pca.modes),
                variances=np.asarray(pca.variances),
                explained=explained,
                scores=np.asarray(pca.scores),
                mean_velocity=np.asarray(pca.mean_velocity),
                mode_paths=paths,
                settings=json.dumps(summary["settings"]),
            )
        )
    )
    names = [pathlib.Path(f).stem for f in inputs]
    scores = {
        "files": inputs,
        "modes": n_modes,
        "sigmas": args.sigmas,
        "variances": json_floats(pca.variances),
        "explained": json_floats(explained),
        "scores": {
            name: json_floats(row) for name, row in zip(names, np.asarray(pca.scores), strict=True)
        },
    }
    text = json.dumps(json_safe(scores), indent=2, allow_nan=False)
    files.append(str(io.write_text_atomic(args.out / "scores.json", text + "\n")))
    files += write_figure(
        args.out / "modes.png",
        lambda: plot.plot_modes(
            paths, modes=len(paths), explained=explained, sigmas=args.sigmas, view="fit"
        ),
        progress,
    )
    summary["settings"].update(modes=n_modes, sigmas=args.sigmas, mode_times=args.mode_times)
    summary["pca"] = {
        "variances": json_floats(pca.variances),
        "explained": json_floats(explained),
        # All modes' variance against the mean squared distance: equal when every
        # velocity's G-norm is its distance and the mean velocity vanishes.
        "total_variance": float(np.sum(np.asarray(full.variances))),
        "mean_sq_distance": float(np.mean(np.asarray(distances) ** 2)),
        "mode_paths_unconverged": unconverged,
        # Per mode, the sigmas the solved nodes span: [-sigmas, +sigmas] when converged.
        "mode_paths_reached_sigmas": reached,
        "scores": scores["scores"],
    }
    summary["converged"] = karcher_converged and not unconverged
    return summary


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``pca`` command's arguments: the ``karcher`` command's, then the modes'."""
    karcher_arguments(p, files_help=SURFACE_FILES + "; or one karcher run's mean.npz")
    p.add_argument("--modes", type=int, default=3, help="modes to keep (at most shapes - 1)")
    p.add_argument(
        "--sigmas", type=float, default=2.0, help="mode paths reach +-sigmas standard deviations"
    )
    p.add_argument(
        "--mode-times",
        type=int,
        default=7,
        help="time points of each half of a mode path (mean to +-sigmas)",
    )


COMMAND = Command(
    name="pca",
    run=run_pca,
    add_arguments=add_arguments,
    help="Karcher mean, tangent PCA and mode paths of a collection of shapes",
    description="The Karcher mean of the shapes (as the karcher command), the metric "
    "PCA of their velocities at the mean (tangent_pca) and the geodesics through the "
    "mean along the first modes (mode_path). Writes the mean and each mode's +-sigma "
    "shapes as meshes, each mode's one-sigma velocity (modeK_velocity.npz, for the "
    "shoot command), pca.npz, scores.json and a figure (modes.png). Given a karcher "
    "run's mean.npz as its only input, it starts from that mean and its velocities, "
    "with that run's metric and options, and solves no geodesic.",
)
