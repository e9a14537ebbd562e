import jax
import jax.numpy as jnp
import numpy as np

import elastic_jax as ej
from elastic_jax import shapes


def test_resample_converges_at_second_order():
    exact = shapes.sample(shapes.bumpy, 37, 73)
    errors = []
    for m, n in [(25, 49), (50, 99), (100, 199)]:
        moved = ej.resample(shapes.sample(shapes.bumpy, m, n), 37, 73)
        errors.append(float(jnp.abs(moved - exact).max()))
    assert errors[0] / errors[1] > 3.5 and errors[1] / errors[2] > 3.5


def test_resample_onto_the_same_grid_is_the_identity_and_output_is_well_formed():
    f = shapes.sample(shapes.bent_cylinder, 25, 49)
    np.testing.assert_allclose(ej.resample(f, 25, 49), f, atol=1e-14)
    g = np.asarray(ej.resample(f, 18, 35))
    assert np.all(g[:, 0] == g[:, 0, :1]) and np.all(g[:, -1] == g[:, -1, :1])
    np.testing.assert_allclose(g[..., -1], g[..., 0], atol=1e-14)
    assert ej.validate_surface(g).shape == (3, 18, 35)


def test_resample_is_linear_and_differentiable():
    f = shapes.sample(shapes.bumpy, 13, 25)
    g = shapes.sample(shapes.ellipsoid, 13, 25)
    both = ej.resample(2.0 * f - g, 21, 41)
    np.testing.assert_allclose(
        both, 2.0 * ej.resample(f, 21, 41) - ej.resample(g, 21, 41), atol=1e-13
    )
    grad = jax.grad(lambda x: jnp.sum(ej.resample(x, 21, 41) ** 2))(f)
    # Bilinear weights sum to one at every target point: d/dc sum(resample(f + c)) = count.
    ones = jax.grad(lambda c: jnp.sum(ej.resample(f + c, 21, 41)))(0.0)
    assert abs(float(ones) - 3 * 21 * 41) < 1e-9
    assert bool(jnp.all(jnp.isfinite(grad)))
