"""Meshes resample in their own frame: grids that follow rigid motions (issue 33, D1)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import trimesh

from elastic_jax import io, resample, shapes

from .conftest import load_shape
from .test_io import grid_directions
from .test_sphere_map import diagonal, off_mesh


def moved(
    mesh: trimesh.Trimesh, seed: int
) -> tuple[trimesh.Trimesh, np.ndarray, np.ndarray, float]:
    """The mesh under a random rotation, a translation several times its size and a scaling."""
    rng = np.random.default_rng(seed)
    r = np.asarray(shapes.random_rotation(seed))
    shift = rng.normal(size=3) * 5 * diagonal(mesh)
    scale = float(np.exp(rng.uniform(-2, 2)))
    v = scale * np.asarray(mesh.vertices) @ r.T + shift
    return trimesh.Trimesh(v, mesh.faces, process=False), r, shift, scale


def moved_grid(f: np.ndarray, r, shift, scale) -> np.ndarray:
    return scale * np.einsum("ij,jkl->ikl", r, f) + shift[:, None, None]


def shared_mesh(name: str, m: int, n: int) -> trimesh.Trimesh:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # resample's float64 note when x64 is off
        return io.grid_to_mesh(np.asarray(resample(load_shape(name), m, n)))


def box_mesh(a: float, b: float, c: float) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=(2 * a, 2 * b, 2 * c))


def test_the_moments_are_exact_integrals():
    # A box's surface, half-extents (a, b, c): int x^2 dA = 8 a^2 b c + 8 a^3 (b + c) / 3
    # over the area 8 (ab + bc + ca); the triangles are flat, so the formula is exact.
    a, b, c = 1.3, 0.7, 0.4
    frame = io.mesh_frame(box_mesh(a, b, c))
    second = [
        8 * p * p * q * r + 8 * p**3 * (q + r) / 3 for p, q, r in [(a, b, c), (b, c, a), (c, a, b)]
    ]
    second = np.array(second) / (8 * (a * b + b * c + c * a))
    np.testing.assert_allclose(frame.scale**2 * frame.moments, second, rtol=1e-13)
    np.testing.assert_allclose(np.abs(frame.axes), np.eye(3), atol=1e-13)
    assert "third moments vanish" in frame.undetermined
    # Subdividing a mesh keeps its (flat) surface, so exact moments do not change.
    mesh = io.grid_to_mesh(shapes.sample(shapes.bumpy, 13, 25))
    fine = trimesh.Trimesh(*trimesh.remesh.subdivide(mesh.vertices, mesh.faces), process=False)
    one, two = io.mesh_frame(mesh), io.mesh_frame(fine)
    assert one.undetermined == ""
    np.testing.assert_allclose(two.center, one.center, atol=1e-14)
    np.testing.assert_allclose(two.axes, one.axes, atol=1e-12)
    np.testing.assert_allclose(two.skewness, one.skewness, rtol=1e-12)
    np.testing.assert_allclose(two.scale, one.scale, rtol=1e-14)


def test_the_frame_follows_rigid_motions_and_scalings():
    mesh = io.grid_to_mesh(shapes.sample(shapes.bumpy, 13, 25))
    frame = io.mesh_frame(mesh)
    other, r, shift, scale = moved(mesh, 4)
    got = io.mesh_frame(other)
    np.testing.assert_allclose(got.axes, r @ frame.axes, atol=1e-13)
    np.testing.assert_allclose(got.center, scale * r @ frame.center + shift, atol=1e-12 * scale)
    np.testing.assert_allclose(got.scale, scale * frame.scale, rtol=1e-13)
    # A mirror image turns the frame's handedness back: det stays +1, the axes follow.
    mirror = trimesh.Trimesh(np.asarray(mesh.vertices) * [-1, 1, 1], mesh.faces[:, ::-1])
    assert np.linalg.det(io.mesh_frame(mirror).axes) == pytest.approx(1.0, abs=1e-13)


@pytest.mark.parametrize("method", ["auto", "radial", "spherical"])
def test_a_star_shaped_mesh_follows_rigid_motions_under_every_method(method):
    mesh = io.grid_to_mesh(shapes.sample(shapes.bumpy, 13, 25))
    f = io.mesh_to_grid(mesh, 13, 25, method=method)
    size = diagonal(mesh)
    for seed in (1, 2):
        other, r, shift, scale = moved(mesh, seed)
        g = io.mesh_to_grid(other, 13, 25, method=method)
        # measured 2e-15 .. 3e-13 of the size
        assert np.abs(g - moved_grid(f, r, shift, scale)).max() <= 1e-6 * scale * size
        assert off_mesh(other, g) <= 1e-10
    assert off_mesh(mesh, f) <= 1e-10


def test_a_given_center_moves_with_the_mesh():
    mesh = io.grid_to_mesh(shapes.sample(shapes.bumpy, 13, 25))
    c = np.array([0.05, -0.1, 0.02])
    f = io.mesh_to_grid(mesh, 13, 25, center=c)
    other, r, shift, scale = moved(mesh, 3)
    g = io.mesh_to_grid(other, 13, 25, center=scale * r @ c + shift)
    assert np.abs(g - moved_grid(f, r, shift, scale)).max() <= 1e-6 * scale * diagonal(mesh)
    # the rays start at c: every point minus c is along the frame's grid direction
    u = (f - c[:, None, None]) / np.linalg.norm(f - c[:, None, None], axis=0)
    axes = io.mesh_frame(mesh).axes
    expected = np.einsum("ij,jkl->ikl", axes, grid_directions(13, 25))
    np.testing.assert_allclose(u, expected, atol=1e-12)


@pytest.mark.data
@pytest.mark.parametrize(
    "name, m, n",
    [
        pytest.param("cat1", 25, 49, marks=pytest.mark.slow),
        ("hand4", 25, 49),
        pytest.param("cat2", 50, 99, marks=pytest.mark.slow),
        pytest.param("horse0", 50, 99, marks=pytest.mark.slow),
        pytest.param("hand4", 50, 99, marks=pytest.mark.slow),
        pytest.param("cat1", 50, 99, marks=pytest.mark.slow),
    ],
)
def test_the_shared_shapes_follow_rigid_motions(name, m, n):
    # Not star-shaped about any point: "auto" is the spherical map. Before the map was
    # computed in the mesh's frame from snapped coordinates, moved copies of these meshes
    # gave grids up to 0.70 of the size apart (principal axes ignored) or 7e-4 (rounding
    # amplified by the optimizer).
    mesh = shared_mesh(name, m, n)
    f = io.mesh_to_grid(mesh, m, n)
    assert off_mesh(mesh, f) <= 1e-10
    other, r, shift, scale = moved(mesh, 7)
    g = io.mesh_to_grid(other, m, n)
    # measured at 50 x 99 (2 motions each): 4e-15 .. 2e-11 of the size
    assert np.abs(g - moved_grid(f, r, shift, scale)).max() <= 1e-6 * scale * diagonal(mesh)
    assert off_mesh(other, g) <= 1e-10


@pytest.mark.parametrize(
    "make, reason",
    [
        (lambda: trimesh.creation.icosphere(subdivisions=2), "second moments"),
        (lambda: box_mesh(1.0, 0.6, 0.3), "third moments vanish"),
        (
            lambda: io.grid_to_mesh(shapes.sample(shapes.bent_cylinder, 13, 25, curvature=1.0)),
            "third moments vanish",
        ),
    ],
    ids=["sphere", "box", "bent tube"],
)
def test_a_symmetric_mesh_is_reported_and_resampled_in_the_input_axes(make, reason):
    mesh = make()
    assert reason in io.mesh_frame(mesh).undetermined
    with pytest.warns(io.FrameWarning, match=reason):
        f = io.mesh_to_grid(mesh, 9, 17)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        g = io.mesh_to_grid(mesh, 9, 17, frame="input")
        # A frame the caller gives (e.g. from landmarks) moves with the mesh they move.
        other, r, shift, scale = moved(mesh, 5)
        h = io.mesh_to_grid(other, 9, 17, frame=r)
    np.testing.assert_array_equal(f, g)
    assert np.abs(h - moved_grid(g, r, shift, scale)).max() <= 1e-9 * scale * diagonal(mesh)


def test_frame_options_are_checked():
    mesh = io.grid_to_mesh(shapes.sample(shapes.bumpy, 9, 17))
    with pytest.raises(ValueError, match="frame must be one of"):
        io.mesh_to_grid(mesh, 9, 17, frame="world")
    with pytest.raises(ValueError, match="rotation"):
        io.mesh_to_grid(mesh, 9, 17, frame=np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError, match="rotation"):
        io.mesh_to_grid(mesh, 9, 17, frame=np.eye(3)[:2])
    with pytest.raises(ValueError, match="no frame"):
        io.mesh_to_grid(mesh, 9, 17, frame="input", sphere=np.asarray(mesh.vertices))


# Issue 48 item 4: a mesh in its own units. hand4 comes in metres (1.4 cm across); the
# scales put it in kilometres-ish (1e-3) and millimetres-ish (1e3).
SCALES = (1e-3, 1.0, 1e3)


def scaled(mesh: trimesh.Trimesh, s: float) -> trimesh.Trimesh:
    return trimesh.Trimesh(s * np.asarray(mesh.vertices), mesh.faces, process=False)


def resampled_at_scales(mesh: trimesh.Trimesh, method: str, m: int, n: int) -> dict:
    """The grid of each scaled copy of the mesh, checked on its mesh; by scale."""
    grids = {}
    for s in SCALES:
        other = scaled(mesh, s)
        if method == "sphere":  # the sphere map computed for this copy, then given back
            sphere = io.spherical_parametrization(other).sphere
            grids[s] = io.mesh_to_grid(other, m, n, sphere=sphere)
        else:
            grids[s] = io.mesh_to_grid(other, m, n, method=method)
        # off_mesh is scale-free (the mesh moved to unit size before any trimesh query)
        assert off_mesh(other, grids[s]) <= 1e-10, (s, off_mesh(other, grids[s]))
    return grids


@pytest.mark.data
@pytest.mark.parametrize(
    "name, method",
    [("hand4", "spherical"), ("hand4", "auto"), ("hand4", "sphere"), ("bumpy", "radial")],
)
def test_the_mesh_path_works_in_the_meshs_own_units(name, method):
    # Measured (25 x 49 meshes resampled at 25 x 49): on the mesh to 4e-16 of the
    # diagonal and equal up to the scale to 2e-15 at every scale and method. The 1.2 % off
    # the mesh once reported for hand4 in metres was trimesh.proximity.closest_point's
    # (its triangles.closest_point compares squared and fourth-power lengths with
    # tol.zero = 1e-13); off_mesh measures in units of the diagonal.
    m, n = 25, 49
    if name == "bumpy":  # the shared shapes are star-shaped about no point
        mesh = io.grid_to_mesh(shapes.sample(shapes.bumpy, m, n))
    else:
        mesh = shared_mesh(name, m, n)
    grids = resampled_at_scales(mesh, method, m, n)
    size = diagonal(mesh)
    for s in SCALES:
        assert np.abs(grids[s] / s - grids[1.0]).max() <= 1e-10 * size, s


@pytest.mark.data
def test_star_center_works_in_the_meshs_own_units():
    # trimesh zeroes the normals of faces with edges under ~3e-7 and HiGHS's tolerances
    # are absolute: star_center called a tiny hand star-shaped and a tiny bumpy sphere not.
    bumpy = io.grid_to_mesh(shapes.sample(shapes.bumpy, 25, 49))
    hand = shared_mesh("hand4", 25, 49)
    c = io.star_center(bumpy)
    assert c is not None and io.star_center(hand) is None
    for s in (1e-6, *SCALES):
        assert io.star_center(scaled(hand, s)) is None, s
        got = io.star_center(scaled(bumpy, s))
        assert got is not None, s
        assert np.abs(got / s - c).max() <= 1e-10 * diagonal(bumpy), s


@pytest.mark.data
def test_load_surface_works_in_the_meshs_own_units(tmp_path):
    # trimesh.load(process=True) merged vertices closer than 1e-8 in any unit: hand4 in
    # kilometres (1.4e-5 across) lost vertices. Each file is read as the in-memory mesh of
    # its (float32) vertices resamples.
    mesh = shared_mesh("hand4", 25, 49)
    for s in (1e-5, 1.0, 1e3):
        other = scaled(mesh, s)
        path = tmp_path / f"hand_{s:g}.ply"
        other.export(path)
        f = io.load_surface(path, 25, 49)
        rounded = trimesh.Trimesh(
            np.asarray(other.vertices).astype(np.float32).astype(np.float64),
            other.faces,
            process=False,
        )
        np.testing.assert_array_equal(f, io.mesh_to_grid(rounded, 25, 49))
        assert off_mesh(rounded, f) <= 1e-10
