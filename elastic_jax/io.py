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
job leaves the previous file or the new one, never part of one. The same writes serve a
user's own long jobs: :func:`atomic_path`, :func:`save_npz_atomic`, :func:`write_text_atomic`,
and :func:`stale_temporaries` for the temporaries a killed job left behind.

Like the package's functions, these trace float32 matrix products at float32's own
precision unless the caller has chosen one (the sphere map and the grid reads are such
products; on recent GPUs JAX's default is TensorFloat-32).

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
from collections.abc import Callable, Mapping, Sequence

import jax
import numpy as np
import scipy.io
import trimesh
from jaxtyping import ArrayLike

from ._checks import check_bool, check_choice, check_grid_shape, check_positive
from ._errors import FrameWarning, InputError
from ._geometry.interp import resample
from ._geometry.srnf import center_unchecked, surface_area_unchecked
from ._geometry.validation import validate_surface
from ._meshes.frame import MeshFrame
from ._meshes.resample import (
    VertexMap,
    checked_surfaces,
    grid_to_mesh,
    grid_to_vertices,
    mesh_frame,
    mesh_to_grid,
    spherical_parametrization,
    star_center,
)
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
)
from ._runtime import precision as _precision
from ._runtime.atomic import atomic_path, save_npz_atomic, stale_temporaries, write_text_atomic

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
    "atomic_path",
    "grid_to_mesh",
    "grid_to_vertices",
    "load_surface",
    "mesh_frame",
    "mesh_to_grid",
    "normalize_scale",
    "save_npz_atomic",
    "save_path",
    "save_surface",
    "spherical_parametrization",
    "stale_temporaries",
    "star_center",
    "surface_files",
    "write_text_atomic",
]

#: Mesh formats that :func:`save_surface` and :func:`save_path` write with trimesh and that
#: load back. (glTF is left out: trimesh writes it as several files, which cannot be renamed
#: at once.) Both also write GIfTI (``.gii``) with nibabel, the ``neuro`` extra.
MESH_FORMATS = ("ply", "obj", "off", "stl", "glb")

# What save_surface and save_path write: trimesh's formats and GIfTI (nibabel).
_WRITTEN_FORMATS = MESH_FORMATS + ("gii",)

# What area normalize= scales a surface to: the unit sphere's.
_UNIT_AREA = 4.0 * np.pi


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


# The decimals trimesh's text writers give coordinates of size 1 (fixed point).
_DECIMALS = {"obj": 8, "off": 10}


def _mesh_loadable_formats() -> tuple[str, ...]:
    # xyz is a point cloud and stl_ascii no file suffix; both are loader names only.
    return tuple(sorted(trimesh.exchange.load.mesh_formats() - {"xyz", "stl_ascii"}))


def _suffix(path: pathlib.Path) -> str:
    return path.suffix.lower().lstrip(".")


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
    f = checked_surfaces(np.asarray(f, dtype=np.float64), "f", "(..., 3, m, n)", any_rank=True)
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


def _export_gifti(
    mesh: trimesh.Trimesh, path: pathlib.Path, values: Mapping[str, np.ndarray] | None = None
) -> pathlib.Path:
    """A GIfTI surface: the vertices as a float32 NIFTI_INTENT_POINTSET, the faces as an
    int32 NIFTI_INTENT_TRIANGLE (the types GIfTI readers expect), base64-gzip encoded;
    each per-vertex value a float32 NIFTI_INTENT_SHAPE array named by its ``Name``."""
    nibabel = _nibabel(path, "writing GIfTI surfaces")
    gifti = nibabel.gifti
    darrays = [
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
    for name, value in (values or {}).items():
        darrays.append(
            gifti.GiftiDataArray(
                np.asarray(value, np.float32),
                intent="NIFTI_INTENT_SHAPE",
                datatype="NIFTI_TYPE_FLOAT32",
                meta={"Name": name},
            )
        )
    image = gifti.GiftiImage(darrays=darrays)
    with atomic_path(path) as tmp:
        # Written to bytes here: nibabel picks its writer by the temporary's suffix.
        pathlib.Path(tmp).write_bytes(image.to_bytes())
    return path


def _export_mesh(
    mesh: trimesh.Trimesh, path: pathlib.Path, values: Mapping[str, np.ndarray] | None = None
) -> pathlib.Path:
    kind = _suffix(path)
    if kind == "gii":
        return _export_gifti(mesh, path, values)
    for name, value in (values or {}).items():  # .ply: vertex properties (float64)
        mesh.vertex_attributes[name] = np.asarray(value, np.float64)
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


# The formats that carry per-vertex values beside the surface (save_surface's fields).
_FIELD_FORMATS = ("npz", "ply", "gii")


def _checked_fields(fields: Mapping, grid: tuple[int, int], kind: str) -> dict[str, np.ndarray]:
    if not isinstance(fields, Mapping):
        raise InputError(f"fields must be a mapping of names to (m, n) arrays; got {fields!r}")
    if fields and kind not in _FIELD_FORMATS:
        raise InputError(
            f"fields are written to {', '.join('.' + k for k in _FIELD_FORMATS)} files, not .{kind}"
        )
    checked = {}
    for name, value in fields.items():
        if not isinstance(name, str) or not name.isidentifier() or name in ("f", "x", "y", "z"):
            raise InputError(f"field name {name!r} must be an identifier other than f, x, y, z")
        value = np.asarray(value, dtype=np.float64)
        if value.shape != grid:
            raise InputError(
                f"field {name!r} must have the surface's grid shape {grid}; got {value.shape}"
            )
        if not np.isfinite(value).all():
            raise InputError(f"field {name!r} has NaN or infinite values")
        checked[name] = value
    return checked


def _vertex_values(field: np.ndarray) -> np.ndarray:
    """A grid field's values at grid_to_mesh's vertices: the distinct grid points, each
    pole the mean of its row (a field of the pole's own point is constant there)."""
    poles = np.stack([field[0, :-1].mean(), field[-1, :-1].mean()])
    return np.concatenate([poles[:1], field[1:-1, :-1].reshape(-1), poles[1:]])


def save_surface(
    f, path: str | os.PathLike, fields: Mapping[str, ArrayLike] | None = None
) -> pathlib.Path:
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

    ``fields`` are values on the grid beside the surface (e.g. the terms of
    :func:`~elastic_jax.energy_density`), so that a viewer (FreeSurfer, Connectome
    Workbench, ParaView, MeshLab) shows them on the mesh: in ``.npz`` each array under its
    name, exactly; in ``.ply`` a float64 vertex property per field; in ``.gii`` a float32
    ``NIFTI_INTENT_SHAPE`` array per field with its name in the array's ``Name``. A mesh
    vertex takes its grid point's value, each pole the mean of its row.

    Args:
        f: ``(3, m, n)`` surface, checked with ``validate_surface``.
        path: the destination; its directory is created if missing.
        fields: ``{name: (m, n) array}``, finite; names are identifiers other than f, x, y
            and z. Only for ``.npz``, ``.ply`` and ``.gii``.

    Returns:
        the path written.

    Raises:
        ValueError: a bad surface or an unknown suffix (the supported ones are named).
        InputError: ``.gii`` without nibabel (the extra to install is named); a field of
            the wrong shape, not finite, badly named, or for a format without fields (each
            names the field or the format).
    """
    path = pathlib.Path(path)
    kind = _suffix(path)
    if kind != "npz" and kind not in _WRITTEN_FORMATS:
        raise _unknown_suffix(path, "save", ("npz",) + _WRITTEN_FORMATS)
    f = checked_surfaces(f, "f", "(3, m, n)")
    values = _checked_fields(fields or {}, tuple(f.shape[1:]), kind)
    if kind == "npz":
        return save_npz_atomic(path, f=f, **values)
    vertex_values = {name: _vertex_values(value) for name, value in values.items()}
    return _export_mesh(grid_to_mesh(f), path, vertex_values)


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
    surfaces = checked_surfaces(path, "path", "(N, 3, m, n)")
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


_precision.trace_public_at_full_precision(globals(), __all__)
