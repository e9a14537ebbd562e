"""What the finest level of a resolved distance spends: the 97 x 193 level continuing
the 49 x 97 level of the same pair, by phase, with its rounds and solver steps.

For each pair, modulo rigid, metric (1, 1, 0.1, 0), the package's defaults otherwise,
float64: the levels 13 x 25, 25 x 49, 49 x 97 are solved once (kept in ``--keep``, a
folder, so that later runs continue the very same 49 x 97 solution), then the 97 x 193
level is solved from it under each ``--variants`` entry:

- ``default``: the package's continuation (the level below's registration, path and
  parametrized path; each round's BFGS starts from the path's block of the inverse
  Hessian the round before ended with);
- a Python dict of ShapeOptions fields, e.g. ``{'outer_steps': 2}``.

One JSON record per solve: the variant, wall seconds (``compiled`` says whether the
process compiled it first), each phase's seconds, rounds, solver steps, the distance,
the parametrized distance, the result, the energy after each round, and the same
registration and path evaluated on the 193 x 385 grid (``distance_grid``).

``--level 49x97`` measures that level from 25 x 49 instead (the level at which the
finer nodes' default resolves the cats).

Run: python benchmarks/bench_finest.py [--pairs cats,cat-horse,horse-hand,pial] [--level 97x193]
     [--variants "default;{'outer_steps': 2}"] [--keep DIR] [--repeat K]
"""

from __future__ import annotations

import argparse
import ast
import pathlib
import pickle
import tempfile
import time
import warnings

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from bench_order import PAIRS, load  # noqa: E402

import elastic_jax as ej  # noqa: E402
from elastic_jax._registration import levels as _levels  # noqa: E402
from elastic_jax._registration.phases import Reporter  # noqa: E402

from _common import emit, environment  # noqa: E402

METRIC = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)
FINEST = (97, 193)


def below_level(name: str, f1, f2, keep: pathlib.Path, finest: tuple = FINEST):
    """The pair's levels below ``finest`` (rtol tiny, so that all run), kept in
    ``keep``; the last one's result (numpy leaves) and its levels' record."""
    levels = ej.ShapeOptions().levels
    below = levels[: levels.index(tuple(finest))]
    path = keep / f"below_{name}_{below[-1][0]}x{below[-1][1]}.pkl"
    if path.exists():
        return pickle.loads(path.read_bytes())
    # Every level runs (rtol tiny), each stopping its rounds as the defaults' levels do.
    default = ej.ShapeOptions()
    options = default.replace(levels=below, rtol=1e-12, rounds_tol=default.level_rounds_tol)
    begin = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ej.ConvergenceWarning)
        res = ej.shape_geodesic(f1, f2, METRIC, modulo="rigid", options=options)
    res = jax.tree_util.tree_map(np.asarray, res)
    emit(
        {
            "benchmark": "finest_below",
            "pair": name,
            "levels": res.levels.distances.tolist(),
            "level_seconds": res.levels.seconds.tolist(),
            "seconds": time.perf_counter() - begin,
        }
    )
    path.write_bytes(pickle.dumps(res))
    return res


def finest(name: str, f1, f2, below, variant: str, compiled: bool, grid: tuple = FINEST) -> dict:
    """The level on ``grid`` (97 x 193 by default) from ``below`` under ``variant``: its
    record."""
    options = ej.ShapeOptions()
    if variant != "default":
        options = options.replace(**ast.literal_eval(variant))
    reports: list[dict] = []
    reporter = Reporter(reports.append)
    begin = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ej.ConvergenceWarning)
        res = _levels.level_solve(
            jnp.asarray(f1),
            jnp.asarray(f2),
            METRIC,
            "rigid",
            options,
            tuple(grid),
            below,
            None,
            reporter,
        )
        distance = float(res.distance)
    seconds = time.perf_counter() - begin
    phases, last = {}, 0.0
    for report in reports:
        phases[report["stage"]] = report["seconds"] - last
        last = report["seconds"]
    history = np.asarray(res.energy_history)
    return {
        "benchmark": "finest_level",
        "pair": name,
        "grid": list(grid),
        "variant": variant,
        "compiled": compiled,
        "seconds": seconds,
        "phases": phases,
        "rounds": int(res.rounds),
        "num_steps": int(res.num_steps),
        "distance": distance,
        "below_distance": float(below.distance),
        "parametrized_distance": float(res.parametrized_distance),
        "result": ej.RESULTS.name(res.result),
        "round_energies": history[1:][np.isfinite(history[1:])].tolist(),
        "distance_grid": float(res.refinement.distance_grid),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", default="cats,cat-horse")
    parser.add_argument("--variants", default="default")
    parser.add_argument("--keep", default=None, help="folder for the 49 x 97 solutions")
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument(
        "--level", default="97x193", help="the level measured (one of the defaults' levels)"
    )
    args = parser.parse_args()
    grid = tuple(int(k) for k in args.level.split("x"))
    if grid not in ej.ShapeOptions().levels[1:]:
        parser.error(f"--level must be one of the default levels above the first; got {args.level}")
    keep = pathlib.Path(args.keep or tempfile.mkdtemp(prefix="bench-finest-"))
    keep.mkdir(parents=True, exist_ok=True)
    emit({"benchmark": "environment", "environment": environment(), "keep": str(keep)})
    variants = [v.strip() for v in args.variants.split(";" if "{" in args.variants else ",")]
    for name in args.pairs.split(","):
        f1, f2 = (load(k) for k in PAIRS[name])
        if f1 is None or f2 is None:
            emit({"benchmark": "finest_level", "pair": name, "skipped": "data absent"})
            continue
        below = below_level(name, f1, f2, keep, grid)
        seen: set = set()
        for variant in variants:
            for _ in range(args.repeat):
                emit(finest(name, f1, f2, below, variant, variant not in seen, grid))
                seen.add(variant)


if __name__ == "__main__":
    main()
