"""Distance matrices and Karcher means on a real Dask LocalCluster (two worker processes)
equal the in-process ones, and a worker killed mid-job costs nothing but time."""

import os
import signal
import warnings

import jax.numpy as jnp
import numpy as np
import pytest

import elastic_jax as ej
from elastic_jax import shapes

from .conftest import COMPILATION_CACHE

distributed = pytest.importorskip("distributed")

M, N = 13, 25
METRIC = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)
FAST = ej.ShapeOptions(degree=3, n_times=5)  # tests/test_karcher.py's "none" options


def _collection():
    return jnp.stack(
        [
            shapes.sample(shapes.bumpy, M, N),
            shapes.sample(shapes.ellipsoid, M, N, axes=(1.1, 0.9, 0.7)),
            shapes.sample(shapes.bumpy, M, N, scale=1.3),
            shapes.sample(shapes.ellipsoid, M, N, axes=(0.8, 1.0, 1.2)),
        ]
    )


@pytest.fixture(scope="module")
def client():
    with (
        distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, dashboard_address="127.0.0.1:0"
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        # The workers load what this session compiled (and what the other one compiles).
        ej.enable_compilation_cache(COMPILATION_CACHE, client=client, exported=False)
        yield client


def test_distance_matrix_and_karcher_mean_equal_the_in_process_ones(client):
    coll = _collection()
    kwargs = {"modulo": "none", "options": FAST}
    job = ej.JobOptions(strategy="map", batch_size=2)
    here = ej.distance_matrix(coll, METRIC, **kwargs, job=job)
    seen = []
    there = ej.distance_matrix(
        coll, METRIC, **kwargs, job=job.replace(progress=seen.append, client=client)
    )
    np.testing.assert_allclose(there.distances, here.distances, rtol=1e-9, atol=0)
    np.testing.assert_array_equal(there.pairs_converged, here.pairs_converged)
    assert int(there.num_steps) == int(here.num_steps)
    # Three chunks of two pairs, reported as they arrived, with an estimate of the rest.
    assert [info["pairs_done"] for info in seen] == [2, 4, 6]
    assert seen[-1]["eta_s"] == 0.0 and all(info["pairs"] == 6 for info in seen)

    # A Karcher mean: chunks of 2 and 1 shapes (padded to 2), two steps.
    three = coll[:3]
    kwargs = {**kwargs, "max_steps": 2}
    here = ej.karcher_mean(three, METRIC, **kwargs, job=job)
    there = ej.karcher_mean(three, METRIC, **kwargs, job=job.replace(client=client))
    assert there.num_steps == here.num_steps == 2
    np.testing.assert_allclose(there.mean, here.mean, rtol=0, atol=1e-9)
    np.testing.assert_allclose(there.history, here.history, rtol=1e-9)
    np.testing.assert_allclose(there.velocities, here.velocities, rtol=0, atol=1e-9)


def test_a_killed_worker_has_its_task_rerun(client, tmp_path):
    coll = _collection()
    kwargs = {"modulo": "none", "options": FAST}
    job = ej.JobOptions(strategy="map", batch_size=1)
    # Chunks of two pairs here, one pair a task there: each pair is solved on its own,
    # so neither the batch nor the worker changes its numbers.
    here = ej.distance_matrix(coll, METRIC, **kwargs, job=job.replace(batch_size=2))
    pids = list(client.run(os.getpid).values())
    killed = []

    def kill_one(info):
        if not killed:  # after the first finished task: the other worker is mid-task
            os.kill(pids[0], signal.SIGKILL)
            killed.append(info["pairs_done"])

    path = tmp_path / "pairs.npz"
    there = ej.distance_matrix(
        coll, METRIC, **kwargs, job=job.replace(checkpoint=path, progress=kill_one, client=client)
    )
    assert killed == [1]
    np.testing.assert_allclose(there.distances, here.distances, rtol=1e-9, atol=0)
    saved = np.load(path)
    assert saved["done"].all() and saved["done"].size == 6  # every pair, once
    np.testing.assert_allclose(saved["values"], here.distances[np.triu_indices(4, 1)], rtol=1e-9)
    client.wait_for_workers(2, timeout=120)  # the nanny restarted the killed one
    assert pids[0] not in client.run(os.getpid).values()


@pytest.mark.slow
def test_fit_metric_on_the_cluster_equals_the_in_process_fit(client):
    coll, labels = shapes.two_classes("bending", 4, M, N, seed=3)
    kwargs = {"modulo": "none", "options": FAST}
    job = ej.JobOptions(strategy="map", batch_size=2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ej.ConvergenceWarning)
        here = ej.fit_metric(coll, labels, max_steps=2, **kwargs, job=job)
        there = ej.fit_metric(coll, labels, max_steps=2, **kwargs, job=job.replace(client=client))
    assert int(there.num_steps) == int(here.num_steps) >= 1
    for c in "abcd":
        assert getattr(there.metric, c) == pytest.approx(getattr(here.metric, c), rel=1e-9)
    np.testing.assert_allclose(there.history, here.history, rtol=1e-9)
    np.testing.assert_allclose(there.distances, here.distances, rtol=1e-9)


def test_bad_clients_are_refused():
    coll = _collection()[:2]
    with pytest.raises(ej.InputError, match="dask.distributed.Client"):
        ej.distance_matrix(coll, METRIC, modulo="none", options=FAST, job=ej.JobOptions(client=42))
