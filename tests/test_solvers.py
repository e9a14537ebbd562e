"""The Lanczos estimate of the smallest eigenvalue (used by the geodesic saddle check)."""

import jax
import jax.numpy as jnp
import numpy as np

from elastic_jax._solvers import lanczos_smallest


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
