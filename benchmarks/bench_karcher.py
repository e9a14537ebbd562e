"""Karcher steps and distance matrices: time per step for three batching strategies.

Settings: 8 surfaces at 25 x 49 (synthetic, plus the authors' cats, horse and
hand from elastic_jax.datasets when they can be had: $ELASTIC_JAX_DATA or a download; each
scaled to unit area since the shape space here keeps scale), metric (1, 1, 0.1, 0),
modulo="rigid", ShapeOptions(degree=5, vf_degree=5, n_times=7) (midpoint scheme,
registration rounds to convergence); one Karcher step per strategy ("vmap", "map" =
lax.map in one jit, "loop" = Python loop of jitted solves), each in its own process so
that its peak resident memory (ru_maxrss) is its own; then a 16-shape distance matrix
(120 pairs, strategy "map" by default). One JSON record per measurement: first call (with
compilation), a repeat, and the sum of the distances and of their squares (what every
strategy must give alike) with whether every inner solve converged.

Measured on 2 CPU cores (jax 0.10.2, float64), repeat after compilation, with the solver
of that version (central scheme, 2 outer steps): Karcher step map 17.7 s, loop 19.8 s, vmap
52.8 s; distance matrix map 140.5 s, loop 206 s.

Run: python benchmarks/bench_karcher.py [--shapes 8] [--matrix-shapes 16]
     [--strategies vmap,map,loop] [--matrix-strategy map] [--dtype float64|float32]
     (--strategies "" skips them)
     python benchmarks/bench_karcher.py --resolved [--deformations 12] [--medoid]
     [--synthetic] [--finest M N] [--small] [--max-steps 10] [--no-statistics]: one mean
     at the package's defaults (resolved; --finest caps the levels, --small the degrees
     and time points), its SSD history, levels, time, PCA variances, how far the first
     two mode paths get toward +-2 sigma, exp(log) and transport errors at the mean, and
     with --medoid every member's SSD as the centre.

--resolved --deformations 12 --finest 25 49 --small --max-steps 1 --no-statistics on one
H200 (2026-11-28, four processes on the GPU at once; the progress lines give each step's
time): the 16 first, levelled solves 240 s in float64 (compilation included), then one
Karcher step at the mean's grid (16 batched continued solves) 0.81 s, SSD 47.60 -> 22.55;
float32 (TF32 products, before the package traced at full precision) 221 s and 1.73 s.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

WORKER = r"""
import json, resource, sys, time, warnings
import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import numpy as np
sys.path.insert(0, {bench_dir!r})
from _common import shape
import elastic_jax as ej
from elastic_jax import shapes

k, task, strategy = {k}, {task!r}, {strategy!r}
m, n = 25, 49
options = ej.ShapeOptions(degree=5, vf_degree=5, n_times=7, rtol=None)
coll = []
for name in ("cat1", "cat2", "horse0", "hand4"):
    f = shape(name) if len(coll) < k // 2 else None
    if f is not None:
        f = np.asarray(ej.center(ej.resample(f, m, n)))
        coll.append(f / np.sqrt(float(ej.surface_area(f))))
i = 0
while len(coll) < k:
    r = shapes.random_rotation(i)
    make = [shapes.bumpy, shapes.ellipsoid, shapes.bent_cylinder][i % 3]
    f = np.asarray(ej.center(shapes.sample(make, m, n, rotation=r)))
    coll.append(f / np.sqrt(float(ej.surface_area(f))) * (1 + 0.05 * i))
    i += 1
coll = jnp.asarray(np.stack(coll), {dtype!r})
metric = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)
warnings.simplefilter("ignore", ej.ConvergenceWarning)

job = ej.JobOptions(strategy=strategy)

def run():
    if task == "karcher":
        kw = dict(modulo="rigid", max_steps=1, job=job, options=options)
        return ej.karcher_mean(coll, metric, **kw)
    kw = dict(modulo="rigid", job=job, options=options)
    return ej.distance_matrix(coll, metric, **kw)

t = time.perf_counter(); jax.block_until_ready(run()); first = time.perf_counter() - t
t = time.perf_counter(); out = jax.block_until_ready(run()); again = time.perf_counter() - t
# Invariant figures (a mean is defined up to rotation, so no sum of its coordinates):
# the distances, which every strategy must give alike.
d = np.asarray(out.distances)
print(json.dumps({{"first_s": first, "repeat_s": again,
                  "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "sum_distances": float(d.sum()), "sum_sq_distances": float((d ** 2).sum()),
                  "converged": bool(np.all(out.geodesics_converged if task == "karcher"
                                           else out.pairs_converged))}}))
"""


def resolved(args, emit, environment) -> None:
    """--resolved: one Karcher mean at the package's defaults (resolved: levels, then
    continuations on the grid they needed), modulo rigid, on the authors' shapes (with
    --deformations more: each one of them under a random stretch, rotation and Moebius
    map of its parameter sphere), or on three synthetic shapes with --synthetic. With
    --medoid every member's SSD as the centre, from resolved pairwise shape geodesics
    (each pair once, the earlier member reparametrized)."""
    import time
    import warnings

    import jax

    jax.config.update("jax_enable_x64", args.dtype == "float64")
    import numpy as np

    import elastic_jax as ej
    from elastic_jax import shapes

    from _common import deformed, shape

    rng = np.random.default_rng(0)
    if args.synthetic:
        m, n = 13, 25
        coll = [
            shapes.sample(shapes.bumpy, m, n),
            shapes.sample(shapes.ellipsoid, m, n, axes=(1.1, 0.9, 0.7)),
            shapes.sample(shapes.bumpy, m, n, scale=1.3, rotation=shapes.random_rotation(3)),
        ]
        options = ej.ShapeOptions(degree=3, vf_degree=3, n_times=5)
    else:
        coll = [shape(name) for name in ("cat1", "cat2", "horse0", "hand4")]
        if any(f is None for f in coll):
            print(
                "bench_karcher --resolved: the authors' shapes cannot be had "
                "(elastic_jax.datasets: $ELASTIC_JAX_DATA or a download)",
                file=sys.stderr,
            )
            return
        coll += [deformed(coll[i % 4], rng, method="spline") for i in range(args.deformations)]
        options = ej.ShapeOptions()
        if args.small:
            # The slow test's settings: minutes, not hours, on 2 cores.
            options = options.replace(degree=4, vf_degree=4, n_times=5)
        if args.finest:
            options = options.replace(
                levels=tuple(g for g in options.levels if g[0] <= args.finest[0])
            )
    coll = np.stack([np.asarray(f, args.dtype) for f in coll])
    metric = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)
    warnings.simplefilter("ignore", ej.ConvergenceWarning)
    start = time.perf_counter()

    def progress(info: dict) -> None:
        # One line per accepted step (step 0: the first, levelled solves), so that the
        # time of a step at the mean's grid is read off the difference of two lines.
        emit({"benchmark": "karcher_resolved_progress", "dtype": args.dtype, **info})

    res = ej.karcher_mean(
        coll,
        metric,
        modulo="rigid",
        options=options,
        max_steps=args.max_steps,
        job=ej.JobOptions(progress=progress),
    )
    seconds = time.perf_counter() - start
    levels = res.level_distances.tolist()  # NaN (past a shape's last level) as null
    record = {
        "benchmark": "karcher_resolved",
        "settings": {
            "shapes": len(coll),
            "synthetic": args.synthetic,
            "deformations": 0 if args.synthetic else args.deformations,
            "metric": [1.0, 1.0, 0.1, 0.0],
            "modulo": "rigid",
            "dtype": args.dtype,
            "max_steps": args.max_steps,
            "options": options.as_dict(),
        },
        "mean_grid": list(res.mean.shape[-2:]),
        "steps": int(res.num_steps),
        "solves": int(res.num_solves),
        "seconds": seconds,
        "sum_sq_history": res.history[:, 0].tolist(),
        "mean_velocity_history": res.history[:, 1].tolist(),
        "level_distances": [[x if x == x else None for x in row] for row in levels],
        "distances": np.asarray(res.distances).tolist(),
        "geodesics_converged": np.asarray(res.geodesics_converged).tolist(),
        "converged": bool(res.converged),
        "result": ej.RESULTS.name(res.result),
    }
    # The mean first, on its own line: what follows solves more (a medoid: K (K - 1) / 2
    # pairs) and must not lose it.
    emit({**record, "environment": environment()})
    if not args.statistics:
        return
    record = {
        "benchmark": "karcher_resolved_statistics",
        "settings": record["settings"],
        "sum_sq": float(res.history[-1, 0]),
        **_statistics_at(res, metric, options, coll),
    }
    if args.medoid:
        k = len(coll)
        d = np.zeros((k, k))
        for i in range(k):
            for j in range(i + 1, k):
                pair = ej.shape_geodesic(coll[i], coll[j], metric, modulo="rigid", options=options)
                d[i, j] = d[j, i] = float(pair.distance)
        record["member_sum_sq"] = (d**2).sum(axis=1).tolist()
    emit({**record, "environment": environment()})


def _statistics_at(res, metric, options, coll) -> dict:
    """What the mean is for: its PCA (variances, and how far the first two modes' paths
    get toward +-2 sigma), exp(log) from the mean to the second member (the shot's gap to
    the log's target over the distance, by a geodesic between them on the mean's grid)
    and the norm drift of the scaling field carried along that log's path on its own
    differentials."""
    import warnings

    import jax.numpy as jnp
    import numpy as np

    import elastic_jax as ej

    mean = res.mean
    pca = ej.tangent_pca(res, metric)
    reached = []
    for mode in range(min(2, pca.modes.shape[0])):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ej.ConvergenceWarning)
            path = ej.mode_path(pca, mode, metric, degree=options.degree, n_times=5)
        reached.append(ej.sigmas_reached(path, 2.0))
    grid = mean.shape[-2:]
    member = ej.reparametrize(coll[1], ej.sphere_points(*grid), method="spline")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ej.ConvergenceWarning)
        # On the mean's grid (rtol=None), where the mean's tangent space is.
        at_mean = options.replace(rtol=None)
        lg = ej.log(mean, member, metric, modulo="rigid", options=at_mean)
        shot = ej.shoot(mean, lg.velocity, metric, options=options, frames=lg.frames)
        gap = float("nan")
        if bool(shot.converged):
            gap = float(ej.geodesic(shot.endpoint, lg.target, metric, options=options).distance)
        centred = mean - jnp.mean(mean, axis=(1, 2), keepdims=True)
        moved = ej.parallel_transport(
            centred,
            lg.path,
            metric,
            options=options,
            path_frames=lg.path_frames,
            w_frame=lg.path_frames[0],
        )
    return {
        "pca_variances": np.asarray(pca.variances).tolist(),
        "pca_explained": np.asarray(pca.explained).tolist(),
        "mode_paths_reached_sigmas": reached,
        # null when the shot stopped short (exp_log_nodes_reached says where).
        "exp_log_gap_over_distance": gap / float(lg.distance) if gap == gap else None,
        "exp_log_shot_converged": bool(shot.converged),
        "exp_log_nodes_reached": int(shot.n_valid),
        "scaling_transport_drift": float(moved.norm_drift),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--resolved", action="store_true", help="one resolved mean (defaults) instead"
    )
    parser.add_argument("--synthetic", action="store_true", help="--resolved on 3 small shapes")
    parser.add_argument("--deformations", type=int, default=0, help="--resolved: more shapes")
    parser.add_argument("--medoid", action="store_true", help="--resolved: members as centres")
    parser.add_argument(
        "--finest",
        type=int,
        nargs=2,
        metavar=("M", "N"),
        help="--resolved: levels up to this working grid (default: all, to 97 x 193)",
    )
    parser.add_argument(
        "--small", action="store_true", help="--resolved: degree 4, vf_degree 4, 5 time points"
    )
    parser.add_argument(
        "--max-steps", type=int, default=10, help="--resolved: Karcher steps at most"
    )
    parser.add_argument(
        "--statistics",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="--resolved: PCA, mode paths, exp(log) and transport at the mean",
    )
    parser.add_argument("--shapes", type=int, default=8)
    parser.add_argument("--matrix-shapes", type=int, default=16)
    parser.add_argument("--strategies", default="vmap,map,loop")
    parser.add_argument("--matrix-strategy", default="map")
    parser.add_argument("--dtype", default="float64", choices=("float64", "float32"))
    args = parser.parse_args()
    import pathlib

    bench_dir = str(pathlib.Path(__file__).resolve().parent)
    sys.path.insert(0, bench_dir)
    from _common import emit, environment

    if args.resolved:
        resolved(args, emit, environment)
        return
    env = environment()
    jobs = [("karcher", s, args.shapes) for s in args.strategies.split(",") if s]
    if args.matrix_shapes:
        jobs.append(("distance_matrix", args.matrix_strategy, args.matrix_shapes))
    for task, strategy, k in jobs:
        code = WORKER.format(
            bench_dir=bench_dir, k=k, task=task, strategy=strategy, dtype=args.dtype
        )
        out = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, check=True
        )
        record = json.loads(out.stdout.strip().splitlines()[-1])
        emit(
            {
                "benchmark": "karcher_step" if task == "karcher" else "distance_matrix",
                "settings": {
                    "shapes": k,
                    "pairs": k * (k - 1) // 2 if task != "karcher" else None,
                    "strategy": strategy,
                    "grid": [25, 49],
                    "metric": [1.0, 1.0, 0.1, 0.0],
                    "modulo": "rigid",
                    "dtype": args.dtype,
                    "options": {"degree": 5, "vf_degree": 5, "n_times": 7},
                },
                **record,
                "environment": env,
            }
        )


if __name__ == "__main__":
    main()
