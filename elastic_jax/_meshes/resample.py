"""Meshes onto the grid and back: radial projection about a centre the mesh is
star-shaped about, or the fold-free spherical parametrization (``sphere_map``), the mesh's
frame, the grid's triangulation, and the way from a grid back to the input's vertices
(``VertexMap``). ``elastic_jax.io`` re-exports the public names and adds the files."""

from __future__ import annotations

import operator
from collections.abc import Callable, Sequence
from typing import NamedTuple

import jax
import numpy as np
import trimesh

from .._checks import check_bool, check_choice, check_finite, check_grid_shape
from .._errors import FrameWarning, InputError, warn_user
from .._geometry.grid import distinct_points, from_distinct, grid_directions, grid_faces
from .._geometry.reparam import METHODS as INTERPOLATIONS
from .._geometry.reparam import reparametrize_unchecked
from .._geometry.validation import validate_surface
from .frame import MeshFrame, principal_frame
from .sphere_map import (
    MeshError,
    NotStarShapedError,
    SphericalParametrization,
    check_mesh,
    given_map,
    parametrize,
)

# The spherical map is computed from frame coordinates rounded to multiples of 1 / _SNAP.
_SNAP = 2.0**16


# Hits of one ray closer than this (times the mesh's size) are one crossing: a ray through
# an edge or a vertex is reported once by each triangle there.
_MERGE_RTOL = 1e-9


# Bounds the (ray, candidate triangle) pairs that trimesh materialises per call: a ray
# from the centre has a few percent (up to a third) of the faces as candidates.
_PAIRS_PER_CHUNK = 5_000_000


def as_trimesh(mesh) -> trimesh.Trimesh:
    if isinstance(mesh, trimesh.Scene):
        parts = [g for g in mesh.dump() if isinstance(g, trimesh.Trimesh)]
        if not parts:
            raise MeshError("the scene holds no triangle mesh")
        return parts[0] if len(parts) == 1 else trimesh.util.concatenate(parts)
    if not isinstance(mesh, trimesh.Trimesh):
        raise TypeError(f"mesh must be a trimesh.Trimesh or trimesh.Scene; got {type(mesh)!r}")
    return mesh


def _checked_mesh(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray]:
    """The mesh's float64 vertices and its faces wound outward, after ``check_mesh``."""
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    return vertices, check_mesh(vertices, np.asarray(mesh.faces))


def _crossings(
    mesh: trimesh.Trimesh, origin: np.ndarray, directions: np.ndarray, atol: float
) -> tuple[np.ndarray, np.ndarray]:
    """Where each ray ``origin + t u`` (t > 0) crosses the mesh; hits closer than atol merged.

    Args:
        directions: ``(R, 3)`` unit vectors u.

    Returns:
        ``(ray, t)``: the ray index and distance of every distinct crossing, sorted by ray
        and then by distance (``(H,)`` each).
    """
    rays, dists = [], []
    chunk = int(np.clip(_PAIRS_PER_CHUNK // max(len(mesh.faces), 1), 16, 1024))
    for start in range(0, len(directions), chunk):
        u = directions[start : start + chunk]
        _, index_ray, loc = mesh.ray.intersects_id(
            np.broadcast_to(origin, u.shape), u, multiple_hits=True, return_locations=True
        )
        rays.append(np.asarray(index_ray, dtype=np.int64) + start)
        dists.append(np.einsum("ij,ij->i", np.reshape(loc, (-1, 3)) - origin, u[index_ray]))
    ray, t = np.concatenate(rays), np.concatenate(dists)
    # trimesh keeps hits up to 1e-6 behind the origin; a crossing needs t > 0.
    ahead = t > atol
    ray, t = ray[ahead], t[ahead]
    order = np.lexsort((t, ray))
    ray, t = ray[order], t[order]
    new = np.ones(len(ray), dtype=bool)
    new[1:] = (ray[1:] != ray[:-1]) | (t[1:] - t[:-1] > atol)
    return ray[new], t[new]


def star_center(mesh: trimesh.Trimesh | trimesh.Scene) -> np.ndarray | None:
    """A point the closed mesh is star-shaped about, or None when there is none.

    The points a closed polyhedron is star-shaped about (its kernel) are those on the inner
    side of every face's plane: n_T . (p - v_T) < 0 for each face T with outward normal n_T
    and a vertex v_T. The linear program max s subject to n_T . (p - v_T) + s <= 0
    (scipy.optimize.linprog, HiGHS) finds the point deepest inside that intersection of
    half-spaces; the kernel is non-empty exactly when the optimal s is positive (above
    1e-9 of the mesh's size). It is solved in the mesh's own units (coordinates over its
    largest extent), so the answer does not depend on the unit the mesh is given in.

    Args:
        mesh: a closed, consistently oriented ``trimesh.Trimesh`` (or a Scene of one).

    Returns:
        ``(3,)`` float64, a point to pass as ``mesh_to_grid(..., center=...)``; None if the
        mesh is star-shaped about no point (radial projection cannot parametrize it).
    """
    import scipy.optimize

    mesh = as_trimesh(mesh)
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    # Solved in the mesh's own units (its bounding box's middle and largest extent): HiGHS's
    # feasibility tolerances (1e-7) are absolute, and so is trimesh's cut-off below which
    # face_normals are zero (a cross product under 1e-13, i.e. edges under ~3e-7): a hand
    # of 1.4 cm scaled by 1e-6 was called star-shaped, a bumpy sphere so scaled was not.
    used = vertices[np.unique(faces)]
    middle = (used.min(axis=0) + used.max(axis=0)) / 2
    size = float(np.ptp(used, axis=0).max())
    if size == 0:
        return None
    t = (vertices[faces] - middle) / size
    normals = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    volume = np.einsum("ij,ij->", t[:, 0], normals)
    if volume < 0:  # inward-wound faces: their normals point inside
        normals = -normals
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    # A face of zero area has no side to be on: its constraint s <= 0 leaves no kernel.
    normals = normals / np.where(length > 0, length, 1.0)
    res = scipy.optimize.linprog(
        c=[0.0, 0.0, 0.0, -1.0],
        A_ub=np.hstack([normals, np.ones((len(normals), 1))]),
        b_ub=np.einsum("ij,ij->i", normals, t[:, 0]),
        bounds=[(None, None)] * 3 + [(None, 1.0)],
        method="highs",
    )
    # A margin relative to the mesh's size, so that rays from the point cross cleanly.
    if res.status != 0 or res.x[3] <= 1e-9:
        return None
    return middle + size * np.asarray(res.x[:3], dtype=np.float64)


def _direction_name(k: int, m: int, n: int, u: np.ndarray) -> str:
    if k == 0:
        where = "the north pole, row i=0"
    elif k == 1 + (m - 2) * (n - 1):
        where = f"the south pole, row i={m - 1}"
    else:
        i, j = divmod(k - 1, n - 1)
        phi, theta = (i + 1) * np.pi / (m - 1), j * 2 * np.pi / (n - 1)
        where = f"row i={i + 1}, column j={j}: phi={phi:.4f}, theta={theta:.4f}"
    return f"({u[0]:.4f}, {u[1]:.4f}, {u[2]:.4f}) ({where})"


def _grid_frame(vertices: np.ndarray, faces: np.ndarray, frame) -> MeshFrame:
    """The frame mesh_to_grid works in: principal axes (None), the input's, or given ones."""
    found = principal_frame(vertices, faces)
    if isinstance(frame, str):
        check_choice("frame", frame, ("principal", "input"))
        if frame == "input":
            return found._replace(axes=np.eye(3))
        frame = None
    if frame is None:
        if not found.undetermined:
            return found
        warn_user(
            f"the mesh's principal frame is undetermined ({found.undetermined}); the grid "
            "uses the input's coordinate axes, so it does not follow rigid motions of this "
            "mesh (a symmetric mesh: pass frame='input' to choose this, or a rotation)",
            FrameWarning,
        )
        return found._replace(axes=np.eye(3))
    axes = np.asarray(frame, dtype=np.float64)
    if axes.shape != (3, 3) or not np.all(np.isfinite(axes)):
        raise InputError(f"frame must be 'principal', 'input' or a (3, 3) rotation; got {frame!r}")
    if np.abs(axes.T @ axes - np.eye(3)).max() > 1e-9 or np.linalg.det(axes) < 0:
        raise InputError(
            "frame must be a rotation (orthonormal columns, determinant +1, to 1e-9); got "
            f"{np.array2string(axes, precision=4)}"
        )
    return found._replace(axes=axes)


def mesh_frame(mesh: trimesh.Trimesh | trimesh.Scene) -> MeshFrame:
    """The centroid, size and signed principal axes mesh_to_grid resamples a mesh in.

    c = int x dA / A (area centroid), C = int (x - c)(x - c)^T dA / A, exact over the
    triangles; the axes are C's eigenvectors, largest eigenvalue first, each signed by its
    third moment int (e_k . (x - c))^3 dA (the two largest in magnitude; the third makes
    the frame right-handed). A rigid motion x -> R x + t and a scaling of the mesh move
    the frame with it. ``undetermined`` says why when the surface does not fix the axes:
    equal eigenvalues or third moments below 1e-6 (a symmetry: spheres, ellipsoids,
    mirror-symmetric tubes).

    Args:
        mesh: a ``trimesh.Trimesh`` (or a Scene of one).

    Returns:
        :class:`MeshFrame` (center ``(3,)``, scale, axes ``(3, 3)``, moments, skewness,
        undetermined).
    """
    mesh = as_trimesh(mesh)
    return principal_frame(
        np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
    )


def spherical_parametrization(
    mesh: trimesh.Trimesh | trimesh.Scene,
    *,
    area_weight: float = 0.9,
    max_steps: int = 20_000,
    rtol: float = 1e-5,
    init: np.ndarray | None = None,
    frame: str | np.ndarray | None = None,
    progress: Callable[[str], None] | None = None,
    max_iter: int | None = None,
) -> SphericalParametrization:
    """A bijective, orientation-preserving map of a closed genus-0 mesh onto the sphere.

    For meshes that are not star-shaped (animals, hands, bent tubes): a mean-value Tutte
    map of the mesh with one face removed, inverse stereographic projection and a Moebius
    centring give a fold-free start; the foldover-free energy of Garanzha et al. (ACM TOG
    2021), per face A_T ((1 - w) ‖J‖_F^2 + w (det J^2 + 1)) / chi(det J, eps) with J the map's
    Jacobian from the mesh triangle (scaled to total area 4 pi) to its chord triangle on the
    sphere and chi(D, eps) = (D + sqrt(eps^2 + D^2)) / 2, is minimized by optimistix L-BFGS
    for decreasing eps. ``w = area_weight`` trades angle distortion (w -> 0, conformal) for
    area distortion (w -> 1, equal areas); area balance keeps thin parts of the mesh (legs,
    tails) from shrinking to nothing on the sphere, which is what the grid needs.
    Runs in float64 whatever JAX's x64 setting (``jax.enable_x64`` locally).

    The map is computed on the mesh moved into its frame (:func:`mesh_frame`: centroid at
    the origin, unit RMS size, principal axes along x, y, z) and ends with the area-weighted
    Kabsch rotation that turns it towards the directions of the vertices in that frame: the
    map is attached to the mesh, so a rigidly moved or scaled copy of the mesh gets the same
    map (``sphere``), and ``to_grid`` the moved grid.

    The map is never folded: a face whose image is turned over (triple product of its
    sphere points <= 0) after ``max_steps`` iterations raises ParametrizationError.

    Args:
        mesh: a closed, consistently wound, vertex-manifold ``trimesh.Trimesh`` with Euler
            characteristic 2 and no zero-area faces (or a Scene of one).
        area_weight: w in (0, 1], default 0.9.
        max_steps: L-BFGS iterations in all (>= 1); the record's ``num_steps`` counts them.
        rtol: stop when a round of 250 iterations lowers the energy by less than this
            fraction (with no folded face).
        init: optional ``(V, 3)`` starting directions on the sphere (normalized here), for
            example a map from another tool; folded starts are untangled.
        frame: None (default) or ``"principal"``: the mesh's principal frame, with a
            FrameWarning and the input's axes when a symmetry leaves it undetermined;
            ``"input"``: the input's coordinate axes; or a ``(3, 3)`` rotation whose
            columns are the axes to use.
        progress: called with a line of text after every round.
        max_iter: the former name of max_steps (until 2026-11-26; a DeprecationWarning).

    Returns:
        :class:`SphericalParametrization`: vertices (the mesh's own), faces (wound
        outward), sphere positions (in the frame's axes) and the quality figures (flipped
        faces, area-distortion ratio, mean angle error, energy, iterations, time);
        ``.to_grid(m, n)`` resamples the mesh.

    Raises:
        MeshError: the mesh fails a check (the subclass and message say which).
        ParametrizationError: folded faces remain (``.flipped`` holds their count).
        InputError: bad options.

    Warns:
        ConvergenceWarning: ``max_steps`` ran out while the energy was still falling (the
            record says ``converged=False``; the map has no folds).
        FrameWarning: the principal frame is undetermined (a symmetric mesh).
    """
    if max_iter is not None:
        # Every step limit of the package is called max_steps.
        warn_user(
            "spherical_parametrization: max_iter is now called max_steps",
            DeprecationWarning,
        )
        max_steps = max_iter
    mesh = as_trimesh(mesh)
    vertices, faces = _checked_mesh(mesh)
    y = _grid_frame(vertices, faces, frame).to_frame(vertices)
    options = {"area_weight": area_weight, "max_steps": max_steps, "rtol": rtol, "init": init}
    return _spherical(y, vertices, faces, progress, **options)


def mesh_to_grid(
    mesh: trimesh.Trimesh | trimesh.Scene,
    m: int = 50,
    n: int = 99,
    *,
    method: str = "auto",
    center: Sequence[float] | np.ndarray | None = None,
    sphere: np.ndarray | None = None,
    frame: str | np.ndarray | None = None,
    progress: Callable[[str], None] | None = None,
    return_map: bool = False,
) -> np.ndarray | tuple[np.ndarray, VertexMap]:
    """A closed genus-0 triangle mesh as a surface on the m x n grid.

    Every method works in the mesh's frame (:func:`mesh_frame`): the grid direction
    e1(phi_i, theta_j) of :ref:`math §1 <math-1>` is read in the mesh's principal axes, so a rigidly
    moved or uniformly scaled mesh gives the moved grid (to rounding), and where the
    surface's symmetry leaves the axes undetermined a FrameWarning says so and the input's
    axes are used (``frame=`` chooses them). Every grid point lies on the mesh (to
    rounding: 1e-15 of the mesh's size measured).

    Everything is computed in the mesh's own units: in its frame the mesh has unit RMS
    size about its area centroid (:class:`MeshFrame`'s ``scale``), and every tolerance
    (ray hits, merges, the snapping of the spherical map's input, :func:`star_center`'s
    linear program) is relative to that size, so a mesh in metres, millimetres or
    kilometres gives the same grid up to the scale (measured at scales 1e-3 and 1e3, every
    method: the same to 2e-15 of the size, on the mesh to 4e-16).

    Methods:

    - ``"radial"``: with c the mesh's area-weighted centroid (sum_T area_T centroid_T /
      sum_T area_T) or ``center``, f(phi_i, theta_j) = c + t_ij A e1(phi_i, theta_j), A the
      frame's axes, where t_ij > 0 is where the ray from c crosses the mesh. Exact, and it
      needs the mesh star-shaped about c: every ray must cross the mesh exactly once
      (crossings closer than 1e-9 times the mesh's size, as at an edge or a vertex that
      several triangles share, count once).
    - ``"spherical"``: :func:`spherical_parametrization` maps the mesh onto the sphere;
      each grid direction is located in its spherical triangle and the mesh's vertices
      are interpolated with the same (projective barycentric) weights. Any closed genus-0
      mesh.
    - ``"auto"`` (default): radial about ``center`` when one is given; otherwise radial
      about the area centroid when the mesh is star-shaped about it, else radial about
      :func:`star_center` when it is star-shaped about some point, else spherical.
    - ``sphere=`` a spherical map the caller has (FreeSurfer's ``?h.sphere``, a
      ``sphere_left.gii``): resampled through it as through the spherical method's own
      map, after the same checks (no face folded over, the sphere tiled once). The map
      is the caller's, in its own axes (a moved mesh with the same map gives the moved
      grid); method "auto" or "spherical", no ``center`` or ``frame``.

    One point per distinct grid point: (m - 2)(n - 1) interior directions and the two
    poles; the pole rows repeat the pole point and the seam column repeats column 0.

    Args:
        mesh: a ``trimesh.Trimesh``, or a ``trimesh.Scene`` whose meshes are concatenated.
        m, n: grid size (n odd, both >= 5).
        method: ``"auto"``, ``"radial"`` or ``"spherical"``.
        center: the point the rays start from, ``(3,)`` (radial only).
        sphere: ``(V, 3)`` the given map: one position per vertex of ``mesh.vertices``, in
            their order (trimesh merges and reorders vertices unless the mesh is built or
            loaded with ``process=False``), on a sphere about the origin (any radius).
        frame: None (default) or ``"principal"``: the mesh's principal axes (the input's,
            with a FrameWarning, when undetermined); ``"input"``: the input's coordinate
            axes (no warning; the grid then follows translations and scalings only); or a
            ``(3, 3)`` rotation whose columns are the axes.
        progress: called with a line of text during a spherical parametrization.
        return_map: also return the map that brought the mesh in, as a :class:`VertexMap`
            (each vertex's direction on the grid's sphere), whose ``to_vertices`` and
            ``to_mesh`` read any grid surface back at the input's vertices.

    Returns:
        ``(3, m, n)`` float64 numpy array; with ``return_map``, ``(grid, VertexMap)``.

    Raises:
        NotWatertightError: the mesh has boundary or non-manifold edges (counts given).
        NonManifoldVertexError: the faces around a vertex form several fans.
        NotGenusZeroError: its Euler characteristic is not 2 (value and genus given).
        InconsistentWindingError, DegenerateFaceError: flipped faces, zero-area faces.
        NotStarShapedError: method "radial" and some rays miss the mesh or cross it more
            than once (counts and the first such direction given).
        ParametrizationError: method "spherical" (or "auto" on a non-star-shaped mesh)
            and the map could not be unfolded; or the given ``sphere`` folds faces over or
            does not tile the sphere once.
        MeshError: no faces, several connected components, or a scene without meshes.
        TypeError: ``mesh`` is not a trimesh mesh or scene.
        ValueError: a bad grid size, method, center or frame.

    Warns:
        FrameWarning: the principal frame is undetermined and ``frame`` was not given.
    """
    m, n = operator.index(m), operator.index(n)
    check_grid_shape((3, m, n), "the grid (3, m, n)")
    check_choice("method", method, ("auto", "radial", "spherical"))
    return_map = check_bool("return_map", return_map)
    if method == "spherical" and center is not None:
        raise InputError("center applies to method='radial' (or 'auto'), not 'spherical'")
    if sphere is not None and (method == "radial" or center is not None or frame is not None):
        raise InputError(
            "sphere= is a spherical map in its own axes: use method 'auto' or 'spherical', "
            "no center, no frame"
        )
    mesh = as_trimesh(mesh)
    vertices, faces = _checked_mesh(mesh)

    def through(par: SphericalParametrization, how: str):
        grid = par.to_grid(m, n)
        if not return_map:
            return grid
        return grid, VertexMap(par.sphere, vertices, np.asarray(mesh.faces, np.int64), how)

    if sphere is not None:
        return through(given_map(vertices, faces, sphere), "sphere")
    where = _grid_frame(vertices, faces, frame)
    y = where.to_frame(vertices)
    if method == "spherical":
        return through(_spherical(y, vertices, faces, progress), "spherical")
    # In the frame the mesh has unit RMS size about the origin: trimesh's absolute
    # tolerances (1e-6 behind a ray's origin, 1e-8 merges) are then relative ones.
    local = trimesh.Trimesh(y, faces, process=False)
    if method == "radial" or center is not None:
        grid, origin = _radial(local, m, n, center, where, hint=True)
    else:
        try:
            grid, origin = _radial(local, m, n, None, where, hint=False)
        except NotStarShapedError:
            kernel = star_center(local)
            if kernel is None:
                if progress is not None:
                    progress("the mesh is star-shaped about no point: spherical parametrization")
                return through(_spherical(y, vertices, faces, progress), "spherical")
            grid, origin = _radial(local, m, n, where.from_frame(kernel), where, hint=False)
    grid = np.moveaxis(where.from_frame(np.moveaxis(grid, 0, -1)), -1, 0)
    if not return_map:
        return grid
    # The ray from the centre through a vertex, in the frame's axes: where the grid's
    # direction e1(phi, theta) reads that vertex.
    ray = y - origin
    length = np.linalg.norm(ray, axis=1, keepdims=True)
    directions = np.where(length > 0, ray / np.where(length > 0, length, 1.0), [0.0, 0.0, 1.0])
    return grid, VertexMap(directions, vertices, np.asarray(mesh.faces, np.int64), "radial")


def _spherical(y, vertices, faces, progress, **options) -> SphericalParametrization:
    """The map computed on the mesh in its frame (``y``, the vertices in frame coordinates),
    recorded with the mesh's own vertices (the grid's points are then interpolated from
    them, on the mesh to rounding)."""
    # The optimizer amplifies rounding: the frame coordinates of a moved copy of the mesh
    # differ from the original's by 1e-16 to 1e-12 (a translation large against the size)
    # and the maps then differed by up to 7e-4 of the size (hand4, 2,000 iterations).
    # Rounded to multiples of 2^-16 (1.5e-5 of the mesh's RMS size) both copies give the
    # same bits, unless a coordinate sits within that difference of a rounding boundary
    # (under 1e-7 per coordinate); the map is then a function of the mesh, and the grid's
    # points still come from the exact vertices. Not where rounding would turn a sliver
    # face over.
    snapped = np.round(y * _SNAP) / _SNAP
    if np.all(np.einsum("ij,ij->i", _normals(snapped, faces), _normals(y, faces)) > 0):
        y = snapped
    par = parametrize(y, faces, progress=progress, **options)
    return par._replace(vertices=vertices)


def _normals(y: np.ndarray, faces: np.ndarray) -> np.ndarray:
    t = y[faces]
    return np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])


def _radial(
    local, m: int, n: int, center, where: MeshFrame, hint: bool
) -> tuple[np.ndarray, np.ndarray]:
    """Radial projection of a checked mesh in its frame about ``center`` (in the mesh's
    coordinates; None: its area centroid, the frame's origin): the grid and the rays'
    origin ``(3,)``, both in frame coordinates."""
    if center is None:
        origin = np.zeros(3)
        about = "its area-weighted centroid"
    else:
        center = np.asarray(center, dtype=np.float64)
        if center.shape != (3,) or not np.all(np.isfinite(center)):
            raise InputError(f"center must be 3 finite numbers; got {center!r}")
        origin = where.to_frame(center)
        about = "the given center"
    vertices = local.vertices.view(np.ndarray)
    scale = float(np.max(np.linalg.norm(vertices - origin, axis=1)))
    directions = grid_directions(m, n)
    ray, t = _crossings(local, origin, directions, _MERGE_RTOL * scale)
    count = np.bincount(ray, minlength=len(directions))

    bad = np.flatnonzero(count != 1)
    if bad.size:
        k = int(bad[0])
        missed, multiple = int(np.sum(count == 0)), int(np.sum(count > 1))
        found = (
            "misses the mesh"
            if count[k] == 0
            else f"crosses it {count[k]} times, at distances "
            + ", ".join(f"{d * where.scale:.4g}" for d in t[ray == k])
        )
        o = where.from_frame(origin)
        u = directions[k] @ where.axes.T
        raise NotStarShapedError(
            f"the mesh is not star-shaped about {about} "
            f"({o[0]:.4g}, {o[1]:.4g}, {o[2]:.4g}): of {len(directions)} rays "
            f"from it, {missed} missed the mesh and {multiple} crossed it more than once "
            f"(up to {int(count.max())} times); the first, in direction "
            f"{_direction_name(k, m, n, u)}, {found}"
            + (_star_hint(local, where, center) if hint else "")
        )
    # One crossing per ray, sorted by ray: t lines up with the directions.
    return from_distinct(origin + t[:, None] * directions, m, n), origin


def _star_hint(local: trimesh.Trimesh, where: MeshFrame, center) -> str:
    kernel = star_center(local)
    if kernel is None:
        return (
            "; it is star-shaped about no point at all (the inner half-spaces of its faces do "
            "not intersect), so radial projection cannot parametrize it"
        )
    kernel = np.array2string(where.from_frame(kernel), precision=4)
    if center is not None:
        return f"; it is star-shaped about {kernel} (star_center)"
    return f"; it is star-shaped about {kernel}: pass center=star_center(mesh)"


def grid_to_mesh(f) -> trimesh.Trimesh:
    """Triangulate a surface on the grid: one vertex per distinct grid point.

    Vertices: the north pole, the interior rows i = 1 .. m-2 at columns j = 0 .. n-2 (the
    seam column is column 0 again), the south pole: (m - 2)(n - 1) + 2 in all. Faces: a
    fan of n - 1 triangles at each pole and two triangles per grid quad between interior
    rows, wrapping across the seam: 2 (n - 1)(m - 2) faces. Faces are oriented along
    e_phi x e_theta, which is outward for the grid's own parametrisation of the sphere, so
    ``grid_to_mesh(sample(sphere, m, n))`` has positive volume and outward normals; for an
    orientation-reversing parametrization (negative signed volume) every face is turned, so
    the triangles always face outward. The
    result is closed with Euler characteristic 2; ``process=False``, so trimesh merges no
    vertices even where the surface touches itself.

    Args:
        f: ``(3, m, n)`` surface (array-like), checked with ``validate_surface``.

    Returns:
        ``trimesh.Trimesh`` with float64 vertices.

    Raises:
        ValueError: ``f`` is not a single well-formed surface on the grid.
    """
    # Validate a float64 copy: validate_surface returns a JAX array, float32 without x64.
    f = checked_surfaces(np.asarray(f, dtype=np.float64), "f", "(3, m, n)")
    m, n = f.shape[1:]
    vertices = distinct_points(f)
    mesh = trimesh.Trimesh(vertices=vertices, faces=grid_faces(m, n), process=False)
    if mesh.volume < 0:
        # An orientation-reversing parametrization (a mirror image): turn every face.
        mesh = trimesh.Trimesh(vertices=vertices, faces=mesh.faces[:, ::-1], process=False)
    return mesh


def grid_to_vertices(f, directions, *, method: str = "spline") -> np.ndarray:
    """A grid surface (or vector field) read at given directions of the parameter sphere.

    The way back from a grid to the vertices of the mesh it was resampled from: with u_k
    the direction of vertex k on the parameter sphere (:class:`VertexMap`'s
    ``directions``, in the grid's axes, where e1(phi, theta) of :ref:`math §1 <math-1>`
    lives), the result is f(u_k), f's interpolant on the grid (the package's
    reparametrization read, :ref:`math §6 <math-6>`: periodic in theta, across the poles
    by the half-turn rule) at each u_k. ``grid_to_vertices(mesh_to_grid(mesh), map.directions)``
    gives back the mesh's vertices up to the grid's resolution of the mesh (measured at
    50 x 99, relative to the bounding box's diagonal: RMS 1.0e-3 to 1.7e-3 and max 1.0e-2
    to 1.6e-2 for the shared cats, horse and hand meshed and mapped by the spherical
    parametrization, RMS 1.6e-3 and max 1.2e-2 for fsaverage5's pial hemisphere through its
    sphere; both about halve at 100 x 199); a deformed or registered surface on the same
    grid (a geodesic's frames) is then painted on the input mesh.

    Args:
        f: ``(..., 3, m, n)`` float array: surfaces, a path, or a displacement or velocity
            field on the grid (pole rows and seam as in math §1); finite.
        directions: ``(V, 3)`` nonzero vectors (each taken as a direction), e.g.
            ``VertexMap.directions``.
        method: the interpolation, ``"spline"`` (the interpolating cubic B-spline, fourth
            order; default), ``"bicubic"`` (Catmull-Rom) or ``"bilinear"`` (the paper's).

    Returns:
        ``(..., V, 3)`` float64 numpy array: the points (or vectors) at the V directions,
        in f's coordinates.

    Raises:
        InputError: f not ``(..., 3, m, n)`` on a valid grid or not finite, directions not
            ``(V, 3)`` finite nonzero rows, or an unknown method (each named).
    """
    check_choice("method", method, INTERPOLATIONS)
    f = np.asarray(f)
    if not (np.issubdtype(f.dtype, np.floating) or np.issubdtype(f.dtype, np.integer)):
        raise InputError(f"f must hold real numbers; got dtype {f.dtype}")
    check_grid_shape(f.shape, "f")
    check_finite(f, "f")
    u = np.asarray(directions, dtype=np.float64)
    if u.ndim != 2 or u.shape[1] != 3:
        raise InputError(f"directions must have shape (V, 3); got {u.shape}")
    check_finite(u, "directions")
    length = np.linalg.norm(u, axis=1, keepdims=True)
    if np.any(length == 0):
        raise InputError(f"directions has a zero row (row {int(np.argmin(length[:, 0]))})")
    # float64 whatever the caller's JAX precision setting (a local setting, not the global).
    with jax.enable_x64(True):
        out = reparametrize_unchecked(
            jax.numpy.asarray(f, jax.numpy.float64),
            jax.numpy.asarray((u / length).T),
            method=method,
        )
        out = np.asarray(out, dtype=np.float64)
    return np.swapaxes(out, -1, -2)


class VertexMap(NamedTuple):
    """Where each vertex of a mesh lies on the sphere that :func:`mesh_to_grid` resampled
    it through: the way from the grid back to the input's vertices.

    ``directions[k]`` is the unit vector u_k, in the grid's axes (those of e1(phi, theta),
    math §1), at which the grid surface passes through ``vertices[k]``, to the grid's
    resolution: for method ``"radial"`` the direction of the vertex from the rays'
    centre in the frame's axes, (A^T (x_k - c)) / ‖A^T (x_k - c)‖; for ``"spherical"`` the
    spherical parametrization's position of the vertex; for ``"sphere"`` the caller's
    map, normalized. :meth:`to_vertices` reads any grid surface of the same m x n (the
    input's grid, a geodesic's frames, a registered surface) at those directions, so a
    deformation or a correspondence is painted on the input mesh.

    Attributes:
        directions: ``(V, 3)`` float64 unit vectors.
        vertices: ``(V, 3)`` float64, the mesh's vertices as resampled (a loaded file's
            after merging duplicates, unless a sphere map was given).
        faces: ``(F, 3)`` int64, the mesh's faces as given.
        method: ``"radial"``, ``"spherical"`` or ``"sphere"`` (a given map).
    """

    directions: np.ndarray
    vertices: np.ndarray
    faces: np.ndarray
    method: str

    def to_vertices(self, f, method: str = "spline") -> np.ndarray:
        """``(..., V, 3)``: f ``(..., 3, m, n)`` at the vertices' directions
        (:func:`grid_to_vertices`)."""
        return grid_to_vertices(f, self.directions, method=method)

    def vertex_areas(self) -> np.ndarray:
        """``(V,)`` each vertex's share of the parameter sphere: a third of the spherical
        area of each face at it (the faces' vertices at their directions). They sum to
        4 pi when the directions embed the faces (a spherical parametrization's do)."""
        a, b, c = (self.directions[self.faces[:, k]] for k in range(3))
        # Van Oosterom and Strackee: tan(E / 2) of the spherical triangle a, b, c.
        triple = np.abs(np.einsum("ij,ij->i", a, np.cross(b, c)))
        dots = 1.0 + np.einsum("ij,ij->i", a, b) + np.einsum("ij,ij->i", b, c)
        dots += np.einsum("ij,ij->i", c, a)
        excess = 2.0 * np.arctan2(triple, dots)
        areas = np.zeros(len(self.directions))
        for k in range(3):
            np.add.at(areas, self.faces[:, k], excess / 3.0)
        return areas

    def to_vertex_values(self, field, *, integrals: bool = True, method: str = "spline"):
        """A grid field ``(..., m, n)`` at the mesh's vertices, ``(..., V)``.

        ``integrals`` (default): the field holds per-point integrals on the grid (its
        quadrature weight included, as :func:`~elastic_jax.energy_density`'s fields do).
        It is divided by :func:`~elastic_jax.quadrature_weights` into a density per unit
        area of the parameter sphere (the pole rows taken from their neighbouring rows'
        mean), read at each vertex's direction and multiplied by the vertex's share of
        the sphere (:meth:`vertex_areas`), so that the vertices' values sum to about
        the grid's (to the two quadratures' difference). Otherwise the field's values
        themselves are read at the directions (a pointwise quantity).
        """
        from .._geometry.grid import per_unit_area_np

        if not isinstance(integrals, bool):
            raise InputError(f"integrals must be True or False; got {integrals!r}")
        values = np.asarray(field, dtype=np.float64)
        if values.ndim < 2:
            raise InputError(f"field must have shape (..., m, n); got {values.shape}")
        m, n = values.shape[-2:]
        if integrals:
            inner = per_unit_area_np(values)[..., 1:-1, :]
            north = inner[..., :1, :-1].mean(axis=-1, keepdims=True)
            south = inner[..., -1:, :-1].mean(axis=-1, keepdims=True)
            rows = [np.broadcast_to(north, inner.shape[:-2] + (1, n)), inner]
            rows.append(np.broadcast_to(south, inner.shape[:-2] + (1, n)))
            values = np.concatenate(rows, axis=-2)
        stacked = np.broadcast_to(values[..., None, :, :], values.shape[:-2] + (3, m, n))
        read = grid_to_vertices(stacked, self.directions, method=method)[..., 0]
        return read * self.vertex_areas() if integrals else read

    def to_mesh(self, f, method: str = "spline") -> trimesh.Trimesh:
        """The surface f ``(3, m, n)`` as a mesh with the input's faces: vertex k is f(u_k)
        (``process=False``: the input's vertex order)."""
        points = self.to_vertices(f, method=method)
        if points.ndim != 2:
            raise InputError(f"f must be one surface (3, m, n); got shape {np.shape(f)}")
        return trimesh.Trimesh(points, self.faces, process=False)


def checked_surfaces(x, name: str, layout: str, any_rank: bool = False) -> np.ndarray:
    """``x`` as a floating numpy array that passed validate_surface and has ``layout``'s rank
    (any rank with ``any_rank``)."""
    x = np.asarray(x)
    if not np.issubdtype(x.dtype, np.floating):
        x = x.astype(np.float64)
    validate_surface(x, name)
    if not any_rank and x.ndim != layout.count(",") + 1:
        raise InputError(f"{name} must have shape {layout}; got shape {x.shape}")
    return x
