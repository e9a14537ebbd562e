"""Minimizers from optimistix and jaxopt behind one small interface (no own quasi-Newton)."""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array

SOLVERS = ("bfgs", "lbfgs")


class Minimum(NamedTuple):
    """What a solve returns: the minimizer, the solver's result code and its step count."""

    x: Array
    result: optx.RESULTS
    num_steps: Array


def _jaxopt():
    # jaxopt announces on import that it is unmaintained; silence exactly that message.
    with warnings.catch_warnings():
        warnings.filterwarnings(
            "ignore", message="JAXopt is no longer maintained", category=DeprecationWarning
        )
        import jaxopt
    return jaxopt


def check_solver(solver: str) -> None:
    if solver not in SOLVERS:
        raise ValueError(f"solver must be one of {SOLVERS}; got {solver!r}")


def minimize(
    fun: Callable[[Array], Array], x0, *, solver: str, max_steps: int, tol: float
) -> Minimum:
    """Minimize a smooth scalar function of one array (traceable, vmappable).

    bfgs: ``optimistix.BFGS(rtol=tol, atol=tol)``, whose Cauchy rule stops when both the
    step (max norm, relative to the iterate) and the change of the value are below tol;
    the dense inverse Hessian suits up to a few thousand variables. lbfgs:
    ``jaxopt.LBFGS(tol=tol)``, which stops when the gradient's 2-norm is below tol.
    Neither raises: a solve that hits ``max_steps`` returns
    ``RESULTS.nonlinear_max_steps_reached``. The caller scales x and the value to O(1).
    """
    check_solver(solver)
    # optimistix tests its stopping rule only after a step the line search accepts; at a
    # start that is already optimal (f1 = f2) no step passes Armijo, so stop here first.
    start_grad = optx.two_norm(jax.grad(fun)(x0))
    return jax.lax.cond(
        start_grad <= tol,
        lambda x: Minimum(x, optx.RESULTS.successful, jnp.zeros((), jnp.int32)),
        lambda x: _run(fun, x, solver=solver, max_steps=max_steps, tol=tol),
        x0,
    )


def _run(fun, x0, *, solver, max_steps, tol) -> Minimum:
    if solver == "bfgs":
        sol = optx.minimise(
            lambda x, _: fun(x),
            optx.BFGS(rtol=tol, atol=tol),
            x0,
            max_steps=max_steps,
            throw=False,
        )
        return Minimum(sol.value, sol.result, jnp.asarray(sol.stats["num_steps"], jnp.int32))
    lbfgs = _jaxopt().LBFGS(fun=fun, maxiter=max_steps, tol=tol)
    x, state = lbfgs.run(x0)
    # jaxopt stops silently at maxiter: judge convergence from its gradient norm.
    ok = (state.error <= tol) & jnp.isfinite(state.value)
    result = optx.RESULTS.where(
        ok, optx.RESULTS.successful, optx.RESULTS.nonlinear_max_steps_reached
    )
    return Minimum(x, result, jnp.asarray(state.iter_num, jnp.int32))


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

    def step(j, carry):
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


def result_message(result: optx.RESULTS) -> str:
    """The solver's words for a (concrete, unbatched) result code; '' on success."""
    return optx.RESULTS[result] if result != optx.RESULTS.successful else ""
