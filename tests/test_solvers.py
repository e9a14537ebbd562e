"""The minimizer wrapper, and the Lanczos estimate of the smallest eigenvalue (used by the
geodesic saddle check)."""

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

from elastic_jax._geodesics.solvers import lanczos_smallest, minimize
from elastic_jax._results import RESULTS


def _rosenbrock(x):
    return jnp.sum(100.0 * (x[1:] - x[:-1] ** 2) ** 2 + (1.0 - x[:-1]) ** 2)


@pytest.mark.parametrize("solver", ["bfgs", "lbfgs"])
@pytest.mark.parametrize("max_steps", [3, 500])
def test_minimum_reports_value_and_gradient_at_its_point(solver, max_steps):
    # The value and gradient norm come from the solver's own evaluations, not from a new
    # one: they must be those of the returned point, also when the step limit cuts a solve.
    x0 = jnp.asarray([-1.2, 1.0, -0.5, 0.8])
    found = minimize(_rosenbrock, x0, solver=solver, max_steps=max_steps, tol=1e-8)
    # Absolute floors at rounding of the start's scale (f(x0) ~ 50, |grad| ~ 400): near the
    # minimum both are sums that cancel, and another evaluation order moves their last bits.
    assert float(found.value) == pytest.approx(float(_rosenbrock(found.x)), rel=1e-12, abs=1e-15)
    grad_norm = float(optx.two_norm(jax.grad(_rosenbrock)(found.x)))
    assert float(found.grad_norm) == pytest.approx(grad_norm, rel=1e-9, abs=1e-12)
    if max_steps == 3:
        assert found.result == RESULTS.nonlinear_max_steps_reached and found.num_steps == 3
    else:
        assert found.result == RESULTS.successful and grad_norm <= 1e-8
        np.testing.assert_allclose(found.x, 1.0, atol=1e-6)


def test_a_carried_inverse_hessian_solves_a_nearby_problem_in_fewer_steps():
    """bfgs from another solve's inverse Hessian (``inverse0``, a quasi-Newton warm
    start): an ill-conditioned quadratic (eigenvalues 1 to 100, n = 40) solved once from
    the identity, then the same quadratic with a shifted minimum from the first solve's
    end operator. The second solve meets tol at the exact minimizer A^-1 b', in at most
    half the first solve's steps (measured 10 against 163); from the identity it needs as
    many as the first (161)."""
    rng = np.random.default_rng(3)
    n = 40
    q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    a = jnp.asarray(q @ np.diag(np.logspace(0, 2, n)) @ q.T)
    b1, b2 = (jnp.asarray(rng.normal(size=n)) for _ in range(2))

    def quadratic(b):
        # Written around its minimizer, so that its minimum value is 0: in the form
        # 0.5 x A x - b x (minimum -4.8) the last steps' decreases fall below the value's
        # rounding before the gradient meets tol, and the solve stalls or not by the
        # rounding of the compiled program.
        center = jnp.linalg.solve(a, b)
        return lambda x: 0.5 * (x - center) @ a @ (x - center)

    tol = 1e-7
    first = minimize(
        quadratic(b1), jnp.zeros(n), solver="bfgs", max_steps=1000, tol=tol, keep_inverse=True
    )
    start = jnp.linalg.solve(a, b1)
    warm = minimize(
        quadratic(b2), start, solver="bfgs", max_steps=1000, tol=tol, inverse0=first.inverse
    )
    cold = minimize(quadratic(b2), start, solver="bfgs", max_steps=1000, tol=tol)
    assert first.result == warm.result == cold.result == RESULTS.successful
    np.testing.assert_allclose(warm.x, jnp.linalg.solve(a, b2), rtol=1e-6, atol=1e-9)
    print(
        "steps: first",
        int(first.num_steps),
        "warm",
        int(warm.num_steps),
        "cold",
        int(cold.num_steps),
    )
    assert int(warm.num_steps) <= 0.5 * int(first.num_steps)
    assert int(warm.num_steps) < int(cold.num_steps)
    # Only when asked for: a solve's program does not carry the n x n operator out.
    assert cold.inverse is None


@pytest.mark.parametrize("solver", ["bfgs", "lbfgs"])
def test_a_start_that_meets_tol_stops_at_the_first_step(solver):
    x0 = jnp.ones(4)  # Rosenbrock's minimum: gradient exactly zero
    found = minimize(_rosenbrock, x0, solver=solver, max_steps=50, tol=1e-8)
    assert found.result == RESULTS.successful and int(found.num_steps) <= 1
    assert float(found.grad_norm) == 0.0 and float(found.value) == 0.0
    np.testing.assert_array_equal(found.x, x0)


@pytest.mark.parametrize("solver", ["bfgs", "lbfgs"])
def test_a_traced_step_cap_stops_where_that_max_steps_stops(solver):
    """One compiled solve with the cap traced (vmapped over three caps) returns, for each
    cap, what a solve compiled with max_steps = cap returns: the same point and value to
    the bit (the same iterates), the same step count and result code."""
    x0 = jnp.asarray([-1.2, 1.0, -0.5, 0.8])
    caps = jnp.asarray([2, 9, 400])
    capped = jax.jit(
        jax.vmap(
            lambda cap: minimize(
                _rosenbrock, x0, solver=solver, max_steps=400, tol=1e-8, step_cap=cap
            )
        )
    )(caps)
    for k, cap in enumerate((2, 9, 400)):
        alone = minimize(_rosenbrock, x0, solver=solver, max_steps=cap, tol=1e-8)
        one = jax.tree_util.tree_map(lambda leaf, k=k: leaf[k], capped)
        np.testing.assert_array_equal(one.x, alone.x)
        assert float(one.value) == float(alone.value)
        # The norm is a reduction: the batched program may sum in another order.
        assert float(one.grad_norm) == pytest.approx(float(alone.grad_norm), rel=1e-12)
        assert int(one.num_steps) == int(alone.num_steps)
        assert one.result == alone.result
        # The two short caps stop at their limit; the long one converges before it.
        expected = RESULTS.successful if cap == 400 else RESULTS.nonlinear_max_steps_reached
        assert one.result == expected
    assert capped.num_steps.tolist()[:2] == [2, 9] and int(capped.num_steps[2]) < 400


def _symmetric(n, seed):
    a = np.random.default_rng(seed).standard_normal((n, n))
    return jnp.asarray((a + a.T) / np.sqrt(n) + 2.0 * np.eye(n))


def test_lanczos_is_exact_on_a_full_krylov_space():
    h = _symmetric(10, 0)
    start = jnp.asarray(np.random.default_rng(1).standard_normal((2, 5)))
    theta, v = lanczos_smallest(lambda x: (h @ x.reshape(10)).reshape(2, 5), start, iterations=24)
    lowest = np.linalg.eigvalsh(np.asarray(h))[0]
    assert v.shape == (2, 5)
    assert abs(float(theta) - lowest) < 1e-12
    np.testing.assert_allclose(h @ v.reshape(10), theta * v.reshape(10), atol=1e-12)


def test_lanczos_bounds_and_approaches_the_smallest_eigenvalue():
    h = _symmetric(300, 2)
    start = jnp.asarray(np.random.default_rng(3).standard_normal(300))
    lowest = np.linalg.eigvalsh(np.asarray(h))[0]
    # Ritz values bound the spectrum from inside and descend with more steps.
    errors = []
    for k in (10, 24, 60):
        theta, v = jax.jit(lambda s, k=k: lanczos_smallest(lambda x: h @ x, s, iterations=k))(start)
        assert abs(float(jnp.linalg.norm(v)) - 1.0) < 1e-12
        errors.append(float(theta) - lowest)
    assert errors[0] > errors[1] > errors[2] > -1e-12
    assert errors[2] < 1e-6


def test_lanczos_survives_breakdown():
    # The start is an eigenvector: the Krylov space is invariant after one step.
    h = jnp.diag(jnp.arange(1.0, 41.0))
    start = jnp.zeros(40).at[5].set(1.0)
    theta, v = lanczos_smallest(lambda x: h @ x, start, iterations=24)
    assert bool(jnp.all(jnp.isfinite(v)))
    assert abs(float(theta) - 1.0) < 1e-12  # found through the fresh directions
    assert abs(abs(float(v[0])) - 1.0) < 1e-12
    # vmap over start vectors agrees with one at a time.
    starts = jnp.stack([start, jnp.ones(40)])
    batched, _ = jax.vmap(lambda s: lanczos_smallest(lambda x: h @ x, s, iterations=24))(starts)
    assert abs(float(batched[0]) - float(theta)) < 1e-12
    # Equally spaced spectrum 1..40, 24 steps from the all-ones vector: close, not exact.
    assert 0 <= float(batched[1]) - 1.0 < 1e-5
