"""Reparametrizations of S^2: Proj(Id + U), Theorem 3's bound, Jacobians, f o gamma (math §6)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import scipy.special
from jaxtyping import Array, ArrayLike, Float

from .._checks import is_concrete
from .._errors import InputError
from .._runtime.cache import cached
from .differential import cross, dot, interior_frame, pole_fourier1, pole_phi_derivative
from .grid import angles_np, sphere_points
from .harmonics import check_degree, vector_fields_np
from .interp import sample_at
from .validation import as_surface, check_grid_shape

METHODS = ("bilinear", "bicubic", "spline")


def _check_coefficients(x: Array, degree: int) -> None:
    size = 2 * (degree + 1) ** 2 - 2
    if x.shape[-1:] != (size,):
        raise InputError(
            f"x must have shape (..., Lbar) with Lbar = 2(degree + 1)^2 - 2 = {size} for "
            f"degree={degree}; got {x.shape}"
        )


@jax.jit
def _diffeomorphism(x, fields, e1):
    shift = jnp.einsum("...k,kimn->...imn", x, fields)
    w = e1 + shift
    return w / jnp.linalg.norm(w, axis=-3, keepdims=True)


def diffeomorphism(
    x: Float[ArrayLike, "*batch Lbar"], m: int, n: int, degree: int
) -> Float[Array, "*batch 3 m n"]:
    """gamma_x = Proj(Id + sum_k x_k v_k) sampled on the grid (paper eq. (4.6),
    :ref:`math §6 <math-6>`).

    v_k is :func:`vector_field_basis`; Proj(y) = y / ‖y‖. A diffeomorphism for x inside
    :func:`diffeomorphism_bound` (Theorem 3); larger deformations are compositions.

    Args:
        x: ``(..., Lbar)`` coefficients, Lbar = 2(degree + 1)^2 - 2.
        m, n: grid; degree: of the vector fields.

    Returns:
        ``(..., 3, m, n)`` unit vectors: gamma at every grid point.
    """
    check_grid_shape((3, m, n), "the grid")
    check_degree(degree, m, n)
    x = jnp.asarray(x)
    _check_coefficients(x, degree)
    fields = jnp.asarray(vector_fields_np(m, n, degree), x.dtype)
    e1 = sphere_points(m, n, dtype=x.dtype)
    lead = (1,) * (x.ndim - 1)
    return _diffeomorphism(x, fields, e1.reshape(lead + e1.shape))


@cached
def _field_derivatives_np(m: int, n: int, degree: int) -> np.ndarray:
    """u, v, u_phi, u_theta, v_phi, v_theta of each basis field, U = u e_phi + v e_theta.

    Exact, from the Legendre functions' first and second derivatives; interior rows only.
    Shape ``(6, Lbar, m - 2, n)``, fields ordered as in :func:`vector_field_basis`.
    """
    phi, theta = angles_np(m, n)
    p, dp, d2p = scipy.special.sph_legendre_p_all(degree, degree, phi, diff_n=2)
    sp, cp = np.sin(phi)[1:-1, None], np.cos(phi)[1:-1, None]
    out = []
    for l in range(1, degree + 1):
        norm = np.sqrt(l * (l + 1.0))
        for k in range(-l, l + 1):
            a = abs(k)
            scale = 1.0 if k == 0 else np.sqrt(2) * (-1) ** a
            if k >= 0:
                t, dt = np.cos(a * theta), -a * np.sin(a * theta)
            else:
                t, dt = np.sin(a * theta), a * np.cos(a * theta)
            ddt = -(a**2) * t
            pp, dpp, d2pp = (scale * q[l, a, 1:-1, None] for q in (p, dp, d2p))
            y_theta, y_phi = pp * dt, dpp * t
            grad = (
                y_phi / norm,  # u
                y_theta / (sp * norm),  # v
                d2pp * t / norm,  # u_phi
                dpp * dt / norm,  # u_theta
                (dpp * dt * sp - y_theta * cp) / (sp**2 * norm),  # v_phi
                pp * ddt / (sp * norm),  # v_theta
            )
            u, v, u_phi, u_theta, v_phi, v_theta = grad
            rotated = (-v, u, -v_phi, -v_theta, u_phi, u_theta)  # e1 x (u e_phi + v e_theta)
            out.extend([grad, rotated])
    return np.moveaxis(np.asarray(out), 1, 0)


@jax.jit
def _bound(x, derivs, cos_phi, sin_phi):
    u, v, u_phi, u_theta, v_phi, v_theta = jnp.einsum("...k,jkmn->j...mn", x, derivs)
    a, b = u_phi, v_phi
    c = (u_theta - v * cos_phi) / sin_phi
    d = (v_theta + u * cos_phi) / sin_phi
    lam = 0.5 * (a + d - jnp.sqrt((a - d) ** 2 + (b + c) ** 2))
    low = jnp.min(lam, axis=(-2, -1))
    return jnp.where(low < 0, -1.0 / jnp.where(low < 0, low, -1.0), jnp.inf)


def diffeomorphism_bound(
    x: Float[ArrayLike, "*batch Lbar"], m: int, n: int, degree: int
) -> Float[Array, "*batch"]:
    """The largest t for which gamma_{t x} is guaranteed a diffeomorphism (paper Theorem 3).

    t_max = -1 / inf_p lambda_min(sym grad U), U = sum_k x_k v_k, lambda_min the smaller
    eigenvalue (a + d - sqrt((a - d)^2 + (b + c)^2)) / 2 with a = u_phi, b = v_phi,
    c = (u_theta - v cos phi) / sin phi, d = (v_theta + u cos phi) / sin phi for
    U = u e_phi + v e_theta. Derivatives are exact; the infimum is over the grid's
    interior points (a finer grid gives a tighter, still exact-in-the-limit bound).
    Sufficient, not necessary: maps beyond it may still be diffeomorphisms.

    Returns:
        ``(...)``; +inf when lambda_min >= 0 everywhere (only for U = 0).
    """
    check_grid_shape((3, m, n), "the grid")
    check_degree(degree, m, n)
    x = jnp.asarray(x)
    _check_coefficients(x, degree)
    derivs = jnp.asarray(_field_derivatives_np(m, n, degree), x.dtype)
    phi, _ = angles_np(m, n)
    lead = (1,) * (x.ndim - 1)
    cos_phi = jnp.asarray(np.cos(phi[1:-1])[:, None], x.dtype).reshape(lead + (m - 2, 1))
    sin_phi = jnp.asarray(np.sin(phi[1:-1])[:, None], x.dtype).reshape(lead + (m - 2, 1))
    return _bound(x, derivs, cos_phi, sin_phi)


@jax.jit
def jacobian_determinant_unchecked(gamma):
    a1, a2 = interior_frame(gamma)
    inner = dot(cross(a2, a1), gamma[..., 1:-1, :-1])
    # At a pole the azimuth-theta direction maps to f_phi(pole, theta) = cos X + sin Y.
    north, south = pole_phi_derivative(gamma)
    xn, yn = pole_fourier1(north)
    xs, ys = pole_fourier1(south)
    jn = jnp.sum(jnp.cross(xn, yn, axis=-1) * gamma[..., :, 0, 0], axis=-1)
    js = jnp.sum(jnp.cross(ys, xs, axis=-1) * gamma[..., :, -1, 0], axis=-1)
    cols = inner.shape[-1]
    rows = [jnp.broadcast_to(jn[..., None, None], jn.shape + (1, cols)), inner]
    rows.append(jnp.broadcast_to(js[..., None, None], js.shape + (1, cols)))
    det = jnp.concatenate(rows, axis=-2)
    return jnp.concatenate([det, det[..., :1]], axis=-1)


def jacobian_determinant(gamma: Float[ArrayLike, "*batch 3 m n"]) -> Float[Array, "*batch m n"]:
    """Signed Jacobian determinant of gamma: S^2 -> S^2 on the grid (area ratio, 1 for Id).

    J = gamma . (gamma_phi x gamma_theta / sin phi) with the differential of
    :ref:`math §2 <math-2>`; on the pole rows the tangent plane fitted to the pole row's phi
    derivatives is used.
    gamma is an orientation-preserving diffeomorphism iff J > 0 everywhere.

    Args:
        gamma: ``(..., 3, m, n)`` points on S^2.

    Returns:
        ``(..., m, n)``.
    """
    return jacobian_determinant_unchecked(as_surface(gamma, "gamma", check_immersion=False))


def _angles_of(points: Array) -> tuple[Array, Array]:
    """(phi, theta) of points ``(3, ...)``, with gradients kept finite on the z axis."""
    x, y, z = points[0], points[1], points[2]
    r2 = x * x + y * y
    off_axis = r2 > 0
    # At the poles theta is arbitrary (the pole row is constant): a safe where keeps the
    # derivative of atan2 and of the square root finite there (zero; the derivative of f
    # read at a pole comes from sample_points' rule instead).
    r = jnp.sqrt(jnp.where(off_axis, r2, 1.0))
    phi = jnp.arctan2(jnp.where(off_axis, r, 0.0), z)
    theta = jnp.arctan2(jnp.where(off_axis, y, 0.0), jnp.where(off_axis, x, 1.0))
    return phi, theta


def moebius(x: Float[ArrayLike, "3 ..."], a: Float[ArrayLike, " 3"]) -> Float[Array, "3 ..."]:
    """The Moebius map phi_a(x) = (1 - ‖a‖^2)(x - a) / ‖x - a‖^2 - a of S^2 (math §9).

    ‖a‖ < 1; a = 0 is the identity and phi_a's inverse is phi_{-a}. It fixes +-a/‖a‖,
    stretches areas near a/‖a‖ by ((1 + ‖a‖) / (1 - ‖a‖))^2 and shrinks them near -a/‖a‖
    by the inverse (16x both ways at ‖a‖ = 0.6); with the rotations these maps are the
    whole Moebius (conformal) group of the sphere. d(f, f o phi_a) = 0 for every shape f.

    Args:
        x: ``(3, ...)`` unit vectors (e.g. :func:`sphere_points`).
        a: ``(3,)`` a point of the open unit ball.

    Returns:
        ``(3, ...)`` unit vectors.

    Example:
        >>> import jax.numpy as jnp
        >>> from elastic_jax import moebius, sphere_points
        >>> x = sphere_points(13, 25)
        >>> y = moebius(x, jnp.asarray([0.0, 0.3, 0.4]))
        >>> bool(jnp.allclose(moebius(y, -jnp.asarray([0.0, 0.3, 0.4])), x))
        True
    """
    x = jnp.asarray(x)
    a = jnp.asarray(a, x.dtype)
    if x.shape[:1] != (3,) or a.shape != (3,):
        raise InputError(f"moebius needs x (3, ...) and a (3,); got {x.shape} and {a.shape}")
    if is_concrete(a) and not float(jnp.linalg.norm(a)) < 1.0:
        raise InputError(f"moebius needs |a| < 1; got |a| = {float(jnp.linalg.norm(a))}")
    a = a.reshape((3,) + (1,) * (x.ndim - 1))
    d = x - a
    d2 = jnp.sum(d * d, axis=0, keepdims=True)
    return (1.0 - jnp.sum(a * a)) * d / d2 - a


def _cubic_weights(t: Array) -> tuple[Array, Array, Array, Array]:
    """Catmull-Rom (cubic convolution, a = -1/2) weights of the 4 nodes around t in [0, 1)."""
    t2, t3 = t * t, t * t * t
    return (
        -0.5 * t3 + t2 - 0.5 * t,
        1.5 * t3 - 2.5 * t2 + 1.0,
        -1.5 * t3 + 2.0 * t2 + 0.5 * t,
        0.5 * t3 - 0.5 * t2,
    )


def _spline_weights(t: Array) -> tuple[Array, Array, Array, Array]:
    """Cubic B-spline weights of the 4 coefficients around t in [0, 1)."""
    s = 1.0 - t
    t2, t3 = t * t, t * t * t
    return (
        s * s * s / 6.0,
        0.5 * t3 - t2 + 2.0 / 3.0,
        (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0,
        t3 / 6.0,
    )


def _cubic_slopes(t: Array) -> tuple[Array, Array, Array, Array]:
    """d/dt of :func:`_cubic_weights`."""
    t2 = t * t
    return (-1.5 * t2 + 2.0 * t - 0.5, 4.5 * t2 - 5.0 * t, -4.5 * t2 + 4.0 * t + 0.5, 1.5 * t2 - t)


def _spline_slopes(t: Array) -> tuple[Array, Array, Array, Array]:
    """d/dt of :func:`_spline_weights`."""
    s = 1.0 - t
    t2 = t * t
    return (-0.5 * s * s, 1.5 * t2 - 2.0 * t, -1.5 * t2 + t + 0.5, 0.5 * t2)


def _doubly_periodic(f: Array) -> Array:
    """f's distinct columns extended across the poles by the half-turn rule to rows
    0 .. 2m - 3, periodic in both directions: ``(..., 2(m - 1), n - 1)``."""
    g = f[..., :-1]
    half = g.shape[-1] // 2
    mirrored = jnp.roll(jnp.flip(g[..., 1:-1, :], axis=-2), -half, axis=-1)
    return jnp.concatenate([g, mirrored], axis=-2)


def spline_coefficients(f: Array) -> Array:
    """The cubic B-spline coefficients ``(..., m, n)`` that interpolate ``f (..., m, n)``.

    The grid's values extend across the poles by the half-turn rule to a doubly periodic
    array of 2(m - 1) x (n - 1) values; the interpolation conditions are then a
    circulant system in each direction, solved by dividing f's Fourier coefficients by
    the B-spline's symbol (2 + cos w) / 3 (never below 1/3). The coefficients keep the
    half-turn symmetry, so rows 0..m-1 hold them all.
    """
    m = f.shape[-2]
    periodic = _doubly_periodic(f)
    p, q = periodic.shape[-2:]
    symbol_r = (2.0 + np.cos(2.0 * np.pi * np.fft.fftfreq(p))) / 3.0
    symbol_c = (2.0 + np.cos(2.0 * np.pi * np.fft.rfftfreq(q))) / 3.0
    spectrum = jnp.fft.rfft2(periodic)
    inverse = (1.0 / (symbol_r[:, None] * symbol_c[None, :])).reshape(
        (1,) * (periodic.ndim - 2) + (p, q // 2 + 1)
    )
    inverse = jnp.asarray(inverse, dtype=spectrum.dtype)
    c = jnp.fft.irfft2(spectrum * inverse, s=(p, q))[..., :m, :].astype(f.dtype)
    return jnp.concatenate([c, c[..., :1]], axis=-1)


def spline_upsample(f: Array, factor: int) -> Array:
    """f's interpolating cubic spline at the points of the grid ``factor`` times finer,
    ``(..., factor (m - 1) + 1, factor (n - 1) + 1)`` from ``f (..., m, n)``.

    The finer grid's points sit at the fixed offsets k / factor inside every cell, so
    the spline's 4 x 4 weights there are constants: one separable filter of the
    coefficients per offset (shifted copies of the doubly periodic extension), the same
    numbers as reading the spline at those points (sample_points, "spline") without a
    gather, whose reverse-mode derivative is a scatter.
    """
    m, n = f.shape[-2:]
    c = _doubly_periodic(spline_coefficients(f))

    def along(x: Array, axis: int) -> Array:
        shifted = [jnp.roll(x, 1 - a, axis=axis) for a in range(4)]  # c_(i - 1 + a) at i
        parts = []
        for k in range(factor):
            weights = _spline_weights(np.float64(k / factor))
            parts.append(sum(float(w) * s for w, s in zip(weights, shifted, strict=True)))
        # Interleave: the finer index factor i + k holds offset k of cell i.
        stacked = jnp.stack(parts, axis=axis + 1 if axis >= 0 else axis)
        shape = list(x.shape)
        shape[axis] = shape[axis] * factor
        return stacked.reshape(shape)

    fine = along(along(c, -2), -1)[..., : factor * (m - 1) + 1, :]
    return jnp.concatenate([fine, fine[..., :1]], axis=-1)


def spline_frame(f: Array) -> tuple[Array, Array]:
    """The derivatives of f's interpolating cubic spline at the interior grid points, in
    :func:`interior_frame`'s layout ``(a1, a2)``, each ``(..., m - 2, n - 1)``: a1 =
    S_theta / sin(phi), a2 = S_phi.

    At a knot the tensor spline's derivative along one direction is (c_{i+1} -
    c_{i-1}) / 2h of its coefficients, and its B-spline weights along the other
    direction (1, 4, 1) / 6 undo that direction's filter: what remains is the Pade
    derivative per direction, f's spectrum times 3 i sin(w) / (h (2 + cos w)), on the
    periodic theta rows and on the doubly periodic extension across the poles (the
    half-turn rule). Fourth order, like the spline's derivative anywhere, and two FFTs
    instead of a derivative through the spline's evaluation.
    """
    m, n = f.shape[-2:]
    q = n - 1
    w_c = 2.0 * np.pi * np.fft.rfftfreq(q)
    d_c = 3.0 * np.sin(w_c) / ((2.0 + np.cos(w_c)) * (2.0 * np.pi / q))
    inner = f[..., 1:-1, :-1]
    spectrum = jnp.fft.rfft(inner, axis=-1)
    lead = (1,) * (f.ndim - 2)  # explicit ranks: callers may forbid rank promotion
    d_c = jnp.asarray(1j * d_c.reshape(lead + (1, -1)), spectrum.dtype)
    f_theta = jnp.fft.irfft(spectrum * d_c, n=q, axis=-1)
    sin_phi = np.sin(np.arange(1, m - 1) * (np.pi / (m - 1))).reshape(lead + (-1, 1))
    a1 = (f_theta / jnp.asarray(sin_phi, f_theta.dtype)).astype(f.dtype)
    periodic = _doubly_periodic(f)
    p = periodic.shape[-2]
    w_r = 2.0 * np.pi * np.fft.rfftfreq(p)
    d_r = 3.0 * np.sin(w_r) / ((2.0 + np.cos(w_r)) * (np.pi / (m - 1)))
    spectrum = jnp.fft.rfft(periodic, axis=-2)
    d_r = jnp.asarray(1j * d_r.reshape(lead + (-1, 1)), spectrum.dtype)
    f_phi = jnp.fft.irfft(spectrum * d_r, n=p, axis=-2)
    a2 = f_phi[..., 1 : m - 1, :].astype(f.dtype)
    return a1, a2


def _bicubic_patches(f, phi, theta, kernel):
    """Every point's 4 x 4 stencil of f ``(..., *points, 4, 4)`` and its offsets (x, y)
    in grid units from the stencil's second node, in [0, 1)."""
    m, n = f.shape[-2:]
    g = f[..., :-1]
    half = g.shape[-1] // 2
    # One row beyond each pole by the half-turn rule, for the 4-row stencil.
    above = jnp.roll(g[..., 1:2, :], -half, axis=-1)
    below = jnp.roll(g[..., -2:-1, :], -half, axis=-1)
    ext = jnp.concatenate([above, g, below], axis=-2)  # rows -1..m
    x = jnp.clip(phi * ((m - 1) / np.pi), 0.0, m - 1.0)
    row = jnp.clip(jnp.floor(x), 0, m - 2)
    y = jnp.mod(theta * ((n - 1) / (2.0 * np.pi)), n - 1.0)
    col = jnp.floor(y)
    i0, j0 = row.astype(jnp.int32), col.astype(jnp.int32)
    lead = (1,) * i0.ndim
    offsets = jnp.arange(4, dtype=jnp.int32)
    rows = i0[..., None, None] + offsets.reshape(lead + (4, 1))
    cols = jnp.mod(j0[..., None, None] + offsets.reshape(lead + (1, 4)) - 1, n - 1)
    # One gather of every 4 x 4 stencil (16 separate gathers compile and differentiate
    # several times slower).
    return ext[..., rows, cols], x - row, y - col


def _sample_bicubic(f, phi, theta, kernel=_cubic_weights):
    patch, tx, ty = _bicubic_patches(f, phi, theta, kernel)
    weights_r = jnp.stack(kernel(tx), axis=-1).astype(f.dtype)
    weights_c = jnp.stack(kernel(ty), axis=-1).astype(f.dtype)
    return jnp.einsum("...ab,...a,...b->...", patch, weights_r, weights_c)


_KERNELS = {
    "bicubic": (_cubic_weights, _cubic_slopes),
    "spline": (_spline_weights, _spline_slopes),
    "coefficients": (_spline_weights, _spline_slopes),
}


def directional_derivatives(f, points, directions, method):
    """f's interpolant differentiated at ``points (3, *pts)`` of S^2 along each of
    ``directions`` (tangent vectors, each ``(3, *pts)``): a tuple of ``(..., 3, *pts)``.

    The same numbers as ``jax.jvp`` of :func:`sample_points` along each direction (to
    rounding; the pole rule included), from one gather of the 4 x 4 stencils and the
    weights' slopes: the chain rule of f o gamma reads two directions at every point,
    and its reverse-mode derivative through two forward-mode derivatives of the read
    was most of a registration objective's cost at 97 x 193. Bicubic-family methods
    only ("bicubic", "spline", "coefficients").
    """
    weights, slopes = _KERNELS[method]
    source = spline_coefficients(f) if method == "spline" else f
    m, n = f.shape[-2:]
    x, y, z = points[0], points[1], points[2]
    r2 = x * x + y * y
    # As in _angles_of: a safe radius keeps every branch (and its derivative) finite.
    r2 = jnp.where(r2 > 0, r2, 1.0)
    r = jnp.sqrt(r2)
    phi, theta = _angles_of(points)
    patch, tx, ty = _bicubic_patches(source, phi, theta, weights)
    w_r, w_c, s_r, s_c = (
        jnp.stack(k(t), axis=-1).astype(f.dtype)
        for k, t in ((weights, tx), (weights, ty), (slopes, tx), (slopes, ty))
    )
    f_phi = jnp.einsum("...ab,...a,...b->...", patch, s_r, w_c) * ((m - 1) / np.pi)
    f_theta = jnp.einsum("...ab,...a,...b->...", patch, w_r, s_c) * ((n - 1) / (2.0 * np.pi))
    at_pole, on_axis = _pole_rule(f, points, method)
    out = []
    for d in directions:
        dx, dy, dz = d[0], d[1], d[2]
        dphi = (z * (x * dx + y * dy) / r - r * dz) / (r2 + z * z)
        dtheta = (x * dy - y * dx) / r2
        moved = f_phi * _per_point(f, dphi) + f_theta * _per_point(f, dtheta)
        out.append(jnp.where(on_axis, at_pole(d), moved))
    return tuple(out)


def _per_point(f, a):
    """``a (*points)`` as ``(1, ..., 1, *points)``: results are laid out as f's leading
    axes (batch and coordinate) then the points'."""
    return a.reshape((1,) * (f.ndim - 2) + a.shape)


def _pole_rule(f, points, method):
    """(along, on_axis): ``along(d)`` is f's differential at the pole applied to the
    tangents ``d (3, *points)`` (see _sample_points_jvp), ``on_axis`` where it replaces
    the angles' chart (within sqrt(eps) of the z axis), both laid out as _per_point's."""
    (xn, yn), (xs, ys) = _pole_planes(f, method)
    k = points.ndim - 1
    xn, yn, xs, ys = (c.reshape(c.shape + (1,) * k) for c in (xn, yn, xs, ys))
    north = _per_point(f, points[2] > 0)
    eps = jnp.finfo(points.dtype).eps
    on_axis = _per_point(f, points[0] * points[0] + points[1] * points[1] <= eps)

    def along(d):
        dx, dy = _per_point(f, d[0]), _per_point(f, d[1])
        return jnp.where(north, xn * dx + yn * dy, -(xs * dx + ys * dy))

    return along, on_axis


def _sample_in_angles(f, points, method):
    phi, theta = _angles_of(points)
    if method == "bilinear":
        return sample_at(f, phi, theta)
    if method == "spline":
        return _sample_bicubic(spline_coefficients(f), phi, theta, _spline_weights)
    if method == "coefficients":  # f holds a spline's coefficients (spline_coefficients)
        return _sample_bicubic(f, phi, theta, _spline_weights)
    return _sample_bicubic(f, phi, theta)


def _pole_planes(f, method):
    """((X, Y) north, (X', Y') south): f's differential at the poles (pole_fourier1 of
    f_phi on the pole rows), of the interpolant that ``method`` reads."""
    if method not in ("spline", "coefficients"):
        return tuple(pole_fourier1(row) for row in pole_phi_derivative(f))
    # The spline's f_phi on a pole row is the central difference of its coefficients
    # smoothed along the row by the B-spline's (1, 4, 1) / 6, which scales the first
    # Fourier mode by (2 + cos dtheta) / 3.
    n = f.shape[-1]
    smoothing = float(2.0 + np.cos(2.0 * np.pi / (n - 1))) / 3.0  # a weak scalar: keeps f32
    rows = pole_phi_derivative(spline_coefficients(f) if method == "spline" else f)
    return tuple(tuple(smoothing * v for v in pole_fourier1(row)) for row in rows)


@functools.partial(jax.custom_jvp, nondiff_argnums=(2,))
def sample_points(f, points, method):
    """f read at ``points (3, ...)`` of S^2: ``(..., 3, ...)``."""
    return _sample_in_angles(f, points, method)


@sample_points.defjvp
def _sample_points_jvp(method, primals, tangents):
    # The angles are a singular chart on the z axis: _angles_of keeps their derivative
    # finite there by holding it at zero, so a point exactly on a pole (every pole-row
    # point under a Diff step at x = 0, the start of each registration round) would get
    # no derivative at all. The derivative there is f's differential at the pole
    # instead: moving the north pole by d changes f by X d_x + Y d_y, with (X, Y) the
    # first Fourier mode of f_phi on the pole row (the tangent plane of
    # jacobian_determinant); moving the south pole, phi decreases: -(X' d_x + Y' d_y).
    f, points = primals
    df, dpoints = tangents
    value, moved = jax.jvp(lambda p: _sample_in_angles(f, p, method), (points,), (dpoints,))
    at_pole, on_axis = _pole_rule(f, points, method)
    # Within sqrt(eps) of the axis as well: the chart's derivative divides f_theta, whose
    # rounding is ~eps, by the distance rho to the axis, so its error is ~eps / rho, and
    # the pole's differential is off by ~rho there; the two meet at rho = sqrt(eps). A
    # rotation that maps a grid point onto a pole leaves it ~1e-16 off the axis (the
    # icosahedral starts at 13 x 25 map the equator's theta = 0 there): the chart gave
    # gradients wrong by O(1), which moved 10 of the 60 start searches of cat1 -> cat2
    # when the data changed by 1e-10.
    tangent = jnp.where(on_axis, at_pole(dpoints), moved) + _sample_in_angles(df, points, method)
    return value, tangent


@functools.partial(jax.jit, static_argnames=("method",))
def reparametrize_unchecked(f, gamma, *, method):
    return sample_points(f, gamma, method)


def reparametrize(
    f: Float[ArrayLike, "*batch 3 m n"], gamma: Float[ArrayLike, "3 p q"], method: str = "bilinear"
) -> Float[Array, "*batch 3 p q"]:
    """f o gamma by interpolation on the grid (:ref:`math §6 <math-6>`), differentiable in f and
    gamma.

    gamma gives, at every point of a (p, q) grid, the point of S^2 where f is read. The
    interpolation is periodic in theta and crosses the poles by the half-turn rule.
    "bilinear" (the paper's) is second order; "bicubic" (Catmull-Rom, C^1) third order,
    its derivative second; "spline" (the interpolating cubic B-spline, C^2: f's values
    filtered once, by FFT, on the doubly periodic extension across the poles) fourth
    order, its derivative too (the bumpy surface rotated: 3.2e-6 against 4.6e-5 for
    bicubic at 50 x 99).

    Args:
        f: ``(..., 3, m, n)`` surfaces.
        gamma: ``(3, p, q)`` unit vectors, e.g. from :func:`diffeomorphism`.
        method: ``"bilinear"``, ``"bicubic"`` or ``"spline"``.

    Returns:
        ``(..., 3, p, q)``.
    """
    if method not in METHODS:
        raise InputError(f"method must be one of {METHODS}; got {method!r}")
    f = as_surface(f, "f", check_immersion=False)
    gamma = jnp.asarray(gamma, f.dtype)
    if gamma.ndim != 3 or gamma.shape[0] != 3:
        raise InputError(f"gamma must have shape (3, p, q); got {gamma.shape}")
    return reparametrize_unchecked(f, gamma, method=method)


def rotate_parametrization(
    f: Float[ArrayLike, "*batch 3 m n"], rotation: Float[ArrayLike, "3 3"], method: str = "bilinear"
) -> Float[Array, "*batch 3 m n"]:
    """f o R: the surface reparametrized by the rotation x -> R x of the sphere
    (:ref:`math §6 <math-6>`).

    Args:
        f: ``(..., 3, m, n)``; rotation: ``(3, 3)``; method: as in :func:`reparametrize`.

    Returns:
        ``(..., 3, m, n)``.
    """
    f = as_surface(f, "f", check_immersion=False)
    m, n = f.shape[-2:]
    gamma = jnp.einsum("ij,jmn->imn", jnp.asarray(rotation, f.dtype), sphere_points(m, n, f.dtype))
    return reparametrize(f, gamma, method=method)
