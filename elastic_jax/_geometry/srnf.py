"""Square root normal functions (math §3; Jermyn et al. 2012) and surface-level quantities."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .differential import (
    area_element,
    cross,
    dot,
    interior_frame,
    pole_fourier1,
    pole_phi_derivative,
)
from .energy import as_path
from .grid import integrate_interior
from .validation import as_surface


def sqrt_normal(normal: Array) -> Array:
    # q = N / |N|^(1/2); |N| = 0 only where f is not an immersion.
    return normal * jax.lax.rsqrt(jnp.sqrt(dot(normal, normal)))[..., None, :, :]


@jax.jit
def srnf_unchecked(f: Array) -> Array:
    a1, a2 = interior_frame(f)
    # a1 x a2 points inward for the identity immersion; q uses the outward normal.
    q = sqrt_normal(cross(a2, a1))
    # At a pole df maps the direction at azimuth theta to f_phi(pole, theta); its
    # first Fourier mode cos(theta) X + sin(theta) Y gives the tangent plane X, Y.
    north, south = pole_phi_derivative(f)
    xn, yn = pole_fourier1(north)
    xs, ys = pole_fourier1(south)
    qn = sqrt_normal(jnp.cross(xn, yn, axis=-1)[..., :, None, None])
    qs = sqrt_normal(jnp.cross(ys, xs, axis=-1)[..., :, None, None])
    n_cols = q.shape[-1]
    qn = jnp.broadcast_to(qn, qn.shape[:-1] + (n_cols,))
    qs = jnp.broadcast_to(qs, qs.shape[:-1] + (n_cols,))
    q = jnp.concatenate([qn, q, qs], axis=-2)
    return jnp.concatenate([q, q[..., :1]], axis=-1)


def srnf(f: Float[ArrayLike, "*batch 3 m n"]) -> Float[Array, "*batch 3 m n"]:
    """The square root normal function q(f) = sqrt(‖f_theta x f_phi‖ / sin phi) n (math §3).

    n is the unit normal pointing outward for the identity parametrization
    (f_phi x f_theta direction), so q(r e1) = r e1. The differential is that of
    :ref:`math §2 <math-2>`.
    On the pole rows (zero quadrature weight) q is taken from the tangent plane fitted
    to the pole row's phi derivatives, so it is the pole value to discretization order.

    Args:
        f: ``(..., 3, m, n)`` immersion(s).

    Returns:
        ``(..., 3, m, n)``.
    """
    return srnf_unchecked(as_surface(f, "f"))


@jax.jit
def _srnf_distance(f1, f2):
    q1, q2 = srnf_unchecked(f1), srnf_unchecked(f2)
    diff = (q1 - q2)[..., 1:-1, :-1]
    return jnp.sqrt(integrate_interior(dot(diff, diff)))


def srnf_distance(
    f1: Float[ArrayLike, "*batch 3 m n"], f2: Float[ArrayLike, "*batch 3 m n"]
) -> Float[Array, "*batch"]:
    """L2 distance over S^2 of the SRNFs, ||q(f1) - q(f2)|| (:ref:`math §3 <math-3>`; paper Table
    2).

    A lower bound of the geodesic distance under the split metric (0, 1/2, 1, 0).

    Args:
        f1, f2: ``(..., 3, m, n)`` immersions on the same grid (leading axes broadcast).

    Returns:
        ``(...)``.
    """
    f1, f2 = jnp.broadcast_arrays(as_surface(f1, "f1"), as_surface(f2, "f2"))
    return _srnf_distance(f1, f2)


@jax.jit
def _srnf_path_length(path):
    q = srnf_unchecked(path)[..., 1:-1, :-1]
    steps = q[..., 1:, :, :, :] - q[..., :-1, :, :, :]
    return jnp.sum(jnp.sqrt(integrate_interior(dot(steps, steps))), axis=-1)


def srnf_path_length(path: Float[ArrayLike, "*batch N 3 m n"]) -> Float[Array, "*batch"]:
    """L2 length of the SRNF image of a path: sum_k ||q(f_{k+1}) - q(f_k)|| (paper Table 1).

    Equals the (0, 1/2, 1, 0) split-metric length of the path up to time discretization.

    Args:
        path: ``(..., N, 3, m, n)``, N >= 2.

    Returns:
        ``(...)``.
    """

    return _srnf_path_length(as_path(path))


@jax.jit
def surface_area_unchecked(f):
    return integrate_interior(area_element(*interior_frame(f)))


def surface_area(f: Float[ArrayLike, "*batch 3 m n"]) -> Float[Array, "*batch"]:
    """Area of the surface, integral over S^2 of sqrt(det g) (:ref:`math §2 <math-2>` quadrature).

    Args:
        f: ``(..., 3, m, n)``.

    Returns:
        ``(...)``; 4 pi r^2 for a sphere of radius r, to O(h^2).
    """
    return surface_area_unchecked(as_surface(f, "f"))


@jax.jit
def center_unchecked(f):
    a1, a2 = interior_frame(f)
    dens = area_element(a1, a2)
    mass = integrate_interior(dens)
    moment = integrate_interior(f[..., 1:-1, :-1] * dens[..., None, :, :])
    centroid = moment / mass[..., None]
    return f - centroid[..., :, None, None]


def center(f: Float[ArrayLike, "*batch 3 m n"]) -> Float[Array, "*batch 3 m n"]:
    """Translate the surface so that its area-weighted centroid is at the origin
    (:ref:`math §7 <math-7>`).

    centroid = integral of f sqrt(det g) / integral of sqrt(det g). The metric sees only
    df, so centering changes no energy; it is for display and rigid alignment.

    Args:
        f: ``(..., 3, m, n)``.

    Returns:
        ``(..., 3, m, n)``.
    """
    return center_unchecked(as_surface(f, "f"))
