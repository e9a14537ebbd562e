"""Geodesics between shapes: registration modulo reparametrization and rigid motion.

Paper sections 4.2-4.3 (Algorithms 2 and 3, Remark 4), MATH.md 6, 7 and 9. f1 is
reparametrized by gamma (f1 o gamma), f2 is rotated in R^3 by R for modulo="rigid";
translations cost nothing (the metric sees only df), so both surfaces are centered for
modulo="rigid".

The solve runs in phases over one problem record: the starts (icosahedral rotations
ranked, the best refined over rotations and over the Moebius group); coarse-to-fine
registration rounds (every start on the L2 mismatch, the best on the straight line's
energy, then with the whole path) until the energy stops changing; the parametrized and
the final geodesics; and the refinement check (the result re-evaluated with halved time
steps and on a finer grid). Every phase is traceable: a single solve compiles one
program per phase (smaller programs, less compiler memory), and under a caller's jit or
vmap the whole solve is one program, vmappable over f2.
"""

from __future__ import annotations

import functools
import warnings
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Float, Int

from ._cache import exported_call, solver_jit
from ._checks import check_finite, check_grid_shape, is_concrete, real_array
from ._differential import area_element, interior_frame
from ._energy import frame_energy
from ._errors import ConvergenceWarning, InputError
from ._geodesic import (
    GeodesicResult,
    basis_np,
    check_pair,
    constant,
    default_tol,
    frames_between,
    path_from_coefficients,
    perturbed_frames,
    safe_sqrt,
    solve_path,
    solver_scaling,
    upsample_coefficients,
)
from ._grid import interior_weights, interior_weights_np, sphere_points, sphere_points_np
from ._harmonics import check_degree, harmonics_np, vector_fields_np
from ._metric import SplitMetric
from ._options import ShapeOptions, check_choice
from ._reparam import (
    jacobian_determinant_unchecked,
    moebius,
    reparametrize_unchecked,
    sample_points,
)
from ._so3 import icosahedral_np, so3_exp_unchecked
from ._solvers import RESULTS, minimize, result_message
from ._srnf import center_unchecked
from ._units import in_units

MODULI = ("diff", "rigid")
# Shrink factors tried for a reparametrization step, largest first; 0 keeps gamma.
_STEP_SCALES = (1.0, 0.5, 0.25, 0.125, 0.0625, 0.0)
# BFGS steps spent on each of the 60 icosahedral starting rotations before ranking them.
_SEARCH_STEPS = 12


class Refinement(NamedTuple):
    """The distance of a result re-evaluated at a finer discretization (MATH.md 9).

    Nothing is optimized again: the registered ends and the path are carried over, so a
    discretization the solve exploited shows as a jump here.

    Attributes:
        distance_time: ``()`` the same path with every time step halved (2N - 1 time
            points, frames linearly interpolated).
        distance_grid: ``()`` the same path on the (2m - 1) x (2n - 1) grid: gamma and
            f2 interpolated there, f1 o gamma read from f1's own grid, the path's
            spherical-harmonic perturbation evaluated on the finer grid.
        relative_change: ``()`` max(|distance_time - d|, |distance_grid - d|) / d.
    """

    distance_time: Float[Array, ""]
    distance_grid: Float[Array, ""]
    relative_change: Float[Array, ""]


class ShapeGeodesicResult(NamedTuple):
    """A geodesic between shapes; a pytree, batched by ``jax.vmap``.

    Attributes:
        path: ``(N, 3, m, n)`` from f1 o gamma to R f2 (centered surfaces when modulo="rigid").
        distance: ``()`` sqrt(energy), the shape distance.
        energy: ``()`` the energy of ``path`` (the options' scheme).
        parametrized_distance: ``()`` the geodesic distance without registration (same scheme).
        f1_registered: ``(3, m, n)`` f1 o gamma (= path[0]).
        gamma: ``(3, m, n)`` the reparametrization, a point of S^2 per grid point; its
            Jacobian determinant is positive at every grid point.
        rotation: ``(3, 3)`` R applied to f2 (the identity for modulo="diff").
        coefficients: ``(N - 2, L)`` the path's perturbation (as in :class:`GeodesicResult`).
        energy_history: ``(outer_steps + 2,)`` the parametrized geodesic's energy, the
            straight line's after the initialization, then the energy after each
            registration round (NaN for rounds not taken).
        rounds: ``()`` registration rounds taken.
        num_steps: ``()`` solver steps, all solves together.
        converged: ``()`` the final geodesic solve converged (a minimum, not a saddle, when
            saddle_checks >= 1) and the last round changed the
            energy by at most outer_tol (E + outer_tol E_0) (always true when outer_steps=0
            asks for no rounds) or was refused, and that round's step did not have to shrink
            to stay resolved.
        result: an ``elastic_jax.RESULTS`` code: the final solve's failure if it failed, else
            ``resolution_limited`` when the last round's step had to shrink until the grid
            resolved it (J > 0, area floor) and then lowered the energy little or not at
            all, else ``nonlinear_max_steps_reached`` when the rounds ran out, else successful.
        grad_norm: ``()`` 2-norm of the gradient of the joint objective (path in whitened
            coefficients and the next Diff step, energy / its scale) at the result.
        min_curvature: ``()`` the final geodesic solve's estimate of the smallest Hessian
            eigenvalue of its scaled objective (:class:`GeodesicResult`): positive at a
            minimum of the path for this registration.
        refinement: :class:`Refinement` (NaN when the options turn it off).
    """

    path: Float[Array, "N 3 m n"]
    distance: Float[Array, ""]
    energy: Float[Array, ""]
    parametrized_distance: Float[Array, ""]
    f1_registered: Float[Array, "3 m n"]
    gamma: Float[Array, "3 m n"]
    rotation: Float[Array, "3 3"]
    coefficients: Float[Array, "K L"]
    energy_history: Float[Array, " H"]
    rounds: Int[Array, ""]
    num_steps: Int[Array, ""]
    converged: Array
    result: RESULTS
    grad_norm: Float[Array, ""]
    min_curvature: Float[Array, ""]
    refinement: Refinement

    @property
    def message(self) -> str:
        """How the solve ended, in words; '' when the last round met outer_tol.

        A converged result whose last round was refused (its full step, resolved by the
        grid, raised the energy: the composed reparametrization's interpolation cost more
        than the step gained) says so.
        """
        message = result_message(self.result)
        if not message and not bool(self.converged):
            message = (
                "the final geodesic ended at a saddle point (smallest Hessian eigenvalue "
                f"{float(self.min_curvature):.3g}); raise saddle_checks"
            )
        history, k = np.asarray(self.energy_history), int(self.rounds)
        # After at least one accepted round: a first round refused at once is a match at
        # interpolation noise (identical inputs), not a registration held back.
        if not message and k >= 2 and history[k + 1] == history[k] > 0:
            change = 100.0 * (history[k - 1] - history[k]) / history[k]
            message = (
                "the rounds ended where the next round's Diff step raised the energy (the "
                f"last accepted round lowered it by {change:.2g} %); refinement shows how a "
                "finer grid sees the result"
            )
        return message


@functools.cache
def _field_scale_np(m: int, n: int, degree: int) -> np.ndarray:
    """1 / sqrt(l(l+1)) per vector field: differentials grow like l; this evens the Hessian."""
    ls = harmonics_np(m, n, degree)[4][1:]
    return np.repeat(1.0 / np.sqrt(ls * (ls + 1.0)), 2)


class _Bases(NamedTuple):
    """The arrays a solve needs besides the surfaces (precomputed per grid and degree)."""

    values: Array  # (K, m n) path harmonics
    dframe: Array  # (K, 2 P) their differentials
    fields: Array  # (Lbar, 3, m, n) Diff-step vector fields
    field_scale: Array  # (Lbar,)
    ico: Array  # (60, 3, 3)
    fine_points: Array  # (3, 2m - 1, 2n - 1) the refinement grid's points
    fine_dframe: Array  # (K, 2 P') the path harmonics' differentials there
    area_floor: Array  # () least grid area a reparametrization may keep (_resolution_np)
    max_boost: Array  # () largest |a| of a Moebius map the grid resolves


def _ball(b: Array, radius: Array) -> Array:
    """b -> radius tanh(|b|) b / |b|: R^3 onto the open ball of that radius, smooth at 0."""
    t2 = jnp.sum(b * b)
    small = t2 < np.sqrt(np.finfo(b.dtype).eps)
    # Safe where: tanh(t)/t's series below sqrt(eps), so no 0/0 reaches the gradient.
    t = jnp.sqrt(jnp.where(small, 1.0, t2))
    return radius * b * jnp.where(small, 1.0 - t2 / 3.0, jnp.tanh(t) / t)


# A reparametrization is resolved by the grid when the unit sphere it reparametrizes keeps
# its discrete area to within this many times the area the grid already loses for the
# identity (0.71 % at 25 x 49): a Moebius map with |a| = 0.6 needs 2.6-3.2 times, and the
# bounded boost search below must reach it well inside its bound.
_RESOLUTION_FACTOR = 5.0
# BFGS steps per round of the L2 matching of every start.
_MATCH_STEPS = 30
# Shrink factors tried for an initial Moebius boost that the grid does not resolve.
_BOOST_SCALES = (1.0, 0.95, 0.9, 0.85, 0.8, 0.7, 0.6, 0.5, 0.25, 0.0)


def _grid_area_np(gamma: np.ndarray) -> float:
    """Discrete area of the unit sphere reparametrized by gamma: the integral of its J."""
    a1, a2 = interior_frame(gamma)
    m, n = gamma.shape[-2:]
    signed = np.sum(np.cross(a2, a1, axis=0) * gamma[:, 1:-1, :-1], axis=0)
    return float(np.sum(signed * interior_weights_np(m, n)))


@functools.cache
def _resolution_np(m: int, n: int) -> tuple[float, float]:
    """(area floor, largest resolved Moebius |a|) of the m x n grid.

    Where a reparametrization stretches a region beyond what the grid resolves, finite
    differences of f o gamma lose area (chords for arcs), and a registration that wants a
    smaller start surface gains by it: the radius-3 sphere registered to a unit sphere
    came out at 40 % of the distance before this floor. A gamma may keep no less than
    (1 - 5 eps_id) of the identity's discrete area, eps_id = 1 - A_grid(e1) / (4 pi); the
    boost |a| of the initial Moebius search is bounded to where a Moebius map keeps it.
    """
    e1 = sphere_points_np(m, n)
    area_id = _grid_area_np(e1)
    floor = area_id * (1.0 - _RESOLUTION_FACTOR * (1.0 - area_id / (4.0 * np.pi)))
    # A direction that no grid symmetry favours; moebius() written out in numpy, because
    # this runs while callers (karcher_mean) trace their jitted batches.
    direction = np.array([0.36, 0.48, 0.8]) / np.linalg.norm([0.36, 0.48, 0.8])
    low, high = 0.0, 0.99
    for _ in range(30):
        mid = 0.5 * (low + high)
        a = mid * direction[:, None, None]
        d = e1 - a
        gamma = (1.0 - mid * mid) * d / np.sum(d * d, axis=0) - a
        low, high = (mid, high) if _grid_area_np(gamma) >= floor else (low, mid)
    return floor, low


def _compose(gamma, step, interpolation):
    """gamma o step: read gamma's coordinates at the points of step, back onto the sphere."""
    g = reparametrize_unchecked(gamma, step, method=interpolation)
    return g / jnp.linalg.norm(g, axis=-3, keepdims=True)


def _step_field(y, fields, scale, e1):
    """Proj(Id + sum_k y_k s_k v_k) (MATH.md 6), s_k = 1 / sqrt(l(l+1))."""
    w = e1 + jnp.einsum("k,kimn->imn", y * scale, fields)
    return w / jnp.linalg.norm(w, axis=-3, keepdims=True)


def _rotate(r, f):
    return jnp.einsum("ij,j...->i...", r, f)


def _kabsch(source, target):
    """The rotation R minimizing the area-weighted sum |R source - target|^2 (centered)."""
    m, n = target.shape[-2:]
    weights = area_element(*interior_frame(target)) * interior_weights(m, n, target.dtype)
    x, y = source[:, 1:-1, :-1], target[:, 1:-1, :-1]
    total = jnp.sum(weights)
    x = x - jnp.sum(x * weights[None], axis=(1, 2), keepdims=True) / total
    y = y - jnp.sum(y * weights[None], axis=(1, 2), keepdims=True) / total
    h = jnp.einsum("imn,jmn,mn->ij", x, y, weights)
    u, _, vt = jnp.linalg.svd(h)
    d = jnp.sign(jnp.linalg.det(vt.T @ u.T))
    return vt.T @ jnp.diag(jnp.asarray([1.0, 1.0, 1.0], h.dtype).at[2].set(d)) @ u.T


def _resolved(gammas, floor):
    """Whether each of ``gammas (..., 3, m, n)`` is a diffeomorphism the grid resolves.

    J > 0 at every grid point, and the discrete area of the reparametrized unit sphere
    (the integral of J) at least ``floor`` (:func:`_resolution_np`).
    """
    jac = jacobian_determinant_unchecked(gammas)
    m, n = gammas.shape[-2:]
    area = jnp.einsum("...ij,ij->...", jac[..., 1:-1, :-1], interior_weights(m, n, jac.dtype))
    return (jnp.min(jac, axis=(-2, -1)) > 0) & (area >= floor)


def _safe_update(prob, cfg, gamma, y):
    """The largest shrink of the step whose composition with gamma stays resolved, and
    whether the step had to shrink.

    The shrinks are tried one after the other (a loop, not one candidate per shrink in
    the program): the first usually passes, and each candidate is a bicubic composition
    whose kernels would otherwise be compiled six times over at each of three call sites.
    """
    bases = prob.bases
    scales = jnp.asarray(_STEP_SCALES, y.dtype)
    last = len(_STEP_SCALES) - 1

    def candidate(i):
        step = _step_field(scales[i] * y, bases.fields, bases.field_scale, prob.e1)
        return _compose(gamma, step, cfg.interpolation)

    def usable(i, g):
        # The last shrink (scale 0) is gamma itself, which is valid.
        return _resolved(g, bases.area_floor) | (i == last)

    def next_shrink(carry):
        i, _, _ = carry
        g = candidate(i + 1)
        return i + 1, g, usable(i + 1, g)

    first = candidate(0)
    start = (jnp.zeros((), jnp.int32), first, usable(0, first))
    index, chosen, _ = jax.lax.while_loop(lambda c: ~c[2], next_shrink, start)
    return chosen, index > 0


class _Problem(NamedTuple):
    """The traced data of one solve: metric, surfaces (centered when rigid), bases."""

    metric: SplitMetric
    f1: Array
    f2: Array
    e1: Array
    bases: _Bases


class _State(NamedTuple):
    gamma: Array
    rotation: Array
    coefficients: Array
    energy: Array
    steps: Array
    shrunk: Array  # () bool: the (last) round's step had to shrink to stay resolved


def _registered(prob, cfg, gamma):
    return reparametrize_unchecked(prob.f1, gamma, method=cfg.interpolation)


def _stepped_gamma(prob, cfg, gamma, x):
    """gamma o Proj(Id + sum x_k v_k): the reparametrization after one more Diff step."""
    step = _step_field(x, prob.bases.fields, prob.bases.field_scale, prob.e1)
    return _compose(gamma, step, cfg.interpolation)


@functools.cache
def _chord_correction_np(m: int, n: int) -> tuple[float, float]:
    """h / sin(h) per grid direction: central differences of the identity (and of any
    rotation) are chords of great circles, shorter than its tangents by sin(h) / h."""
    dtheta, dphi = 2.0 * np.pi / (n - 1), np.pi / (m - 1)
    return dtheta / np.sin(dtheta), dphi / np.sin(dphi)


def _chain_frame(f, gamma, interpolation):
    """The differential of f o gamma on the interior points by the chain rule (MATH.md 2's
    frame): (df at gamma) applied to gamma's frame.

    df is the exact derivative of f's interpolant (at grid points, for bicubic, the
    central difference); gamma's frame is its central differences with the chords of a
    rotation made exact. Central differences of f o gamma itself are chords across
    gamma(p +- h), which on a real shape cut corners wherever gamma stretches: they lower
    the energy, and a registration minimizing it learns to under-sample f.
    """
    m, n = gamma.shape[-2:]
    g1, g2 = interior_frame(gamma)
    c1, c2 = _chord_correction_np(m, n)
    points = gamma[:, 1:-1, :-1]

    def along(direction):
        return jax.jvp(lambda p: sample_points(f, p, interpolation), (points,), (direction,))[1]

    return along(g1 * c1), along(g2 * c2)


def _frame_of(f, gamma, cfg):
    """The differential of f o gamma on gamma's interior points (cfg.differential)."""
    if cfg.differential == "grid":
        return interior_frame(reparametrize_unchecked(f, gamma, method=cfg.interpolation))
    return _chain_frame(f, gamma, cfg.interpolation)


def _registered_frame(prob, cfg, gamma):
    """The differential of f1 o gamma (interior points)."""
    if cfg.differential == "grid":
        return interior_frame(_registered(prob, cfg, gamma))
    return _chain_frame(prob.f1, gamma, cfg.interpolation)


def _end_frame(prob, cfg, rotation):
    """The differential of R f2 (interior points), taken as f1 o gamma's at the identity:
    identical inputs then have identical frames."""
    if cfg.differential == "grid":
        frame = interior_frame(prob.f2)
    else:
        frame = _chain_frame(prob.f2, prob.e1, cfg.interpolation)
    return tuple(_rotate(rotation, a) for a in frame)


def _identity_frames(prob, cfg):
    """(f1's frame, f2's frame): the straight line without registration."""
    if cfg.differential == "grid":  # the surfaces themselves, not read back at their points
        return interior_frame(prob.f1), interior_frame(prob.f2)
    eye = jnp.eye(3, dtype=prob.f1.dtype)
    return _registered_frame(prob, cfg, prob.e1), _end_frame(prob, cfg, eye)


def _geodesic_options(cfg):
    return {
        "n_times": cfg.n_times,
        "solver": cfg.solver,
        "max_steps": cfg.max_steps,
        "tol": cfg.tol,
        "scheme": cfg.scheme,
    }


def _geodesic_at(prob, cfg, gamma, rotation, init):
    """The parametrized geodesic from f1 o gamma to R f2, warm-started at ``init``."""
    return solve_path(
        prob.metric,
        _registered(prob, cfg, gamma),
        _rotate(rotation, prob.f2),
        init,
        prob.bases.values,
        prob.bases.dframe,
        **_geodesic_options(cfg),
        frames=(_registered_frame(prob, cfg, gamma), _end_frame(prob, cfg, rotation)),
    )


def _straight_energy(prob, cfg, start_frame, end_frame):
    """The straight line's energy between two ends given by their frames."""
    # Ranking and refining straight lines needs no time resolution: 3 time points
    # (4.5x cheaper than N = 10) order the candidates the same way.
    frames = frames_between(start_frame, end_frame, 3)
    return frame_energy(prob.metric, *frames, cfg.scheme)


def _l2_mismatch(start, end):
    """int |start - end|^2 dsigma over the round sphere, for ``(3, m, n)`` surfaces."""
    m, n = start.shape[-2:]
    gap = jnp.sum((start - end)[:, 1:-1, :-1] ** 2, axis=0)
    return jnp.sum(gap * interior_weights(m, n, start.dtype))


def _distinct_best(values, points, k, separation):
    """Indices of k low ``values (S,)`` whose ``points (S, 3, P)`` lie apart.

    Greedy: the lowest value first, then the lowest whose mean distance on the sphere to
    every chosen one exceeds ``separation``; when fewer than k are that far apart, the
    remaining picks are the lowest not yet taken.
    """
    distances = jnp.mean(jnp.linalg.norm(points[:, None] - points[None], axis=-2), axis=-1)

    def pick(carry, _):
        taken, far = carry
        free = jnp.where(taken, jnp.inf, values)
        apart = jnp.argmin(jnp.where(far, free, jnp.inf))
        i = jnp.where(jnp.any(far & ~taken), apart, jnp.argmin(free)).astype(jnp.int32)
        return (taken.at[i].set(True), far & (distances[i] > separation)), i

    start = (jnp.zeros(values.shape, bool), jnp.isfinite(values))
    return jax.lax.scan(pick, start, None, length=k)[1]


# Mean distance on the unit sphere (about radians) below which two refined starts are
# taken for one: the three best of the 60 often end in one basin, and three copies of it
# are one start.
_DISTINCT_STARTS = 0.1


def _start_map(points, max_boost, q, vb):
    """The start (q, vb) of the search applied to ``points (3, ...)`` of the sphere:
    q exp(hat v) phi_b, vb = (v, b), the boost b bounded to ``max_boost`` (_ball)."""
    return _rotate(q @ so3_exp_unchecked(vb[:3]), moebius(points, _ball(vb[3:], max_boost)))


def _aligned(prob, cfg, rigid, gamma):
    """f1 o gamma and R^3's Procrustes rotation of f2 onto it (the identity unless rigid)."""
    start = _registered(prob, cfg, gamma)
    r = _kabsch(prob.f2, start) if rigid else jnp.eye(3, dtype=start.dtype)
    return start, r


def _start(prob, cfg, rigid, q, vb):
    """A searched start as (gamma, R): its boost shrunk until the grid resolves gamma.

    The boost is bounded to what the grid resolves for a generic direction; shrink it
    where this direction needs less (a pure rotation, the last scale, always does).
    """
    boosts = jnp.asarray(_BOOST_SCALES, vb.dtype)[:, None] * vb[None, 3:]
    maps = jax.vmap(lambda b: _start_map(prob.e1, prob.bases.max_boost, q, vb.at[3:].set(b)))
    ok = _resolved(maps(boosts), prob.bases.area_floor).at[-1].set(True)
    gamma = _start_map(prob.e1, prob.bases.max_boost, q, vb.at[3:].set(boosts[jnp.argmax(ok)]))
    return gamma, _aligned(prob, cfg, rigid, gamma)[1]


def _initialize_moebius(prob, cfg, rigid):
    """The starts of the registration for init="moebius" (docs/registration.md).

    Returns (gammas ``(S, 3, m, n)``, rotations ``(S, 3, 3)``, solver steps). Each of the
    60 icosahedral rotations starts a short BFGS over the Moebius group of the parameter
    sphere (rotations and conformal boosts, six parameters); when rigid, R^3's rotation
    is the Procrustes optimum for each correspondence (variable projection). They are ranked by
    the L2 mismatch int |f1 o gamma - R f2|^2 dsigma, and the best ``init_candidates``
    that lie apart (``_distinct_best``) are refined to the tolerance: these are the
    starts.

    The criterion is the L2 mismatch, not the elastic energy: the straight line's energy
    between real shapes is rough far from the right correspondence, and it ranked every
    start of cat1 against itself under a rotation and a Moebius map (|a| = 0.3, 50 x 99)
    about half a turn wrong (energy 5.2-6.0, mean error of gamma 1.5-2.1 rad); the L2
    search from the same 60 rotations finds the map (distance 3e-4 after the rounds,
    against 1.78). Searching the boosts from every rotation, not only from the best
    three, is what reaches it: the identity's rotation search alone ranked below a
    flipped start (L2 0.61 before refinement; 0.38 for the flipped basin).
    """
    dtype = prob.f1.dtype

    reference = _l2_mismatch(prob.f1, prob.f2)
    reference = jnp.where(reference > 0, reference, 1.0)

    def objective(q, vb):
        start, r = _aligned(prob, cfg, rigid, _start_map(prob.e1, prob.bases.max_boost, q, vb))
        return _l2_mismatch(start, _rotate(r, prob.f2)) / reference

    # The short search from every icosahedral rotation and then the refinement of the
    # chosen init_candidates are jobs of one scan, and so one compiled solve (its
    # objective and gradient are the bulk of the program); the step limit is traced.
    ico, k = prob.bases.ico, cfg.init_candidates
    n_ico = ico.shape[0]
    # Where each searched start maps a few points of the sphere: the icosahedron's 12
    # vertices and 20 face centres under the rotation only would miss the boost, so the
    # grid's own points are used (every 4th row and column).
    probe = prob.e1[:, ::4, ::4].reshape(3, -1)

    def job(searched, j):
        values, params = searched
        searching = j < n_ico
        # The distinct best, once the search is done (the rows are then final).
        points = jax.vmap(lambda q, vb: _start_map(probe, prob.bases.max_boost, q, vb))(ico, params)
        chosen = _distinct_best(values, points, k, _DISTINCT_STARTS)
        i = jnp.where(searching, j, chosen[(j - n_ico) % k])
        u0 = jnp.where(searching, jnp.zeros(6, dtype), params[i])
        cap = jnp.where(searching, _SEARCH_STEPS, cfg.max_steps)
        found = minimize(
            lambda u: objective(ico[i], u),
            u0,
            solver=cfg.solver,
            max_steps=max(cfg.max_steps, _SEARCH_STEPS),
            tol=cfg.tol,
            step_cap=cap,
        )
        value = jnp.where(jnp.isfinite(found.value), found.value, jnp.inf)
        slot = jnp.minimum(j, n_ico - 1)
        values = jnp.where(searching, values.at[slot].set(value), values)
        params = jnp.where(searching, params.at[slot].set(found.x), params)
        return (values, params), (i, found.x, found.num_steps)

    searched = (jnp.full((n_ico,), jnp.inf, dtype), jnp.zeros((n_ico, 6), dtype))
    jobs = jnp.arange(n_ico + k, dtype=jnp.int32)
    _, (index, us, job_steps) = jax.lax.scan(job, searched, jobs)
    qs, vbs = ico[index[n_ico:]], us[n_ico:]

    gammas, rotations = jax.vmap(lambda q, vb: _start(prob, cfg, rigid, q, vb))(qs, vbs)
    return gammas, rotations, jnp.sum(job_steps).astype(jnp.int32)


def _initialize_energy(prob, cfg, rigid):
    """The starts for init="energy" and "icosahedral": Remark 4, widened to the Moebius group.

    Returns (gammas ``(S, 3, m, n)``, rotations ``(S, 3, 3)``, solver steps). The 60
    icosahedral rotations as reparametrizations, each refined by a short BFGS over
    rotations of the parameter sphere, are ranked by straight-line energy; when rigid,
    R^3's rotation is the Procrustes optimum for each correspondence (variable
    projection). The best ``init_candidates`` are refined over rotations to the
    tolerance and, with init="energy", also over rotations and Moebius maps together
    (six parameters), which finds large conformal reparametrizations that no rotation
    approaches. All of them are starts: which start ends best shows only after the
    straight-line rounds (cat1 against cat2 at 25 x 49: 0.84 from the best rotation,
    1.35 from the best Moebius map; cat1 against horse0 the other way round; measured
    before the pole derivative fix of 2026-11-23).
    """
    dtype = prob.f1.dtype

    reference = _straight_energy(prob, cfg, *_identity_frames(prob, cfg))
    reference = jnp.where(reference > 0, reference, 1.0)

    def objective(q, vb):
        gamma = _start_map(prob.e1, prob.bases.max_boost, q, vb)
        _, r = _aligned(prob, cfg, rigid, gamma)
        start, end = _registered_frame(prob, cfg, gamma), _end_frame(prob, cfg, r)
        return _straight_energy(prob, cfg, start, end) / reference

    def refine(q, vb0, max_steps, free, cap=None):
        # free = 3: rotations only (the boost stays 0); 6: the Moebius group.
        def restricted(u):
            return objective(q, vb0.at[:free].set(u) if free == 3 else u)

        found = minimize(
            restricted,
            vb0[:free],
            solver=cfg.solver,
            max_steps=max_steps,
            tol=cfg.tol,
            step_cap=cap,
        )
        vb = vb0.at[:free].set(found.x) if free == 3 else found.x
        value = found.value  # objective(q, vb), as the solver evaluated it
        # A straight line through a fold has an infinite (midpoint) or NaN energy: last.
        return jnp.where(jnp.isfinite(value), value, jnp.inf), vb, found.num_steps

    # The short search from every icosahedral rotation and then the refinement of the
    # best init_candidates over rotations are jobs of one scan, and so one compiled solve
    # (its objective and gradient are the bulk of the program); the step limit is traced.
    ico, k = prob.bases.ico, cfg.init_candidates
    n_ico = ico.shape[0]

    def job(searched, j):
        energies, params = searched
        searching = j < n_ico
        top = jax.lax.top_k(-energies, k)[1].astype(jnp.int32)  # once the search is done
        i = jnp.where(searching, j, top[(j - n_ico) % k])
        start = jnp.where(searching, jnp.zeros(6, dtype), params[i])
        cap = jnp.where(searching, _SEARCH_STEPS, cfg.max_steps)
        energy, vb, steps = refine(ico[i], start, max(cfg.max_steps, _SEARCH_STEPS), 3, cap)
        slot = jnp.minimum(j, n_ico - 1)
        energies = jnp.where(searching, energies.at[slot].set(energy), energies)
        params = jnp.where(searching, params.at[slot].set(vb), params)
        return (energies, params), (i, vb, steps)

    searched = (jnp.full((n_ico,), jnp.inf, dtype), jnp.zeros((n_ico, 6), dtype))
    jobs = jnp.arange(n_ico + k, dtype=jnp.int32)
    (_, params), (index, vbs, job_steps) = jax.lax.scan(job, searched, jobs)
    top, vbs = index[n_ico:], vbs[n_ico:]
    qs = ico[top]
    steps = jnp.sum(job_steps)
    if cfg.init == "energy":
        # Six parameters where the rotations have three: a solve of its own.
        _, boosted, more = jax.lax.map(lambda i: refine(ico[i], params[i], cfg.max_steps, 6), top)
        qs, vbs = jnp.concatenate([qs, qs]), jnp.concatenate([vbs, boosted])
        steps = steps + jnp.sum(more)

    gammas, rotations = jax.vmap(lambda q, vb: _start(prob, cfg, rigid, q, vb))(qs, vbs)
    return gammas, rotations, steps.astype(jnp.int32)


def _initialize(prob, cfg, rigid):
    """The starts of the registration: (gammas ``(S, 3, m, n)``, rotations ``(S, 3, 3)``,
    solver steps), by ``cfg.init`` (:class:`ShapeOptions`)."""
    if cfg.init == "none":
        eye = jnp.eye(3, dtype=prob.f1.dtype)
        return prob.e1[None], eye[None], jnp.zeros((), jnp.int32)
    if cfg.init == "moebius":
        return _initialize_moebius(prob, cfg, rigid)
    return _initialize_energy(prob, cfg, rigid)


def _registration_variables(prob, y, rigid):
    """Split the registration variables into the Diff step's x and R^3's rotation step."""
    n_fields = prob.bases.fields.shape[0]
    x = y[:n_fields]
    r_step = so3_exp_unchecked(y[n_fields:]) if rigid else jnp.eye(3, dtype=y.dtype)
    return x, r_step


def _joint_objective(prob, cfg, rigid, gamma, rotation, scaling):
    """Energy / scale as a function of (whitened path coefficients z, registration step y)."""
    end_frame = _end_frame(prob, cfg, rotation)

    def objective(variables):
        z, y = variables
        x, r_step = _registration_variables(prob, y, rigid)
        start = _registered_frame(prob, cfg, _stepped_gamma(prob, cfg, gamma, x))
        end = [_rotate(r_step, a) for a in end_frame]
        straight = frames_between(start, end, cfg.n_times)
        frames = perturbed_frames(straight, scaling.coefficients(z), prob.bases.dframe)
        return frame_energy(prob.metric, *frames, cfg.scheme) / scaling.energy_scale

    return objective


def _scaling_at(prob, cfg, gamma, rotation):
    return solver_scaling(
        prob.metric,
        _registered(prob, cfg, gamma),
        _rotate(rotation, prob.f2),
        prob.bases.dframe,
        cfg.n_times,
        cfg.scheme,
        (_registered_frame(prob, cfg, gamma), _end_frame(prob, cfg, rotation)),
    )


def _zero_registration(prob, rigid, dtype):
    return jnp.zeros(prob.bases.fields.shape[0] + (3 if rigid else 0), dtype)


def _path_energy_at(prob, cfg, gamma, rotation, coefficients):
    """Energy of the straight line from f1 o gamma to R f2 plus the perturbation."""
    start, end = _registered_frame(prob, cfg, gamma), _end_frame(prob, cfg, rotation)
    straight = frames_between(start, end, cfg.n_times)
    frames = perturbed_frames(straight, coefficients, prob.bases.dframe)
    return frame_energy(prob.metric, *frames, cfg.scheme)


def _matching_criterion(prob, cfg, weight):
    """weight * L2 position mismatch + (1 - weight) * straight-line energy (3 time points).

    The L2 mismatch int |f1 o gamma - R f2|^2 dsigma has no derivatives of the surfaces
    in it, so its landscape over gamma is far smoother than the elastic energy's: from a
    wrong basin it finds the right correspondence where the energy cannot (cat1 against
    itself under two large Diff steps: the energy stalled at 0.63, the L2 rounds found the
    map to 0.017 rad). It only initializes: the rounds that follow minimize the energy.
    """

    def criterion(gamma, rotation):
        l2 = _l2_mismatch(_registered(prob, cfg, gamma), _rotate(rotation, prob.f2))
        frames = _registered_frame(prob, cfg, gamma), _end_frame(prob, cfg, rotation)
        return weight * l2 + (1.0 - weight) * _straight_energy(prob, cfg, *frames)

    return criterion


def _straight_round(prob, cfg, rigid, weight, cap, state: _State) -> _State:
    """One registration round on the matching criterion from f1 o gamma to R f2.

    Coarse in time before the rounds with the whole path: the straight line cannot bend
    around a wrong correspondence, so its energy keeps a clear pull towards the right
    one. Measured on a bumpy surface against itself under two large degree-3 Diff steps
    (J from 0.13 to 3.0): joint rounds straight from the Moebius start stalled at a
    distance of 0.17; these rounds first brought it to 0.05. ``weight`` and the BFGS's
    step limit ``cap`` are traced (see _coarse_registration).
    """
    dtype = state.energy.dtype
    criterion = _matching_criterion(prob, cfg, weight)
    reference = jnp.maximum(state.energy, jnp.finfo(dtype).tiny)

    def objective(y):
        x, r_step = _registration_variables(prob, y, rigid)
        gamma = _stepped_gamma(prob, cfg, state.gamma, x)
        return criterion(gamma, r_step @ state.rotation) / reference

    y0 = _zero_registration(prob, rigid, dtype)
    found = minimize(
        objective,
        y0,
        solver=cfg.solver,
        max_steps=max(cfg.max_steps, _MATCH_STEPS),
        tol=cfg.tol,
        step_cap=cap,
    )
    x, r_step = _registration_variables(prob, found.x, rigid)
    gamma, shrunk = _safe_update(prob, cfg, state.gamma, x)
    rotation = r_step @ state.rotation
    energy = criterion(gamma, rotation)
    steps = state.steps + found.num_steps
    return _State(gamma, rotation, state.coefficients, energy, steps, shrunk)


def _iterate(round_fn, state: _State, max_rounds: int, small_change, history=None):
    """Rounds until one changes the energy little, or max_rounds; never a rising energy.

    Returns (state, history, rounds taken, whether the last round met small_change or
    was refused); ``state.shrunk`` says whether the last round's step had to shrink.
    ``history`` (optional) gets each round's energy at index 2 + round.
    """
    if history is None:
        history = jnp.zeros((max_rounds + 2,), state.energy.dtype)

    def keep_going(carry):
        _, _, k, done = carry
        return (k < max_rounds) & ~done

    def body(carry):
        state, history, k, _ = carry
        new = round_fn(state)
        # A round whose step had to shrink can end higher: keep the better registration
        # (no round may raise the energy), and stop there.
        better = new.energy <= state.energy
        kept = jax.tree_util.tree_map(lambda a, b: jnp.where(better, a, b), new, state)
        # The last round's shrink is kept whether or not the round was: rounds that end
        # shrunk ended at the edge of what the grid resolves, not at a minimum.
        kept = kept._replace(steps=new.steps, shrunk=new.shrunk)
        done = ~better | small_change(state.energy, kept.energy)
        return kept, history.at[k + 2].set(kept.energy), k + 1, done

    start = (state, history, jnp.zeros((), jnp.int32), jnp.asarray(max_rounds == 0))
    return jax.lax.while_loop(keep_going, body, start)


def _round(prob, cfg, rigid, state: _State) -> _State:
    """One registration round.

    joint (Algorithm 2): BFGS over the path coefficients and the next Diff step (and a
    rotation of f2) together; the path is not solved again for a shrunk step (the next
    round or the final solve does it). coordinate: BFGS over the Diff step (and
    rotation) with the path's perturbation held, then the geodesic. The paper's
    Algorithm 3 holds the path's interior frames instead, which pins the start to its
    neighbour: it moved the energy by 7-8 % per round on the cats where this reaches
    1 % of its limit in 4 rounds.
    """
    dtype = state.energy.dtype
    scaling = _scaling_at(prob, cfg, state.gamma, state.rotation)
    objective = _joint_objective(prob, cfg, rigid, state.gamma, state.rotation, scaling)
    y0 = _zero_registration(prob, rigid, dtype)
    z0 = scaling.whitened(state.coefficients)
    options = {"solver": cfg.solver, "max_steps": cfg.max_steps, "tol": cfg.tol}
    if cfg.method == "joint":
        found = minimize(objective, (z0, y0), **options)
        z, y = found.x
    else:
        found = minimize(lambda y: objective((z0, y)), y0, **options)
        z, y = z0, found.x
    x, r_step = _registration_variables(prob, y, rigid)
    gamma, shrunk = _safe_update(prob, cfg, state.gamma, x)
    rotation = r_step @ state.rotation
    coefficients = scaling.coefficients(z)
    steps = state.steps + found.num_steps
    if cfg.method == "joint":
        energy = _path_energy_at(prob, cfg, gamma, rotation, coefficients)
    else:
        res = _geodesic_at(prob, cfg, gamma, rotation, coefficients)
        coefficients, energy, steps = res.coefficients, res.energy, steps + res.num_steps
    return _State(gamma, rotation, coefficients, energy, steps, shrunk)


def _refinement(prob, cfg, gamma, rotation, coefficients, energy) -> Refinement:
    """The result re-evaluated with halved time steps and on the (2m - 1) x (2n - 1) grid."""
    metric, bases, degree = prob.metric, prob.bases, cfg.degree
    start, end = _registered_frame(prob, cfg, gamma), _end_frame(prob, cfg, rotation)
    n_fine = 2 * cfg.n_times - 1
    halved = upsample_coefficients(coefficients, degree, degree, n_fine)
    straight = frames_between(start, end, n_fine)
    frames = perturbed_frames(straight, halved, bases.dframe)
    time_energy = frame_energy(metric, *frames, cfg.scheme)

    fine_gamma = _compose(gamma, bases.fine_points, cfg.interpolation)
    fine_start = _frame_of(prob.f1, fine_gamma, cfg)
    fine_end = [_rotate(rotation, a) for a in _frame_of(prob.f2, bases.fine_points, cfg)]
    straight = frames_between(fine_start, fine_end, cfg.n_times)
    frames = perturbed_frames(straight, coefficients, bases.fine_dframe)
    grid_energy = frame_energy(metric, *frames, cfg.scheme)

    d = jnp.sqrt(energy)
    d_time, d_grid = jnp.sqrt(time_energy), jnp.sqrt(grid_energy)
    change = jnp.maximum(jnp.abs(d_time - d), jnp.abs(d_grid - d))
    return Refinement(d_time, d_grid, change / jnp.maximum(d, jnp.finfo(d.dtype).tiny))


def _straight_rounds(prob, cfg, rigid, state: _State, weight, cap) -> _State:
    """Rounds on the matching criterion (weight 1: L2, 0: the straight line's energy),
    each round's BFGS cut at ``cap`` steps."""
    criterion = _matching_criterion(prob, cfg, weight)
    current = criterion(state.gamma, state.rotation)
    floor = criterion(prob.e1, jnp.eye(3, dtype=prob.f1.dtype))

    def small(before, after):
        return jnp.abs(before - after) <= cfg.outer_tol * (after + cfg.outer_tol * floor)

    state, _, _, _ = _iterate(
        lambda s: _straight_round(prob, cfg, rigid, weight, cap, s),
        state._replace(energy=current),
        cfg.outer_steps,
        small,
    )
    return state


def _coarse_registration(prob, cfg, rigid, starts) -> _State:
    """From the starts (_initialize's result) to the registration the rounds with the
    whole path begin from.

    Coarse to fine in the criterion and in time. Every start gets rounds on the L2
    mismatch, each round's BFGS cut at _MATCH_STEPS (a round only has to move towards the
    basin: the next round linearizes again); the start whose straight line then has the
    lowest energy gets rounds on that energy.
    """
    dtype = prob.f1.dtype
    gammas, rotations, steps = starts
    zero = _State(
        prob.e1,
        jnp.eye(3, dtype=dtype),
        _zero_coefficients(prob, cfg),
        jnp.zeros((), dtype),
        jnp.zeros((), jnp.int32),
        jnp.zeros((), bool),
    )

    # Every start's L2 rounds and then the best start's energy rounds are jobs of one
    # scan, and so one compiled copy of the rounds (weight and step limit traced).
    n_starts = gammas.shape[0]
    starts = jax.tree_util.tree_map(
        lambda x: jnp.broadcast_to(x, (n_starts, *x.shape)), zero
    )._replace(gamma=gammas, rotation=rotations)

    def job(ends, j):
        matching = j < n_starts
        best = jnp.argmin(jnp.where(jnp.isfinite(ends.energy), ends.energy, jnp.inf))
        i = jnp.where(matching, j, best.astype(jnp.int32))
        state = jax.tree_util.tree_map(lambda x: x[i], ends)
        weight = jnp.where(matching, 1.0, 0.0).astype(dtype)
        cap = jnp.where(matching, _MATCH_STEPS, cfg.max_steps)
        state = _straight_rounds(prob, cfg, rigid, state, weight, cap)
        # A matched start is ranked by its straight line's energy.
        frames = _registered_frame(prob, cfg, state.gamma), _end_frame(prob, cfg, state.rotation)
        straight = _straight_energy(prob, cfg, *frames)
        slot = jnp.minimum(j, n_starts - 1)
        ends = jax.tree_util.tree_map(
            lambda e, x: jnp.where(matching, e.at[slot].set(x), e),
            ends,
            state._replace(energy=straight),
        )
        return ends, state

    ends, states = jax.lax.scan(job, starts, jnp.arange(n_starts + 1, dtype=jnp.int32))
    state = jax.tree_util.tree_map(lambda x: x[-1], states)
    best = jnp.argmin(jnp.where(jnp.isfinite(ends.energy), ends.energy, jnp.inf))
    others = jnp.sum(ends.steps).astype(jnp.int32) - ends.steps[best]
    return state._replace(steps=state.steps + steps + others)


def _zero_coefficients(prob, cfg):
    return jnp.zeros((cfg.n_times - 2, prob.bases.dframe.shape[0] * 3), prob.f1.dtype)


def _final_solves(prob, cfg, state: _State):
    """The unregistered and the registered geodesics, saddle-checked.

    One traced solve for both (lax.map runs them one after the other): half the
    compilation of two call sites.
    """
    f1, f2, bases = prob.f1, prob.f2, prob.bases
    starts = jnp.stack([f1, _registered(prob, cfg, state.gamma)])
    ends = jnp.stack([f2, _rotate(state.rotation, f2)])
    inits = jnp.stack([_zero_coefficients(prob, cfg), state.coefficients])
    identity = _identity_frames(prob, cfg)
    registered = _registered_frame(prob, cfg, state.gamma), _end_frame(prob, cfg, state.rotation)
    frames = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), identity, registered)

    def solve(problem):
        start, end, init, (start_frame, end_frame) = problem
        return solve_path(
            prob.metric,
            start,
            end,
            init,
            bases.values,
            bases.dframe,
            **_geodesic_options(cfg),
            saddle_checks=cfg.saddle_checks,
            frames=(start_frame, end_frame),
        )

    return jax.lax.map(solve, (starts, ends, inits, frames))


def _problem(metric, f1, f2, bases, rigid) -> _Problem:
    m, n = f1.shape[-2:]
    if rigid:
        f1, f2 = center_unchecked(f1), center_unchecked(f2)
    return _Problem(metric, f1, f2, sphere_points(m, n, f1.dtype), bases)


class _Rounds(NamedTuple):
    """Where the registration rounds stand between the phases of a solve."""

    state: _State
    history: Array  # (outer_steps + 2,) as ShapeGeodesicResult.energy_history, [0] unset
    rounds: Array  # () rounds with the whole path taken
    done: Array  # () bool: the last round met outer_tol or was refused


def _shape_starts(metric, f1, f2, bases, cfg, rigid) -> tuple[Array, Array, Array]:
    """Phase 1 of a solve: the starts (_initialize)."""
    return _initialize(_problem(metric, f1, f2, bases, rigid), cfg, rigid)


def _shape_coarse(metric, f1, f2, bases, starts, cfg, rigid) -> tuple[_State, Array]:
    """Phase 2: the coarse registration from the starts, and the energy history with its
    energy at [1] (no rounds with the path yet)."""
    prob = _problem(metric, f1, f2, bases, rigid)
    state = _coarse_registration(prob, cfg, rigid, starts)
    energy = _path_energy_at(prob, cfg, state.gamma, state.rotation, state.coefficients)
    state = state._replace(energy=energy, shrunk=jnp.zeros((), bool))
    history = jnp.full((cfg.outer_steps + 2,), jnp.nan, energy.dtype).at[1].set(energy)
    return state, history


def _shape_rounds(metric, f1, f2, bases, coarse, cfg, rigid) -> _Rounds:
    """Phase 3: the registration rounds with the whole path."""
    prob = _problem(metric, f1, f2, bases, rigid)
    straight0 = _straight_energy(prob, cfg, *_identity_frames(prob, cfg))

    def small_change(before, after):
        # Relative to the current energy, with a floor at outer_tol times the straight
        # line's: near a perfect match the energy is interpolation noise.
        return jnp.abs(before - after) <= cfg.outer_tol * (after + cfg.outer_tol * straight0)

    state, history = coarse
    return _Rounds(
        *_iterate(
            lambda s: _round(prob, cfg, rigid, s), state, cfg.outer_steps, small_change, history
        )
    )


def _shape_geodesics(metric, f1, f2, bases, rounds: _Rounds, cfg, rigid):
    """Phase 4: the parametrized and the final geodesic (``rounds`` passed on)."""
    prob = _problem(metric, f1, f2, bases, rigid)
    return rounds, _final_solves(prob, cfg, rounds.state)


def _shape_end(metric, f1, f2, bases, solved, cfg, rigid) -> ShapeGeodesicResult:
    """Phase 5: the result from the rounds and the geodesics (status, refinement)."""
    prob = _problem(metric, f1, f2, bases, rigid)
    dtype = prob.f1.dtype
    rounds, both = solved
    parametrized, final = (jax.tree_util.tree_map(lambda x, i=i: x[i], both) for i in (0, 1))
    state, history = rounds.state, rounds.history
    history = history.at[0].set(parametrized.energy)
    steps = state.steps + jnp.sum(both.num_steps).astype(jnp.int32)
    scaling = _scaling_at(prob, cfg, state.gamma, state.rotation)
    joint = _joint_objective(prob, cfg, rigid, state.gamma, state.rotation, scaling)
    zero_step = _zero_registration(prob, rigid, dtype)
    grad_norm = optx.two_norm(jax.grad(joint)((scaling.whitened(final.coefficients), zero_step)))
    rounds_result = RESULTS.where(
        state.shrunk,
        RESULTS.resolution_limited,
        RESULTS.where(rounds.done, RESULTS.successful, RESULTS.nonlinear_max_steps_reached),
    )
    result = RESULTS.where(final.converged, rounds_result, final.result)
    if cfg.refinement:
        refinement = _refinement(
            prob, cfg, state.gamma, state.rotation, final.coefficients, final.energy
        )
    else:
        nan = jnp.asarray(jnp.nan, dtype)
        refinement = Refinement(nan, nan, nan)
    return ShapeGeodesicResult(
        path=final.path,
        distance=final.distance,
        energy=final.energy,
        parametrized_distance=parametrized.distance,
        f1_registered=final.path[0],
        gamma=state.gamma,
        rotation=state.rotation,
        coefficients=final.coefficients,
        energy_history=history,
        rounds=rounds.rounds,
        num_steps=steps,
        converged=final.converged & rounds.done & ~state.shrunk,
        result=result,
        grad_norm=grad_norm,
        min_curvature=final.min_curvature,
        refinement=refinement,
    )


# The structures of the phases' results (leaves are placeholders), to rebuild them from
# an exported program's flat outputs (see _cache.exported_call).
_STATE_SKELETON = _State(*([0] * 6))
_ROUNDS_SKELETON = _Rounds(_STATE_SKELETON, 0, 0, 0)
_RESULT_SKELETON = ShapeGeodesicResult(*([0] * 12), RESULTS.successful, 0, 0, Refinement(0, 0, 0))
_GEODESIC_SKELETON = GeodesicResult(*([0] * 7), RESULTS.successful, 0, 0)
# (name, function, skeleton) per phase, in order; each takes the previous one's result.
_PHASES = (
    ("shape_starts", _shape_starts, (0, 0, 0)),
    ("shape_coarse", _shape_coarse, (_STATE_SKELETON, 0)),
    ("shape_rounds", _shape_rounds, _ROUNDS_SKELETON),
    ("shape_geodesics", _shape_geodesics, (_ROUNDS_SKELETON, _GEODESIC_SKELETON)),
    ("shape_end", _shape_end, _RESULT_SKELETON),
)
# The last phase runs for milliseconds and decides nothing the result reports as found
# (its gradient norm and refinement are diagnostics): compiled for compile speed.
_PHASE_JITS = {
    name: solver_jit(f, static_argnames=("cfg", "rigid"), quick=name == "shape_end")
    for name, f, _ in _PHASES
}


def _solve_in_phases(
    args: tuple, cfg: ShapeOptions, rigid: bool, starts=None
) -> ShapeGeodesicResult:
    """_shape_solve(*args, cfg, rigid), one compiled program per phase; ``starts`` (the
    first phase's result, given) skips the start search.

    XLA:CPU's compile time and memory grow with a program, and the phases share no
    compiled code: compiled one after the other, the largest program sets the peak
    memory, not their sum (measured: 25 x 49 at the defaults, peak RSS 789 MB as one
    program, 600 MB as five). JAX's asynchronous dispatch loads (or compiles) a phase
    while the one before runs. The arithmetic is that of one program, except the last
    phase's diagnostics (solver_jit's quick compilation: grad_norm rounds differently,
    about 1e-11 relative). Inside a caller's trace (karcher_mean, distance_matrix) the
    phases are part of the caller's one program.
    """
    static = {"cfg": cfg, "rigid": rigid}
    phases, carried = (_PHASES, ()) if starts is None else (_PHASES[1:], (starts,))
    for name, function, skeleton in phases:
        carried = (
            exported_call(name, function, _PHASE_JITS[name], (*args, *carried), static, skeleton),
        )
    return carried[0]


def _shape_solve(metric, f1, f2, bases, cfg, rigid) -> ShapeGeodesicResult:
    """The whole solve (_solve_in_phases); traced inside a jit, one program."""
    return _solve_in_phases((metric, f1, f2, bases), cfg, rigid)


@functools.partial(jax.jit, static_argnames=("cfg", "rigid"))
def _shape_evaluate(metric, f1, f2, bases, gamma, rotation, coefficients, *, cfg, rigid):
    """The path from f1 o gamma to R f2 with the perturbation C, and its energy."""
    if rigid:
        f1, f2 = center_unchecked(f1), center_unchecked(f2)
    prob = _Problem(metric, f1, f2, sphere_points(*f1.shape[-2:], f1.dtype), bases)
    start, end = _registered(prob, cfg, gamma), _rotate(rotation, f2)
    path = path_from_coefficients(start, end, coefficients, bases.values, cfg.n_times)
    return path, _path_energy_at(prob, cfg, gamma, rotation, coefficients)


def _bases(m: int, n: int, cfg: ShapeOptions, dtype) -> _Bases:
    values, dframe = basis_np(m, n, cfg.degree)
    fine = (2 * m - 1, 2 * n - 1)
    fine_dframe = basis_np(*fine, cfg.degree)[1] if cfg.refinement else np.zeros((1, 1))
    arrays = _Bases(
        values=values,
        dframe=dframe,
        fields=vector_fields_np(m, n, cfg.vf_degree),
        field_scale=_field_scale_np(m, n, cfg.vf_degree),
        ico=icosahedral_np(),
        fine_points=sphere_points_np(*fine),
        fine_dframe=fine_dframe,
        area_floor=np.asarray(_resolution_np(m, n)[0]),
        max_boost=np.asarray(_resolution_np(m, n)[1]),
    )
    return _Bases(*(jnp.asarray(a, dtype) for a in arrays))


def resolve_options(options: ShapeOptions | None, changes: dict) -> ShapeOptions:
    """``options`` (default ShapeOptions()) with keyword changes applied and validated."""
    if options is None:
        options = ShapeOptions()
    elif not isinstance(options, ShapeOptions):
        raise TypeError(f"options must be a ShapeOptions; got {type(options).__name__}")
    return options.replace(**changes) if changes else options


# Newton steps of _inverse_gamma: quadratic from the nearest grid image; 12 reach rounding
# on the cats' registrations (residual 2e-15 at 25 x 49, smallest Jacobian 0.095).
_INVERSE_STEPS = 12


@jax.jit
def _inverse_gamma(gamma: Array) -> tuple[Array, Array]:
    """gamma^-1 on the grid: the points x with gamma(x) = p for the grid points p, and
    the largest |gamma(x) - p|.

    gamma is read between grid points by its bicubic interpolant (as _compose reads it),
    and each x solved by Newton's method in the tangent plane, from the grid point whose
    image lies nearest p.
    """
    m, n = gamma.shape[-2:]
    points = sphere_points(m, n, gamma.dtype).reshape(3, -1)
    images = gamma.reshape(3, -1)
    nearest = jax.lax.map(lambda p: jnp.argmax(p @ images), points.T, batch_size=256)

    def read(x):
        y = sample_points(gamma, x[:, None], "bicubic")[:, 0]
        return y / jnp.linalg.norm(y)

    def solve(x, target):
        def step(x, _):
            # A tangent basis at x that stays well conditioned at the poles.
            axis = jnp.where(
                jnp.abs(x[2]) < 0.9, jnp.eye(3, dtype=x.dtype)[2], jnp.eye(3, dtype=x.dtype)[0]
            )
            t1 = jnp.cross(x, axis)
            t1 = t1 / jnp.linalg.norm(t1)
            t2 = jnp.cross(x, t1)
            y, d1 = jax.jvp(read, (x,), (t1,))
            _, d2 = jax.jvp(read, (x,), (t2,))
            move = jnp.linalg.lstsq(jnp.stack([d1, d2], axis=1), target - y)[0]
            x = x + move[0] * t1 + move[1] * t2
            return x / jnp.linalg.norm(x), None

        x, _ = jax.lax.scan(step, x, None, length=_INVERSE_STEPS)
        return x, jnp.max(jnp.abs(read(x) - target))

    x, residual = jax.vmap(solve, in_axes=(1, 1), out_axes=(1, 0))(points[:, nearest], points)
    return x.reshape(3, m, n), jnp.max(residual)


def _given_start(start, m: int, n: int, dtype, rigid: bool):
    """A caller's registration as the starts of the rounds: (gamma[None], R[None], 0).

    gamma on another grid is read at this grid's points (bicubic, back onto the sphere):
    gamma_fine(p) = gamma(p) for the coarse gamma's interpolant.
    """
    if isinstance(start, ShapeGeodesicResult):
        gamma, rotation = start.gamma, start.rotation
    else:
        try:
            gamma, rotation = start
        except (TypeError, ValueError):
            raise InputError(
                "start must be a ShapeGeodesicResult or a pair (gamma (3, p, q), rotation "
                f"(3, 3)); got {type(start).__name__}"
            ) from None
    gamma = real_array(gamma, "start's gamma").astype(dtype)
    rotation = real_array(rotation, "start's rotation").astype(dtype)
    if gamma.ndim != 3:
        raise InputError(f"start's gamma must have shape (3, p, q); got {gamma.shape}")
    check_grid_shape(gamma.shape, "start's gamma")
    if rotation.shape != (3, 3):
        raise InputError(f"start's rotation must have shape (3, 3); got {rotation.shape}")
    check_finite(gamma, "start's gamma")
    check_finite(rotation, "start's rotation")
    if is_concrete(gamma, rotation):
        radius = np.linalg.norm(np.asarray(gamma, np.float64), axis=0)
        if np.abs(radius - 1.0).max() > 1e-4:
            raise InputError(
                "start's gamma must hold unit vectors (points of S^2); |gamma| ranges "
                f"over [{radius.min():.4g}, {radius.max():.4g}]"
            )
        r = np.asarray(rotation, np.float64)
        if np.abs(r @ r.T - np.eye(3)).max() > 1e-4 or np.linalg.det(r) < 0:
            raise InputError("start's rotation must be a rotation (orthogonal, det +1)")
    if gamma.shape[-2:] != (m, n):
        gamma = _compose(gamma, sphere_points(m, n, dtype), "bicubic")
    if is_concrete(gamma) and not float(jnp.min(jacobian_determinant_unchecked(gamma))) > 0:
        raise InputError(
            f"start's gamma is not a diffeomorphism on the {m} x {n} grid (its Jacobian "
            "determinant is not positive at every grid point)"
        )
    if not rigid:
        rotation = jnp.eye(3, dtype=dtype)
    return gamma[None], rotation[None], jnp.zeros((), jnp.int32)


def check_grid_options(options: ShapeOptions, m: int, n: int) -> None:
    """The grid-dependent limits of ``options`` (degrees) on an m x n grid."""
    check_degree(options.degree, m, n)
    check_degree(options.vf_degree, m, n, "vf_degree")


def shape_geodesic(
    f1: Float[ArrayLike, "3 m n"],
    f2: Float[ArrayLike, "3 m n"],
    metric: SplitMetric,
    *,
    modulo: str = "diff",
    options: ShapeOptions | None = None,
    start: ShapeGeodesicResult | tuple[ArrayLike, ArrayLike] | None = None,
    symmetric: bool = False,
    **changes,
) -> ShapeGeodesicResult:
    """Geodesic between the shapes of f1 and f2, modulo reparametrization (and rigid motion).

    Minimizes the path energy (MATH.md 4; the options' scheme, midpoint by default) over
    paths from f1 o gamma to R f2 and over gamma in Diff+(S^2) (and R in SO(3) for
    modulo="rigid"); paper sections 4.2-4.3.

    1. The parametrized geodesic f1 -> f2 (``parametrized_distance``).
    2. Starts (``init="moebius"``): the 60 icosahedral rotations as reparametrizations
       ranked by straight-line energy, the best ``init_candidates`` refined over the
       rotations and over the Moebius group of S^2 (rotations and conformal boosts).
       Every start gets registration rounds on the L2 mismatch; the one whose straight
       line then has the lowest energy gets rounds on that energy (coarse to fine in the
       criterion and in time).
    3. Registration rounds with the whole path (``method="joint"``: path and Diff step
       together, Algorithm 2; ``"coordinate"``: alternately). Each Diff step
       Proj(Id + sum x_k v_k) of degree vf_degree is composed onto gamma and shrunk (by
       halves, down to no step) until the composed gamma has a positive Jacobian at every
       grid point and keeps the area the grid can resolve (MATH.md 9); rounds never raise
       the energy and stop when one changes it by at most outer_tol, or after outer_steps.
       Rounds whose last step had to shrink stopped at that edge, not at a minimum:
       ``RESULTS.resolution_limited``, not converged.
    4. The final geodesic, its status, and the refinement check (:class:`Refinement`).

    Each phase is one compiled program (five in all, see _solve_in_phases); under
    ``jax.vmap`` or a caller's ``jax.jit`` the whole solve is one program, vmappable
    over f2.

    Args:
        f1, f2: ``(3, m, n)`` immersions on the same grid.
        metric: split metric coefficients.
        modulo: ``"diff"`` (reparametrizations) or ``"rigid"`` (also rotations; centers both).
        options: a :class:`ShapeOptions` (its defaults when None).
        start: a registration to start the rounds from instead of the start search (step
            2; ``init`` is then not used): a :class:`ShapeGeodesicResult`, e.g. of the same
            pair on a coarser grid (multiresolution in grid, the paper's section 5), or
            a pair (gamma ``(3, p, q)``, rotation ``(3, 3)``). gamma on another grid is
            read at this grid's points (bicubic); the rotation is ignored modulo "diff".
        symmetric: also solve the other order, f2 to f1; when it ends lower, solve this
            order again from its registration inverted (gamma^-1 by Newton's method on
            gamma's interpolant, R^T), and return the lower of this order's results. The
            two orders' rounds end in different local minima (the cats at 25 x 49: 0.751
            one way, 0.722 the other, and 0.7225 this way from the other's registration),
            so this finds the lower basin from either side. Two or three solves; concrete
            inputs only (not under jit or vmap).
        **changes: fields of ShapeOptions to change, e.g. ``degree=5, n_times=9``.

    Returns:
        :class:`ShapeGeodesicResult`. A result that did not converge also warns
        (:class:`ConvergenceWarning`); it never raises for that.

    Example:
        >>> import elastic_jax as ej
        >>> from elastic_jax import shapes
        >>> f1 = shapes.sample(shapes.bumpy, 13, 25)
        >>> f2 = shapes.sample(shapes.bumpy, 13, 25, rotation=shapes.random_rotation(1))
        >>> options = ej.ShapeOptions(degree=4, vf_degree=4, n_times=5)
        >>> metric = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)
        >>> res = ej.shape_geodesic(f1, f2, metric, modulo="rigid", options=options)
        >>> bool(res.distance < 0.1 * res.parametrized_distance)
        True
    """
    check_choice("modulo", modulo, MODULI)
    cfg = resolve_options(options, changes)
    f1, f2 = check_pair(f1, f2)
    if symmetric:
        return _symmetric_solve(f1, f2, metric, modulo, cfg, start)
    m, n = f1.shape[-2:]
    check_grid_options(cfg, m, n)
    dtype = f1.dtype
    if cfg.tol is None:
        cfg = cfg.replace(tol=default_tol(dtype))
    rigid = modulo == "rigid"
    # Solve in units of the surfaces' size (see _units): float32 then works at any scale.
    units, (g1, g2) = in_units(f1, f2)
    bases = _bases(m, n, cfg, dtype)
    starts = None if start is None else _given_start(start, m, n, dtype, rigid)
    # As in geodesic: the solve runs on constants and the energy is evaluated again,
    # differentiably, at the solution (envelope theorem: the derivative of the minimal
    # energy in f1, f2 and the metric, with gamma, R and C held).
    solved = _solve_in_phases(
        (constant(metric), jax.lax.stop_gradient(g1), jax.lax.stop_gradient(g2), bases),
        cfg,
        rigid,
        starts,
    )
    result = _shape_finish(metric, g1, g2, bases, solved, units, cfg=cfg, rigid=rigid)
    _warn_unless_converged(result)
    return result


def _symmetric_solve(f1, f2, metric, modulo, cfg, start) -> ShapeGeodesicResult:
    """shape_geodesic(symmetric=True): the lower of this order's solve and its solve from
    the other order's registration inverted (when that one ends lower)."""
    if not is_concrete(f1, f2, metric):
        raise InputError(
            "symmetric=True compares whole solves: it needs concrete inputs, not tracers "
            "(call it outside jax.jit and jax.vmap)"
        )
    solve = functools.partial(shape_geodesic, metric=metric, modulo=modulo, options=cfg)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        best = solve(f1, f2, start=start)
        other = solve(f2, f1)
        if float(other.distance) < float(best.distance):
            inverse, residual = _inverse_gamma(other.gamma)
            tol = 10.0 * float(np.sqrt(np.finfo(np.dtype(inverse.dtype)).eps))
            if (
                float(residual) <= tol
                and float(jnp.min(jacobian_determinant_unchecked(inverse))) > 0
            ):
                again = solve(f1, f2, start=(inverse, other.rotation.T))
                if float(again.distance) < float(best.distance):
                    best = again
    _warn_unless_converged(best)
    return best


def _warn_unless_converged(result: ShapeGeodesicResult) -> None:
    """ConvergenceWarning for a concrete result that did not converge."""
    if is_concrete(result.converged, result.energy_history, result.rounds) and not bool(
        result.converged
    ):
        history = np.asarray(result.energy_history)
        # Every other ending's words (stalled, saddle, resolution-limited) say what to
        # change; running out of steps is the one that does not.
        ran_out = bool(result.result == RESULTS.nonlinear_max_steps_reached)
        advice = "; raise outer_steps or max_steps" if ran_out else ""
        warnings.warn(
            f"shape_geodesic: not converged after {int(result.rounds)} registration rounds "
            f"({result.message}; energies {history[np.isfinite(history)].round(6).tolist()})"
            f"{advice}",
            ConvergenceWarning,
            stacklevel=3,
        )


@functools.partial(jax.jit, static_argnames=("cfg", "rigid"))
def _shape_finish(metric, g1, g2, bases, solved, units, *, cfg, rigid) -> ShapeGeodesicResult:
    """The result in the user's units from the solve's: the path and its energy evaluated
    again at the solution (differentiably, see shape_geodesic), then the units restored.
    One compiled program: op by op, a first call would compile each operation alone."""
    gamma, rotation, coefficients = (
        jax.lax.stop_gradient(x) for x in (solved.gamma, solved.rotation, solved.coefficients)
    )
    path, energy = _shape_evaluate(
        metric, g1, g2, bases, gamma, rotation, coefficients, cfg=cfg, rigid=rigid
    )
    unit_result = solved._replace(
        path=path, f1_registered=path[0], energy=energy, distance=safe_sqrt(energy)
    )
    return _restore_shape_units(unit_result, units, rigid)


def _restore_shape_units(result: ShapeGeodesicResult, units, rigid: bool) -> ShapeGeodesicResult:
    """A result solved in ``units`` in the user's units again. Modulo "rigid" the solve
    centres both surfaces, so the path is only scaled back; modulo "diff" it is also
    moved back to the inputs' place."""
    s = units.scale

    def surfaces(x):
        return x * s if rigid else units.restore(x)

    return result._replace(
        path=surfaces(result.path),
        distance=result.distance * s,
        energy=result.energy * s**2,
        parametrized_distance=result.parametrized_distance * s,
        f1_registered=surfaces(result.f1_registered),
        coefficients=result.coefficients * s,
        energy_history=result.energy_history * s**2,
        refinement=result.refinement._replace(
            distance_time=result.refinement.distance_time * s,
            distance_grid=result.refinement.distance_grid * s,
        ),
    )


def turned_back(res, end):
    """A shape geodesic's path (from f1 o gamma to R f2) turned by R^T and moved so that it
    ends at ``end`` (its f2) as parametrized and placed (modulo "rigid" centres both)."""
    back = jnp.einsum("ji,tj...->ti...", res.rotation, res.path)
    return back + (end - back[-1]).mean(axis=(-2, -1), keepdims=True)[None]
