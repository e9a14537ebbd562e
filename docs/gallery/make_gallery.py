"""Solve what the gallery shows and store it: figures (PNG) and numbers (figures.json).

    python docs/gallery/make_gallery.py [--parts geodesics,multires,karcher] [--quick]

Reads the shared real surfaces (``../shared/data``, cat1, cat2, horse0 on the
50 x 99 grid; never copied into the project); writes ``docs/gallery/figures/*.png`` and
``docs/gallery/figures.json``. The paper's tables come from the benchmark harness
(``benchmarks/bench_shape.py`` and ``bench_statistics.py --only-table``), whose JSON lines
are stored in ``docs/gallery/bench/``; ``docs/_generate.py`` turns both into the gallery's
tables at every build, so the site never solves anything. ``--quick`` runs every part on a
13 x 25 grid with small settings (a check that the script works, not a gallery).

Settings (float64, metric (1, 1, 0.1, 0), the paper's examples section):
- geodesics: ``shape_geodesic`` modulo rigid motion at 25 x 49 with the package's default
  ``ShapeOptions``, for cat1 -> cat2, cat1 -> horse0 and cat2 -> horse0; each path and
  the energy of the parametrized geodesic before registration and after each round;
- multires: the parametrized geodesic cat1 -> horse0 solved at 13 x 25 (degree 4, N 5),
  then 25 x 49 (degree 7, N 9), then 50 x 99 (degree 9, N 13), each warm-started from the
  previous (``schedule``), the paper's remark after Table 3;
- karcher: the Karcher mean of the three animals modulo rigid motion at 25 x 49 (degree 5,
  vf degree 5, N 7), its history, and the tangent PCA's first two modes at +-1 sigma.
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
# ELASTIC_JAX_DATA points elsewhere (a machine without the shared folder beside the repo).
DATA = pathlib.Path(os.environ.get("ELASTIC_JAX_DATA", HERE.parents[2] / "shared" / "data"))
FIGURES = HERE / "figures"
METRIC = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)
# The animals only: the shared hand4 is stored about 100 times smaller (area 1.0e-4
# against 0.92-1.87), so a path to it is mostly a change of size.
NAMES = ("cat1", "cat2", "horse0")
PAIRS = (("cat1", "cat2"), ("cat1", "horse0"), ("cat2", "horse0"))


def load(name: str, m: int, n: int) -> np.ndarray:
    f = np.load(DATA / f"{name}_50x99.npz")["f"]
    return np.asarray(ej.resample(f, m, n)) if (m, n) != f.shape[1:] else f


def save(fig, name: str) -> str:
    plot.save_figure(fig, FIGURES / name)
    import matplotlib.pyplot as plt

    plt.close(fig)
    return f"figures/{name}"


def geodesics(quick: bool) -> dict:
    m, n = (13, 25) if quick else (25, 49)
    options = ej.ShapeOptions(degree=3, vf_degree=3, n_times=5) if quick else ej.ShapeOptions()
    out, histories = {}, {}
    for a, b in PAIRS:
        start = time.perf_counter()
        res = ej.shape_geodesic(
            load(a, m, n), load(b, m, n), METRIC, modulo="rigid", options=options
        )
        seconds = time.perf_counter() - start
        key = f"{a}-{b}"
        histories[key] = np.asarray(res.energy_history)[: int(res.rounds) + 2]
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
            "energy_history": histories[key].tolist(),
            "figure": save(plot.plot_path(res.path, frames=5), f"geodesic_{key}.png"),
        }
        print(key, out[key]["distance"], f"{seconds:.1f} s", flush=True)
    fig = plot.plot_energy(histories)
    fig.axes[0].set_xlabel("0: parametrized geodesic; k: after registration round k")
    fig.axes[0].set_ylabel("path energy")
    out["energy_figure"] = save(fig, "geodesic_energies.png")
    return out


def multires(quick: bool) -> dict:
    levels = [(4, 5, 13, 25), (7, 9, 25, 49), (9, 13, 50, 99)]
    if quick:
        levels = [(2, 3, 7, 13), (3, 5, 13, 25)]
    out = {"levels": []}
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
                "figure": save(
                    plot.plot_path(res.path, frames=min(5, n_times)), f"multires_{k + 1}.png"
                ),
            }
        )
        print("level", k + 1, out["levels"][-1]["distance"], flush=True)
    return out


def karcher(quick: bool) -> dict:
    m, n = (13, 25) if quick else (25, 49)
    options = ej.ShapeOptions(
        degree=3 if quick else 5, vf_degree=3 if quick else 5, n_times=5 if quick else 7
    )
    shapes_ = np.stack([load(name, m, n) for name in NAMES])
    start = time.perf_counter()
    res = ej.karcher_mean(
        shapes_, METRIC, modulo="rigid", options=options, max_steps=3 if quick else 10
    )
    karcher_s = time.perf_counter() - start
    pca = ej.tangent_pca(res, METRIC)
    start = time.perf_counter()
    fig = plot.plot_modes(pca, METRIC, modes=2, sigmas=1.0, n_times=5 if quick else 7)
    modes_s = time.perf_counter() - start
    history = np.asarray(res.history)
    fig_history = plot.plot_energy(
        history[:, :2], labels=["sum of squared distances", "|mean velocity|"]
    )
    fig_history.axes[0].set_xlabel("Karcher step")
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
        "history": history.tolist(),
        "explained": np.asarray(pca.explained).tolist(),
        "modes_seconds": modes_s,
        "mean_figure": save(plot.plot_path(res.mean), "karcher_mean.png"),
        "inputs_figure": save(
            plot.plot_path(np.asarray(res.registered), frames=len(NAMES)), "karcher_inputs.png"
        ),
        "history_figure": save(fig_history, "karcher_history.png"),
        "modes_figure": save(fig, "pca_modes.png"),
    }
    print("karcher", out["distances"], out["explained"], flush=True)
    return out


PARTS = {"geodesics": geodesics, "multires": multires, "karcher": karcher}


def _parts(text: str) -> list[str]:
    parts = text.split(",")
    unknown = [p for p in parts if p not in PARTS]
    if unknown:
        raise argparse.ArgumentTypeError(f"unknown parts {unknown}; choose from {list(PARTS)}")
    return parts


def main() -> None:
    global FIGURES  # save() writes there; --figures moves it
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parts", type=_parts, default=list(PARTS))
    parser.add_argument("--quick", action="store_true", help="13 x 25, small settings")
    parser.add_argument("--out", type=pathlib.Path, default=HERE / "figures.json")
    parser.add_argument("--figures", type=pathlib.Path, default=FIGURES, help="PNG folder")
    args = parser.parse_args()
    FIGURES = args.figures
    FIGURES.mkdir(parents=True, exist_ok=True)
    stored = json.loads(args.out.read_text()) if args.out.exists() else {}
    for part in args.parts:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ej.ConvergenceWarning)
            stored[part] = PARTS[part](args.quick)
        stored[part]["device"] = str(jax.devices()[0].device_kind)
        stored[part]["jax"] = jax.__version__
        stored[part]["measured"] = time.strftime("%Y-%m-%d")
        # One part at a time, atomically: a later part's failure keeps the earlier ones.
        write_text_atomic(args.out, json.dumps(stored, indent=1) + "\n")


if __name__ == "__main__":
    main()
