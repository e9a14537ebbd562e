"""Reading and writing surfaces: grids (.npz, .mat) and triangle meshes (.ply, .obj, ...).

A surface is an array ``(3, m, n)`` on the spherical grid (math §1). A closed genus-0
mesh becomes such an array through a map of the mesh onto the unit sphere: by radial
projection when the mesh is star-shaped (one ray per grid direction from a centre of the
mesh, the surface point is where the ray leaves the mesh; exact, and checked rather than
assumed), otherwise by :func:`spherical_parametrization`, a fold-free map of any closed
genus-0 mesh (module ``_sphere_map``). The way back, :func:`grid_to_mesh`, triangulates
the grid with one vertex per distinct grid point; :func:`grid_to_vertices` (with the
:class:`VertexMap` that ``mesh_to_grid(..., return_map=True)`` gives) reads a grid surface
at the input mesh's own vertices, through the same sphere map that brought the mesh in.

Every file is written atomically (a temporary beside it, then a rename), so an interrupted
job leaves the previous file or the new one, never part of one.

Example:
    >>> import numpy as np
    >>> from elastic_jax import io, shapes
    >>> mesh = io.grid_to_mesh(np.asarray(shapes.sample(shapes.ellipsoid, 13, 25)))
    >>> bool(mesh.is_watertight), int(mesh.euler_number)
    (True, 2)
    >>> io.mesh_to_grid(mesh, 9, 17, frame="input").shape  # symmetric: the input's axes
    (3, 9, 17)
"""

from __future__ import annotations

import json
import operator
import os
import pathlib
import warnings
from collections.abc import Callable, Mapping, Sequence
from typing import NamedTuple

import jax
import numpy as np
import scipy.io
import trimesh

from ._checks import check_bool, check_choice, check_finite, check_grid_shape, check_positive
from ._errors import FrameWarning, InputError
from ._geometry.grid import distinct_points, from_distinct, grid_directions
from ._geometry.interp import resample
from ._geometry.reparam import METHODS as INTERPOLATIONS
from ._geometry.reparam import reparametrize_unchecked
from ._geometry.srnf import center_unchecked, surface_area_unchecked
from ._geometry.validation import validate_surface
from ._meshes.frame import MeshFrame, principal_frame
from ._meshes.sphere_map import (
    DegenerateFaceError,
    InconsistentWindingError,
    MeshError,
    NonManifoldVertexError,
    NotGenusZeroError,
    NotStarShapedError,
    NotWatertightError,
    ParametrizationError,
    SphericalParametrization,
    check_mesh,
    given_map,
    parametrize,
)
from ._runtime.atomic import atomic_path, save_npz_atomic

__all__ = [
    "MESH_FORMATS",
    "DegenerateFaceError",
    "FrameWarning",
    "InconsistentWindingError",
    "MeshError",
    "MeshFrame",
    "NonManifoldVertexError",
    "NotGenusZeroError",
    "NotStarShapedError",
    "NotWatertightError",
    "ParametrizationError",
    "SphericalParametrization",
    "VertexMap",
    "grid_to_mesh",
    "grid_to_vertices",
    "load_surface",
    "mesh_frame",
    "mesh_to_grid",
    "normalize_scale",
    "save_path",
    "save_surface",
    "spherical_parametrization",
    "star_center",
    "surface_files",
]

#: Mesh formats that :func:`save_surface` and :func:`save_path` write with trimesh and that
#: load back. (glTF is left out: trimesh writes it as several files, which cannot be renamed
#: at once.) Both also write GIfTI (``.gii``) with nibabel, the ``neuro`` extra.
MESH_FORMATS = ("ply", "obj", "off", "stl", "glb")

# What save_surface and save_path write: trimesh's formats and GIfTI (nibabel).
_WRITTEN_FORMATS = MESH_FORMATS + ("gii",)

# What area normalize= scales a surface to: the unit sphere's.
_UNIT_AREA = 4.0 * np.pi

# The spherical map is computed from frame coordinates rounded to multiples of 1 / _SNAP.
_SNAP = 2.0**16

# Grid files; every other suffix is handed to trimesh.
_GRID_FORMATS = ("npz", "mat")

# Brain and anatomy surfaces, read with nibabel (the "neuro" extra): GIfTI by its suffix,
# FreeSurfer's binary surfaces by their names (lh.white, rh.pial, lh.sphere.reg, ...).
_NEURO_FORMATS = ("gii",)
_FREESURFER_SURFACES = (
    "white",
    "pial",
    "inflated",
    "sphere",
    "orig",
    "smoothwm",
    "reg",
    "midthickness",
)

# Hits of one ray closer than this (times the mesh's size) are one crossing: a ray through
# an edge or a vertex is reported once by each triangle there.
_MERGE_RTOL = 1e-9

# The decimals trimesh's text writers give coordinates of size 1 (fixed point).
_DECIMALS = {"obj": 8, "off": 10}

# Bounds the (ray, candidate triangle) pairs that trimesh materialises per call: a ray
# from the centre has a few percent (up to a third) of the faces as candidates.
_PAIRS_PER_CHUNK = 5_000_000


def _mesh_loadable_formats() -> tuple[str, ...]:
    # xyz is a point cloud and stl_ascii no file suffix; both are loader names only.
    return tuple(sorted(trimesh.exchange.load.mesh_formats() - {"xyz", "stl_ascii"}))


def _suffix(path: pathlib.Path) -> str:
    return path.suffix.lower().lstrip(".")


def _as_trimesh(mesh) -> trimesh.Trimesh:
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

    mesh = _as_trimesh(mesh)
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
        warnings.warn(
            f"the mesh's principal frame is undetermined ({found.undetermined}); the grid "
            "uses the input's coordinate axes, so it does not follow rigid motions of this "
            "mesh (a symmetric mesh: pass frame='input' to choose this, or a rotation)",
            FrameWarning,
            stacklevel=3,
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
    mesh = _as_trimesh(mesh)
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
        # Every step limit of the package is called max_steps (issue 31).
        warnings.warn(
            "spherical_parametrization: max_iter is now called max_steps",
            DeprecationWarning,
            stacklevel=2,
        )
        max_steps = max_iter
    mesh = _as_trimesh(mesh)
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
    mesh = _as_trimesh(mesh)
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


def _grid_faces(m: int, n: int) -> np.ndarray:
    """Triangles of the grid mesh, counterclockwise seen from outside (normal e_phi x e_theta).

    Vertex k of an interior point (i, j), 1 <= i <= m - 2, 0 <= j <= n - 2, is
    1 + (i - 1)(n - 1) + j; the north pole is vertex 0 and the south pole the last one.
    """
    c = n - 1
    south = 1 + (m - 2) * c
    j = np.arange(c)
    jn = (j + 1) % c  # the seam: the last column's neighbour is column 0
    # Along +phi then +theta: (e_phi, e_theta, e_r) is right-handed on the unit sphere.
    north = np.stack([np.zeros(c, dtype=np.int64), 1 + j, 1 + jn], axis=1)
    southfan = np.stack([south - c + j, np.full(c, south), south - c + jn], axis=1)
    top = 1 + np.arange(m - 3)[:, None] * c  # first vertex of interior rows 1 .. m-3
    a, b = top + j, top + jn  # (i, j), (i, j + 1)
    lower, lower_next = a + c, b + c  # (i + 1, j), (i + 1, j + 1)
    quads = np.concatenate(
        [
            np.stack([a, lower, b], axis=-1).reshape(-1, 3),
            np.stack([lower, lower_next, b], axis=-1).reshape(-1, 3),
        ]
    )
    return np.concatenate([north, quads, southfan])


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
    f = _checked_surfaces(np.asarray(f, dtype=np.float64), "f", "(3, m, n)")
    m, n = f.shape[1:]
    vertices = distinct_points(f)
    mesh = trimesh.Trimesh(vertices=vertices, faces=_grid_faces(m, n), process=False)
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

    def to_mesh(self, f, method: str = "spline") -> trimesh.Trimesh:
        """The surface f ``(3, m, n)`` as a mesh with the input's faces: vertex k is f(u_k)
        (``process=False``: the input's vertex order)."""
        points = self.to_vertices(f, method=method)
        if points.ndim != 2:
            raise InputError(f"f must be one surface (3, m, n); got shape {np.shape(f)}")
        return trimesh.Trimesh(points, self.faces, process=False)


def normalize_scale(f, area: float = _UNIT_AREA) -> tuple[np.ndarray, np.ndarray]:
    """Surfaces scaled about their area centroids to a given area: (c + s (f - c), s).

    With A(f) the grid's area of f (:func:`elastic_jax.surface_area`, math §2's
    quadrature) and c its area-weighted centroid (:func:`elastic_jax.center`),
    s = sqrt(area / A(f)), so the result has exactly the given area (to rounding: A is
    homogeneous of degree 2) and the same centroid. The default, 4 pi, is the unit
    sphere's: a round sphere of any radius becomes the unit sphere.

    What it does to distances: the split metric is homogeneous,
    G_{s df}(s xi, s xi) = s^2 G_{df}(xi, xi) (math §3), so every distance (parametrized
    or modulo reparametrizations and rigid motions, for every metric) scales by s:
    d(s f1, s f2) = s d(f1, f2) (measured to the last bit of float64 at s = 1e-3 ... 1e3:
    the solver's iterates are the scaled ones), and the closed form of two concentric
    spheres, sqrt(8 pi b) abs(r2 - r1) (math §9), is linear in the radii. Distances between
    normalized surfaces are therefore in units of the normalized size (sqrt(area / 4 pi):
    the radius of the sphere of that area) and compare shapes with size removed; a
    translation changes no distance (the metric sees df only).

    Args:
        f: ``(..., 3, m, n)`` surfaces, checked with ``validate_surface``.
        area: the target area, positive (default 4 pi).

    Returns:
        ``(f_scaled, s)``: ``(..., 3, m, n)`` and the factors ``(...)``, float64 numpy.

    Raises:
        InputError: a bad surface or a non-positive area.
    """
    area = check_positive("area", area)
    f = _checked_surfaces(np.asarray(f, dtype=np.float64), "f", "(..., 3, m, n)", any_rank=True)
    with jax.enable_x64(True):
        x = jax.numpy.asarray(f)
        centroid = np.asarray(x - center_unchecked(x))[..., :, :1, :1]
        scale = np.sqrt(area / np.asarray(surface_area_unchecked(x)))
    return centroid + scale[..., None, None, None] * (f - centroid), scale


def _neuro_kind(path: pathlib.Path) -> str | None:
    """ "gii" for a GIfTI file, "freesurfer" for a FreeSurfer surface, else None."""
    kind = _suffix(path)
    if kind in _NEURO_FORMATS:
        return kind
    if path.name.lower().endswith(".gii.gz"):  # nibabel reads compressed GIfTI (nilearn's)
        return "gii"
    if kind in _FREESURFER_SURFACES and path.name[:3].lower() in ("lh.", "rh."):
        return "freesurfer"
    return None


def _nibabel(path: pathlib.Path, what: str):
    """The nibabel module; an InputError naming the file and the extra when it is missing."""
    try:
        import nibabel
    except ImportError as err:
        raise InputError(
            f'{str(path)!r}: {what} needs nibabel: pip install "elastic-jax[neuro]"'
        ) from err
    return nibabel


def _neuro_mesh(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Vertices ``(V, 3)`` and faces ``(F, 3)`` of a GIfTI (``.gii``) or FreeSurfer surface
    file (``lh.white``, ``rh.pial``, ``lh.sphere`` ...), in the file's vertex order.

    Needs nibabel: ``pip install "elastic-jax[neuro]"``.
    """
    path = pathlib.Path(path)
    kind = _neuro_kind(path)
    if kind is None:
        raise _unknown_suffix(path, "read as a GIfTI or FreeSurfer surface", _NEURO_FORMATS)
    _check_exists(path)
    nibabel = _nibabel(path, "reading GIfTI and FreeSurfer surfaces")

    def gifti():
        image = nibabel.load(path)
        points = image.get_arrays_from_intent("NIFTI_INTENT_POINTSET")
        triangles = image.get_arrays_from_intent("NIFTI_INTENT_TRIANGLE")
        if len(points) != 1 or len(triangles) != 1:
            raise InputError(
                f"{str(path)!r} holds {len(points)} point sets and {len(triangles)} triangle "
                "arrays; a surface has one of each"
            )
        return points[0].data, triangles[0].data

    def freesurfer():
        return nibabel.freesurfer.read_geometry(path)[:2]

    vertices, faces = _read(path, kind, gifti if kind == "gii" else freesurfer)
    return np.asarray(vertices, np.float64), np.asarray(faces, np.int64)


def _read(path: pathlib.Path, kind: str, reader):
    """``reader()``, with a failure to parse the file an InputError naming the file."""
    try:
        return reader()
    except (InputError, KeyError, FileNotFoundError, IsADirectoryError):
        raise
    except Exception as err:  # zipfile, numpy, trimesh and their parsers raise many kinds
        raise InputError(
            f"{str(path)!r} cannot be read as a .{kind} file ({type(err).__name__}: {err})"
        ) from err


def _load_npz_f(path: pathlib.Path) -> np.ndarray:
    # Our own handle: np.load leaves the file open when the archive is truncated.
    with open(path, "rb") as fh, np.load(fh, allow_pickle=False) as data:
        return _from_key(data, path)


def _loadmat(path: pathlib.Path) -> dict:
    try:
        return scipy.io.loadmat(path)
    except NotImplementedError as err:  # MATLAB v7.3 files are HDF5
        raise InputError(
            f"{str(path)!r} is a MATLAB v7.3 (HDF5) file, which scipy cannot read; "
            "save it with save(..., '-v7') or convert it to .npz"
        ) from err


def _check_exists(path: pathlib.Path) -> None:
    if not path.exists():
        raise FileNotFoundError(f"no such file: {str(path)!r}")
    if path.is_dir():
        raise IsADirectoryError(f"{str(path)!r} is a directory, not a surface file")


def _unknown_suffix(path: pathlib.Path, verb: str, formats: Sequence[str]) -> ValueError:
    return InputError(
        f"cannot {verb} {str(path)!r}: unknown file type {path.suffix or '(no suffix)'!r}; "
        f"supported: {', '.join('.' + s for s in formats)}"
    )


def _from_key(data: Mapping, path: pathlib.Path) -> np.ndarray:
    if "f" not in data:
        keys = sorted(k for k in data if not k.startswith("__"))
        raise KeyError(
            f"{str(path)!r} holds no array 'f' (the surface); it holds {keys or 'nothing'}"
        )
    return np.asarray(data["f"])


def surface_files(directory: str | os.PathLike) -> list[pathlib.Path]:
    """The files directly in ``directory`` that :func:`load_surface` reads (grid files
    ``.npz``/``.mat`` and the mesh formats trimesh loads, by suffix), sorted by name;
    hidden files (a leading dot) are left out.

    Raises:
        FileNotFoundError: no such directory.
        ValueError: the directory holds no such file (its suffixes are named).
    """
    directory = pathlib.Path(directory)
    if not directory.is_dir():
        raise FileNotFoundError(f"{str(directory)!r}: no such directory")
    readable = set(_GRID_FORMATS) | set(_mesh_loadable_formats()) | set(_NEURO_FORMATS)
    entries = sorted(p for p in directory.iterdir() if not p.name.startswith("."))
    found = [p for p in entries if p.is_file() and _suffix(p) in readable]
    if not found:
        seen = sorted({_suffix(p) or "(none)" for p in entries if p.is_file()})
        raise ValueError(
            f"{str(directory)!r} holds no surface file (.npz, .mat or a mesh format); "
            f"suffixes found: {', '.join(seen) if seen else 'none'}"
        )
    return found


def _load_mesh(path: pathlib.Path, merge: bool) -> trimesh.Trimesh:
    """``trimesh.load(path, force="mesh", process=merge)``, the merge in the mesh's units.

    trimesh's process=True merges the vertices of each of the file's meshes that round
    alike at 1e-8 (tol.merge), an absolute distance: every vertex of a surface a few
    micrometres across given in metres became one. Here each mesh's vertices are merged at
    1e-9 to 1e-8 of its largest extent (the same digits as trimesh's for extents from 1 to
    10), after dropping non-finite values as process=True does.
    """
    scene = trimesh.load(path, force="scene", process=False)
    if merge:
        for geometry in scene.geometry.values():
            if isinstance(geometry, trimesh.Trimesh) and len(geometry.vertices):
                geometry.remove_infinite_values()
                vertices = geometry.vertices.view(np.ndarray)
                extent = float(np.ptp(vertices, axis=0).max()) if len(vertices) else 0.0
                digits = None
                if extent > 0:
                    digits = -int(np.floor(np.log10(trimesh.tol.merge * extent)))
                geometry.merge_vertices(digits_vertex=digits)
    return scene.to_mesh()


def _map_positions(path: pathlib.Path) -> np.ndarray:
    """The vertex positions of a sphere map's file (GIfTI, FreeSurfer or a mesh file)."""
    if _neuro_kind(path) is not None:
        return _neuro_mesh(path)[0]
    kind = _suffix(path)
    if kind not in _mesh_loadable_formats():
        raise _unknown_suffix(path, "read as a sphere map", _NEURO_FORMATS + MESH_FORMATS)
    _check_exists(path)
    mesh = _read(path, kind, lambda: trimesh.load(path, force="mesh", process=False))
    return np.asarray(mesh.vertices, np.float64)


def load_surface(
    path: str | os.PathLike,
    m: int | None = None,
    n: int | None = None,
    *,
    sphere: str | os.PathLike | np.ndarray | None = None,
    frame: str | np.ndarray | None = None,
    progress: Callable[[str], None] | None = None,
    normalize: str | None = None,
    return_map: bool = False,
) -> np.ndarray | tuple[np.ndarray, VertexMap]:
    """Read a surface ``(3, m, n)`` from a grid file or a mesh file.

    - ``.npz``: the array ``f`` ``(3, m, n)``.
    - ``.mat`` (the paper's MATLAB files, read by ``scipy.io.loadmat``): the variable ``f``,
      stored ``(3, m, n)`` or ``(m, n, 3)``; the latter (last axis 3, first axis not) is
      transposed to ``(3, m, n)``.
    - a mesh file trimesh reads (``.ply .obj .off .stl .glb`` ...): loaded with
      ``trimesh.load(path, force="mesh")`` and resampled by :func:`mesh_to_grid` (method
      "auto": radial projection when the mesh is star-shaped, else a spherical
      parametrization) on the m x n grid, default 50 x 99.
    - a GIfTI surface (``.gii``, ``.gii.gz``) or a FreeSurfer surface (``lh.white``, ``rh.pial``,
      ``lh.sphere`` ...; by name), read with nibabel (``pip install
      "elastic-jax[neuro]"``) in the file's vertex order and resampled as a mesh.

    ``sphere``: a spherical map of the mesh to resample through instead of computing one
    (:func:`mesh_to_grid`'s ``sphere=``): an array ``(V, 3)`` or a file of the same mesh's
    sphere (FreeSurfer's ``?h.sphere``, a ``sphere_left.gii``, a mesh file trimesh reads
    without reordering); meshes only. ``frame``: the axes a mesh is resampled in
    (:func:`mesh_to_grid`'s ``frame=``; ``"input"`` gives back the grid a file of
    :func:`save_surface` was written from).

    A mesh is read and resampled in its own units: the vertices merged on loading (those
    that round alike at 1e-8 of the mesh's largest extent, where trimesh's own merge is at
    1e-8 in any unit) and every step of :func:`mesh_to_grid` are relative to the mesh's
    size, so the grid does not depend on the file's unit.

    For grid files, giving m and n that differ from the file's grid resamples bilinearly
    (``elastic_jax.resample``, :ref:`math §6 <math-6>`) in float64.

    ``normalize="area"`` scales the surface about its area centroid to the unit sphere's
    area 4 pi (:func:`normalize_scale`, on the grid read or resampled), so that distances
    compare shapes with size removed: they are then in units of the normalized size
    (every distance scales with the surfaces, d(s f1, s f2) = s d(f1, f2)). Call
    :func:`normalize_scale` on the result instead to keep the factor.

    Args:
        path: the file; the suffix picks the format.
        m, n: grid size, both or neither.
        progress: called with a line of text during a spherical parametrization.
        normalize: None (default, the file's size) or ``"area"``.
        return_map: meshes only: also return the :class:`VertexMap` of the mesh as read
            (:func:`mesh_to_grid`'s ``return_map``), to read grid surfaces back at its
            vertices. With ``normalize``, the grid is the scaled one and the map's
            vertices the file's.

    Returns:
        ``(3, m, n)`` float64 numpy array that passed ``validate_surface``; with
        ``return_map``, ``(grid, VertexMap)``.

    Raises:
        FileNotFoundError: no such file.
        KeyError: a grid file without the array ``f`` (the keys it has are named).
        ValueError: an unknown suffix (the supported ones are named), a badly shaped array,
            NaN/inf, or any other ``validate_surface`` failure; an unknown ``normalize``, or
            ``sphere``, ``frame`` or ``return_map`` with a grid file.
        MeshError: from :func:`mesh_to_grid` for meshes that are not closed, manifold,
            consistently wound genus-0 meshes without zero-area faces, or whose spherical
            parametrization stays folded (ParametrizationError).
    """
    path = pathlib.Path(path)
    if (m is None) != (n is None):
        raise InputError(f"give both m and n or neither; got m={m}, n={n}")
    if m is not None:
        m, n = operator.index(m), operator.index(n)
        check_grid_shape((3, m, n), "the grid (3, m, n)")
    kind = _suffix(path)
    mesh_formats = _mesh_loadable_formats()
    neuro = _neuro_kind(path)
    if kind not in _GRID_FORMATS and kind not in mesh_formats and neuro is None:
        raise _unknown_suffix(path, "load", _GRID_FORMATS + mesh_formats + _NEURO_FORMATS)
    return_map = check_bool("return_map", return_map)
    if (sphere is not None or frame is not None or return_map) and kind in _GRID_FORMATS:
        raise InputError(
            f"sphere=, frame= and return_map= resample a mesh; {str(path)!r} is a grid file"
        )
    if normalize is not None:
        check_choice("normalize", normalize, ("area",))
    _check_exists(path)
    vertex_map = None

    if neuro is not None or kind in mesh_formats:
        if neuro is not None:
            mesh = trimesh.Trimesh(*_neuro_mesh(path), process=False)
        else:
            # Keep the file's vertices as they are when a map of them is given.
            merge = sphere is None
            mesh = _read(path, kind, lambda: _load_mesh(path, merge))
        if sphere is not None and not isinstance(sphere, np.ndarray):
            sphere = _map_positions(pathlib.Path(sphere))
        try:
            f = mesh_to_grid(
                mesh,
                50 if m is None else m,
                99 if n is None else n,
                sphere=sphere,
                frame=frame,
                progress=progress,
                return_map=return_map,
            )
        except MeshError as err:
            err.args = (f"{str(path)!r}: {err}", *err.args[1:])
            raise
        if return_map:
            f, vertex_map = f
    else:
        if kind == "npz":
            f = _read(path, kind, lambda: _load_npz_f(path))
        else:
            f = _read(path, kind, lambda: _from_key(_loadmat(path), path))
            if f.ndim == 3 and f.shape[-1] == 3 and f.shape[0] != 3:
                f = f.transpose(2, 0, 1)
        if f.ndim != 3:
            raise InputError(f"the array 'f' in {str(path)!r} has shape {f.shape}; need (3, m, n)")
        if not np.issubdtype(f.dtype, np.number) or np.iscomplexobj(f):
            raise InputError(f"the array 'f' in {str(path)!r} is not real numbers: {f.dtype}")
        f = f.astype(np.float64)
        validate_surface(f, f"the surface in {str(path)!r}")
        if m is not None and (m, n) != f.shape[1:]:
            # Keep float64 whatever the caller's JAX precision setting.
            with jax.enable_x64(True):
                f = np.asarray(resample(f, m, n), dtype=np.float64)
    # Checked once: a valid grid resamples to a valid grid, and mesh_to_grid builds exact
    # pole rows and seams.
    if normalize == "area":
        f = normalize_scale(f)[0]
    return f if vertex_map is None else (f, vertex_map)


def _checked_surfaces(x, name: str, layout: str, any_rank: bool = False) -> np.ndarray:
    """``x`` as a floating numpy array that passed validate_surface and has ``layout``'s rank
    (any rank with ``any_rank``)."""
    x = np.asarray(x)
    if not np.issubdtype(x.dtype, np.floating):
        x = x.astype(np.float64)
    validate_surface(x, name)
    if not any_rank and x.ndim != layout.count(",") + 1:
        raise InputError(f"{name} must have shape {layout}; got shape {x.shape}")
    return x


def _export_gifti(mesh: trimesh.Trimesh, path: pathlib.Path) -> pathlib.Path:
    """A GIfTI surface: the vertices as a float32 NIFTI_INTENT_POINTSET, the faces as an
    int32 NIFTI_INTENT_TRIANGLE (the types GIfTI readers expect), base64-gzip encoded."""
    nibabel = _nibabel(path, "writing GIfTI surfaces")
    gifti = nibabel.gifti
    image = gifti.GiftiImage(
        darrays=[
            gifti.GiftiDataArray(
                np.asarray(mesh.vertices, np.float32),
                intent="NIFTI_INTENT_POINTSET",
                datatype="NIFTI_TYPE_FLOAT32",
            ),
            gifti.GiftiDataArray(
                np.asarray(mesh.faces, np.int32),
                intent="NIFTI_INTENT_TRIANGLE",
                datatype="NIFTI_TYPE_INT32",
            ),
        ]
    )
    with atomic_path(path) as tmp:
        # Written to bytes here: nibabel picks its writer by the temporary's suffix.
        pathlib.Path(tmp).write_bytes(image.to_bytes())
    return path


def _export_mesh(mesh: trimesh.Trimesh, path: pathlib.Path) -> pathlib.Path:
    kind = _suffix(path)
    if kind == "gii":
        return _export_gifti(mesh, path)
    options = {}
    if kind in _DECIMALS:
        # Fixed-point text: trimesh's decimals (8 for .obj, 10 for .off) are absolute; a
        # mesh smaller than 1 across gets as many more as keep its precision relative to
        # its size (.obj kept 3 digits of a 14 um surface given in metres).
        extent = float(np.ptp(mesh.vertices, axis=0).max())
        extra = max(0, -int(np.floor(np.log10(extent)))) if extent > 0 else 0
        options["digits"] = _DECIMALS[kind] + extra
    with atomic_path(path) as tmp:
        mesh.export(tmp, file_type=kind, **options)
    return path


def save_surface(f, path: str | os.PathLike) -> pathlib.Path:
    """Write one surface ``(3, m, n)`` to ``path`` atomically; the suffix picks the format.

    ``.npz``: the array under the key ``f``, exactly. A mesh format (``MESH_FORMATS``:
    ``.ply .obj .off .stl .glb``, or GIfTI ``.gii``): the triangulation of
    :func:`grid_to_mesh` (the grid's vertices, no seam copies), which :func:`load_surface`
    projects back onto a grid (with ``frame="input"`` the same grid, when it is radial
    about its area centroid). The mesh writers round coordinates: .ply, .stl, .glb and
    .gii store float32, .obj 8 decimals and .off 10 (more for a surface smaller than 1
    across: as many as keep that precision relative to its size); use .npz to keep float64.
    GIfTI is written with nibabel (``pip install "elastic-jax[neuro]"``): one float32
    ``NIFTI_INTENT_POINTSET`` and one int32 ``NIFTI_INTENT_TRIANGLE`` array, the types
    neuroimaging readers (FreeSurfer, Workbench, nilearn) expect (float32 is the only
    floating type GIfTI's standard lists).

    Args:
        f: ``(3, m, n)`` surface, checked with ``validate_surface``.
        path: the destination; its directory is created if missing.

    Returns:
        the path written.

    Raises:
        ValueError: a bad surface or an unknown suffix (the supported ones are named).
        InputError: ``.gii`` without nibabel (the extra to install is named).
    """
    path = pathlib.Path(path)
    kind = _suffix(path)
    if kind != "npz" and kind not in _WRITTEN_FORMATS:
        raise _unknown_suffix(path, "save", ("npz",) + _WRITTEN_FORMATS)
    f = _checked_surfaces(f, "f", "(3, m, n)")
    if kind == "npz":
        return save_npz_atomic(path, f=f)
    return _export_mesh(grid_to_mesh(f), path)


def _json_default(value):
    # numpy and JAX scalars and arrays: what settings dicts built from results hold.
    if isinstance(value, np.generic | np.ndarray | jax.Array):
        return np.asarray(value).tolist()
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    raise TypeError(f"settings value {value!r} of type {type(value).__name__} is not JSON data")


def save_path(
    path,
    directory: str | os.PathLike,
    format: str = "ply",
    settings: Mapping | None = None,
) -> list[pathlib.Path]:
    """Write a path of surfaces: one mesh per time point and the whole array as .npz.

    Files, each written atomically: ``frame_000.<format>``, ``frame_001.<format>``, ...
    (three digits, more when N > 1000), the triangulation of :func:`grid_to_mesh` for
    each time point, and ``path.npz`` holding the array ``path`` and, under ``settings``,
    the settings as a JSON string (a 0-d unicode array, so ``np.load`` reads it without
    pickles: ``json.loads(str(np.load(p)["settings"]))``).

    Args:
        path: ``(N, 3, m, n)`` surfaces, e.g. ``GeodesicResult.path``.
        directory: created if missing.
        format: a mesh format in ``MESH_FORMATS`` (``ply obj off stl glb``), or ``gii``
            (GIfTI, float32, with nibabel: see :func:`save_surface`).
        settings: JSON data (numbers, strings, lists, dicts; numpy and JAX scalars and
            arrays become numbers and lists), e.g. the metric and solver options used.

    Returns:
        The paths written: the N frames in order, then ``path.npz``.

    Raises:
        ValueError: a bad path array or an unknown format.
        TypeError: settings that are not JSON data (checked before anything is written).
    """
    kind = str(format).lower().lstrip(".")
    if kind not in _WRITTEN_FORMATS:
        raise InputError(
            f"unknown mesh format {format!r}; supported: {', '.join(_WRITTEN_FORMATS)}"
        )
    if kind == "gii":  # before anything is written
        _nibabel(pathlib.Path(directory), "writing GIfTI surfaces")
    surfaces = _checked_surfaces(path, "path", "(N, 3, m, n)")
    text = json.dumps({} if settings is None else dict(settings), default=_json_default)
    directory = pathlib.Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    digits = max(3, len(str(len(surfaces) - 1)))
    written = [
        _export_mesh(grid_to_mesh(f), directory / f"frame_{k:0{digits}d}.{kind}")
        for k, f in enumerate(surfaces)
    ]
    # Not save_npz_atomic: its first parameter is called path, like the array.
    target = directory / "path.npz"
    with atomic_path(target, suffix=".npz") as tmp, open(tmp, "wb") as fh:
        np.savez(fh, path=surfaces, settings=np.str_(text))
    written.append(target)
    return written
