"""Tangent PCA at a mean under the split metric."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import elastic_jax as ej
from elastic_jax import mode_path, shapes, tangent_pca

METRIC = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)
M, N_GRID, DEGREE, N_TIMES = 13, 25, 3, 5


def ellipsoid_family(count: int = 10, seed: int = 0):
    """Ellipsoids whose log axis ratios are two independent factors; their logs at the
    ellipsoid of the mean log axes (modulo nothing: one grid, one parametrization)."""
    factors = np.random.default_rng(seed).uniform(-0.3, 0.3, size=(count, 2))
    base = np.array([1.0, 0.8, 0.6])

    def surface(x):
        axes = base * np.exp([x[0], x[1], 0.0])
        return shapes.sample(lambda p: shapes.ellipsoid(p, tuple(axes)), M, N_GRID)

    mean = surface(factors.mean(axis=0))
    logs = [
        ej.log(mean, surface(x), METRIC, degree=DEGREE, n_times=N_TIMES, tol=1e-7) for x in factors
    ]
    assert all(bool(lg.converged) for lg in logs)
    return factors, mean, jnp.stack([lg.velocity for lg in logs])


@pytest.mark.slow
def test_pca_of_a_two_factor_family_finds_two_modes():
    factors, mean, velocities = ellipsoid_family()
    pca = tangent_pca((mean, velocities), METRIC, n_modes=4)
    print("explained", np.asarray(pca.explained))
    assert float(pca.explained[:2].sum()) >= 0.99
    # G_mu-orthonormal modes.
    gram = jnp.stack([ej.metric_inner(METRIC, mean, e, pca.modes) for e in pca.modes])
    assert float(jnp.max(jnp.abs(gram - jnp.eye(4)))) <= 1e-10
    # Scores times modes give the centred velocities back (all K - 1 modes kept).
    full = tangent_pca((mean, velocities), METRIC, n_modes=len(factors) - 1)
    centred = velocities - velocities.mean(axis=0, keepdims=True)
    rebuilt = jnp.einsum("ik,k...->i...", full.scores, full.modes)
    assert float(jnp.max(jnp.abs(rebuilt - centred)) / jnp.max(jnp.abs(centred))) <= 1e-10
    # The two leading scores explain each factor linearly.
    design = np.column_stack([np.ones(len(factors)), np.asarray(pca.scores[:, :2])])
    for j in range(2):
        y = factors[:, j]
        fit = design @ np.linalg.lstsq(design, y, rcond=None)[0]
        r2 = 1 - np.sum((y - fit) ** 2) / np.sum((y - y.mean()) ** 2)
        print("factor", j, "R^2", r2)
        assert r2 >= 0.99
    # The mode path runs through the mean.
    path = mode_path(pca, 0, METRIC, sigmas=1.0, n_times=N_TIMES, degree=DEGREE)
    assert path.shape == (2 * N_TIMES - 1, 3, M, N_GRID)
    assert float(jnp.max(jnp.abs(path[N_TIMES - 1] - mean))) == 0.0
    # Both shots converged: the path reached -1 and +1 sigma; a lost end node, one step less.
    assert ej.sigmas_reached(path, 1.0) == [-1.0, 1.0]
    cut = np.array(path)
    cut[-1] = np.nan
    assert ej.sigmas_reached(cut, 1.0) == [-1.0, 1.0 - 1.0 / (N_TIMES - 1)]
    with pytest.raises(ej.InputError, match="2 T \\+ 1"):
        ej.sigmas_reached(path[1:], 1.0)


def test_default_modes_stop_at_the_rank_in_float32():
    # K centred velocities have rank K - 1; in float32 the missing direction's eigenvalue
    # is rounding (3e-8 of the total), not a mode.
    mean = shapes.sample(shapes.bumpy, 9, 17)
    velocities = jnp.asarray(np.random.default_rng(0).normal(size=(3, 3, 9, 17)))
    reference = tangent_pca((mean, velocities), METRIC)
    single = tangent_pca((mean.astype(jnp.float32), velocities.astype(jnp.float32)), METRIC)
    assert reference.modes.shape[0] == single.modes.shape[0] == 2
    np.testing.assert_allclose(single.variances, reference.variances, rtol=1e-5)


def test_pca_refuses_bad_input():
    mean = ej.sphere_points(M, N_GRID)
    with pytest.raises(ej.InputError, match="at least 2"):
        tangent_pca((mean, mean[None]), METRIC)
    with pytest.raises(ej.InputError, match="velocities must have shape"):
        tangent_pca((mean, mean[None, :, :-1]), METRIC)
    with pytest.raises(ej.InputError, match="KarcherResult or a pair"):
        tangent_pca(mean, METRIC)
    with pytest.raises(ej.InputError, match="above K - 1"):
        tangent_pca((mean, jnp.stack([mean, 2 * mean, 3 * mean])), METRIC, n_modes=3)
