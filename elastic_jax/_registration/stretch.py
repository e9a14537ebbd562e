"""The path energy with the cells where gamma stretches most integrated finer (math §10).

The working grid's node rule integrates f1 o gamma well where gamma keeps f1's data
points apart on the working grid. Where gamma stretches a region of f1's parameter sphere
over a few working cells, f1's content between the nodes is not seen, and a registration
that minimizes the node rule learns to hide f1 there: on the shared cats at 97 x 193,
62-80 % of the rise of the energy under 2x / 4x finer quadrature lies in the 0.7 % of the
sphere where gamma's J exceeds 8 (:doc:`/guides/registration_notes`).

Here the cells with the largest J are integrated by the midpoint rule on s x s sub-cells
instead of the trapezoid share the node rule gives them:

    E = E_nodes + sum over chosen cells (Q_sub(cell) - Q_trapezoid(cell)),

with the start's frames at the sub-points by the chain rule through gamma's and f1's
interpolants (the same interpolants the nodes read), R f2's through its interpolant at the
identity's interpolant (as the nodes read it: identical inputs, identical frames), and the
path's perturbation (a low-degree harmonic field, smooth across a cell) bilinear from the
cell's corners. The cells are chosen from gamma with its gradient stopped: the choice is
piecewise constant in gamma, like a quadrature's nodes.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike

from .._geometry.energy import pointwise_speeds2
from .._geometry.grid import sphere_points
from .._geometry.reparam import jacobian_determinant_unchecked, sample_points, spline_coefficients


def stretched_cells(gamma: ArrayLike, fraction: float) -> tuple[Array, Array]:
    """The ``fraction`` of the grid's cells (at least one) whose corners hold the largest
    J of ``gamma (3, m, n)``, gamma at the nodes of the grid whose cells are meant (the
    quadrature's): ``(rows, cols)``, each ``(k,)``.

    A cell spans interior rows ``r, r + 1`` (grid rows r + 1, r + 2; the cells on a pole
    row are never chosen) and columns ``c, c + 1`` (periodic over the n - 1 distinct ones).
    """
    jac = jax.lax.stop_gradient(jacobian_determinant_unchecked(gamma))[1:-1, :-1]
    right = jnp.roll(jac, -1, axis=1)
    cell = jnp.maximum(jnp.maximum(jac[:-1], jac[1:]), jnp.maximum(right[:-1], right[1:]))
    k = max(1, int(fraction * cell.size))
    _, index = jax.lax.top_k(cell.reshape(-1), k)
    return index // cell.shape[1], index % cell.shape[1]


def _sub_offsets(subdivision: int) -> tuple[np.ndarray, np.ndarray]:
    """The sub-cells' midpoints in a cell's own coordinates (u down the rows, v along)."""
    u = (np.arange(subdivision) + 0.5) / subdivision
    uu, vv = np.meshgrid(u, u, indexing="ij")
    return uu.reshape(-1), vv.reshape(-1)


def stretch_correction(
    metric,
    source1: ArrayLike,
    source2: ArrayLike,
    read: str,
    interpolation: str,
    dframe: ArrayLike,
    gamma: ArrayLike,
    rotation: ArrayLike,
    coefficients: ArrayLike,
    frames: tuple[Array, Array],
    cells: tuple[Array, Array],
    subdivision: int,
) -> Array:
    """sum over ``cells`` of (the s x s midpoint rule - the node rule's trapezoid share)
    of the path energy (midpoint scheme), s = ``subdivision``.

    ``frames``: the path's interior frames ``(N, 3, M - 2, N' - 1)`` as the node rule
    integrates them (:func:`problem.path_frames_at`), on the quadrature's grid M x N'
    (the working grid, or the grid q times finer with ``ShapeOptions.quadrature``), whose
    cells ``cells`` indexes; ``coefficients`` ``(N - 2, 3 K)`` their perturbation in
    ``dframe``'s harmonics (K, 2 (M - 2) (N' - 1)); ``source1``, ``source2`` read by
    ``read``; ``gamma`` the working grid's ``(3, m, n)``, read at the sub-points as
    ``interpolation`` composes it.
    """
    m, n = frames[0].shape[-2] + 2, frames[0].shape[-1] + 1
    dtype = gamma.dtype
    rows, cols = cells
    dphi, dtheta = np.pi / (m - 1), 2.0 * np.pi / (n - 1)
    u, v = (jnp.asarray(x, dtype) for x in _sub_offsets(subdivision))
    phi = ((rows + 1).astype(dtype)[:, None] + u[None]) * dphi
    theta = (cols.astype(dtype)[:, None] + v[None]) * dtheta
    sp, cp, st, ct = jnp.sin(phi), jnp.cos(phi), jnp.sin(theta), jnp.cos(theta)
    points = jnp.stack([sp * ct, sp * st, cp])
    # math §2's frame: a1 = f_theta / sin(phi), a2 = f_phi, derivatives along these.
    east = jnp.stack([-st, ct, jnp.zeros_like(st)])
    south = jnp.stack([cp * ct, cp * st, -sp])

    with jax.ensure_compile_time_eval():  # a constant of the program, not per evaluation
        identity = sphere_points(*gamma.shape[-2:], dtype=dtype)
        if interpolation == "spline":
            identity = spline_coefficients(identity)
    sources, gamma_read = (gamma, identity), interpolation
    if interpolation == "spline":
        sources, gamma_read = (spline_coefficients(gamma), identity), "coefficients"

    def through(source: Array, g_source: Array, p: Array):
        g = sample_points(g_source, p, gamma_read)
        return sample_points(source, g / jnp.linalg.norm(g, axis=0, keepdims=True), read)

    def start(p: Array):
        return through(source1, sources[0], p)

    def end(p: Array):
        # R f2 read as f1 o gamma is at the identity (the nodes' rule for the end's frame,
        # problem.rotated_end_frame): identical inputs, identical sub-frames; the identity's
        # interpolant is not the identity between the points (d(f, f) was 2.4e-6 at 25 x 49).
        return jnp.einsum("ij,j...->i...", rotation, through(source2, sources[1], p))

    start_frame = [jax.jvp(start, (points,), (d,))[1] for d in (east, south)]
    end_frame = [jax.jvp(end, (points,), (d,))[1] for d in (east, south)]
    n_times = frames[0].shape[0]
    t = jnp.linspace(0.0, 1.0, n_times, dtype=dtype).reshape(n_times, 1, 1, 1)
    sub = [a[None] + t * (b - a)[None] for a, b in zip(start_frame, end_frame, strict=True)]

    k = dframe.shape[0]
    perturbation = (coefficients.reshape(-1, k) @ dframe).reshape(n_times - 2, 3, 2, m - 2, n - 1)
    right = (cols + 1) % (n - 1)
    corners = ((rows, cols), (rows + 1, cols), (rows, right), (rows + 1, right))
    bilinear = ((1 - u) * (1 - v), u * (1 - v), (1 - u) * v, u * v)
    for axis in range(2):
        inside = sum(
            perturbation[:, :, axis][:, :, r, c][..., None] * w[None, None, None]
            for (r, c), w in zip(corners, bilinear, strict=True)
        )
        sub[axis] = sub[axis].at[1:-1].add(inside)
    sub_weights = sp * dphi * dtheta / subdivision**2
    density, weights = pointwise_speeds2(metric, *sub, "midpoint")
    fine = jnp.einsum("tks,ks,t->", density, sub_weights, weights)

    at_corners = [jnp.stack([a[:, :, r, c] for r, c in corners], axis=-1) for a in frames]
    corner_rows = jnp.stack([rows, rows + 1, rows, rows + 1], axis=-1)
    corner_weights = jnp.sin((corner_rows + 1).astype(dtype) * dphi) * dphi * dtheta / 4.0
    density, weights = pointwise_speeds2(metric, *at_corners, "midpoint")
    coarse = jnp.einsum("tks,ks,t->", density, corner_weights, weights)
    return fine - coarse
