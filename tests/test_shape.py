import jax
import jax.numpy as jnp
import numpy as np
import pytest

import elastic_jax as ej
from elastic_jax import shapes

from .conftest import load_shape

M, N = 25, 49
METRIC = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)
# One configuration for most tests, so that they share one compilation.
OPTIONS = {"degree": 5, "vf_degree": 5, "n_times": 7, "outer_steps": 2}


def _check_gamma(res):
    assert float(ej.jacobian_determinant(res.gamma).min()) > 0
    np.testing.assert_allclose(jnp.linalg.norm(res.gamma, axis=0), 1.0, atol=1e-12)


@pytest.fixture(scope="module")
def bumpy_pair():
    h = shapes.random_rotation(11)  # not an icosahedral rotation
    return shapes.sample(shapes.bumpy, M, N), shapes.sample(shapes.bumpy, M, N, rotation=h), h


def test_recovers_a_reparametrization(bumpy_pair):
    f1, f2, _ = bumpy_pair
    res = ej.shape_geodesic(f1, f2, METRIC, **OPTIONS)
    assert float(res.distance) < 0.05 * float(res.parametrized_distance)
    _check_gamma(res)
    np.testing.assert_allclose(res.f1_registered, res.path[0], atol=0)
    np.testing.assert_allclose(res.rotation, np.eye(3), atol=0)
    assert float(ej.path_energy(METRIC, res.path)) == pytest.approx(float(res.energy), rel=1e-10)
    history = np.asarray(res.energy_history)
    assert history.shape == (OPTIONS["outer_steps"] + 2,)
    assert history[0] == pytest.approx(float(res.parametrized_distance) ** 2, rel=1e-12)
    assert np.all(np.diff(history[1:]) <= 1e-12 * history[0])  # registration never raises it


@pytest.mark.slow
def test_recovers_a_rigid_motion_and_a_reparametrization(bumpy_pair):
    f1, f2, _ = bumpy_pair
    r = shapes.random_rotation(5)
    moved = jnp.einsum("ij,jmn->imn", r, f2) + jnp.asarray([0.3, -0.2, 0.5])[:, None, None]
    res = ej.shape_geodesic(f1, moved, METRIC, modulo="rigid", **OPTIONS)
    assert float(res.distance) < 0.05 * float(res.parametrized_distance)
    assert float(jnp.abs(res.rotation - r.T).max()) < 1e-2
    _check_gamma(res)


def test_joint_and_coordinate_descent_agree(bumpy_pair):
    # Different shapes (a stretch) under an unknown reparametrization.
    f1, _, h = bumpy_pair
    stretch = jnp.asarray([1.3, 1.0, 0.8])
    f2 = jnp.einsum("i,imn->imn", stretch, shapes.sample(shapes.bumpy, M, N, rotation=h))
    coordinate = ej.shape_geodesic(f1, f2, METRIC, **OPTIONS)
    joint = ej.shape_geodesic(f1, f2, METRIC, method="joint", **OPTIONS)
    assert abs(float(joint.distance) - float(coordinate.distance)) < 0.05 * float(
        coordinate.distance
    )
    for res in (coordinate, joint):
        assert float(res.distance) < 0.5 * float(res.parametrized_distance)
        _check_gamma(res)


@pytest.mark.data
# Two outer rounds leave real pairs still improving (8-18 % per round with Algorithm 3),
# which the result reports as not converged; the asserted inequality holds from round one.
@pytest.mark.filterwarnings("ignore::elastic_jax.ConvergenceWarning")
@pytest.mark.parametrize("other", ["cat2", "horse0"])
def test_shape_distance_is_below_the_parametrized_one_on_real_shapes(other):
    f1 = ej.resample(load_shape("cat1"), M, N)
    f2 = ej.resample(load_shape(other), M, N)
    res = ej.shape_geodesic(f1, f2, METRIC, **OPTIONS)
    assert float(res.distance) < float(res.parametrized_distance)
    _check_gamma(res)


@pytest.mark.slow
def test_vmap_over_targets_equals_a_loop(bumpy_pair):
    f1, f2, _ = bumpy_pair
    targets = jnp.stack([f2, shapes.sample(shapes.bumpy, M, N, rotation=shapes.random_rotation(2))])
    options = {**OPTIONS, "outer_steps": 1}
    solve = lambda g: ej.shape_geodesic(f1, g, METRIC, **options)  # noqa: E731
    batched = jax.vmap(solve)(targets)
    # Batched and single solves round differently, and the pipeline has discrete choices
    # (best of 60 rotations, step shrinking); agreement is judged at the problem's scale.
    for i, target in enumerate(targets):
        single = solve(target)
        scale = float(single.parametrized_distance)
        assert abs(float(batched.distance[i]) - float(single.distance)) < 1e-3 * scale
        assert float(batched.parametrized_distance[i]) == pytest.approx(scale, rel=1e-9)
        np.testing.assert_allclose(batched.gamma[i], single.gamma, atol=1e-2)


def test_errors(bumpy_pair):
    f1, f2, _ = bumpy_pair
    with pytest.raises(ValueError, match="modulo must be one of"):
        ej.shape_geodesic(f1, f2, METRIC, modulo="affine")
    with pytest.raises(ValueError, match="method must be one of"):
        ej.shape_geodesic(f1, f2, METRIC, method="newton")
    with pytest.raises(ValueError, match="init must be one of"):
        ej.shape_geodesic(f1, f2, METRIC, init="random")
    with pytest.raises(ValueError, match="vf_degree=30 is too high"):
        ej.shape_geodesic(f1, f2, METRIC, vf_degree=30)
    with pytest.raises(ValueError, match="share grid"):
        ej.shape_geodesic(f1, shapes.sample(shapes.bumpy, 13, 25), METRIC)
