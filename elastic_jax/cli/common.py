"""What the commands share: the bad-input error, progress lines, loading the surfaces,
the options from the flags, and the atomic writes of arrays, meshes, figures and the
summary.
"""

from __future__ import annotations

import json
import math
import pathlib
import platform
import sys
import time
from collections.abc import Callable, Sequence

import jax
import numpy as np

from .. import RESULTS, InputError, JobOptions, ShapeOptions, SplitMetric, io, max_degree
from .signals import raise_if_signalled

CHECKPOINTS = {
    "karcher": "karcher_checkpoint.npz",
    "pca": "karcher_checkpoint.npz",
    "distances": "distances_checkpoint.npz",
    "fit-metric": "fit_metric_checkpoint.npz",
}


DEFAULT_METRIC = (1.0, 1.0, 0.1, 0.0)


SURFACE_FILE = "a surface: .npz (array f), .mat (the authors'), or a mesh trimesh reads"


SURFACE_FILES = SURFACE_FILE.replace("a surface", "surfaces") + ", or a directory of them"


# What pca reads from a karcher run's mean.npz instead of solving the mean again.
KARCHER_OUTPUT_KEYS = ("f", "velocities", "distances", "settings", "inputs", "result", "converged")


SHAPE_COMMANDS = ("shape-geodesic", "karcher", "pca", "distances", "fit-metric", "warmup")


SHAPE_DEFAULTS = ShapeOptions()


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

# The candidates' flags, given with --rtol (the commands that resolve by levels).
CANDIDATE_FLAGS = {
    "level_candidates": ("level_candidates", "--level-candidates"),
    "both_orders": ("both_orders", "--both-orders"),
    "search_smoothing": ("search_smoothing", "--search-smoothing"),
    "smoothing_kernel": ("smoothing_kernel", "--smoothing-kernel"),
    "alternations": ("alternations", "--alternations"),
}


# Flags that pca on a karcher output takes from that run: giving them is refused.
KARCHER_OWN_FLAGS = {
    **{dest: flag for dest, flag in SHAPE_FLAGS.values()},
    **{dest: flag for dest, flag in CANDIDATE_FLAGS.values()},
    **{
        dest: "--" + dest.replace("_", "-")
        for dest in ("metric", "grid", "dtype", "modulo", "strategy", "batch_size", "workers")
        + ("scheduler", "resume", "karcher_steps", "tol", "step_size", "warm_start", "rtol")
        + ("sphere", "normalize")
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
        raise_if_signalled()
        if not self.quiet:
            print(f"[{self.elapsed():7.1f} s] {message}", file=sys.stderr, flush=True)


def environment_record() -> dict:
    return {
        "python": platform.python_version(),
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "devices": [str(d) for d in jax.devices()],
    }


def is_grid_file(name) -> bool:
    return str(name).lower().endswith((".npz", ".mat"))


def input_files(args) -> list[str]:
    """The surface files a command reads (its positional inputs; [] for demo, bench, warmup)."""
    if getattr(args, "files", None) is not None:
        return list(args.files)
    return [getattr(args, k) for k in ("source", "target") if getattr(args, k, None) is not None]


def check_spheres(args) -> None:
    """--sphere: one existing file per input, every input a mesh (before any file is read)."""
    spheres = getattr(args, "sphere", None)
    if spheres is None:
        return
    files = input_files(args)
    if len(spheres) != len(files):
        raise BadInput(
            f"--sphere: {len(spheres)} sphere file(s) for {len(files)} input surface(s); give "
            "one per input mesh, in the inputs' order"
        )
    for name, sphere in zip(files, spheres, strict=True):
        if is_grid_file(name):
            raise BadInput(
                f"--sphere: {name} is a grid file; a sphere map resamples a mesh (every input "
                "must be a mesh when --sphere is given)"
            )
        if not pathlib.Path(sphere).is_file():
            raise BadInput(f"--sphere {sphere}: no such file")


def input_settings(args) -> dict:
    """How the inputs were read: their scale normalization and sphere maps."""
    return {
        "normalize": getattr(args, "normalize", "none"),
        "sphere": getattr(args, "sphere", None),
    }


def _load_all(
    files: Sequence[str],
    grid,
    dtype,
    progress: Progress,
    frame: str = "principal",
    spheres: Sequence[str] | None = None,
    normalize: str = "none",
    maps: list | None = None,
):
    """Surfaces as one (K, 3, m, n) array on a common grid; BadInput names the file.

    ``frame``: the axes mesh files are resampled in (io.mesh_to_grid's ``frame``); grid
    files keep their own parametrization. ``spheres``: one sphere map file per input
    (io.load_surface's ``sphere``). ``normalize``: "none" or "area" (io.normalize_scale).
    ``maps``: a list that receives each input's io.VertexMap (None for a grid file)."""

    out = []
    m, n = (None, None) if grid is None else grid
    for k, name in enumerate(files):
        progress(f"reading {name}" + ("" if spheres is None else f" through {spheres[k]}"))
        try:
            options = {"frame": None if is_grid_file(name) else frame}
            if spheres is not None:
                # A given map is in its own axes: no frame (io.mesh_to_grid).
                options = {"sphere": spheres[k]}
            wants_map = maps is not None and not is_grid_file(name)
            f = io.load_surface(name, m=m, n=n, progress=progress, return_map=wants_map, **options)
            if maps is not None:
                f, vertex_map = f if wants_map else (f, None)
                maps.append(vertex_map)
            if normalize == "area":
                f, scale = io.normalize_scale(f)
                progress(f"{name}: scaled by {float(scale):.6g} to area 4 pi")
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


def metric_from(args):
    try:
        return SplitMetric(*args.metric)
    except ValueError as err:
        raise BadInput(str(err)) from err


def check_degrees(args, m: int, n: int) -> None:
    """--degree and --vf-degree within 1 .. max_degree(m, n), the degrees whose harmonics
    are independent on the m x n grid."""
    limit = max_degree(m, n)
    for name in ("degree", "vf_degree"):
        value = getattr(args, name, None)
        if value is not None and not 1 <= value <= limit:
            raise BadInput(
                f"--{name.replace('_', '-')} {value}: must be between 1 and {limit} on the "
                f"{m} x {n} grid (min(m - 3, (n - 3) // 2), beyond which the harmonics are "
                "not independent on the grid)"
            )


def geodesic_options_from(args) -> dict:
    options = {"degree": args.degree, "n_times": args.times, "solver": args.solver}
    if args.max_steps is not None:
        options["max_steps"] = args.max_steps
    return options


def shape_options_from(args) -> ShapeOptions:
    """One validated ShapeOptions from the shape commands' arguments.

    A bad value is BadInput naming the flag, e.g. ``--times 2: n_times must be ...``.
    """
    values = {field: getattr(args, dest) for field, (dest, _) in SHAPE_FLAGS.items()}
    # --rtol is the commands' that resolve by levels; the others solve on one grid
    # (rtol None, which is what they use).
    values["rtol"] = getattr(args, "rtol", None)
    for field, (dest, _) in CANDIDATE_FLAGS.items():
        if getattr(args, dest, None) is not None:
            values[field] = getattr(args, dest)
    if isinstance(values.get("search_smoothing"), str):
        raise BadInput(
            f"--search-smoothing {values['search_smoothing']}: wants kernel widths "
            "w1,w2,... (numbers, wide to narrow)"
        )
    try:
        return ShapeOptions(**values)
    except ValueError as err:
        field = str(err).split()[0]
        flag = {**SHAPE_FLAGS, **CANDIDATE_FLAGS}.get(field, (field, f"--{field}"))[1]
        raise BadInput(f"{flag} {values.get(field)}: {err}") from err


def shape_geodesic_options(args) -> ShapeOptions:
    return args.shape_options


def json_safe(value):
    """``value`` with every non-finite float (not JSON) replaced by None, recursively."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    return value


def write_summary(out: pathlib.Path, summary: dict) -> None:
    target = out / "summary.json"
    summary["files"] = sorted({*summary.get("files", []), str(target)})
    # A failed solve's NaN becomes null: the file stays valid JSON (allow_nan=False).
    text = json.dumps(json_safe(summary), indent=2, allow_nan=False)
    io.write_text_atomic(target, text + "\n")
    print(text)


def write_figure(target: pathlib.Path, make: Callable, progress: Progress) -> list[str]:
    """``[target]`` after drawing ``make()`` into it; ``[]`` (and a progress line) when
    the data cannot be drawn: a failed solve's NaN is reported in the summary, not as
    bad input."""
    from .. import plot

    try:
        fig = make()
    except InputError as err:
        progress(f"{target.name} not drawn: {one_line(err)}")
        return []
    return [str(plot.save_figure(fig, target))]


def write_path(out: pathlib.Path, path, settings: dict, progress: Progress) -> list[str]:
    from .. import plot

    if not np.isfinite(path).all():
        progress("the path is not finite: no meshes and no figure written")
        return []
    progress(f"writing the path's {path.shape[0]} meshes and its figure to {out}")
    written = [str(p) for p in io.save_path(path, out / "path", settings=settings)]
    return written + write_figure(
        out / "path.png", lambda: plot.plot_path(path, view="fit"), progress
    )


def prepare(args, progress: Progress, files, options_of: Callable, surfaces=None, main_inputs=True):
    """The surfaces ``(K, 3, m, n)`` (read unless given), checked degrees, metric, options.

    ``main_inputs``: ``files`` are the command's positional inputs, which ``--sphere``
    maps one to one (fit-metric's ``--test`` files are not).

    Every check that needs no file comes first: the options, the metric and, with
    ``--grid``, the degrees against that grid (reading a mesh maps it to the sphere, which
    takes seconds to minutes)."""
    options, metric = options_of(args), metric_from(args)
    if surfaces is None:
        if args.grid is not None:
            check_degrees(args, *args.grid)
        spheres = getattr(args, "sphere", None) if main_inputs else None
        normalize = getattr(args, "normalize", "none")
        maps = [] if getattr(args, "on_target_mesh", False) and main_inputs else None
        surfaces = _load_all(
            files, args.grid, args.dtype, progress, args.frame, spheres, normalize, maps
        )
        args.vertex_maps = maps
    check_degrees(args, *surfaces.shape[-2:])
    return surfaces, metric, options


def json_float(x) -> float | None:
    """A float for JSON; NaN and inf (not JSON) become null."""

    x = float(x)
    return x if math.isfinite(x) else None


def json_floats(values) -> list:
    """Nested lists of floats for JSON, NaN and inf as null."""

    values = np.asarray(values)
    if values.ndim == 0:
        return json_float(values)
    return [json_floats(v) for v in values]


def collection_settings(args, m: int, n: int, options: ShapeOptions) -> dict:
    return {
        "metric": list(args.metric),
        "modulo": args.modulo,
        "strategy": args.strategy,
        "batch_size": args.batch_size,
        **options.as_dict(),
        # The inputs' grid, which is the working grid here (ShapeOptions.grid is None).
        "grid": [m, n],
        "dtype": args.dtype,
        **input_settings(args),
    }


def job_options(args, checkpoint=None, progress=None):
    """The :class:`JobOptions` of a collection command: --batch-size, --strategy,
    --client, and (with a checkpoint) --resume."""
    return JobOptions(
        batch_size=args.batch_size,
        strategy=args.strategy,
        checkpoint=checkpoint,
        resume=bool(args.resume) if checkpoint is not None else False,
        progress=progress,
        client=args.client,
    )


def at_least(flag: str, value: int, minimum: int) -> int:
    """An integer flag's value (argparse made it an int) if it is at least ``minimum``."""
    if value < minimum:
        raise BadInput(f"{flag} {value}: must be an integer >= {minimum}")
    return value


def positive(flag: str, value: float) -> float:
    """A number flag's value (argparse made it a float) if it is finite and above 0."""
    if not (math.isfinite(value) and value > 0):
        raise BadInput(f"{flag} {value}: must be a positive finite number")
    return value


def one_line(err: Exception) -> str:
    return " ".join(str(err).split())


def result_fields(res) -> dict:
    """The result protocol in a summary: converged, result (by name), message, num_steps."""

    return {
        "converged": bool(res.converged),
        "result": RESULTS.name(res.result),
        "message": res.message,
        "num_steps": int(res.num_steps),
    }
