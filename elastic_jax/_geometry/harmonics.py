"""Real spherical harmonics on the grid and the two bases built from them (math §5)."""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
import scipy.special
from jaxtyping import Array, Float, Int

from .._checks import check_int
from .._errors import InputError
from .._runtime.cache import cached
from .grid import angles_np, sphere_tangents_np


class SphericalHarmonics(NamedTuple):
    """Real spherical harmonics Y_lk of degree 0..deg on the grid, ordered by (l, k), k = -l..l.

    values, d_phi, d_theta: ``(K, m, n)``, K = (deg + 1)^2; degree, order: ``(K,)``.
    """

    values: Float[Array, "K m n"]
    d_phi: Float[Array, "K m n"]
    d_theta: Float[Array, "K m n"]
    degree: Int[Array, " K"]
    order: Int[Array, " K"]


def max_degree(m: int, n: int) -> int:
    """The highest degree whose harmonics stay linearly independent on the m x n grid.

    Order k needs abs(k) < (n - 1) / 2 distinct azimuths and degree l <= m - 3 interior rows
    for order 0, so deg <= min(m - 3, (n - 3) // 2): 9 at 12 x 25, 22 at 25 x 49, 47 at 50 x 99.
    """
    return min(m - 3, (n - 3) // 2)


def check_degree(degree: int, m: int, n: int, name: str = "degree") -> int:
    """``degree`` as an int if 1 <= degree <= :func:`max_degree` (m, n); else InputError."""
    return degree_within(check_int(name, degree, 1), m, n, name)


def degree_within(degree: int, m: int, n: int, name: str = "degree") -> int:
    """An int ``degree`` (an options record's, checked already) if at most
    :func:`max_degree` (m, n), the highest whose harmonics are independent on the grid;
    else InputError."""
    limit = max_degree(m, n)
    if degree > limit:
        raise InputError(
            f"{name}={degree} is too high for the {m} x {n} grid: the limit is {limit} "
            "(min(m - 3, (n - 3) // 2), beyond which the harmonics are not independent on the grid)"
        )
    return degree


class HarmonicsTable(NamedTuple):
    """The real spherical harmonics of degree 0..L on the m x n grid, in numpy float64:
    K = (L + 1)^2 rows ordered by degree l, then order k = -l .. l."""

    values: np.ndarray  # (K, m, n) Y_lk
    d_phi: np.ndarray  # (K, m, n) dY/dphi
    d_theta: np.ndarray  # (K, m, n) dY/dtheta
    theta_over_sin: np.ndarray  # (K, m, n) (dY/dtheta) / sin(phi), pole limits included
    degrees: np.ndarray  # (K,) l
    orders: np.ndarray  # (K,) k


def _azimuthal(k: int, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """The order-k factor of the real harmonics Y_lk on the grid's azimuths: (trig, its
    theta derivative, the normalization sqrt2 (-1)^k, 1 for k = 0); cos for k > 0, sin for
    k < 0. The seam column repeats column 0 exactly."""
    a = abs(k)
    if k == 0:
        trig, dtrig, scale = np.ones_like(theta), np.zeros_like(theta), 1.0
    elif k > 0:
        trig, dtrig, scale = np.cos(a * theta), -a * np.sin(a * theta), np.sqrt(2) * (-1) ** a
    else:
        trig, dtrig, scale = np.sin(a * theta), a * np.cos(a * theta), np.sqrt(2) * (-1) ** a
    trig[-1], dtrig[-1] = trig[0], dtrig[0]
    return trig, dtrig, scale


@cached
def harmonics_np(m: int, n: int, degree: int) -> HarmonicsTable:
    """The harmonics of degree 0..degree and their derivatives on the grid (math §5)."""
    phi, theta = angles_np(m, n)
    p, dp = scipy.special.sph_legendre_p_all(degree, degree, phi, diff_n=1)
    sin_phi = np.sin(phi)
    # p_lk(phi) / sin(phi): at the poles its limit is +-p'_lk for |k| = 1 and 0 otherwise.
    ratio = np.zeros_like(p)
    ratio[..., 1:-1] = p[..., 1:-1] / sin_phi[1:-1]
    for k in (1, -1):
        ratio[:, k, 0] = dp[:, k, 0]
        ratio[:, k, -1] = -dp[:, k, -1]
    rows = []
    for l in range(degree + 1):
        for k in range(-l, l + 1):
            a = abs(k)
            trig, dtrig, scale = _azimuthal(k, theta)
            rows.append(
                (
                    scale * np.outer(p[l, a], trig),
                    scale * np.outer(dp[l, a], trig),
                    scale * np.outer(p[l, a], dtrig),
                    scale * np.outer(ratio[l, a], dtrig),
                    l,
                    k,
                )
            )
    return HarmonicsTable(*map(np.asarray, zip(*rows, strict=True)))


@cached
def harmonic_factors_np(m: int, n: int, degree: int) -> tuple[np.ndarray, np.ndarray]:
    """The harmonics of degree 0..degree on the m x n grid as separable factors:
    ``(rows (K, m), columns (K, n))`` with Y_lk = outer(rows[r], columns[r]) for the
    r-th harmonic in :func:`harmonics_np`'s order (its ``values``, to rounding).

    A combination sum_r c_r Y_r on a fine grid is then ``(c * rows).T @ columns``: two
    small tables instead of a (K, m n) one (the refinement's grid at 97 x 193 levels,
    385 x 769, would hold 150 MB in float64).
    """
    phi, theta = angles_np(m, n)
    p = scipy.special.sph_legendre_p_all(degree, degree, phi, diff_n=1)[0]
    rows, columns = [], []
    for l in range(degree + 1):
        for k in range(-l, l + 1):
            trig, _, scale = _azimuthal(k, theta)
            rows.append(scale * p[l, abs(k)])
            columns.append(trig)
    return np.asarray(rows), np.asarray(columns)


def real_sph_harm(m: int, n: int, degree: int, dtype=None) -> SphericalHarmonics:
    """Orthonormal real spherical harmonics of degree 0..degree on the grid
    (:ref:`math §5 <math-5>`).

    Y_l0 = Re Y_l0, Y_lk = sqrt2 (-1)^k Re Y_lk (k > 0), Y_lk = sqrt2 (-1)^k Im Y_l|k| (k < 0),
    from scipy's normalized associated Legendre functions (stable recurrences, fine to
    degree 47 at 50 x 99), with analytic phi and theta derivatives. Cached per (m, n, degree).

    Args:
        m, n: grid size; degree: highest degree (at most :func:`max_degree`).
        dtype: floating dtype (default: JAX's default float).

    Returns:
        :class:`SphericalHarmonics` with ``(K, m, n)`` arrays, K = (degree + 1)^2.
    """
    check_degree(degree, m, n)
    y, y_phi, y_theta, _, ls, ks = harmonics_np(m, n, degree)
    return SphericalHarmonics(
        *(jnp.asarray(a, dtype=dtype) for a in (y, y_phi, y_theta)),
        jnp.asarray(ls),
        jnp.asarray(ks),
    )


def surface_basis(m: int, n: int, degree: int, dtype=None) -> Float[Array, "L 3 m n"]:
    """Perturbations S_j = Y_lk e_i of a surface, degree 1..degree (paper section 4.1).

    Degree 0 (translations) is left out: L = 3((degree + 1)^2 - 1). Index j = i K + k for
    coordinate i and harmonic k (K = (degree + 1)^2 - 1), so coefficients ``(..., L)``
    reshape to ``(..., 3, K)``. Orthonormal in L2(S^2, R^3) up to the quadrature error.

    Returns:
        ``(L, 3, m, n)``.
    """
    check_degree(degree, m, n)
    y = harmonics_np(m, n, degree).values[1:]
    k = y.shape[0]
    basis = np.zeros((3, k, 3, m, n))
    for i in range(3):
        basis[i, :, i] = y
    return jnp.asarray(basis.reshape(3 * k, 3, m, n), dtype=dtype)


@cached
def vector_fields_np(m: int, n: int, degree: int) -> np.ndarray:
    """grad Y / sqrt(l(l+1)) and e1 x grad Y / sqrt(l(l+1)), ``(Lbar, 3, m, n)`` float64."""
    table = harmonics_np(m, n, degree)
    y_phi, grad_theta, ls = table.d_phi, table.theta_over_sin, table.degrees
    e_theta, e_phi = sphere_tangents_np(m, n)
    norm = np.sqrt(ls[1:] * (ls[1:] + 1.0))[:, None, None, None]
    a, b = y_phi[1:, None], grad_theta[1:, None]
    grad = (a * e_phi + b * e_theta) / norm
    rotated = (a * e_theta - b * e_phi) / norm
    fields = np.stack([grad, rotated], axis=1).reshape(-1, 3, m, n)
    # The pole rows describe one tangent vector each; remove the rounding across columns.
    fields[..., 0, :] = fields[..., 0, :1]
    fields[..., -1, :] = fields[..., -1, :1]
    fields[..., -1] = fields[..., 0]
    return fields


class FieldTables(NamedTuple):
    """:func:`vector_fields_np` in separable form (float64 numpy): on the interior rows a
    field is p(phi) t(theta) e_phi + q(phi) s(theta) e_theta, t and s two of the
    trigonometric functions 1, cos k theta, sin k theta (k <= degree), so that
    sum_k y_k v_k = (R_phi y) S_phi T e_phi + (R_theta y) S_theta T e_theta costs O(m Lbar G
    + m G n) instead of the dense sum's O(Lbar m n) (and no (Lbar, 3, m, n) array to read:
    72 MB at 97 x 193, degree 8). The pole rows, one tangent vector each, stay dense."""

    rows: np.ndarray  # (2, m, Lbar): p and q per field, zero on the pole rows
    select: np.ndarray  # (2, Lbar, G): which trigonometric function each field's t, s is
    trig: np.ndarray  # (G, n): 1, cos theta, sin theta, ..., cos(degree theta), sin(...)
    frames: np.ndarray  # (2, 3, m, n): e_phi and e_theta, zero on the pole rows
    poles: np.ndarray  # (Lbar, 3, 2, n): the fields on the two pole rows


@cached
def vector_field_tables_np(m: int, n: int, degree: int) -> FieldTables:
    """:class:`FieldTables` of the fields of :func:`vector_fields_np`, read off them (each
    field's components along e_phi and e_theta projected on the trigonometric functions
    over the n - 1 distinct columns) and checked to rebuild them to 1e-12."""
    fields = vector_fields_np(m, n, degree)
    e_theta, e_phi = sphere_tangents_np(m, n)
    theta = angles_np(m, n)[1]
    trig = [np.ones_like(theta)]
    for k in range(1, degree + 1):
        trig += [np.cos(k * theta), np.sin(k * theta)]
    trig = np.stack(trig)
    trig[:, -1] = trig[:, 0]  # the seam column repeats column 0, as the fields' does
    count = fields.shape[0]
    rows = np.zeros((2, m, count))
    select = np.zeros((2, count, trig.shape[0]))
    for c, frame in enumerate((e_phi, e_theta)):
        part = np.einsum("kcmn,cmn->kmn", fields[:, :, 1:-1], frame[:, 1:-1])
        coef = part[..., :-1] @ trig[:, :-1].T / np.sum(trig[:, :-1] ** 2, axis=1)
        which = np.argmax(np.sum(coef**2, axis=1), axis=-1)
        rows[c, 1:-1] = coef[np.arange(count), :, which].T
        select[c, np.arange(count), which] = 1.0
    frames = np.stack([e_phi, e_theta])
    frames[:, :, [0, -1]] = 0.0
    tables = FieldTables(rows, select, trig, frames, fields[:, :, [0, -1]])
    error = np.max(np.abs(_rebuilt_fields(tables) - fields))
    if not error <= 1e-12 * max(1.0, np.max(np.abs(fields))):
        raise AssertionError(f"vector fields not separable on {m} x {n}: error {error:.2e}")
    return tables


def _rebuilt_fields(tables: FieldTables) -> np.ndarray:
    """The dense fields ``(Lbar, 3, m, n)`` from their tables (the check above)."""
    along = np.einsum("aik,akg,gn->akin", tables.rows, tables.select, tables.trig)
    fields = np.einsum("akin,acin->kcin", along, tables.frames)
    fields[:, :, 0], fields[:, :, -1] = tables.poles[:, :, 0], tables.poles[:, :, 1]
    return fields


def vector_field_basis(m: int, n: int, degree: int, dtype=None) -> Float[Array, "Lbar 3 m n"]:
    """Tangent vector fields on S^2: grad Y_lk and e1 x grad Y_lk over sqrt(l(l+1))
    (:ref:`math §5 <math-5>`).

    grad Y = Y_phi e_phi + (Y_theta / sin phi) e_theta with e_phi, e_theta the unit
    coordinate vectors; on the pole rows the limit of Y_theta / sin phi is used, so the
    fields are exact there too. Lbar = 2(degree + 1)^2 - 2; entries 2j and 2j + 1 are the
    gradient and the rotated gradient of harmonic j (degree >= 1). Unit L2 norm each.

    Returns:
        ``(Lbar, 3, m, n)`` fields tangent to the sphere (stored in R^3).
    """
    check_degree(degree, m, n)
    return jnp.asarray(vector_fields_np(m, n, degree), dtype=dtype)
