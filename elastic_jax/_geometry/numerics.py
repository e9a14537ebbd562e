"""Small numerical building blocks the solvers share: a square root safe to differentiate
at zero, a tree held constant under differentiation, a matrix's inverse square root, the
default tolerance of a precision."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.typing import DTypeLike
from jaxtyping import Array

__all__ = ["constant", "default_tol", "safe_sqrt", "sqrt_inverse_pair"]


def constant(tree):
    """``tree`` with its JAX arrays under ``stop_gradient`` (Python numbers left as they are)."""
    return jax.tree_util.tree_map(
        lambda x: jax.lax.stop_gradient(x) if isinstance(x, jax.Array) else x, tree
    )


def safe_sqrt(x: Array) -> Array:
    """sqrt(x) with a zero, not an infinite, derivative at x = 0 (the double-where pattern:
    the branch not taken never sees 0, so its derivative is finite too). NaN stays NaN: a
    non-finite energy must not read as a zero distance."""
    positive = x > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, x, 1.0)), jnp.where(x == x, 0.0, x))


def sqrt_inverse_pair(matrix: Array, floor: float) -> tuple[Array, Array]:
    """M^(-1/2) and M^(1/2) of a symmetric PSD matrix, eigenvalues floored at floor * max."""
    lam, vec = jnp.linalg.eigh(matrix)
    lam = jnp.maximum(lam, floor * lam[-1])
    root = jnp.sqrt(lam)[None, :]
    return (vec / root) @ vec.T, (vec * root) @ vec.T


def default_tol(dtype: DTypeLike) -> float:
    """The inner solves' default tolerance on the scaled gradient's 2-norm: 1e-6 in
    float64; 3e-3 in float32, whose rounding floor there is 7e-4 to 8e-4 (sphere-like pair
    at degree 7, N = 13 on 25 x 49 and 50 x 99; the floor grows like the square root of
    the number of coefficients). With Hessian ~2 I the energy is then within tol^2 / 4
    of the minimum, relative: 2e-6 in float32."""
    return 1e-6 if jnp.dtype(dtype) == jnp.float64 else 3e-3
