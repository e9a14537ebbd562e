import jax
import jax.numpy as jnp
import numpy as np

import elastic_jax as ej
from elastic_jax import shapes


def _analytic_differential(shape, m, n):
    """[F_theta / sin phi, F_phi] of F(e1(phi, theta)) by automatic differentiation."""
    phi, theta = ej.grid_angles(m, n)

    def surface(p, t):
        x = jnp.stack([jnp.sin(p) * jnp.cos(t), jnp.sin(p) * jnp.sin(t), jnp.cos(p)])
        return shape(x)

    d_theta = jax.vmap(jax.vmap(jax.jacfwd(surface, 1), (None, 0)), (0, None))(phi, theta)
    d_phi = jax.vmap(jax.vmap(jax.jacfwd(surface, 0), (None, 0)), (0, None))(phi, theta)
    col1 = jnp.moveaxis(d_theta, -1, 0) / jnp.sin(phi)[None, :, None]
    col2 = jnp.moveaxis(d_phi, -1, 0)
    return jnp.stack([col1, col2], axis=1)


def test_differential_converges_to_the_analytic_one():
    errors = []
    for m, n in [(13, 25), (25, 49), (49, 97)]:
        df = ej.differential(shapes.sample(shapes.bumpy, m, n))
        exact = _analytic_differential(shapes.bumpy, m, n)
        assert df.shape == (3, 2, m, n)
        errors.append(float(jnp.max(jnp.abs(df - exact)[:, :, 1:-1])))
    # Central differences: O(h^2) on interior rows, across the poles included.
    assert errors[0] / errors[1] > 3.0 and errors[1] / errors[2] > 3.5


def test_pole_rows_use_the_half_turn_rule():
    m, n = 25, 49
    f = shapes.sample(shapes.ellipsoid, m, n)
    df = np.asarray(ej.differential(f))
    np.testing.assert_array_equal(df[:, 0, 0], 0.0)
    np.testing.assert_array_equal(df[:, 0, -1], 0.0)
    dphi = np.pi / (m - 1)
    half = (n - 1) // 2
    f = np.asarray(f)
    j = 7
    np.testing.assert_allclose(
        df[:, 1, 0, j], (f[:, 1, j] - f[:, 1, j + half]) / (2 * dphi), rtol=1e-14
    )
    # The unit sphere: f_phi at the north pole is (cos theta, sin theta, 0) * sin(dphi)/dphi.
    e1 = ej.differential(ej.sphere_points(m, n))
    _, theta = ej.grid_angles(m, n)
    expected = np.sin(dphi) / dphi * np.stack([np.cos(theta), np.sin(theta), 0 * theta])
    np.testing.assert_allclose(np.asarray(e1[:, 1, 0]), expected, atol=1e-14)


def test_differential_is_linear_and_batched():
    f = shapes.sample(shapes.bumpy, 13, 25)
    g = shapes.sample(shapes.ellipsoid, 13, 25)
    both = ej.differential(jnp.stack([f, g]))
    np.testing.assert_allclose(both[1], ej.differential(g), rtol=1e-15)
    np.testing.assert_allclose(
        ej.differential(2 * f - 3 * g), 2 * ej.differential(f) - 3 * ej.differential(g), atol=1e-13
    )
