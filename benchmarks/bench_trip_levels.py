"""Where round trips between the orders pay: bench_levels.py with ``--alternations``
kept on every level (``--trips all``, the package's behaviour) or only on each
candidate's first level (``--trips first``: the levels above continue without them).

The package has no option for the second; this script wraps the levels' round-trip
step (``elastic_jax._registration.levels.alternated``) for the run and then runs
bench_levels.py with the remaining arguments (one pair), so its record is bench_levels.py's with
``trips`` added, and each round trip's grid, distance before and after, and seconds
(``round_trips``, in the order they ran).

Run: python benchmarks/bench_trip_levels.py --trips first --pairs pial --both-orders
     --search-smoothing 1,0.5,0.25 --alternations 3
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import pathlib
import runpy
import sys
import time

import elastic_jax._registration.levels as levels

HERE = pathlib.Path(__file__).resolve().parent


def main() -> None:
    # --trips is this script's own; the rest goes to bench_levels.py, which checks it.
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], add_help=False)
    parser.add_argument("--trips", choices=("all", "first"), default="all")
    known, args = parser.parse_known_args()
    trips = known.trips
    package_step, seen = levels.alternated, []

    def alternated(f1, f2, metric, modulo, options, grid, result, reporter=None):
        if trips == "first" and tuple(grid) != tuple(options.levels[0]):
            return result
        begin = time.perf_counter()
        out = package_step(f1, f2, metric, modulo, options, grid, result, reporter)
        if options.alternations:
            seconds = time.perf_counter() - begin
            seen.append([list(grid), float(result.distance), float(out.distance), seconds])
        return out

    levels.alternated = alternated
    sys.path.insert(0, str(HERE))
    sys.argv = [str(HERE / "bench_levels.py"), *args]
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        runpy.run_path(sys.argv[0], run_name="__main__")
    for line in printed.getvalue().splitlines():
        record = json.loads(line)
        print(json.dumps({**record, "trips": trips, "round_trips": seen}))


if __name__ == "__main__":
    main()
