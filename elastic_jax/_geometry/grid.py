"""The spherical grid: angles, quadrature weights and the identity immersion (math §1, 2)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._checks import check_grid_shape, check_int
from .._runtime.cache import cached


@cached
def angles_np(m: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    phi = np.arange(m) * (np.pi / (m - 1))
    theta = np.arange(n) * (2.0 * np.pi / (n - 1))
    return phi, theta


def grid_angles(m: int, n: int, dtype=None) -> tuple[Float[Array, " m"], Float[Array, " n"]]:
    """Polar angles and azimuths of the m x n spherical grid (:ref:`math §1 <math-1>`).

    phi_i = i pi / (m - 1) (row 0 is the north pole, row m - 1 the south pole) and
    theta_j = 2 pi j / (n - 1) (column n - 1 repeats column 0).

    Args:
        m, n: grid size; n must be odd so that theta + pi is again a column.
        dtype: floating dtype of the result (default: JAX's default float).

    Returns:
        ``(phi, theta)`` with shapes ``(m,)`` and ``(n,)``.
    """
    phi, theta = angles_np(m, n)
    return jnp.asarray(phi, dtype=dtype), jnp.asarray(theta, dtype=dtype)


@cached
def interior_weights_np(m: int, n: int) -> np.ndarray:
    # Trapezoid rule in phi and theta times sin(phi). The pole rows have weight zero
    # (sin phi = 0) and the periodic trapezoid in theta gives every distinct column the
    # full weight, so only interior rows and columns 0..n-2 carry weight.
    phi, _ = angles_np(m, n)
    dphi = np.pi / (m - 1)
    dtheta = 2.0 * np.pi / (n - 1)
    w = np.sin(phi[1:-1]) * dphi * dtheta
    return np.repeat(w[:, None], n - 1, axis=1)


def interior_weights(m: int, n: int, dtype) -> Float[Array, "mi ni"]:
    """Quadrature weights on interior rows and distinct columns (the only ones with weight)."""
    return jnp.asarray(interior_weights_np(m, n), dtype=dtype)


def quadrature_weights(m: int, n: int, dtype=None) -> Float[Array, "m n"]:
    """Weights w_ij of the quadrature over S^2 on the inclusive grid (:ref:`math §2 <math-2>`).

    Trapezoid rule in phi and in theta times sin(phi_i):
    w_ij = sin(phi_i) dphi dtheta c_j with c_0 = c_{n-1} = 1/2 and c_j = 1 otherwise.
    The pole rows get weight zero. ``sum(w) -> 4 pi`` with error O(h^2).

    Returns:
        ``(m, n)`` array; ``integral_{S^2} h = sum(w * h)`` for ``h`` sampled on the grid.
    """
    return jnp.asarray(quadrature_weights_np(m, n), dtype=dtype)


def per_unit_area_np(values: np.ndarray) -> np.ndarray:
    """A field of per-point integrals ``(..., m, n)`` (its quadrature weight included) as a
    density per unit area of the parameter sphere; NaN on the pole rows, which carry no
    weight."""
    weights = quadrature_weights_np(*values.shape[-2:])
    out = np.full(values.shape, np.nan)
    np.divide(values, weights, out=out, where=weights > 0)
    return out


@cached
def quadrature_weights_np(m: int, n: int) -> np.ndarray:
    """:func:`quadrature_weights` in float64 numpy."""
    w = np.zeros((m, n))
    w[1:-1, :-1] = interior_weights_np(m, n)
    # Split the seam column's weight between the two copies of theta = 0.
    w[1:-1, 0] *= 0.5
    w[1:-1, -1] = w[1:-1, 0]
    w.flags.writeable = False
    return w


def integrate(values: Float[ArrayLike, "*batch m n"]) -> Float[Array, "*batch"]:
    """Integral over S^2 of a function sampled on the grid (:ref:`math §2 <math-2>` quadrature).

    Args:
        values: ``(..., m, n)`` samples, seam column included.

    Returns:
        ``(...)`` the integrals ``sum_ij w_ij values_ij``.
    """
    values = jnp.asarray(values)
    return integrate_interior(values[..., 1:-1, :-1])


def integrate_interior(values: Float[ArrayLike, "*batch mi ni"]) -> Float[Array, "*batch"]:
    """Quadrature of values given on interior rows and distinct columns only."""
    m, n = values.shape[-2] + 2, values.shape[-1] + 1
    w = interior_weights(m, n, values.dtype)
    return jnp.einsum("...ij,ij->...", values, w)


def sphere_points(m: int, n: int, dtype=None) -> Float[Array, "3 m n"]:
    """The identity immersion e1 = (sin phi cos theta, sin phi sin theta, cos phi) on the grid.

    Pole rows are exactly constant and the seam column exactly repeats column 0.

    Args:
        m, n: the grid (:ref:`math §1 <math-1>`): m >= 5 rows, n >= 5 columns, n odd.
        dtype: the array's dtype (JAX's default float when None).

    Returns:
        ``(3, m, n)``.
    """
    check_grid_shape((3, check_int("m", m, 5), check_int("n", n, 5)), "the grid")
    return jnp.asarray(sphere_points_np(m, n), dtype=dtype)


@cached
def sphere_tangents_np(m: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The unit frame (e_theta, e_phi) of the round sphere at the grid's points, ``(3, m,
    n)`` each in float64 numpy: e_theta = d e1 / dtheta / sin(phi), e_phi = d e1 / dphi."""
    phi, theta = angles_np(m, n)
    sp, cp = np.sin(phi)[:, None], np.cos(phi)[:, None]
    ct, st = np.cos(theta)[None, :], np.sin(theta)[None, :]
    e_theta = np.stack([-st * np.ones_like(cp), ct * np.ones_like(cp), np.zeros((m, n))])
    e_phi = np.stack([cp * ct, cp * st, -sp * np.ones_like(ct)])
    return e_theta, e_phi


def sphere_points_np(m: int, n: int) -> np.ndarray:
    """:func:`sphere_points` in float64 numpy (usable while an outer jit traces)."""
    phi, theta = angles_np(m, n)
    sp, cp = np.sin(phi)[:, None], np.cos(phi)[:, None]
    ct, st = np.cos(theta)[None, :], np.sin(theta)[None, :]
    x = np.stack([sp * ct, sp * st, np.broadcast_to(cp, (m, n))])
    # Make the pole rows and the seam bitwise consistent, as docs/math.md §1 requires of input.
    x[:, 0, :] = np.array([0.0, 0.0, 1.0])[:, None]
    x[:, -1, :] = np.array([0.0, 0.0, -1.0])[:, None]
    x[:, :, -1] = x[:, :, 0]
    return x


def distinct_points(f):
    """The distinct grid points of ``f (3, m, n)`` as ``(2 + (m - 2)(n - 1), 3)``: north
    pole, interior rows without the seam column, south pole (the vertex order of
    ``io.grid_to_mesh``); a JAX array for a JAX input, so that triangle-based quantities
    stay differentiable. :func:`from_distinct` is its inverse."""
    xp = np if isinstance(f, np.ndarray) else jnp
    return xp.concatenate([f[:, 0, :1], f[:, 1:-1, :-1].reshape(3, -1), f[:, -1, :1]], axis=1).T


def grid_directions(m: int, n: int) -> np.ndarray:
    """The unit vectors of the distinct grid points (:func:`distinct_points` of the
    identity immersion), float64."""
    return distinct_points(sphere_points_np(m, n))


def grid_faces(m: int, n: int) -> np.ndarray:
    """Triangles of the grid mesh, counterclockwise seen from outside (normal e_phi x e_theta).

    Vertex k of an interior point (i, j), 1 <= i <= m - 2, 0 <= j <= n - 2, is
    1 + (i - 1)(n - 1) + j; the north pole is vertex 0 and the south pole the last one.
    """
    c = n - 1
    south = 1 + (m - 2) * c
    j = np.arange(c)
    jn = (j + 1) % c  # the seam: the last column's neighbour is column 0
    # Along +phi then +theta: (e_phi, e_theta, e_r) is right-handed on the unit sphere.
    north = np.stack([np.zeros(c, dtype=np.int64), 1 + j, 1 + jn], axis=1)
    southfan = np.stack([south - c + j, np.full(c, south), south - c + jn], axis=1)
    top = 1 + np.arange(m - 3)[:, None] * c  # first vertex of interior rows 1 .. m-3
    a, b = top + j, top + jn  # (i, j), (i, j + 1)
    lower, lower_next = a + c, b + c  # (i + 1, j), (i + 1, j + 1)
    quads = np.concatenate(
        [
            np.stack([a, lower, b], axis=-1).reshape(-1, 3),
            np.stack([lower, lower_next, b], axis=-1).reshape(-1, 3),
        ]
    )
    return np.concatenate([north, quads, southfan])


def from_distinct(points: np.ndarray, m: int, n: int) -> np.ndarray:
    """``(2 + (m - 2)(n - 1), 3)`` distinct grid points -> ``(3, m, n)`` with poles and seam."""
    f = np.empty((3, m, n))
    f[:, 0, :] = points[0][:, None]
    f[:, -1, :] = points[-1][:, None]
    f[:, 1:-1, :-1] = points[1:-1].reshape(m - 2, n - 1, 3).transpose(2, 0, 1)
    f[:, :, -1] = f[:, :, 0]
    return f
