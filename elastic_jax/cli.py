"""The ``elastic-jax`` command line: geodesics, shape geodesics, Karcher means, distances.

Every command reads surfaces (``.npz`` with array ``f``, the authors' ``.mat``, or any mesh
trimesh reads, resampled by :func:`elastic_jax.io.mesh_to_grid`), computes, and writes into
``--out DIR``: the arrays (``.npz``), meshes (``.ply``), figures (``.png``) and
``summary.json``. The summary is also printed on stdout. All files are written atomically,
so Ctrl-C never leaves half a file; ``karcher`` and ``distances`` checkpoint every finished
step or chunk and continue with ``--resume``. A directory among the inputs stands for the
surface files in it. The statistics run in two commands: ``karcher`` writes ``mean.npz``
(the mean, the velocities at it, the settings) and ``pca`` on that file computes the modes
and their figure without solving again.

Exit codes: 0 done and converged; 2 bad input (unreadable file, invalid surface or mesh,
bad option, an --out that is not a writable directory or that another run holds, a
checkpoint there without --resume or --overwrite), reported in one line before any work;
3 finished but the solver did not converge (results are still written); 130 interrupted
(Ctrl-C), 143 terminated (SIGTERM), both leaving only complete files; 1 anything else
(a bug: please report it).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import pathlib
import platform
import signal
import sys
import tempfile
import time
import warnings
from collections.abc import Callable, Sequence

from ._atomic import TEMPORARY, stale_temporaries
from ._checks import check_grid_shape, check_int, check_positive
from ._errors import InputError
from ._options import INITS, METHODS, SCHEMES, SHOOTING_SCHEMES, SOLVERS, ShapeOptions

EXIT_OK, EXIT_FAILURE, EXIT_BAD_INPUT, EXIT_NOT_CONVERGED = 0, 1, 2, 3
EXIT_INTERRUPTED, EXIT_TERMINATED = 130, 143  # 128 + SIGINT, 128 + SIGTERM
LOCK_NAME = ".elastic-jax.lock"
CHECKPOINTS = {
    "karcher": "karcher_checkpoint.npz",
    "pca": "karcher_checkpoint.npz",
    "distances": "distances_checkpoint.npz",
}
DEFAULT_METRIC = (1.0, 1.0, 0.1, 0.0)
SURFACE_FILE = "a surface: .npz (array f), .mat (the authors'), or a mesh trimesh reads"
SURFACE_FILES = SURFACE_FILE.replace("a surface", "surfaces") + ", or a directory of them"
# What pca reads from a karcher run's mean.npz instead of solving the mean again.
KARCHER_OUTPUT_KEYS = ("f", "velocities", "distances", "settings", "inputs", "result", "converged")
SHAPE_COMMANDS = ("shape-geodesic", "karcher", "pca", "distances")
_SHAPE_DEFAULTS = ShapeOptions()
# ShapeOptions field -> (argparse destination, flag): one record is built from these.
SHAPE_FLAGS = {
    "degree": ("degree", "--degree"),
    "n_times": ("times", "--times"),
    "solver": ("solver", "--solver"),
    "max_steps": ("max_steps", "--max-steps"),
    "scheme": ("scheme", "--scheme"),
    "method": ("method", "--method"),
    "vf_degree": ("vf_degree", "--vf-degree"),
    "outer_steps": ("outer_steps", "--outer-steps"),
    "init": ("init", "--init"),
    "refinement": ("refinement", "--no-refinement"),
}
# Flags that pca on a karcher output takes from that run: giving them is refused.
KARCHER_OWN_FLAGS = {
    **{dest: flag for dest, flag in SHAPE_FLAGS.values()},
    **{
        dest: "--" + dest.replace("_", "-")
        for dest in ("metric", "grid", "dtype", "modulo", "strategy", "batch_size", "workers")
        + ("scheduler", "resume", "karcher_steps", "tol", "step_size", "warm_start")
    },
}


class BadInput(InputError):
    """An input the command cannot use; reported in one line with exit code 2."""


class Progress:
    """One line per stage on stderr, with the time since the command started."""

    def __init__(self, quiet: bool):
        self.quiet = quiet
        self.start = time.perf_counter()

    def elapsed(self) -> float:
        return time.perf_counter() - self.start

    def __call__(self, message: str) -> None:
        if not self.quiet:
            print(f"[{self.elapsed():7.1f} s] {message}", file=sys.stderr, flush=True)


# --------------------------------------------------------------------------- arguments


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


def _shape_options(parser: argparse.ArgumentParser, *, modulo: str, inner: str = "") -> None:
    """The options of shape geodesics (one ShapeOptions record; the library's defaults)."""
    d = _SHAPE_DEFAULTS
    _common(
        parser,
        degree=d.degree,
        times=d.n_times,
        max_steps=d.max_steps,
        max_steps_help=f"step limit of each inner solve (solver steps){inner}",
    )
    parser.add_argument(
        "--modulo",
        choices=("diff", "rigid"),
        default=modulo,
        help="reparametrizations, or reparametrizations and rigid motions",
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
        help="Karcher convergence: |mean velocity| <= tol x RMS distance, or a full step "
        "lowers the sum of squared distances by less than tol (relative)",
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
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    add = sub.add_parser

    def command(name: str, **kwargs) -> argparse.ArgumentParser:
        return add(name, formatter_class=_DefaultsShown, **kwargs)

    p = command("geodesic", help="geodesic between two parametrized surfaces")
    p.add_argument("source", help=SURFACE_FILE)
    p.add_argument("target", help=SURFACE_FILE)
    _common(p, degree=7, times=13)

    p = command("shape-geodesic", help="geodesic between shapes (registration)")
    p.add_argument("source", help=SURFACE_FILE)
    p.add_argument("target", help=SURFACE_FILE)
    _shape_options(p, modulo="diff")

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
    _batch_options(p)
    _karcher_options(p)

    p = command("distances", help="matrix of pairwise shape distances")
    p.add_argument("files", nargs="+", help=SURFACE_FILES)
    _shape_options(p, modulo="rigid")
    _batch_options(p)

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

    p = command("demo", help="a geodesic between two built-in surfaces, with figures")
    _common(p, degree=7, times=10)

    p = command("bench", help="time the energy gradient and a geodesic solve (JSON)")
    _common(p, degree=7, times=13)
    p.add_argument("--repeat", type=int, default=3, help="timed calls after the first")
    return parser


# --------------------------------------------------------------------------- helpers


def _environment() -> dict:
    import jax

    return {
        "python": platform.python_version(),
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "devices": [str(d) for d in jax.devices()],
    }


def _load_all(files: Sequence[str], grid, dtype, progress: Progress):
    """Surfaces as one (K, 3, m, n) array on a common grid; BadInput names the file."""
    import numpy as np

    from . import io

    out = []
    m, n = (None, None) if grid is None else grid
    for name in files:
        progress(f"reading {name}")
        try:
            f = io.load_surface(name, m=m, n=n, progress=progress)
        except (InputError, KeyError) as err:  # their messages name the file
            raise BadInput(err.args[0] if err.args else str(err)) from err
        except (OSError, ValueError) as err:
            raise BadInput(f"{name}: {err}") from err
        except Exception as err:  # a file trimesh or scipy cannot parse is still bad input
            raise BadInput(f"{name}: cannot be read ({type(err).__name__}: {err})") from err
        if m is None:
            m, n = f.shape[1:]
        out.append(f)
    return np.stack(out).astype(dtype)


def _metric_from(args):
    from ._metric import SplitMetric

    try:
        return SplitMetric(*args.metric)
    except ValueError as err:
        raise BadInput(str(err)) from err


def _check_degrees(args, m: int, n: int) -> None:
    from ._harmonics import check_degree

    for name in ("degree", "vf_degree"):
        value = getattr(args, name, None)
        if value is not None:
            try:
                check_degree(value, m, n, name)
            except ValueError as err:
                raise BadInput(f"--{name.replace('_', '-')} {value}: {err}") from err


def _geodesic_options(args) -> dict:
    options = {"degree": args.degree, "n_times": args.times, "solver": args.solver}
    if args.max_steps is not None:
        options["max_steps"] = args.max_steps
    return options


def shape_options_from(args) -> ShapeOptions:
    """One validated ShapeOptions from the shape commands' arguments.

    A bad value is BadInput naming the flag, e.g. ``--times 2: n_times must be ...``.
    """
    values = {field: getattr(args, dest) for field, (dest, _) in SHAPE_FLAGS.items()}
    try:
        return ShapeOptions(**values)
    except ValueError as err:
        field = str(err).split()[0]
        flag = SHAPE_FLAGS.get(field, (field, f"--{field}"))[1]
        raise BadInput(f"{flag} {values.get(field)}: {err}") from err


def _shape_geodesic_options(args) -> ShapeOptions:
    return args.shape_options


def _json_safe(value):
    """``value`` with every non-finite float (not JSON) replaced by None, recursively."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    return value


def _write_summary(out: pathlib.Path, summary: dict) -> None:
    from ._atomic import write_text_atomic

    target = out / "summary.json"
    summary["files"] = sorted({*summary.get("files", []), str(target)})
    # A failed solve's NaN becomes null: the file stays valid JSON (allow_nan=False).
    text = json.dumps(_json_safe(summary), indent=2, allow_nan=False)
    write_text_atomic(target, text + "\n")
    print(text)


def _figure(target: pathlib.Path, make: Callable, progress: Progress) -> list[str]:
    """``[target]`` after drawing ``make()`` into it; ``[]`` (and a progress line) when
    the data cannot be drawn: a failed solve's NaN is reported in the summary, not as
    bad input."""
    from . import plot

    try:
        fig = make()
    except InputError as err:
        progress(f"{target.name} not drawn: {_one_line(err)}")
        return []
    return [str(plot.save_figure(fig, target))]


def _write_path(out: pathlib.Path, path, settings: dict, progress: Progress) -> list[str]:
    import numpy as np

    from . import io, plot

    if not np.isfinite(path).all():
        progress("the path is not finite: no meshes and no figure written")
        return []
    progress(f"writing the path's {path.shape[0]} meshes and its figure to {out}")
    written = [str(p) for p in io.save_path(path, out / "path", settings=settings)]
    return written + _figure(out / "path.png", lambda: plot.plot_path(path), progress)


# --------------------------------------------------------------------------- commands


def _prepare(args, progress: Progress, files, options_of: Callable, surfaces=None):
    """The surfaces ``(K, 3, m, n)`` (read unless given), checked degrees, metric, options."""
    if surfaces is None:
        surfaces = _load_all(files, args.grid, args.dtype, progress)
    _check_degrees(args, *surfaces.shape[-2:])
    return surfaces, _metric_from(args), options_of(args)


def _run_geodesic(args, progress: Progress, surfaces=None, label=None) -> dict:
    import jax
    import numpy as np

    from ._geodesic import geodesic

    files = [args.source, args.target] if surfaces is None else []
    (f1, f2), metric, options = _prepare(args, progress, files, _geodesic_options, surfaces)
    m, n = f1.shape[1:]
    progress(
        f"solving the geodesic on {m} x {n}, degree {args.degree}, N = {args.times} "
        "(the first call compiles)"
    )
    start = time.perf_counter()
    res = jax.block_until_ready(geodesic(f1, f2, metric, **options))
    seconds = time.perf_counter() - start
    progress(f"distance {float(res.distance):.6g} after {int(res.num_steps)} steps")
    settings = {"metric": list(args.metric), "grid": [m, n], **options, "dtype": args.dtype}
    summary = {
        "command": args.command,
        "inputs": label or [args.source, args.target],
        "settings": settings,
        "distance": float(res.distance),
        "energy": float(res.energy),
        "straight_energy": float(res.straight_energy),
        "num_steps": int(res.num_steps),
        "converged": bool(res.converged),
        "message": res.message,
        "grad_norm": float(res.grad_norm),
        "seconds": seconds,
        "environment": _environment(),
    }
    summary["files"] = _write_path(args.out, np.asarray(res.path), settings, progress)
    return summary


def _run_shape_geodesic(args, progress: Progress) -> dict:
    import jax
    import numpy as np

    from . import plot
    from ._atomic import save_npz_atomic
    from ._shape import shape_geodesic

    files = [args.source, args.target]
    (f1, f2), metric, options = _prepare(args, progress, files, _shape_geodesic_options)
    m, n = f1.shape[1:]
    progress(
        f"registering and solving modulo {args.modulo} on {m} x {n}, "
        f"at most {options.outer_steps} registration rounds (the first call compiles)"
    )
    start = time.perf_counter()
    res = jax.block_until_ready(shape_geodesic(f1, f2, metric, modulo=args.modulo, options=options))
    seconds = time.perf_counter() - start
    progress(
        f"shape distance {float(res.distance):.6g} "
        f"(parametrized {float(res.parametrized_distance):.6g}) "
        f"after {int(res.rounds)} rounds"
    )
    settings = {
        "metric": list(args.metric),
        "grid": [m, n],
        "modulo": args.modulo,
        **options.as_dict(),
        "dtype": args.dtype,
    }
    files = _write_path(args.out, np.asarray(res.path), settings, progress)
    files.append(
        str(
            save_npz_atomic(
                args.out / "registration.npz",
                gamma=np.asarray(res.gamma),
                rotation=np.asarray(res.rotation),
                f1_registered=np.asarray(res.f1_registered),
                energy_history=np.asarray(res.energy_history),
            )
        )
    )
    history = np.asarray(res.energy_history)
    # Rounds not taken are NaN in the record; the figure shows the rounds taken.
    energies = {"path energy": history[np.isfinite(history)]}
    files += _figure(args.out / "energy.png", lambda: plot.plot_energy(energies), progress)
    return {
        "command": args.command,
        "inputs": [args.source, args.target],
        "settings": settings,
        "distance": float(res.distance),
        "parametrized_distance": float(res.parametrized_distance),
        "energy": float(res.energy),
        "energy_history": _json_floats(res.energy_history),
        "rounds": int(res.rounds),
        "num_steps": int(res.num_steps),
        "converged": bool(res.converged),
        "result": "converged" if bool(res.converged) else res.message,
        "message": res.message,
        "grad_norm": float(res.grad_norm),
        "refinement": {
            "distance_time": _json_float(res.refinement.distance_time),
            "distance_grid": _json_float(res.refinement.distance_grid),
            "relative_change": _json_float(res.refinement.relative_change),
        },
        "seconds": seconds,
        "files": files,
        "environment": _environment(),
    }


def _json_float(x) -> float | None:
    """A float for JSON; NaN and inf (not JSON) become null."""

    x = float(x)
    return x if math.isfinite(x) else None


def _json_floats(values) -> list:
    """Nested lists of floats for JSON, NaN and inf as null."""
    import numpy as np

    values = np.asarray(values)
    if values.ndim == 0:
        return _json_float(values)
    return [_json_floats(v) for v in values]


def _collection_settings(args, m: int, n: int, options: ShapeOptions) -> dict:
    return {
        "metric": list(args.metric),
        "grid": [m, n],
        "modulo": args.modulo,
        "strategy": args.strategy,
        "batch_size": args.batch_size,
        **options.as_dict(),
        "dtype": args.dtype,
    }


def _karcher(args, progress: Progress):
    """The Karcher mean of ``args.files`` with its files and summary: (result, metric,
    options, summary), the summary holding ``files`` already written."""
    import numpy as np

    from . import io, plot
    from ._atomic import save_npz_atomic
    from ._karcher import karcher_mean

    shapes, metric, options = _prepare(args, progress, args.files, _shape_geodesic_options)
    m, n = shapes.shape[2:]
    settings = _collection_settings(args, m, n, options)
    settings.update(
        karcher_steps=args.karcher_steps,
        tol=args.tol,
        step_size=args.step_size,
        warm_start=args.warm_start,
    )
    checkpoint = args.out / CHECKPOINTS["karcher"]

    def report(info):
        # The pace so far (step 0: the first solves, compilation included) times the
        # steps left: the most the run can still take at that pace; it stops earlier
        # when it converges.
        pace = info["seconds"] / max(info["step"], 1)
        left = args.karcher_steps - info["step"]
        eta = f"; at most ~{left * pace:.0f} s left ({left} steps at {pace:.0f} s)" if left else ""
        progress(
            f"Karcher step {info['step']}/{args.karcher_steps}: sum of squared distances "
            f"{info['sum_sq_distances']:.6g}, mean velocity {info['mean_velocity_norm']:.3g}, "
            f"step {info['step_size']:g}{eta} (checkpoint {checkpoint.name})"
        )

    progress(
        f"Karcher mean of {len(args.files)} shapes modulo {args.modulo} on {m} x {n} "
        f"(each step solves {len(args.files)} geodesics; the first compiles)"
    )
    start = time.perf_counter()
    res = karcher_mean(
        shapes,
        metric,
        modulo=args.modulo,
        options=options,
        max_steps=args.karcher_steps,
        tol=args.tol,
        step_size=args.step_size,
        batch_size=args.batch_size,
        strategy=args.strategy,
        checkpoint=checkpoint,
        resume=args.resume,
        progress=report,
        client=args.client,
        warm_start=args.warm_start,
    )
    seconds = time.perf_counter() - start
    mean = np.asarray(res.mean)
    files = [
        str(
            save_npz_atomic(
                args.out / "mean.npz",
                f=mean,
                distances=np.asarray(res.distances),
                registered=np.asarray(res.registered),
                velocities=np.asarray(res.velocities),
                geodesics_converged=np.asarray(res.geodesics_converged),
                history=np.asarray(res.history),
                result=res.result,
                converged=bool(res.converged),
                inputs=json.dumps(list(args.files)),
                settings=json.dumps(settings),
            )
        )
    ]
    if np.isfinite(mean).all():
        files.append(str(io.save_surface(mean, args.out / "mean.ply")))
    files += _figure(args.out / "mean.png", lambda: plot.plot_path(mean), progress)
    history = np.asarray(res.history)
    columns = {"sum of squared distances": history[:, 0], "mean velocity norm": history[:, 1]}
    files += _figure(args.out / "history.png", lambda: plot.plot_energy(columns), progress)
    summary = {
        "command": args.command,
        "inputs": list(args.files),
        "settings": settings,
        "distances": [float(d) for d in np.asarray(res.distances)],
        "sum_sq_distances": float(np.sum(np.asarray(res.distances) ** 2)),
        "history": {
            "sum_sq_distances": _json_floats(history[:, 0]),
            "mean_velocity_norm": _json_floats(history[:, 1]),
            "step_size": _json_floats(history[:, 2]),
        },
        "num_steps": int(res.num_steps),
        "num_solves": int(res.num_solves),
        "converged": bool(res.converged),
        "result": res.result,
        "message": res.message,
        "geodesics_converged": [bool(c) for c in np.asarray(res.geodesics_converged)],
        "seconds": seconds,
        "files": files,
        "environment": _environment(),
    }
    return res, metric, options, summary


def _run_karcher(args, progress: Progress) -> dict:
    return _karcher(args, progress)[-1]


def _run_pca(args, progress: Progress) -> dict:
    import numpy as np

    from . import io, plot
    from ._atomic import save_npz_atomic, write_text_atomic
    from ._errors import ConvergenceWarning
    from ._pca import mode_path, tangent_pca

    if args.karcher_output is None:
        karcher, metric, options, summary = _karcher(args, progress)
        mean, velocities = np.asarray(karcher.mean), np.asarray(karcher.velocities)
        distances, karcher_converged = np.asarray(karcher.distances), bool(karcher.converged)
        inputs = list(args.files)
    else:
        saved = args.karcher_output
        metric, options = _metric_from(args), args.shape_options
        mean, velocities = saved["f"].astype(args.dtype), saved["velocities"].astype(args.dtype)
        distances, inputs = saved["distances"], saved["inputs"]
        karcher_converged = bool(saved["converged"])
        progress(
            f"the Karcher mean of {len(inputs)} shapes from {args.files[0]} "
            f"({saved['result']}); its metric and options"
        )
        summary = {
            "command": args.command,
            "inputs": list(args.files),
            "karcher_inputs": inputs,
            "settings": dict(saved["settings"]),
            "karcher_result": str(saved["result"]),
            "converged": karcher_converged,
            "files": [],
            "environment": _environment(),
        }
    files = summary["files"]
    if not np.isfinite(velocities).all():
        # Nothing to analyse; the Karcher part of the summary says what failed.
        progress("the velocities at the mean are not finite: no PCA")
        summary.update(converged=False, pca=None)
        return summary
    k = len(inputs)
    n_modes = min(args.modes, k - 1)
    if n_modes < args.modes:
        progress(f"{k} shapes span at most {k - 1} modes: keeping {n_modes}")
    # Modes whose variance is at round-off (tangent_pca's rtol) are not modes: fewer kept.
    # The kept ones are the leading ones of the full decomposition (explained is already
    # relative to the total variance).
    full = tangent_pca((mean, velocities), metric)
    n_modes = min(n_modes, int(full.modes.shape[0]))
    pca = full._replace(
        modes=full.modes[:n_modes],
        variances=full.variances[:n_modes],
        explained=full.explained[:n_modes],
        scores=full.scores[:, :n_modes],
    )
    explained = np.asarray(pca.explained)
    progress("explained variance by mode: " + ", ".join(f"{100 * e:.1f} %" for e in explained))
    # Shot with the scheme of the mean's geodesics (central is refused by _preflight).
    shoot_options = {"n_times": args.mode_times, "degree": options.degree, "scheme": options.scheme}
    paths, unconverged = [], []
    for mode in range(n_modes):
        progress(f"mode {mode + 1}: shooting +-{args.sigmas:g} sigma from the mean")
        # mode_path returns the path only; a failed Newton step shows as its warning.
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", ConvergenceWarning)
            path = mode_path(pca, mode, metric, sigmas=args.sigmas, **shoot_options)
        paths.append(np.asarray(path))
        if any(issubclass(w.category, ConvergenceWarning) for w in caught):
            progress(f"mode {mode + 1}: a shooting step did not converge")
            unconverged.append(mode + 1)
    paths = np.stack(paths)
    sigma = np.sqrt(np.asarray(pca.variances))
    reached = []
    for mode, path in enumerate(paths, start=1):
        files.append(
            str(
                save_npz_atomic(
                    args.out / f"mode{mode}_velocity.npz",
                    v=sigma[mode - 1] * np.asarray(pca.modes[mode - 1]),
                    f=mean,
                )
            )
        )
        # Each half is a shot from the mean (frame c): a failed step leaves the frames
        # beyond it NaN, so the solved ones are a run of frames around the centre.
        solved = np.isfinite(path).all(axis=(1, 2, 3))
        c = (len(path) - 1) // 2
        down = int(np.argmin([*solved[c::-1], False]))  # solved frames from c down
        up = int(np.argmin([*solved[c:], False]))
        first, last = c - down + 1, c + up - 1
        reached.append([args.sigmas * (first - c) / c, args.sigmas * (last - c) / c])
        if solved.all():
            for end, name in ((path[0], "minus"), (path[-1], "plus")):
                files.append(str(io.save_surface(end, args.out / f"mode{mode}_{name}.ply")))
        else:
            progress(
                f"mode {mode}: the shots reached {reached[-1][0]:+.3g} and {reached[-1][1]:+.3g} "
                "sigma (a Newton step failed beyond); no meshes written for it"
            )
    files.append(
        str(
            save_npz_atomic(
                args.out / "pca.npz",
                mean=mean,
                modes=np.asarray(pca.modes),
                variances=np.asarray(pca.variances),
                explained=explained,
                scores=np.asarray(pca.scores),
                mean_velocity=np.asarray(pca.mean_velocity),
                mode_paths=paths,
                settings=json.dumps(summary["settings"]),
            )
        )
    )
    names = [pathlib.Path(f).stem for f in inputs]
    scores = {
        "files": inputs,
        "modes": n_modes,
        "sigmas": args.sigmas,
        "variances": _json_floats(pca.variances),
        "explained": _json_floats(explained),
        "scores": {
            name: _json_floats(row) for name, row in zip(names, np.asarray(pca.scores), strict=True)
        },
    }
    text = json.dumps(_json_safe(scores), indent=2, allow_nan=False)
    files.append(str(write_text_atomic(args.out / "scores.json", text + "\n")))
    files += _figure(
        args.out / "modes.png",
        lambda: plot.plot_modes(paths, modes=len(paths), explained=explained, sigmas=args.sigmas),
        progress,
    )
    summary["settings"].update(modes=n_modes, sigmas=args.sigmas, mode_times=args.mode_times)
    summary["pca"] = {
        "variances": _json_floats(pca.variances),
        "explained": _json_floats(explained),
        # All modes' variance against the mean squared distance: equal when every
        # velocity's G-norm is its distance and the mean velocity vanishes.
        "total_variance": float(np.sum(np.asarray(full.variances))),
        "mean_sq_distance": float(np.mean(np.asarray(distances) ** 2)),
        "mode_paths_unconverged": unconverged,
        # Per mode, the sigmas the solved nodes span: [-sigmas, +sigmas] when converged.
        "mode_paths_reached_sigmas": reached,
        "scores": scores["scores"],
    }
    summary["converged"] = karcher_converged and not unconverged
    return summary


def _load_velocity(name: str, shape: tuple, dtype: str):
    """The array ``v`` (or ``velocity``) of an .npz, checked against the surface's shape."""
    import numpy as np

    try:
        with np.load(name) as data:
            arrays = {k: np.asarray(data[k]) for k in ("v", "velocity") if k in data.files}
            found = ", ".join(data.files) or "none"
    except (OSError, ValueError) as err:
        raise BadInput(f"{name}: not a readable .npz ({err})") from err
    if not arrays:
        raise BadInput(f"{name}: no array v or velocity in it (it has {found})")
    v = arrays.get("v", arrays.get("velocity"))
    if v.shape != shape:
        raise BadInput(
            f"{name}: the velocity has shape {v.shape}, the surface {shape}; a velocity "
            "lives on its surface's grid (resampling one would change what it means)"
        )
    if not np.issubdtype(v.dtype, np.floating) or not np.isfinite(v).all():
        raise BadInput(f"{name}: the velocity must be finite real numbers")
    return v.astype(dtype)


def _run_shoot(args, progress: Progress) -> dict:
    import jax
    import numpy as np

    from ._atomic import save_npz_atomic
    from ._shooting import shoot

    (f,), metric, _ = _prepare(args, progress, [args.source], lambda a: None)
    m, n = f.shape[1:]
    v = args.scale * _load_velocity(args.velocity, f.shape, args.dtype)
    options = {"n_times": args.times, "degree": args.degree, "scheme": args.scheme}
    options.update(tol=args.tol, max_newton=args.max_newton)
    progress(
        f"shooting on {m} x {n}, degree {args.degree}, N = {args.times} "
        "(one Newton solve per step; the first call compiles)"
    )
    start = time.perf_counter()
    res = jax.block_until_ready(shoot(f, v, metric, **options))
    seconds = time.perf_counter() - start
    speeds = np.asarray(res.speeds)
    residuals = np.asarray(res.residuals)
    n_valid = int(res.n_valid)
    progress(
        f"speed {speeds[0]:.6g} -> {speeds[-1]:.6g}, largest step residual "
        f"{np.nanmax(residuals):.3g}, converged {bool(res.converged)}"
    )
    settings = {
        "metric": list(args.metric),
        "grid": [m, n],
        "scale": args.scale,
        **options,
        "dtype": args.dtype,
    }
    path = np.asarray(res.path)
    if n_valid < path.shape[0]:
        last = path.shape[0] - 1
        progress(f"nodes {n_valid}..{last} did not solve: writing nodes 0..{n_valid - 1}")
    files = _write_path(args.out, path[:n_valid], settings, progress)
    files.append(
        str(
            save_npz_atomic(
                args.out / "shoot.npz",
                n_valid=n_valid,
                endpoint=path[-1],
                velocity=np.asarray(res.velocity),
                speeds=speeds,
                residuals=residuals,
                newton_steps=np.asarray(res.newton_steps),
                settings=json.dumps(settings),
            )
        )
    )
    return {
        "command": args.command,
        "inputs": [args.source, args.velocity],
        "settings": settings,
        # The path's length: the sum of its steps' speeds over T (constant on a geodesic).
        "length": _json_float(np.mean(speeds)),
        "n_valid": n_valid,
        "speeds": _json_floats(speeds),
        "speed_drift": _json_float(speeds[-1] / speeds[0] - 1) if speeds[0] > 0 else None,
        "residuals": _json_floats(residuals),
        "newton_steps": [int(x) for x in np.asarray(res.newton_steps)],
        "converged": bool(res.converged),
        "seconds": seconds,
        "files": files,
        "environment": _environment(),
    }


def _run_distances(args, progress: Progress) -> dict:
    import numpy as np

    from . import plot
    from ._atomic import save_npz_atomic, write_text_atomic
    from ._karcher import distance_matrix

    shapes, metric, options = _prepare(args, progress, args.files, _shape_geodesic_options)
    k, m, n = shapes.shape[0], *shapes.shape[2:]
    settings = _collection_settings(args, m, n, options)
    checkpoint = args.out / "distances_checkpoint.npz"

    def report(info):
        eta = "" if info["eta_s"] is None else f", about {info['eta_s']:.0f} s left"
        progress(
            f"pairs done {info['pairs_done']}/{info['pairs']}{eta} (checkpoint {checkpoint.name})"
        )

    progress(
        f"{k * (k - 1) // 2} shape geodesics modulo {args.modulo} on {m} x {n} (the first compiles)"
    )
    start = time.perf_counter()
    res = distance_matrix(
        shapes,
        metric,
        modulo=args.modulo,
        options=options,
        batch_size=args.batch_size,
        strategy=args.strategy,
        checkpoint=checkpoint,
        resume=args.resume,
        progress=report,
        client=args.client,
    )
    seconds = time.perf_counter() - start
    matrix = np.asarray(res.distances)
    converged = np.asarray(res.converged)
    if not converged.all():
        progress(f"{int((~converged).sum()) // 2} pairs did not converge (summary: converged)")
    names = [pathlib.Path(f).stem for f in args.files]
    files = [
        str(
            save_npz_atomic(
                args.out / "distances.npz",
                distances=matrix,
                converged=converged,
                refinement_change=np.asarray(res.refinement_change),
                files=np.asarray(args.files),
                settings=json.dumps(settings),
            )
        )
    ]
    rows = [",".join(["", *names])]
    rows += [
        ",".join([name, *(f"{v:.10g}" for v in row)])
        for name, row in zip(names, matrix, strict=True)
    ]
    files.append(str(write_text_atomic(args.out / "distances.csv", "\n".join(rows) + "\n")))
    files += _figure(
        args.out / "distances.png",
        lambda: plot.plot_distance_matrix(matrix, labels=names),
        progress,
    )
    return {
        "command": args.command,
        "inputs": list(args.files),
        "settings": settings,
        "distances": matrix.tolist(),
        "converged": bool(converged.all()),
        "pairs_converged": converged.tolist(),
        # Each pair's relative change under refinement (null: not computed).
        "refinement_change": _json_floats(res.refinement_change),
        "seconds": seconds,
        "files": files,
        "environment": _environment(),
    }


def _builtin_pair(m: int, n: int, dtype: str):
    """The demo's and bench's surfaces ``(2, 3, m, n)``: a straight and a bent cylinder."""
    import numpy as np

    from . import shapes

    straight = shapes.sample(shapes.bent_cylinder, m, n, curvature=0.0)
    bent = shapes.sample(shapes.bent_cylinder, m, n, curvature=0.6, half_length=1.2)
    return np.stack([straight, bent]).astype(dtype)


def _run_demo(args, progress: Progress) -> dict:
    from . import io

    f1, f2 = pair = _builtin_pair(*(args.grid or (25, 49)), args.dtype)
    args.out.mkdir(parents=True, exist_ok=True)
    inputs = [
        str(io.save_surface(f1, args.out / "straight_cylinder.npz")),
        str(io.save_surface(f2, args.out / "bent_cylinder.npz")),
    ]
    summary = _run_geodesic(args, progress, pair, label=inputs)
    summary["files"] = inputs + summary["files"]
    return summary


def _run_bench(args, progress: Progress) -> dict:
    import jax
    import numpy as np

    from ._energy import path_energy, straight_path
    from ._geodesic import geodesic

    m, n = args.grid or (50, 99)
    pair = _builtin_pair(m, n, args.dtype)
    (f1, f2), metric, options = _prepare(args, progress, [], _geodesic_options, pair)
    path = straight_path(f1, f2, args.times)
    grad = jax.jit(jax.value_and_grad(lambda p: path_energy(metric, p)))

    def timed(call: Callable) -> tuple[dict, object]:
        """Times of the first call and of ``repeat`` more; and the last call's output."""
        runs = []
        for _ in range(args.repeat + 1):
            start = time.perf_counter()
            out = jax.block_until_ready(call())
            runs.append(time.perf_counter() - start)
        stats = {
            "first_call_s": runs[0],
            "median_s": float(np.median(runs[1:])),
            "runs_s": runs[1:],
        }
        return stats, out

    progress(f"energy value and gradient, {m} x {n}, N = {args.times}")
    energy, _ = timed(lambda: grad(path))
    progress(f"geodesic solve, degree {args.degree}")
    solve, res = timed(lambda: geodesic(f1, f2, metric, **options))
    return {
        "command": "bench",
        "settings": {
            "grid": [m, n],
            "metric": list(args.metric),
            **options,
            "dtype": args.dtype,
            "repeat": args.repeat,
            "shapes": "straight -> bent cylinder (built-in)",
        },
        "energy_value_and_grad": energy,
        "geodesic_solve": {
            **solve,
            "num_steps": int(res.num_steps),
            "distance": float(res.distance),
        },
        "converged": bool(res.converged),
        "environment": _environment(),
    }


def _checked(flag: str, check: Callable, *args):
    """``check(flag, value, ...)`` from the validation layer, its InputError as BadInput."""
    try:
        return check(flag, *args)
    except InputError as err:
        raise BadInput(str(err)) from err


def _expand_directories(args) -> None:
    """Each directory among the inputs stands for the surface files in it, sorted by name
    (:func:`io.surface_files`)."""
    files = getattr(args, "files", None)
    if files is None or not any(pathlib.Path(f).is_dir() for f in files):
        return
    from . import io

    expanded = []
    for name in files:
        if not pathlib.Path(name).is_dir():
            expanded.append(name)
            continue
        try:
            expanded += [str(p) for p in io.surface_files(name)]
        except ValueError as err:
            raise BadInput(str(err)) from err
    args.files = expanded


def _read_karcher_output(args) -> dict | None:
    """pca's only input as a karcher run's mean.npz (it holds ``velocities``): its arrays,
    with that run's metric, grid, dtype and options put into ``args``; else None."""
    import dataclasses

    import numpy as np

    if args.command != "pca" or len(args.files) != 1:
        return None
    name = args.files[0]
    if not (name.lower().endswith(".npz") and pathlib.Path(name).is_file()):
        return None
    try:
        with np.load(name) as data:
            if "velocities" not in data.files:
                return None
            missing = [k for k in KARCHER_OUTPUT_KEYS if k not in data.files]
            if missing:
                raise BadInput(f"{name}: a karcher output without {', '.join(missing)}")
            saved = {k: data[k] for k in KARCHER_OUTPUT_KEYS}
    except (OSError, ValueError) as err:
        raise BadInput(f"{name}: not a readable .npz ({err})") from err
    defaults = vars(build_parser().parse_args(["pca", name]))
    given = [
        flag for dest, flag in KARCHER_OWN_FLAGS.items() if getattr(args, dest) != defaults[dest]
    ]
    if given:
        raise BadInput(
            f"pca on a karcher output ({name}) uses that run's mean, metric and options; "
            f"leave out {', '.join(given)}"
        )
    settings = json.loads(str(saved["settings"]))
    fields = {f.name for f in dataclasses.fields(ShapeOptions)}
    args.shape_options = ShapeOptions(**{k: v for k, v in settings.items() if k in fields})
    args.metric, args.dtype = tuple(settings["metric"]), settings["dtype"]
    args.modulo, args.grid = settings["modulo"], tuple(settings["grid"])
    saved["settings"], saved["inputs"] = settings, json.loads(str(saved["inputs"]))
    return saved


def _preflight(args) -> None:
    """Refuse bad options before reading any file or starting any work."""
    _expand_directories(args)
    args.karcher_output = _read_karcher_output(args)
    _metric_from(args)
    if args.grid is not None:
        _checked("--grid", lambda name, grid: check_grid_shape((3, *grid), name), args.grid)
    if args.command in SHAPE_COMMANDS and args.karcher_output is None:
        args.shape_options = shape_options_from(args)
    else:
        _checked("--degree", check_int, args.degree, 1)
        _checked("--times", check_int, args.times, 3)
        if getattr(args, "max_steps", None) is not None:
            _checked("--max-steps", check_int, args.max_steps, 1)
    if args.command in ("karcher", "pca", "distances") and args.karcher_output is None:
        if len(args.files) < 2:
            also = " (or one karcher run's mean.npz)" if args.command == "pca" else ""
            raise BadInput(
                f"{args.command} needs at least 2 surface files{also}; got {len(args.files)}"
            )
    if args.command in ("karcher", "pca"):
        _checked("--karcher-steps", check_int, args.karcher_steps, 0)
        _checked("--tol", check_positive, args.tol)
        _checked("--step-size", check_positive, args.step_size)
    if args.command == "pca":
        _checked("--modes", check_int, args.modes, 1)
        _checked("--sigmas", check_positive, args.sigmas)
        _checked("--mode-times", check_int, args.mode_times, 3)
        if args.scheme == "central":
            raise BadInput(
                "--scheme central: the mode paths are shot, and the central scheme cannot be "
                "(its energy couples five nodes); use midpoint or forward"
            )
    if args.command == "shoot":
        if not math.isfinite(args.scale):
            raise BadInput(f"--scale {args.scale}: must be a finite number")
        if args.tol is not None:
            _checked("--tol", check_positive, args.tol)
        _checked("--max-newton", check_int, args.max_newton, 1)
        if not pathlib.Path(args.velocity).is_file():
            raise BadInput(f"{args.velocity}: no such file (the velocity .npz)")
    if getattr(args, "batch_size", None) is not None:
        _checked("--batch-size", check_int, args.batch_size, 1)
    if getattr(args, "workers", None) is not None:
        _checked("--workers", check_int, args.workers, 1)
    if args.command == "bench":
        _checked("--repeat", check_int, args.repeat, 1)


def _claim_out(args, stack: contextlib.ExitStack) -> None:
    """Make --out, prove it writable, lock it for this run, and sweep what killed runs left.

    All before any file is read or any solve starts, so that a bad --out never costs a
    solve. The lock is advisory (flock on ``.elastic-jax.lock``): a second run on the
    same directory is refused (BadInput) instead of overwriting the first one's
    checkpoint. A checkpoint already there is continued with --resume or discarded with
    --overwrite, never silently.
    """
    out = args.out
    if out.exists() and not out.is_dir():
        raise BadInput(f"--out {out}: exists and is not a directory")
    if not out.exists():
        # A run refused before writing anything leaves no empty directory behind
        # (rmdir fails, harmlessly, once the directory holds files).
        stack.callback(_remove_if_empty, out)
    try:
        out.mkdir(parents=True, exist_ok=True)
        stack.enter_context(_locked(out / LOCK_NAME))
        probe = tempfile.NamedTemporaryFile(dir=out, prefix=f".probe{TEMPORARY}")
        probe.close()
    except BlockingIOError:
        raise BadInput(
            f"--out {out}: another elastic-jax run is writing there (it holds {LOCK_NAME}); "
            "wait for it or choose another --out"
        ) from None
    except OSError as err:
        raise BadInput(f"--out {out}: not a writable directory ({err.strerror or err})") from err
    # Temporaries of atomic writes that a killed run left behind: nobody else writes here
    # while we hold the lock.
    for stale in stale_temporaries(out):
        stale.unlink(missing_ok=True)
    checkpoint = CHECKPOINTS.get(args.command)
    if checkpoint and (out / checkpoint).exists() and not (args.resume or args.overwrite):
        raise BadInput(
            f"--out {out} holds the checkpoint {checkpoint} of an earlier run; continue it "
            "with --resume or discard it with --overwrite"
        )


def _dask_client(args, stack: contextlib.ExitStack, progress: Progress):
    """The Dask client of --workers or --scheduler (None without them), closed with the
    stack; its workers share the compilation cache unless --no-cache."""
    workers, address = getattr(args, "workers", None), getattr(args, "scheduler", None)
    if workers is None and address is None:
        return None
    try:
        import distributed
    except ImportError:
        raise BadInput(
            '--workers and --scheduler need Dask distributed: pip install "elastic-jax[dask]"'
        ) from None
    if workers is not None:
        progress(f"starting a local Dask cluster of {workers} worker processes")
        cluster = stack.enter_context(
            distributed.LocalCluster(
                n_workers=workers,
                threads_per_worker=1,
                processes=True,
                # The scheduler's web server on a free local port: with dashboard_address
                # None it still tries 8787, and warns when another cluster holds it.
                dashboard_address="127.0.0.1:0",
            )
        )
        client = stack.enter_context(distributed.Client(cluster))
    else:
        progress(f"connecting to the Dask scheduler at {address}")
        try:
            client = stack.enter_context(distributed.Client(address, timeout="30s"))
        except OSError as err:
            raise BadInput(f"--scheduler {address}: cannot connect ({err})") from err
    if not args.no_cache:
        from ._cache import enable_compilation_cache

        enable_compilation_cache(args.cache_dir, client=client, exported=not args.no_export)
    return client


def _remove_if_empty(directory: pathlib.Path) -> None:
    with contextlib.suppress(OSError):
        directory.rmdir()


@contextlib.contextmanager
def _locked(path: pathlib.Path):
    """Hold an exclusive advisory lock on ``path`` (BlockingIOError if another holds it)."""
    import fcntl

    while True:
        fh = open(path, "a+")  # noqa: SIM115 (held for the whole run)
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BaseException:
            fh.close()
            raise
        # The previous holder may have removed the file between our open and our lock:
        # then we hold a lock on a file nobody else can find; take the new one.
        try:
            same = os.fstat(fh.fileno()).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        fh.close()
    try:
        fh.write(f"{os.getpid()}\n")
        fh.flush()
        yield
    finally:
        path.unlink(missing_ok=True)
        fh.close()


class Terminated(KeyboardInterrupt):
    """SIGTERM, handled like Ctrl-C (complete files only, exit 143)."""


def _raise_terminated(signum, frame):
    raise Terminated()


COMMANDS = {
    "geodesic": _run_geodesic,
    "shape-geodesic": _run_shape_geodesic,
    "karcher": _run_karcher,
    "distances": _run_distances,
    "pca": _run_pca,
    "shoot": _run_shoot,
    "demo": _run_demo,
    "bench": _run_bench,
}


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``elastic-jax`` (and ``python -m elastic_jax``); returns the exit code."""
    args = build_parser().parse_args(argv)
    import jax

    if args.dtype == "float64":
        # The program chooses its precision (the library never changes JAX's global config);
        # float32 runs cast their inputs instead, so an in-process call changes nothing else.
        jax.config.update("jax_enable_x64", True)
    if not args.no_cache and jax.config.jax_compilation_cache_dir is None:
        # Solves compile for 5-60 s and a command runs once per process: keep the
        # executables (and the exported shape solve) on disk; a program's choice, the
        # library never sets this by itself. A caller that set a cache keeps its own.
        from ._cache import enable_compilation_cache

        try:
            enable_compilation_cache(args.cache_dir, exported=not args.no_export)
        except OSError as err:  # e.g. a read-only home: the run goes on, compiling
            print(
                f"elastic-jax: --cache-dir {args.cache_dir}: cannot be created ({err}); "
                "compiling without a cache",
                file=sys.stderr,
            )
    from ._errors import ConvergenceWarning

    progress = Progress(args.quiet)
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        with warnings.catch_warnings(), contextlib.ExitStack() as stack:
            # Non-convergence is reported in the summary and the exit code instead.
            warnings.simplefilter("ignore", ConvergenceWarning)
            _preflight(args)
            _claim_out(args, stack)
            args.client = _dask_client(args, stack, progress)
            summary = COMMANDS[args.command](args, progress)
            _write_summary(args.out, summary)
    except (BadInput, InputError) as err:
        print(f"elastic-jax {args.command}: bad input: {_one_line(err)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt as err:
        how = "terminated" if isinstance(err, Terminated) else "interrupted"
        print(
            f"elastic-jax {args.command}: {how}; every file in {args.out} is complete "
            "(karcher, pca and distances continue with --resume)",
            file=sys.stderr,
        )
        return EXIT_TERMINATED if isinstance(err, Terminated) else EXIT_INTERRUPTED
    finally:
        signal.signal(signal.SIGTERM, previous)
    progress(f"done; summary in {args.out / 'summary.json'}")
    return EXIT_NOT_CONVERGED if summary.get("converged") is not True else EXIT_OK


def _one_line(err: Exception) -> str:
    return " ".join(str(err).split())


if __name__ == "__main__":
    raise SystemExit(main())
