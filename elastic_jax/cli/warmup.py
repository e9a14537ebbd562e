"""``elastic-jax warmup``: compile a batch job's shape solves into the cache before it runs."""

from __future__ import annotations

import argparse

import jax

from .. import warmup
from .arguments import Command, rtol_option, shape_options
from .common import BadInput, Progress, check_degrees

# The data's grid when none is given: the shared surfaces', and meshes' default.
DEFAULT_INPUT_GRID = (50, 99)


def _grids(args) -> tuple[tuple[int, int], tuple[tuple[int, int], ...]]:
    """The inputs' grid and the working grids the job's options solve on."""

    grid = tuple(args.grid) if args.grid else DEFAULT_INPUT_GRID
    return grid, args.shape_options.working_grids(grid)


def check_warmup(args) -> None:
    """Refuse, before any work, a warmup without a cache or with degrees a grid lacks."""
    for m, n in _grids(args)[1]:
        check_degrees(args, m, n)
    if args.no_cache:
        raise BadInput("warmup fills the compilation cache: --no-cache leaves none to fill")


def run_warmup(args, progress: Progress) -> dict:
    if jax.config.jax_compilation_cache_dir is None:  # --cache-dir could not be created
        raise BadInput(f"warmup fills the compilation cache: {args.cache_dir} could not be one")
    moduli = ("diff", "rigid") if args.modulo == "both" else (args.modulo,)
    grid, working = _grids(args)
    options = args.shape_options
    progress(
        f"compiling the shape solves for inputs on {grid[0]} x {grid[1]}, working grids "
        f"{', '.join(f'{m} x {n}' for m, n in working)}, modulo {' and '.join(moduli)}, "
        f"{args.dtype} (minutes the first time)"
    )
    report = warmup(grid, modulo=moduli, options=options, dtype=args.dtype)
    progress(f"{report.programs} programs compiled in {report.seconds:.0f} s")
    return {
        "command": "warmup",
        "converged": True,
        "settings": {
            "modulo": list(moduli),
            **options.as_dict(),
            "input_grid": list(report.input_grid),
            "dtype": report.dtype,
        },
        "grids": [list(g) for g in report.grids],
        "programs_compiled": report.programs,
        "seconds": report.seconds,
        "cache_dir": report.cache_dir,
    }


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``warmup`` command's arguments."""
    shape_options(p, modulo="diff", moduli=("diff", "rigid", "both"))
    rtol_option(p, "the job's resolved distances")


COMMAND = Command(
    name="warmup",
    run=run_warmup,
    add_arguments=add_arguments,
    help="compile a batch job's shape solves into the cache ahead of it",
    description="Solves a built-in pair with the job's shape options on every working "
    "grid (each level of --rtol), so that the compilation cache (--cache-dir) holds "
    "every program the job's shape geodesics, distances and resolved Karcher means run "
    "for inputs on --grid (default 50 99): later runs load them instead of compiling.",
)
