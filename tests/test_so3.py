import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import elastic_jax as ej


def _axis_angles(scale, shape=(7,), seed=0):
    w = np.random.default_rng(seed).standard_normal(shape + (3,))
    return jnp.asarray(w / np.linalg.norm(w, axis=-1, keepdims=True) * scale)


@pytest.mark.parametrize("batch", [(), (1,), (3, 2)])
def test_exp_is_a_rotation_and_log_inverts_it(batch):
    w = _axis_angles(1.3, batch + (5,))[..., 0, :] if batch == () else _axis_angles(1.3, batch)
    r = ej.so3_exp(w)
    assert r.shape == batch + (3, 3)
    eye = np.broadcast_to(np.eye(3), r.shape)
    np.testing.assert_allclose(jnp.swapaxes(r, -1, -2) @ r, eye, atol=1e-14)
    np.testing.assert_allclose(jnp.linalg.det(r), 1.0, atol=1e-14)
    np.testing.assert_allclose(ej.so3_log(r), w, atol=1e-14)
    np.testing.assert_allclose(ej.so3_exp(ej.so3_log(r)), r, atol=1e-14)


def test_exp_matches_the_matrix_exponential():
    w = _axis_angles(2.2, (4,), seed=3)
    expected = jax.vmap(jax.scipy.linalg.expm)(ej.hat(w))
    np.testing.assert_allclose(ej.so3_exp(w), expected, atol=1e-13)
    np.testing.assert_allclose(ej.hat(w) @ jnp.ones(3), jnp.cross(w, jnp.ones(3)), atol=1e-15)


@pytest.mark.parametrize("scale", [0.0, 1e-9, 1e-4, 1.0, np.pi - 1e-3, np.pi - 1e-7])
def test_values_and_gradients_near_the_singular_angles(scale):
    w = _axis_angles(scale, (3,), seed=1)
    np.testing.assert_allclose(ej.so3_log(ej.so3_exp(w)), w, atol=1e-13)
    for v in w:
        # log o exp is the identity, so its Jacobian is I exactly: gradients of both are
        # right, in both modes (reverse mode also differentiates the branches not taken).
        for jacobian in (jax.jacfwd, jax.jacrev):
            jac = jacobian(lambda x: ej.so3_log(ej.so3_exp(x)))(v)
            np.testing.assert_allclose(jac, np.eye(3), atol=1e-9)
    check_grads(ej.so3_exp, (w[0],), order=2, modes=["fwd", "rev"])


def test_exp_gradient_at_zero_is_hat():
    jac = jax.jacfwd(ej.so3_exp)(jnp.zeros(3))
    for i in range(3):
        np.testing.assert_array_equal(jac[..., i], ej.hat(jnp.eye(3)[i]))
    check_grads(ej.so3_exp, (jnp.zeros(3),), order=1, modes=["rev"], eps=1e-6)


def test_log_at_a_half_turn():
    r = jnp.diag(jnp.asarray([-1.0, -1.0, 1.0]))
    w = ej.so3_log(r)
    assert float(jnp.linalg.norm(w)) == pytest.approx(np.pi, abs=1e-12)
    np.testing.assert_allclose(ej.so3_exp(w), r, atol=1e-12)
    # Reverse mode agrees with forward mode there (it was NaN).
    np.testing.assert_allclose(jax.jacrev(ej.so3_log)(r), jax.jacfwd(ej.so3_log)(r), atol=1e-12)


@pytest.mark.parametrize("scale", [0.0, 1e-4, 0.5])
def test_log_gradient_in_float32(scale):
    # grad of sum(log(exp(w))) is (1, 1, 1); float32's 1 - cos(theta) rounds to 0 already
    # at |w| = 1e-4.
    w = jnp.asarray(_axis_angles(scale, (1,), seed=2)[0], jnp.float32)
    grad = jax.grad(lambda x: ej.so3_log(ej.so3_exp(x)).sum())(w)
    np.testing.assert_allclose(grad, np.ones(3), atol=1e-3)


def test_icosahedral_group():
    g = np.asarray(ej.icosahedral_group())
    assert g.shape == (60, 3, 3)
    np.testing.assert_allclose(
        np.einsum("gji,gjk->gik", g, g), np.broadcast_to(np.eye(3), g.shape), atol=1e-13
    )
    np.testing.assert_allclose(np.linalg.det(g), 1.0, atol=1e-13)
    distances = np.abs(g[:, None] - g[None]).max(axis=(-1, -2))
    assert np.sort(distances + 10 * np.eye(60), axis=1)[:, 0].min() > 0.1  # 60 distinct

    def index(r):
        d = np.abs(g - r).max(axis=(-1, -2))
        assert d.min() < 1e-12
        return int(d.argmin())

    for a in range(60):
        index(g[a].T)  # inverses
        for b in range(0, 60, 7):
            index(g[a] @ g[b])  # products
    # Rotation angles of the icosahedral group: 1 identity, 15 half-turns, 20 of 2pi/3,
    # 24 of 2pi/5 or 4pi/5.
    angles = np.round(np.linalg.norm(np.asarray(ej.so3_log(g)), axis=-1) / np.pi * 15).astype(int)
    assert sorted(np.bincount(angles).tolist()) == sorted(
        [1, 15, 20, 12, 12] + [0] * (len(np.bincount(angles)) - 5)
    )
