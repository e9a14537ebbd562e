"""Evaluating a gridded surface off the grid: bilinear interpolation in (phi, theta) (math §6)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .grid import angles_np
from .validation import as_surface, check_grid_shape


def sample_at(
    f: Float[ArrayLike, "*batch 3 m n"],
    phi: Float[ArrayLike, "..."],
    theta: Float[ArrayLike, "..."],
) -> Float[Array, "..."]:
    """f at points (phi, theta) by bilinear interpolation in the grid's angles: (..., 3, *pts).

    Periodic in theta; phi in [0, pi] lies between grid rows, and the pole rows are
    constant, so no half-turn is needed for a bilinear stencil. Differentiable in f and
    (almost everywhere) in phi and theta.
    """
    m, n = f.shape[-2:]
    x = jnp.clip(phi * ((m - 1) / np.pi), 0.0, m - 1.0)
    row = jnp.clip(jnp.floor(x), 0, m - 2)
    y = jnp.mod(theta * ((n - 1) / (2.0 * np.pi)), n - 1.0)
    col = jnp.clip(jnp.floor(y), 0, n - 2)
    wx, wy = x - row, y - col
    i0, j0 = row.astype(jnp.int32), col.astype(jnp.int32)

    def at(i, j):
        return f[..., i, j]

    lead = (1,) * (f.ndim - 2)  # the weights broadcast over (..., 3)
    wx, wy = (w.astype(f.dtype).reshape(lead + w.shape) for w in (wx, wy))
    top = at(i0, j0) * (1 - wy) + at(i0, j0 + 1) * wy
    bottom = at(i0 + 1, j0) * (1 - wy) + at(i0 + 1, j0 + 1) * wy
    return top * (1 - wx) + bottom * wx


@jax.jit
def _resample(f, phi, theta):
    return sample_at(f, phi[:, None], theta[None, :])


def resample(f: Float[ArrayLike, "*batch 3 m0 n0"], m: int, n: int) -> Float[Array, "*batch 3 m n"]:
    """The surface on another m x n grid, by bilinear interpolation (:ref:`math §6 <math-6>`).

    For multiresolution and for bringing shapes to a common grid; error O(h^2) in the
    source grid's spacing. Pole rows stay constant and the seam column exact.

    Args:
        f: ``(..., 3, m0, n0)``.
        m, n: the new grid size (n odd, both >= 5).

    Returns:
        ``(..., 3, m, n)``.
    """
    f = as_surface(f, "f", check_immersion=False)
    check_grid_shape((3, m, n), "the new grid")
    phi, theta = angles_np(m, n)
    return _resample(f, jnp.asarray(phi, f.dtype), jnp.asarray(theta, f.dtype))
