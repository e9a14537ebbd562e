import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import elastic_jax as ej
from elastic_jax import shapes
from elastic_jax._geometry.reparam import (
    _field_derivatives_np,
    directional_derivatives,
    reparametrize_unchecked,
    sample_points,
    spline_upsample,
)

DEGREE = 5


def _field(seed):
    return np.random.default_rng(seed).standard_normal(2 * (DEGREE + 1) ** 2 - 2)


def _analytic_jacobian(x, m, n):
    """D / |W|^3 from the proof of Theorem 3 (exact derivatives), interior rows."""
    u, v, u_phi, u_theta, v_phi, v_theta = np.einsum(
        "k,jkmn->jmn", x, _field_derivatives_np(m, n, DEGREE)
    )
    phi = np.asarray(ej.grid_angles(m, n)[0])[1:-1, None]
    a, b = u_phi, v_phi
    c, d = (u_theta - v * np.cos(phi)) / np.sin(phi), (v_theta + u * np.cos(phi)) / np.sin(phi)
    one = np.ones_like(u)
    rows = [np.stack([one, u, v], -1), np.stack([-u, 1 + a, b], -1), np.stack([-v, c, 1 + d], -1)]
    return np.linalg.det(np.stack(rows, -2)) / (1 + u**2 + v**2) ** 1.5


def test_identity():
    x = np.zeros(2 * (DEGREE + 1) ** 2 - 2)
    np.testing.assert_allclose(
        ej.diffeomorphism(x, 25, 49, DEGREE), ej.sphere_points(25, 49), atol=1e-15
    )
    assert float(ej.diffeomorphism_bound(x, 25, 49, DEGREE)) == np.inf
    j = ej.jacobian_determinant(ej.sphere_points(50, 99))
    # Central differences of sin/cos lose sin(h)/h per direction: J = 1 - O(h^2).
    assert float(jnp.abs(j - 1).max()) < 2e-3


def test_jacobian_converges_to_the_analytic_one():
    x = 0.05 * _field(0)
    errors = []
    for m, n in [(25, 49), (50, 99), (100, 199)]:
        j = np.asarray(ej.jacobian_determinant(ej.diffeomorphism(x, m, n, DEGREE)))[1:-1]
        errors.append(np.abs(j - _analytic_jacobian(x, m, n)).max())
    assert errors[0] / errors[1] > 3.5 and errors[1] / errors[2] > 3.5


def test_theorem3_bound():
    folded = 0
    for seed in range(4):
        x = _field(seed)
        bound = float(ej.diffeomorphism_bound(x, 100, 199, DEGREE))
        assert 0 < bound < np.inf
        # Below the bound: positive Jacobian everywhere, on a grid finer than the bound's.
        for t in (0.5, 0.99):
            gamma = ej.diffeomorphism(t * bound * x, 150, 299, DEGREE)
            assert float(ej.jacobian_determinant(gamma).min()) > 0
        # The bound is sufficient; a few times beyond it the map folds.
        gamma = ej.diffeomorphism(3 * bound * x, 150, 299, DEGREE)
        folded += float(ej.jacobian_determinant(gamma).min()) < 0
    assert folded >= 1


def test_bound_batches_and_scales():
    xs = np.stack([_field(1), _field(2)])
    bounds = ej.diffeomorphism_bound(xs, 50, 99, DEGREE)
    assert bounds.shape == (2,)
    np.testing.assert_allclose(
        ej.diffeomorphism_bound(2.0 * xs, 50, 99, DEGREE), bounds / 2, rtol=1e-12
    )
    assert ej.diffeomorphism(xs, 25, 49, DEGREE).shape == (2, 3, 25, 49)


@pytest.mark.parametrize("method", ["bilinear", "bicubic", "spline"])
def test_reparametrize_by_a_rotation_converges(method):
    r = shapes.random_rotation(3)
    errors = []
    for m, n in [(25, 49), (50, 99), (100, 199)]:
        f = shapes.sample(shapes.bumpy, m, n)
        exact = shapes.sample(shapes.bumpy, m, n, rotation=r)
        errors.append(float(jnp.abs(ej.rotate_parametrization(f, r, method=method) - exact).max()))
    # Second, third and fourth order (measured ratios 3.9-4.0, 8.9-9.8, 15.8-15.9).
    order = {"bilinear": 3.5, "bicubic": 7.0, "spline": 14.0}[method]
    assert errors[0] / errors[1] > order and errors[1] / errors[2] > order
    if method != "bilinear":
        assert errors[1] < {"bicubic": 1e-4, "spline": 1e-5}[method]


def test_reparametrize_identity_and_gradients():
    f = shapes.sample(shapes.bent_cylinder, 13, 25)
    e1 = ej.sphere_points(13, 25)
    for method in ("bilinear", "bicubic", "spline"):
        np.testing.assert_allclose(ej.reparametrize(f, e1, method=method), f, atol=1e-13)
    gamma = ej.diffeomorphism(0.03 * _field(5), 13, 25, DEGREE)

    def energy(g):
        return jnp.sum(ej.reparametrize(f, g, method="bicubic") ** 2)

    grad = jax.grad(energy)(gamma)
    assert bool(jnp.all(jnp.isfinite(grad)))
    # Differentiable in gamma through the diffeomorphism's coefficients (interior points),
    # and in f (the spline's coefficients are a linear filter of f).
    for method in ("bicubic", "spline"):
        check_grads(
            lambda x, method=method: ej.reparametrize(
                f, ej.diffeomorphism(x, 13, 25, DEGREE), method=method
            ),
            (jnp.asarray(0.03 * _field(6)),),
            order=1,
            modes=["fwd", "rev"],
            atol=1e-5,
            rtol=1e-5,
        )
    check_grads(  # unchecked: the perturbed f's pole rows are not constant
        lambda g: reparametrize_unchecked(g, gamma, method="spline"),
        (f,),
        order=1,
        modes=["fwd", "rev"],
        atol=1e-5,
        rtol=1e-5,
    )


@pytest.mark.parametrize("method", ["bilinear", "bicubic", "spline"])
def test_derivative_in_gamma_holds_on_the_poles(method):
    # f(p) = A p: f o gamma = A gamma, so moving gamma by d moves f o gamma by A d. At the
    # identity the pole rows sit exactly on the z axis, where the angles' chart is
    # singular (the derivative there used to be zero: a registration round starts there).
    m, n = 25, 49
    a = jnp.asarray([[1.3, 0.2, 0.0], [0.1, 1.0, -0.3], [0.0, 0.4, 0.8]])
    e1 = ej.sphere_points(m, n)
    f = jnp.einsum("ij,jmn->imn", a, e1)
    u = jnp.asarray([0.3, -0.5, 0.2])[:, None, None]
    d = u - jnp.sum(u * e1, axis=0, keepdims=True) * e1  # tangent to the sphere

    def read(g):
        return ej.reparametrize(f, g, method=method)

    _, tangent = jax.jvp(read, (e1,), (d,))
    exact = jnp.einsum("ij,jmn->imn", a, d)
    for row in (0, m - 1):
        error = jnp.linalg.norm(tangent[:, row] - exact[:, row], axis=0)
        # The pole row's central difference loses sin(h)/h = 0.9971 at 25 rows; the
        # spline's derivative is fourth order (measured 1.6e-6).
        bound = 1e-5 if method == "spline" else 4e-3
        assert float(error.max()) <= bound * float(jnp.linalg.norm(exact[:, row, 0]))
    # Reverse mode is the transpose of that rule: <w, J d> = <J^T w, d>.
    w = jnp.asarray(np.random.default_rng(3).standard_normal(f.shape))
    (back,) = jax.vjp(read, e1)[1](w)
    np.testing.assert_allclose(float(jnp.sum(back * d)), float(jnp.sum(w * tangent)), rtol=1e-12)


@pytest.mark.parametrize("method", ["bicubic", "spline"])
def test_derivative_in_gamma_holds_one_rounding_off_the_poles(method):
    """A rotation that maps grid points onto the poles leaves them about 1e-16 off the z
    axis (the icosahedral starts map the equator's theta = 0 there). The angles' chart
    divides f_theta's rounding by that distance: the derivative of the read was wrong by
    O(1) there (and the chain rule's frame with it), and it changed with the data's last
    bits. Within sqrt(eps) of the axis the pole's differential is used."""
    m, n = 13, 25
    a = jnp.asarray([[1.3, 0.2, 0.0], [0.1, 1.0, -0.3], [0.0, 0.4, 0.8]])
    f = jnp.einsum("ij,jmn->imn", a, ej.sphere_points(m, n))
    turn = ej.so3_exp(jnp.asarray([0.0, -0.5 * np.pi, 0.0]))  # x axis -> z axis, rounded
    gamma = jnp.einsum("ij,jmn->imn", turn, ej.sphere_points(m, n))
    i, j = (m - 1) // 2, 0
    off_axis = float(jnp.hypot(gamma[0, i, j], gamma[1, i, j]))
    assert 0.0 < off_axis < 1e-12  # a rounding off the pole, not on it
    u = jnp.asarray([0.3, -0.5, 0.2])[:, None, None]
    d = u - jnp.sum(u * gamma, axis=0, keepdims=True) * gamma
    _, tangent = jax.jvp(lambda g: ej.reparametrize(f, g, method=method), (gamma,), (d,))
    exact = jnp.einsum("ij,jmn->imn", a, d)
    error = float(jnp.linalg.norm(tangent[:, i, j] - exact[:, i, j]))
    # The pole's differential as in test_derivative_in_gamma_holds_on_the_poles, at 13 rows
    # (spline measured 2.6e-5, fourth order; bicubic's central difference loses 1 - sin(h)
    # / h = 1.1 %). The chart gave 0.48 against 0.59 here.
    bound = 1e-4 if method == "spline" else 4e-2
    assert error <= bound * float(jnp.linalg.norm(exact[:, i, j]))


@pytest.mark.parametrize("method", ["bicubic", "spline", "coefficients"])
def test_directional_derivatives_are_the_reads_jvp(method):
    """The chain rule's reader (one stencil gather, the weights' slopes) gives the jvp of
    sample_points along each direction, the pole rule included (points on both poles and
    one rounding off the axis), and so does its reverse-mode derivative in the points."""
    rng = np.random.default_rng(11)
    f = shapes.sample(shapes.bumpy, 25, 49)
    points = rng.standard_normal((3, 6, 7))
    points[:, 0, :3] = np.asarray([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1e-17, 0.0, 1.0]]).T
    points = jnp.asarray(points / np.linalg.norm(points, axis=0))
    directions = tuple(jnp.asarray(rng.standard_normal((3, 6, 7))) for _ in range(2))

    def by_jvp(p, ds):
        return tuple(jax.jvp(lambda q: sample_points(f, q, method), (p,), (d,))[1] for d in ds)

    for new, old in zip(
        directional_derivatives(f, points, directions, method),
        by_jvp(points, directions),
        strict=True,
    ):
        np.testing.assert_allclose(new, old, rtol=0, atol=1e-12 * float(jnp.abs(old).max()))
    w = jnp.asarray(rng.standard_normal((3, 6, 7)))

    def pairing(read):  # the direction moves with the points, as gamma's frame does
        return lambda p: jnp.sum(read(p, (p + directions[0],))[0] * w)

    new = jax.grad(pairing(lambda p, ds: directional_derivatives(f, p, ds, method)))(points)
    old = jax.grad(pairing(by_jvp))(points)
    np.testing.assert_allclose(new, old, rtol=0, atol=1e-10 * float(jnp.abs(old).max()))


def test_inputs_are_made_well_formed_at_the_poles_and_seam():
    """Pole rows and seam within the checks' tolerance are made exact (math §1): a pole row
    off by 1e-10 is one point again, and a well-formed input comes back bitwise."""
    from elastic_jax._geometry.validation import as_surface

    f = np.asarray(shapes.sample(shapes.bumpy, 13, 25))
    rough = f.copy()
    rng = np.random.default_rng(0)
    rough[:, 0, :] += 1e-10 * rng.standard_normal((3, 25))
    rough[:, :, -1] += 1e-10 * rng.standard_normal((3, 13))
    made = np.asarray(as_surface(rough, "f"))
    assert np.ptp(made[:, 0, :], axis=1).max() == 0.0 and np.ptp(made[:, -1, :], axis=1).max() == 0
    assert np.array_equal(made[:, :, -1], made[:, :, 0])
    assert np.abs(made - f).max() <= 2e-10  # moved by the perturbation, no more
    assert np.array_equal(np.asarray(as_surface(f, "f")), f)


def test_errors():
    with pytest.raises(ValueError, match=r"Lbar = 2\(degree \+ 1\)\^2 - 2 = 70"):
        ej.diffeomorphism(np.zeros(5), 25, 49, DEGREE)
    with pytest.raises(ValueError, match="method must be one of"):
        ej.reparametrize(ej.sphere_points(13, 25), ej.sphere_points(13, 25), method="nearest")
    with pytest.raises(ValueError, match=r"gamma must have shape \(3, p, q\)"):
        ej.reparametrize(ej.sphere_points(13, 25), np.zeros((2, 3, 5, 5)))


@pytest.mark.parametrize("grid", [(13, 25), (14, 27)])
def test_the_spline_frame_is_the_splines_derivative_at_the_knots(grid):
    """spline_frame (a Fourier multiplier) against the derivative of the spline's own
    evaluation (reparametrize's JVP along the sphere's unit frame at the grid points): the
    same numbers by two computations, to rounding, on an odd and an even number of rows."""
    from elastic_jax._geometry.differential import interior_frame
    from elastic_jax._geometry.grid import sphere_tangents_np
    from elastic_jax._geometry.reparam import spline_frame

    m, n = grid
    f = shapes.sample(shapes.bumpy, m, n, rotation=shapes.random_rotation(3))
    e = ej.sphere_points(m, n)[:, 1:-1, :-1]
    frame = spline_frame(f)
    for a, t in zip(frame, sphere_tangents_np(m, n), strict=True):
        t = jnp.asarray(t[:, 1:-1, :-1])
        _, along = jax.jvp(lambda p: ej.reparametrize(f, p, "spline"), (e,), (t,))
        assert float(jnp.max(jnp.abs(a - along))) <= 1e-12 * float(jnp.max(jnp.abs(along)))
    # and not the central differences (second order), which differ at this grid
    central = interior_frame(f)
    assert float(jnp.max(jnp.abs(frame[1] - central[1]))) > 1e-4


@pytest.mark.parametrize("factor", [2, 3])
def test_spline_upsample_is_the_spline_read_at_the_finer_points(factor):
    # The spline of a Moebius map's samples (13 x 25) at every point of the grid 2 and
    # 3 times finer: the fixed-offset filter against the general read (measured
    # 1.5e-15 and 1.1e-15), pole rows and seam included.
    from elastic_jax._geometry.grid import sphere_points

    m, n = 13, 25
    gamma = ej.moebius(sphere_points(m, n, jnp.float64), jnp.asarray([0.55, 0.3, 0.1]))
    points = sphere_points(factor * (m - 1) + 1, factor * (n - 1) + 1, jnp.float64)
    read = reparametrize_unchecked(gamma, points, method="spline")
    upsampled = spline_upsample(gamma, factor)
    assert upsampled.shape == read.shape
    np.testing.assert_allclose(np.asarray(upsampled), np.asarray(read), rtol=0, atol=1e-13)
    # At the working grid's own points it is the samples themselves.
    np.testing.assert_allclose(
        np.asarray(upsampled[:, ::factor, ::factor]), np.asarray(gamma), rtol=0, atol=1e-14
    )
