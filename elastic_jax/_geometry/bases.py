"""The spherical-harmonic surface basis of the path's perturbation (math §5, 7) on a grid,
and the straight line's frames that it perturbs: what geodesics, registration and
statistics all build paths from."""

from __future__ import annotations

from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike

from .._runtime.cache import cached
from .differential import interior_frame
from .harmonics import harmonics_np

__all__ = [
    "basis_np",
    "frames_between",
    "path_from_coefficients",
    "perturbed_frames",
]


@cached
def basis_np(m: int, n: int, degree: int) -> tuple[np.ndarray, np.ndarray]:
    """Harmonics of degree 1..deg as ``(K, m n)`` and their differentials as ``(K, 2 P)``.

    P = (m - 2)(n - 1) interior points. One matmul with the second gives the
    perturbation of every frame's differential (measured faster than an einsum).
    """
    y = harmonics_np(m, n, degree).values[1:]
    a1, a2 = interior_frame(y)
    k = y.shape[0]
    return y.reshape(k, m * n), np.concatenate([a1.reshape(k, -1), a2.reshape(k, -1)], axis=1)


def frames_between(start: Sequence[ArrayLike], end: Sequence[ArrayLike], n_times: int):
    """Interior frames of the straight line between two surfaces given by their frames."""
    t = jnp.linspace(0.0, 1.0, n_times, dtype=start[0].dtype).reshape(n_times, 1, 1, 1)
    # a + t (b - a): velocities are exactly zero when f1 = f2.
    return [a[None] + t * (b - a)[None] for a, b in zip(start, end, strict=True)]


def perturbed_frames(straight: Sequence[Array], coefficients: ArrayLike, dframe: ArrayLike):
    """Frames of the straight line plus sum_j C[k, j] S_j on the interior time points."""
    s1, s2 = straight
    n_inner, shape = s1.shape[0] - 2, s1.shape[1:]
    k = dframe.shape[0]
    points = dframe.shape[1] // 2
    pert = (coefficients.reshape(-1, k) @ dframe).reshape(n_inner, 3, 2 * points)
    p1 = pert[..., :points].reshape((n_inner, *shape))
    p2 = pert[..., points:].reshape((n_inner, *shape))
    return s1.at[1:-1].add(p1), s2.at[1:-1].add(p2)


def path_from_coefficients(
    f1: ArrayLike, f2: ArrayLike, coefficients: ArrayLike, values: ArrayLike, n_times: int
):
    """The path (N, 3, m, n): straight line plus the basis perturbation (paper eq. (4.2))."""
    m, n = f1.shape[-2:]
    k = values.shape[0]
    t = jnp.linspace(0.0, 1.0, n_times, dtype=f1.dtype)[1:-1].reshape(n_times - 2, 1, 1, 1)
    interior = f1[None] + t * (f2 - f1)[None]
    interior = interior + (coefficients.reshape(-1, k) @ values).reshape(n_times - 2, 3, m, n)
    return jnp.concatenate([f1[None], interior, f2[None]])
