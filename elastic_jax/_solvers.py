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


def result_message(result: optx.RESULTS) -> str:
    """The solver's words for a (concrete, unbatched) result code; '' on success."""
    return optx.RESULTS[result] if result != optx.RESULTS.successful else ""
