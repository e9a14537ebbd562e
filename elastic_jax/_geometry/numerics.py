"""Small numerical building blocks the solvers share: a square root safe to differentiate
at zero, a tree held constant under differentiation, a matrix's inverse square root."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array

__all__ = ["constant", "safe_sqrt", "sqrt_inverse_pair"]


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
