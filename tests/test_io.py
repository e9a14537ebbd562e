"""Reading and writing surfaces: mesh <-> grid conversion, file formats, atomic writes."""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest
import scipy.io
import trimesh

import elastic_jax as ej
from elastic_jax import io, resample, shapes
from elastic_jax._geometry.grid import angles_np

from .conftest import fsaverage5

AXES = np.array([1.0, 0.7, 0.5])
# Smallest radius of curvature of that ellipsoid: c^2 / a, at the ends of the long axis.
R_MIN = AXES.min() ** 2 / AXES.max()

# The synthetic meshes here are symmetric (spheres, ellipsoids, tubes): their frame is the
# input's, which test_mesh_frame.py tests with the warning it gives.
pytestmark = pytest.mark.filterwarnings("ignore::elastic_jax.io.FrameWarning")


def grid_directions(m: int, n: int) -> np.ndarray:
    """Unit vectors e1 on the grid, (3, m, n) float64, computed here in numpy."""
    phi, theta = angles_np(m, n)
    u = np.stack(
        [
            np.outer(np.sin(phi), np.cos(theta)),
            np.outer(np.sin(phi), np.sin(theta)),
            np.outer(np.cos(phi), np.ones(n)),
        ]
    )
    u[:, 0, :] = np.array([0.0, 0.0, 1.0])[:, None]
    u[:, -1, :] = np.array([0.0, 0.0, -1.0])[:, None]
    u[:, :, -1] = u[:, :, 0]
    return u


def radial_ellipsoid(m: int, n: int) -> np.ndarray:
    """The ellipsoid point in each grid direction u from its centre: u / |diag(1/AXES) u|."""
    u = grid_directions(m, n)
    return u / np.sqrt(np.sum((u / AXES[:, None, None]) ** 2, axis=0))


def ellipsoid_mesh(subdivisions: int) -> trimesh.Trimesh:
    """An icosphere stretched onto the ellipsoid: vertices on it, faces inscribed chords."""
    ico = trimesh.creation.icosphere(subdivisions=subdivisions)
    return trimesh.Trimesh(ico.vertices * AXES, ico.faces)


def cap_height(mesh: trimesh.Trimesh, radius: float) -> float:
    """How far a flat face can sit from a surface through its vertices, curvature radii >= R.

    The worst case is a sphere of radius R: the face's circumcircle cuts off a cap of height
    R - sqrt(R^2 - rho^2) ~ rho^2 / (2 R), rho the circumradius (abc / (4 area)). For
    near-equilateral faces, rho^2 = e^2 / 3, and this is e^2 / (6 R), more than the edge
    chord's sagitta e^2 / (8 R): faces bulge less than their circumcircle, not less than
    their edges.
    """
    t = mesh.triangles
    a, b, c = (np.linalg.norm(t[:, i] - t[:, j], axis=1) for i, j in ((1, 2), (2, 0), (0, 1)))
    rho = np.max(a * b * c / (4 * mesh.area_faces))
    return float(radius - np.sqrt(radius**2 - rho**2))


def listing(directory) -> list[str]:
    return sorted(p.name for p in directory.iterdir())


# --- mesh_to_grid -------------------------------------------------------------------


def test_mesh_to_grid_ellipsoid_converges_at_second_order():
    errors = {}
    for sub in (3, 4):
        mesh = ellipsoid_mesh(sub)
        f = io.mesh_to_grid(mesh, 25, 49)
        assert f.shape == (3, 25, 49) and f.dtype == np.float64
        err = float(np.max(np.linalg.norm(f - radial_ellipsoid(25, 49), axis=0)))
        bound = cap_height(mesh, R_MIN)
        assert err < bound, (sub, err, bound)
        errors[sub] = err
    # Measured: 4.38e-3 and 1.10e-3, ratio 3.98; halving the edges quarters the error.
    assert 3.5 < errors[3] / errors[4] < 4.5, errors


def test_mesh_to_grid_result_is_a_valid_surface_with_exact_poles_and_seam():
    f = io.mesh_to_grid(ellipsoid_mesh(2), 9, 17)
    io.validate_surface(f)
    assert np.array_equal(f[:, 0, :], np.repeat(f[:, 0, :1], 17, axis=1))
    assert np.array_equal(f[:, -1, :], np.repeat(f[:, -1, :1], 17, axis=1))
    assert np.array_equal(f[..., -1], f[..., 0])
    # The poles of this ellipsoid lie on the z axis at +-c, vertices of the icosphere.
    np.testing.assert_allclose(f[:, 0, 0], [0.0, 0.0, AXES[2]], atol=1e-12)
    np.testing.assert_allclose(f[:, -1, 0], [0.0, 0.0, -AXES[2]], atol=1e-12)


def test_mesh_to_grid_points_lie_on_the_mesh_along_rays_from_the_centroid():
    # bumpy is not radial about its centroid: the grid comes back reparametrised, but
    # every point is on the mesh and on the ray from the centroid in its grid direction.
    mesh = io.grid_to_mesh(shapes.sample(shapes.bumpy, 25, 49))
    g = io.mesh_to_grid(mesh, 13, 25)
    c = np.average(mesh.triangles_center, axis=0, weights=mesh.area_faces)
    r = g - c[:, None, None]
    u = r / np.linalg.norm(r, axis=0)
    # The grid's directions are read in the mesh's principal axes.
    axes = io.mesh_frame(mesh).axes
    expected = np.einsum("ij,jkl->ikl", axes, grid_directions(13, 25))
    np.testing.assert_allclose(u, expected, atol=1e-12)
    _, distance, _ = mesh.nearest.on_surface(g.reshape(3, -1).T)
    assert distance.max() < 1e-12


def test_mesh_to_grid_accepts_a_scene_and_a_center():
    mesh = ellipsoid_mesh(2)
    f = io.mesh_to_grid(mesh, 9, 17)
    np.testing.assert_array_equal(io.mesh_to_grid(trimesh.Scene([mesh]), 9, 17), f)
    shifted = trimesh.Trimesh(mesh.vertices + [0.1, -0.2, 0.05], mesh.faces)
    g = io.mesh_to_grid(shifted, 9, 17, center=[0.1, -0.2, 0.05])
    np.testing.assert_allclose(g - np.array([0.1, -0.2, 0.05])[:, None, None], f, atol=1e-12)


def test_mesh_to_grid_checks_the_grid_size():
    with pytest.raises(ValueError, match="even number of columns n=16"):
        io.mesh_to_grid(ellipsoid_mesh(1), 9, 16)
    with pytest.raises(TypeError, match="trimesh"):
        io.mesh_to_grid(np.zeros((3, 9, 17)), 9, 17)


# --- refusals -----------------------------------------------------------------------


def test_torus_is_not_genus_zero():
    torus = trimesh.creation.torus(major_radius=1.0, minor_radius=0.3)
    with pytest.raises(io.NotGenusZeroError, match=r"Euler characteristic .* is 0") as info:
        io.mesh_to_grid(torus, 13, 25)
    assert "genus (2 - chi)/2 = 1" in str(info.value)
    assert isinstance(info.value, io.MeshError) and isinstance(info.value, ValueError)


def test_open_mesh_is_not_watertight():
    ico = trimesh.creation.icosphere(subdivisions=2)
    # Three faces that share no edge: removing them leaves 9 boundary edges.
    faces = np.delete(ico.faces, [0, 100, 200], axis=0)
    open_mesh = trimesh.Trimesh(ico.vertices, faces)
    assert len(open_mesh.faces) == len(ico.faces) - 3
    with pytest.raises(io.NotWatertightError, match="not closed") as info:
        io.mesh_to_grid(open_mesh, 13, 25)
    assert "9 edge(s) belong to one face only" in str(info.value)


def test_two_spheres_are_refused():
    a = trimesh.creation.icosphere(subdivisions=1)
    b = trimesh.Trimesh(a.vertices + [3.0, 0.0, 0.0], a.faces)
    with pytest.raises(io.MeshError, match="2 connected components"):
        io.mesh_to_grid(trimesh.util.concatenate([a, b]), 9, 17)


def test_dumbbell_is_not_star_shaped():
    # An icosphere squeezed to a thin neck at z = 0 with lobes at the ends: rays from the
    # centre leaving through the neck at a low angle re-enter a lobe and leave it again.
    ico = trimesh.creation.icosphere(subdivisions=3)
    v = ico.vertices
    s = 0.1 + 3.0 * v[:, 2] ** 4
    dumbbell = trimesh.Trimesh(np.stack([v[:, 0] * s, v[:, 1] * s, 2 * v[:, 2]], 1), ico.faces)
    assert dumbbell.is_watertight and dumbbell.euler_number == 2
    with pytest.raises(io.NotStarShapedError, match="not star-shaped") as info:
        io.mesh_to_grid(dumbbell, 13, 25, method="radial")
    message = str(info.value)
    # Measured: 48 of the 266 rays cross three times, none misses.
    assert "0 missed the mesh and 48 crossed it more than once (up to 3 times)" in message
    assert "row i=1, column j=0" in message
    assert "star-shaped about no point at all" in message
    assert io.star_center(dumbbell) is None


def test_star_center_is_the_deepest_kernel_point():
    # A sphere's faces are tangent planes at equal distance from the centre: the deepest
    # point of their intersection is the centre itself.
    ico = trimesh.creation.icosphere(subdivisions=3)
    assert np.linalg.norm(io.star_center(ico)) < 1e-9
    flipped = trimesh.Trimesh(ico.vertices + [1.0, 2.0, 3.0], ico.faces[:, ::-1])  # inward
    np.testing.assert_allclose(io.star_center(flipped), [1.0, 2.0, 3.0], atol=1e-9)


def test_a_spike_moves_the_centroid_out_of_the_kernel_and_star_center_recovers():
    # Radial about the origin, so star-shaped about it; a long thin spike along +x pulls
    # the area centroid into the spike, from where four rays cross the surface 3 times.
    x = np.asarray(ej.sphere_points(25, 49))
    mesh = io.grid_to_mesh((1 + 5 * np.exp(30 * (x[0] - 1))) * x)
    with pytest.raises(io.NotStarShapedError, match="pass center=star_center") as info:
        io.mesh_to_grid(mesh, 13, 25, method="radial")
    assert "4 crossed it more than once" in str(info.value)
    c = io.star_center(mesh)
    normals, corners = mesh.face_normals, mesh.triangles[:, 0]
    assert np.einsum("ij,ij->i", normals, c - corners).max() < 0  # inside every face plane
    f = io.mesh_to_grid(mesh, 25, 49, center=c)
    points = f.reshape(3, -1).T
    _, distance, _ = trimesh.proximity.closest_point(mesh, points)
    assert distance.max() < 1e-9  # every grid point lies on the mesh
    u = (points - c) / np.linalg.norm(points - c, axis=1, keepdims=True)
    np.testing.assert_allclose(u, np.asarray(ej.sphere_points(25, 49)).reshape(3, -1).T, atol=1e-9)


def test_bent_tube_centroid_outside_misses():
    # Bent into most of a ring, the tube's centroid lies outside it: rays miss.
    tube = io.grid_to_mesh(shapes.sample(shapes.bent_cylinder, 25, 49, curvature=1.5))
    with pytest.raises(io.NotStarShapedError) as info:
        io.mesh_to_grid(tube, 13, 25, method="radial")
    assert "40 missed the mesh and 226 crossed it more than once" in str(info.value)
    assert "the north pole" in str(info.value)


# --- grid_to_mesh -------------------------------------------------------------------


def test_grid_to_mesh_faces_outward_for_a_mirrored_parametrization():
    f = np.asarray(shapes.sample(shapes.ellipsoid, 13, 25))
    mirrored = f * np.asarray([-1.0, 1.0, 1.0])[:, None, None]  # reverses the orientation
    a, b = io.grid_to_mesh(f), io.grid_to_mesh(mirrored)
    assert b.volume == pytest.approx(a.volume, rel=1e-12) and a.volume > 0
    outward = np.einsum("ij,ij->i", b.face_normals, b.triangles_center)
    assert outward.min() > 0


def test_grid_to_mesh_sphere_is_closed_outward_and_second_order_in_volume():
    deficits = []
    for m, n in ((13, 25), (25, 49)):
        mesh = io.grid_to_mesh(shapes.sample(shapes.sphere, m, n))
        assert len(mesh.vertices) == (m - 2) * (n - 1) + 2
        assert len(mesh.faces) == 2 * (m - 2) * (n - 1)
        assert mesh.is_watertight and mesh.is_winding_consistent and mesh.euler_number == 2
        outward = np.einsum("ij,ij->i", mesh.face_normals, mesh.triangles_center)
        assert outward.min() > 0
        assert mesh.volume > 0
        deficits.append(4 / 3 * np.pi - mesh.volume)
    # An inscribed polyhedron: smaller than the ball by O(h^2). Measured 0.118, 0.0298.
    assert 0 < deficits[1] < deficits[0] < 0.03 * 4 / 3 * np.pi
    assert 3.5 < deficits[0] / deficits[1] < 4.5


def test_grid_to_mesh_keeps_float64_vertices_without_x64():
    f = radial_ellipsoid(13, 25)
    with jax.enable_x64(False):
        mesh = io.grid_to_mesh(f)
    assert mesh.vertices.dtype == np.float64
    np.testing.assert_array_equal(mesh.vertices[1], f[:, 1, 0])


def test_round_trip_through_a_mesh_on_the_same_grid_is_exact():
    m, n = 25, 49
    f = radial_ellipsoid(m, n)
    mesh = io.grid_to_mesh(f)
    assert mesh.is_watertight and mesh.euler_number == 2
    volume = 4 / 3 * np.pi * AXES.prod()
    # Inscribed: 1.2% below the ellipsoid's volume on this grid (measured 1.4491 / 1.4661).
    assert 0 < volume - mesh.volume < 0.02 * volume
    # The rays from the centroid (here the origin, by symmetry) pass through the vertices.
    g = io.mesh_to_grid(mesh, m, n)
    assert np.max(np.abs(g - f)) < 1e-12  # measured 4e-16
    # On another grid the rays hit triangle interiors: within the faces' cap height.
    h = io.mesh_to_grid(mesh, 37, 73)
    err = np.max(np.linalg.norm(h - radial_ellipsoid(37, 73), axis=0))
    assert err < cap_height(mesh, R_MIN)


# --- load_surface and save_surface --------------------------------------------------


def test_npz_round_trip_is_exact(tmp_path):
    f = np.asarray(shapes.sample(shapes.bumpy, 13, 25))
    path = io.save_surface(f, tmp_path / "s.npz")
    g = io.load_surface(path)
    assert g.dtype == np.float64
    np.testing.assert_array_equal(g, f)
    assert listing(tmp_path) == ["s.npz"]


def test_npz_resampled_on_request_in_float64(tmp_path):
    f = np.asarray(shapes.sample(shapes.bumpy, 13, 25))
    io.save_surface(f, tmp_path / "s.npz")
    g = io.load_surface(tmp_path / "s.npz", 25, 49)
    np.testing.assert_array_equal(g, np.asarray(resample(f, 25, 49)))
    with jax.enable_x64(False):
        h = io.load_surface(tmp_path / "s.npz", 25, 49)
    assert h.dtype == np.float64
    np.testing.assert_allclose(h, g, rtol=0, atol=1e-14)


@pytest.mark.parametrize("layout", ["m n 3", "3 m n"])
def test_mat_file_in_either_layout(tmp_path, layout):
    f = np.asarray(shapes.sample(shapes.bumpy, 13, 25))
    stored = f.transpose(1, 2, 0) if layout == "m n 3" else f
    scipy.io.savemat(tmp_path / "s.mat", {"f": stored, "other": np.arange(3)})
    g = io.load_surface(tmp_path / "s.mat")
    assert g.shape == (3, 13, 25)
    np.testing.assert_array_equal(g, f)


@pytest.mark.parametrize("fmt", io.MESH_FORMATS)
def test_mesh_file_round_trip(tmp_path, fmt):
    f = radial_ellipsoid(13, 25)
    path = io.save_surface(f, tmp_path / f"s.{fmt}")
    assert listing(tmp_path) == [f"s.{fmt}"]
    g = io.load_surface(path, 13, 25, frame="input")
    # The writers round to float32 (ply, stl, glb), 8 decimals (obj) or 10 (off); the rays
    # still pass through the vertices. Measured: 2.6e-8, 5e-9, 5.5e-11.
    assert np.max(np.abs(g - f)) < 1e-7


def test_mesh_file_default_grid(tmp_path):
    ico = trimesh.creation.icosphere(subdivisions=2)
    ico.export(tmp_path / "ball.off")
    g = io.load_surface(tmp_path / "ball.off")
    assert g.shape == (3, 50, 99)
    radius = np.linalg.norm(g, axis=0)
    assert radius.max() < 1 + 1e-9 and radius.min() > 1 - cap_height(ico, 1.0)


def test_load_errors_name_the_problem(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.npz"):
        io.load_surface(tmp_path / "nope.npz")
    np.savez(tmp_path / "wrong.npz", g=np.zeros((3, 9, 17)))
    with pytest.raises(KeyError, match=r"no array 'f'.*\['g'\]"):
        io.load_surface(tmp_path / "wrong.npz")
    scipy.io.savemat(tmp_path / "wrong.mat", {"x": np.zeros(3)})
    with pytest.raises(KeyError, match=r"no array 'f'.*\['x'\]"):
        io.load_surface(tmp_path / "wrong.mat")
    (tmp_path / "s.txt").write_text("1 2 3")
    with pytest.raises(ValueError, match=r"unknown file type '.txt'; supported: .npz, .mat, .*ply"):
        io.load_surface(tmp_path / "s.txt")
    f = np.array(shapes.sample(shapes.sphere, 9, 17))
    f[1, 3, 4] = np.nan
    np.savez(tmp_path / "nan.npz", f=f)
    with pytest.raises(
        ValueError, match=r"1 non-finite value.*coordinate 1 at row i=3, column j=4"
    ):
        io.load_surface(tmp_path / "nan.npz")
    np.savez(tmp_path / "flat.npz", f=np.zeros((3, 9)))
    with pytest.raises(ValueError, match=r"shape \(3, 9\)"):
        io.load_surface(tmp_path / "flat.npz")
    with pytest.raises(ValueError, match="both m and n"):
        io.load_surface(tmp_path / "nan.npz", m=9)


def test_save_errors(tmp_path):
    f = np.asarray(shapes.sample(shapes.sphere, 9, 17))
    with pytest.raises(ValueError, match=r"unknown file type '.vtk'; supported: .npz, .ply"):
        io.save_surface(f, tmp_path / "s.vtk")
    with pytest.raises(ValueError, match="even number of columns"):
        io.save_surface(np.zeros((3, 9, 16)), tmp_path / "s.npz")
    assert listing(tmp_path) == []


# --- save_path ----------------------------------------------------------------------


@pytest.mark.parametrize("fmt", ["ply", "obj"])
def test_save_path_writes_frames_and_npz(tmp_path, fmt):
    m, n = 13, 25
    a, b = np.asarray(shapes.sample(shapes.sphere, m, n)), radial_ellipsoid(m, n)
    s = np.linspace(0.0, 1.0, 4)[:, None, None, None]
    path = (1 - s) * a + s * b
    settings = {"metric": "split", "a": 1.0, "steps": 4, "grid": [m, n], "w": np.float64(0.5)}
    out = tmp_path / "out" / "geodesic"
    written = io.save_path(path, out, format=fmt, settings=settings)
    frames = [f"frame_{k:03d}.{fmt}" for k in range(4)]
    assert [p.name for p in written] == frames + ["path.npz"]
    assert listing(out) == sorted(frames + ["path.npz"])  # and no temporaries
    for k, name in enumerate(frames):
        mesh = trimesh.load(out / name, force="mesh", process=False)
        assert len(mesh.vertices) == (m - 2) * (n - 1) + 2
        assert len(mesh.faces) == 2 * (m - 2) * (n - 1)
        np.testing.assert_allclose(mesh.vertices[0], path[k, :, 0, 0], atol=1e-7)
    with np.load(out / "path.npz", allow_pickle=False) as data:
        np.testing.assert_array_equal(data["path"], path)
        back = json.loads(str(data["settings"]))
    assert back == {"metric": "split", "a": 1.0, "steps": 4, "grid": [13, 25], "w": 0.5}


def test_save_path_refuses_bad_input_before_writing(tmp_path):
    path = np.stack([np.asarray(shapes.sample(shapes.sphere, 9, 17))] * 2)
    with pytest.raises(ValueError, match="unknown mesh format 'vtk'"):
        io.save_path(path, tmp_path / "a", format="vtk")
    with pytest.raises(TypeError, match="not JSON data"):
        io.save_path(path, tmp_path / "b", settings={"f": object()})
    with pytest.raises(ValueError, match=r"\(N, 3, m, n\)"):
        io.save_path(path[0], tmp_path / "c")
    assert listing(tmp_path) == []


# --- atomic writes ------------------------------------------------------------------


def interrupt_after_writing(original_target_arg):
    """A stand-in writer that writes a few bytes to its file, then is interrupted."""

    def write(*args, **kwargs):
        target = original_target_arg(*args, **kwargs)
        if hasattr(target, "write"):
            target.write(b"partial")
        else:
            with open(target, "wb") as fh:
                fh.write(b"partial")
        raise KeyboardInterrupt

    return write


def test_interrupted_mesh_export_leaves_old_file_and_no_temporary(tmp_path, monkeypatch):
    f = radial_ellipsoid(9, 17)
    target = io.save_surface(f, tmp_path / "s.ply")
    before = target.read_bytes()
    monkeypatch.setattr(
        trimesh.Trimesh, "export", interrupt_after_writing(lambda self, file_obj, **kw: file_obj)
    )
    with pytest.raises(KeyboardInterrupt):
        io.save_surface(2 * f, target)
    assert target.read_bytes() == before
    with pytest.raises(KeyboardInterrupt):
        io.save_surface(f, tmp_path / "new.obj")
    assert listing(tmp_path) == ["s.ply"]


def test_interrupted_npz_leaves_nothing(tmp_path, monkeypatch):
    monkeypatch.setattr(np, "savez", interrupt_after_writing(lambda file, *a, **kw: file))
    f = radial_ellipsoid(9, 17)
    with pytest.raises(KeyboardInterrupt):
        io.save_surface(f, tmp_path / "s.npz")
    assert listing(tmp_path) == []


def test_interrupted_save_path_keeps_finished_frames_only(tmp_path, monkeypatch):
    calls = []
    real_export = trimesh.Trimesh.export

    def export(self, file_obj=None, file_type=None, **kwargs):
        calls.append(file_obj)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real_export(self, file_obj, file_type=file_type, **kwargs)

    monkeypatch.setattr(trimesh.Trimesh, "export", export)
    path = np.stack([radial_ellipsoid(9, 17)] * 3)
    with pytest.raises(KeyboardInterrupt):
        io.save_path(path, tmp_path)
    assert listing(tmp_path) == ["frame_000.ply"]


def test_surface_files_lists_what_load_surface_reads(tmp_path):
    f = np.asarray(shapes.sample(shapes.ellipsoid, 9, 17))
    io.save_surface(f, tmp_path / "b.npz")
    io.save_surface(f, tmp_path / "a.ply")
    (tmp_path / "notes.txt").write_text("not a surface")
    (tmp_path / ".hidden.npz").write_bytes(b"")
    (tmp_path / "sub.npz").mkdir()  # a directory with a surface's suffix is not a file
    found = io.surface_files(tmp_path)
    assert [p.name for p in found] == ["a.ply", "b.npz"]
    np.testing.assert_array_equal(io.load_surface(found[1]), f)
    (tmp_path / "a.ply").unlink()
    (tmp_path / "b.npz").unlink()
    with pytest.raises(ValueError, match="holds no surface file.*suffixes found: txt"):
        io.surface_files(tmp_path)
    with pytest.raises(FileNotFoundError, match="no such directory"):
        io.surface_files(tmp_path / "absent")


# --- results out: GIfTI, the way back to the input mesh's vertices, scale (issue 52) ---


def vertex_errors(mesh: trimesh.Trimesh, m: int, n: int, **options) -> tuple[float, float]:
    """(max, RMS) distance of each vertex of ``mesh`` from the grid mesh_to_grid resamples
    it on, read back at the vertex's own direction, over the bounding box's diagonal."""
    grid, vertex_map = io.mesh_to_grid(mesh, m, n, return_map=True, **options)
    vertices = np.asarray(mesh.vertices)
    error = np.linalg.norm(io.grid_to_vertices(grid, vertex_map.directions) - vertices, axis=1)
    error /= np.linalg.norm(np.ptp(vertices, axis=0))
    return float(error.max()), float(np.sqrt(np.mean(error**2)))


def test_gifti_output_holds_the_grid_mesh_in_float32(tmp_path):
    nibabel = pytest.importorskip("nibabel")
    f = np.asarray(shapes.sample(shapes.bumpy, 13, 25)) + np.array([3.0, -1.0, 2.0])[:, None, None]
    path = io.save_surface(f, tmp_path / "b.gii")
    assert listing(tmp_path) == ["b.gii"]
    image = nibabel.load(path)
    points = image.get_arrays_from_intent("NIFTI_INTENT_POINTSET")[0].data
    triangles = image.get_arrays_from_intent("NIFTI_INTENT_TRIANGLE")[0].data
    assert points.dtype == np.float32 and triangles.dtype == np.int32
    mesh = io.grid_to_mesh(f)
    size = np.ptp(mesh.vertices, axis=0).max()
    # float32 rounding of coordinates up to 4 across a surface of size ~2: measured 1.3e-8.
    assert np.abs(points - mesh.vertices).max() / size < 1e-6
    np.testing.assert_array_equal(triangles, mesh.faces)
    # load_surface reads it back as a mesh through nibabel.
    assert io.load_surface(path, 13, 25).shape == (3, 13, 25)
    written = io.save_path(np.stack([f, 2.0 * f]), tmp_path / "p", format="gii")
    assert [p.name for p in written] == ["frame_000.gii", "frame_001.gii", "path.npz"]
    second = nibabel.load(written[1]).get_arrays_from_intent("NIFTI_INTENT_POINTSET")[0].data
    assert np.abs(second - 2.0 * mesh.vertices).max() / size < 2e-6


def test_gifti_output_without_nibabel_names_the_extra(tmp_path, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "nibabel", None)  # import nibabel raises ImportError
    f = np.asarray(shapes.sample(shapes.sphere, 9, 17))
    with pytest.raises(ej.InputError, match=r'pip install "elastic-jax\[neuro\]"'):
        io.save_surface(f, tmp_path / "s.gii")
    with pytest.raises(ej.InputError, match=r"elastic-jax\[neuro\]"):
        io.save_path(np.stack([f, f]), tmp_path / "p", format="gii")
    assert listing(tmp_path) == []


@pytest.mark.parametrize("method", ["bilinear", "bicubic", "spline"])
def test_grid_to_vertices_interpolates_the_grid_points(method):
    # At the grid's own directions every interpolant gives back the grid's values; the
    # batch axes and a field that is not a surface (a displacement) are read alike.
    f = np.asarray(shapes.sample(shapes.bumpy, 13, 25))
    u = np.asarray(ej.sphere_points(13, 25)).reshape(3, -1).T
    batch = np.stack([f, 2.0 * f - 1.0])
    got = io.grid_to_vertices(batch, 5.0 * u, method=method)
    assert got.shape == (2, 13 * 25, 3)
    np.testing.assert_allclose(got, np.swapaxes(batch.reshape(2, 3, -1), -1, -2), atol=1e-12)


def test_grid_to_vertices_refuses_bad_input(tmp_path):
    f = np.asarray(shapes.sample(shapes.sphere, 9, 17))
    u = np.eye(3)
    with pytest.raises(ej.InputError, match="method"):
        io.grid_to_vertices(f, u, method="nearest")
    with pytest.raises(ej.InputError, match="directions must have shape"):
        io.grid_to_vertices(f, u[:, :2])
    with pytest.raises(ej.InputError, match="zero row"):
        io.grid_to_vertices(f, np.zeros((2, 3)))
    with pytest.raises(ej.InputError, match="directions contains"):
        io.grid_to_vertices(f, np.full((2, 3), np.nan))
    with pytest.raises(ej.InputError, match="f must have shape"):
        io.grid_to_vertices(f[:2], u)
    with pytest.raises(ej.InputError, match="return_map"):
        io.load_surface(io.save_surface(f, tmp_path / "s.npz"), return_map=True)


def test_vertex_map_gives_back_a_radial_mesh_and_its_faces():
    """A bumpy surface meshed at 25 x 49, resampled radially at 50 x 99 in its principal
    frame (the grid's directions are not the vertices'): read back at each vertex's
    direction, the vertices to 1.8e-3 of the diagonal (RMS 4.6e-4; measured)."""
    mesh = io.grid_to_mesh(np.asarray(shapes.sample(shapes.bumpy, 25, 49)))
    grid, vertex_map = io.mesh_to_grid(mesh, 50, 99, return_map=True)
    assert vertex_map.method == "radial"
    np.testing.assert_allclose(np.linalg.norm(vertex_map.directions, axis=1), 1.0, atol=1e-15)
    worst, rms = vertex_errors(mesh, 50, 99)
    assert worst < 3e-3 and rms < 1e-3
    back = vertex_map.to_mesh(grid)
    np.testing.assert_array_equal(back.faces, mesh.faces)
    # the interpolant smooths the bumps a little: volume 4.7e-3 lower (measured)
    assert back.is_watertight and back.volume == pytest.approx(mesh.volume, rel=1e-2)
    # a moved and scaled mesh moves its map with it: the same directions
    moved = trimesh.Trimesh(2.0 * mesh.vertices + 1.0, mesh.faces, process=False)
    _, moved_map = io.mesh_to_grid(moved, 50, 99, return_map=True)
    np.testing.assert_allclose(moved_map.directions, vertex_map.directions, atol=1e-12)


@pytest.mark.parametrize("name", ["cat1", "cat2", "horse0", "hand4"])
def test_shared_shapes_come_back_on_their_own_vertices(name):
    """Each shared shape's grid meshed (grid_to_mesh), mapped by the spherical
    parametrization (not star-shaped; the map is not the grid's parametrization) and read
    back at the vertices' directions on the sphere: relative to the bounding box's diagonal,
    max / RMS measured 1.26e-2 / 1.05e-3 (cat1), 1.12e-2 / 1.33e-3 (cat2), 1.61e-2 /
    1.65e-3 (horse0), 9.9e-3 / 1.14e-3 (hand4) at 50 x 99 (the grid's resolution of legs
    and tails squeezed on the sphere: a few vertices), and at 100 x 199 max 4.5e-3, 5.6e-3,
    8.0e-3, 4.0e-3. 5 to 10 s each on 2 cores (the parametrization)."""
    from .conftest import load_shape

    mesh = io.grid_to_mesh(load_shape(name))
    grid, vertex_map = io.mesh_to_grid(mesh, 50, 99, return_map=True, method="spherical")
    assert vertex_map.method == "spherical"
    vertices = np.asarray(mesh.vertices)
    diagonal = np.linalg.norm(np.ptp(vertices, axis=0))
    for (m, n), worst, rms in (((50, 99), 2e-2, 2.5e-3), ((100, 199), 1e-2, 1.2e-3)):
        # the same map at another grid: computed once, given back as sphere=
        f = grid if m == 50 else io.mesh_to_grid(mesh, m, n, sphere=vertex_map.directions)
        error = np.linalg.norm(vertex_map.to_vertices(f) - vertices, axis=1) / diagonal
        assert error.max() < worst and np.sqrt(np.mean(error**2)) < rms, (m, n)


@pytest.mark.filterwarnings("ignore:.*:DeprecationWarning")
def test_fsaverage_pial_comes_back_through_its_sphere():
    """fsaverage5's left pial hemisphere (10,242 vertices; not star-shaped) resampled through
    its own sphere (sphere_left, as --sphere reads it): read back at each vertex, max / RMS
    1.18e-2 / 1.61e-3 of the diagonal at 50 x 99, 3.9e-3 / 8.5e-4 at 100 x 199 (measured)."""
    import nibabel

    image = nibabel.load(fsaverage5("pial_left"))
    vertices = np.asarray(image.darrays[0].data, np.float64)
    faces = np.asarray(image.darrays[1].data, np.int64)
    sphere = np.asarray(nibabel.load(fsaverage5("sphere_left")).darrays[0].data, np.float64)
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    diagonal = np.linalg.norm(np.ptp(vertices, axis=0))
    for (m, n), worst, rms in (((50, 99), 2e-2, 2.5e-3), ((100, 199), 1e-2, 1.2e-3)):
        grid, vertex_map = io.mesh_to_grid(mesh, m, n, sphere=sphere, return_map=True)
        assert vertex_map.method == "sphere"
        error = np.linalg.norm(vertex_map.to_vertices(grid) - vertices, axis=1) / diagonal
        assert error.max() < worst and np.sqrt(np.mean(error**2)) < rms, (m, n)
    # load_surface through the sphere file gives the same map
    f, loaded = io.load_surface(
        fsaverage5("pial_left"), 50, 99, sphere=fsaverage5("sphere_left"), return_map=True
    )
    np.testing.assert_allclose(loaded.vertices, vertices, rtol=0, atol=0)
    np.testing.assert_allclose(
        loaded.directions, sphere / np.linalg.norm(sphere, axis=1, keepdims=True), atol=1e-15
    )


def test_normalize_scale_reaches_the_area_and_keeps_the_centroid():
    f = (
        np.asarray(shapes.sample(shapes.bumpy, 13, 25)) * 3.7
        + np.array([1.0, 2.0, -3.0])[:, None, None]
    )
    batch = np.stack([f, 0.01 * f])
    scaled, s = io.normalize_scale(batch)
    assert s.shape == (2,) and s[1] == pytest.approx(100.0 * s[0], rel=1e-12)
    np.testing.assert_allclose(ej.surface_area(scaled), 4.0 * np.pi, rtol=1e-12)
    centroid = np.asarray(batch - ej.center(batch))[..., :1, :1]
    np.testing.assert_allclose(np.asarray(scaled - ej.center(scaled))[..., :1, :1], centroid)
    one, s1 = io.normalize_scale(f, area=1.0)
    assert float(ej.surface_area(one)) == pytest.approx(1.0, rel=1e-12)
    assert float(s1) == pytest.approx(float(s[0]) / np.sqrt(4.0 * np.pi), rel=1e-12)
    with pytest.raises(ej.InputError, match="area"):
        io.normalize_scale(f, area=0.0)


def test_distances_scale_with_the_surfaces():
    """d(s f1, s f2) = s d(f1, f2): the split metric is homogeneous of degree 2
    (math §3), and the solve's iterates are the scaled ones (measured: equal to the last
    bit at s = 1e-3 ... 1e3). Concentric spheres: sqrt(8 pi b) |r2 - r1| (math §9), linear
    in the radii; normalized to area 4 pi both are the unit sphere (distance 0)."""
    f1 = np.asarray(shapes.sample(shapes.ellipsoid, 13, 25))
    f2 = 1.3 * np.asarray(shapes.sample(shapes.sphere, 13, 25)) + 0.2
    d = float(ej.geodesic(f1, f2, METRIC_SCALE, degree=3, n_times=5).distance)
    for s in (1e-3, 2.5, 1e3):
        scaled = float(ej.geodesic(s * f1, s * f2, METRIC_SCALE, degree=3, n_times=5).distance)
        assert scaled == pytest.approx(s * d, rel=1e-8)
    a, b = (np.asarray(shapes.sample(shapes.sphere, 25, 49, radius=r)) for r in (1.0, 2.0))
    d = float(ej.geodesic(a, b, METRIC_SCALE, degree=3, n_times=5).distance)
    # O(h^2) on the grid: 3.6e-3 relative at 25 x 49
    assert d == pytest.approx(np.sqrt(8 * np.pi * METRIC_SCALE.b), rel=1e-2)
    scaled = float(ej.geodesic(7 * a, 7 * b, METRIC_SCALE, degree=3, n_times=5).distance)
    assert scaled == pytest.approx(7 * d, rel=1e-8)
    (na, nb), _ = io.normalize_scale(np.stack([a, b]))
    np.testing.assert_allclose(na, nb, atol=1e-14)


METRIC_SCALE = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)


def test_load_surface_normalizes_on_request(tmp_path):
    f = 5.0 * np.asarray(shapes.sample(shapes.bumpy, 13, 25))
    grid_file = io.save_surface(f, tmp_path / "b.npz")
    mesh_file = io.save_surface(f, tmp_path / "b.ply")
    for path in (grid_file, mesh_file):
        g = io.load_surface(path, 13, 25, normalize="area")
        assert float(ej.surface_area(g)) == pytest.approx(4.0 * np.pi, rel=1e-12)
    np.testing.assert_allclose(
        io.load_surface(grid_file, normalize="area"), io.normalize_scale(f)[0], atol=1e-15
    )
    with pytest.raises(ej.InputError, match="normalize"):
        io.load_surface(grid_file, normalize="volume")


def _energy_fields(f):
    """Per-point fields of a real computation: the terms of a straight line's energy."""
    density = ej.energy_density(ej.SplitMetric(1.0, 1.0, 0.1, 0.2), ej.straight_path(f, 1.5 * f, 3))
    return {name: np.asarray(getattr(density, name)) for name in ("shear", "area", "total")}


def test_fields_beside_the_surface_read_back_in_every_format(tmp_path):
    nibabel = pytest.importorskip("nibabel")
    f = np.asarray(shapes.sample(shapes.bumpy, 13, 25))
    fields = _energy_fields(f)
    # .npz: the arrays themselves.
    stored = np.load(io.save_surface(f, tmp_path / "b.npz", fields=fields))
    np.testing.assert_array_equal(stored["f"], f)
    for name, value in fields.items():
        np.testing.assert_array_equal(stored[name], value)
    # A mesh vertex takes its grid point's value; a pole the mean of its row.
    mesh = io.grid_to_mesh(f)
    expected = {
        name: np.concatenate([[v[0, :-1].mean()], v[1:-1, :-1].ravel(), [v[-1, :-1].mean()]])
        for name, v in fields.items()
    }
    # .ply: float64 vertex properties, as trimesh reads them.
    ply = trimesh.load(io.save_surface(f, tmp_path / "b.ply", fields=fields), process=False)
    vertices = ply.metadata["_ply_raw"]["vertex"]["data"]
    assert len(vertices) == len(mesh.vertices)
    for name, value in expected.items():
        np.testing.assert_array_equal(vertices[name], value)
    # .gii: one float32 shape array per field, named, as nibabel reads them.
    image = nibabel.load(io.save_surface(f, tmp_path / "b.gii", fields=fields))
    shapes_ = image.get_arrays_from_intent("NIFTI_INTENT_SHAPE")
    assert [a.meta["Name"] for a in shapes_] == list(fields)
    for array, value in zip(shapes_, expected.values(), strict=True):
        np.testing.assert_array_equal(array.data, value.astype(np.float32))
    assert io.load_surface(tmp_path / "b.gii", 13, 25).shape == (3, 13, 25)


def test_a_field_that_does_not_fit_is_refused_by_name(tmp_path):
    f = np.asarray(shapes.sample(shapes.bumpy, 13, 25))
    with pytest.raises(ej.InputError, match="'energy'.*\\(13, 25\\)"):
        io.save_surface(f, tmp_path / "b.ply", fields={"energy": np.zeros((13, 24))})
    with pytest.raises(ej.InputError, match="'energy'.*NaN"):
        io.save_surface(f, tmp_path / "b.ply", fields={"energy": np.full((13, 25), np.nan)})
    with pytest.raises(ej.InputError, match="'x'"):
        io.save_surface(f, tmp_path / "b.ply", fields={"x": np.zeros((13, 25))})
    with pytest.raises(ej.InputError, match=r"\.obj"):
        io.save_surface(f, tmp_path / "b.obj", fields={"energy": np.zeros((13, 25))})
    assert not list(tmp_path.iterdir())  # nothing was written


def test_an_energy_density_on_the_input_meshs_own_vertices_keeps_its_sum():
    import warnings

    mesh = io.grid_to_mesh(shapes.sample(shapes.bumpy, 25, 49))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", io.FrameWarning)  # the bumpy surface is symmetric
        f, vertex_map = io.mesh_to_grid(mesh, 25, 49, return_map=True)
    # The vertices' shares of the parameter sphere tile it.
    areas = vertex_map.vertex_areas()
    assert areas.min() > 0.0 and areas.sum() == pytest.approx(4.0 * np.pi, rel=1e-12)
    metric = ej.SplitMetric(1.0, 1.0, 0.1, 0.2)
    density = ej.energy_density(metric, ej.straight_path(f, 1.3 * f, 3))
    on_vertices = density.on_vertices(vertex_map)
    assert on_vertices.total.shape == (len(mesh.vertices),)
    # The same energy by the vertices' quadrature: 0.1 % apart here.
    assert on_vertices.total.sum() == pytest.approx(float(density.total.sum()), rel=5e-3)
    parts = on_vertices.shear + on_vertices.area + on_vertices.bending + on_vertices.rotation
    np.testing.assert_allclose(parts, on_vertices.total, rtol=1e-12)
    # A pointwise quantity is read as it is: the grid's z coordinate gives the vertices'.
    z = vertex_map.to_vertex_values(np.asarray(f[2]), integrals=False)
    np.testing.assert_allclose(z, vertex_map.to_vertices(f)[:, 2], rtol=0, atol=1e-12)
