import jax.numpy as jnp
import numpy as np
import pytest
import scipy.special

import elastic_jax as ej


def _gram(basis, m, n):
    w = np.asarray(ej.quadrature_weights(m, n))
    b = np.asarray(basis)
    return np.einsum("aimn,bimn,mn->ab", b, b, w)


def _deviation(basis, m, n):
    g = _gram(basis, m, n)
    return np.abs(g - np.eye(len(g))).max()


def test_basis_sizes():
    assert ej.surface_basis(25, 49, 7).shape == (189, 3, 25, 49)  # 3((7 + 1)^2 - 1)
    assert ej.vector_field_basis(25, 49, 7).shape == (126, 3, 25, 49)  # 2(7 + 1)^2 - 2
    assert ej.real_sph_harm(25, 49, 7).values.shape == (64, 25, 49)


def test_gram_matrices_are_near_the_identity_and_converge():
    # The trapezoid rule in phi misses the zonal harmonics' diagonal by O(h^2 l^2).
    for degree in range(1, 7):
        assert _deviation(ej.surface_basis(25, 49, degree), 25, 49) < 2e-2
        assert _deviation(ej.vector_field_basis(25, 49, degree), 25, 49) < 2e-2
    for basis in (ej.surface_basis, ej.vector_field_basis):
        coarse = _deviation(basis(25, 49, 7), 25, 49)
        fine = _deviation(basis(50, 99, 7), 50, 99)
        assert coarse < 2.5e-2 and fine < 6e-3 and coarse / fine > 4.0


def test_high_degrees_are_accurate():
    sh = ej.real_sph_harm(50, 99, 25)
    y = np.asarray(sh.values)
    assert np.isfinite(y).all() and np.isfinite(np.asarray(sh.d_phi)).all()
    w = np.asarray(ej.quadrature_weights(50, 99))
    gram = np.einsum("amn,bmn,mn->ab", y, y, w)
    assert np.abs(gram - np.eye(len(gram))).max() < 0.1
    assert np.linalg.cond(gram) < 2.0
    # Against scipy's complex harmonics: Y_lk = sqrt2 (-1)^k Re Y_l^k for k > 0.
    phi, theta = (np.asarray(a) for a in ej.grid_angles(50, 99))
    l, k = 25, 17
    index = l * l + l + k
    complex_y = scipy.special.sph_harm_y(l, k, phi[:, None], theta[None, :])
    np.testing.assert_allclose(y[index], np.sqrt(2) * (-1) ** k * complex_y.real, atol=1e-12)


def test_analytic_derivatives():
    m, n = 401, 801
    sh = ej.real_sph_harm(m, n, 6)
    y, d_phi, d_theta = (np.asarray(a) for a in (sh.values, sh.d_phi, sh.d_theta))
    # theta: d/dtheta cos(k theta) = -k sin(k theta), so dY_{l,k} = -k Y_{l,-k} exactly.
    for l, k in [(1, 1), (4, 3), (6, 6)]:
        plus, minus = l * l + l + k, l * l + l - k
        np.testing.assert_allclose(d_theta[plus], -k * y[minus], atol=1e-12)
        np.testing.assert_allclose(d_theta[minus], k * y[plus], atol=1e-12)
    # phi: a fourth-order central difference (error ~ h^4 l^5 / 30 ~ 1e-6).
    h = np.pi / (m - 1)
    fd = (-y[:, 4:] + 8 * y[:, 3:-1] - 8 * y[:, 1:-3] + y[:, :-4]) / (12 * h)
    np.testing.assert_allclose(fd, d_phi[:, 2:-2], atol=1e-5)


def test_vector_fields_are_tangent():
    for m, n in [(12, 25), (25, 49), (50, 99)]:
        v = np.asarray(ej.vector_field_basis(m, n, 7 if m > 12 else 5))
        x = np.asarray(ej.sphere_points(m, n))
        assert np.abs(np.einsum("aimn,imn->amn", v, x)).max() < 1e-12
        assert np.all(v[..., 0, :] == v[..., 0, :1])  # one vector per pole


def test_the_diff_steps_separable_sum_is_the_dense_one():
    """The registration's Diff step sums its vector fields in separable form
    (harmonics.FieldTables): the same step and gradient as the dense sum, at the degree
    limit of an odd-sized grid too."""
    import jax

    from elastic_jax._geometry.bases import make_bases
    from elastic_jax._geometry.harmonics import vector_fields_np
    from elastic_jax._registration.problem import _step_field

    for m, n, degree in [(7, 13, 2), (12, 25, 5), (25, 49, 8)]:
        bases = make_bases(m, n, ej.ShapeOptions(vf_degree=degree, degree=2), jnp.float64)
        fields = jnp.asarray(vector_fields_np(m, n, degree))
        e1 = ej.sphere_points(m, n)
        rng = np.random.default_rng(m)
        y = jnp.asarray(0.05 * rng.normal(size=fields.shape[0]))
        weights = jnp.asarray(rng.normal(size=(3, m, n)))

        def dense(y, fields=fields, e1=e1, scale=bases.field_scale):
            w = e1 + jnp.einsum("k,kimn->imn", y * scale, fields)
            return w / jnp.linalg.norm(w, axis=0, keepdims=True)

        def separable(y, bases=bases, e1=e1):
            return _step_field(y, bases, e1)

        np.testing.assert_allclose(separable(y), dense(y), rtol=0, atol=1e-14)
        g1, g2 = (
            jax.grad(lambda y, f=f, w=weights: jnp.sum(w * f(y)))(y) for f in (separable, dense)
        )
        np.testing.assert_allclose(g1, g2, rtol=1e-12, atol=1e-12)


def test_the_refinements_separable_factors_are_the_harmonics():
    """The refinement evaluates the path's harmonics on its fine grid from separable
    factors (harmonic_factors_np): their outer products are harmonics_np's values, and
    the perturbation's frames equal the (K, 2 P) table's product (basis_np) to rounding."""

    from elastic_jax._geometry.bases import basis_np, make_bases
    from elastic_jax._geometry.harmonics import harmonic_factors_np, harmonics_np
    from elastic_jax._registration.problem import Problem, refined_frames

    for m, n, degree in [(7, 13, 2), (25, 49, 7), (49, 97, 7)]:
        rows, columns = harmonic_factors_np(m, n, degree)
        values = harmonics_np(m, n, degree).values
        outer = np.einsum("ki,kj->kij", rows, columns)
        np.testing.assert_allclose(outer, values, rtol=0, atol=1e-14)
    # On 7 x 13 (the refinement grid of a 4 x 7 working grid: 2 (4 - 1) + 1, 2 (7 - 1) + 1).
    bases = make_bases(4, 7, ej.ShapeOptions(degree=1, vf_degree=1), jnp.float64)
    assert bases.fine_rows.shape == (3, 7) and bases.fine_columns.shape == (3, 13)
    table = basis_np(7, 13, 1)[1]
    rng = np.random.default_rng(0)
    c = jnp.asarray(rng.normal(size=(2, 9)))  # N = 4: two interior times, 3 x 3
    zeros = [jnp.zeros((4, 3, 5, 12))] * 2
    prob = Problem(None, None, None, None, bases, None, None)
    a1, a2 = refined_frames(zeros, prob, c)
    pert = (c.reshape(-1, 3) @ table).reshape(2, 3, 2 * 60)
    np.testing.assert_allclose(a1[1:-1].reshape(2, 3, 60), pert[..., :60], atol=1e-13)
    np.testing.assert_allclose(a2[1:-1].reshape(2, 3, 60), pert[..., 60:], atol=1e-13)
    assert float(jnp.max(jnp.abs(a1[0]))) == 0.0 and bool(jnp.isfinite(a2).all())


def test_degree_limits():
    assert (
        ej.max_degree(50, 99) == 47 and ej.max_degree(25, 49) == 22 and ej.max_degree(12, 25) == 9
    )
    with pytest.raises(
        ValueError, match=r"degree=23 is too high for the 25 x 49 grid: the limit is 22"
    ):
        ej.surface_basis(25, 49, 23)
    with pytest.raises(ValueError, match="integer >= 1"):
        ej.vector_field_basis(25, 49, 0)
    assert jnp.asarray(ej.real_sph_harm(50, 99, 47).values).shape[0] == 48**2
