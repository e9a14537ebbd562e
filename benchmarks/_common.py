"""Shared pieces of the benchmark scripts: timing, environment record, JSON output."""

from __future__ import annotations

import json
import math
import os
import pathlib
import platform
import statistics
import sys
import time
from collections.abc import Callable
from importlib import metadata
from typing import TYPE_CHECKING

import jax

if TYPE_CHECKING:
    import numpy as np


def environment() -> dict:
    """Versions and device of this run."""
    versions = {}
    for package in ("jax", "jaxlib", "numpy", "optimistix", "jaxopt", "elastic-jax"):
        try:
            versions[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            versions[package] = None
    device = jax.devices()[0]
    return {
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "cpu_count": os.cpu_count(),
        "device": {
            "platform": device.platform,
            "kind": device.device_kind,
            "count": jax.device_count(),
        },
        "versions": versions,
    }


def time_calls(fn: Callable[[], object], repeats: int) -> dict:
    """Wall-clock seconds of ``repeats`` calls (each blocked until ready): min, median, all."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    return {"min_s": min(times), "median_s": statistics.median(times), "repeats": repeats}


def _finite(value):
    """NaN and inf (a failed step's figures) as null: JSON has no such numbers."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    return value


def emit(record: dict) -> None:
    """Print one JSON record per line (machine-readable; NaN and inf as null)."""
    print(json.dumps(_finite(record), sort_keys=True, allow_nan=False), flush=True)


# The authors' surfaces beside the repository (../shared/data/ShapeData), when present, a
# development convenience: elsewhere elastic_jax.datasets looks in $ELASTIC_JAX_DATA and
# its cache, then downloads.
SHAPE_DATA = pathlib.Path(__file__).resolve().parents[2] / "shared" / "data" / "ShapeData"


def shape(name: str) -> np.ndarray | None:
    """The authors' surface ``name`` (3, 50, 99) from ``elastic_jax.datasets``, or None when
    its file cannot be had (pooch missing, offline). A checksum mismatch still raises."""
    if SHAPE_DATA.is_dir():
        os.environ.setdefault("ELASTIC_JAX_DATA", str(SHAPE_DATA))
    import elastic_jax as ej

    try:
        return ej.datasets.load(name)
    except (ImportError, OSError):
        return None


def cat_pair(m: int, n: int):
    """The authors' cats on an m x n grid (resampled from 50 x 99), or None when absent."""
    import numpy as np

    import elastic_jax as ej

    f1, f2 = shape("cat1"), shape("cat2")
    if f1 is None or f2 is None:
        return None
    if (m, n) != (50, 99):
        f1, f2 = (np.asarray(ej.resample(f, m, n)) for f in (f1, f2))
    return f1, f2


def deformed(base, rng, *, size: float = 0.0, method: str = "bilinear"):
    """``base`` (3, m, n) under a random stretch (log-axes within +-0.1 along random axes),
    a random size factor exp(U(-size, size)) when size > 0, a Moebius map of its parameter
    sphere (|a| uniform in [0, 0.3], read by ``method``) and a random rotation in R^3."""
    import numpy as np

    import elastic_jax as ej
    from elastic_jax import shapes

    m, n = base.shape[-2:]
    axes = shapes.random_rotation(int(rng.integers(1 << 30)))
    stretch = axes @ np.diag(np.exp(rng.uniform(-0.1, 0.1, 3))) @ axes.T
    if size > 0:
        stretch = stretch * np.exp(rng.uniform(-size, size))
    a = rng.normal(size=3)
    a = rng.uniform(0.0, 0.3) * a / np.linalg.norm(a)
    f = np.asarray(ej.reparametrize(base, ej.moebius(ej.sphere_points(m, n), a), method=method))
    rotation = shapes.random_rotation(int(rng.integers(1 << 30)))
    return np.einsum("ij,jk,kmn->imn", rotation, stretch, f)


def moebius_read(f, boost, rotation, grid=None, method: str = "spline"):
    """``rotation`` (f o phi_a) (math §9): f (3, m, n) read through the Moebius map with
    boost a = ``boost`` (3,) at the points of ``grid`` (default: f's own) by ``method``,
    its pole rows and seam column then made exact (every node of a pole row is one point,
    the seam repeats the first column), and turned by the 3 x 3 ``rotation``."""
    import jax.numpy as jnp

    import elastic_jax as ej

    points = ej.moebius(ej.sphere_points(*(grid or f.shape[-2:])), jnp.asarray(boost))
    read = ej.reparametrize(jnp.asarray(f), points, method=method)
    read = read.at[:, 0, :].set(read[:, 0, :1]).at[:, -1, :].set(read[:, -1, :1])
    read = read.at[:, :, -1].set(read[:, :, 0])
    return jnp.einsum("ij,jmn->imn", jnp.asarray(rotation), read)
