"""Parallel transport along a path of surfaces: Schild's ladder with exact discrete midpoints.

One rung carries a vector w_k at f_k to f_{k+1} (Ehlers, Pirani and Schild; in the
discrete geodesic calculus of Rumpf and Wirth, where a one-step path is a geodesic, exp
is f + v and log is the difference):

1. p = f_k + h w_k, the rung's far end (h = 1 / (N - 1): the rung as long as a step);
2. m = the discrete midpoint of p and f_{k+1}: the middle node of the 3-node discrete
   geodesic between them (its Euler-Lagrange equation, Newton's method);
3. q = the reflection of f_k through m: the third node of the discrete geodesic that
   starts f_k, m (one shooting step);
4. w_{k+1} = (q - f_{k+1}) / h.

Both solves are in the geodesic solver's surface basis (:mod:`_shooting`). The ladder
is first order in 1/N. With the affine average (p + f_{k+1}) / 2 as the midpoint
(``midpoint="affine"``, as in H2_SurfaceMatch) step 2 ignores the metric, and the
error does not shrink with N.

The ladder's solves live in the surface basis, so only vectors inside it keep their
length; a real vector (a scaling field, another geodesic's velocity) drifts by 10-40 %
on real shapes. The default, ``transport="galerkin"``, instead integrates the transport
equation of the metric's Levi-Civita connection along the path's straight segments,

    G_f(w', h) + Gamma_f(f', w; h) = 0 for every h in V,
    Gamma_f(u, w; h) = (D_u G(w, h) + D_w G(u, h) - D_h G(u, w)) / 2

(the Koszul formula; D_u G the derivative of G_f in f along u), with w and h in
V = span(w_0, the surface basis). Because w_0 is in V and the test h = w is allowed, the
Galerkin equation keeps G_f(w, w) exactly in continuous time, whatever w_0 is; the
integrator (fourth-order Magnus with two Gauss points per substep) leaves a drift of
order (substep)^4. What V cannot hold of the exact transport (detail outside w_0's
direction and the basis) is lost; the norm does not show it.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._checks import check_choice, check_int, check_positive, is_concrete
from .._errors import ConvergenceWarning, InputError, warn_user
from .._geometry.bases import basis_np
from .._geometry.differential import interior_frame
from .._geometry.energy import as_path
from .._geometry.grid import integrate_interior
from .._geometry.harmonics import check_degree
from .._geometry.metric import SplitMetric, metric_inner, split_bilinear
from .._geometry.units import units_of
from .._options import FROM_OPTIONS, FromOptions, ShapeOptions, settings_from
from .._results import RESULTS, first_failure, status_record, unsolved_message
from .._runtime.cache import solver_jit
from .shooting import (
    as_velocity,
    check_scheme,
    checked_frames,
    default_newton_tol,
    frames_of,
    node_solve,
)


@status_record
class TransportResult(NamedTuple):
    """A vector carried along a path by parallel transport (Galerkin or the ladder); a pytree.

    Attributes:
        vector: ``(3, m, n)`` the transported vector at the path's last surface.
        vectors: ``(N, 3, m, n)`` the vector at every node (the input first).
        norms: ``(N,)`` sqrt(G_{f_k}(w_k, w_k)); constant under exact transport.
        norm_drift: ``()`` norms[-1] / norms[0] - 1.
        residuals: ``(N - 1, 2)`` relative residuals of each rung's midpoint and reflection
            solves (the midpoint's is 0 for ``midpoint="affine"``); NaN after a failed rung.
        n_valid: ``()`` how many leading vectors are transports: N when converged; the
            rung that failed and the later ones give NaN vectors and norms.
        converged: ``()`` every Newton solve met its tolerance.
        result: ``successful``, or the failed rung's Newton result (its midpoint solve's
            if that failed, else its reflection's; ``elastic_jax.RESULTS``).
        num_steps: ``()`` Newton iterations over all rungs (the ladder), or the Magnus
            substeps integrated (Galerkin: (N - 1) x substeps).
        frame: ``(2, 3, m - 2, n - 1)`` the transported vector's differentials on the
            interior points: what :func:`shoot`'s ``frames`` takes with the path's last
            node's (for the ladder, and without ``path_frames``, the central
            differences of ``vector``).
    """

    vector: Float[Array, "3 m n"]
    vectors: Float[Array, "N 3 m n"]
    norms: Float[Array, " N"]
    norm_drift: Float[Array, ""]
    residuals: Float[Array, "K 2"]
    n_valid: Int[Array, ""]
    frame: Float[Array, "2 3 m-2 n-1"]
    converged: Bool[Array, ""]
    result: RESULTS
    num_steps: Int[Array, ""]

    def _explain(self, words: str) -> str:
        last = self.vectors.shape[-4] - 1
        return unsolved_message(self, "rung", int(self.n_valid), last, words)


def _ladder(
    metric: SplitMetric,
    w: ArrayLike,
    path: ArrayLike,
    values: ArrayLike,
    dframe: ArrayLike,
    *,
    scheme: str,
    midpoint: str,
    tol: ArrayLike,
    max_newton: int,
):
    n_times = path.shape[0]
    h = 1.0 / (n_times - 1)
    size = 3 * dframe.shape[0]
    options = {"tol": tol, "max_newton": max_newton}

    def rung(carry: tuple, nodes: tuple):
        w_k, c_mid, c_ref, alive = carry
        f_k, f_next = nodes

        def solve(_: None):
            p = f_k + h * w_k
            if midpoint == "exact":
                m, c_m, r_mid, steps_mid, result_mid = node_solve(
                    metric, scheme, p, f_next, c_mid, values, dframe, unknown="middle", **options
                )
            else:
                m, c_m = 0.5 * (p + f_next), c_mid
                r_mid, steps_mid = jnp.zeros((), w.dtype), 0
                result_mid = RESULTS.successful
            q, c_r, r_ref, steps_ref, result_ref = node_solve(
                metric, scheme, f_k, m, c_ref, values, dframe, unknown="next", **options
            )
            mid_ok = result_mid == RESULTS.successful
            result = RESULTS.where(mid_ok, result_ref, result_mid)
            steps = jnp.asarray(steps_mid + steps_ref, jnp.int32)
            return (q - f_next) / h, c_m, c_r, jnp.stack([r_mid, r_ref]), steps, result

        def skip(_: None):
            nan = jnp.asarray(jnp.nan, w.dtype)
            zero = jnp.zeros((), jnp.int32)
            return (
                jnp.full_like(w_k, nan),
                c_mid,
                c_ref,
                jnp.full((2,), nan),
                zero,
                RESULTS.successful,
            )

        # As in shooting, a rung whose solve failed ends the ladder: its vector and every
        # later one are NaN rather than built on a vector that is not a transport.
        w_next, c_m, c_r, residuals, steps, result = jax.lax.cond(alive, solve, skip, None)
        ok = alive & (result == RESULTS.successful)
        w_next = jnp.where(ok, w_next, jnp.nan)
        c_m, c_r = jnp.where(ok, c_m, c_mid), jnp.where(ok, c_r, c_ref)
        return (w_next, c_m, c_r, ok), (w_next, residuals, ok, steps, result)

    zeros = jnp.zeros(size, w.dtype)
    start = (w, zeros, zeros, jnp.asarray(True))
    _, (vectors, residuals, ok, steps, results) = jax.lax.scan(rung, start, (path[:-1], path[1:]))
    vectors = jnp.concatenate([w[None], vectors])
    norms = jnp.sqrt(jnp.clip(metric_inner(metric, path, vectors, vectors), 0.0))
    n_valid = 1 + jnp.sum(ok.astype(jnp.int32))
    return vectors, norms, residuals, n_valid, jnp.sum(steps), first_failure(results, ok)


# tol is traced (a scalar array): ladders that differ only in it share one program.
_ladder_jit = solver_jit(_ladder, static_argnames=("scheme", "midpoint", "max_newton"))


def _galerkin(
    metric: SplitMetric,
    w: ArrayLike,
    w_frame: tuple,
    path_frames: tuple,
    values: ArrayLike,
    dframe: ArrayLike,
    *,
    substeps: int,
):
    """Traceable Galerkin transport in the units of the path (module docstring), on the
    nodes' differentials: the metric sees a surface only through them, so
    ``path_frames`` (a1, a2), each ``(N, 3, m - 2, n - 1)``, is the path and
    ``w_frame`` (a1, a2) the vector (its values w are carried alongside).

    w_k = x_k[0] w_0 + sum_j x_k[j] S_j; per segment x' = K(t) x with
    K = -A^+ C, A_ij = G_f(V_i, V_j) and C_ij = Gamma_f(f', V_j; V_i), f(t) on the
    straight segment between the nodes' frames and f' = T (f_{k+1} - f_k)."""
    n_times = path_frames[0].shape[0]
    t_steps = n_times - 1
    _, m, n = w.shape
    k = values.shape[0]
    size = 1 + 3 * k
    shape = w_frame[0].shape

    def field(x: ArrayLike):
        return x[0] * w + (x[1:].reshape(3, k) @ values).reshape(3, m, n)

    def field_frame(x: ArrayLike):
        basis = frames_of(x[1:], dframe, shape)
        return tuple(x[0] * a + b for a, b in zip(w_frame, basis, strict=True))

    def inner(f: tuple, a: tuple, b: tuple):
        return integrate_interior(split_bilinear(metric, *f, *a, *b))

    def half_norm2(f: tuple, x: ArrayLike):
        v = field_frame(x)
        return 0.5 * inner(f, v, v)

    def christoffel(f: tuple, u: tuple, x: ArrayLike, y: ArrayLike):
        v, h = field_frame(x), field_frame(y)

        def along(a: tuple, b: tuple, direction: tuple):
            return jax.jvp(lambda g: inner(g, a, b), (f,), (direction,))[1]

        return 0.5 * (along(v, h, u) + along(u, h, v) - along(u, v, h))

    zero = jnp.zeros(size, w.dtype)

    def generator(f: tuple, u: tuple):
        a = jax.hessian(half_norm2, argnums=1)(f, zero)
        c = jax.jacfwd(jax.grad(christoffel, argnums=3), argnums=2)(f, u, zero, zero)
        # The pseudo-inverse: when w_0 lies in the basis' span (a field of degree <= the
        # basis'), A is singular and any solution gives the same field; solve() gave NaN.
        return -jnp.linalg.pinv(a, hermitian=True) @ c

    # Two Gauss points per substep: Magnus' fourth-order exponent
    # h (K1 + K2) / 2 + sqrt(3) h^2 [K2, K1] / 12 (h the substep in t).
    h = 1.0 / (t_steps * substeps)
    offset = 3.0**0.5 / 6.0
    local = jnp.asarray(
        [[(i + 0.5 - offset) / substeps, (i + 0.5 + offset) / substeps] for i in range(substeps)],
        w.dtype,
    )

    def segment(x: ArrayLike, ends: tuple):
        f_a, f_b = ends
        u = tuple(t_steps * (b - a) for a, b in zip(f_a, f_b, strict=True))

        def substep(x: ArrayLike, s: ArrayLike):
            # Both Gauss points in one traced generator (vmap), not two copies of it.
            at = tuple(
                a[None] + s[:, None, None, None] * (b - a)[None]
                for a, b in zip(f_a, f_b, strict=True)
            )
            k1, k2 = jax.vmap(generator, in_axes=(0, None))(at, u)
            omega = 0.5 * h * (k1 + k2) + (3.0**0.5 / 12.0) * h * h * (k2 @ k1 - k1 @ k2)
            return jax.scipy.linalg.expm(omega) @ x, None

        x, _ = jax.lax.scan(substep, x, local)
        return x, x

    start = zero.at[0].set(1.0)
    ends = (tuple(a[:-1] for a in path_frames), tuple(a[1:] for a in path_frames))
    _, xs = jax.lax.scan(segment, start, ends)
    xs = jnp.concatenate([start[None], xs])
    vectors = jax.vmap(field)(xs)
    frames = jax.vmap(field_frame)(xs)
    norms = jnp.sqrt(jnp.clip(jax.vmap(inner)(path_frames, frames, frames), 0.0))
    return vectors, jnp.stack(frames, axis=1), norms


_galerkin_jit = solver_jit(_galerkin, static_argnames=("substeps",))


def _galerkin_result(
    metric: SplitMetric,
    w: ArrayLike,
    w_frame: tuple,
    path_frames: tuple,
    values: ArrayLike,
    dframe: ArrayLike,
    substeps: int,
    scale: ArrayLike,
):
    vectors, frames, norms = _galerkin_jit(
        metric, w, w_frame, path_frames, values, dframe, substeps=substeps
    )
    vectors, frames, norms = vectors * scale, frames * scale, norms * scale
    finite = jnp.all(jnp.isfinite(vectors), axis=(1, 2, 3))
    n_valid = jnp.sum(jnp.cumprod(finite.astype(jnp.int32)))
    converged = n_valid == vectors.shape[0]
    return TransportResult(
        vector=vectors[-1],
        vectors=vectors,
        norms=norms,
        norm_drift=norms[-1] / norms[0] - 1,
        residuals=jnp.zeros((vectors.shape[0] - 1, 2), vectors.dtype),
        n_valid=n_valid,
        converged=converged,
        result=RESULTS.where(converged, RESULTS.successful, RESULTS.nonfinite),
        num_steps=jnp.asarray((vectors.shape[0] - 1) * substeps, jnp.int32),
        frame=frames[-1],
    )


def parallel_transport(
    w: Float[ArrayLike, "3 m n"],
    path: Float[ArrayLike, "N 3 m n"],
    metric: SplitMetric,
    *,
    degree: int | FromOptions = FROM_OPTIONS,
    scheme: str | FromOptions = FROM_OPTIONS,
    transport: str = "galerkin",
    substeps: int = 2,
    midpoint: str = "exact",
    tol: float | None = None,
    max_newton: int = 20,
    options: ShapeOptions | None = None,
    path_frames: Float[ArrayLike, "N 2 3 m-2 n-1"] | None = None,
    w_frame: Float[ArrayLike, "2 3 m-2 n-1"] | None = None,
) -> TransportResult:
    """Carry the tangent vector w at path[0] along the path to path[-1] (the paper's
    metric's parallel transport; module docstring).

    ``transport="galerkin"`` (default) integrates the Levi-Civita transport equation along
    the path's straight segments in V = span(w, surface basis): the norm is kept exactly
    but for the integrator's drift, for any w. ``transport="ladder"`` is Schild's ladder with
    discrete geodesic midpoints (Newton solves in the surface basis): first order in 1/N
    for vectors inside the basis; real vectors outside it drift (on cat1 -> cat2 at
    25 x 49 the scaling field by +40 %, docs/guides/limitations.md).

    Args:
        w: ``(3, m, n)`` a vector at path[0].
        path: ``(N, 3, m, n)`` N >= 2 surfaces, e.g. a geodesic's path or a shot path.
        metric: the split metric coefficients.
        degree: the surface basis (Galerkin space, or the ladder's solves); default 7.
        scheme: the energy's scheme, ``"midpoint"`` (default) or ``"forward"`` (the
            ladder's; checked for both).
        transport: ``"galerkin"`` (default) or ``"ladder"``.
        substeps: Galerkin only: Magnus substeps per segment (two metric evaluations
            each); the norm's drift falls as substeps^-4.
        midpoint: ladder only: ``"exact"`` (the discrete geodesic midpoint, default) or ``"affine"``
            (the coordinates' average; for comparison: it does not converge).
        tol, max_newton: ladder only: each Newton solve's tolerance and iteration limit
            (as in :func:`shoot`).
        options: a :class:`ShapeOptions` whose degree and scheme are the ones not given
            as keywords (None: its defaults).
        path_frames: Galerkin only: ``(N, 2, 3, m - 2, n - 1)`` the nodes' differentials
            on the interior points (``path_frames[k, j]`` the j-th column of node k).
            None (default): their central differences. A registered geodesic under
            ``differential="chain"`` is the path its solve saw only through these
            (:attr:`LogResult.path_frames`); its nodes' grid differences can nearly
            collapse cells the solve never saw.
        w_frame: Galerkin only: ``(2, 3, m - 2, n - 1)`` w's differentials (e.g.
            ``LogResult.frames[1]`` for a registered log's velocity, or
            ``path_frames[0]`` for the scaling field f - c). None (default): w's central
            differences.

    Transfer (a deformation f0 -> f1 carried to g0 and shot; docs/guides/shooting.md)::

        # Both on f0's grid (rtol=None): a resolved log lives on its finest level's.
        a = log(f0, f1, metric, modulo=m, rtol=None)
        b = log(f0, g0, metric, modulo=m, rtol=None)
        tr = parallel_transport(a.velocity, b.path, metric, path_frames=b.path_frames,
                                w_frame=a.frames[1])
        g1 = shoot(b.target, tr.vector, metric,
                   frames=jnp.stack([b.path_frames[-1], tr.frame])).endpoint

    Returns:
        :class:`TransportResult`; a ConvergenceWarning when a ladder's solve failed. The
        Galerkin transport has no iterative solve: its ``residuals`` are 0,
        ``num_steps`` its substeps, and ``n_valid`` counts the leading finite vectors.
    """
    settings = settings_from("parallel_transport", options, degree=degree, scheme=scheme)
    degree, scheme = settings["degree"], settings["scheme"]
    check_scheme(scheme)
    check_choice("transport", transport, ("galerkin", "ladder"))
    check_choice("midpoint", midpoint, ("exact", "affine"))
    substeps = check_int("substeps", substeps, 1)
    path = as_path(path)
    if path.ndim != 4:
        raise InputError(f"path must be one path (N, 3, m, n); got {path.shape}")
    w = as_velocity(w, path[0], "w")
    m, n = path.shape[-2:]
    degree = check_degree(degree, m, n)
    max_newton = check_int("max_newton", max_newton, 1)
    tol = default_newton_tol(path.dtype) if tol is None else check_positive("tol", tol)
    values, dframe = (jnp.asarray(a, path.dtype) for a in basis_np(m, n, degree))
    frames_given = path_frames is not None or w_frame is not None
    if frames_given and transport != "galerkin":
        raise InputError(
            'path_frames and w_frame are taken by transport="galerkin" only: the ladder '
            "solves on the nodes' central differences"
        )
    # In units of the path's size: vectors scale like the surfaces, norms with them.
    # Frames carry no translation, so they only scale.
    units = units_of(path[0], path[-1])
    s = units.scale
    if transport == "galerkin":
        path_frames = checked_frames(path_frames, path, "path_frames") / s
        w_frame = checked_frames(w_frame, w, "w_frame") / s
        frames = (path_frames[:, 0], path_frames[:, 1])
        w_frame = (w_frame[0], w_frame[1])
        return _galerkin_result(metric, w / s, w_frame, frames, values, dframe, substeps, s)
    vectors, norms, residuals, n_valid, num_steps, result = _ladder_jit(
        metric,
        w / s,
        units.remove(path),
        values,
        dframe,
        scheme=scheme,
        midpoint=midpoint,
        tol=jnp.asarray(tol, path.dtype),
        max_newton=max_newton,
    )
    vectors, norms = vectors * s, norms * s
    converged = n_valid == path.shape[0]
    if is_concrete(converged) and not bool(converged):
        warn_user(
            f"parallel_transport: rung {int(n_valid)} of {path.shape[0] - 1} did not solve "
            f"(Newton and the dogleg: {max_newton} iterations each, then continuation; step "
            f"still {float(jnp.nanmax(residuals)):.3g}, "
            f"tol={tol:g}); its vector and the later ones are NaN",
            ConvergenceWarning,
        )
    return TransportResult(
        vector=vectors[-1],
        vectors=vectors,
        norms=norms,
        norm_drift=norms[-1] / norms[0] - 1,
        residuals=residuals,
        n_valid=n_valid,
        converged=converged,
        result=result,
        num_steps=num_steps,
        frame=jnp.stack(interior_frame(vectors[-1])),
    )
