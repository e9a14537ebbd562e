"""Geodesic shooting: the discrete exponential map of the path energy, and its inverse.

The paper poses the initial value problem next to the boundary value one (Introduction;
Appendix, the geodesic equation). Discretely (Rumpf and Wirth's discrete exponential map)
a geodesic is a path whose energy is stationary in every interior node: for the midpoint
and forward schemes (math §4) the energy couples f_k only to f_{k-1} and f_{k+1}, so

    d/d f_k [ G_{b_{k-1}}(T (f_k - f_{k-1})) + G_{b_k}(T (f_{k+1} - f_k)) ] = 0

determines f_{k+1} from f_{k-1} and f_k, one node at a time. The unknown is taken in the
geodesic solver's own space, f_{k+1} = 2 f_k - f_{k-1} + sum_j c_j S_j with S_j the
surface basis of :func:`surface_basis` (degree 1..d), and the equation is projected on
the same basis: B^T r_k(c) = 0, L = 3((d + 1)^2 - 1) equations in L unknowns, solved by
optimistix's Newton method. A path from :func:`geodesic` (same degree, N and scheme) is
stationary in exactly these projected equations, so shooting its first step reproduces it.

The central scheme couples f_k to f_{k-2} .. f_{k+2}; its recursion has a parasitic
odd-even mode, and shooting refuses it.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.typing import DTypeLike
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._checks import check_choice, check_finite, check_int, check_positive, is_concrete, real_array
from .._errors import ConvergenceWarning, InputError, warn_user
from .._geometry.bases import basis_np
from .._geometry.differential import interior_frame
from .._geometry.energy import frame_energy, frame_speeds2
from .._geometry.harmonics import check_degree
from .._geometry.metric import SplitMetric
from .._geometry.numerics import safe_sqrt
from .._geometry.units import in_units
from .._geometry.validation import as_surface
from .._options import (
    FROM_OPTIONS,
    SHOOTING_SCHEMES,
    FromOptions,
    ShapeOptions,
    settings_from,
)
from .._results import RESULTS, first_failure, status_record, unsolved_message
from .._runtime.cache import solver_jit


@status_record
class ShootingResult(NamedTuple):
    """A geodesic shot from a surface with an initial velocity; a pytree (vmappable).

    Attributes:
        path: ``(N, 3, m, n)`` f_0 = f, f_1 = f + v / T, then one node per Newton solve;
            NaN from the first node whose solve failed on (see ``n_valid``).
        endpoint: ``(3, m, n)`` f_{N-1} = exp_f(v).
        velocity: ``(3, m, n)`` T (f_{N-1} - f_{N-2}), the final velocity.
        speeds: ``(N - 1,)`` sqrt(G_b(T (f_{k+1} - f_k))) per step, b the scheme's base
            point; constant along an exact geodesic.
        residuals: ``(N - 2,)`` per step, the 2-norm of J0^-1 r(c) at the solution (r the
            projected equation, J0 its Jacobian at the step's start): the size of one
            more Newton step, in coefficients of f's units; 0 on an exact solution; NaN
            for the steps after a failed one (not attempted).
        coefficients: ``(N - 2, L)`` the c of each step.
        newton_steps: ``(N - 2,)`` iterations per step, Newton's and a rescue's (0: not
            attempted).
        n_valid: ``()`` how many leading nodes of ``path`` are solutions: N when converged.
        converged: ``()`` every step's Newton solve met its tolerance.
        result: ``successful``, or the first failed step's Newton result
            (``elastic_jax.RESULTS``, optimistix's code).
        num_steps: ``()`` Newton iterations over all steps.
    """

    path: Float[Array, "N 3 m n"]
    endpoint: Float[Array, "3 m n"]
    velocity: Float[Array, "3 m n"]
    speeds: Float[Array, " T"]
    residuals: Float[Array, " K"]
    coefficients: Float[Array, "K L"]
    newton_steps: Int[Array, " K"]
    n_valid: Int[Array, ""]
    converged: Bool[Array, ""]
    result: RESULTS
    num_steps: Int[Array, ""]

    def _explain(self, words: str) -> str:
        last = self.path.shape[-4] - 1
        return unsolved_message(self, "node", int(self.n_valid), last, words)


def default_newton_tol(dtype: DTypeLike) -> float:
    """Tolerance of each step's Newton solve: on the relative residual and on the change of
    the coefficients (in units of the surface's size). Newton converges quadratically, so
    the result is near rounding level: 1e-10 in float64, 1e-4 in float32."""
    return 1e-10 if jnp.dtype(dtype) == jnp.float64 else 1e-4


def frames_of(coefficients: ArrayLike, dframe: ArrayLike, shape: tuple[int, ...]):
    """The interior frames of sum_j c_j S_j, from the basis' precomputed differentials."""
    k = dframe.shape[0]
    points = dframe.shape[1] // 2
    pert = coefficients.reshape(3, k) @ dframe
    return pert[:, :points].reshape(shape), pert[:, points:].reshape(shape)


def _frames_plus(frames: tuple, coefficients: ArrayLike, dframe: ArrayLike):
    """frames + the frames of sum_j c_j S_j."""
    shape = frames[0].shape
    return tuple(x + y for x, y in zip(frames, frames_of(coefficients, dframe, shape), strict=True))


def _energy_of(metric: SplitMetric, scheme: str, *frames):
    """The energy of the short path through the given frames (the factor from its own T
    is common to all its terms and drops out of a stationarity equation)."""
    a1 = jnp.stack([a[0] for a in frames])
    a2 = jnp.stack([a[1] for a in frames])
    return frame_energy(metric, a1, a2, scheme)


def node_solve(
    metric: SplitMetric,
    scheme: str,
    f_a: ArrayLike,
    f_b: ArrayLike,
    c_guess: ArrayLike,
    values: ArrayLike,
    dframe: ArrayLike,
    *,
    unknown: str,
    tol: ArrayLike,
    max_newton: int,
    frames: tuple | None = None,
):
    """One node of a discrete geodesic f_a, f_mid, f_b by Newton's method on the energy's
    Euler-Lagrange equation in the middle node, projected on the surface basis.

    unknown="next": f_a, f_mid = f_b are known and the unknown is the third node,
    2 f_b - f_a + sum_j c_j S_j (a shooting step). unknown="middle": the ends are known and
    the unknown is the middle, (f_a + f_b) / 2 + sum_j c_j S_j (the discrete midpoint).
    ``frames``: the known nodes' differentials (a_a, a_b), each (a1, a2); default their
    central differences. Returns (the unknown node, c, the residual as a Newton step's
    size, Newton steps, the result code).
    """
    import optimistix as optx

    m, n = f_a.shape[-2:]
    a_a, a_b = (interior_frame(f_a), interior_frame(f_b)) if frames is None else frames
    zero = jnp.zeros(c_guess.shape, f_a.dtype)
    if unknown == "next":
        base = 2.0 * f_b - f_a
        a_base = tuple(2.0 * x - y for x, y in zip(a_b, a_a, strict=True))

        def frames(c: ArrayLike, d: ArrayLike):  # (first, middle, last)
            return a_a, _frames_plus(a_b, d, dframe), _frames_plus(a_base, c, dframe)

    else:
        base = 0.5 * (f_a + f_b)
        a_base = tuple(0.5 * (x + y) for x, y in zip(a_a, a_b, strict=True))

        def frames(c: ArrayLike, d: ArrayLike):
            return a_a, _frames_plus(a_base, c + d, dframe), a_b

    def gradient(c: ArrayLike):
        return jax.grad(lambda d: _energy_of(metric, scheme, *frames(c, d)))(zero)

    # The equation is solved as J(c0)^-1 g(c) = 0, J(c0) its Jacobian at Newton's start:
    # Newton's iterates are the same (it is affine invariant), and the residual is then
    # the size of a Newton step, in the surface's units, whatever the scale of g: a
    # ladder's rung along the path has nearly coinciding known nodes and a vanishing g.
    solver = optx.Newton(rtol=tol, atol=tol)
    factor = jax.scipy.linalg.lu_factor(jax.jacfwd(gradient)(c_guess))

    def residual(c: ArrayLike, _: None):
        return jax.scipy.linalg.lu_solve(factor, gradient(c))

    def newton(c0: ArrayLike, solve: Callable, method=solver):
        sol = optx.root_find(solve, method, c0, max_steps=max_newton, throw=False)
        return (
            sol.value,
            RESULTS.promote(sol.result),
            jnp.asarray(sol.stats["num_steps"], jnp.int32),
        )

    first = newton(c_guess, residual)

    def followed(_: None):
        # Newton from the guess fails where a step's cells nearly collapse: on a real
        # horse's last node at 25 x 49 its first step was 4x too long and 67 degrees off
        # a root 0.4 guess-lengths away. The root is then followed from the guess,
        # which solves g(c) = g(c_guess), along g(c) = (1 - s) g(c_guess) to s = 1: the
        # root continuously connected to the extrapolation (there, one 4 % of the
        # correction's length from the boundary value solve's). No gradient flows
        # through the following; the Newton solve that ends it carries the implicit
        # adjoint.
        start = jax.lax.stop_gradient(c_guess)
        far, reached, follow_steps = _follow_root(
            gradient, start, jax.lax.stop_gradient(gradient(start)), newton
        )
        c, result, steps = _newton_from(gradient, jax.lax.stop_gradient(far), 0.0, newton)
        result = RESULTS.where(reached, result, first[1])
        return c, result, steps + follow_steps

    def rescued(_: None):
        # A trust region first: on the resolved cats' log (49 x 97) the last node's root
        # lies 0.47 guess-lengths from the guess, and Newton's undamped steps wander
        # there (16 iterations on the log's own nodes, none converging within 200 on
        # nodes 1e-5 off them), where optimistix's dogleg reaches it in 11-12. The
        # continuation is the last resort.
        second = newton(c_guess, residual, optx.Dogleg(rtol=tol, atol=tol))
        c, result, steps = jax.lax.cond(
            second[1] == RESULTS.successful, lambda _: second, followed, None
        )
        steps = steps + jnp.where(second[1] == RESULTS.successful, 0, second[2])
        return c, result, steps + first[2]

    c, result, steps = jax.lax.cond(first[1] == RESULTS.successful, lambda _: first, rescued, None)
    node = base + (c.reshape(3, -1) @ values).reshape(3, m, n)
    return node, c, jnp.linalg.norm(residual(c, None)), steps, result


def _newton_from(gradient: Callable, c0: ArrayLike, shift: ArrayLike, newton: Callable):
    """``newton`` on J(c0)^-1 (g(c) - shift) = 0 from c0 (J the Jacobian of g)."""
    factor = jax.scipy.linalg.lu_factor(jax.jacfwd(gradient)(c0))
    return newton(c0, lambda c, _: jax.scipy.linalg.lu_solve(factor, gradient(c) - shift))


def _follow_root(
    gradient: Callable,
    start: ArrayLike,
    g0: ArrayLike,
    newton: Callable,
    *,
    rounds: int = 48,
    smallest: float = 2.0**-12,
):
    """Natural-parameter continuation of the root of g(c) = (1 - s) g0 from (start, 0) to
    s = 1 (g(start) = g0): Newton from the last root at s + ds, ds doubling after a
    solve and halving after a failure (at most 1/4, at least ``smallest``).
    Returns (c, whether s reached 1, Newton iterations)."""
    dtype = start.dtype

    def keep_going(state: tuple):
        _, s, ds, k, _ = state
        return (s < 1) & (ds >= smallest) & (k < rounds)

    def step(state: tuple):
        c, s, ds, k, steps = state
        trial = jnp.minimum(s + ds, 1.0)
        c_new, result, k_new = _newton_from(gradient, c, (1 - trial) * g0, newton)
        ok = (result == RESULTS.successful) & jnp.all(jnp.isfinite(c_new))
        return (
            jnp.where(ok, c_new, c),
            jnp.where(ok, trial, s),
            jnp.where(ok, jnp.minimum(2 * ds, 0.25), ds / 2),
            k + 1,
            steps + k_new,
        )

    zero = jnp.zeros((), jnp.int32)
    state = (start, jnp.zeros((), dtype), jnp.asarray(0.25, dtype), zero, zero)
    c, s, _, _, steps = jax.lax.while_loop(keep_going, step, state)
    return c, s >= 1, steps


def _shoot(
    metric: SplitMetric,
    f: ArrayLike,
    v: ArrayLike,
    a_f: tuple,
    a_v: tuple,
    values: ArrayLike,
    dframe: ArrayLike,
    *,
    n_times: int,
    scheme: str,
    tol: ArrayLike,
    max_newton: int,
):
    """Traceable shooting in the units of f (the jitted entry point is ``_shoot_jit``).

    The nodes' differentials travel with them: a_{k+1} = 2 a_k - a_{k-1} + sum_j c_j dS_j
    from a_0 = a_f and a_1 = a_f + a_v / T, the same linear recursion as the nodes, so
    that a path whose ends' differentials are not their grid differences (a registered
    geodesic under the chain rule) is shot back node by node from its own frames.

    The recursion stops at the first step whose Newton solve fails: that node and every
    later one are NaN (their steps report no Newton iterations and a NaN residual). A
    node that does not solve its equation is not on the geodesic, and every later node
    is built on it: at 50 x 99 on the cats the shot path went on from a failed node at
    speed 5462 instead of 2.3, each later node solved to 1e-13 on a path that had left.
    """
    t = n_times - 1
    size = dframe.shape[0] * 3
    dtype = f.dtype

    def step(carry: tuple, _: None):
        (f_prev, a_prev), (f_here, a_here), c_guess, alive = carry

        def solve(_: None):
            f_next, c, residual, steps, result = node_solve(
                metric,
                scheme,
                f_prev,
                f_here,
                c_guess,
                values,
                dframe,
                unknown="next",
                tol=tol,
                max_newton=max_newton,
                frames=(a_prev, a_here),
            )
            return f_next, c, residual, jnp.asarray(steps, jnp.int32), result

        def skip(_: None):
            nan = jnp.asarray(jnp.nan, dtype)
            zero = jnp.zeros((), jnp.int32)
            return jnp.full_like(f_here, nan), c_guess, nan, zero, RESULTS.successful

        f_next, c, residual, steps, result = jax.lax.cond(alive, solve, skip, None)
        ok = alive & (result == RESULTS.successful)
        base = tuple(2.0 * x - y for x, y in zip(a_here, a_prev, strict=True))
        next_node = jax.tree_util.tree_map(
            lambda x: jnp.where(ok, x, jnp.nan), (f_next, _frames_plus(base, c, dframe))
        )
        # After a failure the known pair stays the last solved one (the later steps skip).
        kept = jax.tree_util.tree_map(
            functools.partial(jnp.where, ok),
            ((f_here, a_here), next_node, c),
            ((f_prev, a_prev), (f_here, a_here), c_guess),
        )
        return (*kept, ok), (next_node, (c, residual, steps, ok, result))

    first = (f + v / t, tuple(x + y / t for x, y in zip(a_f, a_v, strict=True)))
    carry = ((f, a_f), first, jnp.zeros(size, dtype), jnp.asarray(True))
    _, ((nodes, node_frames), (coefficients, residuals, newton_steps, ok, results)) = jax.lax.scan(
        step, carry, None, length=n_times - 2
    )
    path = jnp.concatenate([f[None], first[0][None], nodes])
    known = zip(a_f, first[1], node_frames, strict=True)
    frames = tuple(jnp.concatenate([a[None], b[None], c]) for a, b, c in known)
    speeds2, _ = frame_speeds2(metric, *frames, scheme)
    speeds = safe_sqrt(speeds2)
    n_valid = 2 + jnp.sum(ok.astype(jnp.int32))
    result = first_failure(results, ok)
    return path, speeds, residuals, coefficients, newton_steps, n_valid, result


# tol is traced (a scalar array): shots that differ only in it share one program.
_shoot_jit = solver_jit(_shoot, static_argnames=("n_times", "scheme", "max_newton"))


def check_scheme(scheme: str) -> None:
    if scheme == "central":
        raise InputError(
            'scheme="central" cannot be shot: its energy couples each node to two neighbours '
            "on each side, and the recursion has a parasitic odd-even mode; use "
            '"midpoint" (default) or "forward"'
        )
    check_choice("scheme", scheme, SHOOTING_SCHEMES)


def shoot(
    f: Float[ArrayLike, "3 m n"],
    v: Float[ArrayLike, "3 m n"],
    metric: SplitMetric,
    *,
    n_times: int | FromOptions = FROM_OPTIONS,
    degree: int | FromOptions = FROM_OPTIONS,
    scheme: str | FromOptions = FROM_OPTIONS,
    tol: float | None = None,
    max_newton: int = 20,
    options: ShapeOptions | None = None,
    frames: Float[ArrayLike, "2 2 3 m-2 n-1"] | None = None,
) -> ShootingResult:
    """Shoot the discrete geodesic from f with initial velocity v (the discrete exp map).

    f_0 = f, f_1 = f + v / T (T = N - 1), then for k = 1 .. N - 2 the node f_{k+1} =
    2 f_k - f_{k-1} + sum_j c_j S_j whose c makes the path energy stationary in f_k,
    projected on the surface basis of ``degree`` (module docstring; the Euler-Lagrange
    equation of :ref:`math §4 <math-4>`'s energy, paper Appendix). The scheme is first order in 1/N
    (the start f + v / T); a path of :func:`geodesic` with the same degree, N and scheme
    is reproduced node by node from its T (f_1 - f_0) (see :func:`log`).

    Args:
        f: ``(3, m, n)`` the starting immersion.
        v: ``(3, m, n)`` the initial velocity (a vector field on the grid).
        metric: the split metric coefficients.
        n_times: N >= 3 time points, f and the endpoint included; default 13.
        degree: the surface basis' degree, default 7 (limit: min(m - 3, (n - 3) // 2)).
        scheme: ``"midpoint"`` (default) or ``"forward"``; ``"central"`` is refused.
        tol: each Newton solve's tolerance (``default_newton_tol()``); a limit of
            shooting's own, not the record's minimization tol.
        max_newton: iterations of each Newton solve, and of the dogleg's rescue
            (shooting's own limit).
        options: a :class:`ShapeOptions` whose n_times, degree and scheme are the ones
            not given as keywords (None: its defaults), so that a path shot from a
            :func:`geodesic` or :func:`log` uses that solve's record.
        frames: ``(2, 2, 3, m - 2, n - 1)`` the differentials of f and of v on the
            interior points (``frames[i, j]`` the j-th column of the i-th;
            :attr:`LogResult.frames`). None (default): their central differences on the
            grid. A registered geodesic under ``differential="chain"`` takes its ends'
            differentials by the chain rule, not from the grid (math §2); shooting its
            log back reproduces its path only from those (the nodes' differentials
            follow the nodes' own recursion).

    A step whose Newton solve fails from the extrapolated guess is retried from the
    guess by optimistix's dogleg trust region (at most ``max_newton`` iterations), then
    by continuation: the root of the node's equation is followed from the guess (module
    ``_follow_root``; docs/guides/shooting.md), at the cost of more iterations, all
    counted in ``newton_steps``.

    Returns:
        :class:`ShootingResult`; a ConvergenceWarning when a step's solve failed, also
        by the dogleg and by continuation. The recursion stops there: that node and the
        later ones are NaN and ``n_valid`` counts the solved nodes. Vmappable over f and v;
        differentiable (optimistix's implicit adjoint per step).
    """
    settings = settings_from("shoot", options, n_times=n_times, degree=degree, scheme=scheme)
    n_times, degree, scheme = settings["n_times"], settings["degree"], settings["scheme"]
    check_scheme(scheme)
    f = as_surface(f, "f")
    if f.ndim != 3:
        raise InputError(f"f must be one surface (3, m, n); got {f.shape}. Batch with jax.vmap.")
    v = as_velocity(v, f)
    m, n = f.shape[-2:]
    degree = check_degree(degree, m, n)
    n_times = check_int("n_times", n_times, 3)
    max_newton = check_int("max_newton", max_newton, 1)
    tol = default_newton_tol(f.dtype) if tol is None else check_positive("tol", tol)
    values, dframe = (jnp.asarray(a, f.dtype) for a in basis_np(m, n, degree))
    a_f, a_v = _checked_frames(frames, f, v)
    # In units of f's size (see _geometry/units.py): the energy is homogeneous, the path scales.
    units, (g,) = in_units(f)
    s = units.scale
    path, speeds, residuals, coefficients, newton_steps, n_valid, code = _shoot_jit(
        metric,
        g,
        v / s,
        tuple(a / s for a in a_f),
        tuple(a / s for a in a_v),
        values,
        dframe,
        n_times=n_times,
        scheme=scheme,
        tol=jnp.asarray(tol, g.dtype),
        max_newton=max_newton,
    )
    path = units.restore(path).at[0].set(f)
    t = n_times - 1
    converged = n_valid == n_times
    result = ShootingResult(
        path=path,
        endpoint=path[-1],
        velocity=t * (path[-1] - path[-2]),
        speeds=speeds * s,
        residuals=residuals,
        coefficients=coefficients * s,
        newton_steps=newton_steps,
        n_valid=n_valid,
        converged=converged,
        result=code,
        num_steps=jnp.sum(newton_steps),
    )
    if is_concrete(converged) and not bool(converged):
        warn_user(_failure_message(result, tol, max_newton), ConvergenceWarning)
    return result


def _checked_frames(frames: ArrayLike | None, f: ArrayLike, v: ArrayLike):
    """(f's frame, v's frame), each (a1, a2): ``frames`` checked, or the central
    differences of f and v."""
    frames = checked_frames(frames, jnp.stack([f, v]), "frames")
    return (frames[0, 0], frames[0, 1]), (frames[1, 0], frames[1, 1])


def checked_frames(frames: ArrayLike | None, x: ArrayLike, name: str):
    """The differentials of the fields x (``(..., 3, m, n)``) on the interior points as one
    array ``(..., 2, 3, m - 2, n - 1)`` (``[..., j]`` the j-th column): ``frames``
    checked, or x's central differences when it is None."""
    m, n = x.shape[-2:]
    if frames is None:
        return jnp.stack(interior_frame(x), axis=x.ndim - 3)
    frames = real_array(frames, name).astype(x.dtype)
    want = (*x.shape[:-3], 2, 3, m - 2, n - 1)
    if frames.shape != want:
        raise InputError(
            f"{name} must hold differentials on the interior points, shape {want}; "
            f"got {frames.shape}"
        )
    check_finite(frames, name)
    return frames


def _failure_message(result: ShootingResult, tol: float, max_newton: int) -> str:
    """Which node failed and how far its Newton solve got."""
    k = int(result.n_valid)  # the first node that is not a solution
    last = result.path.shape[0] - 1
    residual = float(result.residuals[k - 2])
    return (
        f"shoot: node {k} of {last} did not solve (Newton and the dogleg: {max_newton} "
        f"iterations each, then continuation; step still {residual:.3g} in units of f's "
        f"size, tol={tol:g}); nodes {k}..{last} are "
        f"NaN, path[:{k}] is the solved part. Measured on real surfaces: Newton fails at a "
        "step that makes a grid cell's area at the step's midpoint fall well below its "
        "area at the nodes (docs/guides/limitations.md); more time points do not avoid it."
    )


def as_velocity(v: ArrayLike, f: Array, name: str = "v") -> Array:
    """v as a finite array of f's dtype and shape (a tangent vector: no immersion check)."""
    v = real_array(v, name)
    check_finite(v, name)
    if v.shape != f.shape:
        raise InputError(f"{name} must have the shape of its surface {f.shape}; got {v.shape}")
    return v.astype(f.dtype)


def exp(
    f: Float[ArrayLike, "3 m n"], v: Float[ArrayLike, "3 m n"], metric: SplitMetric, **options
) -> Float[Array, "3 m n"]:
    """The discrete exponential map: :func:`shoot`'s endpoint (same arguments)."""
    return shoot(f, v, metric, **options).endpoint
