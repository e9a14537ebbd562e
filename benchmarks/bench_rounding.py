"""How far a shape distance moves when nothing changes but the floating-point rounding.

The registration is a nonconvex search (starts, rounds of truncated quasi-Newton solves,
accept-or-refuse decisions), so two runs of the same mathematics whose arithmetic
rounds differently can end in different local minima. That happens in practice when
the same pair is solved by another XLA version, on a CPU with other vector
instructions (a Dask cluster of unlike machines), or batched with other pairs under
jax.vmap. This script measures the spread directly: one pair, one ShapeOptions, the same
traced program compiled several ways that change only code generation (XLA:CPU's fusion
emitters off, as the library compiles it, or on, as XLA would; LLVM optimization level
1 or 2), plus the pair solved inside a jax.vmap batch next to another pair. Every
variant is a correct computation; their spread is the reproducibility of the reported
distance, at that grid, under rounding.

One JSON record per variant (distance, converged, resolution-limited, rounds, the joint
gradient norm, the energy history, the refinement's relative change), then one summary
per pair: the relative spread (max - min) / min of the distance over the variants and
over those that converged, and whether every variant converged.

Pairs: cat1 -> cat2 and cat1 -> horse0 (the authors' surfaces from elastic_jax.datasets:
$ELASTIC_JAX_DATA or a download; skipped when they cannot be had) and a synthetic pair (a
bumpy surface against a stretched copy under a rotation of the parameter sphere), metric
(1, 1, 0.1, 0), modulo "diff". Rows: the paper's low (12 x 25, degree 5 / 5, N 5) and
middle (25 x 49, 7 / 8, N 10).

Measured (2026-11-24, 2 CPU cores, float64, jax 0.10.2; distances in the user's units;
the library compiles without the fusion emitters, and reports RESULTS.resolution_limited):
    low row: every pair agrees within itself (relative spread 1e-10 for the cats at
        0.56171, 5e-14 for cat1 -> horse0 at 1.11153, 2e-16 for the synthetic pair at
        0.53818). cat1 -> horse0 is resolution-limited every way (converged False: its
        gamma keeps 0.17 % more area than the grid's floor); the others converge.
    middle row: the synthetic pair agrees to 2e-16 (0.55514). The cats converge three
        ways: 0.77178 (library: 10 rounds, grad norm 0.023), 0.77178 (fusion emitters,
        LLVM level 1) and 0.77277 (LLVM level 1: 7 rounds), a spread of 0.13 %; XLA's
        default and the vmap batch stop resolution-limited at 0.79298 (7 rounds).
        cat1 -> horse0 converges every way, 0.8489-0.8702 (library 0.8544, 4 rounds):
        a spread of 2.5 %.
    Before the resolution rule (2026-11-23, the solve's program one field smaller, so
        rounded differently): the cats' 0.79298 runs were reported converged, and
        cat1 -> horse0 without fusion emitters at LLVM level 1 gave 1.4937, "converged"
        after 2 rounds with a joint grad norm of 0.945 (the others 0.014-0.034). Its last
        round was refused: the step the energy asked for (energy 0.60 -> 0.26) folded gamma
        (min J -0.14), and so did every shrink down to 1/16 (min J -0.02 to -0.20). The
        rule now reports such runs. Before the pole derivative of f o gamma was fixed
        (outer_steps 10): low row, synthetic: spread 2.5e-6. middle row, cats:
        0.8395-0.8588 (grad norms 0.04-0.27); cat1 -> horse0: 0.8526-0.8642 and 1.0400.
    So the search is reproducible for the smooth synthetic pair, and for the real pairs
    up to the choice between nearby minima; the runs that stop at the edge of what the
    grid resolves say so. docs/guides/settings.md ("What the distance means") says how to read them.

Run: python benchmarks/bench_rounding.py [--rows low,middle] [--pairs cats,horse,synthetic]
"""

from __future__ import annotations

import argparse
import warnings

import jax

jax.config.update("jax_enable_x64", True)  # a script, not the library

import bench_shape  # noqa: E402  (its synthetic pair)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import elastic_jax as ej  # noqa: E402
from elastic_jax import shapes  # noqa: E402
from elastic_jax._geometry.bases import make_bases  # noqa: E402
from elastic_jax._geometry.numerics import constant, default_tol  # noqa: E402
from elastic_jax._geometry.units import in_units  # noqa: E402
from elastic_jax._registration import phases as _phases  # noqa: E402

from _common import emit, environment, shape  # noqa: E402

METRIC = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)
ROWS = {
    "low": {"grid": (12, 25), "degree": 5, "vf_degree": 5, "n_times": 5},
    "middle": {"grid": (25, 49), "degree": 7, "vf_degree": 8, "n_times": 10},
}
# XLA:CPU code-generation options: the same program, rounded differently. The first is
# what the library compiles its solves with on CPU (_cache._CPU_COMPILER_OPTIONS); the
# second is XLA's own default. Names of the jaxlib this was written against; a jaxlib
# that lacks one skips that variant. Each compiles the whole solve as one program; a
# single shape_geodesic compiles it as five (one per phase), with the same arithmetic
# (measured: the same distance to the last bit) but for the last phase's diagnostics.
COMPILATIONS = {
    "library (no fusion emitters)": {"xla_cpu_use_fusion_emitters": False},
    "fusion emitters (XLA's default)": {"xla_cpu_use_fusion_emitters": True},
    "LLVM level 1": {"xla_cpu_use_fusion_emitters": False, "xla_backend_optimization_level": 1},
    "fusion emitters, LLVM level 1": {
        "xla_cpu_use_fusion_emitters": True,
        "xla_backend_optimization_level": 1,
    },
}


def surfaces(name: str, m: int, n: int):
    """(f1, f2, a third surface to batch f2 with), or None when the data is absent."""
    if name == "synthetic":
        other = shapes.sample(shapes.ellipsoid, m, n, axes=(1.0, 0.8, 0.6))
        return (*(np.asarray(f) for f in bench_shape.pair("synthetic", m, n)), np.asarray(other))
    files = {"cats": ("cat1", "cat2", "horse0"), "horse": ("cat1", "horse0", "cat2")}[name]
    loaded = [shape(f) for f in files]
    if any(f is None for f in loaded):
        return None
    return tuple(np.asarray(ej.resample(f, m, n)) for f in loaded)


def summary(result, scale: float) -> dict:
    history = np.asarray(result.energy_history) * scale**2
    return {
        "distance": float(result.distance) * scale,
        "converged": bool(result.converged),
        "resolution_limited": bool(result.result == ej.RESULTS.resolution_limited),
        "rounds": int(result.rounds),
        "grad_norm": float(result.grad_norm),
        "energy_history": history[np.isfinite(history)].tolist(),
        "refinement_change": float(result.refinement.relative_change),
    }


def spread(distances: list) -> dict:
    """Count, least, largest and relative spread (max - min) / min of some distances."""
    if not distances:
        return {"count": 0}
    low, high = min(distances), max(distances)
    return {
        "count": len(distances),
        "distance_min": low,
        "distance_max": high,
        "relative_spread": (high - low) / low,
    }


def variants(f1, f2, other, cfg) -> dict:
    """Each variant's summary ({"error": ...} for a compilation option this jaxlib lacks)."""
    units, (g1, g2) = in_units(f1, f2)
    scale = float(units.scale)
    m, n = f1.shape[-2:]
    bases = make_bases(m, n, cfg, np.float64)
    args = (constant(METRIC), g1, g2, bases)
    out = {}
    for label, options in COMPILATIONS.items():
        solve = jax.jit(
            _phases.shape_solve, static_argnames=("options", "rigid"), compiler_options=options
        )
        try:
            result = jax.block_until_ready(solve(*args, options=cfg, rigid=False))
        except Exception as error:  # an option this jaxlib does not know
            out[label] = {"error": str(error).splitlines()[0]}
            continue
        out[label] = summary(result, scale)
    # The public call batched with another pair: the program differs (vmap), the
    # mathematics of this pair does not.
    batch = jax.vmap(lambda f: ej.shape_geodesic(f1, f, METRIC, options=cfg))(
        jnp.stack([jnp.asarray(f2), jnp.asarray(other)])
    )
    first = jax.tree_util.tree_map(lambda x: x[0], batch)
    out["vmap next to another pair"] = summary(first, 1.0)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", default="low,middle")
    parser.add_argument("--pairs", default="cats,horse,synthetic")
    args = parser.parse_args()
    rows, pairs = args.rows.split(","), args.pairs.split(",")
    for flag, given, known in (
        ("--rows", rows, ROWS),
        ("--pairs", pairs, ("cats", "horse", "synthetic")),
    ):
        unknown = sorted(set(given) - set(known))
        if unknown:
            parser.error(f"{flag}: unknown {', '.join(unknown)}")
    warnings.simplefilter("ignore", ej.ConvergenceWarning)
    env = environment()
    for row in rows:
        settings = ROWS[row]
        m, n = settings["grid"]
        cfg = ej.ShapeOptions(
            degree=settings["degree"],
            vf_degree=settings["vf_degree"],
            n_times=settings["n_times"],
            rtol=None,
        )
        cfg = cfg.replace(tol=default_tol(np.float64))
        for name in pairs:
            data = surfaces(name, m, n)
            if data is None:
                continue
            found = variants(*data, cfg)
            base = {"row": row, "pair": name, "settings": {**settings, "modulo": "diff"}}
            for label, record in found.items():
                emit({"benchmark": "rounding_variant", **base, "variant": label, **record})
            solved = [r for r in found.values() if "distance" in r]
            emit(
                {
                    "benchmark": "rounding_spread",
                    **base,
                    "variants": len(solved),
                    **spread([r["distance"] for r in solved]),
                    "all_converged": all(r["converged"] for r in solved),
                    # The same over the runs that report converged.
                    "converged": spread([r["distance"] for r in solved if r["converged"]]),
                    "environment": env,
                }
            )


if __name__ == "__main__":
    main()
