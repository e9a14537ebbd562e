"""Geodesics between shapes (modulo reparametrization): the paper's Table 3 rows and accuracy.

Rows (paper, Table 3, laptop without GPU): low 12 x 25, degree 5 / vf degree 5, N = 5
(32-41 s); middle 25 x 49, 7 / 8, N = 10 (95-183 s); high 50 x 99, 9 / 11, N = 15
(505-842 s); plus the package's defaults (ShapeOptions()) at 25 x 49. Metric
(1, 1, 0.1, 0), modulo="diff". Pairs: a synthetic one (a bumpy surface against a stretched
copy under a random rotation of the parameter sphere, sampled exactly at every grid, so
every row sees the same continuous surfaces) and every pair of the authors' four animals
(cat1, cat2, horse0, hand4 from elastic_jax.datasets: $ELASTIC_JAX_DATA or a download;
50 x 99, interpolated bicubically to the lower rows' grids; skipped when they cannot be
had), so that a slowdown on one pair shows.

One JSON record per solve: compile time (first call minus a repeat), solve time, the
distance, its refinement (halved time steps, the finer grid), converged, rounds, steps,
peak RSS. Then one record per pair: the accuracy-versus-time table, each row's distance
error against a fine reference solve (50 x 99, degree 12, vf degree 12, N = 21). The
target: every row at least 20 x faster than the paper's fastest time for it.

Run: python benchmarks/bench_shape.py [--rows low,middle,high,defaults]
     [--pairs synthetic,animals | synthetic,cat1-horse0,...] [--no-reference]
     [--dtype float64|float32]

``--pairs``: ``synthetic``, ``animals`` (the six pairs of the four animals), ``cats``
(cat1-cat2) or any ``a-b`` of two animals' names.
"""

from __future__ import annotations

import argparse
import resource
import time
import warnings

import jax

jax.config.update("jax_enable_x64", True)  # a script, not the library

import jax.numpy as jnp  # noqa: E402

import elastic_jax as ej  # noqa: E402
from elastic_jax import shapes  # noqa: E402
from elastic_jax._runtime.cache import CompileCounter  # noqa: E402

from _common import emit, environment, shape  # noqa: E402

METRIC = (1.0, 1.0, 0.1, 0.0)
ROWS = {
    "low": {"grid": (12, 25), "degree": 5, "vf_degree": 5, "n_times": 5, "paper_s": [32, 41]},
    "middle": {"grid": (25, 49), "degree": 7, "vf_degree": 8, "n_times": 10, "paper_s": [95, 183]},
    "high": {"grid": (50, 99), "degree": 9, "vf_degree": 11, "n_times": 15, "paper_s": [505, 842]},
    "defaults": {"grid": (25, 49), "paper_s": None},
}
REFERENCE = {"grid": (50, 99), "degree": 12, "vf_degree": 12, "n_times": 21}
ANIMALS = ("cat1", "cat2", "horse0", "hand4")


def pair_names(text: str) -> list[str]:
    """--pairs expanded: "animals" is every pair of ANIMALS (cat1-cat2 under its
    records' name, "cats")."""
    names = []
    for name in text.split(","):
        if name == "animals":
            every = [f"{a}-{b}" for i, a in enumerate(ANIMALS) for b in ANIMALS[i + 1 :]]
            names += ["cats" if pair == "cat1-cat2" else pair for pair in every]
        else:
            names.append(name)
    return names


def pair(name: str, m: int, n: int):
    """The pair on an m x n grid, or None when its data is absent."""
    if name == "synthetic":
        stretch = jnp.asarray([1.3, 1.0, 0.8])
        h = shapes.random_rotation(11)
        moved = shapes.sample(shapes.bumpy, m, n, rotation=h)
        return shapes.sample(shapes.bumpy, m, n), jnp.einsum("i,imn->imn", stretch, moved)
    first, second = ("cat1", "cat2") if name == "cats" else name.split("-")
    animals = [shape(animal) for animal in (first, second)]
    if any(f is None for f in animals):
        return None
    points = ej.sphere_points(m, n)
    if (m, n) == (50, 99):
        return tuple(jnp.asarray(f) for f in animals)
    return tuple(_grid(ej.reparametrize(f, points, "bicubic")) for f in animals)


def _grid(f):
    """Pole rows and seam exact after interpolation (docs/math.md §1)."""
    f = f.at[:, 0, :].set(f[:, 0, :1]).at[:, -1, :].set(f[:, -1, :1])
    return f.at[:, :, -1].set(f[:, :, 0])


def options_of(settings: dict) -> ej.ShapeOptions:
    keys = ("degree", "vf_degree", "n_times")
    # One working grid, the row's (the paper's protocol), not levels.
    return ej.ShapeOptions(**{k: settings[k] for k in keys if k in settings}, rtol=None)


def solve(
    name: str, settings: dict, metric: ej.SplitMetric, row: str, dtype: str = "float64"
) -> dict | None:
    m, n = settings["grid"]
    surfaces = pair(name, m, n)
    if surfaces is None:
        return None
    surfaces = tuple(jnp.asarray(f, dtype) for f in surfaces)
    options = options_of(settings)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ej.ConvergenceWarning)
        start = time.perf_counter()
        with CompileCounter() as programs:
            jax.block_until_ready(ej.shape_geodesic(*surfaces, metric, options=options))
        first = time.perf_counter() - start
        start = time.perf_counter()
        res = jax.block_until_ready(ej.shape_geodesic(*surfaces, metric, options=options))
        seconds = time.perf_counter() - start
    record = {
        "benchmark": "shape_geodesic",
        "settings": {
            "row": row,
            "pair": name,
            "m": m,
            "n": n,
            "metric": METRIC,
            "modulo": "diff",
            "dtype": dtype,
            "options": options.as_dict(),
        },
        "compile_s_estimate": first - seconds,
        "first_call_s": first,
        "programs_compiled_first_call": programs.count,
        "solve_s": seconds,
        "distance": float(res.distance),
        "parametrized_distance": float(res.parametrized_distance),
        "refinement": {
            "distance_time": float(res.refinement.distance_time),
            "distance_grid": float(res.refinement.distance_grid),
            "relative_change": float(res.refinement.relative_change),
        },
        "converged": bool(res.converged),
        "message": res.message,
        "rounds": int(res.rounds),
        "num_steps": int(res.num_steps),
        "grad_norm": float(res.grad_norm),
        "min_jacobian": float(ej.jacobian_determinant(res.gamma).min()),
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "paper_s": settings["paper_s"],
    }
    if settings["paper_s"]:
        record["speedup_vs_paper_fastest"] = settings["paper_s"][0] / seconds
    emit(record)
    return record


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", default="low,middle,high,defaults")
    parser.add_argument("--pairs", default="synthetic,animals")
    parser.add_argument("--no-reference", action="store_true")
    parser.add_argument("--dtype", default="float64", choices=("float64", "float32"))
    args = parser.parse_args()
    env = environment()
    emit({"benchmark": "environment", "environment": env})
    metric = ej.SplitMetric(*METRIC)
    for name in pair_names(args.pairs):
        records = {
            row: solve(name, ROWS[row], metric, row, args.dtype) for row in args.rows.split(",")
        }
        if args.no_reference or not any(records.values()):
            continue
        reference = solve(name, {**REFERENCE, "paper_s": None}, metric, "reference")
        if reference is None:
            continue
        table = [
            {
                "row": row,
                "grid": list(ROWS[row]["grid"]),
                "solve_s": r["solve_s"],
                "distance": r["distance"],
                "error_vs_reference": abs(r["distance"] - reference["distance"])
                / reference["distance"],
                "refinement_change": r["refinement"]["relative_change"],
                "converged": r["converged"],
            }
            for row, r in records.items()
            if r is not None
        ]
        emit(
            {
                "benchmark": "shape_accuracy_vs_time",
                "pair": name,
                "reference": {"settings": REFERENCE, "distance": reference["distance"]},
                "rows": table,
            }
        )


if __name__ == "__main__":
    main()
