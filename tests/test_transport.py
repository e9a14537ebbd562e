"""Parallel transport by Schild's ladder with exact discrete midpoints."""

from __future__ import annotations

import warnings

import jax.numpy as jnp
import numpy as np
import pytest

import elastic_jax as ej
from elastic_jax import shapes
from elastic_jax._geometry.differential import interior_frame

METRIC = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)
M, N_GRID, DEGREE = 13, 25, 3


def in_span(seed: int):
    basis = ej.surface_basis(M, N_GRID, 2)
    c = np.random.default_rng(seed).standard_normal(basis.shape[0])
    v = jnp.einsum("l,l...->...", jnp.asarray(c / np.linalg.norm(c)), basis)
    return 0.4 * v / jnp.max(jnp.abs(v))


@pytest.mark.slow
def test_the_ladder_keeps_norms_and_carries_a_geodesic_along_itself():
    f = shapes.sample(shapes.ellipsoid, M, N_GRID)
    v, w = in_span(0), in_span(1)
    drifts, apart = [], []
    for n_times in (5, 9):
        # A discrete geodesic one node longer than the path the vector travels along.
        shot = ej.shoot(f, v, METRIC, degree=DEGREE, n_times=n_times + 1)
        path = shot.path[:-1]
        moved = ej.parallel_transport(w, path, METRIC, degree=DEGREE, transport="ladder")
        assert bool(moved.converged)
        drifts.append(abs(float(moved.norm_drift)))
        assert drifts[-1] <= 0.05 / (n_times - 1)  # measured 3.3e-3, 1.9e-3
        # The ladder converges at first order to the Galerkin transport (an independent
        # computation: an ODE, no Newton solves): measured 4.8 % and 2.4 % apart on
        # paths shot at N = 5, 9, 17 (1.2 %).
        galerkin = ej.parallel_transport(w, path, METRIC, degree=DEGREE).vector
        gap = galerkin - moved.vector
        apart.append(float(jnp.sqrt(ej.metric_inner(METRIC, path[-1], gap, gap))) / moved.norms[0])
        # The path's own velocity is carried to the velocity of the step beyond the path
        # (exactly so when rungs and steps have one length; here they differ by a factor
        # N / (N - 1)): measured 1.8e-2 and 4.8e-3.
        tangent = ej.parallel_transport(v, path, METRIC, degree=DEGREE, transport="ladder").vector
        beyond = n_times * (shot.path[-1] - shot.path[-2])
        error = float(jnp.max(jnp.abs(tangent - beyond)) / jnp.max(jnp.abs(beyond)))
        assert error <= 0.5 / (n_times - 1)
        if n_times == 9:
            # The affine midpoint ignores the metric: its drift does not shrink (measured
            # +1.2e-2 at N = 5, +1.5e-2 at 9, +1.7e-2 at 17).
            affine = ej.parallel_transport(
                w, path, METRIC, degree=DEGREE, transport="ladder", midpoint="affine"
            )
            assert abs(float(affine.norm_drift)) > 0.05 / (n_times - 1)
    assert drifts[1] < 0.7 * drifts[0]
    print("ladder - galerkin", apart)
    assert apart[0] <= 0.1 and apart[1] <= 0.65 * apart[0]


def test_galerkin_transport_keeps_any_vectors_norm_at_fourth_order():
    # A vector far outside the degree-3 basis (the bumpy surface's own coordinates) along
    # a shot ellipsoid path: the Galerkin equation keeps its norm exactly in continuous
    # time (the vector is in its space), so what drifts is the Magnus integrator's
    # error, fourth order in the substep. Measured -3.34e-6, -2.28e-7, -1.42e-8 for 1, 2
    # and 4 substeps; the ladder's drift for it is -1.7e-2.
    f = shapes.sample(shapes.ellipsoid, M, N_GRID)
    bumps = shapes.sample(shapes.bumpy, M, N_GRID)
    w = bumps - jnp.mean(bumps, axis=(1, 2), keepdims=True)
    path = ej.shoot(f, in_span(0), METRIC, degree=DEGREE, n_times=5).path
    drifts = []
    for substeps in (1, 2):
        moved = ej.parallel_transport(w, path, METRIC, degree=DEGREE, substeps=substeps)
        assert bool(moved.converged) and int(moved.num_steps) == 4 * substeps
        norms = [
            float(jnp.sqrt(ej.metric_inner(METRIC, f, v, v)))
            for f, v in zip(path, moved.vectors, strict=True)
        ]
        np.testing.assert_allclose(np.asarray(moved.norms), norms, rtol=1e-12)
        drifts.append(abs(float(moved.norm_drift)))
    assert drifts[1] <= 1e-5
    assert drifts[0] / drifts[1] >= 10.0  # 2^4 = 16 for a fourth-order method
    # The transport works on the nodes' differentials: given as the grid's central
    # differences they are the default, to rounding; the carried frame is the vector's.
    frames = jnp.stack(interior_frame(path), axis=1)
    given = ej.parallel_transport(
        w, path, METRIC, degree=DEGREE, path_frames=frames, w_frame=jnp.stack(interior_frame(w))
    )
    np.testing.assert_allclose(given.vectors, moved.vectors, rtol=0, atol=1e-12)
    np.testing.assert_allclose(given.frame, jnp.stack(interior_frame(moved.vector)), atol=1e-12)
    # A vector inside the basis' span makes the Galerkin space's Gram matrix singular
    # (w_0 is also a basis combination): the pseudo-inverse keeps it finite and kept
    # (measured drift -5.2e-8; a plain solve gave NaN from the first segment).
    inside = ej.parallel_transport(in_span(1), path, METRIC, degree=DEGREE)
    assert bool(inside.converged) and abs(float(inside.norm_drift)) <= 1e-5
    with pytest.raises(ej.InputError, match="transport"):
        ej.parallel_transport(w, path, METRIC, transport="pole")


def test_transport_refuses_what_it_cannot_do():
    f = ej.sphere_points(M, N_GRID)
    path = ej.straight_path(f, 2.0 * f, 3)
    with pytest.raises(ej.InputError, match="central"):
        ej.parallel_transport(f, path, METRIC, scheme="central")
    with pytest.raises(ej.InputError, match="midpoint"):
        ej.parallel_transport(f, path, METRIC, midpoint="pole")
    with pytest.raises(ej.InputError, match="w must have the shape"):
        ej.parallel_transport(f[:, :-1], path, METRIC)
    frames = jnp.stack(interior_frame(path), axis=1)
    with pytest.raises(ej.InputError, match="galerkin"):
        ej.parallel_transport(f, path, METRIC, transport="ladder", path_frames=frames)
    with pytest.raises(ej.InputError, match=r"path_frames .* shape \(3, 2, 3, 11, 24\)"):
        ej.parallel_transport(f, path, METRIC, path_frames=frames[:2])
    with pytest.raises(ej.InputError, match="w_frame"):
        ej.parallel_transport(f, path, METRIC, w_frame=frames[0, :, :2])


@pytest.mark.slow
def test_a_failed_rung_ends_the_ladder():
    f = shapes.sample(shapes.ellipsoid, M, N_GRID)
    path = ej.shoot(f, in_span(0), METRIC, degree=DEGREE, n_times=5).path
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        moved = ej.parallel_transport(
            in_span(1), path, METRIC, degree=DEGREE, transport="ladder", max_newton=1
        )
    messages = [str(w.message) for w in caught if issubclass(w.category, ej.ConvergenceWarning)]
    assert len(messages) == 1 and "rung 1 of 4 did not solve" in messages[0]
    # One Newton iteration cannot meet 1e-10 from a zero start: the first rung fails and
    # nothing is carried on from it.
    assert int(moved.n_valid) == 1 and not bool(moved.converged)
    assert bool(jnp.all(jnp.isfinite(moved.vectors[0])))
    assert bool(jnp.all(jnp.isnan(moved.vectors[1:]))) and bool(jnp.all(jnp.isnan(moved.norms[1:])))
    assert bool(jnp.all(jnp.isnan(moved.residuals[1:])))
