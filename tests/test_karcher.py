import json
import os
import subprocess
import sys

import jax.numpy as jnp
import numpy as np
import pytest

import elastic_jax as ej
from elastic_jax import shapes

M, N = 13, 25
METRIC = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)
# The central scheme: with N = 5 forward differences the velocity average cycles (the
# first segment's metric sits at the mean; its O(|step|^2) term moves the fixed point).
FAST = {"degree": 3, "n_times": 5, "scheme": "central"}


def _collection():
    return jnp.stack(
        [
            shapes.sample(shapes.bumpy, M, N),
            shapes.sample(shapes.ellipsoid, M, N, axes=(1.1, 0.9, 0.7)),
            shapes.sample(shapes.bumpy, M, N, scale=1.3),
        ]
    )


def test_concentric_spheres_mean_is_the_mean_radius():
    radii = [1.0, 1.5, 2.2]
    spheres = jnp.stack([shapes.sample(shapes.sphere, M, N, radius=r) for r in radii])
    res = ej.karcher_mean(spheres, METRIC, modulo="none", **FAST)
    assert res.converged
    expected = shapes.sample(shapes.sphere, M, N, radius=float(np.mean(radii)))
    assert float(jnp.abs(res.mean - expected).max()) < 1e-6
    # Distances from the mean: sqrt(8 pi b) |r_i - r|, to the 13 x 25 discretization error.
    exact = np.sqrt(8 * np.pi) * np.abs(np.asarray(radii) - np.mean(radii))
    np.testing.assert_allclose(res.distances, exact, rtol=3e-2)


@pytest.mark.slow
def test_strategies_agree_and_permutation_does_not_matter():
    coll = _collection()
    options = {"modulo": "none", "tol": 1e-6, "max_steps": 15, **FAST}
    loop = ej.karcher_mean(coll, METRIC, strategy="loop", **options)
    assert loop.converged
    for strategy in ("vmap", "map"):
        other = ej.karcher_mean(coll, METRIC, strategy=strategy, **options)
        assert float(jnp.abs(other.mean - loop.mean).max()) < 1e-6
    permuted = ej.karcher_mean(coll[::-1], METRIC, init=coll[0], **options)
    assert float(jnp.abs(permuted.mean - loop.mean).max()) < 1e-5
    np.testing.assert_allclose(permuted.distances[::-1], loop.distances, rtol=1e-4)
    # Sum of squared distances decreases along the iteration.
    assert np.all(np.diff(loop.history[:, 0]) <= 1e-9 * loop.history[0, 0])


def test_resume_after_a_kill_equals_an_uninterrupted_run(tmp_path):
    coll = _collection()
    options = {"modulo": "none", "tol": 1e-9, "max_steps": 4, **FAST}
    full = ej.karcher_mean(coll, METRIC, **options)
    path = tmp_path / "karcher.npz"

    def kill_after_two(info):
        if info["step"] == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        ej.karcher_mean(coll, METRIC, checkpoint=path, progress=kill_after_two, **options)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["karcher.npz"]  # nothing half-written
    resumed = ej.karcher_mean(coll, METRIC, checkpoint=path, resume=True, **options)
    np.testing.assert_allclose(resumed.mean, full.mean, atol=1e-12)
    np.testing.assert_allclose(resumed.history, full.history, rtol=1e-12)
    with pytest.raises(ValueError, match="different shapes or settings"):
        ej.karcher_mean(coll[::-1], METRIC, checkpoint=path, resume=True, **options)


def test_distance_matrix_is_symmetric_and_matches_single_solves(tmp_path):
    coll = _collection()
    d = np.asarray(ej.distance_matrix(coll, METRIC, modulo="none", **FAST))
    np.testing.assert_array_equal(d, d.T)
    np.testing.assert_array_equal(np.diag(d), 0.0)
    for i, j in [(0, 1), (0, 2), (1, 2)]:
        single = float(ej.geodesic(coll[i], coll[j], METRIC, **FAST).distance)
        assert d[i, j] == pytest.approx(single, rel=1e-9)
    # Killed after the first chunk, resumed: the same matrix.
    path = tmp_path / "pairs.npz"

    def kill(info):
        if info["pairs_done"] == 1:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        ej.distance_matrix(
            coll, METRIC, modulo="none", batch_size=1, checkpoint=path, progress=kill, **FAST
        )
    resumed = ej.distance_matrix(
        coll, METRIC, modulo="none", batch_size=1, checkpoint=path, resume=True, **FAST
    )
    np.testing.assert_allclose(resumed, d, rtol=1e-12)


SHARDED = """
import json, jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import elastic_jax as ej
from elastic_jax import shapes
m, n = 13, 25
coll = jnp.stack([shapes.sample(shapes.bumpy, m, n),
                  shapes.sample(shapes.ellipsoid, m, n, axes=(1.1, 0.9, 0.7)),
                  shapes.sample(shapes.bumpy, m, n, scale=1.3)])
res = ej.karcher_mean(coll, ej.SplitMetric(1.0, 1.0, 0.1, 0.0), modulo="none", strategy="vmap",
                      degree=3, n_times=5, scheme="central", max_steps=2)
print(json.dumps({"devices": jax.device_count(), "mean": res.mean.ravel().tolist()}))
"""


@pytest.mark.slow
def test_sharded_equals_unsharded():
    env = {
        **os.environ,
        "XLA_FLAGS": "--xla_force_host_platform_device_count=4",
        "JAX_PLATFORMS": "cpu",
    }
    out = subprocess.run(
        [sys.executable, "-c", SHARDED],
        env=env,
        capture_output=True,
        text=True,
        check=True,
        timeout=600,
    )
    sharded = json.loads(out.stdout.strip().splitlines()[-1])
    assert sharded["devices"] == 4
    coll = _collection()
    single = ej.karcher_mean(coll, METRIC, modulo="none", strategy="vmap", max_steps=2, **FAST)
    np.testing.assert_allclose(np.asarray(sharded["mean"]).reshape(3, M, N), single.mean, atol=1e-9)


def test_errors():
    coll = _collection()
    with pytest.raises(ValueError, match="modulo must be one of"):
        ej.karcher_mean(coll, METRIC, modulo="affine")
    with pytest.raises(ValueError, match="strategy must be one of"):
        ej.distance_matrix(coll, METRIC, strategy="threads")
    with pytest.raises(ValueError, match=r"\(K, 3, m, n\) with K >= 2"):
        ej.karcher_mean(coll[:1], METRIC)


# Inner shape geodesics at 13 x 25 stop at interpolation-noise energies and may warn.
@pytest.mark.filterwarnings("ignore::elastic_jax.ConvergenceWarning")
@pytest.mark.slow
def test_mean_is_invariant_to_reparametrization_and_rotation():
    f = shapes.sample(shapes.bumpy, M, N)
    moved = shapes.sample(shapes.bumpy, M, N, rotation=shapes.random_rotation(1))
    turned = jnp.einsum(
        "ij,jmn->imn",
        shapes.random_rotation(2),
        shapes.sample(shapes.bumpy, M, N, rotation=shapes.random_rotation(3)),
    )
    options = {"degree": 3, "vf_degree": 3, "n_times": 5, "scheme": "central", "outer_steps": 1}
    res = ej.karcher_mean(
        jnp.stack([f, moved, turned]), METRIC, modulo="rigid", max_steps=3, **options
    )
    to_f = ej.shape_geodesic(res.mean, f, METRIC, modulo="rigid", **options).distance
    reference = ej.shape_geodesic(
        shapes.sample(shapes.ellipsoid, M, N), f, METRIC, modulo="rigid", **options
    )
    assert float(to_f) < 0.1 * float(reference.distance)
    assert float(jnp.max(res.distances)) < 0.1 * float(reference.distance)
