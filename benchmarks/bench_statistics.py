"""Statistics on the parametrized space: shoot, log, transport, tangent PCA; the paper's Table 2.

Part 1, timings. Metric (1, 1, 0.1, 0), degree 7, N = 13, float64, midpoint
scheme, at 25 x 49 and 50 x 99, on the authors' cats and horse (elastic_jax.datasets:
$ELASTIC_JAX_DATA or a download; resampled from 50 x 99; synthetic surfaces from
elastic_jax.shapes when they cannot be had, and the record says so). What is timed, each
with its first call (compilation included) and the min / median of ``--repeat`` further
calls:

- ``log``: modulo "none", cat1 -> cat2 (one :func:`geodesic` solve with its saddle check);
- ``shoot``: from cat1 with that log's velocity (N - 2 Newton solves); the record holds
  the endpoint's distance to cat2 relative to cat2's size, the Newton residuals and steps;
- ``parallel_transport``: ``--transport-scale`` (0.1) times the velocity of log(cat1 ->
  horse0) carried along the cat1 -> cat2 geodesic (Schild's ladder, 12 rungs of two
  Newton solves each); with the full velocity (scale 1) the ladder diverges (below);
- ``tangent_pca``: at the base point cat1, of K = 3 velocities: log(cat1 -> cat2),
  log(cat1 -> horse0) and 0 (cat1 itself); the logs are computed once beforehand and not
  part of this time (it is the Gram matrix and its eigen-decomposition only);
- ``mode_path``: the first mode, +-2 sigma, 7 time points each way (two shoots).

Part 2, the paper's Table 2 (section "Comparison to the SRNF-framework"): metric
(0, 1/2, 1, 0), the pull-back of the flat L2 metric of SRNFs (docs/math.md §3), degree 7,
N = 25, pairs cat1 -> horse0 and cat1 -> cat2. L_l: the (0, 1/2, 1, 0) length of the
straight line f1 + t (f2 - f1) at N time points; L_g: that length of the parametrized
geodesic (:func:`geodesic`, no registration); L_i: that length of the inverted SRNF
straight line (:func:`srnf_geodesic`, 7 time points as the paper's "7 stps"; the length
on those 7 nodes); L2: ||q(f1) - q(f2)|| (:func:`srnf_distance`). All lengths with the
package's :func:`path_length` (midpoint scheme; the forward ones are recorded too). The
paper's relations: L2 <= L_g <= L_l < L_i. The inverted line's last nodes miss their
targets (relative SRNF residuals 0.4 to 0.65), so its last step is a jump that one
evaluation of the metric per step does not resolve: the record adds L_i_subdivided, the
length of the piecewise-linear path through the 7 nodes with each step cut in 4 (25
nodes, as N), and each step's length. An unconverged geodesic is solved again from the
converged 25 x 49 one (``schedule``) and recorded next to it. The isometry check (paper
Table 1): the straight line's (0, 1/2, 1, 0) length against the L2 length of its SRNF
image (:func:`srnf_path_length`) at N = 13, 25, 99. The paper's surfaces are scaled
otherwise: compare ratios to L2, not the lengths.

MEASURED (2026-11-23) on 2 CPU cores shared with two other sessions (1-minute load 8 to
13 during the timings: every time is inflated several fold and noisy; a first run at load
~4 gave log 3.0 s and shoot 49.7 s at 25 x 49). Timings, first call / min / median, s:

    25 x 49, --repeat 2   log 88.3 / 5.6 / 10.1 (converged); shoot 204 / 136 / 153
                          (converged, 52 Newton steps, residual 7e-15, endpoint 1.0e-4
                          from cat2, nodes 3e-5 from the log's path); tangent_pca
                          8.9 / 0.024 / 0.028; mode_path 254 / 97 / 126;
                          parallel_transport, scale 1: 691 / 333 / 368, NOT converged
                          (norm drift 1205, residual 141); scale 0.1: 275 (one call),
                          converged (residual 2e-15), norm drift 0.36
    50 x 99, --repeat 1   log 207 / 72.6 (converged); tangent_pca (--repeat 2) 4.4 /
                          0.008 / 0.010; shoot 613 / 620, NOT converged: the second
                          node's Newton solve stops at max_newton = 20 with residual 197
                          and the path leaves (speeds 2.5, 2.5, then 3082);
                          parallel_transport, scale 0.1 (load ~2): 370 / 267, NOT
                          converged: rungs 1-9 at residual 3e-16, rungs 10-12 at 1e-3,
                          40, 3e5 (norm 0.22 -> 0.33 -> 1.2e7); log(cat1 -> horse0) itself
                          unconverged at 50 x 99; mode_path (load ~2) 224 / 173 (it
                          reports no convergence; its frames' smallest area ratio 2e-3)

At 25 x 49 the transport of the cat1 -> cat2 geodesic's own velocity along it (exact
answer: its final velocity) keeps the norm within 5 % for 11 rungs and fails in the last
(norm 2.1 -> 2456, residual 82); that rung's reflection lands about a step beyond the
path's end.

Follow-up at 50 x 99 (cat1 -> cat2, degree 7, shooting the geodesic's own velocity; the
shoot record's ``midpoint_area_ratio`` is the figure below): the shot path equals the
geodesic to 1e-7 relative up to the first failing node, which is node 2 of 12 (N = 13),
18 of 24 (N = 25), 21 of 48 (N = 49), and node 3 of 12 for the registered log (modulo
"diff", N = 13). Every failing step has a cell whose area at the step's midpoint is
0.20 / 0.29 / 0.44 / 0.40 of its area at the nodes (the smallest over cells); every step
that solved has at least 0.49. At the N = 25 failure the start is 7e-4 from the node, the
Jacobian's smallest singular value there is 0.67 (not singular) but its largest grows from
970 to 3980 between start and node; Newton leaves, optimistix's Levenberg-Marquardt
gets 2.5 times closer in 60 iterations, a Gauss-Newton with Armijo backtracking does not
move, and a continuation from the zero step reaches 2.3e-4 of the node and then a fold
of the solution branch. Since then shoot stops at the first failed node (NaN after it,
``n_valid``) instead of going on from it.

Table 2, metric (0, 1/2, 1, 0), degree 7, N = 25, midpoint lengths, ratio to L2 in ():

    pair, grid          L_l            L_g            L_i (7)        L_i (7, cut 4)  L2
    cat1-horse0 50x99   1.611 (1.568)  1.306 (1.271)* 1.477 (1.437)  1.838 (1.789)   1.028
    cat1-cat2   50x99   1.645 (1.445)  1.383 (1.215)  1.715 (1.507)  2.004 (1.760)   1.138
    cat1-horse0 25x49   1.410 (1.512)  1.146 (1.229)  1.297 (1.391)  1.641 (1.760)   0.932
    cat1-cat2   25x49   1.390 (1.378)  1.144 (1.134)  1.409 (1.397)  1.737 (1.722)   1.009
    paper cat/horse     0.8932 (1.457) 0.7948 (1.297) 1.1442 (1.867) -               0.6130

    * from the straight line the solve stopped at max_steps (1000 steps, gradient
      0.042, L_g 1.316); warm-started from 25 x 49 it converged (707 steps), L_g 1.306.

L2 <= L_g <= L_l holds in every row; L_l < L_i fails for cat1-horse0 on both grids with
the 7-node length and holds with the steps cut in 4: the inversions' last node misses its
target by 51 % (25 x 49) and 65 % (50 x 99) relative SRNF residual, and the last step
(node 5 to the horse) carries 0.85 of L_i's 1.48 (forward scheme: 3.0 of 3.6). Isometry
(relative gap of the (0, 1/2, 1, 0) length of the straight line to the L2 length of its
SRNF image, midpoint, N = 13 / 25 / 99): cat1-cat2 50 x 99 2.8e-2 / 6.7e-3 / 4.4e-5;
cat1-horse0 50 x 99 2.9e-3 / 1.7e-2 / 3.7e-3 (not monotone, as docs/math.md §3 says of these
lines); the forward length at N = 13 on the cats, 1.6251290345, is the value pinned in
tests/test_srnf.py.

Run: python benchmarks/bench_statistics.py [--grids 25x49,50x99] [--repeat 2]
     [--ops log,shoot,transport,pca,mode_path] [--transport-scale 0.1]
     [--skip-table | --only-table] [--pairs cat1-horse0,cat1-cat2] [--table-grids 50x99]
     [--max-steps 1000]
"""

from __future__ import annotations

import argparse
import os
import resource
import time
import warnings

import jax

jax.config.update("jax_enable_x64", True)  # a script, not the library

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import elastic_jax as ej  # noqa: E402
from elastic_jax import shapes  # noqa: E402

from _common import emit, environment, shape, time_calls  # noqa: E402

METRIC = (1.0, 1.0, 0.1, 0.0)
SRNF_METRIC = (0.0, 0.5, 1.0, 0.0)
DEGREE = 7
N_TIMES = 13
TABLE_N_TIMES = 25
SRNF_N_TIMES = 7  # the paper's "L_i (7 stps)"
ISOMETRY_N_TIMES = (13, 25, 99)
WARM_START_GRID = (25, 49)  # an unconverged table geodesic is solved again, warm-started here
SUBDIVIDE = 4  # the inverted line's 6 steps cut in 4: 25 nodes, as N of the table
# Paper, Table 2, the cat / horse row (its surfaces are scaled otherwise: compare ratios).
OPS = ("log", "shoot", "transport", "pca", "mode_path")
PAPER_CAT_HORSE = {"L_l": 0.8932, "L_g": 0.7948, "L_i": 1.1442, "L2": 0.6130}


def _synthetic(name: str, m: int, n: int) -> np.ndarray:
    if name == "cat1":
        return np.asarray(shapes.sample(shapes.bumpy, m, n))
    if name == "cat2":
        return np.asarray(shapes.sample(shapes.ellipsoid, m, n))
    return np.asarray(shapes.sample(shapes.bent_cylinder, m, n, curvature=0.6, half_length=1.2))


def midpoint_area_ratios(path) -> list[float]:
    """Per step k: min over cells of |a1 x a2| at (f_k + f_{k+1}) / 2 over the smaller of
    its values at f_k and f_{k+1} (1 when frames only stretch; small when a cell's frame
    turns through a large angle or it passes near a fold within the step)."""
    from elastic_jax._geometry.differential import area_element, interior_frame

    areas = area_element(*interior_frame(jnp.asarray(path)))
    middle = area_element(*interior_frame(0.5 * (jnp.asarray(path)[1:] + jnp.asarray(path)[:-1])))
    ratio = middle / jnp.minimum(areas[1:], areas[:-1])
    return [float(x) for x in jnp.min(ratio.reshape(ratio.shape[0], -1), axis=1)]


def surface(name: str, m: int, n: int) -> tuple[np.ndarray, str]:
    """One of the authors' shapes on an m x n grid (resampled from 50 x 99), or its
    synthetic stand-in."""
    f = shape(name)
    if f is None:
        return _synthetic(name, m, n), "synthetic (the authors' surfaces absent)"
    if (m, n) != (50, 99):
        f = np.asarray(ej.resample(f, m, n))
    return f, f"elastic_jax.datasets {name}"


def grid(text: str) -> tuple[int, int]:
    m, n = text.lower().split("x")
    return int(m), int(n)


def timed(fn, repeat: int) -> tuple[object, dict]:
    """fn's result and its first call (compilation included) and min / median of repeats."""
    start = time.perf_counter()
    result = jax.block_until_ready(fn())
    first = time.perf_counter() - start
    timing = time_calls(fn, repeat)
    return result, {
        "first_call_s": first,
        "compile_s_estimate": first - timing["min_s"],
        "min_s": timing["min_s"],
        "median_s": timing["median_s"],
        "repeats": repeat,
    }


def relative(x, y) -> float:
    return float(jnp.linalg.norm(x - y) / jnp.linalg.norm(y))


def min_area_ratio(path) -> float:
    """min over the path's frames and interior grid of the area density |q|^2 over its mean
    (|q|^2 = |f_theta x f_phi| / sin phi, docs/math.md §3): near 0, a frame is nearly not
    immersed."""
    density = jnp.sum(ej.srnf(path)[..., 1:-1, :-1] ** 2, axis=-3)
    return float(jnp.min(density / jnp.mean(density, axis=(-2, -1), keepdims=True)))


def subdivided(path, k: int):
    """The piecewise-linear path through the nodes, each step cut into k equal steps."""
    s = jnp.arange(k, dtype=path.dtype)[None, :, None, None, None] / k
    inner = path[:-1, None] + s * (path[1:] - path[:-1])[:, None]
    return jnp.concatenate([inner.reshape((-1, *path.shape[1:])), path[-1:]])


def statistics_records(
    m: int, n: int, repeat: int, ops: set[str], transport_scale: float, env: dict
) -> None:
    metric = ej.SplitMetric(*METRIC)
    (f1, src1), (f2, src2), (f3, src3) = (surface(s, m, n) for s in ("cat1", "cat2", "horse0"))
    settings = {
        "m": m,
        "n": n,
        "metric": METRIC,
        "degree": DEGREE,
        "n_times": N_TIMES,
        "scheme": "midpoint",
        "dtype": "float64",
        "data": {"cat1": src1, "cat2": src2, "horse0": src3},
    }
    options = {"degree": DEGREE, "n_times": N_TIMES}

    def record(name: str, what: str, timing: dict, **fields) -> None:
        emit(
            {
                "benchmark": f"statistics.{name}",
                "settings": {**settings, "timed": what},
                **timing,
                **fields,
                "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                # The machine's other jobs: 1-minute load average after the timings.
                "load_average_1min": os.getloadavg()[0],
                "environment": env,
            }
        )

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ej.ConvergenceWarning)
        if "log" in ops:
            lg, timing = timed(lambda: ej.log(f1, f2, metric, **options), repeat)
            record(
                "log",
                'log(cat1, cat2, modulo="none"): one geodesic solve (saddle check included)',
                timing,
                converged=bool(lg.converged),
                distance=float(lg.distance),
            )
        else:
            lg = ej.log(f1, f2, metric, **options)

        if "shoot" in ops:
            sh, timing = timed(lambda: ej.shoot(f1, lg.velocity, metric, **options), repeat)
            record(
                "shoot",
                "shoot(cat1, log(cat1, cat2).velocity): N - 2 Newton solves",
                timing,
                converged=bool(sh.converged),
                n_valid=int(sh.n_valid),
                endpoint_relative_error=relative(sh.endpoint, f2),
                path_relative_error=relative(sh.path, lg.path),
                max_residual=float(jnp.nanmax(sh.residuals)),
                newton_steps_total=int(jnp.sum(sh.newton_steps)),
                newton_steps_max=int(jnp.max(sh.newton_steps)),
                residuals=[float(x) for x in sh.residuals],
                newton_steps=[int(x) for x in sh.newton_steps],
                node_relative_errors=[relative(sh.path[k], lg.path[k]) for k in range(N_TIMES)],
                speed_spread=float((sh.speeds.max() - sh.speeds.min()) / sh.speeds.mean()),
                # Per step of the log's path: the smallest ratio over the cells of the area
                # at the step's midpoint to the smaller of its areas at the two nodes (the
                # steps where Newton fails are those where it is far below 1:
                # docs/guides/limitations.md).
                midpoint_area_ratio=midpoint_area_ratios(lg.path),
            )

        if not ops & {"transport", "pca", "mode_path"}:
            return
        lg3 = ej.log(f1, f3, metric, **options)
        if "transport" in ops:
            w = transport_scale * lg3.velocity
            pt, timing = timed(
                lambda: ej.parallel_transport(w, lg.path, metric, degree=DEGREE), repeat
            )  # the default method, "galerkin" (the ladder's figures predate 2026-11-27)
            record(
                "parallel_transport",
                f"{transport_scale:g} x log(cat1, horse0).velocity along the cat1 -> cat2 "
                "geodesic (Galerkin transport, N - 1 segments)",
                timing,
                transport_scale=transport_scale,
                norms=[float(x) for x in pt.norms],
                converged=bool(pt.converged),
                n_valid=int(pt.n_valid),
                norm_drift=float(pt.norm_drift),
                max_residual=float(jnp.nanmax(pt.residuals)),
                residuals_per_rung=[float(x) for x in jnp.max(pt.residuals, axis=1)],
                log_horse_converged=bool(lg3.converged),
                log_horse_distance=float(lg3.distance),
            )

        if not ops & {"pca", "mode_path"}:
            return
        velocities = jnp.stack([lg.velocity, lg3.velocity, jnp.zeros_like(lg.velocity)])
        pca, timing = timed(lambda: ej.tangent_pca((f1, velocities), metric), repeat)
        if "pca" in ops:
            record(
                "tangent_pca",
                "tangent_pca at cat1 of K = 3 velocities (logs to cat2, horse0, and 0); "
                "the logs precomputed, not timed",
                timing,
                variances=[float(x) for x in pca.variances],
                explained=[float(x) for x in pca.explained],
            )

        if "mode_path" in ops:
            path, timing = timed(lambda: ej.mode_path(pca, 0, metric, degree=DEGREE), repeat)
            record(
                "mode_path",
                "mode_path(pca, 0): +-2 sigma, 7 time points each way (two shoots)",
                timing,
                shape=list(path.shape),
                min_area_ratio=min_area_ratio(path),
            )


def table_record(pair: str, m: int, n: int, max_steps: int, env: dict) -> dict:
    metric = ej.SplitMetric(*SRNF_METRIC)
    name1, name2 = pair.split("-")
    (f1, src1), (f2, src2) = surface(name1, m, n), surface(name2, m, n)
    f1, f2 = jnp.asarray(f1), jnp.asarray(f2)

    def length(path, scheme="midpoint"):
        return float(ej.path_length(metric, path, scheme=scheme))

    line = ej.straight_path(f1, f2, TABLE_N_TIMES)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ej.ConvergenceWarning)
        start = time.perf_counter()
        geo = jax.block_until_ready(
            ej.geodesic(f1, f2, metric, degree=DEGREE, n_times=TABLE_N_TIMES, max_steps=max_steps)
        )
        geodesic_s = time.perf_counter() - start
        warm = None
        if not bool(geo.converged) and (m, n) != WARM_START_GRID:
            # An unconverged L_g is only an upper bound: solve again from the converged
            # coarse-grid geodesic (schedule, paper remark after Table 3).
            start = time.perf_counter()
            warm = jax.block_until_ready(
                ej.geodesic(
                    f1,
                    f2,
                    metric,
                    degree=DEGREE,
                    n_times=TABLE_N_TIMES,
                    max_steps=max_steps,
                    schedule=[(DEGREE, TABLE_N_TIMES, *WARM_START_GRID)],
                )
            )
            warm_s = time.perf_counter() - start
        start = time.perf_counter()
        inv = jax.block_until_ready(ej.srnf_geodesic(f1, f2, SRNF_N_TIMES))
        srnf_s = time.perf_counter() - start
    # L_i on the 7 nodes resolves each step by one metric evaluation; the piecewise-linear
    # path through them, each step cut in SUBDIVIDE, shows what that discretization misses.
    refined = subdivided(inv.path, SUBDIVIDE)
    lengths = {
        "L_l": length(line),
        "L_g": length(geo.path),
        "L_i": length(inv.path),
        "L2": float(ej.srnf_distance(f1, f2)),
        "L_i_subdivided": length(refined),
    }
    forward = {
        "L_l": length(line, "forward"),
        "L_g": length(geo.path, "forward"),
        "L_i": length(inv.path, "forward"),
        "L_i_subdivided": length(refined, "forward"),
    }
    relations = {
        "L2 <= L_g": lengths["L2"] <= lengths["L_g"],
        "L_g <= L_l": lengths["L_g"] <= lengths["L_l"],
        "L_l < L_i": lengths["L_l"] < lengths["L_i"],
    }
    relations["all"] = all(relations.values())
    relations["L_l < L_i_subdivided"] = lengths["L_l"] < lengths["L_i_subdivided"]
    relations["L_g <= L_i"] = lengths["L_g"] <= lengths["L_i"]
    isometry = []
    for n_times in ISOMETRY_N_TIMES:
        path = ej.straight_path(f1, f2, n_times)
        srnf_length = float(ej.srnf_path_length(path))
        row = {"n_times": n_times, "srnf_l2_length": srnf_length}
        for scheme in ("midpoint", "forward"):
            value = length(path, scheme)
            row[f"{scheme}_length"] = value
            row[f"{scheme}_relative_error"] = abs(value - srnf_length) / srnf_length
        isometry.append(row)
    # The same check on the paths of L_g and L_i (their SRNF images' L2 lengths).
    image = {
        "geodesic_srnf_l2_length": float(ej.srnf_path_length(geo.path)),
        "inversion_srnf_l2_length": float(inv.srnf_length),
        "inversion_subdivided_srnf_l2_length": float(ej.srnf_path_length(refined)),
    }
    record = {
        "benchmark": "statistics.table2",
        "settings": {
            "pair": pair,
            "m": m,
            "n": n,
            "metric": SRNF_METRIC,
            "degree": DEGREE,
            "n_times": TABLE_N_TIMES,
            "srnf_n_times": SRNF_N_TIMES,
            "srnf_degrees": [2, 4, 7],
            "scheme": "midpoint",
            "dtype": "float64",
            "data": {name1: src1, name2: src2},
        },
        "lengths": lengths,
        "forward_lengths": forward,
        "ratios_to_L2": {k: v / lengths["L2"] for k, v in lengths.items()},
        "relations": relations,
        "isometry_straight_line": isometry,
        "srnf_images": image,
        "geodesic": {
            "solve_s_first_call": geodesic_s,
            "converged": bool(geo.converged),
            "message": geo.message,
            "num_steps": int(geo.num_steps),
            "grad_norm": float(geo.grad_norm),
            "min_curvature": float(geo.min_curvature),
            "distance": float(geo.distance),
            "min_area_ratio": min_area_ratio(geo.path),
            "max_steps": max_steps,
        },
        "srnf_geodesic": {
            "solve_s_first_call": srnf_s,
            "converged": [bool(x) for x in inv.nodes_converged],
            "relative_residuals": [float(x) for x in inv.relative_residuals],
            "num_steps": [int(x) for x in inv.node_steps],
            "srnf_distance": float(inv.srnf_distance),
            "step_lengths": [length(inv.path[k : k + 2]) for k in range(SRNF_N_TIMES - 1)],
            "step_lengths_forward": [
                length(inv.path[k : k + 2], "forward") for k in range(SRNF_N_TIMES - 1)
            ],
            "min_area_ratio": min_area_ratio(inv.path),
        },
        "straight_line_min_area_ratio": min_area_ratio(line),
        "areas": [float(ej.surface_area(f1)), float(ej.surface_area(f2))],
        "environment": env,
    }
    if warm is not None:
        warm_length = length(warm.path)
        record["geodesic_warm_started"] = {
            "schedule": [[DEGREE, TABLE_N_TIMES, *WARM_START_GRID]],
            "solve_s_first_call": warm_s,
            "converged": bool(warm.converged),
            "message": warm.message,
            "num_steps": int(warm.num_steps),
            "grad_norm": float(warm.grad_norm),
            "min_curvature": float(warm.min_curvature),
            "L_g": warm_length,
            "L_g_forward": length(warm.path, "forward"),
            "L_g_over_L2": warm_length / lengths["L2"],
            "srnf_l2_length": float(ej.srnf_path_length(warm.path)),
            "relations": {
                "L2 <= L_g": lengths["L2"] <= warm_length,
                "L_g <= L_l": warm_length <= lengths["L_l"],
                "L_g <= L_i": warm_length <= lengths["L_i"],
            },
        }
    if pair == "cat1-horse0":
        record["paper"] = {
            "lengths": PAPER_CAT_HORSE,
            "ratios_to_L2": {k: v / PAPER_CAT_HORSE["L2"] for k, v in PAPER_CAT_HORSE.items()},
        }
    emit(record)
    return record


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--grids", default="25x49,50x99", help="grids of the timings")
    parser.add_argument("--repeat", type=int, default=2, help="timed calls after the first")
    parser.add_argument("--ops", default=",".join(OPS), help="what part 1 times")
    parser.add_argument(
        "--transport-scale",
        type=float,
        default=0.1,
        help="the transported vector is this times log(cat1, horse0).velocity",
    )
    parser.add_argument("--pairs", default="cat1-horse0,cat1-cat2", help="Table 2 pairs")
    parser.add_argument("--table-grids", default="50x99", help="grids of Table 2")
    parser.add_argument(
        "--max-steps", type=int, default=1000, help="Table 2: max_steps of each geodesic solve"
    )
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--skip-table", action="store_true")
    group.add_argument("--only-table", action="store_true")
    args = parser.parse_args()
    unknown = set(args.ops.split(",")) - set(OPS)
    if unknown:
        parser.error(f"--ops: unknown {sorted(unknown)}; choose from {','.join(OPS)}")
    env = environment()
    if not args.only_table:
        for text in args.grids.split(","):
            ops = set(args.ops.split(","))
            statistics_records(*grid(text), args.repeat, ops, args.transport_scale, env)
    if not args.skip_table:
        for text in args.table_grids.split(","):
            for pair in args.pairs.split(","):
                table_record(pair, *grid(text), args.max_steps, env)


if __name__ == "__main__":
    main()
