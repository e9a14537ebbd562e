import numpy as np
import pytest

import elastic_jax as ej
from elastic_jax import shapes

M, N = 13, 25


def _surface():
    return np.array(shapes.sample(shapes.bumpy, M, N))


def test_a_well_formed_surface_passes():
    f = _surface()
    assert ej.validate_surface(f, "f").shape == (3, M, N)


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda f: f[:2], r"f must have shape \(\.\.\., 3, m, n\); got shape \(2, 13, 25\)"),
        (lambda f: f[0], r"must have shape"),
        (lambda f: f[:, :, :-1], r"even number of columns n=24"),
        (lambda f: f[:, :4], r"at least 5 rows and 5 columns; got m=4"),
    ],
)
def test_shape_errors(make, message):
    with pytest.raises(ValueError, match=message):
        ej.surface_area(make(_surface()))


def test_non_finite_values_are_located():
    f = _surface()
    f[1, 4, 7] = np.nan
    with pytest.raises(ValueError, match=r"non-finite.*coordinate 1 at row i=4, column j=7"):
        ej.srnf(f)
    batch = np.stack([_surface(), _surface()])
    batch[1, 0, 3, 2] = np.inf
    with pytest.raises(
        ValueError,
        match=r"row i=3, column j=2 of item 1\b",
    ):
        ej.surface_area(batch)


def test_pole_and_seam_mismatches_are_located():
    f = _surface()
    f[0, 0, 5] += 1e-3
    with pytest.raises(ValueError, match=r"north pole row \(i=0\) is not constant.*column j=5"):
        ej.surface_area(f)
    f = _surface()
    f[2, -1, 9] -= 1e-3
    with pytest.raises(ValueError, match=r"south pole row \(i=12\) is not constant.*column j=9"):
        ej.surface_area(f)
    f = _surface()
    f[0, 6, -1] += 1e-3
    with pytest.raises(ValueError, match=r"seam column j=24 does not repeat column 0.*row i=6"):
        ej.surface_area(f)
    # Tolerances are relative to the surface's size: tiny surfaces are judged fairly.
    small = _surface() * 1e-6
    small[0, 0, 5] += 1e-12
    with pytest.raises(ValueError, match=r"north pole"):
        ej.surface_area(small)
    ok = _surface() * 1e-6
    ok[0, 0, 5] += 1e-16
    assert float(ej.surface_area(ok)) > 0


def test_non_immersions_are_located():
    f = _surface()
    f[:, 5:8, :] = f[:, 5:6, :1]  # three interior rows collapsed to one point
    with pytest.raises(
        ValueError, match=r"not an immersion: the area element vanishes at .* row i=5"
    ):
        ej.metric_inner(ej.SplitMetric(1, 1, 1, 0), f, f, f)
    with pytest.raises(ValueError, match="single point"):
        ej.surface_area(np.zeros((3, M, N)))


def test_path_and_argument_errors():
    f = _surface()
    with pytest.raises(ValueError, match=r"N >= 2"):
        ej.path_energy(ej.SplitMetric(1, 1, 1, 0), f[None])
    with pytest.raises(ValueError, match="scheme must be one of"):
        ej.path_energy(ej.SplitMetric(1, 1, 1, 0), np.stack([f, f]), scheme="backward")
    with pytest.raises(ValueError, match="n_times must be an integer >= 2"):
        ej.straight_path(f, f, 1)
    with pytest.raises(ValueError, match="same grid"):
        ej.straight_path(f, np.asarray(shapes.sample(shapes.bumpy, M, 27)), 3)
    with pytest.raises(ValueError, match=r"u must be a field on the grid of f"):
        ej.metric_inner(ej.SplitMetric(1, 1, 1, 0), f, f[:, :, :5], f)
