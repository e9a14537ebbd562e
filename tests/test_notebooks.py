"""The four notebooks run top to bottom (nbclient) and reach the numbers they promise.

Each notebook's last cell prints a JSON line of its results; the tests read it back.
"""

import json
import pathlib

import numpy as np
import pytest

nbclient = pytest.importorskip("nbclient")
nbformat = pytest.importorskip("nbformat")

NOTEBOOKS = pathlib.Path(__file__).resolve().parents[1] / "notebooks"


def _run(name: str) -> tuple[dict, int]:
    """Execute a notebook in a fresh kernel; return its JSON results and the figures shown."""
    nb = nbformat.read(NOTEBOOKS / f"{name}.ipynb", as_version=4)
    nbclient.NotebookClient(nb, timeout=900, kernel_name="python3").execute()
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs]
    figures = sum("image/png" in o.get("data", {}) for o in outputs)
    text = [o["text"] for o in outputs if o["output_type"] == "stream" and o["name"] == "stdout"]
    return json.loads(text[-1].strip().splitlines()[-1]), figures


def test_parametrized_geodesic_notebook():
    out, figures = _run("01_parametrized_geodesic")
    assert figures == 1
    # 13 x 25 quadrature error of the concentric-spheres closed form (MATH.md 3).
    assert out["sphere_distance"] == pytest.approx(out["closed_form"], rel=2e-2)
    assert out["energy"] < 0.9 * out["straight_energy"]
    assert out["stiff"] > out["soft"]  # bending costs more when c is larger


def test_shape_geodesic_notebook():
    out, figures = _run("02_shape_geodesic")
    assert figures == 2
    assert out["shape"] < 0.1 * out["parametrized"]
    assert out["min_jacobian"] > 0
    assert out["rigid_shape"] < out["rigid_parametrized"]


def test_karcher_mean_notebook():
    out, figures = _run("03_karcher_mean")
    assert figures == 2
    history = np.asarray(out["history"])
    assert history[-1, 0] < history[0, 0]  # the sum of squared distances went down
    mean_sv, input_sv = np.asarray(out["mean_sv"]), np.asarray(out["input_sv"])
    assert np.all(mean_sv >= 0.97 * input_sv.min(axis=0))
    assert np.all(mean_sv <= 1.03 * input_sv.max(axis=0))


def test_any_mesh_notebook():
    out, figures = _run("04_any_mesh")
    assert figures == 1
    assert out["star_center"] is None  # radial projection cannot parametrize the U-tube
    assert out["flipped"] == 0 and abs(out["tiles_minus_4pi"]) < 1e-8
    assert out["min_jacobian"] > 0
    # MATH.md 9: the area bound holds for every quotient; registration lowers the distance.
    assert out["area_bound"] <= out["shape"] < out["parametrized"]
