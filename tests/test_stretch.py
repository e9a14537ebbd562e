"""The stretched cells' finer quadrature of a registered path's energy (stretch.py)."""

import jax.numpy as jnp
import numpy as np
import pytest

import elastic_jax as ej
from elastic_jax import shapes
from elastic_jax._geometry.bases import make_bases
from elastic_jax._geometry.composition import compose
from elastic_jax._geometry.reparam import moebius
from elastic_jax._registration import problem as P

METRIC = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)


def _energy(f1, f2, grid, fraction, gamma=None, coefficients=None, subdivision=4, quadrature=1):
    """The path energy from f1 o gamma to f2 plus the perturbation on ``grid``; gamma a
    Moebius map sampled at the grid's points, or another grid's gamma read through its
    spline (the same continuous map)."""
    options = ej.ShapeOptions(
        grid=grid,
        rtol=None,
        stretch_quadrature=fraction,
        stretch_subdivision=subdivision,
        quadrature=quadrature,
    )
    bases = make_bases(*grid, options, f1.dtype)
    prob = P.make_problem(METRIC, f1, f2, bases, rigid=False, interpolation=options.interpolation)
    if gamma is None:
        gamma = moebius(prob.e1, jnp.asarray([0.55, 0.3, 0.1]))
    else:
        gamma = compose(P.gamma_source(options, gamma), prob.e1, "coefficients")
    if coefficients is None:
        coefficients = P.zero_coefficients(prob, options)
    energy = P.path_energy_at(prob, options, gamma, jnp.eye(3), coefficients)
    return float(energy), gamma, coefficients


@pytest.mark.parametrize(
    ("grid", "node_above", "stretched_below"),
    [((13, 25), 1e-2, 1e-3), pytest.param((25, 49), 1e-3, 1e-4, marks=pytest.mark.slow)],
)
def test_integrating_every_cell_finer_reaches_the_fine_grids_integral(
    grid, node_above, stretched_below
):
    # The same continuous path (the straight line from f1 o gamma, gamma the Moebius
    # map's spline on the coarse grid) integrated by the coarse grid's nodes, by its
    # cells 4 x 4 finer (all but those on a pole row), and by the nodes of the grid 8x
    # finer. 13 x 25: node rule 3.0e-2 off, every cell finer 2.6e-4; 25 x 49: 1.6e-3,
    # 1.1e-5. (A perturbation's frames are central differences at the nodes, read
    # bilinearly inside a cell; the fine grid's differences are another discretization.)
    f1 = shapes.sample(shapes.bumpy, 25, 49)
    f2 = shapes.sample(shapes.ellipsoid, 25, 49)
    node, gamma, coefficients = _energy(f1, f2, grid, 0.0)
    fine = tuple(8 * (k - 1) + 1 for k in grid)
    reference, _, _ = _energy(f1, f2, fine, 0.0, gamma=gamma, coefficients=coefficients)
    stretched, _, _ = _energy(f1, f2, grid, 1.0, coefficients=coefficients)
    assert abs(node - reference) / reference > node_above
    assert abs(stretched - reference) / reference < stretched_below


def test_the_stretched_cells_refine_the_finer_nodes_cells():
    # With quadrature 2 the cells are those of the grid twice finer (gamma read at its
    # nodes): every one of them 4 x 4 finer integrates the 13 x 25 working grid's path as
    # the grid 8x finer does. Measured: the finer nodes alone 1.4e-3 off, with every cell
    # refined 5.2e-5 (the working grid's cells refined 4 x 4: 2.6e-4, above).
    f1 = shapes.sample(shapes.bumpy, 25, 49)
    f2 = shapes.sample(shapes.ellipsoid, 25, 49)
    grid = (13, 25)
    _, gamma, coefficients = _energy(f1, f2, grid, 0.0)
    fine = tuple(8 * (k - 1) + 1 for k in grid)
    reference, _, _ = _energy(f1, f2, fine, 0.0, gamma=gamma, coefficients=coefficients)
    finer, _, _ = _energy(f1, f2, grid, 0.0, coefficients=coefficients, quadrature=2)
    both, _, _ = _energy(f1, f2, grid, 1.0, coefficients=coefficients, quadrature=2)
    assert abs(finer - reference) / reference > 5e-4
    assert abs(both - reference) / reference < 2e-4
    assert abs(both - reference) < 0.1 * abs(finer - reference)


def test_a_surface_and_itself_have_the_same_stretched_frames():
    # d(f, f) = 0: at the identity the sub-cells read f2 as they read f1 o gamma, through
    # the identity's interpolant (not the identity between the points): every cell of the
    # finer grid refined, the straight line from f to f has energy 0 to rounding, where
    # reading f2 at the sub-points themselves left d(f, f) at 2.4e-6 at 25 x 49.
    f = shapes.sample(shapes.bumpy, 25, 49)
    e1 = ej.sphere_points(13, 25, dtype=f.dtype)
    energy, _, _ = _energy(f, f, (13, 25), 1.0, gamma=e1, quadrature=2)
    assert abs(energy) < 1e-24


def test_the_stretched_cells_are_where_gamma_stretches():
    # The Moebius map phi_a stretches most around a / |a| (J = ((1 - |a|^2) / |x - a|^2)^2):
    # the chosen cells' J are the largest on the grid, and they lie around a / |a|.
    from elastic_jax._geometry.reparam import jacobian_determinant_unchecked
    from elastic_jax._registration.stretch import stretched_cells

    e1 = ej.sphere_points(25, 49)
    a = jnp.asarray([0.2, -0.4, 0.3])
    gamma = moebius(e1, a)
    rows, cols = stretched_cells(gamma, 0.05)
    jac = np.asarray(jacobian_determinant_unchecked(gamma))[1:-1, :-1]
    corners = np.maximum.reduce(
        [
            jac[rows, cols],
            jac[rows + 1, cols],
            jac[rows, (cols + 1) % 48],
            jac[rows + 1, (cols + 1) % 48],
        ]
    )
    assert len(rows) == int(0.05 * 22 * 48)
    assert corners.min() >= np.quantile(jac, 0.9)
    centre = np.asarray(e1)[:, rows + 1, cols]
    direction = np.asarray(a) / np.linalg.norm(a)
    assert np.median(direction @ centre) > 0.9


@pytest.mark.parametrize(
    ("changes", "says"),
    [
        ({"stretch_quadrature": 1.5}, r"in \[0, 1\]"),
        ({"stretch_quadrature": "all"}, "a number"),
        ({"stretch_quadrature": 0.03, "scheme": "forward"}, "midpoint"),
        ({"stretch_quadrature": 0.03, "differential": "grid"}, "chain"),
        ({"stretch_subdivision": 1}, "stretch_subdivision"),
    ],
)
def test_stretch_options_are_checked(changes, says):
    with pytest.raises(ej.InputError, match=says):
        ej.ShapeOptions(**changes)
