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

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import DTypeLike
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


class Cells(NamedTuple):
    """The stretched cells of a round (:func:`chosen_cells`) and what stays fixed while
    the round's solver runs: their sub-points, the frame's directions there and R f2's
    frames there before the rotation (R f2 is read at the identity, so only R changes
    within a round)."""

    rows: Array  # (k,) the cells' first interior row
    cols: Array  # (k,) the cells' first column
    points: Array  # (3, k, s^2) the sub-points
    east: Array  # (3, k, s^2) the directions of math §2's frame there
    south: Array  # (3, k, s^2)
    sin_phi: Array  # (k, s^2) sin(phi) at the sub-points, for the quadrature's weights
    end_frame: tuple[Array, Array]  # each (3, k, s^2): f2's sub-frames before the rotation


def _sub_points(rows: Array, cols: Array, m: int, n: int, subdivision: int, dtype):
    """The sub-cells' midpoints of the cells (rows, cols) of an m x n grid, and the
    directions of math §2's frame there (a1 = f_theta / sin(phi), a2 = f_phi):
    (points, east, south, sin_phi), each vector ``(3, k, s^2)``, sin_phi ``(k, s^2)``."""
    dphi, dtheta = np.pi / (m - 1), 2.0 * np.pi / (n - 1)
    u, v = (jnp.asarray(x, dtype) for x in _sub_offsets(subdivision))
    phi = ((rows + 1).astype(dtype)[:, None] + u[None]) * dphi
    theta = (cols.astype(dtype)[:, None] + v[None]) * dtheta
    sp, cp, st, ct = jnp.sin(phi), jnp.cos(phi), jnp.sin(theta), jnp.cos(theta)
    points = jnp.stack([sp * ct, sp * st, cp])
    east = jnp.stack([-st, ct, jnp.zeros_like(st)])
    south = jnp.stack([cp * ct, cp * st, -sp])
    return points, east, south, sp


def _through(interpolation: str, read: str):
    """``through(source, g_source, p)``: a source read at g(p), g given by ``g_source``
    (an interpolant of the working grid's gamma, or of the identity), as the nodes read
    f o gamma."""
    gamma_read = "coefficients" if interpolation == "spline" else interpolation

    def through(source: Array, g_source: Array, p: Array):
        g = sample_points(g_source, p, gamma_read)
        return sample_points(source, g / jnp.linalg.norm(g, axis=0, keepdims=True), read)

    return through


def _sub_frame(read_at, points: Array, east: Array, south: Array) -> list[Array]:
    """The frame (a1, a2) of p -> read_at(p) at the sub-points: its derivatives along
    east and south."""
    return [jax.jvp(read_at, (points,), (d,))[1] for d in (east, south)]


def chosen_cells(
    gamma_at_nodes: ArrayLike,
    fraction: float,
    source2: ArrayLike,
    read: str,
    interpolation: str,
    working: tuple[int, int],
    subdivision: int,
) -> Cells:
    """The stretched cells of ``gamma_at_nodes (3, M, N')`` (gamma at the quadrature's
    nodes, :func:`stretched_cells`) with what a round holds fixed on them: R f2's frames
    at the sub-points before the rotation, read as f1 o gamma is at the identity (the
    nodes' rule for the end's frame, problem.rotated_end_frame: identical inputs,
    identical sub-frames; the identity's interpolant is not the identity between the
    points: d(f, f) was 2.4e-6 at 25 x 49). ``source2`` is read by ``read``; ``working``
    is the working grid (m, n) whose gamma ``interpolation`` composes."""
    m, n = gamma_at_nodes.shape[-2:]
    dtype = gamma_at_nodes.dtype
    rows, cols = stretched_cells(gamma_at_nodes, fraction)
    points, east, south, sin_phi = _sub_points(rows, cols, m, n, subdivision, dtype)
    with jax.ensure_compile_time_eval():  # a constant of the program, not per evaluation
        identity = sphere_points(*working, dtype=dtype)
        if interpolation == "spline":
            identity = spline_coefficients(identity)
    through = _through(interpolation, read)
    end = _sub_frame(lambda p: through(source2, identity, p), points, east, south)
    return Cells(rows, cols, points, east, south, sin_phi, tuple(end))


def cell_corners(cells: Cells, m: int, n: int, dtype: DTypeLike) -> tuple[Array, Array]:
    """The four corners of each of ``cells`` on the m x n quadrature grid: their flat
    indices into its interior ``(k, 4)`` and the node rule's trapezoid share of each
    ``(k, 4)`` (what :func:`stretch_correction` takes back from the nodes)."""
    rows, cols = cells.rows, cells.cols
    dphi, dtheta = np.pi / (m - 1), 2.0 * np.pi / (n - 1)
    right = (cols + 1) % (n - 1)
    corner_rows = jnp.stack([rows, rows + 1, rows, rows + 1], axis=-1)
    corner_cols = jnp.stack([cols, cols, right, right], axis=-1)
    flat = corner_rows * (n - 1) + corner_cols
    shares = jnp.sin((corner_rows + 1).astype(dtype) * dphi) * dphi * dtheta / 4.0
    return flat, shares


def cell_frames(
    source1: ArrayLike,
    read: str,
    interpolation: str,
    gamma: ArrayLike,
    rotation: ArrayLike,
    frames: tuple[Array, Array],
    cells: Cells,
    subdivision: int,
) -> tuple[list[Array], Array, list[Array], Array, Array]:
    """What :func:`stretch_correction` integrates: the path's frames at the cells'
    sub-points ``(N, 3, k, s^2)`` each, with their weights ``(k, s^2)``, and at the
    cells' corners ``(N, 3, k, 4)`` each, with the node rule's trapezoid share ``(k, 4)``
    and the corners' flat indices into the quadrature grid's interior ``(k, 4)``
    (arguments as there)."""
    m, n = frames[0].shape[-2] + 2, frames[0].shape[-1] + 1
    dtype = gamma.dtype
    dphi, dtheta = np.pi / (m - 1), 2.0 * np.pi / (n - 1)
    through = _through(interpolation, read)
    source = spline_coefficients(gamma) if interpolation == "spline" else gamma
    start_frame = _sub_frame(
        lambda p: through(source1, source, p), cells.points, cells.east, cells.south
    )
    end_frame = [jnp.einsum("ij,j...->i...", rotation, a) for a in cells.end_frame]
    n_times = frames[0].shape[0]
    t = jnp.linspace(0.0, 1.0, n_times, dtype=dtype).reshape(n_times, 1, 1, 1)
    sub = [a[None] + t * (b - a)[None] for a, b in zip(start_frame, end_frame, strict=True)]

    # The four corners of every cell in one gather per frame (its transpose one scatter).
    flat, corner_weights = cell_corners(cells, m, n, dtype)
    at_corners = [a.reshape(*a.shape[:2], -1)[:, :, flat] for a in frames]
    u, v = (jnp.asarray(x, dtype) for x in _sub_offsets(subdivision))
    bilinear = jnp.stack([(1 - u) * (1 - v), u * (1 - v), (1 - u) * v, u * v], axis=-1)
    for axis in range(2):
        # The perturbation at the corners is the frames' departure from the straight
        # line between their own ends (it vanishes at both ends): read from the frames,
        # not multiplied out again over the whole grid for a few percent of its cells.
        a = at_corners[axis]
        departure = a[1:-1] - (a[:1] + t[1:-1] * (a[-1:] - a[:1]))
        sub[axis] = sub[axis].at[1:-1].add(jnp.einsum("tikc,sc->tiks", departure, bilinear))
    sub_weights = cells.sin_phi * dphi * dtheta / subdivision**2
    return sub, sub_weights, at_corners, corner_weights, flat


def stretch_correction(
    metric,
    source1: ArrayLike,
    read: str,
    interpolation: str,
    gamma: ArrayLike,
    rotation: ArrayLike,
    frames: tuple[Array, Array],
    cells: Cells,
    subdivision: int,
) -> Array:
    """sum over ``cells`` of (the s x s midpoint rule - the node rule's trapezoid share)
    of the path energy (midpoint scheme), s = ``subdivision``.

    ``frames``: the path's interior frames ``(N, 3, M - 2, N' - 1)`` as the node rule
    integrates them (:func:`problem.path_frames_at`), on the quadrature's grid M x N'
    (the working grid, or the grid q times finer with ``ShapeOptions.quadrature``), whose
    cells ``cells`` (:func:`chosen_cells`) indexes: the straight line between their
    first and last time plus the path's perturbation, which is read bilinearly from each
    cell's corners; ``source1`` read by ``read``; ``gamma`` the working grid's
    ``(3, m, n)``, read at the sub-points as ``interpolation`` composes it; ``rotation``
    turns f2's sub-frames.

    A node's trapezoid shares over the chosen cells around it add up to at most its own
    weight, so the corrected rule is still a sum of squares with weights >= 0.
    """
    sub, sub_weights, at_corners, corner_weights, _ = cell_frames(
        source1, read, interpolation, gamma, rotation, frames, cells, subdivision
    )
    density, weights = pointwise_speeds2(metric, *sub, "midpoint")
    fine = jnp.einsum("tks,ks,t->", density, sub_weights, weights)
    density, weights = pointwise_speeds2(metric, *at_corners, "midpoint")
    coarse = jnp.einsum("tks,ks,t->", density, corner_weights, weights)
    return fine - coarse
