"""Units of a solve: the surfaces' centre and scale, removed before it and restored after.

The path energy is invariant under translation and homogeneous of degree 2 under scaling
(every term of the split metric is a ratio of first derivatives times the area element,
math §3), so E(s f + c) = s^2 E(f) and the geodesic between s f1 + c and s f2 + c is
s times the geodesic between f1 and f2, plus c. Solving on surfaces of size ~1 centred
at the origin keeps float32 away from underflow (det g ~ size^4: 1e-24 for a surface
1e-6 across) and overflow, and its rounding away from a large offset.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float


class Units(NamedTuple):
    """A centre ``(3, 1, 1)`` and a scale ``()``, a power of two (so that dividing by it
    and multiplying by it again are exact)."""

    centre: Float[Array, "3 1 1"]
    scale: Float[Array, ""]

    def remove(self, f: Float[Array, "*batch 3 m n"]) -> Float[Array, "*batch 3 m n"]:
        """(f - centre) / scale."""
        return (f - self._centre_for(f)) / self.scale

    def restore(self, f: Float[Array, "*batch 3 m n"]) -> Float[Array, "*batch 3 m n"]:
        """f * scale + centre."""
        return f * self.scale + self._centre_for(f)

    def _centre_for(self, f: Array) -> Array:
        # Explicit leading axes: no implicit rank promotion.
        return self.centre.reshape((1,) * (f.ndim - 3) + self.centre.shape)


@jax.jit
def units_of(*surfaces: Float[ArrayLike, "3 m n"]) -> Units:
    """The units of a solve between ``surfaces`` (each ``(3, m, n)``): the centre of their
    common bounding box and the power of two nearest their largest coordinate range.

    Constants of the solve (under ``stop_gradient``): the exact solution does not depend
    on them, so gradients through a solve are those of the solve in the user's units.
    Traceable and vmappable; jitted, so that a first call compiles one small program
    rather than one per operation.
    """
    # Each surface on its own grid (a shape solve's inputs may come on different grids).
    flat = [jnp.asarray(f).reshape(3, -1) for f in surfaces]
    lower = jnp.min(jnp.stack([jnp.min(f, axis=1) for f in flat]), axis=0)
    upper = jnp.max(jnp.stack([jnp.max(f, axis=1) for f in flat]), axis=0)
    extent = jnp.max(upper - lower)
    # A single point (refused on concrete input) keeps unit scale instead of 0; the log
    # never sees 0 (double where).
    positive = extent > 0
    power = jnp.round(jnp.log2(jnp.where(positive, extent, 1.0))).astype(jnp.int32)
    # ldexp is exact; exp2 is not on every backend (exp2(3.0) = 7.999999999999998 on CPU).
    scale = jnp.where(positive, jnp.ldexp(jnp.ones_like(extent), power), 1.0)
    centre = (0.5 * lower + 0.5 * upper)[:, None, None]
    return Units(jax.lax.stop_gradient(centre), jax.lax.stop_gradient(scale))


@jax.jit
def in_units(*surfaces: Float[ArrayLike, "3 m n"]) -> tuple[Units, tuple[Array, ...]]:
    """``units_of(*surfaces)`` and every surface in those units, as one compiled program.

    Done op by op outside jit, these few scalar operations would each compile a program of
    their own on a process's first call (some twenty, ~25 ms each on 2 cores).
    """
    units = units_of(*surfaces)
    return units, tuple(units.remove(f) for f in surfaces)
