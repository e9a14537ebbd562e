"""Scale-out and first calls: distance matrices on Dask clusters, time to first result, memory.

Six measurements, one JSON record each (settings, figures, environment):

1. ``matrix``: pairs per second of a distance matrix of K shapes at 25 x 49 (metric
   (1, 1, 0.1, 0), modulo "rigid", ShapeOptions(degree=5, vf_degree=5, n_times=7),
   strategy "map", chunks of 4 pairs): in this process, and on LocalClusters of 1 and 2
   worker processes (one thread each). Each configuration runs in a fresh process with
   its own empty compilation cache, so every one pays its compilations; the record gives
   the wall time, pairs per second, and the largest difference from the in-process
   matrix. Shapes: the authors' cats, horse and hand at unit area when they can be had
   (elastic_jax.datasets: $ELASTIC_JAX_DATA or a download), then rotated ellipsoids and
   bumpy surfaces.
2. ``first_call``: a fresh Python process solving one shape geodesic (the cats, modulo
   "diff"), cold (empty persistent compilation cache) and warm (the cache filled by the
   cold run): the paper's low row (12 x 25, degree 5 / 5, N = 5) and middle row
   (25 x 49, 7 / 8, N = 10). Time from the start of the process (imports included) to
   the result, the solve call alone, and the process's peak RSS; with the exported
   solve kept in the cache (``exported=True``, the default) and without it.
3. ``memory``: peak RSS of a fresh process for one 50 x 99 geodesic (degree 7, N = 13)
   and one 25 x 49 shape geodesic at the defaults.
4. ``compile``: where a cold first call goes, for both rows: tracing, lowering and XLA's
   compilation of the shape solve, its first run, and the compiled program's size
   (StableHLO characters, HLO instructions, fusions). XLA:CPU generates code fusion by
   fusion, and loading a cached executable links them again: both the cold and the warm
   first call grow with the program, so its size is the figure to bring down.
5. ``programs``: how many XLA programs a resolved solve compiles (levels 13 x 25 and
   25 x 49 by default, ``--programs-levels 4`` all of the package's, synthetic shapes,
   no persistent cache): one pair by shape_geodesic, and distance matrices of 3 and 5
   shapes one pair after another ("loop") and of 3 side by side ("vmap")
   (``--programs-solves`` picks them).
6. ``resolved``: a resolved distance matrix of real shapes at the package's defaults
   (levels to 97 x 193, rtol 3 %; metric (1, 1, 0.1, 0), modulo "rigid", float64): the
   shared animals cat1, cat2, horse0 and hand4 at their own 50 x 99 grid, then deformed
   copies (bench_karcher's ``--deformations``, seed 0) up to ``--resolved-shapes``
   (default 5: 10 pairs), in a fresh process with an empty compilation cache, so the
   wall time includes every first call. The record has each pair's distance, levels
   estimate, finest grid and status, the XLA programs compiled, and the time at each
   finished chunk (``--resolved-strategy loop``: one pair a chunk); with
   ``--resolved-checkpoint PATH`` a run stopped part way resumes from the finished pairs.

Measured (2026-11-23, 2 CPU cores, quiet, float64; each configuration's compilations
included):
    matrix, 8 shapes (28 pairs, 27 converged): in process 221 s (0.127 pairs/s, RSS
        2.34 GB); LocalCluster 1 worker 237 s (0.118); 2 workers 215 s (0.131); every
        matrix equal to the in-process one (largest difference 0.0). On 2 cores one process
        already keeps both busy (XLA threads) and each worker compiles the solve itself:
        the cluster pays on more cores and machines, not here.
    first_call, low row: cold 49.5 s to the result (the solve call 47.8 s, RSS 2.17 GB),
        warm 12.0 s (10.8 s, 1.14 GB); middle row: cold 58.4 s, warm 23.5 s. The
        targets (cold <= 6.9 s, warm <= 2 s at the low row) are not met.
    memory: geodesic 50 x 99, degree 7, N 13: 982 MB; shape_geodesic 25 x 49 at the
        defaults: 2010 MB.
Again after the exported shape solve landed (same day, quiet; exported / plain jit):
    first_call, low row: cold 46.2 / 48.1 s (RSS 2.24 / 2.22 GB), warm 7.2 / 12.8 s
        (1.10 / 1.14 GB); middle row: cold 59.4 / 56.8 s, warm 24.5 / 24.3 s in this run,
        17.2 and 20.0 s in two reruns with the exported solve (its solve alone runs 12-13
        s); identical distances.
    memory: geodesic 50 x 99: 938 MB; shape_geodesic 25 x 49 at the defaults 1960 MB with
        no cache, 2157 MB filling it, 1112 MB loading it (the compiler's share is about
        half; the target, half of 1.38 GB, is not met).
Again after the compiled program shrank (same day; minimize reuses the solver's own value
and gradient, no start check, the Diff step's shrinks in a loop; exported / plain jit):
    compile, low row: trace 2.4 s (3.1 before), lower 0.5 (0.8), XLA 17.3 s (25.8);
        2312 fusions (3154), 56.9k HLO instructions (86.7k), 1.98 M StableHLO characters
        (2.91 M). Middle row: XLA 15.6 s (23.3), 2415 fusions (3322).
    first_call, low row: cold 24.6 / 23.4 s (RSS 1.71 / 1.66 GB), warm 4.1 / 7.0 s
        (0.83 / 0.86 GB), distance 0.56172 both; middle row: cold 30.5 / 30.0 s, warm
        11.1 / 13.9 s (the solve itself about 10 s), distance 0.8572 (0.8773 before: the
        changed rounding moved this pair's registration to another start; both runs
        converged).
    memory: geodesic 50 x 99: 900 MB; shape_geodesic 25 x 49 at the defaults 1677 MB with
        no cache, 1879 MB filling it, 931 MB loading it. Still missed: cold <= 6.9 s and
        warm <= 2 s at the low row, and half of 1.38 GB.
Again after the solve's call sites were merged (same day; the start search's short solves
and its refinements over rotations are one scan over one solve, and so are the
straight-line rounds of every start and of the best one: their step limits are traced,
minimize's step_cap, with the same iterates; the conversions into and out of the solve's
units are one program each; exported / plain jit):
    compile, low row: trace 2.1 s, lower 0.5, XLA 15.7 s (17.3); 1886 fusions (2312),
        45.4k HLO instructions (56.9k), 1.71 M StableHLO characters (1.98 M); the same
        distance to 1e-15 (0.28085879534 in the solve's units). Middle row: XLA 14.6 s
        (15.6), 1972 fusions (2415), the same distance.
    first_call, low row: cold 19.7 / 19.4 s (RSS 1.65 / 1.62 GB), warm 3.3 / 5.4 s
        (0.70 / 0.73 GB), distance 0.56172; middle row: cold 26.5 / 26.4 s, warm 11.1 /
        13.1 s, distance 0.8572 as before.
    memory: geodesic 50 x 99: 794 MB; shape_geodesic 25 x 49 at the defaults 1569 MB with
        no cache, 1799 MB filling it, 809 MB loading it. Still missed: cold <= 6.9 s, warm
        <= 2 s, and 690 MB.
    Also tried: the Moebius refinement (six parameters) in the same scan, its rotations
        as six parameters with three held (1700 fusions). The starts it produced differ
        from these by 1e-14 (rounding), and that moved cat1 -> horse0 at 25 x 49 (degree
        5 / 8, N 7) from a coarse registration at energy 0.771 to one at 2.399; the rounds
        then needed more than 10 rounds. Not landed: the start selection amplifies
        rounding (see docs/guides/settings.md, "What the distance means").
Again after the shape solves compile with XLA:CPU's classic fusion emitters (2026-11-24,
quiet; the solve's code is also newer: the pole derivative fix and the resolution rule,
so cats at the middle row take 10 rounds, 0.7718, where they took 2-3; exported / plain
jit):
    compile, low row: trace 1.9 s, lower 0.5, XLA 12.6 s (15.7); 1692 fusions (1936 with
        the fusion emitters, same code); run 0.93 s; RSS 647 MB. Middle row: XLA 12.2 s,
        1728 fusions, RSS 724 MB.
    first_call, low row: cold 17.6 / 17.9 s (RSS 822 / 802 MB), warm 2.9 / 5.4 s (699 /
        736 MB), distance 0.56171 both; middle row: cold 29.6 / 29.2 s, warm 14.7 / 17.6 s
        (the solve itself 13.5 s), 0.77178.
    memory: geodesic 50 x 99: 843 MB (not compiled with the option); shape_geodesic 25 x
        49 at the defaults 789 MB with no cache (1569), 954 MB filling it (1799), 814 MB
        loading it (809). Half of 1.38 GB (690 MB) is still missed by 100 MB: the
        interpreter and JAX hold 176 MB after the imports, tracing and lowering the solve
        200 MB, and its BFGS's dense inverse Hessians (2272 variables at the defaults) most
        of its 143 MB of temporaries. Still missed: cold <= 6.9 s, warm <= 2 s.
Again after a single shape_geodesic compiles its solve as five programs, one per phase
(starts, coarse registration, rounds, the two geodesics, the result's diagnostics; the
last at LLVM level 0), and enable_compilation_cache stores every program
(min_compile_time_s=0) (2026-11-24, quiet; exported / plain jit):
    compile, low row: trace 2.1 s, lower 0.6, XLA 11.5 s (12.6 as one program): starts
        2.4 s (401 fusions), coarse 2.7 (370), rounds 2.7 (360), geodesics 2.9 (362),
        diagnostics 0.84 (286; 1.7 s at LLVM level 2); 1779 fusions in all; RSS 466 MB.
        Middle row: XLA 10.8 s, 1827 fusions, RSS 543 MB.
    first_call, low row: cold 16.5-16.8 / 15.9 s (RSS 521 / 505 MB), warm 2.10-2.27 s
        over 14 processes / 4.5-4.9 s (479 / 512 MB), distance 0.56171 both; with JAX's
        default min_compile_time (1 s) the warm call took 3.2 s (the last phase and the
        small programs around the solve compiled again). Middle row: cold 27.4-27.9 /
        26.6-27.0 s, warm 14.0-14.5 / 15.9-16.6 s, 0.77178.
    memory: geodesic 50 x 99: 858-860 MB; shape_geodesic 25 x 49 at the defaults 600-613
        MB with no cache (789 as one program), 649-651 MB filling the cache, 603-662 MB
        loading it: half of 1.38 GB (690 MB) is met. The distance is the one-program
        solve's to the last bit (0.77169 at the defaults, 10 rounds).
    Also tried: the phases compiled two at a time in threads (the solve call 12.6 s
        instead of 14.6 at the low row; peak RSS 772 MB instead of 693 at the defaults,
        over the memory target); the warm phases' executables loaded two at a time ahead
        of the first phase (the solve call 1.47-1.76 s against 1.45-1.50: the loads then
        compete with the runs they overlapped before); LLVM level 0 for the search phases
        (compile halves, runs 4-7 times slower: the middle row's coarse phase 4.3 -> 22 s).
        Still missed: cold <= 6.9 s (16.5 s) and warm <= 2 s (2.1-2.3 s).
    matrix, 16 shapes (120 pairs, 111 converged; the authors' cats, horse and hand and 12
        synthetic shapes; batched jobs compile the solve as one program, so this part is
        not changed by the phases): in process 423 s (0.284 pairs/s, RSS 935 MB);
        LocalCluster 1 worker 455 s (0.264); 2 workers 292 s (0.411, 1.45 times the
        in-process rate); every matrix equal to the in-process one (largest difference
        0.0). The 32-shape run follows below.

With the solve's compiled executables stored beside the exported programs (CPU; a warm
process loads them without lowering the programs) (2026-11-24, quiet):
    first_call, low row: warm 1.87-1.95 s over 14 processes, median 1.91 (the solve call
        1.25 s; 2.10-2.27 s with the exported programs alone); one bench record 2.04 s
        (RSS 512 MB); cold 16.3-16.4 s (RSS 514 MB); plain jit 15.5 s cold, 4.7 s warm.
        Middle row: warm 13.7 s, cold 27.0 s (plain jit 26.2 / 15.8 s). Distances
        unchanged to the last bit (0.5617068208516363, 0.7717844018749495).
    memory: shape_geodesic 25 x 49 at the defaults 614 MB with no cache, 657 MB filling
        the cache (executables serialized too), 588 MB loading it; geodesic 50 x 99
        873 MB (code unchanged; 858-860 before).
    matrix, 32 shapes (496 pairs, 473 converged; the authors' cats, horse and hand and 28
        synthetic shapes): in process 1451 s (0.342 pairs/s, RSS 953 MB); LocalCluster
        1 worker 1549 s (0.320); 2 workers 969 s (0.512, 1.50 times the in-process
        rate); every matrix equal to the in-process one (largest difference 0.0).

Measured (2026-12-02, 2 CPU cores, degree 4 / 4, N 5):
    programs: one resolved pair 34; resolved matrices one pair after another 65 (3
        shapes) and 65 (5 shapes, 10 pairs); side by side 47 (3 shapes).
    programs at degree 7 / 8, N 13, all four levels (--programs-levels 4): one pair 58
        (80 s); a matrix of 3 shapes one pair after another 93 (158 s).

Measured (2026-12-06, 2 CPU cores, quiet, float64;
records/bench_scale_resolved5_cpu2_2026-12-06.jsonl):
    resolved, 5 shapes (10 pairs, one pair a chunk, a fresh process and cache): 4095 s
        in all, against the target of 20 minutes (3.4 times over). Per pair 103-1007 s:
        the 3 pairs that resolved at 49 x 97 took 103-159 s, the 7 that went on to
        97 x 193 took 259-1007 s, 3715 s (91 %) of the whole. 8 pairs converged;
        cat2 -> hand4 and horse0 -> hand4 ended `resolution_limited` at 97 x 193
        (estimates 0.15 % and 0.49 %). Distances 0.713-2.297, estimates 0.12-2.47 %;
        151 XLA programs; peak RSS 5.7 GB.

Run: python benchmarks/bench_scale.py [--shapes 32]
     [--parts matrix,compile,first_call,memory,programs,resolved] [--workers 1,2]
     [--resolved-shapes 5] [--resolved-strategy loop] [--resolved-checkpoint PATH]
     [--programs-options 4,4,5] [--programs-levels 2] [--programs-solves 2:loop,3:vmap]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

from _common import emit, environment

HERE = __file__.rsplit("/", 1)[0]

PRELUDE = r"""
import json, resource, sys, time, warnings
START = time.perf_counter()
import jax
jax.config.update("jax_enable_x64", True)
import numpy as np
sys.path.insert(0, {here!r})
from _common import shape as load_shape
import elastic_jax as ej
from elastic_jax import shapes
warnings.simplefilter("ignore", ej.ConvergenceWarning)
metric = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)

def rss_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

def cats(m, n):
    f1, f2 = load_shape("cat1"), load_shape("cat2")
    if f1 is None or f2 is None:
        raise FileNotFoundError("the authors' cats cannot be had (elastic_jax.datasets)")
    return tuple(np.asarray(ej.resample(f, m, n)) for f in (f1, f2))
"""

MATRIX = r"""
ej.enable_compilation_cache({cache!r})
k, workers = {shapes}, {workers}
m, n = 25, 49
coll = []
for name in ("cat1", "cat2", "horse0", "hand4"):
    f = load_shape(name) if len(coll) < k else None
    if f is not None:
        f = np.asarray(ej.center(ej.resample(f, m, n)))
        coll.append(f / np.sqrt(float(ej.surface_area(f))))
i = 0
while len(coll) < k:
    r = shapes.random_rotation(i)
    if i % 2:
        f = shapes.sample(shapes.ellipsoid, m, n, axes=(1.0, 0.8 + 0.02 * i, 0.6), rotation=r)
    else:
        f = shapes.sample(shapes.bumpy, m, n, scale=1.0 + 0.02 * i, rotation=r)
    coll.append(np.asarray(f))
    i += 1
coll = np.stack(coll)
options = ej.ShapeOptions(degree=5, vf_degree=5, n_times=7)
kwargs = dict(modulo="rigid", options=options)
client = None
if workers:
    from dask.distributed import Client, LocalCluster
    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                           dashboard_address="127.0.0.1:0")
    client = Client(cluster)
    ej.enable_compilation_cache({cache!r}, client=client)
t0 = time.perf_counter()
job = ej.JobOptions(strategy="map", batch_size=4, client=client)
res = ej.distance_matrix(coll, metric, job=job, **kwargs)
seconds = time.perf_counter() - t0
np.save({out!r}, np.asarray(res.distances))
print(json.dumps({{"seconds": seconds, "pairs": k * (k - 1) // 2,
                  "converged": int(np.asarray(res.pairs_converged).sum() - k) // 2,
                  "rss_mb": rss_mb()}}))
if client is not None:
    client.close(); cluster.close()
"""

FIRST = r"""
ej.enable_compilation_cache({cache!r}, exported={exported})
m, n = {grid}
f1, f2 = cats(m, n)
options = ej.ShapeOptions(degree={degree}, vf_degree={vf_degree}, n_times={n_times}, rtol=None)
t0 = time.perf_counter()
res = ej.shape_geodesic(f1, f2, metric, modulo="diff", options=options)
d = float(res.distance)
t1 = time.perf_counter()
print(json.dumps({{"to_result_s": t1 - START, "solve_s": t1 - t0, "distance": d,
                  "converged": bool(res.converged), "rss_mb": rss_mb()}}))
"""

MEMORY = r"""
if {cache!r}:
    ej.enable_compilation_cache({cache!r})
m, n = {grid}
f1, f2 = cats(m, n)
if {shape}:
    res = ej.shape_geodesic(f1, f2, metric, modulo="diff", rtol=None)
else:
    res = ej.geodesic(f1, f2, metric, degree=7, n_times=13)
d = float(res.distance)
print(json.dumps({{"distance": d, "rss_mb": rss_mb()}}))
"""

COMPILE = r"""
import re
from elastic_jax._geometry.numerics import default_tol
from elastic_jax._geometry.numerics import constant
from elastic_jax._geometry.units import in_units
from elastic_jax._registration import phases as _phases
from elastic_jax._geometry.bases import make_bases
m, n = {grid}
f1, f2 = cats(m, n)
cfg = ej.ShapeOptions(degree={degree}, vf_degree={vf_degree}, n_times={n_times})
cfg = cfg.replace(tol=default_tol(np.float64))
bases = make_bases(m, n, cfg, np.float64)
# The arguments shape_geodesic gives its solve (the surfaces in units of their size).
_, (g1, g2) = in_units(f1, f2)
args = (constant(metric), g1, g2, bases)
# The solve's phases, one program each as shape_geodesic compiles them: traced, lowered,
# compiled and run one after the other (each takes the one before's result).
record = {{"trace_s": 0.0, "lower_s": 0.0, "compile_s": 0.0, "run_s": 0.0,
          "stablehlo_chars": 0, "hlo_instructions": 0, "fusions": 0, "phases": {{}}}}
carried = ()
for name, _, _ in _phases.PHASES:
    jitted = _phases.PHASE_JITS[name].jitted()
    t0 = time.perf_counter()
    traced = jitted.trace(*args, *carried, options=cfg, rigid=False)
    t1 = time.perf_counter()
    lowered = traced.lower()
    t2 = time.perf_counter()
    compiled = lowered.compile()
    t3 = time.perf_counter()
    carried = (jax.block_until_ready(compiled(*args, *carried)),)
    t4 = time.perf_counter()
    hlo = compiled.as_text()
    phase = {{"trace_s": t1 - t0, "lower_s": t2 - t1, "compile_s": t3 - t2, "run_s": t4 - t3,
             "stablehlo_chars": len(lowered.as_text()),
             "hlo_instructions": len(re.findall(r" = ", hlo)),
             "fusions": len(re.findall(r"\bfusion\(", hlo))}}
    record["phases"][name] = phase
    for key, value in phase.items():
        record[key] += value
record["distance"] = float(carried[0].distance)
record["rss_mb"] = rss_mb()
print(json.dumps(record))
"""

PROGRAMS = r"""
from elastic_jax._runtime.cache import CompileCounter
m, n = 13, 25
coll = [shapes.sample(shapes.bumpy, m, n), shapes.sample(shapes.ellipsoid, m, n)]
coll += [shapes.sample(shapes.bumpy, m, n, scale=1.1 + 0.05 * i,
                       rotation=shapes.random_rotation(i)) for i in range({shapes} - 2)]
coll = np.stack(coll)
options = ej.ShapeOptions(degree={degree}, vf_degree={vf_degree}, n_times={n_times},
                          levels={levels}, rtol={rtol})
job = ej.JobOptions(strategy={strategy!r})
t0 = time.perf_counter()
with CompileCounter() as programs:
    if {shapes} == 2:
        res = ej.shape_geodesic(coll[0], coll[1], metric, modulo="rigid", options=options)
        grids = [np.asarray(res.levels.grids).tolist()[-1]]
    else:
        res = ej.distance_matrix(coll, metric, modulo="rigid", options=options, job=job)
        grids = np.asarray(res.grids)[np.triu_indices({shapes}, 1)].tolist()
print(json.dumps({{"programs_compiled": programs.count, "seconds": time.perf_counter() - t0,
                  "finest_grids": grids}}))
"""

RESOLVED = r"""
from _common import deformed
from elastic_jax._runtime.cache import CompileCounter
ej.enable_compilation_cache({cache!r})
coll = [load_shape(name) for name in ("cat1", "cat2", "horse0", "hand4")]
if any(f is None for f in coll):
    raise FileNotFoundError("the authors' shapes cannot be had (elastic_jax.datasets)")
coll = [np.asarray(f) for f in coll]
# bench_karcher --resolved --deformations's fifth shape onward: seed 0, spline reads.
rng = np.random.default_rng(0)
coll += [deformed(coll[i % 4], rng, method="spline") for i in range({shapes} - 4)]
coll = np.stack(coll[:{shapes}])
chunks = []
def progress(info):
    chunks.append({{"pairs_done": info["pairs_done"], "seconds": info["seconds"]}})
    print(json.dumps({{"progress": chunks[-1]}}), file=sys.stderr, flush=True)
job = ej.JobOptions(strategy={strategy!r}, progress=progress, checkpoint={checkpoint!r},
                    resume={resume})
t0 = time.perf_counter()
with CompileCounter() as programs:
    res = ej.distance_matrix(coll, metric, modulo="rigid", job=job)
seconds = time.perf_counter() - t0
upper = np.triu_indices(len(coll), 1)
print(json.dumps({{"seconds": seconds, "programs_compiled": programs.count,
                  "pairs": len(upper[0]),
                  "pair_indices": np.stack(upper, 1).tolist(),
                  "distances": np.asarray(res.distances)[upper].tolist(),
                  "estimates": np.asarray(res.estimate)[upper].tolist(),
                  "finest_grids": np.asarray(res.grids)[upper].tolist(),
                  "pairs_converged": np.asarray(res.pairs_converged)[upper].tolist(),
                  "converged": bool(res.converged), "result": ej.RESULTS.name(res.result),
                  "chunks": chunks, "rss_mb": rss_mb()}}))
"""

ROWS = {
    "low": {"grid": (12, 25), "degree": 5, "vf_degree": 5, "n_times": 5},
    "middle": {"grid": (25, 49), "degree": 7, "vf_degree": 8, "n_times": 10},
}


def run(script: str) -> dict:
    start = time.perf_counter()
    out = subprocess.run(
        [sys.executable, "-c", PRELUDE.format(here=HERE) + script],
        capture_output=True,
        text=True,
        timeout=7200,
    )
    if out.returncode != 0:
        return {"error": out.stderr[-2000:], "process_s": time.perf_counter() - start}
    record = json.loads(out.stdout.strip().splitlines()[-1])
    record["process_s"] = time.perf_counter() - start
    return record


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shapes", type=int, default=32)
    parser.add_argument("--workers", default="1,2", help="LocalCluster sizes")
    parser.add_argument("--parts", default="matrix,compile,first_call,memory")
    parser.add_argument(
        "--resolved-shapes", type=int, default=5, help="shapes of the resolved part (>= 4)"
    )
    parser.add_argument("--resolved-strategy", default="loop", choices=("loop", "map", "vmap"))
    parser.add_argument(
        "--resolved-checkpoint",
        default=None,
        help="the resolved part's checkpoint (.npz): a run stopped part way resumes there",
    )
    parser.add_argument(
        "--programs-options",
        default="4,4,5",
        help="degree,vf_degree,n_times of the programs part (the package's: 7,8,13)",
    )
    parser.add_argument(
        "--programs-levels",
        type=int,
        default=2,
        help="how many of the package's levels the programs part runs (2: 13 x 25, 25 x 49;"
        " 4: up to 97 x 193); with more than 2 every pair runs them all (rtol 1e-9)",
    )
    parser.add_argument(
        "--programs-solves",
        default="2:loop,3:loop,5:loop,3:vmap",
        help="shapes:strategy of each programs solve (2 shapes: one shape_geodesic)",
    )
    args = parser.parse_args()
    parts = args.parts.split(",")
    known = {"matrix", "compile", "first_call", "memory", "programs", "resolved"}
    unknown = sorted(set(parts) - known)
    if unknown:
        parser.error(f"--parts: unknown part(s) {', '.join(unknown)}")
    env = environment()
    import numpy as np

    if "matrix" in parts:
        reference = None
        for workers in [0, *(int(w) for w in args.workers.split(",") if w)]:
            with tempfile.TemporaryDirectory() as tmp:
                out = f"{tmp}/d.npy"
                record = run(
                    MATRIX.format(
                        cache=f"{tmp}/cache", shapes=args.shapes, workers=workers, out=out
                    )
                )
                matrix = np.load(out) if "error" not in record else None
            if matrix is not None:
                if reference is None:
                    reference = matrix
                record["max_abs_diff_vs_in_process"] = float(np.abs(matrix - reference).max())
                record["pairs_per_s"] = record["pairs"] / record["seconds"]
            emit(
                {
                    "benchmark": "matrix",
                    "where": "in process" if workers == 0 else f"LocalCluster({workers} workers)",
                    "settings": {
                        "shapes": args.shapes,
                        "grid": [25, 49],
                        "modulo": "rigid",
                        "options": {"degree": 5, "vf_degree": 5, "n_times": 7},
                        "strategy": "map",
                        "batch_size": 4,
                    },
                    **record,
                    "environment": env,
                }
            )
    if "first_call" in parts:
        for row, settings in ROWS.items():
            for exported in (True, False):
                with tempfile.TemporaryDirectory() as tmp:
                    script = FIRST.format(cache=f"{tmp}/cache", exported=exported, **settings)
                    cold, warm = run(script), run(script)
                emit(
                    {
                        "benchmark": "first_call",
                        "row": row,
                        "settings": {
                            **settings,
                            "modulo": "diff",
                            "pair": "cat1 -> cat2",
                            "exported": exported,
                        },
                        "cold": cold,
                        "warm": warm,
                        "environment": env,
                    }
                )
    if "compile" in parts:
        # Where a cold first call goes: tracing, lowering and XLA's compilation of the
        # shape solve, and the size of the compiled program (its fusions are the kernels
        # XLA:CPU generates code for one by one; loading a cached executable links them).
        for row, settings in ROWS.items():
            record = run(COMPILE.format(**settings))
            emit(
                {
                    "benchmark": "compile",
                    "row": row,
                    "settings": {**settings, "modulo": "diff", "pair": "cat1 -> cat2"},
                    **record,
                    "environment": env,
                }
            )
    if "programs" in parts:
        # How many XLA programs a resolved solve compiles (no persistent cache: every
        # program counts): one pair, and matrices whose pairs share each level's
        # programs (one after another) or run side by side (vmap, one batch per level).
        try:
            degree, vf_degree, n_times = (int(x) for x in args.programs_options.split(","))
        except ValueError:
            parser.error(
                f"--programs-options: three integers degree,vf_degree,n_times; "
                f"got {args.programs_options!r}"
            )
        # The parts run in subprocesses; this process imports the package only here.
        from elastic_jax import ShapeOptions

        all_levels = ShapeOptions().levels
        if not 1 <= args.programs_levels <= len(all_levels):
            parser.error(f"--programs-levels: 1 to {len(all_levels)}; got {args.programs_levels}")
        levels = all_levels[: args.programs_levels]
        rtol = 0.03 if args.programs_levels <= 2 else 1e-9
        try:
            solves = [
                (int(k), strategy)
                for k, strategy in (item.split(":") for item in args.programs_solves.split(","))
            ]
        except ValueError:
            parser.error(f"--programs-solves: shapes:strategy items; got {args.programs_solves!r}")
        if any(k < 2 or strategy not in ("loop", "map", "vmap") for k, strategy in solves):
            parser.error(f"--programs-solves: shapes >= 2 and loop/map/vmap; got {solves}")
        for shapes, strategy in solves:
            settings = {
                "shapes": shapes,
                "strategy": strategy,
                "degree": degree,
                "vf_degree": vf_degree,
                "n_times": n_times,
                "levels": levels,
                "rtol": rtol,
            }
            record = run(PROGRAMS.format(**settings))
            emit(
                {
                    "benchmark": "programs",
                    "solve": "shape_geodesic" if shapes == 2 else "distance_matrix",
                    "settings": {**settings, "modulo": "rigid"},
                    **record,
                    "environment": env,
                }
            )
    if "resolved" in parts:
        # The collection target: a resolved matrix of real shapes at the package's
        # defaults (levels to 97 x 193, rtol 3 %), modulo rigid, in a fresh process with an
        # empty compilation cache (its first calls included).
        if args.resolved_shapes < 4:
            parser.error("--resolved-shapes: at least the four shared animals (4)")
        checkpoint = args.resolved_checkpoint
        with tempfile.TemporaryDirectory() as tmp:
            settings = {
                "shapes": args.resolved_shapes,
                "strategy": args.resolved_strategy,
                "checkpoint": checkpoint,
                "resume": bool(checkpoint) and os.path.exists(checkpoint),
            }
            record = run(RESOLVED.format(cache=f"{tmp}/cache", **settings))
        emit(
            {
                "benchmark": "resolved_matrix",
                "settings": {
                    **settings,
                    "shapes_used": "cat1, cat2, horse0, hand4, then deformed copies "
                    "(bench_karcher --resolved --deformations, seed 0)",
                    "metric": [1.0, 1.0, 0.1, 0.0],
                    "modulo": "rigid",
                    "options": "ShapeOptions() (the defaults)",
                    "dtype": "float64",
                },
                **record,
                "environment": env,
            }
        )
    if "memory" in parts:
        for label, grid, shape in (
            ("geodesic 50 x 99, degree 7, N 13", (50, 99), False),
            ("shape_geodesic 25 x 49, defaults", (25, 49), True),
        ):
            record = run(MEMORY.format(grid=grid, shape=shape, cache=""))
            emit({"benchmark": "memory", "solve": label, **record, "environment": env})
        # The same shape solve in a process that finds it compiled (and exported) in the
        # cache: the solve's own memory, without the compiler's.
        with tempfile.TemporaryDirectory() as tmp:
            script = MEMORY.format(grid=(25, 49), shape=True, cache=f"{tmp}/cache")
            cold, warm = run(script), run(script)
        emit(
            {
                "benchmark": "memory",
                "solve": "shape_geodesic 25 x 49, defaults, compilation cache",
                "cold": cold,
                "warm": warm,
                "environment": env,
            }
        )


if __name__ == "__main__":
    main()
