"""Both orders in turn: does a level's end move when the other order continues it?

For one pair (bench_order.py's names or ``first:second``), modulo rigid motion, metric
(1, 1, 0.1, 0), float64: the pair's levels 25 x 49 and 49 x 97 as a resolved
shape_geodesic's candidate solves them (``--kind default``: a start search of its own;
``graduated``: the start searches through the low-passed inputs of
``search_smoothing=(1, 0.5, 0.25)``), then ``--steps`` solves at 49 x 97, each in the
other order from the last one's registration inverted (gamma^-1, R^T) with the straight
line as the path (one record each: ``step``, ``order``, ``distance``, ``converged``,
``num_steps``, seconds since the start). ``--restarts K`` instead continues the level's
end K times in its own order from its own registration, the straight line as the path
(``restart``): the control, whether a fresh start alone goes down. ``--finer`` then
continues the level's end and the first step's at 97 x 193 (``finer``): whether the
orders' gap is the grid's. A step whose inverse folds on the grid ends the run
(``inverse`` "unusable").

Run: python benchmarks/bench_alternation.py [--pairs horse-cat] [--kind graduated]
     [--steps 5] [--restarts 0] [--finer]
"""

from __future__ import annotations

import argparse
import time
import warnings

import jax

jax.config.update("jax_enable_x64", True)

from bench_order import METRIC, PAIRS, load  # noqa: E402

import elastic_jax as ej  # noqa: E402
from elastic_jax._registration.levels import GRADUATED, level_solve  # noqa: E402
from elastic_jax._registration.one_grid import one_grid_solve  # noqa: E402
from elastic_jax._registration.starts import usable_inverse  # noqa: E402

from _common import emit, environment  # noqa: E402

LEVELS = ((25, 49), (49, 97))
FINER = (97, 193)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", default="horse-cat")
    parser.add_argument("--kind", default="graduated", choices=("default", "graduated"))
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--restarts", type=int, default=0)
    parser.add_argument("--finer", action="store_true")
    args = parser.parse_args()
    names = PAIRS.get(args.pairs) or tuple(args.pairs.split(":"))
    surfaces = {name: load(name) for name in names}
    if any(f is None for f in surfaces.values()):
        print(f"skipped: {args.pairs} (its surfaces are absent)")
        return
    options = ej.ShapeOptions(levels=LEVELS, search_smoothing=(1.0, 0.5, 0.25))
    level = options.on_level(LEVELS[-1])
    start = GRADUATED if args.kind == "graduated" else None
    base = {"pair": args.pairs, "kind": args.kind, "environment": environment()}
    begin = time.perf_counter()

    def record(res, **fields):
        emit(
            {
                **base,
                **fields,
                "distance": float(res.distance),
                "converged": bool(res.converged),
                "num_steps": int(res.num_steps),
                "seconds": time.perf_counter() - begin,
            }
        )

    warnings.simplefilter("ignore", ej.ConvergenceWarning)
    first, second = names
    f1, f2 = surfaces[first], surfaces[second]
    res = None
    for grid in LEVELS:
        res = level_solve(f1, f2, METRIC, "rigid", options, grid, res, start)
    record(res, step=0, order=f"{first} -> {second}")
    end, ends = res, [(first, second, res)]
    for restart in range(1, args.restarts + 1):
        carry = (res.gamma, res.rotation, None)
        res = one_grid_solve(f1, f2, METRIC, "rigid", level, None, carry=carry)
        record(res, restart=restart, order=f"{first} -> {second}")
    res, a, b = end, first, second
    for step in range(1, args.steps + 1):
        inverse = usable_inverse(res.gamma)
        if inverse is None:
            emit({**base, "step": step, "inverse": "unusable"})
            break
        a, b = b, a
        carry = (inverse, res.rotation.T, None)
        res = one_grid_solve(surfaces[a], surfaces[b], METRIC, "rigid", level, None, carry=carry)
        record(res, step=step, order=f"{a} -> {b}")
        if step == 1:
            ends.append((a, b, res))
    if args.finer:
        for a, b, below in ends:
            res = level_solve(surfaces[a], surfaces[b], METRIC, "rigid", options, FINER, below)
            record(res, finer=list(FINER), order=f"{a} -> {b}")


if __name__ == "__main__":
    main()
