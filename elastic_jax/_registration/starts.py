"""Phase 1, the starts (paper Remark 4, math §7): the 60 icosahedral rotations ranked
on the straight line's energy, the best refined over rotations and over the Moebius
group; a caller's own start; and the inverse of a reparametrization.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import DTypeLike
from jaxtyping import Array, ArrayLike

from .._checks import check_finite, check_grid_shape, is_concrete, real_array
from .._errors import InputError
from .._geodesics.solvers import minimize
from .._geometry.composition import compose, kabsch, rotate_surface
from .._geometry.grid import sphere_points
from .._geometry.metric import SplitMetric
from .._geometry.reparam import (
    jacobian_determinant_unchecked,
    moebius,
    sample_points,
)
from .._geometry.so3 import so3_exp_unchecked
from .._options import ShapeOptions
from .problem import (
    Problem,
    are_resolved,
    identity_frames,
    into_ball,
    l2_mismatch,
    make_problem,
    registered_f1,
    registered_frame,
    rotated_end_frame,
    straight_line_energy,
)
from .records import ShapeGeodesicResult

# BFGS steps spent on each of the 60 icosahedral starting rotations before ranking them.
_SEARCH_STEPS = 12


# Shrink factors tried for an initial Moebius boost that the grid does not resolve.
_BOOST_SCALES = (1.0, 0.95, 0.9, 0.85, 0.8, 0.7, 0.6, 0.5, 0.25, 0.0)


def _distinct_best(values: ArrayLike, points: ArrayLike, k: int, separation: float):
    """Indices of k low ``values (S,)`` whose ``points (S, 3, P)`` lie apart.

    Greedy: the lowest value first, then the lowest whose mean distance on the sphere to
    every chosen one exceeds ``separation``; when fewer than k are that far apart, the
    remaining picks are the lowest not yet taken.
    """
    distances = jnp.mean(jnp.linalg.norm(points[:, None] - points[None], axis=-2), axis=-1)

    def pick(carry: tuple, _: None):
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


def _start_map(points: ArrayLike, max_boost: ArrayLike, q: ArrayLike, vb: ArrayLike):
    """The start (q, vb) of the search applied to ``points (3, ...)`` of the sphere:
    q exp(hat v) phi_b, vb = (v, b), the boost b bounded to ``max_boost`` (into_ball)."""
    return rotate_surface(
        q @ so3_exp_unchecked(vb[:3]), moebius(points, into_ball(vb[3:], max_boost))
    )


def _aligned(prob: Problem, options: ShapeOptions, rigid: bool, gamma: ArrayLike):
    """f1 o gamma and R^3's Procrustes rotation of f2 onto it (the identity unless rigid)."""
    start = registered_f1(prob, options, gamma)
    r = kabsch(prob.f2, start) if rigid else jnp.eye(3, dtype=start.dtype)
    return start, r


def _start(prob: Problem, options: ShapeOptions, rigid: bool, q: ArrayLike, vb: ArrayLike):
    """A searched start as (gamma, R): its boost shrunk until the grid resolves gamma.

    The boost is bounded to what the grid resolves for a generic direction; shrink it
    where this direction needs less (a pure rotation, the last scale, always does).
    """
    boosts = jnp.asarray(_BOOST_SCALES, vb.dtype)[:, None] * vb[None, 3:]
    maps = jax.vmap(lambda b: _start_map(prob.e1, prob.bases.max_boost, q, vb.at[3:].set(b)))
    ok = are_resolved(maps(boosts), prob.bases.area_floor).at[-1].set(True)
    gamma = _start_map(prob.e1, prob.bases.max_boost, q, vb.at[3:].set(boosts[jnp.argmax(ok)]))
    return gamma, _aligned(prob, options, rigid, gamma)[1]


def _initialize_moebius(prob: Problem, options: ShapeOptions, rigid: bool):
    """The starts of the registration for init="moebius" (docs/guides/registration_notes.md).

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

    reference = l2_mismatch(prob.f1, prob.f2)
    reference = jnp.where(reference > 0, reference, 1.0)

    def objective(q: ArrayLike, vb: ArrayLike):
        start, r = _aligned(prob, options, rigid, _start_map(prob.e1, prob.bases.max_boost, q, vb))
        return l2_mismatch(start, rotate_surface(r, prob.f2)) / reference

    # The short search from every icosahedral rotation and then the refinement of the
    # chosen init_candidates are jobs of one scan, and so one compiled solve (its
    # objective and gradient are the bulk of the program); the step limit is traced.
    ico, k = prob.bases.ico, options.init_candidates
    n_ico = ico.shape[0]
    # Where each searched start maps a few points of the sphere: the icosahedron's 12
    # vertices and 20 face centres under the rotation only would miss the boost, so the
    # grid's own points are used (every 4th row and column).
    probe = prob.e1[:, ::4, ::4].reshape(3, -1)

    def job(searched: tuple, j: ArrayLike):
        values, params = searched
        searching = j < n_ico
        # The distinct best, once the search is done (the rows are then final).
        points = jax.vmap(lambda q, vb: _start_map(probe, prob.bases.max_boost, q, vb))(ico, params)
        chosen = _distinct_best(values, points, k, _DISTINCT_STARTS)
        i = jnp.where(searching, j, chosen[(j - n_ico) % k])
        u0 = jnp.where(searching, jnp.zeros(6, dtype), params[i])
        cap = jnp.where(searching, _SEARCH_STEPS, options.max_steps)
        found = minimize(
            lambda u: objective(ico[i], u),
            u0,
            solver=options.solver,
            max_steps=max(options.max_steps, _SEARCH_STEPS),
            tol=options.tol,
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

    gammas, rotations = jax.vmap(lambda q, vb: _start(prob, options, rigid, q, vb))(qs, vbs)
    return gammas, rotations, jnp.sum(job_steps).astype(jnp.int32)


def _initialize_energy(prob: Problem, options: ShapeOptions, rigid: bool):
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

    reference = straight_line_energy(prob, options, *identity_frames(prob, options))
    reference = jnp.where(reference > 0, reference, 1.0)

    def objective(q: ArrayLike, vb: ArrayLike):
        gamma = _start_map(prob.e1, prob.bases.max_boost, q, vb)
        _, r = _aligned(prob, options, rigid, gamma)
        start, end = registered_frame(prob, options, gamma), rotated_end_frame(prob, options, r)
        return straight_line_energy(prob, options, start, end) / reference

    def refine(q: ArrayLike, vb0: ArrayLike, max_steps: int, free: int, cap: Array | None = None):
        # free = 3: rotations only (the boost stays 0); 6: the Moebius group.
        def restricted(u: ArrayLike):
            return objective(q, vb0.at[:free].set(u) if free == 3 else u)

        found = minimize(
            restricted,
            vb0[:free],
            solver=options.solver,
            max_steps=max_steps,
            tol=options.tol,
            step_cap=cap,
        )
        vb = vb0.at[:free].set(found.x) if free == 3 else found.x
        value = found.value  # objective(q, vb), as the solver evaluated it
        # A straight line through a fold has an infinite (midpoint) or NaN energy: last.
        return jnp.where(jnp.isfinite(value), value, jnp.inf), vb, found.num_steps

    # The short search from every icosahedral rotation and then the refinement of the
    # best init_candidates over rotations are jobs of one scan, and so one compiled solve
    # (its objective and gradient are the bulk of the program); the step limit is traced.
    ico, k = prob.bases.ico, options.init_candidates
    n_ico = ico.shape[0]

    def job(searched: tuple, j: ArrayLike):
        energies, params = searched
        searching = j < n_ico
        top = jax.lax.top_k(-energies, k)[1].astype(jnp.int32)  # once the search is done
        i = jnp.where(searching, j, top[(j - n_ico) % k])
        start = jnp.where(searching, jnp.zeros(6, dtype), params[i])
        cap = jnp.where(searching, _SEARCH_STEPS, options.max_steps)
        energy, vb, steps = refine(ico[i], start, max(options.max_steps, _SEARCH_STEPS), 3, cap)
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
    if options.init == "energy":
        # Six parameters where the rotations have three: a solve of its own.
        _, boosted, more = jax.lax.map(
            lambda i: refine(ico[i], params[i], options.max_steps, 6), top
        )
        qs, vbs = jnp.concatenate([qs, qs]), jnp.concatenate([vbs, boosted])
        steps = steps + jnp.sum(more)

    gammas, rotations = jax.vmap(lambda q, vb: _start(prob, options, rigid, q, vb))(qs, vbs)
    return gammas, rotations, steps.astype(jnp.int32)


def _initialize(prob: Problem, options: ShapeOptions, rigid: bool):
    """The starts of the registration: (gammas ``(S, 3, m, n)``, rotations ``(S, 3, 3)``,
    solver steps), by ``options.init`` (:class:`ShapeOptions`)."""
    if options.init == "none":
        eye = jnp.eye(3, dtype=prob.f1.dtype)
        return prob.e1[None], eye[None], jnp.zeros((), jnp.int32)
    if options.init == "moebius":
        return _initialize_moebius(prob, options, rigid)
    return _initialize_energy(prob, options, rigid)


def starts_phase(
    metric: SplitMetric,
    f1: ArrayLike,
    f2: ArrayLike,
    bases,
    options: ShapeOptions,
    rigid: bool,
) -> tuple[Array, Array, Array]:
    """Phase 1 of a solve: the starts (_initialize)."""
    return _initialize(
        make_problem(metric, f1, f2, bases, rigid, options.interpolation), options, rigid
    )


# Newton steps of inverse_gamma: quadratic from the nearest grid image; 12 reach rounding
# on the cats' registrations (residual 2e-15 at 25 x 49, smallest Jacobian 0.095).
_INVERSE_STEPS = 12


@jax.jit
def inverse_gamma(gamma: Array) -> tuple[Array, Array]:
    """gamma^-1 on the grid: the points x with gamma(x) = p for the grid points p, and
    the largest |gamma(x) - p|.

    gamma is read between grid points by its bicubic interpolant (as compose reads it),
    and each x solved by Newton's method in the tangent plane, from the grid point whose
    image lies nearest p.
    """
    m, n = gamma.shape[-2:]
    points = sphere_points(m, n, gamma.dtype).reshape(3, -1)
    images = gamma.reshape(3, -1)
    nearest = jax.lax.map(lambda p: jnp.argmax(p @ images), points.T, batch_size=256)

    def read(x: ArrayLike):
        y = sample_points(gamma, x[:, None], "bicubic")[:, 0]
        return y / jnp.linalg.norm(y)

    def solve(x: ArrayLike, target: ArrayLike):
        def step(x: ArrayLike, _: None):
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


def usable_inverse(gamma: Array) -> Array | None:
    """gamma^-1 on the grid (:func:`inverse_gamma`) where it is usable as a registration:
    its Newton residual within 10 sqrt(eps) of gamma's dtype and its Jacobian positive at
    every grid point; None otherwise (gamma's interpolant folds, or a point's solve did
    not converge)."""
    inverse, residual = inverse_gamma(gamma)
    tol = 10.0 * float(np.sqrt(np.finfo(np.dtype(inverse.dtype)).eps))
    if float(residual) <= tol and float(jnp.min(jacobian_determinant_unchecked(inverse))) > 0:
        return inverse
    return None


def given_start(start: object, m: int, n: int, dtype: DTypeLike, rigid: bool):
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
        gamma = compose(gamma, sphere_points(m, n, dtype), "bicubic")
    if is_concrete(gamma) and not float(jnp.min(jacobian_determinant_unchecked(gamma))) > 0:
        raise InputError(
            f"start's gamma is not a diffeomorphism on the {m} x {n} grid (its Jacobian "
            "determinant is not positive at every grid point)"
        )
    if not rigid:
        rotation = jnp.eye(3, dtype=dtype)
    return gamma[None], rotation[None], jnp.zeros((), jnp.int32)
