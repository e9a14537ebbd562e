import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import elastic_jax as ej
from elastic_jax import shapes
from elastic_jax._geometry.energy import _path_energy

from .conftest import load_shape, relerr

# docs/math.md §2: exact discretization, straight line cat1 -> cat2, N = 13, 50 x 99.
CAT_REFERENCE = [
    ((1.0, 1.0, 0.1, 0.0), 9.9263523348, 3.1433333512),
    ((0.0, 0.5, 1.0, 0.0), 2.6979328566, 1.6251290345),
    ((1.0, 0.0, 1.0, 1.0), 17.2739622485, 4.1490992836),
]


@pytest.mark.data
@pytest.mark.parametrize(("abcd", "energy", "length"), CAT_REFERENCE)
def test_exact_discretization_values_on_the_cats(cats, abcd, energy, length):
    path = ej.straight_path(*cats, 13)
    metric = ej.SplitMetric(*abcd)
    # docs/math.md §2's table is the forward scheme of docs/math.md §4.
    assert float(ej.path_energy(metric, path, "forward")) == pytest.approx(energy, rel=1e-8)
    assert float(ej.path_length(metric, path, "forward")) == pytest.approx(length, rel=1e-8)


@pytest.mark.data
def test_no_absolute_regularization_on_the_small_hand():
    hand = load_shape("hand4")  # coordinates about 5e-3
    cat = load_shape("cat1")
    # A second small surface: the cat scaled to the hand's area, centered on it.
    scale = np.sqrt(float(ej.surface_area(hand) / ej.surface_area(cat)))
    target = np.asarray(ej.center(cat)) * scale + (hand.mean(axis=(1, 2)))[:, None, None]
    path = ej.straight_path(hand, target, 7)
    metric = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)
    small = float(ej.path_energy(metric, path))
    large = float(ej.path_energy(metric, 1e3 * path)) / 1e6
    assert small == pytest.approx(large, rel=1e-10)
    assert small > 0


def _small_path(n_times=5, m=9, n=17):
    f1 = shapes.sample(shapes.bumpy, m, n)
    f2 = shapes.sample(shapes.bent_cylinder, m, n)
    return ej.straight_path(f1, f2, n_times)


def test_straight_path_end_points_and_linearity():
    f1, f2 = shapes.sample(shapes.bumpy, 13, 25), shapes.sample(shapes.ellipsoid, 13, 25)
    path = ej.straight_path(f1, f2, 9)
    assert path.shape == (9, 3, 13, 25)
    assert bool(jnp.all(path[0] == f1)) and bool(jnp.all(path[-1] == f2))
    np.testing.assert_allclose(path[3], 0.625 * f1 + 0.375 * f2, atol=1e-15)
    batched = ej.straight_path(jnp.stack([f1, f2]), f2, 4)
    assert batched.shape == (2, 4, 3, 13, 25)


def test_energy_bounds_length_and_schemes_agree_under_refinement():
    f1, f2 = shapes.sample(shapes.ellipsoid, 13, 25), shapes.sample(shapes.bumpy, 13, 25)
    metric = ej.SplitMetric(1.0, 1.0, 0.1, 0.2)
    gaps = []
    for n_times in (5, 9, 17):
        path = ej.straight_path(f1, f2, n_times)
        energy, length = ej.path_energy(metric, path), ej.path_length(metric, path)
        assert float(length) ** 2 <= float(energy) * (1 + 1e-14)  # Cauchy-Schwarz
        central = ej.path_energy(metric, path, scheme="central")
        gaps.append(abs(float(energy - central)) / float(energy))
    # Both schemes discretize the same integral: their gap shrinks like 1/T.
    assert gaps[1] < 0.6 * gaps[0] and gaps[2] < 0.6 * gaps[1]


def test_central_scheme_is_symmetric_under_reversal():
    path = _small_path(6)
    metric = ej.SplitMetric(1.0, 0.5, 0.3, 0.1)
    assert (
        relerr(
            ej.path_energy(metric, path[::-1], scheme="central"),
            ej.path_energy(metric, path, scheme="central"),
        )
        < 1e-13
    )


def test_jit_matches_eager_and_vmap_matches_a_loop():
    metric = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)
    paths = jnp.stack([_small_path(5), _small_path(5)[::-1], 1.5 * _small_path(5)])
    looped = jnp.stack([ej.path_energy(metric, p) for p in paths])
    vmapped = jax.vmap(lambda p: ej.path_energy(metric, p))(paths)
    batched = ej.path_energy(metric, paths)
    jitted = jax.jit(lambda p: ej.path_energy(metric, p))(paths[0])
    assert relerr(vmapped, looped) < 1e-14
    assert relerr(batched, looped) < 1e-14
    assert relerr(jitted, looped[0]) < 1e-14
    over_metrics = jax.vmap(lambda b: ej.path_energy(ej.SplitMetric(1.0, b, 0.1, 0.0), paths[0]))(
        jnp.asarray([1.0, 2.0])
    )
    assert (
        relerr(over_metrics[1], ej.path_energy(ej.SplitMetric(1.0, 2.0, 0.1, 0.0), paths[0]))
        < 1e-14
    )


@pytest.mark.parametrize("scheme", [pytest.param("forward", marks=pytest.mark.slow), "central"])
def test_gradient_matches_finite_differences(scheme):
    """Derivatives along well-formed perturbations of the interior frames (poles stay constant)."""
    path = _small_path(4)
    m, n = path.shape[-2:]
    fields = jnp.stack(
        [shapes.sample(s, m, n) for s in (shapes.ellipsoid, shapes.bumpy, shapes.sphere)]
    )
    profile = jnp.asarray([0.0, 1.0, -0.5, 0.0])  # end frames fixed
    directions = profile[None, :, None, None, None] * fields[:, None]
    metric = ej.SplitMetric(1.0, 0.7, 0.2, 0.3)

    def moved(c):
        return path + jnp.einsum("k,k...->...", c, directions)

    c0 = jnp.asarray([0.05, -0.02, 0.1])
    check_grads(
        lambda c: ej.path_energy(metric, moved(c), scheme=scheme),
        (c0,),
        order=2,
        modes=["fwd", "rev"],
    )
    check_grads(
        lambda c: ej.path_length(metric, moved(c), scheme=scheme),
        (c0,),
        order=1,
        modes=["fwd", "rev"],
    )
    # The full gradient (what a solver sees) contracts to the directional derivatives.
    grad = jax.grad(lambda p: ej.path_energy(metric, p, scheme=scheme))(path)
    directional = jax.jacfwd(lambda c: ej.path_energy(metric, moved(c), scheme=scheme))(
        jnp.zeros(3)
    )
    np.testing.assert_allclose(jnp.einsum("k...,...->k", directions, grad), directional, rtol=1e-12)


def test_changing_coefficients_does_not_recompile():
    path = _small_path(5, 11, 21)
    ej.path_energy(ej.SplitMetric(1.0, 1.0, 0.1, 0.0), path)
    before = _path_energy._cache_size()
    values = [ej.path_energy(ej.SplitMetric(a, 2.0 * a, 0.1, a / 3), path) for a in (0.5, 2.0, 7.0)]
    assert _path_energy._cache_size() == before
    assert len({float(v) for v in values}) == 3
    traces = []

    @jax.jit
    def energy(metric):
        traces.append(None)
        return ej.path_energy(metric, path)

    for a in (1.0, 2.0, 3.0):
        energy(ej.SplitMetric(a, 1.0, 0.1, 0.0))
    assert len(traces) == 1


def test_float32_agrees_with_float64():
    path = _small_path(5, 13, 25)
    metric = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)
    e64 = ej.path_energy(metric, path)
    e32 = ej.path_energy(metric, path.astype(jnp.float32))
    assert e32.dtype == jnp.float32
    assert relerr(e32, e64) < 1e-5


@pytest.mark.parametrize("scheme", ["midpoint", "forward", "central"])
def test_the_energy_derivatives_from_the_integrands_partials_are_autodiffs(scheme, monkeypatch):
    """speed_density's derivative rule (partials computed once per point, issue 51)
    gives what autodiff through split_bilinear gives: the gradient in the path and in
    the metric, a Hessian-vector product (forward over reverse, as the saddle check and
    shooting take it), the metric's Hessian and a vmapped gradient."""
    from elastic_jax._geometry import differential, energy, metric

    def plain(m, b1, b2, v1, v2):
        return metric.split_bilinear(m, b1, b2, v1, v2, v1, v2)

    f1 = shapes.sample(shapes.bumpy, 9, 17)
    f2 = shapes.sample(shapes.bent_cylinder, 9, 17)
    path = ej.straight_path(f1, f2, 5)
    path = path + 0.01 * jnp.sin(jnp.arange(path.size, dtype=path.dtype).reshape(path.shape))
    coefficients = jnp.asarray([1.0, 1.0, 0.1, 0.3])
    tangent = jnp.cos(path)

    def quantities(energy_of):
        def e(c, p):
            return energy_of(ej.SplitMetric(*c), *differential.interior_frame(p), scheme)

        return [
            e(coefficients, path),
            jax.grad(e, argnums=1)(coefficients, path),
            jax.grad(e, argnums=0)(coefficients, path),
            jax.jvp(lambda p: jax.grad(e, argnums=1)(coefficients, p), (path,), (tangent,))[1],
            jax.hessian(e, argnums=0)(coefficients, path),
            jax.vmap(jax.grad(e, argnums=1), (None, 0))(
                coefficients, jnp.stack([path, 1.1 * path])
            ),
        ]

    new = jax.jit(lambda: quantities(energy.frame_energy))()
    monkeypatch.setattr(energy, "speed_density", plain)
    old = jax.jit(lambda: quantities(energy.frame_energy))()
    for a, b in zip(new, old, strict=True):
        assert float(jnp.max(jnp.abs(a - b))) <= 1e-12 * float(jnp.max(jnp.abs(b)))


def _area_density(f):
    """|f_theta x f_phi| / sin(phi) on the grid (math §2's frame), zero on the pole rows."""
    df = ej.differential(f)
    return jnp.linalg.norm(jnp.cross(df[:, 0], df[:, 1], axis=0), axis=0)


@pytest.mark.parametrize("abcd", [(1.0, 1.0, 0.1, 0.0), (0.0, 0.5, 1.0, 0.0), (2.0, 0.3, 0.0, 1.0)])
def test_the_volume_term_bounds_a_path_by_its_pointwise_change_of_area(abcd):
    """<xi_vol, xi_vol> = 2 (d_t sqrt(rho))^2 pointwise, so by Cauchy-Schwarz in time every
    path through a fixed correspondence costs at least 2 b int (sqrt(rho_1) - sqrt(rho_0))^2
    (the pointwise form of math §9's area bound). A scaled copy attains it exactly: along
    (1 - t + t s) f the change is all volume and its density is constant in time."""
    metric = ej.SplitMetric(*abcd)
    f = shapes.sample(shapes.bumpy, 13, 25)
    for s in (0.5, 1.7):
        energy = ej.path_energy(metric, ej.straight_path(f, s * f, 5))
        closed = 2.0 * metric.b * (s - 1.0) ** 2 * ej.integrate(_area_density(f))
        assert float(energy) == pytest.approx(float(closed), rel=1e-12)
    f1, f2 = shapes.sample(shapes.ellipsoid, 13, 25), f
    rho1, rho2 = _area_density(f1), _area_density(f2)
    bound = 2.0 * metric.b * ej.integrate((jnp.sqrt(rho2) - jnp.sqrt(rho1)) ** 2)
    straight = ej.path_energy(metric, ej.straight_path(f1, f2, 17))
    solved = ej.geodesic(f1, f2, metric, degree=4, n_times=9).energy
    assert 0.0 < float(bound) < float(solved) <= float(straight)


# energy_density: the path energy of each grid point, split by the metric's terms.
DENSITY_METRIC = ej.SplitMetric(1.0, 0.7, 0.3, 0.2)


@pytest.mark.parametrize("scheme", ["midpoint", "forward", "central"])
def test_the_energy_density_partitions_the_path_energy(scheme):
    f1 = shapes.sample(shapes.bumpy, 13, 25)
    f2 = shapes.sample(shapes.ellipsoid, 13, 25)
    paths = jnp.stack([ej.straight_path(f1, f2, 5), ej.straight_path(f2, 1.3 * f1, 5)])
    fields = ej.energy_density(DENSITY_METRIC, paths, scheme)
    assert fields.total.shape == (2, 13, 25)
    terms = fields.shear + fields.area + fields.bending + fields.rotation
    np.testing.assert_allclose(terms, fields.total, rtol=1e-13, atol=0.0)
    energy = ej.path_energy(DENSITY_METRIC, paths, scheme)
    np.testing.assert_allclose(fields.total.sum(axis=(-2, -1)), energy, rtol=1e-10)
    # Every term is a sum of squares; the poles carry no weight, the seam's two columns
    # share theirs.
    for field in fields:
        assert float(field.min()) >= 0.0
        assert float(jnp.abs(field[:, [0, -1], :]).max()) == 0.0
        np.testing.assert_array_equal(field[..., 0], field[..., -1])
    # Divided by the quadrature weights, the seam column reads as its neighbours do.
    per_area = fields.total[0, 1:-1] / ej.quadrature_weights(13, 25)[1:-1]
    assert float(jnp.abs(per_area[:, 0] - per_area[:, 1]).max()) < 0.5 * float(per_area.max())


def test_a_term_whose_coefficient_is_zero_is_zero_everywhere():
    path = ej.straight_path(
        shapes.sample(shapes.bumpy, 13, 25), shapes.sample(shapes.ellipsoid, 13, 25), 5
    )
    for k, name in enumerate(("shear", "area", "bending", "rotation")):
        abcd = [1.0, 0.7, 0.3, 0.2]
        abcd[k] = 0.0
        fields = ej.energy_density(ej.SplitMetric(*abcd), path)
        assert float(jnp.abs(getattr(fields, name)).max()) == 0.0
        others = [getattr(fields, n) for n in ("shear", "area", "bending", "rotation") if n != name]
        assert all(float(f.sum()) > 0.0 for f in others)


def test_concentric_spheres_put_their_energy_in_the_area_term():
    f = shapes.sample(shapes.sphere, 25, 49)
    fields = ej.energy_density(DENSITY_METRIC, ej.straight_path(f, 2.0 * f, 7))
    total = float(fields.total.sum())
    assert float(fields.area.sum()) == pytest.approx(total, rel=1e-12)
    for other in (fields.shear, fields.bending, fields.rotation):
        assert float(other.sum()) <= 1e-8 * total
    # The area term of a scaling by 2 is 2 b (2 - 1)^2 4 pi with the grid's area.
    area = float(ej.surface_area(f))
    assert total == pytest.approx(2.0 * DENSITY_METRIC.b * area, rel=1e-12)


def test_a_translation_costs_nothing_and_a_rotation_neither_shears_nor_changes_area():
    f = shapes.sample(shapes.bumpy, 13, 25)
    moved = ej.straight_path(f, f + jnp.array([0.3, -0.2, 0.5])[:, None, None], 5)
    for field in ej.energy_density(DENSITY_METRIC, moved):  # to the rounding of f + c
        assert float(jnp.abs(field).sum()) <= 1e-24
    # A rigid rotation of f, frame by frame: under the midpoint scheme each step's
    # velocity is a skew-symmetric map of its base frame, which has no symmetric part.
    axis = jnp.array([0.3, 0.5, 0.8]) / jnp.linalg.norm(jnp.array([0.3, 0.5, 0.8]))
    turns = [ej.so3_exp(t * 0.9 * axis) for t in jnp.linspace(0.0, 1.0, 7)]
    rotated = jnp.stack([jnp.einsum("ij,jmn->imn", r, f) for r in turns])
    fields = ej.energy_density(DENSITY_METRIC, rotated)
    total = float(fields.total.sum())
    assert float(fields.bending.sum()) > 0.1 * total
    assert float(fields.shear.sum()) <= 1e-12 * total
    assert float(fields.area.sum()) <= 1e-12 * total
