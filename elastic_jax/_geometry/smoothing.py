"""Low-passing a gridded surface on the sphere: a von Mises-Fisher kernel average."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._checks import check_int, check_positive
from .grid import quadrature_weights_np, sphere_points_np
from .validation import as_surface, well_formed


def smooth_surface(
    f: Float[ArrayLike, "*batch 3 m n"], width: float, batch_size: int = 256
) -> Float[Array, "*batch 3 m n"]:
    """f averaged over its parameter sphere with the von Mises-Fisher kernel of angular
    width ``width`` (radians), at f's own grid points:

        (S f)(p) = int K(p . q) f(q) dq / int K(p . q) dq,   K(t) = exp((t - 1) / width^2),

    both integrals by the grid's quadrature (:ref:`math §2 <math-2>`). For a small width
    the kernel is the sphere's heat kernel at time width^2 / 2 (both are Gaussians of the
    angle between p and q, of standard deviation width): degree-l harmonics are damped by
    about exp(-l (l + 1) width^2 / 2). Linear in f, so rigid motions commute with it and
    constants are kept; a round sphere of radius r becomes the sphere of radius
    r (coth(kappa) - 1 / kappa), kappa = 1 / width^2 (the mean of p . q under the kernel).

    Args:
        f: ``(..., 3, m, n)`` surfaces on one grid.
        width: the kernel's angular width, > 0.
        batch_size: grid points averaged at once (memory ``batch_size x m n``).

    Returns:
        ``(..., 3, m, n)``, pole rows constant and the seam column repeating column 0 as
        in the input. A kernel narrower than the grid's spacing returns f at the
        interior points and the nearest row's mean at the poles.

    Raises:
        InputError: a malformed surface (:func:`validate_surface`'s checks, immersion
            aside: a low-passed surface need not be one), a width that is not a
            positive finite number, or a batch size below 1.
    """
    f = as_surface(f, "f", check_immersion=False)
    return _smooth(
        f, check_positive("width", width), batch_size=check_int("batch_size", batch_size, 1)
    )


@functools.partial(jax.jit, static_argnames=("batch_size",))
def _smooth(f: Array, width: float, batch_size: int) -> Array:
    m, n = f.shape[-2:]
    points = jnp.asarray(sphere_points_np(m, n), f.dtype).reshape(3, -1)
    weights = jnp.asarray(quadrature_weights_np(m, n), f.dtype).reshape(-1)
    values = f.reshape(*f.shape[:-2], -1)
    kappa = 1.0 / jnp.asarray(width, f.dtype) ** 2

    # The kernel times the weights as a softmax of kappa (p . q - 1) + log w: finite at
    # any width (a narrow kernel underflows everywhere but at p, and a pole point's own
    # weight is zero); the pole rows' weight of zero is -inf there.
    log_weights = jnp.where(weights > 0, jnp.log(jnp.where(weights > 0, weights, 1.0)), -jnp.inf)

    def at(p: Array) -> Array:
        return values @ jax.nn.softmax(kappa * (p @ points - 1.0) + log_weights)

    averaged = jax.lax.map(at, points.T, batch_size=batch_size)  # (m n, ..., 3)
    # The pole rows and the seam exactly one point each, as a well-formed input is
    # (their averages differ by rounding where a batch's points are laid out apart).
    return well_formed(jnp.moveaxis(averaged, 0, -1).reshape(f.shape))
