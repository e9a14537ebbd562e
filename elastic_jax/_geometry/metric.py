"""The split elastic metric on M+(3, 2) and its integral over a surface (math §3)."""

from __future__ import annotations

import dataclasses
import numbers

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._checks import is_concrete
from .._errors import InputError
from .differential import cross, dot, interior_frame
from .grid import integrate_interior
from .validation import as_surface


def _coefficient(name: str, value: object):
    if not is_concrete(value):
        return value
    if isinstance(value, numbers.Real) and not isinstance(value, bool):
        arr = np.asarray(float(value))
    else:
        arr = np.asarray(value)
        if not np.issubdtype(arr.dtype, np.floating) and not np.issubdtype(arr.dtype, np.integer):
            raise InputError(
                f"SplitMetric: coefficient {name} must be a real number; got {value!r}"
            )
    if not np.all(np.isfinite(arr)):
        raise InputError(f"SplitMetric: coefficient {name}={value!r} is not finite")
    if np.any(arr < 0):
        raise InputError(f"SplitMetric: coefficient {name}={value!r} is negative; all must be >= 0")
    # Python floats stay weakly typed, so one metric serves float32 and float64 surfaces.
    return float(arr) if arr.ndim == 0 and not isinstance(value, jax.Array) else value


@jax.tree_util.register_pytree_node_class
@dataclasses.dataclass(frozen=True)
class SplitMetric:
    """Coefficients (a, b, c, d) >= 0 of the split metric (paper eq. (3.4),
    :ref:`math §3 <math-3>`).

    G = a <xi_m, xi_m> + b <xi_vol, xi_vol> + c <xi_perp, xi_perp> + d <xi_0, xi_0>:
    a weighs shearing (change of the metric at fixed volume), b the change of volume
    density, c bending (change of the normal), d local rotation in the tangent plane.
    (0, 1/2, 1, 0) is the SRNF metric. A pytree whose leaves are the four coefficients,
    so jitted functions trace them: changing the values never recompiles.

    Raises:
        InputError: (a ValueError) a coefficient is negative, not finite or not a real
            number, or all four are zero (for arrays: at some element).

    Example:
        >>> SplitMetric(1.0, 1.0, 0.1, 0.0)
        SplitMetric(a=1.0, b=1.0, c=0.1, d=0.0)
    """

    # Python floats, or arrays (a batch of metrics, traced leaves under jit and vmap).
    a: ArrayLike
    b: ArrayLike
    c: ArrayLike
    d: ArrayLike

    def __post_init__(self):
        values = [_coefficient(k, getattr(self, k)) for k in "abcd"]
        for k, v in zip("abcd", values, strict=True):
            object.__setattr__(self, k, v)
        if is_concrete(values):
            # Elementwise, so that a batch of metrics (arrays) is checked member by member.
            total = sum(np.asarray(v, dtype=np.float64) for v in values)
            if np.any(total == 0):
                raise InputError("SplitMetric: all four coefficients are zero; the metric vanishes")

    @classmethod
    def from_elastic(cls, ae: ArrayLike, be: ArrayLike, ce: ArrayLike) -> SplitMetric:
        """The split metric equal to Jermyn's elastic metric (ae, be, ce) (paper Theorem 2).

        a = 4 ae, b = 8 be + 4 ae, c = ce, d = 0; needs ae >= 0, be >= -ae / 2, ce >= 0.
        """
        return cls(4 * ae, 8 * be + 4 * ae, ce, 0.0)

    def tree_flatten(self):
        return (self.a, self.b, self.c, self.d), None

    @classmethod
    def tree_unflatten(cls, aux: None, children):
        # Bypass __post_init__: JAX rebuilds pytrees with tracers and placeholder leaves.
        obj = object.__new__(cls)
        for k, v in zip("abcd", children, strict=True):
            object.__setattr__(obj, k, v)
        return obj


SRNF_METRIC = (0.0, 0.5, 1.0, 0.0)


def _pointwise(x: Array) -> tuple[Array, Array]:
    """Columns of ``(..., 3, 2)`` matrices in the kernels' layout ``(..., 3, 1, 1)``."""
    return x[..., 0, None, None], x[..., 1, None, None]


def _split_frame(a1: ArrayLike, a2: ArrayLike):
    """sqrt(det g) at alpha = [a1 a2] and ``parts(v1, v2)``: the six factors of a tangent
    vector xi = [v1 v2] in the frame of :func:`split_bilinear` (sym B's trace-free
    diagonal and off-diagonal, tr B, skew B's entry, p_1, p_2)."""
    r11 = jnp.sqrt(dot(a1, a1))
    e1 = a1 / r11[..., None, :, :]
    normal = cross(a1, a2)
    sqrt_det = jnp.sqrt(dot(normal, normal))
    n = normal / sqrt_det[..., None, :, :]
    e2 = cross(n, e1)
    c1 = 1.0 / r11
    c2 = r11 / sqrt_det  # 1 / r22
    t = dot(e1, a2) * c1  # r12 / r11

    def parts(v1: ArrayLike, v2: ArrayLike):
        u1, u2, w1, w2 = dot(e1, v1), dot(e2, v1), dot(e1, v2), dot(e2, v2)
        b11, b21 = u1 * c1, u2 * c1
        b12, b22 = (w1 - u1 * t) * c2, (w2 - u2 * t) * c2
        q1, q2 = dot(n, v1), dot(n, v2)
        p1, p2 = q1 * c1, (q2 - q1 * t) * c2
        return b11 - b22, b12 + b21, b11 + b22, b21 - b12, p1, p2

    return sqrt_det, parts


def split_bilinear(
    metric: SplitMetric,
    a1: ArrayLike,
    a2: ArrayLike,
    x1: ArrayLike,
    x2: ArrayLike,
    y1: ArrayLike,
    y2: ArrayLike,
) -> Array:
    """G_alpha(xi, eta) for alpha = [a1 a2], xi = [x1 x2], eta = [y1 y2] (vector axis -3).

    Written in an orthonormal frame of the tangent plane, so that every term is a product
    of two factors of one size and G_alpha(xi, xi) a weighted sum of squares. alpha = Q R
    (Q = [e1 e2] orthonormal, e1 = a1 / |a1|, e2 = n x e1 with n the unit normal; R upper
    triangular with r11 = |a1|, r12 = e1 . a2, r22 = sqrt(det g) / r11), and for each
    tangent vector B = Q^T xi R^-1 (2 x 2) and p = n^T xi R^-1 (1 x 2). Then g^-1 S_xi is
    similar to sym B and, with sqrt(det g) = |a1 x a2|,
      shear  = |(sym B_xi)°|^2                   (° the trace-free part)
      volume = (tr B_xi)^2 / 2
      perp   = |p_xi|^2
      rot    = 2 (skew B_xi)_12^2
    each multiplied by sqrt(det g) (written for xi = eta; the bilinear form is the same
    products of xi's factors by eta's). This is math §3's decomposition with the metric
    tensor's inverse and det g^(3/2) cancelled analytically: the written-out 2 x 2 algebra
    of g^-1 (products of the metric's entries) lost the path energy's gradient in float32
    where frames are stretched (relative L2 error 0.96 at 97 x 193 on the cats' straight
    line, against 3e-4 in this form).
    """
    sqrt_det, parts = _split_frame(a1, a2)
    dx, ox, tx, kx, p1x, p2x = parts(x1, x2)
    dy, oy, ty, ky, p1y, p2y = parts(y1, y2)
    shear = 0.5 * (dx * dy + ox * oy)
    volume = 0.5 * tx * ty
    perp = p1x * p1y + p2x * p2y
    rot = 0.5 * kx * ky
    return sqrt_det * (metric.a * shear + metric.b * volume + metric.c * perp + metric.d * rot)


def split_residuals(
    metric: SplitMetric, a1: ArrayLike, a2: ArrayLike, v1: ArrayLike, v2: ArrayLike
) -> list[Array]:
    """G_alpha(xi, xi) as a sum of squares: six arrays ``(..., p, q)`` whose squares add up
    to :func:`split_bilinear` ``(a1, a2, v1, v2, v1, v2)`` (vector axis -3), each factor of
    xi times sqrt(sqrt(det g) c) for its coefficient c in math §3's decomposition (shear
    a / 2 twice, volume b / 2, rotation d / 2, the normal part c twice). The residuals a
    Gauss-Newton or Levenberg-Marquardt solver of the path energy would take."""
    sqrt_det, parts = _split_frame(a1, a2)
    d, o, t, k, p1, p2 = parts(v1, v2)
    root = jnp.sqrt(sqrt_det)
    weights = (0.5 * metric.a, 0.5 * metric.a, 0.5 * metric.b, 0.5 * metric.d, metric.c, metric.c)
    return [root * jnp.sqrt(w) * x for w, x in zip(weights, (d, o, t, k, p1, p2), strict=True)]


def split_parts(
    alpha: Float[ArrayLike, "*batch 3 2"], xi: Float[ArrayLike, "*batch 3 2"]
) -> tuple[Array, Array, Array, Array]:
    """The orthogonal decomposition xi = xi_m + xi_vol + xi_perp + xi_0 (:ref:`math §3 <math-3>`).

    With g = alpha^T alpha, alpha^+ = g^-1 alpha^T, P = alpha alpha^+:
    xi_vol = 1/2 tr(alpha^+ xi) alpha; xi_m = 1/2 alpha g^-1 (alpha^T xi + xi^T alpha) - xi_vol;
    xi_perp = xi - P xi; xi_0 = 1/2 alpha g^-1 (alpha^T xi - xi^T alpha).

    Args:
        alpha: ``(..., 3, 2)`` matrices of rank 2.
        xi: ``(..., 3, 2)`` tangent vectors (broadcast against alpha).

    Returns:
        ``(xi_m, xi_vol, xi_perp, xi_0)``, each ``(..., 3, 2)``.
    """
    alpha, xi = jnp.broadcast_arrays(jnp.asarray(alpha), jnp.asarray(xi))
    if alpha.shape[-2:] != (3, 2):
        raise InputError(f"alpha and xi must have shape (..., 3, 2); got {alpha.shape}")
    return _split_parts(alpha, xi)


def _inv2(g: Array) -> Array:
    det = g[..., 0, 0] * g[..., 1, 1] - g[..., 0, 1] * g[..., 1, 0]
    adj = jnp.stack(
        [
            jnp.stack([g[..., 1, 1], -g[..., 0, 1]], -1),
            jnp.stack([-g[..., 1, 0], g[..., 0, 0]], -1),
        ],
        -2,
    )
    return adj / det[..., None, None]


@jax.jit
def _split_parts(alpha: Array, xi: Array):
    at = jnp.swapaxes(alpha, -1, -2)
    ginv = _inv2(at @ alpha)
    a_xi = at @ xi
    lift = alpha @ ginv  # alpha g^-1, (..., 3, 2)
    tangential = lift @ a_xi
    xi_vol = 0.5 * jnp.trace(ginv @ a_xi, axis1=-2, axis2=-1)[..., None, None] * alpha
    xi_m = lift @ (0.5 * (a_xi + jnp.swapaxes(a_xi, -1, -2))) - xi_vol
    xi_0 = lift @ (0.5 * (a_xi - jnp.swapaxes(a_xi, -1, -2)))
    return xi_m, xi_vol, xi - tangential, xi_0


def base_inner(
    alpha: Float[ArrayLike, "*batch 3 2"],
    xi: Float[ArrayLike, "*batch 3 2"],
    eta: Float[ArrayLike, "*batch 3 2"],
) -> Float[Array, "*batch"]:
    """The base inner product <xi, eta>_alpha = tr(xi g^-1 eta^T) sqrt(det g) (paper eq. (3.3)).

    Args:
        alpha, xi, eta: ``(..., 3, 2)``, broadcast together.

    Returns:
        ``(...)``.
    """
    alpha, xi, eta = jnp.broadcast_arrays(*map(jnp.asarray, (alpha, xi, eta)))
    at = jnp.swapaxes(alpha, -1, -2)
    g = at @ alpha
    det = g[..., 0, 0] * g[..., 1, 1] - g[..., 0, 1] * g[..., 1, 0]
    return jnp.einsum("...ij,...jk,...ik->...", xi, _inv2(g), eta) * jnp.sqrt(det)


def split_inner(
    metric: SplitMetric,
    alpha: Float[ArrayLike, "*batch 3 2"],
    xi: Float[ArrayLike, "*batch 3 2"],
    eta: Float[ArrayLike, "*batch 3 2"],
) -> Float[Array, "*batch"]:
    """The split metric G^{a,b,c,d}_alpha(xi, eta) at one point (paper eq. (3.4),
    :ref:`math §3 <math-3>`).

    Args:
        metric: the coefficients.
        alpha: ``(..., 3, 2)`` of rank 2; xi, eta: ``(..., 3, 2)``; broadcast together.

    Returns:
        ``(...)``.
    """
    alpha, xi, eta = jnp.broadcast_arrays(*map(jnp.asarray, (alpha, xi, eta)))
    if alpha.shape[-2:] != (3, 2):
        raise InputError(f"alpha, xi and eta must have shape (..., 3, 2); got {alpha.shape}")
    out = split_bilinear(metric, *_pointwise(alpha), *_pointwise(xi), *_pointwise(eta))
    return out[..., 0, 0]


@jax.jit
def metric_inner_unchecked(metric: SplitMetric, f: ArrayLike, u: ArrayLike, v: ArrayLike):
    return integrate_interior(
        split_bilinear(metric, *interior_frame(f), *interior_frame(u), *interior_frame(v))
    )


def _broadcast_fields(f: ArrayLike, u: ArrayLike, v: ArrayLike) -> tuple[Array, Array, Array]:
    f = as_surface(f, "f")
    u, v = (jnp.asarray(x, dtype=f.dtype) for x in (u, v))
    grid = ", ".join(map(str, f.shape[-3:]))
    for name, x in (("u", u), ("v", v)):
        if x.shape[-3:] != f.shape[-3:]:
            raise InputError(
                f"{name} must be a field on the grid of f, (..., {grid}); got {x.shape}"
            )
        if is_concrete(x) and not np.isfinite(np.asarray(x)).all():
            raise InputError(f"{name} contains non-finite values (NaN or inf)")
    return tuple(jnp.broadcast_arrays(f, u, v))


def metric_inner(
    metric: SplitMetric,
    f: Float[ArrayLike, "*batch 3 m n"],
    u: Float[ArrayLike, "*batch 3 m n"],
    v: Float[ArrayLike, "*batch 3 m n"],
) -> Float[Array, "*batch"]:
    """The split metric of a surface, G_f(u, v) = integral over S^2 of G_{df}(du, dv)
    (:ref:`math §3 <math-3>`).

    The integrand uses the differential and the quadrature of :ref:`math §2 <math-2>`
    (trapezoid in phi and theta, times sin phi). Exactly invariant under rotations and
    translations of R^3; invariant under reparametrizations up to discretization.

    Args:
        metric: the coefficients (a, b, c, d).
        f: ``(..., 3, m, n)`` base surface(s), an immersion.
        u, v: ``(..., 3, m, n)`` tangent vectors (vector fields along f); leading axes broadcast.

    Returns:
        ``(...)`` the inner products.

    Example:
        >>> from elastic_jax import SplitMetric, metric_inner, sphere_points
        >>> e1 = sphere_points(25, 49)
        >>> g = metric_inner(SplitMetric(1, 1, 0, 0), e1, e1, e1)  # 24.954 in float64
        >>> # 8 pi b = 25.133 in the continuum: u = f is pure volume change; error O(h^2)
    """
    f, u, v = _broadcast_fields(f, u, v)
    return metric_inner_unchecked(metric, f, u, v)


def _elastic_pointwise(
    ae: ArrayLike, be: ArrayLike, ce: ArrayLike, alpha: ArrayLike, xi: ArrayLike, eta: ArrayLike
):
    """Jermyn's elastic metric from dg and dn in matrix form (independent of the split kernel)."""
    at = jnp.swapaxes(alpha, -1, -2)
    g = at @ alpha
    ginv = jnp.linalg.inv(g)
    sqrt_det = jnp.sqrt(jnp.linalg.det(g))
    a1, a2 = alpha[..., 0], alpha[..., 1]
    normal = jnp.cross(a1, a2)

    def dg_dn(x: ArrayLike):
        dg = at @ x + jnp.swapaxes(x, -1, -2) @ alpha
        tr = jnp.trace(ginv @ at @ x, axis1=-2, axis2=-1)
        dn = jnp.cross(x[..., 0], a2) + jnp.cross(a1, x[..., 1]) - normal * tr[..., None]
        return dg, dn / sqrt_det[..., None]

    dg_x, dn_x = dg_dn(xi)
    dg_y, dn_y = dg_dn(eta)
    term_a = jnp.trace(ginv @ dg_x @ ginv @ dg_y, axis1=-2, axis2=-1)
    term_b = jnp.trace(ginv @ dg_x, axis1=-2, axis2=-1) * jnp.trace(ginv @ dg_y, axis1=-2, axis2=-1)
    term_c = jnp.sum(dn_x * dn_y, axis=-1)
    return (ae * term_a + be * term_b + ce * term_c) * sqrt_det


def _as_matrices(f: Array) -> Array:
    """Interior differential as ``(..., m-2, n-1, 3, 2)`` matrices."""
    a1, a2 = interior_frame(f)
    return jnp.moveaxis(jnp.stack([a1, a2], axis=-3), (-4, -3), (-2, -1))


@jax.jit
def _elastic_metric_inner(
    ae: ArrayLike, be: ArrayLike, ce: ArrayLike, f: ArrayLike, u: ArrayLike, v: ArrayLike
):
    values = _elastic_pointwise(ae, be, ce, _as_matrices(f), _as_matrices(u), _as_matrices(v))
    return integrate_interior(values)


def elastic_metric_inner(
    ae: ArrayLike,
    be: ArrayLike,
    ce: ArrayLike,
    f: Float[ArrayLike, "*batch 3 m n"],
    u: Float[ArrayLike, "*batch 3 m n"],
    v: Float[ArrayLike, "*batch 3 m n"],
) -> Float[Array, "*batch"]:
    """The general elastic metric of Jermyn et al., written from dg and dn
    (:ref:`math §3 <math-3>`).

    integral of [ae tr(g^-1 dg_u g^-1 dg_v) + be tr(g^-1 dg_u) tr(g^-1 dg_v) + ce <dn_u, dn_v>]
    sqrt(det g), with dg = alpha^T xi + xi^T alpha and
    dn = (xi1 x a2 + a1 x xi2 - (a1 x a2) tr(alpha^+ xi)) / sqrt(det g). A cross-check of
    the split metric: with d = 0 it equals G^{a,b,c,0} for ae = a/4, be = (b-a)/8, ce = c
    (paper Theorem 2). Uses batched matrix routines, so it is slower than metric_inner.

    Args:
        ae, be, ce: the elastic coefficients (be may be negative down to -ae/2).
        f, u, v: as in :func:`metric_inner`.

    Returns:
        ``(...)``.
    """
    f, u, v = _broadcast_fields(f, u, v)
    return _elastic_metric_inner(ae, be, ce, f, u, v)
