"""How far a shape distance moves when nothing changes but the floating-point rounding.

The registration is a nonconvex search (starts, rounds of truncated quasi-Newton solves,
accept-or-refuse decisions), so two runs of the same mathematics whose arithmetic
rounds differently can end in different local minima. That happens in practice when
the same pair is solved by another XLA version, on a CPU with other vector
instructions (a Dask cluster of unlike machines), or batched with other pairs under
jax.vmap. This script measures the spread directly: one pair, one ShapeOptions, the same
traced program compiled several ways that change only code generation (XLA:CPU's
fusion emitters on or off, LLVM optimization level 1 or 2), plus the pair solved inside
a jax.vmap batch next to another pair. Every variant is a correct computation; their
spread is the reproducibility of the reported distance, at that grid, under rounding.

One JSON record per variant (distance, converged, rounds, the joint gradient norm, the
energy history, the refinement's relative change), then one summary per pair: the
relative spread (max - min) / min of the distance over the variants, and whether every
variant reported converged.

Pairs: cat1 -> cat2 and cat1 -> horse0 (../shared/data, skipped when absent) and a
synthetic pair (a bumpy surface against a stretched copy under a rotation of the
parameter sphere), metric (1, 1, 0.1, 0), modulo "diff". Rows: the paper's low
(12 x 25, degree 5 / 5, N 5) and middle (25 x 49, 7 / 8, N 10).

Measured (2026-11-23, 2 CPU cores, float64, jax 0.10.2; distances in the user's units):
    low row: every pair agrees within itself (relative spread 1e-10 for the cats at
        0.56171, 5e-14 for cat1 -> horse0 at 1.11153, 2e-16 for the synthetic pair at
        0.53818); all converged.
    middle row: the synthetic pair agrees to 2e-16 (0.55514). The cats split between two
        converged minima: 0.79298 (default, and batched under vmap: 7 rounds, grad norm
        0.028) and 0.77178 (the three other compilations: 10 rounds, 0.023); spread 2.7 %.
        cat1 -> horse0: 0.8489, 0.8544, 0.8682, 0.8702, and 1.4937 from the compilation
        without fusion emitters at LLVM level 1. That run was reported converged after 2
        rounds, the second one refused, with a joint grad norm of 0.945; the others have
        0.014-0.034. Spread 76 %.
    The same run before the pole derivative of f o gamma was fixed (outer_steps 10):
        low row, synthetic: spread 2.5e-6. middle row, cats: 0.8395-0.8588 (spread 2.3 %,
        grad norms 0.04-0.27). cat1 -> horse0: 0.8526-0.8642 and 1.0400 (2 rounds,
        grad norm 0.399). synthetic: 1.6e-6.
    So at the middle row the search is reproducible for the smooth synthetic pair, and
    for the real pairs up to the choice between nearby minima, except for rare runs that
    end on a refused round with a large gradient. The README's "What the distance means"
    says how to read such a run.

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
from elastic_jax import _shape, shapes  # noqa: E402

from _common import DATA, emit, environment  # noqa: E402

METRIC = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)
ROWS = {
    "low": {"grid": (12, 25), "degree": 5, "vf_degree": 5, "n_times": 5},
    "middle": {"grid": (25, 49), "degree": 7, "vf_degree": 8, "n_times": 10},
}
# XLA:CPU code-generation options: the same program, rounded differently. Names of the
# jaxlib this was written against; a jaxlib that lacks one skips that variant.
COMPILATIONS = {
    "default": {},
    "no fusion emitters": {"xla_cpu_use_fusion_emitters": False},
    "LLVM level 1": {"xla_backend_optimization_level": 1},
    "no fusion emitters, LLVM level 1": {
        "xla_cpu_use_fusion_emitters": False,
        "xla_backend_optimization_level": 1,
    },
}


def surfaces(name: str, m: int, n: int):
    """(f1, f2, a third surface to batch f2 with), or None when the data is absent."""
    if name == "synthetic":
        other = shapes.sample(shapes.ellipsoid, m, n, axes=(1.0, 0.8, 0.6))
        return (*(np.asarray(f) for f in bench_shape.pair("synthetic", m, n)), np.asarray(other))
    files = {"cats": ("cat1", "cat2", "horse0"), "horse": ("cat1", "horse0", "cat2")}[name]
    paths = [DATA / f"{f}_50x99.npz" for f in files]
    if not all(p.exists() for p in paths):
        return None
    return tuple(np.asarray(ej.resample(np.load(p)["f"], m, n)) for p in paths)


def summary(result, scale: float) -> dict:
    history = np.asarray(result.energy_history) * scale**2
    return {
        "distance": float(result.distance) * scale,
        "converged": bool(result.converged),
        "rounds": int(result.rounds),
        "grad_norm": float(result.grad_norm),
        "energy_history": history[np.isfinite(history)].tolist(),
        "refinement_change": float(result.refinement.relative_change),
    }


def variants(f1, f2, other, cfg) -> dict:
    """Each variant's summary ({"error": ...} for a compilation option this jaxlib lacks)."""
    units, (g1, g2) = _shape.in_units(f1, f2)
    scale = float(units.scale)
    m, n = f1.shape[-2:]
    bases = _shape._bases(m, n, cfg, np.float64)
    args = (_shape.constant(METRIC), g1, g2, bases)
    out = {}
    for label, options in COMPILATIONS.items():
        solve = jax.jit(
            _shape._shape_solve, static_argnames=("cfg", "rigid"), compiler_options=options
        )
        try:
            result = jax.block_until_ready(solve(*args, cfg=cfg, rigid=False))
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
            degree=settings["degree"], vf_degree=settings["vf_degree"], n_times=settings["n_times"]
        )
        cfg = cfg.replace(tol=_shape.default_tol(np.float64))
        for name in pairs:
            data = surfaces(name, m, n)
            if data is None:
                continue
            found = variants(*data, cfg)
            base = {"row": row, "pair": name, "settings": {**settings, "modulo": "diff"}}
            for label, record in found.items():
                emit({"benchmark": "rounding_variant", **base, "variant": label, **record})
            distances = [r["distance"] for r in found.values() if "distance" in r]
            emit(
                {
                    "benchmark": "rounding_spread",
                    **base,
                    "variants": len(distances),
                    "distance_min": min(distances),
                    "distance_max": max(distances),
                    "relative_spread": (max(distances) - min(distances)) / min(distances),
                    "all_converged": all(
                        r.get("converged", False) for r in found.values() if "distance" in r
                    ),
                    "environment": env,
                }
            )


if __name__ == "__main__":
    main()
