"""smooth_surface: the von Mises-Fisher kernel average of a gridded surface."""

import jax.numpy as jnp
import numpy as np
import pytest

import elastic_jax as ej
from elastic_jax import shapes


def _shrink(width):
    """The mean of p . q under the kernel exp((p . q - 1) / width^2) on the sphere."""
    kappa = 1.0 / width**2
    return 1.0 / np.tanh(kappa) - 1.0 / kappa


def test_a_round_sphere_stays_round_and_shrinks_by_the_closed_form():
    # r e1 averaged is r (coth kappa - 1 / kappa) e1: the quadrature's error falls at
    # second order (measured 7.4e-3, 1.7e-3, 4.3e-4 relative at 13 x 25, 25 x 49, 49 x 97).
    width, errors = 0.4, []
    for m, n in ((13, 25), (25, 49), (49, 97)):
        e1 = ej.sphere_points(m, n, dtype=jnp.float64)
        radius = jnp.linalg.norm(ej.smooth_surface(2.0 * e1, width), axis=0)
        errors.append(float(jnp.max(jnp.abs(radius / (2.0 * _shrink(width)) - 1.0))))
    assert errors[0] < 1e-2
    assert errors[0] / errors[1] > 3.5 and errors[1] / errors[2] > 3.5


def test_rigid_motions_commute_and_the_grid_stays_well_formed():
    f = shapes.sample(shapes.bumpy, 13, 25)
    rotation = jnp.asarray(shapes.random_rotation(2))
    shift = jnp.asarray([0.3, -1.0, 2.0])[:, None, None]
    moved = jnp.einsum("ij,jmn->imn", rotation, f) + shift
    smooth = ej.smooth_surface(f, 0.3)
    expected = jnp.einsum("ij,jmn->imn", rotation, smooth) + shift
    np.testing.assert_allclose(ej.smooth_surface(moved, 0.3), expected, atol=1e-12)
    np.testing.assert_array_equal(smooth[:, 0, :], jnp.broadcast_to(smooth[:, 0, :1], (3, 25)))
    np.testing.assert_array_equal(smooth[:, :, -1], smooth[:, :, 0])
    # A kernel narrower than the grid keeps the surface between the poles, and a pole is
    # its nearest row's mean; a batch is averaged surface by surface.
    narrow = ej.smooth_surface(f, 1e-3)
    np.testing.assert_allclose(narrow[:, 1:-1], f[:, 1:-1], atol=1e-12)
    np.testing.assert_allclose(narrow[:, 0, 0], f[:, 1, :-1].mean(axis=1), atol=1e-12)
    both = ej.smooth_surface(jnp.stack([f, 2.0 * f]), 0.3, batch_size=64)
    np.testing.assert_allclose(both, jnp.stack([smooth, 2.0 * smooth]), atol=1e-13)


def test_bad_widths_and_surfaces_are_refused():
    f = ej.sphere_points(9, 17, dtype=jnp.float64)
    for width in (0.0, -0.1, float("nan"), "wide"):
        with pytest.raises(ej.InputError, match="width"):
            ej.smooth_surface(f, width)
    with pytest.raises(ej.InputError, match="batch_size"):
        ej.smooth_surface(f, 0.2, batch_size=0)
    with pytest.raises(ej.InputError, match="finite|NaN"):
        ej.smooth_surface(f.at[0, 3, 3].set(jnp.nan), 0.2)
