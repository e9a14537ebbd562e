"""Geodesics between parametrized surfaces: path straightening with BFGS (paper Algorithm 1).

The path is f_k = (1 - t_k) f1 + t_k f2 + sum_j C[k, j] S_j for interior k, end points
fixed, with S_j the spherical-harmonic surface basis (math §5, 7); the discrete energy
of math §4 is minimized over C. The basis enters through its finite-difference
differential, precomputed once per grid and degree, so that the objective is one matmul
plus the energy kernel, and the energy of the returned path equals path_energy exactly
(the differential is linear).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import DTypeLike
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
from .._geometry.bases import (
    basis_np,
    frames_between,
    path_from_coefficients,
    perturbed_frames,
)
from .._geometry.differential import area_element, interior_frame
from .._geometry.energy import frame_energy
from .._geometry.grid import integrate_interior
from .._geometry.harmonics import check_degree
from .._geometry.interp import resample
from .._geometry.metric import SplitMetric, split_bilinear
from .._geometry.numerics import constant, default_tol, safe_sqrt, sqrt_inverse_pair
from .._geometry.units import Units, in_units
from .._geometry.validation import check_pair
from .._options import (
    FROM_OPTIONS,
    SCHEMES,
    SOLVERS,
    FromOptions,
    ShapeOptions,
    settings_from,
)
from .._results import RESULTS, status_record
from .._runtime.cache import solver_jit
from .solvers import Minimum, lanczos_smallest, minimize


@status_record
class GeodesicResult(NamedTuple):
    """A geodesic between parametrized surfaces; a pytree, batched by ``jax.vmap``.

    Attributes:
        path: ``(N, 3, m, n)`` the optimal path, f1 and f2 at its ends.
        distance: ``()`` sqrt(energy), the geodesic distance.
        energy: ``()`` the path energy (:ref:`math §4 <math-4>`) of ``path``.
        straight_energy: ``()`` the energy of the straight line (the starting point).
        coefficients: ``(N - 2, L)`` C of the interior frames in :func:`surface_basis` order.
        num_steps: ``()`` solver steps taken, over all minimizations (the first and
            those after each saddle escape).
        converged: ``()`` whether the solver met its tolerance within max_steps and, when
            saddle escapes were asked for (``saddle_checks >= 1``), the end point is not a
            saddle (``min_curvature >= saddle_threshold(dtype)``); ``result ==
            RESULTS.successful`` says the same.
        result: the solver's result code, an ``elastic_jax.RESULTS`` (optimistix's codes
            and ``stalled``; jaxopt's outcome mapped to them), or ``saddle_point`` when
            the solver met its tolerance at a saddle that the escapes did not leave.
        grad_norm: ``()`` 2-norm of the gradient of the scaled objective at the end
            (energy / straight_energy in whitened coefficients, where its Hessian is ~2 I).
        min_curvature: ``()`` Lanczos estimate of the smallest eigenvalue of that scaled
            objective's Hessian at the end: an upper bound of it (Ritz value), positive
            at a strict minimum, negative at a saddle (whose direction the solver never
            explored). NaN where it is not estimated (the inner solves of shape_geodesic).
    """

    path: Float[Array, "N 3 m n"]
    distance: Float[Array, ""]
    energy: Float[Array, ""]
    straight_energy: Float[Array, ""]
    coefficients: Float[Array, "K L"]
    grad_norm: Float[Array, ""]
    min_curvature: Float[Array, ""]
    converged: Bool[Array, ""]
    result: RESULTS
    num_steps: Int[Array, ""]

    def _explain(self, words: str) -> str:
        if RESULTS.name(self.result) == "saddle_point":  # no eager == (a program of its own)
            words += f" (smallest Hessian eigenvalue {float(self.min_curvature):.3g})"
        return words


def _straight_frames(f1: ArrayLike, f2: ArrayLike, n_times: int, frames: tuple | None = None):
    """The straight line's interior frames; ``frames`` (start, end), each (a1, a2), when
    the ends' differentials are given rather than taken by central differences."""
    start, end = (interior_frame(f1), interior_frame(f2)) if frames is None else frames
    return frames_between(start, end, n_times)


def _whitening(
    metric: SplitMetric, mid1: ArrayLike, mid2: ArrayLike, dframe: ArrayLike, n_times: int
):
    """Factors of the change of variables X = A Z B that makes the energy's Hessian ~ 2 I.

    Returns (A, B, A^-1, B^-1, mean eigenvalue of M).

    The quadratic part of the energy in the coefficients X ``(N - 2, 3K)`` is
    tr(X^T L X M): L = T tridiag(-1, 2, -1) from the time differences (Dirichlet ends),
    M = [G_f(S_i, S_j)] the metric's Gram matrix of the basis, taken at the middle of the
    straight line. Its condition number grows like l^2 T^2 (about 1e6 at degree 7,
    N = 10), which stalls BFGS started from the identity; with A = L^(-1/2) and
    B = M^(-1/2) the solver sees a problem close to the identity.
    """
    k = dframe.shape[0]
    points = dframe.shape[1] // 2
    shape = (3, *mid1.shape[-2:])

    def quadratic(c: ArrayLike):
        pert = c.reshape(3, k) @ dframe
        x1, x2 = pert[:, :points].reshape(shape), pert[:, points:].reshape(shape)
        return integrate_interior(split_bilinear(metric, mid1, mid2, x1, x2, x1, x2))

    gram = 0.5 * jax.hessian(quadratic)(jnp.zeros(3 * k, mid1.dtype))
    eye = functools.partial(jnp.eye, n_times - 2, dtype=mid1.dtype)
    lap = (n_times - 1) * (2.0 * eye() - eye(k=1) - eye(k=-1))
    a, a_inv = sqrt_inverse_pair(lap, 0.0)
    # Degenerate metrics (SRNF's (0, 1/2, 1, 0)) have nearly free directions: floor them.
    b, b_inv = sqrt_inverse_pair(gram, 1e-6)
    return a, b, a_inv, b_inv, jnp.trace(gram) / gram.shape[0]


class _Scaling(NamedTuple):
    """The change of variables C = sqrt(E) A z B and the energy scale E of one problem."""

    energy_scale: Array
    straight: Array
    a: Array
    b: Array
    a_inv: Array
    b_inv: Array

    def coefficients(self, z: ArrayLike):
        return jnp.sqrt(self.energy_scale) * (self.a @ z @ self.b)

    def whitened(self, coefficients: ArrayLike):
        return (self.a_inv @ coefficients @ self.b_inv) / jnp.sqrt(self.energy_scale)


def solver_scaling(
    metric: SplitMetric,
    f1: ArrayLike,
    f2: ArrayLike,
    dframe: ArrayLike,
    n_times: int,
    scheme: str,
    frames: tuple | None = None,
) -> _Scaling:
    straight_frames = _straight_frames(f1, f2, n_times, frames)
    straight = frame_energy(metric, *straight_frames, scheme)
    # The solver works on z with C = sqrt(E_s) A z B (see _whitening) and the energy
    # divided by E_s: one tolerance then means the same for every shape, size and metric.
    mid = n_times // 2
    mid_frames = (straight_frames[0][mid], straight_frames[1][mid])
    a, b, a_inv, b_inv, gram_mean = _whitening(metric, *mid_frames, dframe, n_times)
    # When f1 = f2 the straight energy is rounding noise; floor the scale at sqrt(eps)
    # times the energy of a deformation of the shapes' own size (not an absolute constant).
    area = integrate_interior(area_element(straight_frames[0][0], straight_frames[1][0]))
    area = area + integrate_interior(area_element(straight_frames[0][-1], straight_frames[1][-1]))
    own_scale = gram_mean * area / (8.0 * np.pi)
    energy_scale = jnp.maximum(straight, np.sqrt(np.finfo(f1.dtype).eps) * own_scale)
    return _Scaling(energy_scale, straight, a, b, a_inv, b_inv)


def saddle_threshold(dtype: DTypeLike) -> float:
    """Curvature below which a stationary point of the scaled objective counts as a saddle.

    The scaled objective is energy / straight-line energy in whitened coordinates, where
    the Hessian is about 2 I. A unit step along an eigenvector of eigenvalue -1e-3
    lowers it by 5e-4, far above the solver's tolerance in float64 (1e-6), while the
    Lanczos estimate itself is exact to ~1e-10 there: -1e-3 in float64. In float32 the
    estimate scatters by ~5e-5 (rounding of the Hessian-vector products), but the solver
    stops about 100 times farther from the stationary point (gradient ~5e-4 to 3e-3),
    which moved the estimate by 2e-3 on the sphere -> bent cylinder pair: -1e-2 keeps a
    factor 5 above that, so that a float32 minimum is not called a saddle.
    """
    return -1e-3 if jnp.dtype(dtype) == jnp.float64 else -1e-2


# Lanczos steps of the saddle check (one Hessian-vector product each): enough to resolve
# a negative eigenvalue separated from a spectrum near 2 by O(1).
_LANCZOS_ITERATIONS = 24
# Trial lengths along the unit negative-curvature direction, in whitened coordinates: the
# straight line has scaled energy 1 and the Hessian is ~2 I, so a unit step changes the
# energy by O(1), as much as the whole bend from the straight line to a geodesic; the
# lengths go from a small move to most of that.
_ESCAPE_LENGTHS = (0.05, 0.1, 0.2, 0.4, 0.8)


def solve_path(
    metric: SplitMetric,
    f1: ArrayLike,
    f2: ArrayLike,
    init: ArrayLike,
    values: ArrayLike,
    dframe: ArrayLike,
    *,
    n_times: int,
    solver: str,
    max_steps: int | None,
    tol: float | Array,
    scheme: str,
    saddle_checks: int | None = None,
    frames: tuple | None = None,
    step_cap: Array | None = None,
):
    """One parametrized geodesic (traceable; the jitted entry point is ``_geodesic``).

    max_steps, tol, step_cap: as in :func:`minimize` (each solve of the saddle loop gets
    the same limits).

    frames: the ends' differentials (start, end), each (a1, a2) on the interior points,
    when they are not the central differences of f1 and f2 (shape_geodesic's chain rule).

    saddle_checks (static): None minimizes only (min_curvature is NaN; the inner solves
    of shape_geodesic). 0 also estimates the smallest Hessian eigenvalue of the scaled
    objective at the result (Lanczos). k >= 1 then, while that estimate is below
    ``saddle_threshold`` and fewer than k escapes were made, steps along its eigenvector
    (the lowest of f(x), f(x +- s v) over a few lengths s) and minimizes again: a start in
    a symmetric subspace keeps BFGS there, where it can stop at a saddle (math §9).
    """
    scaling = solver_scaling(metric, f1, f2, dframe, n_times, scheme, frames)
    straight = _straight_frames(f1, f2, n_times, frames)
    dtype = f1.dtype
    threshold = saddle_threshold(dtype)

    def objective(z: ArrayLike):
        frames = perturbed_frames(straight, scaling.coefficients(z), dframe)
        return frame_energy(metric, *frames, scheme) / scaling.energy_scale

    x0 = scaling.whitened(init)
    # A fixed random start: deterministic, and with probability one not inside the
    # symmetric subspace that the solver's iterates (and a structured vector) keep to.
    # Drawn by numpy at trace time (the shape is static): a constant, no RNG to compile.
    lanczos_start = jnp.asarray(np.random.default_rng(0).standard_normal(x0.shape), dtype)

    def checked_minimum(start: ArrayLike):
        """Minimize from start; the Lanczos estimate (value, vector) of the end's curvature."""
        found = minimize(
            objective, start, solver=solver, max_steps=max_steps, tol=tol, step_cap=step_cap
        )

        # H v = d/de grad(x + e v), the jvp of grad at each Lanczos step. Each step also
        # evaluates the gradient at x again (24 gradients, against the solve's hundreds),
        # but the program compiles smaller than jax.linearize's, which splits out and
        # stores the tangent part: the saddle check compiled in 3.2 s instead of 4.2
        # (12 x 25 cats, degree 5, N 5), the same Ritz value to 15 digits.
        def hessian_vector(v: ArrayLike):
            return jax.jvp(jax.grad(objective), (found.x,), (v,))[1]

        curvature, direction = lanczos_smallest(
            hessian_vector, lanczos_start, iterations=_LANCZOS_ITERATIONS
        )
        return found, curvature, direction

    def escape(x: ArrayLike, direction: ArrayLike):
        # The lowest of f(x) and f(x +- s v): never uphill.
        lengths = jnp.asarray(_ESCAPE_LENGTHS, dtype)
        trials = jnp.concatenate([jnp.zeros(1, dtype), lengths, -lengths])
        energies = jax.lax.map(lambda s: objective(x + s * direction), trials)
        return x + trials[jnp.argmin(energies)] * direction

    def solve_round(state: tuple):
        found, direction, _, steps, rounds = state
        # One loop for the first solve and the escapes, so that the solver and the
        # Hessian-vector product are compiled once.
        start = jax.lax.cond(rounds > 0, escape, lambda x, _: x, found.x, direction)
        found, curvature, direction = checked_minimum(start)
        return found, direction, curvature, steps + found.num_steps, rounds + 1

    def again(state: tuple):
        curvature, rounds = state[2], state[4]
        return (rounds == 0) | ((rounds <= saddle_checks) & (curvature < threshold))

    if saddle_checks is None:
        found = minimize(
            objective, x0, solver=solver, max_steps=max_steps, tol=tol, step_cap=step_cap
        )
        num_steps = found.num_steps
        curvature = jnp.full((), jnp.nan, dtype)
    elif saddle_checks == 0:
        found, curvature, _ = checked_minimum(x0)
        num_steps = found.num_steps
    else:
        zero, nothing = jnp.zeros((), jnp.int32), jnp.zeros((), dtype)
        # The loop's first round overwrites this placeholder (rounds == 0 always runs).
        empty = Minimum(x0, RESULTS.successful, zero, nothing, nothing)
        state = (empty, jnp.zeros_like(x0), nothing, zero, zero)
        found, _, curvature, num_steps, _ = jax.lax.while_loop(again, solve_round, state)
    # The value and gradient norm at the end are the solver's own evaluations there (a
    # new evaluation would compile the objective and its gradient once more).
    x, result = found.x, found.result
    converged = result == RESULTS.successful
    if saddle_checks:
        # Escapes were asked for: a saddle still at the end is a failed solve.
        at_saddle = converged & (curvature < threshold)
        converged = converged & ~at_saddle
        result = RESULTS.where(at_saddle, RESULTS.saddle_point, result)
    coefficients = scaling.coefficients(x)
    energy = found.value * scaling.energy_scale
    return GeodesicResult(
        path=path_from_coefficients(f1, f2, coefficients, values, n_times),
        distance=jnp.sqrt(energy),
        energy=energy,
        straight_energy=scaling.straight,
        coefficients=coefficients,
        num_steps=num_steps,
        converged=converged,
        result=result,
        grad_norm=found.grad_norm,
        min_curvature=curvature,
    )


# The step limit is a traced cap and tol a traced scalar (keywords step_cap and tol):
# the geodesics of one grid, basis and solver compile once, whatever limits they are
# given (the suite's solves with other limits each compiled anew, 11-34 s on 2 cores).
_geodesic = solver_jit(
    functools.partial(solve_path, max_steps=None),
    static_argnames=("n_times", "solver", "scheme", "saddle_checks"),
)


@functools.partial(jax.jit, static_argnames=("n_times", "scheme"))
def _evaluate(
    metric: SplitMetric,
    f1: ArrayLike,
    f2: ArrayLike,
    coefficients: ArrayLike,
    values: ArrayLike,
    dframe: ArrayLike,
    *,
    n_times: int,
    scheme: str,
):
    """The path, its energy and the straight line's energy at given coefficients."""
    straight = _straight_frames(f1, f2, n_times)
    energy = frame_energy(metric, *perturbed_frames(straight, coefficients, dframe), scheme)
    path = path_from_coefficients(f1, f2, coefficients, values, n_times)
    return path, energy, frame_energy(metric, *straight, scheme)


def _check_solve_options(
    n_times: object,
    solver: object,
    max_steps: object,
    tol: object,
    scheme: object,
    dtype: DTypeLike,
) -> tuple[int, int, float]:
    """Validate the inner solves' options; returns n_times, max_steps and tol (whose
    default depends on the dtype)."""
    check_choice("solver", solver, SOLVERS)
    check_choice("scheme", scheme, SCHEMES)
    n_times = check_int("n_times", n_times, 3)
    max_steps = check_int("max_steps", max_steps, 1)
    tol = default_tol(dtype) if tol is None else check_positive("tol", tol)
    return n_times, max_steps, tol


def _check_schedule(schedule: object, degree: int, m: int, n: int) -> list[tuple[int, ...]]:
    """The levels of a schedule as tuples of ints, each checked (InputError naming it)."""
    if isinstance(schedule, str) or not isinstance(schedule, Sequence):
        raise InputError(
            f"schedule must be a sequence of levels (degree, n_times[, m, n]); got {schedule!r}"
        )
    levels = []
    for k, level in enumerate(schedule):
        name = f"schedule[{k}]"
        if isinstance(level, str) or not isinstance(level, Sequence) or len(level) not in (2, 4):
            raise InputError(
                f"{name} must be (degree, n_times) or (degree, n_times, m, n); got {level!r}"
            )
        level_degree = check_int(f"{name} degree", level[0], 1)
        level_times = check_int(f"{name} n_times", level[1], 3)
        grid = tuple(check_int(f"{name} grid", v, 5) for v in level[2:])
        if grid:
            check_grid_shape((3, *grid), f"{name} grid")
        check_degree(level_degree, *(grid or (m, n)), f"{name} degree")
        if level_degree > degree:
            raise InputError(f"{name} degree {level_degree} is above the final degree {degree}")
        levels.append((level_degree, level_times, *grid))
    return levels


def geodesic(
    f1: Float[ArrayLike, "3 m n"],
    f2: Float[ArrayLike, "3 m n"],
    metric: SplitMetric,
    *,
    degree: int | FromOptions = FROM_OPTIONS,
    n_times: int | FromOptions = FROM_OPTIONS,
    solver: str | FromOptions = FROM_OPTIONS,
    max_steps: int | FromOptions = FROM_OPTIONS,
    tol: float | None | FromOptions = FROM_OPTIONS,
    init: Float[ArrayLike, "K L"] | None = None,
    scheme: str | FromOptions = FROM_OPTIONS,
    schedule: Sequence[tuple[int, ...]] = (),
    saddle_checks: int | None | FromOptions = FROM_OPTIONS,
    options: ShapeOptions | None = None,
) -> GeodesicResult:
    """Geodesic between two parametrized surfaces under a split metric (paper Algorithm 1).

    Minimizes the discrete energy (:ref:`math §4 <math-4>`) of
    f_k = (1 - t_k) f1 + t_k f2 + sum_j C[k, j] S_j over the coefficients C of the surface
    basis of the given degree (:ref:`math §5 <math-5>`), starting from the straight line (or
    ``init``), with gradients by autodiff through the energy.
    The whole solve is one jitted call; batch over targets with ``jax.vmap``.

    The path and solver settings (degree, n_times, solver, max_steps, tol, scheme,
    saddle_checks) are the fields of one record, :class:`ShapeOptions`, which
    :func:`shape_geodesic`, :func:`karcher_mean`, :func:`distance_matrix`, :func:`shoot` and
    :func:`parallel_transport` take too: give them as keywords or as ``options``, and a
    setting left out is the record's (its defaults below).

    Args:
        f1, f2: ``(3, m, n)`` immersions on the same grid.
        metric: the split metric coefficients.
        degree: highest spherical-harmonic degree of the perturbations, default 7
            (limit: min(m - 3, (n - 3) // 2)).
        n_times: N >= 3 time points, end points included; default 13.
        solver: ``"bfgs"`` (optimistix.BFGS, default) or ``"lbfgs"`` (jaxopt.LBFGS).
        max_steps: step limit, default 500; reaching it gives ``converged=False`` and a
            ConvergenceWarning.
        tol: converged means the 2-norm of the gradient of the scaled objective (energy /
            straight-line energy in whitened coefficients, Hessian ~2 I) is at most tol,
            for either solver; default (None) 1e-6 in float64, 3e-3 in float32
            (``default_tol()``).
        init: ``(N - 2, L)`` coefficients of an earlier solve (warm start); zeros by default.
        scheme: ``"midpoint"`` (default), ``"forward"`` (the paper's) or ``"central"``
            (see :func:`path_energy`). The forward scheme's discrete energy has minima
            that exploit large time steps, and its symmetric solutions are often saddles:
            sphere -> bent cylinder (13 x 25, degree 3, N = 5) ends at a saddle with
            E = 27.81 whose escape reaches 26.50, and that path refined to 2 and 4 times
            the time points has 28.83 and 28.85; the concentric spheres' straight line is
            a forward saddle (eigenvalue -3.9 at N = 7, 25 x 49) whose escape has 16.6
            against the closed form 25.0, and 60.1 when refined. The midpoint solutions
            are minima (eigenvalues 0.61 and 1.99) at 23.27 and the closed form, and
            move by 1.6 % and 0 under the same refinement.
        schedule: coarser levels ``(degree, n_times)`` or ``(degree, n_times, m, n)`` solved
            first, each warm-starting the next (multiresolution, paper remark after
            Table 3); a level with a grid solves on f1, f2 resampled bilinearly, e.g.
            ``[(4, 5, 25, 49), (7, 7)]``. Spherical-harmonic coefficients do not depend
            on the grid, so they carry over unchanged.
        saddle_checks: after the minimization, the smallest eigenvalue of the scaled
            objective's Hessian is estimated by 24 Lanczos steps (Hessian-vector products,
            reported as ``min_curvature``). With ``saddle_checks = k >= 1`` (default 1), an
            end point whose estimate is below ``saddle_threshold`` (-1e-3 in float64,
            -1e-2 in float32; the Hessian is ~2 I there) is left along its eigenvector and
            the path minimized again, at most k times; one still a saddle after that has
            ``converged=False``. 0 only reports the estimate; None skips it
            (``min_curvature`` is NaN): the 24 products cost about as much as 35 to 70
            BFGS steps at degree 7, N = 13 on 25 x 49 and 50 x 99. A start in a
            symmetric subspace (mirror-symmetric pairs) keeps BFGS in it, where it can
            stop at a saddle (:ref:`math §9 <math-9>`).
        options: a :class:`ShapeOptions` whose path and solver fields are the settings
            not given as keywords (None: its defaults). A keyword that disagrees with the
            record is an InputError.

    Returns:
        :class:`GeodesicResult`.

    Example:
        >>> import elastic_jax as ej
        >>> from elastic_jax import shapes
        >>> f1 = shapes.sample(shapes.bumpy, 13, 25)
        >>> f2 = shapes.sample(shapes.bent_cylinder, 13, 25)
        >>> res = ej.geodesic(f1, f2, ej.SplitMetric(1.0, 1.0, 0.1, 0.0), degree=3, n_times=5)
        >>> bool(res.energy < res.straight_energy)
        True
    """
    result, failure = _geodesic_and_failure(
        f1,
        f2,
        metric,
        degree=degree,
        n_times=n_times,
        solver=solver,
        max_steps=max_steps,
        tol=tol,
        init=init,
        scheme=scheme,
        schedule=schedule,
        saddle_checks=saddle_checks,
        options=options,
    )
    if failure is not None:
        warn_user(failure, ConvergenceWarning)
    return result


def solve_geodesic(f1: ArrayLike, f2: ArrayLike, metric: SplitMetric, **keywords) -> GeodesicResult:
    """:func:`geodesic` (the same keywords, checks and result) without its
    ConvergenceWarning: the package's own callers (collections, logs, coarse schedule
    levels) report each solve's status in their records instead."""
    return _geodesic_and_failure(f1, f2, metric, **keywords)[0]


def _geodesic_and_failure(
    f1: Float[ArrayLike, "3 m n"],
    f2: Float[ArrayLike, "3 m n"],
    metric: SplitMetric,
    *,
    degree: int | FromOptions = FROM_OPTIONS,
    n_times: int | FromOptions = FROM_OPTIONS,
    solver: str | FromOptions = FROM_OPTIONS,
    max_steps: int | FromOptions = FROM_OPTIONS,
    tol: float | None | FromOptions = FROM_OPTIONS,
    init: Float[ArrayLike, "K L"] | None = None,
    scheme: str | FromOptions = FROM_OPTIONS,
    schedule: Sequence[tuple[int, ...]] = (),
    saddle_checks: int | None | FromOptions = FROM_OPTIONS,
    options: ShapeOptions | None = None,
) -> tuple[GeodesicResult, str | None]:
    """:func:`geodesic`'s solve, and the ConvergenceWarning's text when it did not
    converge (None when it did, or when the result is traced)."""
    settings = settings_from(
        "geodesic",
        options,
        degree=degree,
        n_times=n_times,
        solver=solver,
        max_steps=max_steps,
        tol=tol,
        scheme=scheme,
        saddle_checks=saddle_checks,
    )
    degree, n_times, solver, max_steps, tol, scheme, saddle_checks = settings.values()
    f1, f2 = check_pair(f1, f2)
    m, n = f1.shape[-2:]
    degree = check_degree(degree, m, n)
    n_times, max_steps, tol = _check_solve_options(
        n_times, solver, max_steps, tol, scheme, f1.dtype
    )
    if saddle_checks is not None:
        saddle_checks = check_int("saddle_checks", saddle_checks, 0)  # None: no check
    levels = _check_schedule(schedule, degree, m, n)
    size = 3 * ((degree + 1) ** 2 - 1)
    # Solve in units of the surfaces' size (see _geometry/units.py): float32 works at any scale.
    units, (g1, g2) = in_units(f1, f2)
    if init is None:
        init = np.zeros((n_times - 2, size), f1.dtype)
        for level_degree, level_times, *grid in levels:
            h1, h2 = (g1, g2) if not grid else (resample(g, *grid) for g in (g1, g2))
            coarse = solve_geodesic(
                h1,
                h2,
                metric,
                degree=level_degree,
                n_times=level_times,
                solver=solver,
                max_steps=max_steps,
                tol=tol,
                scheme=scheme,
                saddle_checks=saddle_checks,
            )
            init = upsample_coefficients(coarse.coefficients, level_degree, degree, n_times)
    else:
        if levels:
            raise InputError("give either init or schedule, not both")
        init = real_array(init, "init").astype(f1.dtype)
        if init.shape != (n_times - 2, size):
            raise InputError(
                f"init must have shape (n_times - 2, L) = {(n_times - 2, size)} "
                f"for degree={degree}; got {init.shape}"
            )
        check_finite(init, "init")
        init = init / units.scale
    values, dframe = (jnp.asarray(a, f1.dtype) for a in basis_np(m, n, degree))
    # The solve runs on constants: its loops are never differentiated (reverse mode cannot
    # go through a while loop). The energy is then evaluated again, differentiably, at the
    # optimal coefficients C*: there dE/dC = 0, so its derivative in f1, f2 and the metric
    # is the derivative of the minimal energy (envelope theorem); away from an optimum it
    # is the derivative at fixed C.
    solved = _geodesic(
        constant(metric),
        jax.lax.stop_gradient(g1),
        jax.lax.stop_gradient(g2),
        jax.lax.stop_gradient(init),
        values,
        dframe,
        step_cap=jnp.asarray(max_steps, jnp.int32),
        tol=jnp.asarray(tol, f1.dtype),
        n_times=n_times,
        solver=solver,
        scheme=scheme,
        saddle_checks=saddle_checks,
    )
    result = _finish(
        metric, g1, g2, f1, f2, solved, units, values, dframe, n_times=n_times, scheme=scheme
    )
    failure = None
    if is_concrete(result.converged, result.num_steps) and not bool(result.converged):
        if RESULTS.name(result.result) == "saddle_point":
            reason = f"and {saddle_checks} saddle escapes: {result.message}"
        else:
            reason = f"without meeting tol={tol:g}: {result.message}"
        failure = f"geodesic: {solver} stopped after {int(result.num_steps)} steps {reason}"
    return result, failure


@functools.partial(jax.jit, static_argnames=("n_times", "scheme"))
def _finish(
    metric: SplitMetric,
    g1: ArrayLike,
    g2: ArrayLike,
    f1: ArrayLike,
    f2: ArrayLike,
    solved: GeodesicResult,
    units: Units,
    values: ArrayLike,
    dframe: ArrayLike,
    *,
    n_times: int,
    scheme: str,
):
    """The result in the user's units from the solve's: the path and its energies evaluated
    again at the optimal coefficients (differentiably, see geodesic), then the units
    restored. One compiled program: op by op, a first call would compile each operation
    alone."""
    coefficients = jax.lax.stop_gradient(solved.coefficients)
    path, energy, straight = _evaluate(
        metric, g1, g2, coefficients, values, dframe, n_times=n_times, scheme=scheme
    )
    unit_result = solved._replace(
        path=path, energy=energy, distance=safe_sqrt(energy), straight_energy=straight
    )
    return _restore_units(unit_result, units, f1, f2)


def _restore_units(
    result: GeodesicResult, units: Units, f1: ArrayLike, f2: ArrayLike
) -> GeodesicResult:
    """A result solved in ``units`` expressed in the user's units again (the ends exact)."""
    s = units.scale
    path = units.restore(result.path)
    path = path.at[0].set(f1).at[-1].set(f2)
    return result._replace(
        path=path,
        distance=result.distance * s,
        energy=result.energy * s**2,
        straight_energy=result.straight_energy * s**2,
        coefficients=result.coefficients * s,
    )


def upsample_coefficients(
    coefficients: Float[ArrayLike, "K0 L0"], degree: int, new_degree: int, new_n_times: int
) -> Float[Array, "K1 L1"]:
    """Lift a coarse solution to a finer (degree, n_times) as an initial guess.

    Coefficients of spherical harmonics do not depend on the grid, so a change of grid
    needs nothing; a higher degree pads with zeros; more time points interpolate the
    perturbation linearly in time (it vanishes at both ends).

    Args:
        coefficients: ``(N0 - 2, 3 K0)`` from a solve at ``degree``.
        degree, new_degree: old and new degree (new >= old).
        new_n_times: N1 >= 3.

    Returns:
        ``(N1 - 2, 3 K1)``, K = (degree + 1)^2 - 1.
    """
    c = jnp.asarray(coefficients)
    k0, k1 = (degree + 1) ** 2 - 1, (new_degree + 1) ** 2 - 1
    if new_degree < degree:
        raise InputError(f"new_degree={new_degree} is below degree={degree}")
    if c.shape[-1] != 3 * k0:
        raise InputError(f"coefficients of degree {degree} have {3 * k0} columns; got {c.shape}")
    c = c.reshape(c.shape[0], 3, k0)
    c = jnp.pad(c, ((0, 0), (0, 0), (0, k1 - k0)))
    zeros = jnp.zeros((1, 3, k1), c.dtype)
    full = jnp.concatenate([zeros, c, zeros]).reshape(c.shape[0] + 2, -1)
    t_old = jnp.linspace(0.0, 1.0, full.shape[0], dtype=c.dtype)
    t_new = jnp.linspace(0.0, 1.0, new_n_times, dtype=c.dtype)[1:-1]
    lifted = jax.vmap(lambda column: jnp.interp(t_new, t_old, column), in_axes=1, out_axes=1)(full)
    return lifted.reshape(new_n_times - 2, 3 * k1)
