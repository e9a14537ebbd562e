"""The argument parser: one subcommand per command, each with its documented defaults."""

from __future__ import annotations

import argparse
import os
import pathlib
import re

from .._options import INITS, METHODS, SCHEMES, SHOOTING_SCHEMES, SOLVERS
from .._version import VERSION
from .common import DEFAULT_METRIC, SHAPE_DEFAULTS, SURFACE_FILE, SURFACE_FILES


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


def _io_options(parser: argparse.ArgumentParser) -> None:
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


def _input_options(parser: argparse.ArgumentParser) -> None:
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


def _common(
    parser: argparse.ArgumentParser,
    *,
    degree: int,
    times: int,
    max_steps: int | None = None,
    max_steps_help: str = "solver step limit (library default)",
) -> None:
    _io_options(parser)
    parser.add_argument(
        "--degree", type=int, default=degree, help="spherical-harmonic degree of the path"
    )
    parser.add_argument("--times", type=int, default=times, help="time points N, ends included")
    parser.add_argument(
        "--solver",
        choices=SOLVERS,
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


def _shape_options(
    parser: argparse.ArgumentParser,
    *,
    modulo: str,
    inner: str = "",
    moduli: tuple[str, ...] = ("diff", "rigid"),
) -> None:
    """The options of shape geodesics (one ShapeOptions record; the library's defaults)."""
    d = SHAPE_DEFAULTS
    _common(
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
        choices=SCHEMES,
        default=d.scheme,
        help="time discretization of the path energy (see ShapeOptions)",
    )
    parser.add_argument(
        "--method",
        choices=METHODS,
        default=d.method,
        help="registration: paper Algorithm 2 (joint) or alternating (coordinate)",
    )
    parser.add_argument("--vf-degree", type=int, default=d.vf_degree, help="Diff(S^2) basis degree")
    parser.add_argument(
        "--outer-steps", type=int, default=d.outer_steps, help="most registration rounds"
    )
    parser.add_argument("--init", choices=INITS, default=d.init, help="initial registration search")
    parser.add_argument(
        "--no-refinement",
        dest="refinement",
        action="store_false",
        help="skip re-evaluating each distance at halved time steps and on a finer grid",
    )


def _batch_options(parser: argparse.ArgumentParser) -> None:
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


def _rtol_option(parser: argparse.ArgumentParser, what: str) -> None:
    parser.add_argument(
        "--rtol",
        type=_rtol,
        default=SHAPE_DEFAULTS.rtol,
        help=f"{what}: working grids 13 x 25 ... 97 x 193 until two levels' distances agree "
        "within this; 'none': one working grid, the inputs'",
    )


def _karcher_options(parser: argparse.ArgumentParser) -> None:
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


class _DefaultsShown(argparse.ArgumentDefaultsHelpFormatter):
    """Show defaults, except None and those of flags, whose help says what happens."""

    def _get_help_string(self, action):
        if action.default is None or action.nargs == 0:  # flags: their help says it
            return action.help
        return super()._get_help_string(action)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="elastic-jax",
        description="Elastic shape analysis of spherical surfaces (split metrics, Su et al. 2020).",
        epilog="Exit codes: 0 ok, 2 bad input, 3 not converged, 130 interrupted, 143 terminated.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {VERSION}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    add = sub.add_parser

    def command(name: str, **kwargs) -> argparse.ArgumentParser:
        return add(name, formatter_class=_DefaultsShown, **kwargs)

    p = command("geodesic", help="geodesic between two parametrized surfaces")
    p.add_argument("source", help=SURFACE_FILE)
    p.add_argument("target", help=SURFACE_FILE)
    _common(p, degree=7, times=13)
    _input_options(p)

    p = command("shape-geodesic", help="geodesic between shapes (registration)")
    p.add_argument("source", help=SURFACE_FILE)
    p.add_argument("target", help=SURFACE_FILE)
    _shape_options(p, modulo="diff")
    _rtol_option(p, "a resolved distance")
    _input_options(p)
    p.add_argument(
        "--on-target-mesh",
        action="store_true",
        help="also write the path's frames as meshes with the target mesh's faces, each "
        "frame read at the target's vertices through the map that brought it in "
        "(io.VertexMap): path/target_mesh_NNN.ply, the last one the target's own vertices "
        "(rotated and centred under --modulo rigid) to the grid's resolution; the path "
        "starts at the source reparametrized onto the target, so this paints the "
        "deformation on the target's mesh (a mesh target only)",
    )

    p = command(
        "karcher",
        help="Karcher mean of a collection of shapes",
        description="The Karcher mean of the shapes modulo rigid motions (or "
        "reparametrizations only), checkpointed after every step (--resume continues). "
        "Writes mean.npz (the mean, its distances, the velocities at the mean and the "
        "settings: the pca command's input), mean.ply, mean.png and history.png.",
    )
    p.add_argument("files", nargs="+", help=SURFACE_FILES)
    _shape_options(p, modulo="rigid", inner="; the Karcher steps are --karcher-steps")
    _input_options(p)
    _rtol_option(
        p,
        "a resolved mean: each shape's first geodesic by levels, the mean then kept on the "
        "finest grid any shape needed",
    )
    _batch_options(p)
    _karcher_options(p)

    p = command("distances", help="matrix of pairwise shape distances")
    p.add_argument("files", nargs="+", help=SURFACE_FILES)
    _shape_options(p, modulo="rigid")
    _input_options(p)
    _rtol_option(p, "each pair's resolved distance")
    _batch_options(p)

    p = command(
        "fit-metric",
        help="learn the metric's coefficients from labelled shapes (or target distances)",
        description="Fit the split metric's coefficients (a, b, c, d) to the shapes' class "
        "labels (soft nearest neighbours) or to a matrix of target dissimilarities "
        "(elastic_jax.fit_metric), starting from --metric; a + b + c + d = 1 in the result. "
        "With --test and --test-labels, also scores the start and the fitted metric on those "
        "held-out shapes (nearest neighbour, first and second tier). Writes summary.json "
        "and fit_metric.npz (the coefficients, the distance matrices, the history).",
    )
    p.add_argument("files", nargs="+", help=SURFACE_FILES)
    data = p.add_mutually_exclusive_group(required=True)
    data.add_argument(
        "--labels",
        default=None,
        help="text file: one class label per line in the files' order, or lines name,label",
    )
    data.add_argument(
        "--targets", default=None, help="(K, K) dissimilarities: .npy, .npz, .csv or text"
    )
    _shape_options(p, modulo="rigid", moduli=("rigid", "diff", "none"))
    _input_options(p)
    _rtol_option(p, "each pair's resolved distance at the first solve (the steps continue it)")
    _batch_options(p)
    p.add_argument("--learn", default="abc", help="the coefficients that move (of abcd)")
    p.add_argument(
        "--temperature",
        type=float,
        default=0.1,
        help="softness of the soft nearest neighbours (squared mean distances)",
    )
    p.add_argument(
        "--fit-steps",
        type=int,
        default=30,
        help="most trust region steps (each solves every pair once)",
    )
    p.add_argument(
        "--fit-tol",
        type=float,
        default=1e-3,
        help="the fit converges when its gradient norm is at most this",
    )
    p.add_argument(
        "--test",
        nargs="+",
        default=None,
        metavar="FILE",
        help="held-out surface files to score the metrics on",
    )
    p.add_argument("--test-labels", default=None, help="their labels (as --labels)")

    p = command(
        "pca",
        help="Karcher mean, tangent PCA and mode paths of a collection of shapes",
        description="The Karcher mean of the shapes (as the karcher command), the metric "
        "PCA of their velocities at the mean (tangent_pca) and the geodesics through the "
        "mean along the first modes (mode_path). Writes the mean and each mode's +-sigma "
        "shapes as meshes, each mode's one-sigma velocity (modeK_velocity.npz, for the "
        "shoot command), pca.npz, scores.json and a figure (modes.png). Given a karcher "
        "run's mean.npz as its only input, it starts from that mean and its velocities, "
        "with that run's metric and options, and solves no geodesic.",
    )
    p.add_argument("files", nargs="+", help=SURFACE_FILES + "; or one karcher run's mean.npz")
    _shape_options(p, modulo="rigid", inner="; the Karcher steps are --karcher-steps")
    _input_options(p)
    _rtol_option(
        p,
        "a resolved mean: each shape's first geodesic by levels, the mean then kept on the "
        "finest grid any shape needed",
    )
    _batch_options(p)
    _karcher_options(p)
    p.add_argument("--modes", type=int, default=3, help="modes to keep (at most shapes - 1)")
    p.add_argument(
        "--sigmas", type=float, default=2.0, help="mode paths reach +-sigmas standard deviations"
    )
    p.add_argument(
        "--mode-times",
        type=int,
        default=7,
        help="time points of each half of a mode path (mean to +-sigmas)",
    )

    p = command(
        "shoot",
        help="geodesic from a surface with an initial velocity (exponential map)",
        description="Shoot the discrete geodesic from the source surface with initial "
        "velocity --scale times the velocity file's (elastic_jax.shoot). Writes the path "
        "(path/: a mesh per time point and path.npz), shoot.npz (endpoint, final "
        "velocity, speeds, residuals) and a figure.",
    )
    p.add_argument("source", help=SURFACE_FILE)
    p.add_argument(
        "velocity",
        help="the initial velocity: .npz with array v (or velocity) of the surface's shape "
        "(3, m, n), e.g. the pca command's modeK_velocity.npz",
    )
    _io_options(p)
    _input_options(p)
    p.add_argument(
        "--degree", type=int, default=7, help="spherical-harmonic degree of each step's solve"
    )
    p.add_argument("--times", type=int, default=13, help="time points N, ends included")
    p.add_argument("--scale", type=float, default=1.0, help="multiplies the velocity")
    p.add_argument(
        "--scheme",
        choices=SHOOTING_SCHEMES,
        default="midpoint",
        help="time discretization of the path energy (central cannot be shot)",
    )
    p.add_argument(
        "--tol",
        type=float,
        default=None,
        help="each step's Newton tolerance (default: 1e-10 in float64, 1e-4 in float32)",
    )
    p.add_argument("--max-newton", type=int, default=20, help="Newton iterations per step")

    p = command(
        "warmup",
        help="compile a batch job's shape solves into the cache ahead of it",
        description="Solves a built-in pair with the job's shape options on every working "
        "grid (each level of --rtol), so that the compilation cache (--cache-dir) holds "
        "every program the job's shape geodesics, distances and resolved Karcher means run "
        "for inputs on --grid (default 50 99): later runs load them instead of compiling.",
    )
    _shape_options(p, modulo="diff", moduli=("diff", "rigid", "both"))
    _rtol_option(p, "the job's resolved distances")

    p = command("demo", help="a geodesic between two built-in surfaces, with figures")
    _common(p, degree=7, times=10)

    p = command("bench", help="time the energy gradient and a geodesic solve (JSON)")
    _common(p, degree=7, times=13)
    p.add_argument("--repeat", type=int, default=3, help="timed calls after the first")
    return parser
