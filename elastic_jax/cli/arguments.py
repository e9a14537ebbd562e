"""The option groups the commands share (metric, grid and files; shape solves; batch jobs;
Karcher steps) and the help formatter: each command adds its own arguments from them."""

from __future__ import annotations

import argparse
import os
import pathlib
import re
from collections.abc import Callable
from typing import NamedTuple

from .. import ShapeOptions
from .common import DEFAULT_METRIC, SHAPE_DEFAULTS


def _metric(text: str) -> tuple[float, float, float, float]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"--metric wants four numbers a,b,c,d; got {text!r}"
        ) from None
    if len(values) != 4:
        raise argparse.ArgumentTypeError(
            f"--metric wants four numbers a,b,c,d; got {len(values)} in {text!r}"
        )
    return values  # type: ignore[return-value]


def join_negative_values(argv: list[str]) -> list[str]:
    """``--metric -1,1,0.1,0`` as ``--metric=-1,1,0.1,0``: argparse takes a value that
    starts with "-" and is not one plain number for an option, and says "expected one
    argument" instead of what is wrong with the value."""
    out: list[str] = []
    for token in argv:
        if out and out[-1] == "--metric" and re.match(r"-\.?\d", token):
            out[-1] = f"--metric={token}"
        else:
            out.append(token)
    return out


def _default_cache_dir() -> pathlib.Path:
    if os.environ.get("ELASTIC_JAX_CACHE"):
        return pathlib.Path(os.environ["ELASTIC_JAX_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or pathlib.Path.home() / ".cache"
    return pathlib.Path(base) / "elastic-jax"


def io_options(parser: argparse.ArgumentParser) -> None:
    """The options every command has: metric, grid, precision, output, progress, cache."""
    parser.add_argument(
        "--metric",
        type=_metric,
        default=",".join(f"{x:g}" for x in DEFAULT_METRIC),
        metavar="A,B,C,D",
        help="split metric coefficients: shear, stretch, bending, rotation",
    )
    parser.add_argument(
        "--grid",
        type=int,
        nargs=2,
        metavar=("M", "N"),
        default=None,
        help="resample every input onto this grid (default: the first input's grid, "
        "50 99 for meshes)",
    )
    parser.add_argument(
        "--frame",
        choices=("principal", "input"),
        default="principal",
        help="the axes a mesh file is resampled in: its principal axes, so that a moved mesh "
        "gives the moved grid (default; a symmetric mesh warns and keeps the input's), or the "
        "input's coordinate axes",
    )
    parser.add_argument(
        "--dtype",
        choices=("float64", "float32"),
        default="float64",
        help="precision (float64, the reference, is the default; float32 is faster on GPUs)",
    )
    parser.add_argument(
        "--out",
        type=pathlib.Path,
        default=pathlib.Path("elastic-jax-out"),
        help="output directory (created)",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    parser.add_argument(
        "--cache-dir",
        type=pathlib.Path,
        default=_default_cache_dir(),
        help="JAX's persistent compilation cache, so that a second run skips compiling "
        "(ELASTIC_JAX_CACHE or XDG_CACHE_HOME move it)",
    )
    parser.add_argument("--no-cache", action="store_true", help="compile from scratch")
    parser.add_argument(
        "--no-export",
        action="store_true",
        help="keep compiled programs only, not the traced shape solve (jax.export): a new "
        "process then traces it again",
    )


def input_options(parser: argparse.ArgumentParser) -> None:
    """The options of commands that read surface files: sphere maps and scale."""
    parser.add_argument(
        "--sphere",
        nargs="+",
        default=None,
        metavar="PATH",
        help="a spherical map of each input mesh to resample it through instead of computing "
        "one (FreeSurfer's ?h.sphere, a sphere_left.gii, or a mesh file with the same "
        "vertices in the same order): one file per input surface, in the inputs' order "
        "(place it after them); meshes only; the map is in its own axes, so --frame "
        "does not apply",
    )
    parser.add_argument(
        "--normalize",
        choices=("none", "area"),
        default="none",
        help="area: scale each input about its area centroid to the unit sphere's area 4 pi "
        "(io.normalize_scale), so that shapes are compared with size removed; distances "
        "are then in units of that normalized size (a distance scales with the surfaces: "
        "d(s f1, s f2) = s d(f1, f2))",
    )


def common_options(
    parser: argparse.ArgumentParser,
    *,
    degree: int,
    times: int,
    max_steps: int | None = None,
    max_steps_help: str = "solver step limit (library default)",
) -> None:
    io_options(parser)
    parser.add_argument(
        "--degree", type=int, default=degree, help="spherical-harmonic degree of the path"
    )
    parser.add_argument("--times", type=int, default=times, help="time points N, ends included")
    parser.add_argument(
        "--solver",
        choices=ShapeOptions.CHOICES["solver"],
        default="bfgs",
        help="optimistix BFGS or jaxopt L-BFGS",
    )
    parser.add_argument("--max-steps", type=int, default=max_steps, help=max_steps_help)


def _rtol(text: str) -> float | str | None:
    """--rtol's value: a number, or 'none' (one working grid); other text is passed on for
    ShapeOptions to refuse in one line (shape_options_from)."""
    if text.strip().lower() == "none":
        return None
    try:
        return float(text)
    except ValueError:
        return text


def _widths(text: str) -> tuple[float, ...] | str:
    """--search-smoothing's value: comma-separated numbers ('none' or '': no smoothing);
    ShapeOptions checks they are positive and wide to narrow. Other text is passed on
    for shape_options_from to refuse in one line."""
    if text.strip().lower() in ("", "none"):
        return ()
    try:
        return tuple(float(v) for v in text.split(","))
    except ValueError:
        return text


def shape_options(
    parser: argparse.ArgumentParser,
    *,
    modulo: str,
    inner: str = "",
    moduli: tuple[str, ...] = ("diff", "rigid"),
) -> None:
    """The options of shape geodesics (one ShapeOptions record; the library's defaults)."""
    d = SHAPE_DEFAULTS
    common_options(
        parser,
        degree=d.degree,
        times=d.n_times,
        max_steps=d.max_steps,
        max_steps_help=f"step limit of each inner solve (solver steps){inner}",
    )
    parser.add_argument(
        "--modulo",
        choices=moduli,
        default=modulo,
        help="reparametrizations, or reparametrizations and rigid motions"
        + (" (none: parametrized geodesics)" if "none" in moduli else ""),
    )
    parser.add_argument(
        "--scheme",
        choices=ShapeOptions.CHOICES["scheme"],
        default=d.scheme,
        help="time discretization of the path energy (see ShapeOptions)",
    )
    parser.add_argument(
        "--method",
        choices=ShapeOptions.CHOICES["method"],
        default=d.method,
        help="registration: paper Algorithm 2 (joint) or alternating (coordinate)",
    )
    parser.add_argument("--vf-degree", type=int, default=d.vf_degree, help="Diff(S^2) basis degree")
    parser.add_argument(
        "--outer-steps", type=int, default=d.outer_steps, help="most registration rounds"
    )
    parser.add_argument(
        "--init",
        choices=ShapeOptions.CHOICES["init"],
        default=d.init,
        help="initial registration search",
    )
    parser.add_argument(
        "--no-refinement",
        dest="refinement",
        action="store_false",
        help="skip re-evaluating each distance at halved time steps and on a finer grid",
    )


def batch_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--strategy",
        choices=("auto", "vmap", "map", "loop"),
        default="auto",
        help="batching: auto is lax.map on CPU, vmap on accelerators",
    )
    parser.add_argument(
        "--batch-size", type=int, default=None, help="geodesics per batched call (bounds memory)"
    )
    where = parser.add_mutually_exclusive_group()
    where.add_argument(
        "--workers",
        type=int,
        default=None,
        help="solve on a local Dask cluster of this many worker processes (the dask extra)",
    )
    where.add_argument(
        "--scheduler",
        default=None,
        metavar="ADDRESS",
        help="solve on the Dask cluster whose scheduler is at ADDRESS (tcp://host:8786); "
        "--cache-dir must then be a path every worker can reach",
    )
    parser.add_argument(
        "--resume", action="store_true", help="continue from the checkpoint in --out"
    )
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="discard a checkpoint in --out and start over (without it or --resume, a "
        "checkpoint there is refused)",
    )


def rtol_option(parser: argparse.ArgumentParser, what: str) -> None:
    parser.add_argument(
        "--rtol",
        type=_rtol,
        default=SHAPE_DEFAULTS.rtol,
        help=f"{what}: working grids 25 x 49 ... 97 x 193 until two levels' distances agree "
        "within this; 'none': one working grid, the inputs'",
    )
    candidates = parser.add_argument_group(
        "candidates",
        "more starts carried through the levels beside the default's; the lowest final "
        "distance wins and a spread of the candidates' finals above --rtol is not resolved "
        "(ShapeOptions' fields of the same names)",
    )
    candidates.add_argument(
        "--level-candidates",
        type=int,
        default=SHAPE_DEFAULTS.level_candidates,
        metavar="K",
        help="the first level's K best-ranked starts, each through its own levels (0: "
        "none, only the graduated candidates of --search-smoothing)",
    )
    candidates.add_argument(
        "--both-orders",
        action="store_true",
        help="also the other order's starts, inverted (and its graduated solve, with "
        "--search-smoothing)",
    )
    candidates.add_argument(
        "--search-smoothing",
        type=_widths,
        default=None,
        metavar="W,W,...",
        help="one more candidate whose start searches run on the inputs low-passed by "
        "these kernel widths, wide to narrow, in latitude spacings (e.g. 1,0.5,0.25; "
        "default: none)",
    )
    candidates.add_argument(
        "--alternations",
        type=int,
        default=SHAPE_DEFAULTS.alternations,
        metavar="K",
        help="after each level's solve, at most K round trips through the other order "
        "(the registration inverted, continued there and inverted back), each kept where "
        "it ends lower",
    )
    candidates.add_argument(
        "--smoothing-kernel",
        choices=ShapeOptions.CHOICES["smoothing_kernel"],
        default=SHAPE_DEFAULTS.smoothing_kernel,
        help="the kernel of --search-smoothing: the sphere's or the surface's own heat flow",
    )


def karcher_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--karcher-steps",
        type=int,
        default=10,
        help="most Karcher steps (accepted updates of the mean)",
    )
    parser.add_argument(
        "--tol",
        type=float,
        default=1e-3,
        help="Karcher convergence: |mean velocity| <= tol x RMS distance, or the line "
        "search's step changes the sum of squared distances by less than tol (relative)",
    )
    parser.add_argument(
        "--step-size",
        type=float,
        default=1.0,
        help="first trial step along the mean velocity (halved while it raises the sum "
        "of squared distances)",
    )
    parser.add_argument(
        "--warm-start",
        action="store_true",
        help="also solve each shape from its registration at the previous mean and keep "
        "the lower distance (twice the solves; karcher_mean's warm_start)",
    )


class DefaultsShown(argparse.ArgumentDefaultsHelpFormatter):
    """Show defaults, except None and those of flags, whose help says what happens."""

    def _get_help_string(self, action):
        if action.default is None or action.nargs == 0:  # flags: their help says it
            return action.help
        return super()._get_help_string(action)


class Command(NamedTuple):
    """One subcommand: its name, the function that runs it (``run(args, progress)``
    returns the summary), the function that adds its arguments to its subparser, and its
    help (and description) texts."""

    name: str
    run: Callable
    add_arguments: Callable[[argparse.ArgumentParser], None]
    help: str
    description: str | None = None
