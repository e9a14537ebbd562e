"""Real shapes: is the distance a property of the two shapes?

For each pair, modulo rigid motion, metric (1, 1, 0.1, 0), the package's defaults
(ShapeOptions()), float64, one record per solve:

- ``grid25``: both surfaces resampled (bilinear) to 25 x 49;
- ``up49``: those same 25 x 49 surfaces upsampled (bilinear, grid points kept) to 49 x 97,
  so the continuous surfaces are the same as ``grid25``'s;
- ``data``: the surfaces at their own grid (50 x 99 for the authors' surfaces);
- ``moebius``: f1 read from its data through a Moebius map (|a| = 0.3, a seeded direction)
  and rotated, on the data's grid: should equal ``data``;
- ``reversed``: the pair in the other order, on the data's grid: should equal ``data``;
- ``self``: f1 against itself read through a Moebius map (|a| = 0.5) and rotated, on the
  data's grid: should be 0 (ill-posed at the data's grid, docs/math.md §10: kept as a record);
- ``moebius99``, ``self99``: the well-posed forms, the map's input (|a| = 0.3) read by the
  spline at 99 x 197: with ``--rtol`` the first should equal ``data`` and the second be
  small against it (the issue's 3 % and 5 %).

Each record has the distance, the parametrized distance, converged, the result's name,
the refinement (distance_time, distance_grid, relative_change), the solve time (the
first call of each configuration includes its compilation: ``compiled`` says which, and
``programs_compiled`` how many XLA programs the solve compiled; ``phases`` each level's
phases as [level, stage, seconds], ``num_steps`` the solver steps), and
then one summary record per pair with the spreads the issue's targets ask about.

Pairs: cat1 -> cat2, cat1 -> horse0, horse0 -> hand4 (the authors' surfaces from
elastic_jax.datasets: $ELASTIC_JAX_DATA or a download; skipped when they cannot be had), a
synthetic pair (a bumpy surface against a stretched copy, sampled at 50 x 99),
and, when nilearn is installed, FreeSurfer's fsaverage5 left hemisphere against the
mirrored right one, inflated (``fsaverage``), white (``fsaverage-white``) and pial
(``fsaverage-pial``) (nilearn ships the meshes; they are put on the grid by
elastic_jax.io.mesh_to_grid at 50 x 99).

Each solve is a resolved distance (ShapeOptions.rtol, the package's default 0.03;
docs/math.md §10): the working grid refined by levels (``--levels``) until two agree
within rtol, and each record carries the levels' grids, distances and times and the
estimate. ``--rtol none`` solves on one working grid, the inputs' (the records before
levels were the default).

Run: python benchmarks/bench_real.py [--pairs cats,cat-horse,horse-hand,synthetic,fsaverage,
     fsaverage-white,fsaverage-pial]
     [--cases grid25,up49,data,moebius,reversed,self,moebius99,self99]
     [--init moebius|energy|icosahedral|none]
     [--differential chain|grid] [--interpolation spline|bicubic|bilinear] [--rtol 0.03|none]
     [--levels 13x25,25x49,49x97]   (differential and interpolation: the package's defaults)
     [--dtype float64|float32] [--repeat K]   (each case solved K times in this process:
     the first of a configuration compiles, the others are the warm figure)

Measured on one H200 (2026-11-28, cats, data, the defaults, four benchmark processes on
the GPU at once; records/bench_real_levels_h200_2026-11-28.jsonl): float64 first call 209
and 228 s (64 programs), warm 16.9 and 9.9 s, distances 2.180 and 2.208 (two runs; levels
to 97 x 193, estimate 0.4 % and 2.2 %). float32 ended at 0.0 on the 97 x 193 level in both
runs (docs/guides/limitations.md).
"""

from __future__ import annotations

import argparse
import time
import warnings

import jax

jax.config.update("jax_enable_x64", True)  # a script, not the library

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import elastic_jax as ej  # noqa: E402
from elastic_jax import shapes  # noqa: E402
from elastic_jax._options import DIFFERENTIALS, INTERPOLATIONS  # noqa: E402
from elastic_jax._runtime.cache import CompileCounter  # noqa: E402

from _common import emit, environment, moebius_read, shape  # noqa: E402

METRIC = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)
PAIRS = {
    "cats": ("cat1", "cat2"),
    "cat-horse": ("cat1", "horse0"),
    "horse-hand": ("horse0", "hand4"),
    "synthetic": None,
    "fsaverage": None,
    "fsaverage-white": None,
    "fsaverage-pial": None,
}
CASES = ("grid25", "up49", "data", "moebius", "reversed", "self", "moebius99", "self99")


def _moved(f, magnitude: float, seed: int, grid=None, method: str = "bicubic"):
    """R (f o phi_a): f read through a Moebius map with |a| = magnitude, then rotated, at
    the points of ``grid`` (default: f's own)."""
    rng = np.random.default_rng(seed)
    a = rng.standard_normal(3)
    a *= magnitude / np.linalg.norm(a)
    return moebius_read(f, a, ej.so3_exp(jnp.asarray(rng.standard_normal(3))), grid, method)


def _fsaverage(surface: str = "infl"):
    """fsaverage5's left hemisphere and the mirrored right one on 50 x 99 (``surface``:
    "infl", "white" or "pial")."""
    try:
        from nilearn import datasets
        from nilearn import surface as nilearn_surface
    except ImportError:
        return None
    import trimesh

    from elastic_jax import io

    paths = datasets.fetch_surf_fsaverage("fsaverage5")  # files inside nilearn's wheel
    grids = []
    for side, flip in (("left", 1.0), ("right", -1.0)):
        mesh = nilearn_surface.load_surf_mesh(paths[f"{surface}_{side}"])
        coords = getattr(mesh, "coordinates", None)
        coords, faces = (mesh[0], mesh[1]) if coords is None else (coords, mesh.faces)
        coords = np.asarray(coords, float) * np.array([flip, 1.0, 1.0])
        faces = np.asarray(faces)
        if flip < 0:  # a mirror turns the faces' winding inside out
            faces = faces[:, ::-1]
        mesh = trimesh.Trimesh(coords, faces, process=False)
        grids.append(jnp.asarray(io.mesh_to_grid(mesh, 50, 99)))
    return tuple(grids)


def _pair(name: str):
    if name == "synthetic":
        stretch = jnp.asarray([1.3, 1.0, 0.8])
        moved = shapes.sample(shapes.bumpy, 50, 99, rotation=shapes.random_rotation(11))
        return shapes.sample(shapes.bumpy, 50, 99), jnp.einsum("i,imn->imn", stretch, moved)
    if name.startswith("fsaverage"):
        return _fsaverage({"fsaverage": "infl"}.get(name, name.removeprefix("fsaverage-")))
    surfaces = [shape(s) for s in PAIRS[name]]
    if any(f is None for f in surfaces):
        return None
    return tuple(jnp.asarray(f) for f in surfaces)


def _inputs(case: str, f1, f2):
    if case == "grid25":
        return ej.resample(f1, 25, 49), ej.resample(f2, 25, 49)
    if case == "up49":
        return (ej.resample(ej.resample(f, 25, 49), 49, 97) for f in (f1, f2))
    if case == "up97":
        return (ej.resample(ej.resample(f, 25, 49), 97, 193) for f in (f1, f2))
    if case == "data":
        return f1, f2
    if case == "moebius":
        return _moved(f1, 0.3, 1), f2
    if case == "reversed":
        return f2, f1
    # The well-posed forms (docs/math.md §10): the map's input read through the package's
    # spline at 99 x 197, finer than the data by more than the map's stretch (1.86 for
    # abs(a) = 0.3); the solve's working grid is then that finer grid unless --levels.
    if case == "moebius99":
        return _moved(f1, 0.3, 1, (99, 197), "spline"), f2
    if case == "self99":
        return f1, _moved(f1, 0.3, 2, (99, 197), "spline")
    return f1, _moved(f1, 0.5, 2)  # self


def _levels_record(levels) -> dict:
    """The levels of a resolved distance (--rtol): grids, distances, times, estimate."""
    if levels is None:
        return {}
    return {
        "levels": {
            "grids": np.asarray(levels.grids).tolist(),
            "distances": np.asarray(levels.distances).tolist(),
            "seconds": np.asarray(levels.seconds).tolist(),
            "estimate": float(levels.estimate),
            "rtol": float(levels.rtol),
        }
    }


def _phase_seconds(reports: list[dict]) -> list[list]:
    """shape_geodesic's progress as [level, stage, seconds] rows: the time each phase of
    each level took."""
    rows, last = [], 0.0
    for report in reports:
        if report["stage"] != "level":
            rows.append([report.get("level"), report["stage"], report["seconds"] - last])
        last = report["seconds"]
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", default=",".join(PAIRS))
    # The 99 x 197 reads are opt-in: with --rtol none they are solved at 99 x 197.
    parser.add_argument("--cases", default=",".join(CASES[:6]))
    parser.add_argument(
        "--init", default="moebius", choices=("moebius", "energy", "icosahedral", "none")
    )
    defaults = ej.ShapeOptions()
    parser.add_argument("--differential", default=defaults.differential, choices=DIFFERENTIALS)
    parser.add_argument("--interpolation", default=defaults.interpolation, choices=INTERPOLATIONS)
    parser.add_argument(
        "--rtol",
        type=lambda text: None if text == "none" else float(text),
        default=defaults.rtol,
        help="resolve each distance by levels of working grids to this relative tolerance "
        "(the package's default); 'none': one working grid, the inputs'",
    )
    parser.add_argument(
        "--levels",
        default=None,
        help="the levels' grids for --rtol, e.g. 13x25,25x49,49x97 (default: the package's)",
    )
    parser.add_argument("--dtype", default="float64", choices=("float64", "float32"))
    parser.add_argument("--repeat", type=int, default=1, help="solves per case")
    args = parser.parse_args()
    options = ej.ShapeOptions(
        init=args.init,
        differential=args.differential,
        interpolation=args.interpolation,
        rtol=args.rtol,
    )
    if args.levels:
        options = options.replace(
            levels=tuple(tuple(int(k) for k in g.split("x")) for g in args.levels.split(","))
        )
    pairs, cases = args.pairs.split(","), args.cases.split(",")
    for name in pairs:
        if name not in PAIRS:
            parser.error(f"unknown pair {name!r}; choose from {', '.join(PAIRS)}")
    for case in cases:
        if case not in (*CASES, "up97"):
            parser.error(f"unknown case {case!r}; choose from {', '.join(CASES)}, up97")
    emit(
        {
            "kind": "environment",
            **environment(),
            "metric": [METRIC.a, METRIC.b, METRIC.c, METRIC.d],
            "modulo": "rigid",
            "init": args.init,
            "differential": args.differential,
            "interpolation": args.interpolation,
            "rtol": args.rtol,
            "levels": [list(g) for g in options.levels] if args.rtol else None,
            "dtype": args.dtype,
        }
    )
    seen = set()
    for name in pairs:
        surfaces = _pair(name)
        if surfaces is None:
            emit({"kind": "skipped", "pair": name, "why": "data or nilearn absent"})
            continue
        distances = {}
        for case, repeat in ((c, r) for c in cases for r in range(args.repeat)):
            f1, f2 = (jnp.asarray(f, args.dtype) for f in _inputs(case, *surfaces))
            grid = tuple(f1.shape[-2:])
            start = time.perf_counter()
            reports: list[dict] = []
            with warnings.catch_warnings(), CompileCounter() as programs:
                warnings.simplefilter("ignore", ej.ConvergenceWarning)
                res = ej.shape_geodesic(
                    f1, f2, METRIC, modulo="rigid", options=options, progress=reports.append
                )
                jax.block_until_ready(res.distance)
            seconds = time.perf_counter() - start
            distances[case] = float(res.distance)
            emit(
                {
                    "kind": "solve",
                    "pair": name,
                    "case": case,
                    "repeat": repeat,
                    "dtype": args.dtype,
                    "grid": list(grid),
                    "distance": float(res.distance),
                    "parametrized_distance": float(res.parametrized_distance),
                    "converged": bool(res.converged),
                    "result": ej.RESULTS.name(res.result),
                    "rounds": int(res.rounds),
                    "distance_time": float(res.refinement.distance_time),
                    "distance_grid": float(res.refinement.distance_grid),
                    "relative_change": float(res.refinement.relative_change),
                    "seconds": seconds,
                    "compiled": grid not in seen,
                    # XLA programs this solve compiled (few, and none once
                    # its settings have been solved before).
                    "programs_compiled": programs.count,
                    "num_steps": int(res.num_steps),
                    "phases": _phase_seconds(reports),
                    **_levels_record(res.levels),
                }
            )
            seen.add(grid)
        summary = {"kind": "summary", "pair": name}
        d = distances.get("data")
        if d:
            for case in ("moebius", "reversed", "self", "moebius99", "self99"):
                if case in distances:
                    summary[f"{case}_over_data"] = distances[case] / d
        if distances.get("grid25") and "up49" in distances:
            summary["up49_over_grid25"] = distances["up49"] / distances["grid25"]
        emit(summary)


if __name__ == "__main__":
    main()
