"""``elastic-jax shape-geodesic``: the geodesic modulo reparametrization (and rotation)."""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np

from .. import energy_density, io, shape_geodesic
from .arguments import Command, input_options, rtol_option, shape_options
from .common import (
    SURFACE_FILE,
    Progress,
    environment_record,
    input_settings,
    json_float,
    json_floats,
    prepare,
    result_fields,
    shape_geodesic_options,
    write_figure,
    write_path,
)


def solve_reporter(progress: Progress):
    """shape_geodesic's progress dicts as the command's lines: the level, the phase done,
    the energy reached (the line's own time is the command's)."""

    def report(r: dict) -> None:
        grid = "{} x {}".format(*r["grid"])
        where = f"level {r['level']}/{r['levels']} ({grid})" if "level" in r else grid
        if r.get("again"):  # a coarser level solved again from a finer level's minimum
            where += " again"
        if r["stage"] == "level":
            state = "converged" if r["converged"] else "not converged"
            progress(f"{where}: distance {r['distance']:.6g} ({state})")
        elif r["energy"] is None:
            progress(f"{where}: {r['stage']} done")
        else:
            progress(f"{where}: {r['stage']} done, energy {r['energy']:.6g}")

    return report


def write_on_mesh(directory, path, vertex_map, progress: Progress) -> list[str]:
    """Each frame of ``path (N, 3, m, n)`` at the mesh's vertices, with its faces, as
    ``target_mesh_NNN.ply`` (io.VertexMap.to_mesh)."""

    progress(f"writing the path's {len(path)} frames on the target mesh to {directory}")
    digits = max(3, len(str(len(path) - 1)))
    written = []
    for k, f in enumerate(path):
        target = directory / f"target_mesh_{k:0{digits}d}.ply"
        with io.atomic_path(target) as tmp:
            vertex_map.to_mesh(f).export(tmp, file_type="ply")
        written.append(str(target))
    return written


_TERMS = ("shear", "area", "bending", "rotation", "total")


def write_energy_density(out, path, metric, scheme: str, progress: Progress):
    """The path's energy by grid point and term (energy_density) in ``energy_density.npz``,
    on the path's first frame (f1 registered) as ``energy_density.ply`` vertex properties,
    and drawn per unit area on that frame; returns the files and each term's sum."""
    from .. import plot

    density = energy_density(metric, path, scheme)
    fields = {name: np.asarray(getattr(density, name)) for name in _TERMS}
    first = np.asarray(path[0])
    progress(f"writing the path's energy by point and term to {out / 'energy_density.*'}")
    written = [
        str(io.save_npz_atomic(out / "energy_density.npz", **fields)),
        str(io.save_surface(first, out / "energy_density.ply", fields=fields)),
    ]
    written += write_figure(
        out / "energy_density.png",
        lambda: plot.plot_field(first, fields["total"], label="path energy per unit area"),
        progress,
    )
    return written, {name: float(value.sum()) for name, value in fields.items()}


def run_shape_geodesic(args, progress: Progress) -> dict:
    from .. import plot

    files = [args.source, args.target]
    (f1, f2), metric, options = prepare(args, progress, files, shape_geodesic_options)
    m, n = f1.shape[1:]
    where = (
        "on working grids "
        + ", ".join(f"{a} x {b}" for a, b in options.levels)
        + f" until two levels agree within {options.rtol:g}"
        if options.resolves
        else f"on {m} x {n}"
    )
    progress(
        f"registering and solving modulo {args.modulo} {where}, "
        f"at most {options.outer_steps} registration rounds each (the first call compiles)"
    )
    start = time.perf_counter()
    res = jax.block_until_ready(
        shape_geodesic(
            f1, f2, metric, modulo=args.modulo, options=options, progress=solve_reporter(progress)
        )
    )
    seconds = time.perf_counter() - start
    levels = None
    if res.levels is not None:
        levels = {
            "grids": np.asarray(res.levels.grids).tolist(),
            "distances": json_floats(res.levels.distances),
            "seconds": json_floats(res.levels.seconds),
            "estimate": json_float(res.levels.estimate),
            "rtol": float(res.levels.rtol),
        }
    progress(
        f"shape distance {float(res.distance):.6g} "
        f"(parametrized {float(res.parametrized_distance):.6g}) "
        f"after {int(res.rounds)} rounds"
    )
    settings = {
        "metric": list(args.metric),
        "modulo": args.modulo,
        **options.as_dict(),
        "input_grid": [m, n],
        # The working grid the path is on: the finest level's, or the inputs'.
        "grid": list(res.path.shape[-2:]),
        "dtype": args.dtype,
        **input_settings(args),
    }
    files = write_path(args.out, np.asarray(res.path), settings, progress)
    if args.on_target_mesh and files:
        path = np.asarray(res.path)
        files += write_on_mesh(args.out / "path", path, args.vertex_maps[1], progress)
    terms = None
    if files:  # a finite path: where its energy lies, beside the meshes
        written, terms = write_energy_density(args.out, res.path, metric, options.scheme, progress)
        files += written
    files.append(
        str(
            io.save_npz_atomic(
                args.out / "registration.npz",
                gamma=np.asarray(res.gamma),
                rotation=np.asarray(res.rotation),
                f1_registered=np.asarray(res.f1_registered),
                energy_history=np.asarray(res.energy_history),
            )
        )
    )
    history = np.asarray(res.energy_history)
    # Rounds not taken are NaN in the record; the figure shows the rounds taken.
    energies = {"path energy": history[np.isfinite(history)]}
    files += write_figure(args.out / "energy.png", lambda: plot.plot_energy(energies), progress)
    return {
        "command": args.command,
        "inputs": [args.source, args.target],
        "settings": settings,
        "distance": float(res.distance),
        "parametrized_distance": float(res.parametrized_distance),
        "energy": float(res.energy),
        "energy_history": json_floats(res.energy_history),
        "rounds": int(res.rounds),
        "levels": levels,
        "energy_terms": terms,
        **result_fields(res),
        "grad_norm": float(res.grad_norm),
        "refinement": {
            "distance_time": json_float(res.refinement.distance_time),
            "distance_grid": json_float(res.refinement.distance_grid),
            "relative_change": json_float(res.refinement.relative_change),
        },
        "seconds": seconds,
        "files": files,
        "environment": environment_record(),
    }


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``shape-geodesic`` command's arguments."""
    p.add_argument("source", help=SURFACE_FILE)
    p.add_argument("target", help=SURFACE_FILE)
    shape_options(p, modulo="diff")
    rtol_option(p, "a resolved distance")
    input_options(p)
    p.add_argument(
        "--on-target-mesh",
        action="store_true",
        help="also write the path's frames as meshes with the target mesh's faces, each "
        "frame read at the target's vertices through the map that brought it in "
        "(io.VertexMap): path/target_mesh_NNN.ply, the last one the target's own vertices "
        "(rotated and centred under --modulo rigid) to the grid's resolution; the path "
        "starts at the source reparametrized onto the target, so this paints the "
        "deformation on the target's mesh (a mesh target only)",
    )


COMMAND = Command(
    name="shape-geodesic",
    run=run_shape_geodesic,
    add_arguments=add_arguments,
    help="geodesic between shapes (registration)",
)
