import jax.numpy as jnp
import numpy as np
import pytest

import elastic_jax as ej


@pytest.mark.parametrize(("m", "n"), [(12, 25), (25, 49), (50, 99)])
def test_quadrature_weights_match_interior_form(m, n):
    w = ej.quadrature_weights(m, n)
    assert w.shape == (m, n)
    z2 = ej.sphere_points(m, n)[2] ** 2
    np.testing.assert_allclose(float(jnp.sum(w * z2)), float(ej.integrate(z2)), rtol=1e-14)
    np.testing.assert_array_equal(np.asarray(w[0]), 0.0)
    np.testing.assert_array_equal(np.asarray(w[-1]), 0.0)


def test_quadrature_converges_at_second_order():
    # integral of 1 = 4 pi and of z^2 = 4 pi / 3; the trapezoid rule's error is O(h^2).
    errors = []
    for m, n in [(13, 25), (25, 49), (49, 97)]:
        z = ej.sphere_points(m, n)[2]
        err1 = abs(float(ej.integrate(jnp.ones((m, n)))) - 4 * np.pi) / (4 * np.pi)
        err2 = abs(float(ej.integrate(z**2)) - 4 * np.pi / 3) / (4 * np.pi / 3)
        errors.append(max(err1, err2))
    assert errors[0] / errors[1] > 3.5 and errors[1] / errors[2] > 3.5
    assert errors[2] < 2e-3


def test_sphere_points_are_unit_and_well_formed():
    x = np.asarray(ej.sphere_points(25, 49))
    np.testing.assert_allclose(np.linalg.norm(x, axis=0), 1.0, rtol=1e-15)
    assert np.all(x[:, 0] == x[:, 0, :1]) and np.all(x[:, -1] == x[:, -1, :1])
    assert np.all(x[..., -1] == x[..., 0])
    phi, theta = ej.grid_angles(25, 49)
    np.testing.assert_allclose(
        np.asarray(x[2]), np.cos(np.asarray(phi))[:, None] + 0 * x[2], atol=1e-15
    )
    assert float(theta[-1]) == pytest.approx(2 * np.pi)
