"""smooth_surface: the von Mises-Fisher kernel average over the parameter sphere, and the
surface's own heat flow."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import elastic_jax as ej
from elastic_jax import shapes


def _shrink(width):
    """The mean of p . q under the kernel exp((p . q - 1) / width^2) on the sphere."""
    kappa = 1.0 / width**2
    return 1.0 / np.tanh(kappa) - 1.0 / kappa


def _moved_before_and_after(kernel: str, scale: float, seed: int):
    """A bumpy surface f, its smoothing (width 0.3), f under a similarity x -> s R x + b,
    and the smoothing under the same similarity."""
    f = shapes.sample(shapes.bumpy, 13, 25)
    rotation = jnp.asarray(shapes.random_rotation(seed))
    shift = jnp.asarray([0.3, -1.0, 2.0])[:, None, None]

    def similarity(g):
        return scale * jnp.einsum("ij,jmn->imn", rotation, g) + shift

    smooth = ej.smooth_surface(f, 0.3, kernel=kernel)
    return f, smooth, similarity(f), similarity(smooth)


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
    f, smooth, moved, expected = _moved_before_and_after(kernel="sphere", scale=1.0, seed=2)
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
    with pytest.raises(ej.InputError, match="kernel"):
        ej.smooth_surface(f, 0.2, kernel="gaussian")
    with pytest.raises(ej.InputError, match="concrete"):
        jax.jit(lambda g: ej.smooth_surface(g, 0.2, kernel="surface"))(f)
    # Two rows at one place: the triangles between them have no area, no cotangent.
    with pytest.raises(ej.InputError, match="zero area"):
        ej.smooth_surface(f.at[:, 4].set(f[:, 3]), 0.2, kernel="surface")


def test_the_surface_kernel_keeps_a_sphere_round_by_the_closed_form():
    # Coordinates on a sphere of radius r are eigenfunctions of Delta (eigenvalue 2 / r^2):
    # four backward Euler steps of (width r)^2 / 8 scale them by (1 + width^2 / 4)^(-4).
    # The cotangent Laplacian's error falls at about second order (measured 1.4e-2,
    # 4.6e-3, 1.4e-3 at 13 x 25, 25 x 49, 49 x 97).
    width, errors = 0.4, []
    for m, n in ((13, 25), (25, 49), (49, 97)):
        sphere = 2.0 * ej.sphere_points(m, n, dtype=jnp.float64)
        radius = jnp.linalg.norm(ej.smooth_surface(sphere, width, kernel="surface"), axis=0)
        errors.append(float(jnp.max(jnp.abs(radius / (2.0 * (1 + width**2 / 4) ** -4) - 1.0))))
    assert errors[0] < 2e-2
    assert errors[0] / errors[1] > 2.5 and errors[1] / errors[2] > 2.5


def test_the_surface_kernel_commutes_with_similarities_and_batches():
    f, smooth, moved, expected = _moved_before_and_after(kernel="surface", scale=3.0, seed=4)
    found = ej.smooth_surface(moved, 0.3, kernel="surface")
    np.testing.assert_allclose(found, expected, atol=1e-12)
    np.testing.assert_array_equal(smooth[:, -1, :], jnp.broadcast_to(smooth[:, -1, :1], (3, 25)))
    np.testing.assert_array_equal(smooth[:, :, -1], smooth[:, :, 0])
    both = ej.smooth_surface(jnp.stack([f, moved]), 0.3, kernel="surface")
    np.testing.assert_allclose(both, jnp.stack([smooth, expected]), atol=1e-12)
    # float32 in, float32 out (the flow itself runs in float64 on the host).
    single = ej.smooth_surface(f.astype(jnp.float32), 0.3, kernel="surface")
    assert single.dtype == jnp.float32
    np.testing.assert_allclose(single, smooth, atol=1e-5)


def test_only_the_surface_kernel_is_independent_of_the_parametrization():
    """smooth(f o phi) against smooth(f) o phi for a Moebius map phi (abs(a) = 0.3),
    relative to how far the blur moved f: measured 5.4e-3, 1.4e-3 for the surface
    kernel at 25 x 49, 49 x 97 (the discretization's, falling at second order) and 0.51
    at both for the sphere kernel, which averages the parametrization."""
    ratios = {"surface": [], "sphere": []}
    for m, n in ((25, 49), (49, 97)):
        f = shapes.sample(shapes.bumpy, m, n)
        boost = jnp.asarray([0.1, -0.2, 0.2])
        phi = ej.moebius(ej.sphere_points(m, n), 0.3 * boost / jnp.linalg.norm(boost))
        weights = jnp.asarray(ej.quadrature_weights(m, n))

        def size(d, weights=weights):
            return float(jnp.sqrt(jnp.sum(weights * jnp.sum(d**2, axis=0))))

        for kernel, found in ratios.items():
            smooth = ej.smooth_surface(f, 0.5, kernel=kernel)
            read_then_smoothed = ej.smooth_surface(ej.reparametrize(f, phi), 0.5, kernel=kernel)
            moved_apart = size(read_then_smoothed - ej.reparametrize(smooth, phi))
            found.append(moved_apart / size(smooth - f))
    assert ratios["surface"][0] < 2e-2 and ratios["surface"][0] / ratios["surface"][1] > 3
    assert min(ratios["sphere"]) > 0.3
