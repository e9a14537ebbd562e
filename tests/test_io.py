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
