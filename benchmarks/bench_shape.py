"""Geodesics between shapes (modulo reparametrization): the paper's Table 3 settings.

Rows (paper, Table 3, laptop without GPU): low 12 x 25, degree 5 / vf degree 5, N = 5
(32-41 s); middle 25 x 49, 7 / 8, N = 10 (95-183 s); high 50 x 99, 9 / 11, N = 15
(505-842 s). Metric (1, 1, 0.1, 0), modulo="diff", the cat pair (../shared/data, resampled
for the lower rows; skipped when absent) and a synthetic pair (a bumpy surface against a
stretched copy under a random reparametrization). Target: at least 20x faster on 2 CPU
cores at every row, with distances no higher. One JSON record per solve: compile time
(first call minus a repeat), solve time, steps, distance, parametrized distance.

Run: python benchmarks/bench_shape.py [--rows low,middle,high] [--method coordinate]
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

from _common import cat_pair, emit, environment  # noqa: E402

METRIC = (1.0, 1.0, 0.1, 0.0)
ROWS = {
    "low": {"grid": (12, 25), "degree": 5, "vf_degree": 5, "n_times": 5, "paper_s": [32, 41]},
    "middle": {"grid": (25, 49), "degree": 7, "vf_degree": 8, "n_times": 10, "paper_s": [95, 183]},
    "high": {"grid": (50, 99), "degree": 9, "vf_degree": 11, "n_times": 15, "paper_s": [505, 842]},
}


def pairs(m: int, n: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    h = shapes.random_rotation(11)
    stretch = jnp.asarray([1.3, 1.0, 0.8])
    synthetic = (
        np.asarray(shapes.sample(shapes.bumpy, m, n)),
        np.asarray(
            jnp.einsum("i,imn->imn", stretch, shapes.sample(shapes.bumpy, m, n, rotation=h))
        ),
    )
    out = {"bumpy vs stretched, reparametrized (synthetic)": synthetic}
    cats = cat_pair(m, n)
    if cats is not None:
        out["cat1 -> cat2"] = cats
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", default="low,middle,high")
    parser.add_argument("--method", default="coordinate", choices=("coordinate", "joint"))
    parser.add_argument("--outer-steps", type=int, default=5)
    parser.add_argument("--interpolation", default="bilinear", choices=("bilinear", "bicubic"))
    args = parser.parse_args()
    env = environment()
    metric = ej.SplitMetric(*METRIC)
    for row in args.rows.split(","):
        settings = ROWS[row]
        m, n = settings["grid"]
        options = {
            "degree": settings["degree"],
            "vf_degree": settings["vf_degree"],
            "n_times": settings["n_times"],
            "method": args.method,
            "outer_steps": args.outer_steps,
            "interpolation": args.interpolation,
        }
        for pair, (f1, f2) in pairs(m, n).items():
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", ej.ConvergenceWarning)
                start = time.perf_counter()
                jax.block_until_ready(ej.shape_geodesic(f1, f2, metric, **options))
                first = time.perf_counter() - start
                start = time.perf_counter()
                res = jax.block_until_ready(ej.shape_geodesic(f1, f2, metric, **options))
                solve = time.perf_counter() - start
            emit(
                {
                    "benchmark": "shape_geodesic",
                    "settings": {
                        "row": row,
                        "pair": pair,
                        "m": m,
                        "n": n,
                        "metric": METRIC,
                        "modulo": "diff",
                        **options,
                    },
                    "compile_s_estimate": first - solve,
                    "solve_s": solve,
                    "num_steps": int(res.num_steps),
                    "converged": bool(res.converged),
                    "distance": float(res.distance),
                    "parametrized_distance": float(res.parametrized_distance),
                    "energy_history": np.asarray(res.energy_history).tolist(),
                    "min_jacobian": float(ej.jacobian_determinant(res.gamma).min()),
                    "paper_s": settings["paper_s"],
                    "speedup_vs_paper_fastest": settings["paper_s"][0] / solve,
                    "environment": env,
                }
            )


if __name__ == "__main__":
    main()
