"""``python -m elastic_jax`` runs the main job and reports what the library computes."""

import json
import subprocess
import sys

import numpy as np

import elastic_jax as ej
from elastic_jax import shapes


def test_main_job_matches_the_library(tmp_path):
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "elastic_jax",
            "--grid",
            "13",
            "25",
            "--degree",
            "3",
            "--times",
            "5",
            "--out",
            str(tmp_path),
        ],
        capture_output=True,
        text=True,
        check=True,
        timeout=300,
    )
    summary = json.loads(out.stdout)
    f1 = shapes.sample(shapes.bent_cylinder, 13, 25, curvature=0.0)
    f2 = shapes.sample(shapes.bent_cylinder, 13, 25, curvature=0.6, half_length=1.2)
    res = ej.geodesic(f1, f2, ej.SplitMetric(1.0, 1.0, 0.1, 0.0), degree=3, n_times=5)
    assert summary["converged"] is True
    assert abs(summary["distance"] - float(res.distance)) < 1e-9 * float(res.distance)
    saved = np.load(tmp_path / "path.npz")
    np.testing.assert_allclose(saved["path"], np.asarray(res.path), atol=1e-9)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["path.npz"]  # no temporary left
