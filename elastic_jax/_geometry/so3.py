"""Rotations: the SO(3) exponential and logarithm, and the icosahedral group (math §6)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._errors import InputError
from .._runtime.cache import cached


def hat(w: Float[ArrayLike, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
    """The skew matrix K with K v = w x v."""
    w = jnp.asarray(w)
    zero = jnp.zeros_like(w[..., 0])
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    rows = [jnp.stack(r, axis=-1) for r in ((zero, -z, y), (z, zero, -x), (-y, x, zero))]
    return jnp.stack(rows, axis=-2)


def vee(k: Float[ArrayLike, "*batch 3 3"]) -> Float[Array, "*batch 3"]:
    """Inverse of :func:`hat` on the skew part: (K32, K13, K21)."""
    return jnp.stack([k[..., 2, 1], k[..., 0, 2], k[..., 1, 0]], axis=-1)


def _small(t2: Array) -> Array:
    # Below t^2 = sqrt(eps) the Taylor series to t^4 is exact to rounding (error ~ t^6).
    return t2 < np.sqrt(np.finfo(t2.dtype).eps)


@jax.jit
def so3_exp_unchecked(w):
    t2 = jnp.sum(w * w, axis=-1)
    small = _small(t2)
    # The safe where: evaluate sin t / t only where t is not small, so that the unused
    # branch never produces a NaN that would poison the gradient.
    t2_safe = jnp.where(small, 1.0, t2)
    t = jnp.sqrt(t2_safe)
    a = jnp.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, jnp.sin(t) / t)
    b = jnp.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, (1.0 - jnp.cos(t)) / t2_safe)
    k = hat(w)
    eye = jnp.broadcast_to(jnp.eye(3, dtype=w.dtype), k.shape)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def so3_exp(w: Float[ArrayLike, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
    """Rotation matrices exp(hat(w)) by Rodrigues' formula (:ref:`math §6 <math-6>`).

    R = I + sin(t)/t K + (1 - cos t)/t^2 K^2, K = hat(w), t = ‖w‖; below t^2 = sqrt(eps)
    the coefficients use their Taylor series, so value and gradient are exact at w = 0.

    Args:
        w: ``(..., 3)`` axis-angle vectors (angle ‖w‖ about w / ‖w‖).

    Returns:
        ``(..., 3, 3)``.
    """
    w = jnp.asarray(w)
    if w.shape[-1:] != (3,):
        raise InputError(f"w must have shape (..., 3); got {w.shape}")
    if not jnp.issubdtype(w.dtype, jnp.floating):
        w = w.astype(jnp.result_type(float))
    return so3_exp_unchecked(w)


@jax.jit
def _so3_log(r):
    v = 0.5 * vee(r - jnp.swapaxes(r, -1, -2))  # sin(theta) n
    c = 0.5 * (jnp.trace(r, axis1=-2, axis2=-1) - 1.0)  # cos(theta)
    s2 = jnp.sum(v * v, axis=-1)
    small = _small(s2)
    s = jnp.sqrt(jnp.where(small, 1.0, s2))
    theta = jnp.arctan2(s, c)
    # theta / sin(theta) as a series in s = sin(theta) near 0: arcsin(s)/s.
    near_zero = small & (c > 0)
    factor = jnp.where(near_zero, 1.0 + s2 / 6.0 + 3.0 * s2 * s2 / 40.0, theta / s)
    general = factor[..., None] * v
    # Near pi, sin(theta) ~ 0 carries no direction: read n n^T off the symmetric part,
    # (R + R^T)/2 - cos(theta) I = (1 - cos(theta)) n n^T, and orient n along v.
    # Both sides of a where are differentiated: every division and square root of the
    # branch not taken gets a harmless operand (1), or reverse mode multiplies its
    # infinite derivative by the zero cotangent and returns NaN (at R = I, 1 - c = 0).
    near_pi = (c < 0) & (s2 < 1e-4)
    eye = jnp.broadcast_to(jnp.eye(3, dtype=r.dtype), r.shape)
    sym = 0.5 * (r + jnp.swapaxes(r, -1, -2)) - c[..., None, None] * eye
    nn = sym / jnp.where(near_pi, 1.0 - c, 1.0)[..., None, None]
    diag = jnp.diagonal(nn, axis1=-2, axis2=-1)
    col = jnp.take_along_axis(nn, jnp.argmax(diag, axis=-1)[..., None, None], axis=-1)[..., 0]
    n = col / jnp.sqrt(jnp.where(near_pi, jnp.max(diag, axis=-1), 1.0))[..., None]
    n = jnp.where(jnp.sum(n * v, axis=-1, keepdims=True) < 0, -n, n)
    # At the exact half-turn s2 = 0, where sqrt has no derivative; theta = pi there.
    positive = s2 > 0
    sin_pi = jnp.where(positive, jnp.sqrt(jnp.where(positive, s2, 1.0)), 0.0)
    theta_pi = jnp.arctan2(sin_pi, c)
    return jnp.where(near_pi[..., None], theta_pi[..., None] * n, general)


def so3_log(r: Float[ArrayLike, "*batch 3 3"]) -> Float[Array, "*batch 3"]:
    """The axis-angle vector w with exp(hat(w)) = R, ‖w‖ in [0, pi] (inverse of :func:`so3_exp`).

    theta = atan2(‖v‖, (tr R - 1)/2) with v = vee(R - R^T)/2 = sin(theta) n; a Taylor
    branch near 0 and the symmetric part of R near pi keep value and gradient finite.

    Args:
        r: ``(..., 3, 3)`` rotation matrices.

    Returns:
        ``(..., 3)``.
    """
    r = jnp.asarray(r)
    if r.shape[-2:] != (3, 3):
        raise InputError(f"R must have shape (..., 3, 3); got {r.shape}")
    return _so3_log(r)


@cached
def icosahedral_np() -> np.ndarray:
    golden = (1.0 + np.sqrt(5.0)) / 2.0
    axis = np.array([0.0, 1.0, golden]) / np.hypot(1.0, golden)  # through a vertex
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    angle = 2.0 * np.pi / 5.0
    # Rodrigues in float64 numpy: the group must be exact whatever JAX's precision.
    five_fold = np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)
    generators = [five_fold, np.diag([-1.0, -1.0, 1.0])]  # and a half-turn about z
    group = [np.eye(3)]
    frontier = [np.eye(3)]
    while frontier:
        fresh = []
        for g in frontier:
            for h in generators:
                p = g @ h
                if not any(np.abs(p - q).max() < 1e-6 for q in group):
                    group.append(p)
                    fresh.append(p)
        frontier = fresh
    return np.stack(group)


def icosahedral_group(dtype=None) -> Float[Array, "60 3 3"]:
    """The 60 rotations of the icosahedron, generated from a 5-fold and a 2-fold rotation.

    Closure of {rotation by 2 pi / 5 about the vertex axis (0, 1, golden ratio), half-turn
    about z} under products; the identity is element 0. The coarse search set for
    registration (paper, Remark 4).

    Returns:
        ``(60, 3, 3)``.
    """
    return jnp.asarray(icosahedral_np(), dtype=dtype)
