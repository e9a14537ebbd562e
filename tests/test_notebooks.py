"""The notebooks run top to bottom (nbclient) and reach the numbers they promise.

Each notebook's last cell prints a JSON line of its results; the tests read it back.
"""

import json
import os
import pathlib

import numpy as np
import pytest

from .conftest import COMPILATION_CACHE

nbclient = pytest.importorskip("nbclient")
nbformat = pytest.importorskip("nbformat")

NOTEBOOKS = pathlib.Path(__file__).resolve().parents[1] / "notebooks"
# The kernels compile into the suite's compilation cache (JAX reads its options from the
# environment at start): the notebooks solve some of the configurations the tests solve
# (02 and 04 the same shape solve), and a program one of them compiled is loaded by the
# others. Only the kernels' environment: the notebooks themselves set nothing.
_KERNEL_ENV = {
    **os.environ,
    "JAX_COMPILATION_CACHE_DIR": str(COMPILATION_CACHE),
    "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0.5",
}


def _results(nb) -> tuple[dict, int]:
    """The JSON line a notebook's last cell printed, and the number of figures it shows."""
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs]
    figures = sum("image/png" in o.get("data", {}) for o in outputs)
    text = [o["text"] for o in outputs if o["output_type"] == "stream" and o["name"] == "stdout"]
    return json.loads(text[-1].strip().splitlines()[-1]), figures


def _agree(fresh, stored, path="") -> list[str]:
    """Where the fresh results differ from the stored ones (floats to 2 % relative: other
    machines round otherwise and iterate a step more or less)."""
    if isinstance(stored, dict):
        return [d for k in stored for d in _agree(fresh.get(k), stored[k], f"{path}.{k}")]
    if isinstance(stored, list):
        if not isinstance(fresh, list) or len(fresh) != len(stored):
            return [f"{path}: {fresh!r} != {stored!r}"]
        return [
            d
            for i, (a, b) in enumerate(zip(fresh, stored, strict=True))
            for d in _agree(a, b, f"{path}[{i}]")
        ]
    if isinstance(stored, float) and isinstance(fresh, (int, float)):
        ok = abs(fresh - stored) <= 0.02 * abs(stored) + 1e-9
        return [] if ok else [f"{path}: {fresh!r} != {stored!r}"]
    return [] if fresh == stored else [f"{path}: {fresh!r} != {stored!r}"]


def _run(name: str) -> tuple[dict, int]:
    """Execute a notebook in a fresh kernel; return its JSON results and the figures shown.

    The notebook is stored with its outputs (the site renders them): the fresh results must
    agree with the stored ones, or the stored figures are out of date (rerun
    docs/execute_notebooks.py)."""
    nb = nbformat.read(NOTEBOOKS / f"{name}.ipynb", as_version=4)
    stored, stored_figures = _results(nb)
    nbclient.NotebookClient(nb, timeout=900, kernel_name="python3").execute(env=_KERNEL_ENV)
    out, figures = _results(nb)
    assert figures == stored_figures
    assert _agree(out, stored) == []
    return out, figures


@pytest.mark.slow
def test_parametrized_geodesic_notebook():
    out, figures = _run("01_parametrized_geodesic")
    assert figures == 1
    # 13 x 25 quadrature error of the concentric-spheres closed form (docs/math.md §3).
    assert out["sphere_distance"] == pytest.approx(out["closed_form"], rel=2e-2)
    assert out["energy"] < 0.9 * out["straight_energy"]
    assert out["stiff"] > out["soft"]  # bending costs more when c is larger


@pytest.mark.slow
def test_shape_geodesic_notebook():
    out, figures = _run("02_shape_geodesic")
    assert figures == 2
    assert out["shape"] < 0.1 * out["parametrized"]
    assert out["min_jacobian"] > 0
    assert out["rigid_shape"] < out["rigid_parametrized"]


@pytest.mark.slow
def test_karcher_mean_notebook():
    out, figures = _run("03_karcher_mean")
    assert figures == 2
    history = np.asarray(out["history"])
    assert history[-1, 0] < history[0, 0]  # the sum of squared distances went down
    mean_sv, input_sv = np.asarray(out["mean_sv"]), np.asarray(out["input_sv"])
    assert np.all(mean_sv >= 0.97 * input_sv.min(axis=0))
    assert np.all(mean_sv <= 1.03 * input_sv.max(axis=0))


@pytest.mark.slow  # 53-69 s on 2 cores
def test_any_mesh_notebook():
    out, figures = _run("04_any_mesh")
    assert figures == 1
    assert out["star_center"] is None  # radial projection cannot parametrize the U-tube
    assert out["flipped"] == 0 and abs(out["tiles_minus_4pi"]) < 1e-8
    assert out["min_jacobian"] > 0
    # docs/math.md §9: the area bound holds for every quotient; registration lowers the distance.
    assert out["area_bound"] <= out["shape"] < out["parametrized"]


@pytest.mark.slow
def test_statistics_notebook():
    out, figures = _run("05_statistics")
    assert figures == 2  # the modes, then A, A', B, B'
    assert out["karcher_result"] in ("mean_velocity_small", "sum_sq_stalled")
    history = np.asarray(out["karcher_history"])
    assert history[-1, 0] < 0.9 * history[0, 0]  # measured 2.29 from 2.84
    assert history[-1, 1] < 1e-3 * history[0, 1]  # measured 4.6e-5 from 0.30
    # Two factors, two modes: measured 0.761 + 0.239 = 0.99953 of the variance, and each
    # factor read back from the two scores with R^2 0.995 and 0.998.
    explained = np.asarray(out["explained"])
    assert explained[:2].sum() >= 0.998 and explained[1] >= 0.15
    assert min(out["factor_r2"]) >= 0.98
    # Transport keeps the deformation's size (Galerkin drift measured +9.9e-9, the
    # ladder's was -6.1e-3; d(B, B') / d(A, A') - 1 measured +6.3e-3, with the ladder
    # -9e-5), which copying the vector's coordinates does not (+13 %).
    assert out["transport_converged"]
    assert abs(out["norm_drift"]) <= 0.02
    assert out["distance_b"] == pytest.approx(out["distance_a"], rel=0.01)
    assert out["norm_a"] == pytest.approx(out["distance_a"], rel=0.02)
    assert out["copied_norm_b"] > 1.05 * out["norm_a"]
    # The 25 % stretch along x carries over as a stretch along x: B' / B measured
    # (1.292, 0.952, 0.995) against A' / A = (1.25, 1, 1).
    ratio_a, ratio_b = np.log(out["ratio_a"]), np.log(out["ratio_b"])
    np.testing.assert_allclose(ratio_a, [np.log(1.25), 0.0, 0.0], atol=1e-12)
    assert abs(ratio_b[0] - ratio_a[0]) <= 0.06
    assert np.max(np.abs(ratio_b[1:])) <= 0.08


@pytest.mark.slow
def test_fit_metric_notebook():
    out, figures = _run("06_fit_metric")
    assert figures == 3  # six of the shapes, then the two distance matrices (one each)
    assert out["converged"]
    assert out["objective_after"] < out["objective_before"]
    # Held out: the fitted metric classifies the bending family, the default does not.
    assert out["fitted_nn"] >= 0.9 and out["fitted_nn"] >= out["default_nn"] + 0.15
    assert out["fitted_first_tier"] > out["default_first_tier"]
    # Bending is the signal: the fitted metric weighs it most.
    assert out["metric"][2] > max(out["metric"][:2])


@pytest.mark.slow  # about five minutes on 2 cores
def test_shared_animals_notebook():
    from .conftest import DATA

    if not DATA.exists():
        pytest.skip(f"{DATA} is absent")
    out, figures = _run("07_shared_animals")
    assert figures == 2  # the modes, then the transfer
    assert out["karcher_converged"]
    history = np.asarray(out["history"])
    assert np.all(np.diff(history[:, 0]) <= 0)  # the SSD never rises
    # The mean is a better centre than every member (the same capped levels).
    assert history[-1, 0] < min(out["member_ssd"])
    # The deformation keeps its size: the carried norm drifts by at most 1e-3, and both
    # shots (from cat1 and from cat2) start at one speed and get through.
    assert abs(out["norm_drift"]) <= 1e-3
    assert all(out["shots_converged"])
    assert out["speeds"][1] == pytest.approx(out["speeds"][0], rel=0.02)
    assert out["speeds"][1] == pytest.approx(out["carried_norm"], rel=0.01)
