"""``python -m elastic_jax``: a geodesic between two built-in surfaces, summarized as JSON.

The main job on a built-in example: a straight cylinder bent into an arc, 25 x 49 grid,
metric (1, 1, 0.1, 0), degree 7, N = 10. Prints the distance, the straight line's energy,
the solver's steps and the wall time. ``--out DIR`` also writes the path as ``path.npz``
(atomically). The full command line arrives with the CLI issue.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import tempfile
import time


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m elastic_jax", description=__doc__.splitlines()[0]
    )
    parser.add_argument("--grid", type=int, nargs=2, default=(25, 49), metavar=("M", "N"))
    parser.add_argument("--degree", type=int, default=7)
    parser.add_argument("--times", type=int, default=10)
    parser.add_argument("--solver", choices=("bfgs", "lbfgs"), default="bfgs")
    parser.add_argument(
        "--float32", action="store_true", help="compute in float32 (default float64)"
    )
    parser.add_argument("--out", type=pathlib.Path, default=None)
    args = parser.parse_args(argv)

    import jax

    if not args.float32:
        jax.config.update("jax_enable_x64", True)  # the program's choice, not the library's
    import numpy as np

    import elastic_jax as ej
    from elastic_jax import shapes

    m, n = args.grid
    f1 = shapes.sample(shapes.bent_cylinder, m, n, curvature=0.0)
    f2 = shapes.sample(shapes.bent_cylinder, m, n, curvature=0.6, half_length=1.2)
    metric = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)
    start = time.perf_counter()
    res = jax.block_until_ready(
        ej.geodesic(f1, f2, metric, degree=args.degree, n_times=args.times, solver=args.solver)
    )
    summary = {
        "shapes": "straight cylinder -> bent cylinder (built-in)",
        "grid": [m, n],
        "metric": [1.0, 1.0, 0.1, 0.0],
        "degree": args.degree,
        "n_times": args.times,
        "solver": args.solver,
        "dtype": str(res.path.dtype),
        "distance": float(res.distance),
        "energy": float(res.energy),
        "straight_energy": float(res.straight_energy),
        "num_steps": int(res.num_steps),
        "converged": bool(res.converged),
        "seconds_with_compilation": time.perf_counter() - start,
    }
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        target = args.out / "path.npz"
        # Written beside the target and renamed: an interrupted run leaves no half file.
        fields = {k: v for k, v in summary.items() if k != "shapes"}
        with tempfile.NamedTemporaryFile(dir=args.out, suffix=".npz", delete=False) as tmp:
            try:
                np.savez(tmp, path=np.asarray(res.path), **fields)
            except BaseException:
                os.unlink(tmp.name)
                raise
        os.replace(tmp.name, target)
        summary["path_file"] = str(target)
    print(json.dumps(summary, indent=2))
    return 0 if summary["converged"] else 3


if __name__ == "__main__":
    raise SystemExit(main())
