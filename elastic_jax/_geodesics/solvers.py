"""Minimizers from optimistix and jaxopt behind one small interface (no own quasi-Newton)."""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, ArrayLike, PyTree

from .._checks import check_choice
from .._options import SOLVERS
from .._results import RESULTS


class Minimum(NamedTuple):
    """What a solve returns: the minimizer, its result code, step count, and the gradient
    norm and value there (the solver's own evaluations); for bfgs also its inverse
    Hessian approximation at the end (a lineax operator; None for lbfgs), which a later
    solve of a nearby problem may start from (``inverse0``)."""

    x: Array
    result: RESULTS
    num_steps: Array
    grad_norm: Array
    value: Array
    inverse: object = None


def _jaxopt():
    # Imported on first use: only solver="lbfgs" needs it (it warns on import that it is
    # no longer maintained; the package's design names it as the L-BFGS choice).
    import jaxopt

    return jaxopt


def check_solver(solver: str) -> None:
    check_choice("solver", solver, SOLVERS)


class _GradientBFGS(optx.BFGS):
    """optimistix's BFGS, stopped by the gradient norm: ``|grad f(y)|_2 <= gtol`` at an
    accepted point (optimistix's own rule, on changes of y and f, is kept at rounding
    level, rtol = atol = 100 eps, so that a solve that cannot move stops there)."""

    gtol: float | Array  # traced when one compiled solve serves several tolerances
    # The inverse Hessian approximation to start from (another solve's ``Minimum.inverse``
    # on variables of the same structure); None: optimistix's identity.
    inverse0: object

    def __init__(self, gtol: float | Array, rounding: float, inverse0: object = None):
        super().__init__(rtol=rounding, atol=rounding)
        self.gtol = gtol
        self.inverse0 = inverse0

    def init_hessian(self, y: PyTree, f: Array, grad: PyTree):
        f_info, update_state = super().init_hessian(y, f, grad)
        if self.inverse0 is None:
            return f_info, update_state
        return optx.FunctionInfo.EvalGradHessianInv(f, grad, self.inverse0), update_state

    def terminate(
        self, fn: Callable, y: PyTree, args: PyTree, options: dict, state: PyTree, tags: frozenset
    ):
        # Before the first accepted step f_info holds no gradient yet.
        small = optx.two_norm(state.f_info.grad) <= self.gtol
        return (~state.first_step) & (small | state.terminate), state.result


class _Capped(optx.AbstractMinimiser):
    """A minimiser stopped after ``args`` steps (the solve's args carry the cap): a traced
    cap, at most the static ``max_steps`` (None: no bound but the cap), so that one
    compiled solve serves solves of different lengths. It stops exactly where a solve with
    ``max_steps = cap`` stops (the same iterates, result code and step count)."""

    inner: optx.AbstractMinimiser
    rtol: float
    atol: float
    norm: Callable

    def __init__(self, inner: optx.AbstractMinimiser):
        self.inner = inner
        self.rtol, self.atol, self.norm = inner.rtol, inner.atol, inner.norm

    def init(
        self,
        fn: Callable,
        y: PyTree,
        args: PyTree,
        options: dict,
        f_struct: jax.ShapeDtypeStruct,
        aux_struct: PyTree,
        tags: frozenset,
    ):
        state = self.inner.init(fn, y, args, options, f_struct, aux_struct, tags)
        return state, jnp.zeros((), jnp.int32)

    def step(
        self, fn: Callable, y: PyTree, args: PyTree, options: dict, state: tuple, tags: frozenset
    ):
        y, inner, aux = self.inner.step(fn, y, args, options, state[0], tags)
        return y, (inner, state[1] + 1), aux

    def terminate(
        self, fn: Callable, y: PyTree, args: PyTree, options: dict, state: tuple, tags: frozenset
    ):
        done, result = self.inner.terminate(fn, y, args, options, state[0], tags)
        capped = (state[1] >= args) & ~done
        result = optx.RESULTS.where(capped, optx.RESULTS.nonlinear_max_steps_reached, result)
        return done | capped, result

    def postprocess(
        self,
        fn: Callable,
        y: PyTree,
        aux: PyTree,
        args: PyTree,
        options: dict,
        state: tuple,
        tags: frozenset,
        result: optx.RESULTS,
    ):
        return self.inner.postprocess(fn, y, aux, args, options, state[0], tags, result)


def minimize(
    fun: Callable[[Array], Array],
    x0: PyTree,
    *,
    solver: str,
    max_steps: int | None,
    tol: float | Array,
    step_cap: Array | None = None,
    inverse0: object = None,
    keep_inverse: bool = False,
) -> Minimum:
    """Minimize a smooth scalar function of one array (traceable, vmappable).

    ``tol`` means the same for both solvers: the solve has converged when the 2-norm of
    the gradient of ``fun`` at the returned point is at most tol (the caller scales x
    and the value to O(1), so that this is a relative accuracy; near a minimum with
    Hessian ~2 I the value is then within ~tol^2 / 4 of the minimum). bfgs:
    optimistix's BFGS (dense inverse Hessian, suits up to a few thousand variables)
    stopped by that rule; lbfgs: ``jaxopt.LBFGS(tol=tol)``, whose own rule it is.
    Neither raises: a solve that hits ``max_steps`` returns
    ``RESULTS.nonlinear_max_steps_reached`` and one that stops moving before meeting tol
    (rounding) ``RESULTS.stalled``. A start that already meets tol stops after the
    solver's first step, which evaluates it (``num_steps`` 1, x unchanged for bfgs). The
    returned gradient norm is the solver's own, at the returned point.

    ``step_cap`` (an int array, at most ``max_steps``; None: ``max_steps``) stops the
    solve after that many steps as if it were ``max_steps``, but traced: call sites that
    differ only in their step limit can share one solve, and with it one compiled copy of
    the objective and its gradient. ``max_steps`` None (only with a step_cap): no static
    bound at all, so that the cap alone limits the solve.

    ``tol`` may be traced too (a scalar array): it is a threshold the loop compares with,
    never a shape, so one compiled solve serves every tolerance.

    ``inverse0`` (bfgs only): the inverse Hessian approximation to start from, the
    ``inverse`` of an earlier solve over variables of the same shapes (a quasi-Newton
    warm start: a sequence of nearby problems, as the registration rounds are, need not
    learn the curvature again each time); None: the identity. ``keep_inverse``: return
    the solve's own at its end in ``Minimum.inverse`` (bfgs; else None: a dense n x n
    operator that a caller's program would otherwise carry out for nothing).
    """
    check_solver(solver)
    if step_cap is not None:
        step_cap = jnp.asarray(step_cap, jnp.int32)
    elif max_steps is None:
        raise ValueError("minimize: max_steps=None needs a step_cap")
    if solver == "bfgs":
        rounding = 100 * float(jnp.finfo(jax.tree_util.tree_leaves(x0)[0].dtype).eps)
        bfgs = _GradientBFGS(gtol=tol, rounding=rounding, inverse0=inverse0)
        sol = optx.minimise(
            lambda x, _: fun(x),
            bfgs if step_cap is None else _Capped(bfgs),
            x0,
            args=step_cap,
            max_steps=max_steps,
            throw=False,
        )
        x, result, steps = sol.value, RESULTS.promote(sol.result), sol.stats["num_steps"]
        # The value and gradient at the returned (last accepted) point, as the solver
        # evaluated them: evaluating them again would put another copy of the objective
        # and its gradient into the compiled program at every call site.
        info = (sol.state if step_cap is None else sol.state[0]).f_info
        value, gradient, inverse = info.f, info.grad, info.hessian_inv
    else:
        # jaxopt's loop bound may be traced (its while loop compares with it), so the cap,
        # at most max_steps, is the bound itself: no subclass of the solver.
        bound = max_steps if step_cap is None else step_cap
        x, state = _jaxopt().LBFGS(fun=fun, maxiter=bound, tol=tol).run(x0)
        cut = state.iter_num >= jnp.asarray(bound).astype(state.iter_num.dtype)
        # jaxopt stops silently at maxiter; its other stops are judged below.
        result = RESULTS.where(cut, RESULTS.nonlinear_max_steps_reached, RESULTS.successful)
        steps = state.iter_num
        value, gradient, inverse = state.value, state.grad, None
    grad_norm = optx.two_norm(gradient)
    ok = (grad_norm <= tol) & jnp.isfinite(value)
    # A solver that stopped on its own before meeting tol stalled (the step limit and
    # other failures keep their own codes).
    failed = RESULTS.where(result == RESULTS.successful, RESULTS.stalled, result)
    result = RESULTS.where(ok, RESULTS.successful, failed)
    inverse = inverse if keep_inverse else None
    return Minimum(x, result, jnp.asarray(steps, jnp.int32), grad_norm, value, inverse)


def identity_inverse(x0: PyTree) -> object:
    """The inverse Hessian approximation bfgs starts from (the identity on variables
    shaped like ``x0``), as a value for :func:`minimize`'s ``inverse0``: a loop that
    carries one solve's ``Minimum.inverse`` to the next starts from this."""
    zero = jnp.zeros((), jax.tree_util.tree_leaves(x0)[0].dtype)
    return _GradientBFGS(gtol=1.0, rounding=0.0).init_hessian(x0, zero, x0)[0].hessian_inv


def lanczos_smallest(
    matvec: Callable[[Array], Array], start: Array, *, iterations: int
) -> tuple[Array, Array]:
    """Smallest eigenvalue and unit eigenvector of a symmetric operator, by Lanczos.

    k = min(iterations, n) steps (static) of the Lanczos recurrence from ``start``,
    q_0 = start / |start|, beta_j q_{j+1} = H q_j - alpha_j q_j - beta_{j-1} q_{j-1},
    alpha_j = q_j . H q_j, with full reorthogonalization of each new vector against all
    earlier ones (applied twice, "twice is enough"); the smallest eigenpair (theta, y) of
    the tridiagonal T = tridiag(beta, alpha, beta) gives the Ritz pair (theta, Q^T y).
    theta >= lambda_min(H) (Cauchy interlacing), with equality up to rounding once k = n;
    the extreme eigenvalues converge first, fastest when lambda_min is separated from
    the rest of the spectrum. k operator products; memory (k + 1) n.

    Args:
        matvec: v -> H v on arrays shaped like ``start`` (e.g. a Hessian-vector product).
        start: nonzero start vector, any shape (flattened inside); it should not lie in an
            invariant subspace of H (a random vector does not).
        iterations: number of Lanczos steps (static).

    Returns:
        ``(theta, v)``: ``()`` the smallest Ritz value and ``v`` (shape of ``start``) its
        unit Ritz vector. Traceable and vmappable.
    """
    shape, dtype = start.shape, start.dtype
    n = start.size
    k = min(iterations, n)
    q0 = start.reshape(n) / jnp.linalg.norm(start)
    eps, tiny = jnp.finfo(dtype).eps, jnp.finfo(dtype).tiny

    def step(j: ArrayLike, carry: tuple):
        basis, alpha, beta = carry
        w = matvec(basis[j].reshape(shape)).reshape(n)
        alpha = alpha.at[j].set(basis[j] @ w)
        # Rows j + 1.. of basis are still zero, so projecting on all rows is harmless; it
        # subtracts alpha_j q_j and beta_{j-1} q_{j-1} and the rounding drift at once.
        w = w - basis.T @ (basis @ w)
        w = w - basis.T @ (basis @ w)
        norm = jnp.linalg.norm(w)
        # Breakdown (w is rounding noise of |H q_j|): the Krylov space is invariant and T
        # already has H's eigenvalues on it; go on from a new direction orthogonal to it,
        # decoupled (beta = 0), instead of normalizing noise or dividing by zero.
        scale = jnp.abs(alpha[j]) + norm
        # The coordinate axis least represented in the span has |projection|^2 <= (j+1)/n
        # < 1, so its orthogonal part is never zero before k = n.
        axis = jnp.argmin(jnp.sum(basis * basis, axis=0))
        fresh = jnp.zeros(n, dtype).at[axis].set(1.0)
        fresh = fresh - basis.T @ (basis @ fresh)
        fresh = fresh - basis.T @ (basis @ fresh)
        broke = norm <= 100 * eps * scale
        w = jnp.where(broke, fresh, w)
        beta = beta.at[j].set(jnp.where(broke, 0.0, norm))
        # After k = n steps even the fresh direction is zero; row k is never used.
        basis = basis.at[j + 1].set(w / jnp.maximum(jnp.linalg.norm(w), tiny))
        return basis, alpha, beta

    basis = jnp.zeros((k + 1, n), dtype).at[0].set(q0)
    carry = (basis, jnp.zeros(k, dtype), jnp.zeros(k, dtype))
    basis, alpha, beta = jax.lax.fori_loop(0, k, step, carry)
    off = beta[: k - 1]
    tridiagonal = jnp.diag(alpha) + jnp.diag(off, 1) + jnp.diag(off, -1)
    theta, y = jnp.linalg.eigh(tridiagonal)
    vector = basis[:k].T @ y[:, 0]
    return theta[0], (vector / jnp.linalg.norm(vector)).reshape(shape)
