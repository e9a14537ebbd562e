"""Inversion of the square root normal function map, and inverted SRNF straight lines.

Given q, find a surface f with Q(f) ~ q by minimizing ||Q(f0 + sum_j c_j S_j) - q||^2 over
the coefficients c of the spherical-harmonic surface basis S_j (math §5), coarse to fine
in the degree: Laga, Xie, Jermyn, Srivastava, "Numerical inversion of SRNF maps for
elastic shape analysis of genus-zero surfaces", IEEE TPAMI 39(12), 2017. Q(f) is the SRNF
of math §3 (:func:`elastic_jax.srnf`) and the norm the L2 norm over S^2 with the
quadrature of math §2, as in :func:`elastic_jax.srnf_distance`.

Q sees only df, so it is blind to translations: every inverted surface is returned
centred (area-weighted centroid at the origin, :func:`elastic_jax.center`).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._checks import (
    check_choice,
    check_finite,
    check_grid_shape,
    check_int,
    check_positive,
    is_concrete,
    real_array,
)
from .._errors import ConvergenceWarning, InputError, warn_user
from .._geometry.bases import basis_np
from .._geometry.differential import cross, dot, interior_frame
from .._geometry.grid import integrate_interior, interior_weights_np, sphere_points_np
from .._geometry.harmonics import check_degree
from .._geometry.numerics import sqrt_inverse_pair
from .._geometry.srnf import center_unchecked, sqrt_normal, srnf_unchecked, surface_area_unchecked
from .._geometry.validation import as_surface, check_pair
from .._options import FROM_OPTIONS, SOLVERS, FromOptions, ShapeOptions, settings_from
from .._results import RESULTS, first_failure, status_record
from .._runtime.cache import cached, solver_jit
from .solvers import minimize

__all__ = ["SrnfGeodesic", "SrnfInversion", "srnf_geodesic", "srnf_invert"]


@status_record
class SrnfInversion(NamedTuple):
    """A surface whose SRNF approximates a given q; a pytree.

    Attributes:
        surface: ``(3, m, n)`` center(f0 + sum_j c_j S_j), the inverted surface, centred.
        residual: ``()`` ||Q(surface) - q||, the L2 norm over S^2 (the quadrature of
            :ref:`math §2 <math-2>`).
        relative_residual: ``()`` residual / ||q||.
        coefficients: ``(L,)`` c over f0 in :func:`elastic_jax.surface_basis` order at the
            last degree, L = 3((degree + 1)^2 - 1), in the surface's units.
        num_steps: ``()`` solver steps over all levels.
        converged: ``()`` whether the solve of the last level met its tolerance.
        result: the last level's result code (``elastic_jax.RESULTS``).
        grad_norm: ``()`` 2-norm of the gradient of the last level's scaled objective
            (||Q - q||^2 / ||q||^2 in whitened coefficients, Hessian ~2 I).
        level_residuals: ``(levels,)`` the residual ||Q(f) - q|| at the end of each level.
    """

    surface: Float[Array, "3 m n"]
    residual: Float[Array, ""]
    relative_residual: Float[Array, ""]
    coefficients: Float[Array, " L"]
    grad_norm: Float[Array, ""]
    level_residuals: Float[Array, " levels"]
    converged: Bool[Array, ""]
    result: RESULTS
    num_steps: Int[Array, ""]


@status_record
class SrnfGeodesic(NamedTuple):
    """The inverted SRNF straight line between two surfaces (paper, Table 2: L_i); a pytree.

    Attributes:
        path: ``(N, 3, m, n)`` f1, the inversions of (1 - t_k) q1 + t_k q2 at the interior
            times t_k = k / (N - 1), f2. The ends are the inputs, exactly; interior frame k
            has its area-weighted centroid at (1 - t_k) c1 + t_k c2 (c1, c2: the inputs').
        residuals: ``(N,)`` ||Q(path[k]) - ((1 - t_k) q1 + t_k q2)|| (0 at the ends).
        relative_residuals: ``(N,)`` residuals over ||(1 - t_k) q1 + t_k q2||.
        srnf_length: ``()`` sum_k ||Q(path[k + 1]) - Q(path[k])||, the L2 length of the
            path's SRNF image (= its (0, 1/2, 1, 0) split-metric length, :ref:`math §3 <math-3>`).
        srnf_distance: ``()`` ||q1 - q2||, the length of the straight line being inverted;
            srnf_distance <= srnf_length <= srnf_distance + 2 sum(residuals).
        node_steps: ``(N,)`` solver steps of each node's inversion (0 at the ends).
        nodes_converged: ``(N,)`` whether each node's last level met its tolerance (True
            at the ends).
        converged: ``()`` every node's inversion converged.
        result: ``successful``, or the first unconverged node's result code.
        num_steps: ``()`` solver steps over all nodes.
    """

    path: Float[Array, "N 3 m n"]
    residuals: Float[Array, " N"]
    relative_residuals: Float[Array, " N"]
    srnf_length: Float[Array, ""]
    srnf_distance: Float[Array, ""]
    node_steps: Int[Array, " N"]
    nodes_converged: Bool[Array, " N"]
    converged: Bool[Array, ""]
    result: RESULTS
    num_steps: Int[Array, ""]

    def _explain(self, words: str) -> str:
        if bool(self.converged):
            return ""
        failed = np.flatnonzero(~np.asarray(self.nodes_converged)).tolist()
        return f"nodes {failed} did not converge: {words}"


@cached
def _unit_sphere_area(m: int, n: int) -> float:
    # The grid's own area of the unit sphere (4 pi to O(h^2)), so that the start's discrete
    # area matches the area q encodes exactly.
    return float(surface_area_unchecked(jnp.asarray(sphere_points_np(m, n))))


def _srnf_norm2(q_inner: Array) -> Array:
    """||q||^2 from q on interior rows and distinct columns; the area q encodes."""
    return integrate_interior(dot(q_inner, q_inner))


def _invert_level(q_inner, norm2, f0_frames, c0, dframe, *, solver, max_steps, tol):
    """One level: minimize ||Q(f0 + sum_j c_j S_j) - q||^2 over c, from c0 (traceable).

    The objective is divided by ||q||^2 and solved in coordinates z with c = c0 + A z,
    A = G^(-1/2), G = J^T W J / ||q||^2 the Gauss-Newton matrix at c0 (J = dQ/dc, W the
    quadrature weights). G is also the Gram matrix of the basis under the SRNF metric
    (0, 1/2, 1, 0) (math §3), and its condition grows like l^2 with the degree; in z
    the Hessian is ~2 I near a small residual, so one gradient tolerance means the same
    at every degree, size and shape (the geodesic solver's convention).
    """
    k = dframe.shape[0]
    points = dframe.shape[1] // 2
    b1, b2 = f0_frames
    dtype = q_inner.dtype

    def q_of(c):
        pert = c.reshape(3, k) @ dframe
        a1 = b1 + pert[:, :points].reshape(b1.shape)
        a2 = b2 + pert[:, points:].reshape(b2.shape)
        # docs/math.md §3: a1 x a2 points inward for the identity; Q uses the outward normal.
        return sqrt_normal(cross(a2, a1))

    m, n = b1.shape[-2] + 2, b1.shape[-1] + 1
    root_w = jnp.asarray(np.sqrt(interior_weights_np(m, n))[None], dtype)
    jac = jax.jacfwd(lambda c: (q_of(c) * root_w).reshape(-1))(c0)
    gram = (jac.T @ jac) / norm2
    # The SRNF metric has no shear term (a = 0), so G may have nearly free directions;
    # unfloored, A would stretch them without bound (the geodesic solver's floor).
    whiten, _ = sqrt_inverse_pair(gram, 1e-6)

    def objective(z):
        d = q_of(c0 + whiten @ z) - q_inner
        return _srnf_norm2(d) / norm2

    # max_steps and tol are traced scalars (see _STATIC): the step limit is a cap.
    found = minimize(
        objective, jnp.zeros_like(c0), solver=solver, max_steps=None, tol=tol, step_cap=max_steps
    )
    c = c0 + whiten @ found.x
    residual = jnp.sqrt(_srnf_norm2(q_of(c) - q_inner))
    return c, residual, found


def _invert(q, f0, values, dframe, *, degrees, solver, max_steps, tol):
    """Coarse-to-fine inversion of q from f0 (traceable; both in units of size ~1).

    ``values``, ``dframe``: the basis of the last degree from ``basis_np``; a lower
    degree's basis is its leading rows (harmonics ordered by degree).
    """
    m, n = q.shape[-2:]
    q_inner = q[:, 1:-1, :-1]
    norm2 = _srnf_norm2(q_inner)
    frames = interior_frame(f0)
    c = jnp.zeros((3, 0), q.dtype)
    residuals, num_steps = [], jnp.zeros((), jnp.int32)
    for degree in degrees:
        k = (degree + 1) ** 2 - 1
        # Each level starts from the previous level's surface: its coefficients padded
        # with zeros for the new degrees.
        c0 = jnp.pad(c, ((0, 0), (0, k - c.shape[1]))).reshape(-1)
        c, residual, found = _invert_level(
            q_inner,
            norm2,
            frames,
            c0,
            dframe[:k],
            solver=solver,
            max_steps=max_steps,
            tol=tol,
        )
        c = c.reshape(3, k)
        residuals.append(residual)
        num_steps = num_steps + found.num_steps
    k = c.shape[1]
    surface = f0 + (c @ values[:k]).reshape(3, m, n)
    residual = residuals[-1]
    return SrnfInversion(
        surface=center_unchecked(surface),
        residual=residual,
        relative_residual=residual / jnp.sqrt(norm2),
        coefficients=c.reshape(-1),
        num_steps=num_steps,
        converged=found.result == RESULTS.successful,
        result=found.result,
        grad_norm=found.grad_norm,
        level_residuals=jnp.stack(residuals),
    )


# The step limit and tol are traced (int32 and float scalars): inversions that differ
# only in them share one compiled program.
_STATIC = ("degrees", "solver")
_invert_jit = solver_jit(_invert, static_argnames=_STATIC)


@functools.partial(solver_jit, static_argnames=("n_times", *_STATIC))
def _srnf_line(q1, q2, f1, values, dframe, *, n_times, degrees, solver, max_steps, tol):
    """Interior nodes of the inverted straight line, each warm-started from the previous."""
    times = jnp.linspace(0.0, 1.0, n_times, dtype=q1.dtype)[1:-1]

    def node(previous, t):
        target = q1 + t * (q2 - q1)
        found = _invert(
            target,
            previous,
            values,
            dframe,
            degrees=degrees,
            solver=solver,
            max_steps=max_steps,
            tol=tol,
        )
        return found.surface, found

    _, nodes = jax.lax.scan(node, f1, times)
    return nodes


def _srnf_units(*qs: Array) -> Array:
    """The power of two nearest the radius of the sphere with the largest area the qs
    encode (exact to divide by and restore). Q is homogeneous of degree 1, Q(f / s) =
    Q(f) / s, so the solve runs on surfaces of size ~1 in any dtype. Traceable: a call
    under jit or vmap solves in the same units as one outside (the same numbers)."""
    area = jnp.max(jnp.stack([_srnf_norm2(q[:, 1:-1, :-1]) for q in qs]))
    exponent = jnp.round(0.5 * jnp.log2(jnp.where(area > 0, area, 4.0 * jnp.pi) / (4.0 * jnp.pi)))
    return 2.0**exponent


def _check_degrees(degrees, m: int, n: int) -> tuple[int, ...]:
    if isinstance(degrees, str) or not isinstance(degrees, Sequence) or len(degrees) == 0:
        raise InputError(
            f"degrees must be a non-empty sequence of increasing degrees; got {degrees!r}"
        )
    checked = tuple(check_degree(d, m, n, f"degrees[{i}]") for i, d in enumerate(degrees))
    if any(b <= a for a, b in zip(checked, checked[1:], strict=False)):
        raise InputError(f"degrees must be strictly increasing; got {degrees!r}")
    return checked


def _check_options(degrees, solver, max_steps, tol, m, n, dtype):
    """Validate the inversion options; returns degrees, max_steps, tol (dtype default)."""
    degrees = _check_degrees(degrees, m, n)
    check_choice("solver", solver, SOLVERS)
    max_steps = check_int("max_steps", max_steps, 1)
    tol = inversion_tol(dtype) if tol is None else check_positive("tol", tol)
    return degrees, max_steps, tol


def inversion_tol(dtype) -> float:
    """The inversion's default tolerance on the scaled gradient's 2-norm: 1e-8 in float64,
    1e-4 in float32.

    Tighter than a geodesic's (1e-6, 3e-3) because one surface is cheap: in float64, 1e-6
    to 1e-8 took 33 to 44 BFGS steps on an in-span target (13 x 25, degrees (2, 3)) and
    moved the recovered surface from 7e-7 to 4e-9 relative. float32 reached gradients of
    4e-6 (ellipsoid, 13 x 25, degree 2) and 1e-5 (bumpy, 25 x 49, degrees (2, 4, 7, 12))
    before rounding stopped it; 1e-4 keeps a margin above that (relative residuals 1.7e-5
    and 6e-5 there).
    """
    return 1e-8 if jnp.dtype(dtype) == jnp.float64 else 1e-4


def _check_srnf(q) -> Array:
    q = real_array(q, "q")
    m, n = check_grid_shape(q.shape, "q")
    if q.ndim != 3:
        raise InputError(f"q must be one SRNF (3, m, n); got {q.shape}. Batch with jax.vmap.")
    check_finite(q, "q")
    if is_concrete(q) and not float(_srnf_norm2(q[:, 1:-1, :-1])) > 0:
        raise InputError(
            f"q is zero at every interior point of the {m} x {n} grid: it encodes a surface "
            "of area 0, which no immersion has"
        )
    return q


def _warn_unconverged(where: str, solver: str, tol: float, converged, message) -> None:
    # message is a callable: the result code can be read only outside jit and vmap.
    if is_concrete(converged) and not bool(np.all(np.asarray(converged))):
        warn_user(
            f"{where}: {solver} stopped without meeting tol={tol:g}: {message()}",
            ConvergenceWarning,
        )


def srnf_invert(
    q: Float[ArrayLike, "3 m n"],
    *,
    f0: Float[ArrayLike, "3 m n"] | None = None,
    degrees: Sequence[int] = (2, 4, 7),
    options: ShapeOptions | None = None,
    max_steps: int | FromOptions = FROM_OPTIONS,
    tol: float | None | FromOptions = FROM_OPTIONS,
    solver: str | FromOptions = FROM_OPTIONS,
) -> SrnfInversion:
    """A surface whose SRNF is closest to q: min_c ‖Q(f0 + sum_j c_j S_j) - q‖ (Laga et al.).

    Q is the SRNF map of :ref:`math §3 <math-3>` and S_j the surface basis of degree 1..d
    (:ref:`math §5 <math-5>`, 3((d + 1)^2 - 1) fields). The degrees are solved coarse to fine,
    each level starting
    from the previous level's surface (Laga, Xie, Jermyn, Srivastava, "Numerical
    inversion of SRNF maps for elastic shape analysis of genus-zero surfaces", IEEE
    TPAMI 39(12), 2017). Each level is a BFGS solve in coefficients whitened by the
    Gauss-Newton matrix at its start (Hessian ~2 I, as in :func:`elastic_jax.geodesic`),
    on the problem divided by ‖q‖^2 and in units of the size q encodes, so that tol
    means the same at every scale. The whole solve is one jitted call.

    Q is invariant under translations, so the translation of f is not determined: the
    surface is returned centred (:func:`elastic_jax.center`). Q is not injective in
    general; the answer is the local minimum reached from f0. A q off the image of Q (a
    straight line between SRNFs, a q beyond the basis' resolution) leaves a residual.

    Args:
        q: ``(3, m, n)`` the target SRNF on the grid (:ref:`math §1 <math-1>`); the pole rows
            and the seam column carry no quadrature weight and are not used.
        f0: ``(3, m, n)`` the start; default: the unit-sphere grid scaled so that its area
            (on the grid) equals ‖q‖^2, the area q encodes (‖Q(f)‖^2 is f's area element).
        degrees: strictly increasing degrees of the levels, each at most
            min(m - 3, (n - 3) // 2).
        options: a :class:`ShapeOptions` whose ``solver``, ``max_steps`` and ``tol`` this
            solve uses (its defaults when None); the keywords below change one of them.
        max_steps: step limit of each level's solve (default: the record's, 500).
        tol: converged means the 2-norm of the gradient of the last level's scaled
            objective is at most tol (:func:`elastic_jax.geodesic`'s convention). None
            (the record's default) is this objective's precision default, 1e-8 in float64
            and 1e-4 in float32 (``inversion_tol()``), tighter than a geodesic's. Near a
            zero residual the surface is then accurate to about tol / 2 relative.
        solver: ``"bfgs"`` (optimistix.BFGS) or ``"lbfgs"`` (jaxopt.LBFGS); default the
            record's.

    Returns:
        :class:`SrnfInversion`; a ConvergenceWarning when the last level did not converge.

    Example:
        >>> import elastic_jax as ej
        >>> from elastic_jax import shapes
        >>> q = ej.srnf(shapes.sample(shapes.ellipsoid, 13, 25))
        >>> res = ej.srnf_invert(q, degrees=(2,))
        >>> bool(res.relative_residual < 1e-4)
        True
    """
    settings = settings_from("srnf_invert", options, solver=solver, max_steps=max_steps, tol=tol)
    solver, max_steps, tol = settings.values()
    q = _check_srnf(q)
    m, n = q.shape[-2:]
    degrees, max_steps, tol = _check_options(degrees, solver, max_steps, tol, m, n, q.dtype)
    scale = _srnf_units(q)
    if f0 is None:
        radius = jnp.sqrt(_srnf_norm2(q[:, 1:-1, :-1]) / _unit_sphere_area(m, n))
        start = (radius / scale) * jnp.asarray(sphere_points_np(m, n), q.dtype)
    else:
        f0 = as_surface(f0, "f0")
        if f0.shape != q.shape or f0.dtype != q.dtype:
            raise InputError(
                f"f0 must have the shape and dtype of q, {q.shape} {q.dtype}; got "
                f"{f0.shape} {f0.dtype}"
            )
        start = center_unchecked(f0) / scale
    values, dframe = (jnp.asarray(a, q.dtype) for a in basis_np(m, n, degrees[-1]))
    found = _invert_jit(
        q / scale,
        start,
        values,
        dframe,
        degrees=degrees,
        solver=solver,
        max_steps=jnp.asarray(max_steps, jnp.int32),
        tol=jnp.asarray(tol, q.dtype),
    )
    found = found._replace(
        surface=found.surface * scale,
        residual=found.residual * scale,
        coefficients=found.coefficients * scale,
        level_residuals=found.level_residuals * scale,
    )
    _warn_unconverged("srnf_invert", solver, tol, found.converged, lambda: found.message)
    return found


def srnf_geodesic(
    f1: Float[ArrayLike, "3 m n"],
    f2: Float[ArrayLike, "3 m n"],
    n_times: int | FromOptions = FROM_OPTIONS,
    *,
    degrees: Sequence[int] = (2, 4, 7),
    options: ShapeOptions | None = None,
    max_steps: int | FromOptions = FROM_OPTIONS,
    tol: float | None | FromOptions = FROM_OPTIONS,
    solver: str | FromOptions = FROM_OPTIONS,
) -> SrnfGeodesic:
    """The inverted SRNF straight line: f_k = Q^-1((1 - t_k) q1 + t_k q2) (paper, Table 2: L_i).

    q1 = Q(f1), q2 = Q(f2) (:ref:`math §3 <math-3>`) and t_k = k / (N - 1). The straight line is the
    geodesic of the flat L2 metric on SRNFs, but it leaves the image of Q, so its
    inversion (:func:`srnf_invert` at each interior time, the inversion method of Laga
    et al., IEEE TPAMI 2017) is a path of surfaces whose SRNF image only approximates
    it; the residuals say by how much. Node k starts from node k - 1's surface (node 1
    from f1), so that the path follows one branch of the inverse. Its length under the
    split metric (0, 1/2, 1, 0) is ``srnf_length``, the paper's L_i, and ||q1 - q2|| is
    a lower bound of the geodesic distance (:ref:`math §3 <math-3>`).

    Args:
        f1, f2: ``(3, m, n)`` immersions on the same grid.
        n_times: N >= 2 time points, ends included (default: the record's, 13).
        degrees, options, max_steps, tol, solver: the inversion options of
            :func:`srnf_invert`, for every interior node.

    Returns:
        :class:`SrnfGeodesic`; a ConvergenceWarning when a node did not converge.
    """
    settings = settings_from(
        "srnf_geodesic",
        options,
        n_times=n_times,
        solver=solver,
        max_steps=max_steps,
        tol=tol,
    )
    n_times, solver, max_steps, tol = settings.values()
    f1, f2 = check_pair(f1, f2)
    m, n = f1.shape[-2:]
    n_times = check_int("n_times", n_times, 2)
    degrees, max_steps, tol = _check_options(degrees, solver, max_steps, tol, m, n, f1.dtype)
    q1, q2 = srnf_unchecked(f1), srnf_unchecked(f2)
    scale = _srnf_units(q1, q2)
    centred1 = center_unchecked(f1)
    shift1, shift2 = f1 - centred1, f2 - center_unchecked(f2)
    t = jnp.linspace(0.0, 1.0, n_times, dtype=f1.dtype)
    zero_i, true = jnp.zeros(1, jnp.int32), jnp.ones(1, bool)
    if n_times > 2:
        values, dframe = (jnp.asarray(a, f1.dtype) for a in basis_np(m, n, degrees[-1]))
        nodes = _srnf_line(
            q1 / scale,
            q2 / scale,
            centred1 / scale,
            values,
            dframe,
            n_times=n_times,
            degrees=degrees,
            solver=solver,
            max_steps=jnp.asarray(max_steps, jnp.int32),
            tol=jnp.asarray(tol, f1.dtype),
        )
        ti = t[1:-1, None, None, None]
        # Q fixes no translation: carry the ends' centroids along the line.
        interior = nodes.surface * scale + (1.0 - ti) * shift1[None] + ti * shift2[None]
        residual = nodes.residual * scale
        relative = nodes.relative_residual
        steps, converged, results = nodes.num_steps, nodes.converged, nodes.result
    else:
        interior = jnp.zeros((0, 3, m, n), f1.dtype)
        residual = relative = jnp.zeros(0, f1.dtype)
        steps, converged = jnp.zeros(0, jnp.int32), jnp.zeros(0, bool)
        results = None
    zero = jnp.zeros(1, f1.dtype)
    path = jnp.concatenate([f1[None], interior, f2[None]])
    q_path = srnf_unchecked(path)[:, :, 1:-1, :-1]
    steps_q = q_path[1:] - q_path[:-1]
    result = SrnfGeodesic(
        path=path,
        residuals=jnp.concatenate([zero, residual, zero]),
        relative_residuals=jnp.concatenate([zero, relative, zero]),
        srnf_length=jnp.sum(jnp.sqrt(_srnf_norm2(steps_q))),
        srnf_distance=jnp.sqrt(_srnf_norm2((q1 - q2)[:, 1:-1, :-1])),
        node_steps=jnp.concatenate([zero_i, steps, zero_i]),
        nodes_converged=jnp.concatenate([true, converged, true]),
        converged=jnp.all(converged),
        result=first_failure(results, converged),
        num_steps=jnp.sum(steps),
    )
    _warn_unconverged("srnf_geodesic", solver, tol, result.converged, lambda: result.message)
    return result
