"""A resolved distance's levels through the package's own loop, at its defaults.

For each pair, modulo rigid motion, metric (1, 1, 0.1, 0), float64, ``shape_geodesic``
with ``ShapeOptions(rtol=..., levels=...)`` and nothing else changed: one record per pair
with the levels' grids, ``distances`` (the last level's minimum on each grid: where the
levels going up turned back or stopped halving, the coarser grids solved again from the
last level), ``ascent`` (the levels as first solved), ``refined`` (each of those read on the grid
twice finer than its rule), ``refined_gaps`` (abs(refined / ascent - 1)) and their
observed orders ``gap_orders`` (log2 of successive ratios), seconds, the estimate, the
last level's gamma's Jacobian determinant (``gamma_jacobian``: its least and largest
value; ``gamma_jacobian_below_0.1``: how many points), the result's name and the total
time (compiling included), next to the settings and the machine.

Pairs: those of bench_order.py (``cats``, ``cat-horse``, ``horse-cat``, ``horse-hand``,
``pial``) or any two of the authors' surfaces as ``first:second`` (``cat2:horse0``).
``--turn D`` reads f1 through a rotation of its parameter sphere by D degrees about
(1, 2, 3) (bench_order.turned: at 99 x 197 by its spline), f2 as given.

Inputs the levels were not tuned on: ``--perturb SEED`` adds 1e-10 times a standard
normal draw (numpy's generator with that seed) to f1; ``--rotate SEED`` turns f2 in
space by ``shapes.random_rotation(SEED)``; ``--moebius A`` replaces f1 by f1 read at
99 x 197 (its spline) through the Moebius map with boost A (0.3, 0.4, ...) along
(0.36, -0.48, 0.8) and turned by ``shapes.random_rotation(7)``: with ``first:first`` a
surface against its own read. ``--read 99x197`` replaces both inputs by their reads at
that grid (their splines, no map; before ``--moebius``, which then reads the read).
``--degree`` and ``--vf-degree`` set the path's and the
Diff step's degrees (default: ``ShapeOptions()``'s); ``--level-vf-degrees 8,16`` gives
each level its own Diff step degree (``ShapeOptions.level_vf_degrees``);
``--level-candidates K`` carries K of the first level's starts through the levels
(``ShapeOptions.level_candidates``): the record then has every candidate's final
distance (``candidates``), their ``spread`` and each candidate's distance on every level
it solved (``candidate_levels``: [grid, distance, solved again] in order);
``--both-orders`` adds the other order's starts, inverted, as candidates
(``ShapeOptions.both_orders``). ``--search-smoothing 1,0.5,0.25`` adds a candidate that
graduates each level's own start search: the level is solved first on the inputs
low-passed by those kernel widths (in its latitude spacings;
``ShapeOptions.search_smoothing``), by ``--smoothing-kernel sphere`` (the default) or
``surface`` (``ShapeOptions.smoothing_kernel``). ``--alternations K`` continues each
level's solve through at most K round trips between the orders
(``ShapeOptions.alternations``).

``--matrix cat1,cat2,horse0`` runs ``distance_matrix`` of those surfaces instead, with
the same options (its candidates too), by ``--strategy`` (default "loop"): one record
with the matrix, each pair's levels estimate, candidates' spread, finest grid and
status, and the total time; its entries are comparable to the pairs' own records.

``--times N`` sets the path's time points (default: ``ShapeOptions().n_times``).
``--calls K`` solves each pair K times in one process (default 1): the first call
compiles, the later ones are warm. Each record has ``call`` (1, 2, ...) and ``phases``:
for each level, in order, the seconds of each of its phases as shape_geodesic's
progress reports them (start search, coarse registration or the registration carried
from the level below, registration rounds, geodesics, checks, and the result after
them; levels solved again are marked ``again``, a level's solves of the low-passed
inputs carry their kernel width as ``smoothing``, and its round trips between the orders
their number as ``alternation``). Each candidate's level is printed on stderr as it ends
(seconds since the call began, its grid, distance and whether it converged), so a run of
an hour shows how far it got; the records stay on stdout.

Run: python benchmarks/bench_levels.py [--pairs pial,cat2:horse0] [--turn 0]
     [--rtol 0.03] [--levels 13x25,25x49,49x97,97x193] [--times 13] [--calls 1]
     [--perturb SEED] [--rotate SEED] [--moebius A] [--read 99x197] [--degree 7]
     [--vf-degree 8] [--level-vf-degrees 8,16,32] [--level-candidates 1] [--both-orders]
     [--search-smoothing 1,0.5,0.25] [--smoothing-kernel sphere] [--alternations 0]
     [--matrix cat1,cat2,horse0 [--strategy loop]]
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from bench_order import METRIC, PAIRS, load, turned  # noqa: E402

import elastic_jax as ej  # noqa: E402

from _common import emit, environment, moebius_read  # noqa: E402


def phase_seconds(events: list[dict]) -> list[dict]:
    """Each level's phases with their seconds, from shape_geodesic's progress events
    (each event's time less the one before it)."""
    levels, before = [], 0.0
    for event in events:
        seconds, before = event["seconds"] - before, event["seconds"]
        # The level's own event closes it: the time after its checks (the result's
        # energy evaluated again, differentiably) is its "result".
        stage = "result" if event["stage"] == "level" else event["stage"]
        key = (
            event.get("level"),
            bool(event.get("again", False)),
            tuple(event["grid"]),
            event.get("smoothing"),
            event.get("alternation"),
        )
        if not levels or levels[-1]["key"] != key:
            levels.append({"key": key, "phases": {}})
        phases = levels[-1]["phases"]
        phases[stage] = phases.get(stage, 0.0) + seconds
    return [
        {
            "grid": list(grid),
            "again": again,
            "smoothing": width,
            "alternation": trip,
            "phases": level["phases"],
        }
        for level in levels
        for _, again, grid, width, trip in [level["key"]]
    ]


def candidate_levels(events: list[dict]) -> list[list]:
    """Each candidate's levels, in order, as [grid, distance, solved again], from the
    level events of shape_geodesic's progress (one candidate: its own)."""
    found: dict[int, list] = {}
    for event in events:
        if event["stage"] == "level":
            row = [list(event["grid"]), event["distance"], bool(event.get("again", False))]
            found.setdefault(event.get("candidate", 1), []).append(row)
    return [found[k] for k in sorted(found)]


MOEBIUS_DIRECTION = np.array([0.36, -0.48, 0.8])


def varied(f1, f2, variant: dict):
    """(f1, f2) with the variant's perturbation, Moebius read and rotation applied."""
    if variant.get("read"):
        f1, f2 = (moebius_read(f, np.zeros(3), np.eye(3), variant["read"]) for f in (f1, f2))
    if variant.get("moebius"):
        boost = variant["moebius"] * MOEBIUS_DIRECTION / np.linalg.norm(MOEBIUS_DIRECTION)
        f1 = moebius_read(f1, boost, ej.shapes.random_rotation(7), (99, 197))
    if variant.get("perturb") is not None:
        noise = np.random.default_rng(variant["perturb"]).standard_normal(np.shape(f1))
        f1 = np.asarray(f1) + 1e-10 * noise
    if variant.get("rotate") is not None:
        f2 = np.einsum("ij,jmn->imn", ej.shapes.random_rotation(variant["rotate"]), f2)
    return f1, f2


def echo(event: dict, begin: float) -> None:
    """A level's event on stderr as it happens, so a long run shows how far it got."""
    if event.get("stage") == "level":
        seconds = time.perf_counter() - begin
        print(f"{seconds:8.0f} s  {event}", file=sys.stderr, flush=True)


def run_pair(
    name: str,
    options: ej.ShapeOptions,
    turn: float,
    call: int = 1,
    variant: dict | None = None,
) -> dict | None:
    first, second = PAIRS[name] if name in PAIRS else name.split(":")
    f1, f2 = load(first), load(second)
    if f1 is None or f2 is None:
        return None
    if turn:
        f1 = turned(f1, turn)
    f1, f2 = varied(f1, f2, variant or {})
    events: list[dict] = []
    begin = time.perf_counter()

    def heard(event: dict) -> None:
        events.append(event)
        echo(event, begin)

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ej.ConvergenceWarning)
        res = ej.shape_geodesic(
            jnp.asarray(f1),
            jnp.asarray(f2),
            METRIC,
            modulo="rigid",
            options=options,
            progress=heard,
        )
    levels = res.levels
    # What each level's rule under-read: its registration and path on the grid twice finer.
    gaps = np.abs(np.asarray(levels.refined) / np.asarray(levels.ascent) - 1.0)
    # How far the last level's registration stretches and compresses: its Jacobian.
    jacobian = np.asarray(ej.jacobian_determinant(res.gamma))
    return {
        "call": call,
        "phases": phase_seconds(events),
        "benchmark": "levels",
        "pair": name,
        "turn": turn,
        **(variant or {}),
        "parametrized_distance": float(res.parametrized_distance),
        "distance": float(res.distance),
        "converged": bool(res.converged),
        "result": str(res.result).split("<")[-1].split(":")[0].rstrip(">"),
        "grids": np.asarray(levels.grids).tolist(),
        "distances": np.asarray(levels.distances).tolist(),
        "ascent": np.asarray(levels.ascent).tolist(),
        "refined": np.asarray(levels.refined).tolist(),
        "refined_gaps": gaps.tolist(),
        "gap_orders": np.log2(gaps[:-1] / gaps[1:]).tolist(),
        "seconds": np.asarray(levels.seconds).tolist(),
        "estimate": float(levels.estimate),
        "candidates": np.asarray(levels.candidates).tolist(),
        "candidate_levels": candidate_levels(events),
        "spread": float(levels.spread),
        "gamma_jacobian": [float(jacobian.min()), float(jacobian.max())],
        "gamma_jacobian_below_0.1": int((jacobian < 0.1).sum()),
        "total_s": time.perf_counter() - begin,
    }


def run_matrix(names: list[str], options: ej.ShapeOptions, strategy: str) -> dict | None:
    surfaces = [load(name) for name in names]
    if any(f is None for f in surfaces):
        return None
    begin = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ej.ConvergenceWarning)
        res = ej.distance_matrix(
            jnp.asarray(np.stack(surfaces)),
            METRIC,
            modulo="rigid",
            options=options,
            job=ej.JobOptions(strategy=strategy),
        )
    return {
        "benchmark": "levels_matrix",
        "shapes": names,
        "strategy": strategy,
        "distances": np.asarray(res.distances).tolist(),
        "estimate": np.asarray(res.estimate).tolist(),
        "spread": np.asarray(res.spread).tolist(),
        "grids": np.asarray(res.grids).tolist(),
        "pairs_converged": np.asarray(res.pairs_converged).tolist(),
        "result": str(res.result).split("<")[-1].split(":")[0].rstrip(">"),
        "total_s": time.perf_counter() - begin,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", default="cats,cat-horse,pial")
    parser.add_argument("--turn", type=float, default=0.0)
    parser.add_argument("--rtol", type=float, default=ej.ShapeOptions().rtol)
    parser.add_argument(
        "--levels", default=",".join(f"{m}x{n}" for m, n in ej.ShapeOptions().levels)
    )
    parser.add_argument("--times", type=int, default=ej.ShapeOptions().n_times)
    parser.add_argument("--calls", type=int, default=1)
    parser.add_argument("--perturb", type=int, default=None)
    parser.add_argument("--rotate", type=int, default=None)
    parser.add_argument("--moebius", type=float, default=0.0)
    parser.add_argument("--read", default="", help="both inputs read at this grid: 99x197")
    parser.add_argument("--degree", type=int, default=ej.ShapeOptions().degree)
    parser.add_argument("--vf-degree", type=int, default=ej.ShapeOptions().vf_degree)
    parser.add_argument(
        "--level-vf-degrees", default=None, help="one Diff step degree per level: 8,11,14"
    )
    parser.add_argument("--level-candidates", type=int, default=1)
    parser.add_argument("--both-orders", action="store_true")
    parser.add_argument(
        "--search-smoothing", default="", help="kernel widths, wide to narrow: 1,0.5,0.25"
    )
    parser.add_argument(
        "--smoothing-kernel", default="sphere", choices=ej.ShapeOptions.CHOICES["smoothing_kernel"]
    )
    parser.add_argument("--alternations", type=int, default=0)
    parser.add_argument("--matrix", default="", help="distance_matrix of these surfaces")
    parser.add_argument("--strategy", default="loop", choices=("loop", "map", "vmap"))
    args = parser.parse_args()
    if not 0.0 <= args.moebius < 1.0:
        parser.error(f"--moebius must be in [0, 1); got {args.moebius}")
    for flag, seed in (("--perturb", args.perturb), ("--rotate", args.rotate)):
        if seed is not None and seed < 0:
            parser.error(f"{flag} must be a seed >= 0; got {seed}")
    if args.calls < 1:
        parser.error(f"--calls must be at least 1; got {args.calls}")
    levels = tuple(tuple(int(k) for k in grid.split("x")) for grid in args.levels.split(","))
    try:
        widths = tuple(float(w) for w in args.search_smoothing.split(",") if w)
    except ValueError:
        parser.error(f"--search-smoothing must be numbers: {args.search_smoothing}")
    level_vf_degrees = None
    if args.level_vf_degrees:
        try:
            level_vf_degrees = tuple(int(d) for d in args.level_vf_degrees.split(","))
        except ValueError:
            parser.error(f"--level-vf-degrees must be integers: {args.level_vf_degrees}")
    try:
        options = ej.ShapeOptions(
            rtol=args.rtol,
            levels=levels,
            n_times=args.times,
            degree=args.degree,
            vf_degree=args.vf_degree,
            level_vf_degrees=level_vf_degrees,
            level_candidates=args.level_candidates,
            both_orders=args.both_orders,
            search_smoothing=widths,
            smoothing_kernel=args.smoothing_kernel,
            alternations=args.alternations,
        )
    except ValueError as err:
        parser.error(str(err))
    settings = {"rtol": args.rtol, "levels": [list(g) for g in levels], "dtype": "float64"}
    settings.update(n_times=args.times, degree=args.degree, vf_degree=args.vf_degree)
    settings["level_vf_degrees"] = None if level_vf_degrees is None else list(level_vf_degrees)
    settings["level_candidates"] = args.level_candidates
    settings["both_orders"] = args.both_orders
    settings["search_smoothing"] = list(widths)
    settings["smoothing_kernel"] = args.smoothing_kernel
    settings["alternations"] = args.alternations
    if args.matrix:
        record = run_matrix(args.matrix.split(","), options, args.strategy)
        if record is not None:
            emit({**record, "settings": settings, "environment": environment()})
        return
    variant = {"perturb": args.perturb, "rotate": args.rotate, "moebius": args.moebius}
    if args.read:
        try:
            variant["read"] = tuple(int(k) for k in args.read.split("x"))
        except ValueError:
            parser.error(f"--read must be a grid MxN: {args.read}")
        grid = variant["read"]
        if len(grid) != 2 or min(grid) < 5 or grid[1] % 2 == 0:
            parser.error(f"--read must be a grid MxN, m, n >= 5, n odd: {args.read}")
    for name in args.pairs.split(","):
        for call in range(1, args.calls + 1):
            record = run_pair(name, options, args.turn, call, variant)
            if record is not None:
                emit({**record, "settings": settings, "environment": environment()})


if __name__ == "__main__":
    main()
