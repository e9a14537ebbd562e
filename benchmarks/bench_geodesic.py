"""Parametrized geodesics (paper Algorithm 1): compile time, solve time, steps, energies.

Settings: metric (1, 1, 0.1, 0); 25 x 49 with degree 7 and N = 10, and 50 x 99
with degree 7 and N = 13; the authors' cat pair from elastic_jax.datasets ($ELASTIC_JAX_DATA
or a download; resampled to 25 x 49 for the middle row; skipped when they cannot be had)
and a synthetic pair (bent cylinders); both solvers; and the multiresolution schedule at
50 x 99. One JSON record per solve. Targets on a 2-core CPU after compilation: under 5 s
at 25 x 49 and under 20 s at 50 x 99.

Run: python benchmarks/bench_geodesic.py [--repeats 3] [--quick] [--dtypes float64,float32]
     [--solvers bfgs,lbfgs]
"""

from __future__ import annotations

import argparse
import itertools
import time
import warnings

import jax

jax.config.update("jax_enable_x64", True)  # a script, not the library

import numpy as np  # noqa: E402

import elastic_jax as ej  # noqa: E402
from elastic_jax import shapes  # noqa: E402

from _common import cat_pair, emit, environment, time_calls  # noqa: E402

METRIC = (1.0, 1.0, 0.1, 0.0)


def pairs(m: int, n: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    out = {
        "bent cylinders (synthetic)": (
            np.asarray(shapes.sample(shapes.bent_cylinder, m, n, curvature=0.0)),
            np.asarray(shapes.sample(shapes.bent_cylinder, m, n, curvature=0.6, half_length=1.2)),
        )
    }
    cats = cat_pair(m, n)
    if cats is not None:
        out["cat1 -> cat2"] = cats
    return out


def solve_record(f1, f2, *, repeats, **options) -> dict:
    metric = ej.SplitMetric(*METRIC)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ej.ConvergenceWarning)
        start = time.perf_counter()
        result = jax.block_until_ready(ej.geodesic(f1, f2, metric, **options))
        first = time.perf_counter() - start
        timing = time_calls(lambda: ej.geodesic(f1, f2, metric, **options), repeats)
    return {
        "first_call_s": first,
        "compile_s_estimate": first - timing["min_s"],
        "solve_s_median": timing["median_s"],
        "solve_s_min": timing["min_s"],
        "repeats": repeats,
        "num_steps": int(result.num_steps),
        "converged": bool(result.converged),
        "grad_norm": float(result.grad_norm),
        "energy": float(result.energy),
        "straight_energy": float(result.straight_energy),
        "distance": float(result.distance),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help="only the 25 x 49 synthetic row")
    # The issue-3 comparison with the authors' code was made with their forward scheme.
    parser.add_argument("--scheme", default="midpoint", choices=("midpoint", "forward", "central"))
    parser.add_argument("--dtypes", default="float64", help="comma-separated: float64,float32")
    parser.add_argument("--solvers", default="bfgs,lbfgs", help="comma-separated: bfgs,lbfgs")
    args = parser.parse_args()
    # A wrong name is a usage error (exit 2, one line) before anything compiles.
    for flag, given, allowed in (
        ("--dtypes", args.dtypes, ("float64", "float32")),
        ("--solvers", args.solvers, ("bfgs", "lbfgs")),
    ):
        unknown = sorted(set(given.split(",")) - set(allowed))
        if unknown:
            parser.error(f"{flag}: unknown {unknown}; choose from {', '.join(allowed)}")
    env = environment()
    rows = [(25, 49, 7, 10)] if args.quick else [(25, 49, 7, 10), (50, 99, 7, 13)]
    for (m, n, degree, n_times), dtype in itertools.product(rows, args.dtypes.split(",")):
        for pair, (f1, f2) in pairs(m, n).items():
            if args.quick and pair != "bent cylinders (synthetic)":
                continue
            # The library computes in its inputs' precision (float32 is a GPU user's choice).
            f1, f2 = f1.astype(dtype), f2.astype(dtype)
            solvers = ["bfgs"] if args.quick else args.solvers.split(",")
            schedules = [()] if (args.quick or m < 50) else [(), ((4, 5), (7, 7))]
            for solver in solvers:
                for schedule in schedules:
                    options = {
                        "degree": degree,
                        "n_times": n_times,
                        "solver": solver,
                        "scheme": args.scheme,
                    }
                    if schedule:
                        options["schedule"] = schedule
                    record = solve_record(f1, f2, repeats=args.repeats, **options)
                    emit(
                        {
                            "benchmark": "geodesic",
                            "settings": {
                                "pair": pair,
                                "m": m,
                                "n": n,
                                "metric": METRIC,
                                "dtype": dtype,
                                **{k: v for k, v in options.items() if k != "schedule"},
                                "schedule": [list(level) for level in schedule],
                            },
                            **record,
                            "target_solve_s": 5.0 if m == 25 else 20.0,
                            "environment": env,
                        }
                    )


if __name__ == "__main__":
    main()
