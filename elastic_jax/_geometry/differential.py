"""The differential df as a field of 3 x 2 matrices (math §2)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._checks import grid_array


def _phi_rows_extended(g: Array) -> Array:
    """Rows -1..m of ``g (..., m, n-1)``: beyond a pole lies the neighbouring row half a turn on.

    f(-dphi, theta) = f(dphi, theta + pi) and f(pi + dphi, theta) = f(pi - dphi, theta + pi);
    n - 1 is even, so theta + pi is the column (n - 1) / 2 further on.
    """
    half = g.shape[-1] // 2
    above = jnp.roll(g[..., 1:2, :], -half, axis=-1)
    below = jnp.roll(g[..., -2:-1, :], -half, axis=-1)
    return jnp.concatenate([above, g, below], axis=-2)


def interior_frame(f: Float[ArrayLike, "*batch m n"]) -> tuple[ArrayLike, ArrayLike]:
    """Columns of df on interior rows and distinct columns.

    Returns ``(a1, a2)``, each ``(..., m-2, n-1)`` for ``f (..., m, n)`` (usually
    ``(..., 3, m, n)``; numpy in, numpy out): a1 = f_theta / sin(phi), a2 = f_phi,
    by central differences (periodic in theta, half-turn rule across the poles). These
    are the only grid points with quadrature weight, so every integral is built on them.
    Acts on the last two axes only, so any leading shape works; a numpy input gives
    numpy output (used to precompute the differentials of the bases in float64).
    """
    xp = np if isinstance(f, np.ndarray) else jnp
    m, n = f.shape[-2:]
    g = f[..., :-1]  # distinct columns; the seam column repeats column 0
    dphi = np.pi / (m - 1)
    dtheta = 2.0 * np.pi / (n - 1)
    inner = g[..., 1:-1, :]
    f_theta = (xp.roll(inner, -1, axis=-1) - xp.roll(inner, 1, axis=-1)) / (2.0 * dtheta)
    sin_phi = np.sin(np.arange(1, m - 1) * dphi).reshape((1,) * (f.ndim - 2) + (m - 2, 1))
    a1 = f_theta / xp.asarray(sin_phi, dtype=f.dtype)
    a2 = (g[..., 2:, :] - g[..., :-2, :]) / (2.0 * dphi)
    return a1, a2


def pole_phi_derivative(f: Array) -> tuple[Array, Array]:
    """f_phi on the two pole rows, ``(..., 3, n-1)`` each (central, across the pole)."""
    m = f.shape[-2]
    dphi = np.pi / (m - 1)
    ext = _phi_rows_extended(f[..., :-1])
    north = (ext[..., 2, :] - ext[..., 0, :]) / (2.0 * dphi)
    south = (ext[..., -1, :] - ext[..., -3, :]) / (2.0 * dphi)
    return north, south


@jax.jit
def _differential(f: Array) -> Array:
    a1, a2 = interior_frame(f)
    north, south = pole_phi_derivative(f)
    zeros = jnp.zeros_like(north)
    col1 = jnp.concatenate([zeros[..., None, :], a1, zeros[..., None, :]], axis=-2)
    col2 = jnp.concatenate([north[..., None, :], a2, south[..., None, :]], axis=-2)
    df = jnp.stack([col1, col2], axis=-3)
    return jnp.concatenate([df, df[..., :1]], axis=-1)


def differential(f: Float[ArrayLike, "*batch 3 m n"]) -> Float[Array, "*batch 3 2 m n"]:
    """The differential of a surface in the orthonormal frame of the round sphere
    (:ref:`math §2 <math-2>`).

    df = [f_theta / sin(phi), f_phi], a field of 3 x 2 matrices. Reference discretization
    (the paper's code): central differences in theta with periodic wrap; central
    differences in phi, where the row beyond a pole is the neighbouring row shifted by
    half a turn, f(-dphi, theta) = f(dphi, theta + pi). On the two pole rows the theta
    column is undefined and set to zero (those rows carry zero quadrature weight).

    Args:
        f: ``(..., 3, m, n)`` surface(s) on the grid of :ref:`math §1 <math-1>`.

    Returns:
        ``(..., 3, 2, m, n)``; ``[..., :, 0]`` is f_theta / sin(phi), ``[..., :, 1]`` is f_phi.

    Example:
        >>> from elastic_jax import differential, sphere_points
        >>> differential(sphere_points(25, 49)).shape
        (3, 2, 25, 49)
    """
    f = grid_array(f, "f")
    return _differential(f)


def _xp(*arrays):
    """numpy for numpy inputs (checks and precomputation outside jit), else jax.numpy."""
    return np if all(isinstance(a, np.ndarray) for a in arrays) else jnp


def area_element(a1: ArrayLike, a2: ArrayLike) -> ArrayLike:
    """sqrt(det g) = |a1 x a2| for columns ``(..., 3, ...)`` (vector axis -3); numpy in,
    numpy out."""
    return _xp(a1, a2).sqrt(_norm2(cross(a1, a2)))


def dot(x: ArrayLike, y: ArrayLike) -> ArrayLike:
    """Euclidean inner product over the vector axis -3 (numpy in, numpy out)."""
    return _xp(x, y).sum(x * y, axis=-3)


def _norm2(x: ArrayLike) -> ArrayLike:
    return dot(x, x)


def cross(x: ArrayLike, y: ArrayLike) -> ArrayLike:
    """Cross product over the vector axis -3, written out so that it fuses on any backend
    (numpy in, numpy out)."""
    x0, x1, x2 = x[..., 0, :, :], x[..., 1, :, :], x[..., 2, :, :]
    y0, y1, y2 = y[..., 0, :, :], y[..., 1, :, :], y[..., 2, :, :]
    return _xp(x, y).stack([x1 * y2 - x2 * y1, x2 * y0 - x0 * y2, x0 * y1 - x1 * y0], axis=-3)


def pole_fourier1(row: Array) -> tuple[Array, Array]:
    """X, Y with row_j ~ cos(theta_j) X + sin(theta_j) Y, for ``row (..., 3, n-1)``.

    At a pole, df maps the direction at azimuth theta to f_phi(pole, theta); its first
    Fourier mode gives the tangent plane (X, Y) there.
    """
    k = row.shape[-1]
    theta = 2.0 * np.pi * np.arange(k) / k
    cos = jnp.asarray(np.cos(theta) * 2.0 / k, dtype=row.dtype)
    sin = jnp.asarray(np.sin(theta) * 2.0 / k, dtype=row.dtype)
    return jnp.einsum("...j,j->...", row, cos), jnp.einsum("...j,j->...", row, sin)
