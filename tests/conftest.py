"""Test configuration: float64 and strict promotion for the tests only (never on import)."""

from __future__ import annotations

import pathlib

import jax
import numpy as np
import pytest

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
jax.config.update("jax_numpy_dtype_promotion", "strict")

DATA = pathlib.Path(__file__).resolve().parents[1].parent / "shared" / "data"

# Tolerances for float64 identities and for float32, in one place.
RTOL = {np.dtype("float64"): 1e-12, np.dtype("float32"): 1e-5}


def load_shape(name: str) -> np.ndarray:
    """A real surface from ../shared/data, (3, 50, 99) float64; skips the test when absent."""
    path = DATA / f"{name}_50x99.npz"
    if not path.exists():
        pytest.skip(f"{path} is absent")
    return np.load(path)["f"]


@pytest.fixture
def cats() -> tuple[np.ndarray, np.ndarray]:
    return load_shape("cat1"), load_shape("cat2")


def relerr(x, y) -> float:
    x, y = np.asarray(x), np.asarray(y)
    return float(np.max(np.abs(x - y)) / np.max(np.abs(y)))
