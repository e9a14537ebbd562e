"""The spherical-harmonic surface basis of the path's perturbation (math §5, 7) on a grid,
the straight line's frames that it perturbs, and the per-grid tables of a shape solve
(:func:`make_bases`): what geodesics, registration and statistics all build paths and
reparametrizations from."""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from jax.typing import DTypeLike
from jaxtyping import Array, ArrayLike

from .._options import ShapeOptions
from .._runtime.cache import cached
from .differential import interior_frame
from .grid import interior_weights_np, sphere_points_np
from .harmonics import harmonic_factors_np, harmonics_np, vector_field_tables_np
from .so3 import icosahedral_np

__all__ = [
    "RESOLUTION_FACTOR",
    "Bases",
    "basis_np",
    "field_scale_np",
    "frames_between",
    "grid_area_np",
    "make_bases",
    "path_from_coefficients",
    "perturbed_frames",
    "resolution_np",
]


@cached
def basis_np(m: int, n: int, degree: int) -> tuple[np.ndarray, np.ndarray]:
    """Harmonics of degree 1..deg as ``(K, m n)`` and their differentials as ``(K, 2 P)``.

    P = (m - 2)(n - 1) interior points. One matmul with the second gives the
    perturbation of every frame's differential (measured faster than an einsum).
    """
    y = harmonics_np(m, n, degree).values[1:]
    a1, a2 = interior_frame(y)
    k = y.shape[0]
    return y.reshape(k, m * n), np.concatenate([a1.reshape(k, -1), a2.reshape(k, -1)], axis=1)


def frames_between(start: Sequence[ArrayLike], end: Sequence[ArrayLike], n_times: int):
    """Interior frames of the straight line between two surfaces given by their frames."""
    t = jnp.linspace(0.0, 1.0, n_times, dtype=start[0].dtype).reshape(n_times, 1, 1, 1)
    # a + t (b - a): velocities are exactly zero when f1 = f2.
    return [a[None] + t * (b - a)[None] for a, b in zip(start, end, strict=True)]


def perturbed_frames(straight: Sequence[Array], coefficients: ArrayLike, dframe: ArrayLike):
    """Frames of the straight line plus sum_j C[k, j] S_j on the interior time points."""
    s1, s2 = straight
    n_inner, shape = s1.shape[0] - 2, s1.shape[1:]
    k = dframe.shape[0]
    points = dframe.shape[1] // 2
    pert = (coefficients.reshape(-1, k) @ dframe).reshape(n_inner, 3, 2 * points)
    p1 = pert[..., :points].reshape((n_inner, *shape))
    p2 = pert[..., points:].reshape((n_inner, *shape))
    return s1.at[1:-1].add(p1), s2.at[1:-1].add(p2)


def path_from_coefficients(
    f1: ArrayLike, f2: ArrayLike, coefficients: ArrayLike, values: ArrayLike, n_times: int
):
    """The path (N, 3, m, n): straight line plus the basis perturbation (paper eq. (4.2))."""
    m, n = f1.shape[-2:]
    k = values.shape[0]
    t = jnp.linspace(0.0, 1.0, n_times, dtype=f1.dtype)[1:-1].reshape(n_times - 2, 1, 1, 1)
    interior = f1[None] + t * (f2 - f1)[None]
    interior = interior + (coefficients.reshape(-1, k) @ values).reshape(n_times - 2, 3, m, n)
    return jnp.concatenate([f1[None], interior, f2[None]])


@cached
def field_scale_np(m: int, n: int, degree: int) -> np.ndarray:
    """1 / sqrt(l(l+1)) per vector field: differentials grow like l; this evens the Hessian."""
    ls = harmonics_np(m, n, degree).degrees[1:]
    return np.repeat(1.0 / np.sqrt(ls * (ls + 1.0)), 2)


class Bases(NamedTuple):
    """The arrays a solve needs besides the surfaces (precomputed per grid and degree)."""

    values: Array  # (K, m n) path harmonics
    dframe: Array  # (K, 2 P) their differentials
    field_rows: Array  # (2, m, Lbar) the Diff-step vector fields (harmonics.FieldTables)
    field_select: Array  # (2, Lbar, G)
    field_trig: Array  # (G, n)
    field_frames: Array  # (2, 3, m, n)
    field_poles: Array  # (Lbar, 3, 2, n)
    field_scale: Array  # (Lbar,)
    ico: Array  # (60, 3, 3)
    fine_points: Array  # (3, M', N') the refinement grid's points (refinement_grid)
    fine_rows: Array  # (K, M') the path harmonics' row factors there (harmonic_factors_np)
    fine_columns: Array  # (K, N') and their column factors
    quad_points: Array  # (3, M, N) the quadrature's nodes (options.quadrature > 1)
    quad_dframe: Array  # (K, 2 P'') the path harmonics' differentials there
    area_floor: Array  # () least grid area a reparametrization may keep (resolution_np)
    max_boost: Array  # () largest |a| of a Moebius map the grid resolves


# A reparametrization is resolved by the grid when the unit sphere it reparametrizes keeps
# its discrete area to within this many times the area the grid already loses for the
# identity (0.71 % at 25 x 49): a Moebius map with |a| = 0.6 needs 2.6-3.2 times, and the
# bounded boost search below must reach it well inside its bound.
RESOLUTION_FACTOR = 5.0


def grid_area_np(gamma: np.ndarray) -> float:
    """Discrete area of the unit sphere reparametrized by gamma: the integral of its J."""
    a1, a2 = interior_frame(gamma)
    m, n = gamma.shape[-2:]
    signed = np.sum(np.cross(a2, a1, axis=0) * gamma[:, 1:-1, :-1], axis=0)
    return float(np.sum(signed * interior_weights_np(m, n)))


@cached
def resolution_np(m: int, n: int) -> tuple[float, float]:
    """(area floor, largest resolved Moebius |a|) of the m x n grid.

    Where a reparametrization stretches a region beyond what the grid resolves, finite
    differences of f o gamma lose area (chords for arcs), and a registration that wants a
    smaller start surface gains by it: the radius-3 sphere registered to a unit sphere
    came out at 40 % of the distance before this floor. A gamma may keep no less than
    (1 - 5 eps_id) of the identity's discrete area, eps_id = 1 - A_grid(e1) / (4 pi); the
    boost |a| of the initial Moebius search is bounded to where a Moebius map keeps it.
    """
    e1 = sphere_points_np(m, n)
    area_id = grid_area_np(e1)
    floor = area_id * (1.0 - RESOLUTION_FACTOR * (1.0 - area_id / (4.0 * np.pi)))
    # A direction that no grid symmetry favours; moebius() written out in numpy, because
    # this runs while callers (karcher_mean) trace their jitted batches.
    direction = np.array([0.36, 0.48, 0.8]) / np.linalg.norm([0.36, 0.48, 0.8])
    low, high = 0.0, 0.99
    for _ in range(30):
        mid = 0.5 * (low + high)
        a = mid * direction[:, None, None]
        d = e1 - a
        gamma = (1.0 - mid * mid) * d / np.sum(d * d, axis=0) - a
        low, high = (mid, high) if grid_area_np(gamma) >= floor else (low, mid)
    return floor, low


def refinement_grid(m: int, n: int, q: int) -> tuple[int, int]:
    """The grid a result on the m x n working grid is re-evaluated on (:class:`Refinement`):
    twice finer than the grid its energy was integrated on, (2 q (m - 1) + 1) x
    (2 q (n - 1) + 1) for quadrature factor q, so that it reads what that rule did not."""
    return 2 * q * (m - 1) + 1, 2 * q * (n - 1) + 1


def make_bases(m: int, n: int, options: ShapeOptions, dtype: DTypeLike) -> Bases:
    """The :class:`Bases` of a solve on the m x n working grid, in ``dtype``.

    The path's harmonics of degree 1..``options.degree`` (math §5) and their
    differentials, the Diff step's vector fields of degree 1..``options.vf_degree``
    (math §6) with their 1 / sqrt(l(l+1)) scale, the icosahedral rotations of the start
    search, the nodes and separable harmonic factors of the refinement grid
    (:func:`refinement_grid`), the nodes and differentials of the quadrature grid
    (q (m - 1) + 1) x (q (n - 1) + 1), q = ``options.quadrature``,
    and the grid's area floor and largest resolved Moebius boost (:func:`resolution_np`).
    Registration, logs and metric fits build their problems from it.
    """
    values, dframe = basis_np(m, n, options.degree)
    tables = vector_field_tables_np(m, n, options.vf_degree)
    q = options.quadrature_factor
    quad = (q * (m - 1) + 1, q * (n - 1) + 1)
    if q == 1:
        quad_points, quad_dframe = np.zeros((3, 1, 1)), np.zeros((1, 1))
    else:
        quad_points, quad_dframe = sphere_points_np(*quad), basis_np(*quad, options.degree)[1]
    if options.refinement:
        fine = refinement_grid(m, n, q)
        fine_points = sphere_points_np(*fine)
        fine_rows, fine_columns = (a[1:] for a in harmonic_factors_np(*fine, options.degree))
    else:
        fine_points, fine_rows, fine_columns = (
            np.zeros((3, 1, 1)),
            np.zeros((1, 1)),
            np.zeros((1, 1)),
        )
    arrays = Bases(
        values=values,
        dframe=dframe,
        field_rows=tables.rows,
        field_select=tables.select,
        field_trig=tables.trig,
        field_frames=tables.frames,
        field_poles=tables.poles,
        field_scale=field_scale_np(m, n, options.vf_degree),
        ico=icosahedral_np(),
        fine_points=fine_points,
        fine_rows=fine_rows,
        fine_columns=fine_columns,
        quad_points=quad_points,
        quad_dframe=quad_dframe,
        area_floor=np.asarray(resolution_np(m, n)[0]),
        max_boost=np.asarray(resolution_np(m, n)[1]),
    )
    return Bases(*(jnp.asarray(a, dtype) for a in arrays))
