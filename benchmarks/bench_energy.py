"""Value and gradient of the path energy with respect to the interior path points.

Settings: 50 x 99 grid, N = 13 time points, metric (1, 1, 0.1, 0), float64 and
float32; the straight line between the authors' cats (elastic_jax.datasets:
$ELASTIC_JAX_DATA or a download) when they can be had, else between two built-in synthetic
surfaces. Prints one JSON record per dtype: compile time
(ahead of time, separately) and the min and median of repeated calls.
Target on a 2-core CPU: float64 median at most 10 ms.

Roofline (target: within 3x of it where the authors' code cannot be run alongside):
XLA's cost analysis of the compiled value-and-gradient gives its floating-point
operations and bytes accessed; this machine's attainable peaks are measured here, in the
same process and dtype: a 1024 x 1024 matrix product (2 n^3 flops) and a 32 MiB
elementwise add (bytes read and written). flop_bound_s = flops / peak_flops,
byte_bound_s = bytes / peak_bandwidth, roofline_s the larger; the record gives
median_s over each. XLA counts every operation's operands and results as memory traffic
(as if nothing stayed in cache), so its byte bound is an upper bound on the traffic and
the flop bound is the one a fused kernel can approach.

Measured (2026-11-23, 2 cores, float64, cats): XLA counts 108 MFLOP and 281 MB for the
value and gradient; the machine's product reaches 102-106 GFLOP/s and the add 5.5 GB/s,
so the flop bound is 1.02-1.06 ms and the byte bound 50 ms. The call took 5.6-6.1 ms
(min) and 7.2-9.4 ms (median) on a machine shared with other jobs (4.4 / 5.2 ms quiet):
4.3-6x the flop bound, 0.14-0.19 of the byte bound. Against the authors' 93 ms
(one side-by-side run) that is 15-21x; the 50x target is not met.

Where the time goes (XLA's trace events, float64, same day): 16 "pad" fusions, the
transposes of the coordinate and time slices, hold about 65 % of the threads' time; each
recomputes the pointwise graph of the metric. Variants measured in one process (median,
current 5.9-6.4 ms): a custom_vjp whose forward also returns the pointwise partials 4.8 ms;
a custom_jvp with the chain rule through the invariants written out 5.6 ms (40 fusions
against 44); the coordinates as separate arrays 33 ms; time mixing by small matrices
12.5 ms; a lax.map over time steps 13.6 ms; optimization barriers change nothing (XLA:CPU
expands them before fusing). None reaches 1.9 ms (50x), so none landed.

Measured again (2026-11-28, 2 cores, cats, the solvers' compiler options): the path energy's
derivative now comes from the integrand's partials, computed once per point behind a
conditional (energy.py, speed_density): XLA counts 54 MFLOP and 187 MB instead of 109
MFLOP and 301 MB; float64 median 3.06 ms (min 2.68) against 4.78 ms (3.78) in the same
session, float32 2.54 ms against 3.58 ms. This machine's product reached 237-243 GFLOP/s
(float64), so the flop bound of the new count is 0.22 ms: the call runs at 13x it, and
the 2x target is not met. The issue's 50x over the authors' 166-203 ms asks for 3.3-4.1
ms on their machine; by ratio to this session's old kernel (4.78 ms against their
7.6-8.3 ms for it), 3.06 ms here is 4.9-5.3 ms there: 31-41x.

Run: python benchmarks/bench_energy.py [--repeats 50] [--m 50 --n 99 --n-times 13]
"""

from __future__ import annotations

import argparse
import json
import time

import jax

jax.config.update("jax_enable_x64", True)  # a script, not the library: float64 must be available

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import elastic_jax as ej  # noqa: E402
from elastic_jax import shapes  # noqa: E402

from _common import emit, environment, shape, time_calls  # noqa: E402


def end_surfaces(m: int, n: int) -> tuple[np.ndarray, np.ndarray, str]:
    if (m, n) == (50, 99):
        cat1, cat2 = shape("cat1"), shape("cat2")
        if cat1 is not None and cat2 is not None:
            return cat1, cat2, "cat1 -> cat2"
    f1 = np.asarray(shapes.sample(shapes.bumpy, m, n))
    f2 = np.asarray(shapes.sample(shapes.bent_cylinder, m, n))
    return f1, f2, "bumpy -> bent_cylinder (synthetic)"


def machine_peaks(dtype, repeats: int = 10) -> dict:
    """Attainable flop rate (a matrix product) and memory bandwidth (an elementwise add)."""
    n = 1024
    a = jnp.ones((n, n), dtype)
    matmul = jax.jit(lambda x: x @ x).lower(a).compile()
    flops = time_calls(lambda: matmul(a), repeats)["min_s"]
    size = 32 * 2**20 // jnp.dtype(dtype).itemsize
    x = jnp.ones(size, dtype)
    add = jax.jit(lambda x: x + 1).lower(x).compile()
    stream = time_calls(lambda: add(x), repeats)["min_s"]
    return {
        "peak_flops_per_s": 2.0 * n**3 / flops,
        "peak_bytes_per_s": 2.0 * size * jnp.dtype(dtype).itemsize / stream,
    }


def roofline_of(compiled, dtype) -> dict:
    """XLA's flop and byte counts of a compiled function and the time they bound it to."""
    cost = compiled.cost_analysis()
    cost = cost[0] if isinstance(cost, list | tuple) else cost
    flops, moved = float(cost.get("flops", 0.0)), float(cost.get("bytes accessed", 0.0))
    peaks = machine_peaks(dtype)
    flop_bound = flops / peaks["peak_flops_per_s"]
    byte_bound = moved / peaks["peak_bytes_per_s"]
    return {
        "xla_flops": flops,
        "xla_bytes_accessed": moved,
        **peaks,
        "flop_bound_s": flop_bound,
        "byte_bound_s": byte_bound,
        "roofline_s": max(flop_bound, byte_bound),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--m", type=int, default=50)
    parser.add_argument("--n", type=int, default=99)
    parser.add_argument("--n-times", type=int, default=13)
    parser.add_argument("--repeats", type=int, default=50)
    parser.add_argument(
        "--xla-options",
        default='{"xla_cpu_use_fusion_emitters": false}',
        help="XLA compiler options as JSON (default: the solvers' on CPU; '{}' for XLA's own)",
    )
    args = parser.parse_args()
    args.options = json.loads(args.xla_options) or None if jax.default_backend() == "cpu" else None

    f1, f2, pair = end_surfaces(args.m, args.n)
    metric = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)
    env = environment()
    reference_grad = None
    for dtype in (jnp.float64, jnp.float32):
        path = ej.straight_path(jnp.asarray(f1, dtype), jnp.asarray(f2, dtype), args.n_times)
        start, end, interior = path[:1], path[-1:], path[1:-1]

        # The ends are arguments, as in a solve (closed over, XLA folds them in as
        # constants and fuses differently: 4.6 against 2.9 ms).
        def energy(x, start, end):
            return ej.path_energy(metric, jnp.concatenate([start, x, end]))

        t0 = time.perf_counter()
        compiled = (
            jax.jit(jax.value_and_grad(energy), compiler_options=args.options)
            .lower(interior, start, end)
            .compile()
        )
        compile_s = time.perf_counter() - t0
        value, grad = jax.block_until_ready(compiled(interior, start, end))
        if reference_grad is None:
            reference_grad = np.asarray(grad)
        grad_error = np.linalg.norm(np.asarray(grad, np.float64) - reference_grad) / np.linalg.norm(
            reference_grad
        )
        timing = time_calls(
            lambda compiled=compiled, ends=(interior, start, end): compiled(*ends), args.repeats
        )
        roofline = roofline_of(compiled, dtype)
        emit(
            {
                "benchmark": "path_energy_value_and_grad",
                "settings": {
                    "m": args.m,
                    "n": args.n,
                    "n_times": args.n_times,
                    "metric": [1.0, 1.0, 0.1, 0.0],
                    "dtype": jnp.dtype(dtype).name,
                    "pair": pair,
                    "variables": int(interior.size),
                    "compiler_options": args.options,
                },
                "compile_s": compile_s,
                **timing,
                "energy": float(value),
                "grad_norm": float(jnp.linalg.norm(grad)),
                "grad_rel_l2_error_vs_float64": float(grad_error),
                "target_median_s": 0.010 if dtype == jnp.float64 else None,
                **roofline,
                "median_over_roofline": timing["median_s"] / roofline["roofline_s"],
                "median_over_flop_bound": timing["median_s"] / roofline["flop_bound_s"],
                "environment": env,
            }
        )


if __name__ == "__main__":
    main()
