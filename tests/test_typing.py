"""The jaxtyping annotations hold at runtime: the public API run under jaxtyping's import
hook (every annotated function and dataclass checked by beartype, array shapes and
dtypes included) gives the same numbers as without it."""

import json
import subprocess
import sys

import numpy as np
import pytest

from .conftest import COMPILATION_CACHE

pytest.importorskip("beartype")

# One script, run with and without the hook: both print the same JSON record.
SCRIPT = """
import json, sys, warnings
import jax
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_compilation_cache_dir", sys.argv[2])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
import numpy as np
if sys.argv[1] == "checked":
    from jaxtyping import install_import_hook
    with install_import_hook("elastic_jax", "beartype.beartype"):
        import elastic_jax as ej
        from elastic_jax import io, shapes
else:
    import elastic_jax as ej
    from elastic_jax import io, shapes

warnings.simplefilter("ignore", ej.ConvergenceWarning)
m, n = 13, 25
metric = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)
f1 = np.asarray(shapes.sample(shapes.bumpy, m, n))
f2 = np.asarray(shapes.sample(shapes.bent_cylinder, m, n))
u = np.asarray(shapes.sample(shapes.ellipsoid, m, n, axes=(1.0, 0.8, 0.6)))
w = np.array([[0.3, -0.2, 0.1], [0.0, 0.0, 0.0]])
gamma = ej.moebius(ej.sphere_points(m, n), np.array([0.2, 0.1, 0.0]))
shape_options = ej.ShapeOptions(degree=4, vf_degree=4, n_times=5, rtol=None)
out = {
    "energy": ej.path_energy(metric, ej.straight_path(f1, f2, 5)),
    "length": ej.path_length(metric, ej.straight_path(f1, f2, 5)),
    "inner": ej.metric_inner(metric, f1, u, f2),
    "srnf": ej.srnf_distance(f1, f2),
    "area": ej.surface_area(f1),
    "differential": ej.differential(f1).sum(),
    "integral": ej.integrate(f1[0]),
    "reparametrized": ej.reparametrize(f1, gamma).sum(),
    "resampled": ej.resample(f1, 25, 49).sum(),
    "so3": ej.so3_log(ej.so3_exp(w)).sum(),
    "geodesic": ej.geodesic(f1, f2, metric, degree=3, n_times=5).distance,
    "shape": ej.shape_geodesic(f1, f2, metric, modulo="rigid", options=shape_options).distance,
    "matrix": ej.distance_matrix(
        np.stack([f1, f2, 1.5 * f1]), metric, modulo="none",
        options=ej.ShapeOptions(degree=3, n_times=5),
        job=ej.JobOptions(strategy="map", batch_size=2),
    ).distances.sum(),
}
out = {key: float(value) for key, value in out.items()}
# The hook is on: a wrong shape is caught by the annotation before the function body.
try:
    ej.so3_exp(np.zeros(2))
except Exception as err:
    out["bad_shape_error"] = type(err).__name__
print(json.dumps(out))
"""


@pytest.mark.slow
def test_the_annotations_hold_at_runtime(capsys, monkeypatch):
    run = subprocess.run(
        [sys.executable, "-c", SCRIPT, "checked", str(COMPILATION_CACHE)],
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert run.returncode == 0, run.stderr[-3000:]
    checked = json.loads(run.stdout.strip().splitlines()[-1])
    # The same script here, without the hook (this session has compiled its solves).
    monkeypatch.setattr(sys, "argv", ["script", "plain", str(COMPILATION_CACHE)])
    exec(compile(SCRIPT, "typing_script", "exec"), {"__name__": "typing_script"})
    plain = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert checked.pop("bad_shape_error") == "TypeCheckError"
    assert plain.pop("bad_shape_error") == "InputError"
    assert checked.keys() == plain.keys()
    for key in plain:
        assert np.isfinite(plain[key]), key
        assert checked[key] == pytest.approx(plain[key], rel=1e-12), key
