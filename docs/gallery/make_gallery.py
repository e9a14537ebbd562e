"""Solve what the gallery shows and store it: figures (PNG) and numbers (figures.json).

    python docs/gallery/make_gallery.py [--parts geodesics,multires,karcher] [--quick]
    python docs/gallery/make_gallery.py --replot [--parts ...]

Reads the authors' surfaces cat1, cat2 and horse0 (50 x 99) through
``elastic_jax.datasets`` (never copied into the project): from ``$ELASTIC_JAX_DATA``, a
folder of the authors' ``.mat`` files (by default ``../shared/data/ShapeData`` beside the
repository when that exists), else the user cache or a download; writes
``docs/gallery/figures/*.png``, ``docs/gallery/figures.json`` and the arrays the figures
draw, ``figures.npz`` beside it (float16, enough to draw: the drawn frames of each path
and mode path, the mean and the registered inputs; about 1 MB). ``--replot`` solves
nothing: it redraws every figure from ``figures.json`` and ``figures.npz`` (a part whose
arrays are missing redraws only what needs none: the energy and Karcher histories, stored
in ``figures.json``, and the Karcher inputs, which are the input shapes). Every figure is
titled: the surfaces are drawn with ``view="fit"``, the geodesics with a title naming the
pair and the distance.

The paper's tables come from the benchmark harness (``benchmarks/bench_shape.py`` and
``bench_statistics.py --only-table``), whose JSON lines are stored in
``docs/gallery/bench/``; ``docs/_generate.py`` turns both into the gallery's tables at every
build, so the site never solves anything. ``--quick`` runs every part on a
13 x 25 grid with small settings (a check that the script works, not a gallery).

Settings (float64, metric (1, 1, 0.1, 0), the paper's examples section):
- geodesics: ``shape_geodesic`` modulo rigid motion with the package's default
  ``ShapeOptions`` (a resolved distance: levels up to 97 x 193 until two agree within
  3 %; 25 x 49 is the first level now, 13 x 25 when the stored records were made), the
  data on its own 50 x 99 grid, for cat1 -> cat2, cat1 -> horse0 and cat2 -> horse0;
  each path, its levels, and the energy of the parametrized geodesic before
  registration and after each round of the last level;
- multires: the parametrized geodesic cat1 -> horse0 solved at 13 x 25 (degree 4, N 5),
  then 25 x 49 (degree 7, N 9), then 50 x 99 (degree 9, N 13), each warm-started from the
  previous (``schedule``), the paper's remark after Table 3;
- karcher: the Karcher mean of the three animals modulo rigid motion (degree 5, vf degree
  5, N 7), its first distances resolved by the levels 13 x 25 and 25 x 49 (so the mean
  lives on 25 x 49 at most), its history, and the tangent PCA's first two modes at +-1
  sigma.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import time
import warnings

import jax

jax.config.update("jax_enable_x64", True)  # a script, not the library

import numpy as np  # noqa: E402

import elastic_jax as ej  # noqa: E402
from elastic_jax import plot  # noqa: E402
from elastic_jax._runtime.atomic import write_text_atomic  # noqa: E402

HERE = pathlib.Path(__file__).resolve().parent
# The authors' .mat files beside the repository, when there, unless ELASTIC_JAX_DATA says
# otherwise; elastic_jax.datasets then looks in its cache and downloads.
SHAPE_DATA = HERE.parents[2] / "shared" / "data" / "ShapeData"
if SHAPE_DATA.is_dir():
    os.environ.setdefault("ELASTIC_JAX_DATA", str(SHAPE_DATA))
FIGURES = HERE / "figures"
METRIC = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)
# The animals only: the authors' hand4 is stored about 100 times smaller (area 1.0e-4
# against 0.92-1.87), so a path to it is mostly a change of size.
NAMES = ("cat1", "cat2", "horse0")
PAIRS = (("cat1", "cat2"), ("cat1", "horse0"), ("cat2", "horse0"))


def load(name: str, m: int, n: int) -> np.ndarray:
    f = ej.datasets.load(name)
    return np.asarray(ej.resample(f, m, n)) if (m, n) != f.shape[1:] else f


def save(fig, name: str) -> str:
    plot.save_figure(fig, FIGURES / name)
    return f"figures/{name}"


# The stored arrays' type: a figure needs no more. Its rounding, 1e-3 of a coordinate of
# size 2 (the cats' length), is a sixth of a pixel of a 300-pixel panel; float32 would
# double the file, past 2 MB once the paths are solved on the 50 x 99 grid.
STORED = np.float16


def drawn_frames(path, count: int) -> tuple[np.ndarray, list[str]]:
    """The ``count`` frames of a path that the figure shows (the first, the last and evenly
    between, as ``plot_path(frames=count)`` chooses them), as STORED, and their titles
    ``t = k/(N-1)``."""
    path = np.asarray(path)
    last = len(path) - 1
    chosen = [int(k) for k in np.rint(np.linspace(0, last, min(count, len(path))))]
    return path[chosen].astype(STORED), [f"t = {k}/{last}" for k in chosen]


# Each part solves (solve_*: its numbers for figures.json and the arrays its figures draw,
# stored in ARRAYS) and draws (draw_*: from the numbers and arrays alone), so that
# ``--replot`` redraws the figures from the stored arrays without solving anything.


def solve_geodesics(quick: bool) -> tuple[dict, dict]:
    # The data's own grid: a resolved distance (the defaults' levels) reads each input on
    # its grid, so that no level sees a coarser surface than the data (math §10).
    m, n = (13, 25) if quick else (50, 99)
    options = (
        ej.ShapeOptions(degree=3, vf_degree=3, n_times=5, rtol=None) if quick else ej.ShapeOptions()
    )
    out, arrays = {}, {}
    for a, b in PAIRS:
        start = time.perf_counter()
        res = ej.shape_geodesic(
            load(a, m, n), load(b, m, n), METRIC, modulo="rigid", options=options
        )
        seconds = time.perf_counter() - start
        key = f"{a}-{b}"
        history = np.asarray(res.energy_history)[: int(res.rounds) + 2]
        arrays[f"{key}/frames"], titles = drawn_frames(res.path, 5)
        out[key] = {
            "grid": [m, n],
            "options": options.as_dict(),
            "seconds_first_call": seconds,
            "distance": float(res.distance),
            "parametrized_distance": float(res.parametrized_distance),
            "converged": bool(res.converged),
            "message": res.message,
            "rounds": int(res.rounds),
            "refinement_relative_change": float(res.refinement.relative_change),
            "result": ej.RESULTS.name(res.result),
            "levels": None
            if res.levels is None
            else {
                "grids": np.asarray(res.levels.grids).tolist(),
                "distances": np.asarray(res.levels.distances).tolist(),
                "estimate": float(res.levels.estimate),
            },
            "energy_history": history.tolist(),
            "frame_titles": titles,
        }
        print(key, out[key]["distance"], f"{seconds:.1f} s", flush=True)
    return out, arrays


def draw_geodesics(out: dict, arrays: dict) -> None:
    for a, b in PAIRS:
        key = f"{a}-{b}"
        if f"{key}/frames" in arrays:
            fig = plot.plot_path(
                arrays[f"{key}/frames"].astype(float),
                titles=out[key]["frame_titles"],
                suptitle=f"{a} to {b}: geodesic modulo rigid motion, "
                f"distance {out[key]['distance']:.4f}",
                view="fit",
            )
            out[key]["figure"] = save(fig, f"geodesic_{key}.png")
    fig = plot.plot_energy(
        {key: out[key]["energy_history"] for key in (f"{a}-{b}" for a, b in PAIRS)},
        title="Shape geodesics: path energy per round",
    )
    fig.axes[0].set_xlabel("0: parametrized geodesic; k: after registration round k")
    fig.axes[0].set_ylabel("path energy")
    out["energy_figure"] = save(fig, "geodesic_energies.png")


def solve_multires(quick: bool) -> tuple[dict, dict]:
    levels = [(4, 5, 13, 25), (7, 9, 25, 49), (9, 13, 50, 99)]
    if quick:
        levels = [(2, 3, 7, 13), (3, 5, 13, 25)]
    out, arrays = {"levels": []}, {}
    for k, (degree, n_times, m, n) in enumerate(levels):
        start = time.perf_counter()
        res = ej.geodesic(
            load("cat1", m, n),
            load("horse0", m, n),
            METRIC,
            degree=degree,
            n_times=n_times,
            schedule=levels[:k],
            max_steps=1000,
        )
        seconds = time.perf_counter() - start
        arrays[f"level{k + 1}/frames"], titles = drawn_frames(res.path, 5)
        out["levels"].append(
            {
                "degree": degree,
                "n_times": n_times,
                "grid": [m, n],
                "seconds_first_call_with_coarser_levels": seconds,
                "distance": float(res.distance),
                "straight_distance": float(np.sqrt(res.straight_energy)),
                "converged": bool(res.converged),
                "num_steps": int(res.num_steps),
                "frame_titles": titles,
            }
        )
        print("level", k + 1, out["levels"][-1]["distance"], flush=True)
    return out, arrays


def draw_multires(out: dict, arrays: dict) -> None:
    for k, level in enumerate(out["levels"]):
        if f"level{k + 1}/frames" not in arrays:
            continue
        m, n = level["grid"]
        fig = plot.plot_path(
            arrays[f"level{k + 1}/frames"].astype(float),
            titles=level["frame_titles"],
            suptitle=f"cat1 to horse0, level {k + 1}: {m} x {n} grid, degree "
            f"{level['degree']}, {level['n_times']} times; distance {level['distance']:.4f}",
            view="fit",
        )
        level["figure"] = save(fig, f"multires_{k + 1}.png")


def inputs(m: int, n: int) -> np.ndarray:
    """The Karcher mean's inputs as given, resampled to its grid ``(K, 3, m, n)``."""
    return np.stack([load(name, m, n) for name in NAMES])


def solve_karcher(quick: bool) -> tuple[dict, dict]:
    m, n = (13, 25) if quick else (50, 99)  # the inputs on their own grid
    # Resolved by levels up to the mean's grid (the distances' levels stop at 25 x 49, as
    # in notebook 07): a mean at 97 x 193 takes hours on 2 cores.
    options = ej.ShapeOptions(
        degree=3 if quick else 5,
        vf_degree=3 if quick else 5,
        n_times=5 if quick else 7,
        levels=((13, 25),) if quick else ((13, 25), (25, 49)),
    )
    start = time.perf_counter()
    res = ej.karcher_mean(
        inputs(m, n), METRIC, modulo="rigid", options=options, max_steps=3 if quick else 10
    )
    karcher_s = time.perf_counter() - start
    pca = ej.tangent_pca(res, METRIC)
    start = time.perf_counter()
    modes = np.stack(
        [
            np.asarray(ej.mode_path(pca, k, METRIC, sigmas=1.0, n_times=5 if quick else 7))
            for k in range(2)
        ]
    )
    modes_s = time.perf_counter() - start
    # The five columns the figure shows, the mean in the middle: a mode path in its own right.
    modes = np.stack([drawn_frames(path, 5)[0] for path in modes])
    out = {
        "grid": [m, n],
        "options": options.as_dict(),
        "shapes": list(NAMES),
        "seconds_first_call": karcher_s,
        "converged": bool(res.converged),
        "result": str(res.result),
        "message": res.message,
        "num_steps": int(res.num_steps),
        "distances": np.asarray(res.distances).tolist(),
        "history": np.asarray(res.history).tolist(),
        "explained": np.asarray(pca.explained).tolist(),
        "modes_seconds": modes_s,
    }
    arrays = {
        "mean": np.asarray(res.mean).astype(STORED),
        "registered": np.asarray(res.registered).astype(STORED),
        "modes": modes,
    }
    print("karcher", out["distances"], out["explained"], flush=True)
    return out, arrays


def draw_karcher(out: dict, arrays: dict) -> None:
    m, n = out["grid"]
    # The inputs as given need no solve: drawn from the authors' surfaces whatever is stored.
    fig = plot.plot_path(
        inputs(m, n), titles=list(NAMES), suptitle="The inputs, as given", view="fit"
    )
    out["inputs_figure"] = save(fig, "karcher_inputs.png")
    if "registered" in arrays:
        fig = plot.plot_path(
            arrays["registered"].astype(float),
            titles=list(NAMES),
            suptitle="The inputs registered to the Karcher mean",
            view="fit",
        )
        out["registered_figure"] = save(fig, "karcher_registered.png")
    if "mean" in arrays:
        fig = plot.plot_path(arrays["mean"].astype(float), titles=["Karcher mean"], view="fit")
        out["mean_figure"] = save(fig, "karcher_mean.png")
    history = np.asarray(out["history"])
    fig = plot.plot_energy(
        history[:, :2],
        labels=["sum of squared distances", "|mean velocity|"],
        title=f"Karcher mean of {', '.join(NAMES)}",
    )
    fig.axes[0].set_xlabel("Karcher step")
    out["history_figure"] = save(fig, "karcher_history.png")
    if "modes" in arrays:
        fig = plot.plot_modes(
            list(arrays["modes"].astype(float)),
            explained=out["explained"][:2],
            sigmas=1.0,
            suptitle="Tangent PCA at the Karcher mean: the first two modes",
            view="fit",
        )
        out["modes_figure"] = save(fig, "pca_modes.png")


PARTS = {
    "geodesics": (solve_geodesics, draw_geodesics),
    "multires": (solve_multires, draw_multires),
    "karcher": (solve_karcher, draw_karcher),
}


def _parts(text: str) -> list[str]:
    parts = text.split(",")
    unknown = [p for p in parts if p not in PARTS]
    if unknown:
        raise argparse.ArgumentTypeError(f"unknown parts {unknown}; choose from {list(PARTS)}")
    return parts


def _load_arrays(path: pathlib.Path) -> dict[str, dict[str, np.ndarray]]:
    """The stored arrays by part: ``{part: {name: array}}`` from keys ``part/name``."""
    if not path.exists():
        return {}
    out: dict[str, dict[str, np.ndarray]] = {}
    with np.load(path) as stored:
        for key in stored.files:
            part, name = key.split("/", 1)
            out.setdefault(part, {})[name] = stored[key]
    return out


def _save_arrays(path: pathlib.Path, arrays: dict[str, dict[str, np.ndarray]]) -> None:
    flat = {f"{part}/{name}": a for part, named in arrays.items() for name, a in named.items()}
    # The same temporary-then-rename as the figures: an interrupted save keeps the old file.
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez_compressed(tmp, **flat)
    os.replace(tmp, path)
    print(f"{path.name}: {path.stat().st_size / 1e6:.2f} MB", flush=True)


def main() -> None:
    global FIGURES  # save() writes there; --figures moves it
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parts", type=_parts, default=list(PARTS))
    parser.add_argument("--quick", action="store_true", help="13 x 25, small settings")
    parser.add_argument(
        "--replot",
        action="store_true",
        help="redraw the figures from the stored numbers and arrays, solving nothing",
    )
    parser.add_argument("--out", type=pathlib.Path, default=HERE / "figures.json")
    parser.add_argument(
        "--arrays",
        type=pathlib.Path,
        default=None,
        help="the solved arrays the figures draw (default: beside --out, figures.npz)",
    )
    parser.add_argument("--figures", type=pathlib.Path, default=FIGURES, help="PNG folder")
    args = parser.parse_args()
    FIGURES = args.figures
    FIGURES.mkdir(parents=True, exist_ok=True)
    arrays_path = args.arrays or args.out.with_name("figures.npz")
    stored = json.loads(args.out.read_text()) if args.out.exists() else {}
    arrays = _load_arrays(arrays_path)
    for part in args.parts:
        solve, draw = PARTS[part]
        if args.replot:
            if part not in stored:
                print(f"{part}: no stored numbers in {args.out}; skipped", flush=True)
                continue
            missing = "" if part in arrays else f" (no arrays in {arrays_path.name}: partly)"
            draw(stored[part], arrays.get(part, {}))
            print(f"{part}: redrawn{missing}", flush=True)
        else:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", ej.ConvergenceWarning)
                stored[part], arrays[part] = solve(args.quick)
            draw(stored[part], arrays[part])
            stored[part]["device"] = str(jax.devices()[0].device_kind)
            stored[part]["jax"] = jax.__version__
            stored[part]["measured"] = time.strftime("%Y-%m-%d")
            _save_arrays(arrays_path, arrays)
        # One part at a time, atomically: a later part's failure keeps the earlier ones.
        write_text_atomic(args.out, json.dumps(stored, indent=1) + "\n")


if __name__ == "__main__":
    main()
