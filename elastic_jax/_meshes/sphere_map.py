"""A bijective map of a closed genus-0 triangle mesh onto the unit sphere.

Pipeline (each step keeps the map free of folds, the last one repairs what the first ones
could not):

1. Puncture: remove the mesh's largest face (the first one, up to rounding); what is left
   is a topological disk.
2. Tutte map with mean-value weights (Floater 2003): fix the removed face's vertices on an
   equilateral triangle and place every other vertex at the weighted mean of its
   neighbours. The weights are positive, so the planar map is an embedding (Floater's
   theorem), whatever the mesh's shape.
3. Inverse stereographic projection, then a Moebius centring: the conformal map of the
   sphere that puts the area-weighted centroid of the vertices at the origin (Baden,
   Crane and Kazhdan, "Moebius registration", 2018). Steps 2-3 are conformal-ish and
   leave thin parts of the mesh (legs, tails) squeezed by many orders of magnitude.
4. A foldover-free optimization on the sphere: the energy of Garanzha, Kaporin,
   Kudryavtseva, Protais, Ray and Sokolov ("Foldover-free maps in 50 lines of code",
   ACM TOG 2021) that balances angle distortion |J|^2 / det J and area distortion
   det J + 1 / det J, with det J regularized by chi(D, eps) = (D + sqrt(eps^2 + D^2)) / 2
   so that it is finite for folded triangles (it untangles) and a barrier as eps -> 0.
   L-BFGS (optimistix) minimizes it for a decreasing sequence of eps until no face is
   folded, then for eps = 1e-8, in multilevel variables (a change of variables; the
   solver is untouched): smoothed-aggregation algebraic multigrid (pyamg) coarsens the
   cotangent Laplacian K of the mesh into levels of about a tenth of the vertices each,
   down to 100 or fewer, with prolongations P_l from level l + 1 to level l; the map is
   x = sum_l Q_l S_l y_l with Q_l = P_0 ... P_(l-1), S_l = diag(Q_l^T K Q_l)^(-1/2).
   L-BFGS then moves all scales at once: the gradient in y_l is S_l Q_l^T g, the additive
   multilevel (BPX) preconditioner of Bramble, Pasciak and Xu (Math. Comp. 1990) with
   multilevel diagonal scaling. Each evaluation costs about 25 % more; the number of
   iterations grows slowly with the mesh's size.
5. An area-weighted Kabsch rotation that turns the sphere map towards the directions of
   the mesh's vertices from its area centroid.

Everything is intrinsic (edge lengths and angles) until step 5; the io layer passes the
mesh in its principal frame (``_meshes.frame``), so the map is attached to the mesh and
a rigidly moved or scaled copy gets the same one.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse
import scipy.sparse.csgraph
import scipy.sparse.linalg
import scipy.spatial
from jaxtyping import Bool

from .._checks import check_grid_shape, check_int, check_positive
from .._errors import ConvergenceWarning, InputError, warn_user
from .._geometry.grid import from_distinct, grid_directions
from .._geometry.triangles import corner_weight_matrix
from .._results import RESULTS, status_record
from .._runtime.cache import cached

# Faces whose area is below this fraction of the mean face area count as zero-area.
_ZERO_AREA = 1e-12

# L-BFGS iterations between updates of eps (Garanzha et al. update it after each solve).
_ROUND = 250

# Cotangent weights below this are raised to it (_stiffness).
_COT_FLOOR = 0.01

# pyamg stops coarsening at this many vertices (_levels).
_COARSEST = 100


class MeshError(InputError):
    """A mesh that cannot be turned into a surface on the spherical grid."""


class NotWatertightError(MeshError):
    """The mesh has boundary edges (or edges shared by more than two faces)."""


class NotGenusZeroError(MeshError):
    """The mesh is closed but not a sphere: its Euler characteristic is not 2."""


class NotStarShapedError(MeshError):
    """Some ray from the centre misses the mesh or crosses it more than once."""


class NonManifoldVertexError(MeshError):
    """The faces around some vertex form more than one fan (surfaces touching at a point)."""


class InconsistentWindingError(MeshError):
    """Neighbouring faces are wound in opposite directions (some faces are flipped)."""


class DegenerateFaceError(MeshError):
    """Some faces have zero area (repeated or collinear vertices)."""


class ParametrizationError(MeshError):
    """The optimization ended with folded (flipped) triangles on the sphere.

    Attributes:
        flipped: the number of faces whose image on the sphere is turned over.
    """

    def __init__(self, message: str, flipped: int):
        super().__init__(message)
        self.flipped = flipped


@status_record
class SphericalParametrization(NamedTuple):
    """A bijective map of a closed genus-0 mesh onto the unit sphere, with its quality.

    ``sphere[k]`` is the image of ``vertices[k]``; every face keeps its orientation (the
    triple product sphere[a] . (sphere[b] x sphere[c]) of each face (a, b, c) is positive)
    and the spherical triangles tile the sphere once (their areas sum to 4 pi).

    Attributes:
        vertices: ``(V, 3)`` float64, the mesh's vertices.
        faces: ``(F, 3)`` int64, the mesh's faces, wound outward (counterclockwise seen from
            outside; the input's faces, all turned if they were wound inward).
        sphere: ``(V, 3)`` float64 unit vectors.
        flipped: faces whose image is folded over (0 in every returned record).
        area_distortion: max over faces of max(r, 1/r), r the face's share of the sphere's
            area over its share of the mesh's area (spherical triangle areas).
        area_distortion_p99: the 99th percentile of the same, less sensitive to one face.
        angle_error: mean absolute difference, in degrees, between each corner's angle on
            the mesh and on the sphere's chord triangle (0 for a conformal map).
        energy: the final distortion energy per unit area (2 for an isometry, the minimum).
        iterations: L-BFGS iterations in all.
        seconds: wall-clock time of the whole parametrization.
        converged: ``()`` bool array, True when the energy stopped decreasing (relative
            change below ``rtol`` over a round of iterations) before ``max_steps``.
    """

    vertices: np.ndarray
    faces: np.ndarray
    sphere: np.ndarray
    flipped: int
    area_distortion: float
    area_distortion_p99: float
    angle_error: float
    energy: float
    iterations: int
    seconds: float
    converged: Bool[np.ndarray, ""]

    # The result protocol (elastic_jax.RESULTS), from the fields above.
    @property
    def num_steps(self) -> int:
        """L-BFGS iterations in all (``iterations``)."""
        return self.iterations

    @property
    def result(self) -> RESULTS:
        """``successful``, or ``nonlinear_max_steps_reached`` (the energy still fell at
        max_steps)."""
        return RESULTS.successful if self.converged else RESULTS.nonlinear_max_steps_reached

    def spherical_areas(self) -> np.ndarray:
        """``(F,)`` signed areas of the faces' spherical triangles; they sum to 4 pi for a
        map that tiles the sphere once (see :func:`spherical_triangle_areas`)."""
        return spherical_triangle_areas(self.sphere, self.faces)

    def to_grid(self, m: int = 50, n: int = 99) -> np.ndarray:
        """The mesh resampled on the m x n spherical grid through this map.

        Each grid direction u (math §1) is located in the spherical triangle that
        contains it, u = sum_k lam_k sphere[c_k] with lam_k >= 0, and the surface point is
        the same combination of the mesh's vertices, sum_k lam_k vertices[c_k] / sum lam:
        a point on the mesh, continuous across edges.

        Returns:
            ``(3, m, n)`` float64 (poles and seam repeated as on the grid).
        """
        check_grid_shape((3, m, n), "the grid (3, m, n)")
        directions = grid_directions(m, n)
        return from_distinct(sample_mesh(self, directions), m, n)


def _face_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    t = vertices[faces]
    return 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)


def _edge_keys(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Half-edges ``(start, end)`` of every face, flattened, and one key per undirected edge."""
    start, end = faces.reshape(-1), faces[:, [1, 2, 0]].reshape(-1)
    return start, end, np.minimum(start, end) * (int(faces.max()) + 1) + np.maximum(start, end)


def _half_edge_pairs(start: np.ndarray, end: np.ndarray, key: np.ndarray):
    """For every undirected edge, its two half-edges (a closed, edge-manifold mesh).

    Returns:
        ``(start, end, corner_start, corner_end)``, each ``(E, 2)``: the half-edge from
        vertex start to vertex end in face f is (f, k) -> (f, k + 1 mod 3); corners are
        indices 3 f + k into the flattened face array.
    """
    corner = np.arange(start.size)
    corner_end = (corner // 3) * 3 + (corner % 3 + 1) % 3
    order = np.argsort(key, kind="stable")
    pairs = order.reshape(-1, 2)  # watertight: every key exactly twice
    return start[pairs], end[pairs], corner[pairs], corner_end[pairs]


def check_mesh(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Refuse what cannot be mapped onto the sphere; return the faces wound outward.

    The checks, in order: faces present; closed (every edge in exactly two faces);
    vertex-manifold (the faces around each vertex form one fan: two spheres glued at two
    vertices are closed, connected and have Euler characteristic 2, but are no sphere);
    one connected component; Euler characteristic V - E + F = 2; consistent winding (each
    edge traversed once in each direction); no face with zero area (below 1e-12 of the
    mean face area). Vertices referenced by no face are allowed and ignored.

    Args:
        vertices: ``(V, 3)`` float64, finite.
        faces: ``(F, 3)`` integer indices into vertices.

    Returns:
        ``(F, 3)`` int64, the faces, all reversed when the mesh encloses negative volume.

    Raises:
        MeshError (or one of its subclasses named above) describing the first failure.
    """
    if len(faces) == 0:
        raise MeshError("the mesh has no faces")
    if not np.all(np.isfinite(vertices)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(vertices), axis=1))[0])
        raise MeshError(f"the mesh has non-finite vertex coordinates (first: vertex {bad})")
    faces = np.asarray(faces, dtype=np.int64)
    repeated = (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2])
    repeated |= faces[:, 2] == faces[:, 0]
    if np.any(repeated):
        raise DegenerateFaceError(
            f"{int(repeated.sum())} face(s) repeat a vertex (first: face "
            f"{int(np.flatnonzero(repeated)[0])}, {faces[repeated][0].tolist()}); they have "
            "zero area"
        )
    start, end, key = _edge_keys(faces)
    _, counts = np.unique(key, return_counts=True)
    if np.any(counts != 2):
        raise NotWatertightError(
            f"the mesh is not closed (watertight): {int(np.sum(counts == 1))} edge(s) belong "
            f"to one face only and {int(np.sum(counts > 2))} to more than two, out of "
            f"{len(counts)} edges; a surface on the sphere grid needs a closed mesh (if the "
            "file repeats vertices per face, load it with trimesh's default process=True "
            "or call mesh.merge_vertices())"
        )
    a, b, ca, cb = _half_edge_pairs(start, end, key)
    # Corners at the same vertex are linked across each edge; the links of a vertex whose
    # faces form one fan connect all its corners.
    same = a[:, 0] == a[:, 1]
    left = np.concatenate([ca[:, 0], cb[:, 0]])
    right = np.concatenate([np.where(same, ca[:, 1], cb[:, 1]), np.where(same, cb[:, 1], ca[:, 1])])
    n_corners = faces.size
    graph = scipy.sparse.coo_matrix(
        (np.ones(left.size), (left, right)), shape=(n_corners, n_corners)
    )
    n_fans, label = scipy.sparse.csgraph.connected_components(graph, directed=False)
    used = np.unique(faces)
    if n_fans != used.size:
        fans_at = np.bincount(
            np.unique(np.stack([faces.reshape(-1), label], axis=1), axis=0)[:, 0],
            minlength=len(vertices),
        )
        bad = np.flatnonzero(fans_at > 1)
        raise NonManifoldVertexError(
            f"the mesh is not a manifold at {bad.size} vertex(es): the faces around vertex "
            f"{int(bad[0])} form {int(fans_at[bad[0]])} separate fans (surfaces touching "
            "at a point); split or remove those vertices"
        )
    edges = scipy.sparse.coo_matrix(
        (np.ones(len(a)), (a[:, 0], b[:, 0])), shape=(len(vertices), len(vertices))
    )
    n_parts, part = scipy.sparse.csgraph.connected_components(edges, directed=False)
    n_parts -= len(vertices) - used.size  # unreferenced vertices are components of their own
    if n_parts != 1:
        raise MeshError(
            f"the mesh has {n_parts} connected components; a surface on the sphere grid is one"
        )
    chi = used.size - len(counts) + len(faces)
    if chi != 2:
        raise NotGenusZeroError(
            f"the mesh is closed but not a topological sphere: its Euler characteristic "
            f"V - E + F is {chi}, not 2 (genus (2 - chi)/2 = {(2 - chi) / 2:g})"
        )
    inconsistent = a[:, 0] == a[:, 1]  # both faces traverse the edge the same way
    if np.any(inconsistent):
        u, w = int(a[inconsistent][0, 0]), int(b[inconsistent][0, 0])
        raise InconsistentWindingError(
            f"{int(inconsistent.sum())} edge(s) are traversed in the same direction by both "
            f"their faces (first: edge {u}-{w}): the faces are not wound consistently; "
            "trimesh.repair.fix_winding(mesh) reorients them"
        )
    area = _face_areas(vertices, faces)
    tiny = area <= _ZERO_AREA * area.mean()
    if np.any(tiny):
        k = int(np.flatnonzero(tiny)[0])
        raise DegenerateFaceError(
            f"{int(tiny.sum())} face(s) have zero area (first: face {k}, vertices "
            f"{faces[k].tolist()}, area {area[k]:.3g} against a mean of {area.mean():.3g}); "
            "remove them (trimesh's mesh.update_faces(mesh.nondegenerate_faces()) and "
            "a re-merge)"
        )
    t = vertices[faces]
    volume = np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum()
    return faces[:, ::-1].copy() if volume < 0 else faces


def _corner_angles(t: np.ndarray) -> np.ndarray:
    """Angles ``(F, 3)`` of triangles ``t`` ``(F, 3, 3)`` at their corners 0, 1, 2."""
    out = np.empty(t.shape[:2])
    for k in range(3):
        u, w = t[:, (k + 1) % 3] - t[:, k], t[:, (k + 2) % 3] - t[:, k]
        cross = np.linalg.norm(np.cross(u, w), axis=1)
        out[:, k] = np.arctan2(cross, np.einsum("ij,ij->i", u, w))
    return out


def _tutte(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Planar mean-value Tutte map of the mesh with its largest face removed.

    Returns:
        ``(V, 2)``: the removed face's corners on an equilateral triangle of circumradius
        1, counterclockwise as seen from inside that face (the rest of the mesh's
        orientation), every other vertex a convex combination of its neighbours.
    """
    t = vertices[faces]
    angle = _corner_angles(t)
    rows, cols, vals = [], [], []
    for k in range(3):
        i, j, l = faces[:, k], faces[:, (k + 1) % 3], faces[:, (k + 2) % 3]
        half = np.tan(angle[:, k] / 2)
        for other in (j, l):
            rows.append(i)
            cols.append(other)
            vals.append(half / np.linalg.norm(vertices[other] - vertices[i], axis=1))
    nv = len(vertices)
    weights = scipy.sparse.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(nv, nv)
    )
    # The first face within rounding of the largest: a moved copy of the mesh (areas equal
    # to rounding) removes the same face, so its map is the same.
    area = _face_areas(vertices, faces)
    hole = faces[int(np.argmax(area >= area.max() * (1 - 1e-9)))]
    # Removing the face (a, b, c) leaves a disk whose boundary runs a -> c -> b.
    corners = np.array([[np.cos(a), np.sin(a)] for a in 2 * np.pi * np.arange(3) / 3])
    fixed = np.zeros(nv, dtype=bool)
    fixed[hole] = True
    uv = np.zeros((nv, 2))
    uv[hole[[0, 2, 1]]] = corners
    used = np.zeros(nv, dtype=bool)
    used[faces] = True
    free = np.flatnonzero(used & ~fixed)
    laplacian = scipy.sparse.diags(np.asarray(weights.sum(axis=1)).ravel()) - weights
    laplacian = laplacian.tocsr()
    lhs = laplacian[free][:, free].tocsc()
    rhs = -laplacian[free][:, np.flatnonzero(fixed)] @ uv[fixed]
    uv[free] = scipy.sparse.linalg.splu(lhs).solve(np.ascontiguousarray(rhs))
    return uv


def _stereographic(uv: np.ndarray) -> np.ndarray:
    """Inverse stereographic projection of the plane onto the unit sphere (from +z)."""
    r2 = np.sum(uv**2, axis=1, keepdims=True)
    return np.concatenate([2 * uv, r2 - 1], axis=1) / (r2 + 1)


def _moebius(p: np.ndarray, a: np.ndarray) -> np.ndarray:
    """The Moebius map of the unit ball taking 0 to a, restricted to the sphere.

    phi_a(x) = ((1 + 2 a.x + |x|^2) a + (1 - |a|^2) x) / (1 + 2 a.x + |a|^2 |x|^2),
    with |x| = 1: conformal, maps the sphere onto itself and gathers points towards a.
    """
    ax = p @ a
    aa = a @ a
    out = ((2 + 2 * ax)[:, None] * a + (1 - aa) * p) / (1 + 2 * ax + aa)[:, None]
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def _centre(p: np.ndarray, weight: np.ndarray, steps: int = 200) -> np.ndarray:
    """Moebius-centre p: the weighted centroid moved to the origin (to 1e-12)."""
    for _ in range(steps):
        c = weight @ p
        if np.linalg.norm(c) < 1e-12:
            break
        # Half a step towards the antipode of the centroid: the centroid of phi_a(p) moves
        # by about -2 a for a spread-out p; a full step overshoots for concentrated ones.
        p = _moebius(p, -0.5 * c)
    return p


def _vertex_weights(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    area = _face_areas(vertices, faces)
    w = np.bincount(faces.reshape(-1), np.repeat(area / 3, 3), minlength=len(vertices))
    return w / w.sum()


def _chi(d, eps):
    return 0.5 * (d + jnp.sqrt(eps**2 + d**2))


def _distortion(x, faces, gram_inv, area, eps, area_weight):
    """Per-face (angle, area) terms of Garanzha et al.'s energy for sphere points x / |x|.

    D = p0 . (p1 x p2) / (2 A) is the chord triangle's area over the reference area A,
    times the chord plane's distance from the origin (1 for small triangles), signed: a
    folded face has D <= 0. |J|^2 = tr(G_T G_R^-1) with G the edge Gram matrices.
    """
    p = x / jnp.linalg.norm(x, axis=1, keepdims=True)
    p0, p1, p2 = p[faces[:, 0]], p[faces[:, 1]], p[faces[:, 2]]
    t1, t2 = p1 - p0, p2 - p0
    g11, g12, g22 = (t1 * t1).sum(1), (t1 * t2).sum(1), (t2 * t2).sum(1)
    frob = g11 * gram_inv[:, 0] + 2 * g12 * gram_inv[:, 1] + g22 * gram_inv[:, 2]
    d = (p0 * jnp.cross(p1, p2)).sum(1) / (2 * area)
    chi = _chi(d, eps)
    return d, ((1 - area_weight) * frob + area_weight * (d**2 + 1)) / chi


def _energy(x, eps, faces, gram_inv, area, area_weight):
    _, e = _distortion(x, faces, gram_inv, area, eps, area_weight)
    return (area * e).sum() / area.sum()


def _stiffness(vertices: np.ndarray, faces: np.ndarray) -> scipy.sparse.csr_matrix:
    """The cotangent Laplacian of the reference mesh, its weights floored, plus a shift.

    K = sum over edges ij of w_ij (e_i - e_j)(e_i - e_j)^T + delta I, w_ij = (cot a + cot b)
    / 2 over the edge's opposite corners. It is the Hessian of the Dirichlet energy of the
    reference triangles, sum_T A_T |J_T|^2 (the angle term of the distortion energy, and the
    ellipticity of its area term): cot a grows as 1 / a for the needle triangles of a grid
    mesh's pole fans, which the graph Laplacian (all weights 1) misses. Each cotangent is
    floored at ``_COT_FLOOR`` (obtuse corners give negative weights, which algebraic
    multigrid does not want), and delta, 1/600 of the median diagonal, makes K positive
    definite (the constants are its kernel).
    """
    half = 0.5 * np.maximum(1 / np.tan(_corner_angles(vertices[faces])), _COT_FLOOR)
    weights = corner_weight_matrix(faces, half, len(vertices))
    diagonal = np.asarray(weights.sum(axis=1)).ravel()
    used = diagonal > 0  # vertices no face uses: identity rows
    shift = np.median(diagonal[used]) / 600
    return (scipy.sparse.diags(np.where(used, diagonal + shift, 1.0)) - weights).tocsr()


class _Levels(NamedTuple):
    """The multilevel change of variables x = sum_l Q_l S_l y_l (module docstring, step 4).

    ``rows[l], cols[l], vals[l]`` are the nonzeros of the prolongation P_l from level l + 1
    to level l (level 0 the mesh's vertices, Q_l = P_0 ... P_(l-1)); ``scales[l]``
    ``(V_l, 1)`` is S_l = diag(Q_l^T K Q_l)^(-1/2), K the stiffness (:func:`_stiffness`).
    """

    rows: tuple
    cols: tuple
    vals: tuple
    scales: tuple


def _levels(vertices: np.ndarray, faces: np.ndarray) -> _Levels:
    """Smoothed-aggregation multigrid levels of the stiffness (pyamg), as a _Levels."""
    import pyamg

    # Jacobi-smoothed prolongations weighted row by row (Gershgorin): pyamg's default
    # weighting divides by a spectral radius estimated from a random vector of numpy's
    # global generator, so two maps of one mesh differed (by 1e-3 of the sphere).
    hierarchy = pyamg.smoothed_aggregation_solver(
        _stiffness(vertices, faces),
        smooth=("jacobi", {"weighting": "local"}),
        max_coarse=_COARSEST,
    )
    prolong = [level.P.tocoo() for level in hierarchy.levels[:-1]]
    # pyamg's coarse operators are Galerkin products, A_(l+1) = P_l^T A_l P_l, so their
    # diagonals are those of Q_l^T K Q_l.
    return _Levels(
        rows=tuple(np.asarray(p.row, dtype=np.int64) for p in prolong),
        cols=tuple(np.asarray(p.col, dtype=np.int64) for p in prolong),
        vals=tuple(np.asarray(p.data, dtype=np.float64) for p in prolong),
        scales=tuple(1 / np.sqrt(level.A.diagonal())[:, None] for level in hierarchy.levels),
    )


def _to_x(ys: tuple, levels: _Levels):
    """x = sum_l Q_l S_l y_l, evaluated coarse to fine (Horner): ``ys[l]`` is ``(V_l, 3)``."""
    z = ys[-1] * levels.scales[-1]
    for k in range(len(levels.rows) - 1, -1, -1):
        spread = levels.vals[k][:, None] * z[levels.cols[k]]
        z = jax.ops.segment_sum(spread, levels.rows[k], num_segments=ys[k].shape[0])
        z = z + ys[k] * levels.scales[k]
    return z


def _to_y(x, levels: _Levels) -> tuple:
    """Variables that give x: all of it on the finest level, zero on the coarser ones."""
    zeros = tuple(jnp.zeros((s.shape[0], 3), dtype=x.dtype) for s in levels.scales[1:])
    return (x / levels.scales[0], *zeros)


@cached
def _solver(maxiter: int):
    """The compiled L-BFGS round of ``maxiter`` steps, in the multilevel variables y."""
    import optimistix as optx

    # optimistix's backtracking search never accepts a step that raises the energy (a
    # folded face under a small eps is a huge value, a point through the origin NaN);
    # rtol = atol at rounding level: the rounds decide when to stop.
    solver = optx.LBFGS(rtol=1e-12, atol=1e-12, history_length=10)

    def energy(ys, args):
        levels, *rest = args
        return _energy(_to_x(ys, levels), *rest)

    @jax.jit
    def solve(x, levels, eps, faces, gram_inv, area, area_weight):
        args = (levels, eps, faces, gram_inv, area, area_weight)
        ys = _to_y(x, levels)
        before = energy(ys, args)
        sol = optx.minimise(energy, solver, ys, args, max_steps=maxiter, throw=False)
        x = _to_x(sol.value, levels)
        d, e = _distortion(x, faces, gram_inv, area, eps, area_weight)
        after = (area * e).sum() / area.sum()
        return x, sol.stats["num_steps"], jnp.min(d), before, after, jnp.sum(d <= 0)

    return solve


def _reference(vertices: np.ndarray, faces: np.ndarray):
    """Reference Gram inverses (F, 3: [11, 12, 22]) and areas, scaled to total area 4 pi."""
    t = vertices[faces]
    r1, r2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    area = _face_areas(vertices, faces)
    scale = 4 * np.pi / area.sum()
    g11, g12, g22 = (r1 * r1).sum(1), (r1 * r2).sum(1), (r2 * r2).sum(1)
    det = g11 * g22 - g12**2
    gram_inv = np.stack([g22, -g12, g11], axis=1) / det[:, None] / scale
    return gram_inv, area * scale


def spherical_triangle_areas(sphere: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Signed areas of the spherical triangles (Van Oosterom and Strackee's formula).

    tan(E / 2) = p0 . (p1 x p2) / (1 + p0.p1 + p1.p2 + p2.p0) for unit p_k, E the spherical
    excess (the area). Positive for counterclockwise faces seen from outside.

    Returns:
        ``(F,)`` float64; they sum to 4 pi exactly when the faces tile the sphere once.
    """
    p0, p1, p2 = sphere[faces[:, 0]], sphere[faces[:, 1]], sphere[faces[:, 2]]
    num = np.einsum("ij,ij->i", p0, np.cross(p1, p2))
    den = 1 + np.einsum("ij,ij->i", p0, p1) + np.einsum("ij,ij->i", p1, p2)
    den += np.einsum("ij,ij->i", p2, p0)
    return 2 * np.arctan2(num, den)


def _triple(p: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """p_a . (p_b x p_c) for every face (a, b, c): positive where the image is not folded."""
    return np.einsum("ij,ij->i", p[faces[:, 0]], np.cross(p[faces[:, 1]], p[faces[:, 2]]))


def _kabsch(sphere, vertices, weight):
    """Rotate the sphere map towards the vertices' directions from their centroid."""
    centred = vertices - weight @ vertices
    cov = (weight[:, None] * centred).T @ sphere  # sum_i w_i y_i p_i^T
    u, _, vt = np.linalg.svd(cov)
    q = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    return sphere @ q.T


def parametrize(
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    area_weight: float = 0.9,
    max_steps: int = 20_000,
    rtol: float = 1e-5,
    init: np.ndarray | None = None,
    progress: Callable[[str], None] | None = None,
) -> SphericalParametrization:
    """The pipeline of the module docstring on checked, outward-wound faces."""
    start = time.perf_counter()
    area_weight = check_positive("area_weight", area_weight)
    if not area_weight <= 1:
        raise InputError(f"area_weight must be in (0, 1]; got {area_weight!r}")
    max_steps = check_int("max_steps", max_steps, 1)
    rtol = check_positive("rtol", rtol)
    if progress is not None and not callable(progress):
        raise InputError(f"progress must be a callable taking a line of text; got {progress!r}")
    weight = _vertex_weights(vertices, faces)
    if init is None:
        uv = _tutte(vertices, faces)
        # The plane's scale is a Moebius map too; start with the median vertex on the
        # equator so that the centring starts from a spread-out map.
        uv /= np.median(np.linalg.norm(uv, axis=1)[np.unique(faces)])
        p = _stereographic(uv)
        # Whether the projection kept the faces' orientation depends on how the plane is
        # seen; a mirror image turns every face over at once, so count and mirror.
        if np.sum(_triple(p, faces) > 0) < len(faces) / 2:
            p[:, 0] = -p[:, 0]
        p = _centre(p, weight)
    else:
        p = _unit_rows(init, vertices, faces, "init")
    gram_inv, area = _reference(vertices, faces)
    iterations, converged = 0, False
    levels = _levels(vertices, faces)
    with jax.enable_x64(True):
        args = (jnp.asarray(faces), jnp.asarray(gram_inv), jnp.asarray(area), area_weight)
        levels = jax.tree.map(jnp.asarray, levels)
        x = jnp.asarray(p)
        dmin = float(jnp.min(_distortion(x, *args[:3], 0.0, area_weight)[0]))
        # A folded start needs a regularized barrier to untangle; an unfolded one barely.
        # (eps is always a float64 scalar: a Python float would compile the round again.)
        eps = np.float64(2 * np.sqrt(1e-2 * (1e-2 - dmin)) if dmin <= 0 else 1e-8)
        while iterations < max_steps:
            steps = min(_ROUND, max_steps - iterations)
            x, k, dmin, before, after, flips = _solver(steps)(x, levels, eps, *args)
            x = x / jnp.linalg.norm(x, axis=1, keepdims=True)
            k, dmin, before, after = int(k), float(dmin), float(before), float(after)
            iterations += max(k, 1)
            if progress is not None:
                progress(
                    f"sphere map: {iterations} iterations, energy {after:.6g}, "
                    f"{int(flips)} folded faces, eps {eps:.2g}"
                )
            decrease = 1 - after / before
            if int(flips) == 0 and (k < steps or decrease < rtol):
                converged = True
                break
            if int(flips) == 0:
                # Untangled: the regularization has done its work, and the barrier itself
                # is minimized from here (Garanzha et al. lower eps slowly all the way;
                # measured: 1,750 -> 1,500 iterations on cat1's mesh, 3,500 -> 2,500 on the
                # horse's, 2,000 -> 1,500 on a 100k-face tube, the same energies to 1e-5).
                eps = np.float64(1e-8)
                continue
            # Garanzha et al.'s update: eps just large enough to keep the worst face's
            # regularized determinant a fraction (1 - sigma) of where it stands.
            sigma = max(decrease, 0.1)
            mu = (1 - sigma) * float(_chi(dmin, eps))
            eps = np.float64(2 * np.sqrt(mu * (mu - dmin)) if dmin < mu else 1e-8)
        sphere = np.asarray(x, dtype=np.float64)
        final = float(_energy(x, 0.0, *args))
    sphere = _kabsch(sphere, vertices, weight)
    flipped = int(np.sum(_triple(sphere, faces) <= 0))
    if flipped:
        raise ParametrizationError(
            f"the spherical parametrization ended with {flipped} folded face(s) of "
            f"{len(faces)} after {iterations} iterations (max_steps={max_steps}); raise max_steps "
            "or remesh the surface (very thin or needle-like triangles)",
            flipped,
        )
    if not converged:
        warn_user(
            f"spherical parametrization: not converged after max_steps={max_steps} iterations "
            f"(energy {final:.6g}, still falling by more than rtol={rtol:g} per round of "
            f"{_ROUND}); the map has no folds but is not the energy's minimizer: raise max_steps",
            ConvergenceWarning,
        )
    return _record(vertices, faces, sphere, final, iterations, converged, start)


def _record(
    vertices, faces, sphere, energy, iterations, converged, start
) -> SphericalParametrization:
    """The record of a map without folds, with its quality figures."""
    area = _face_areas(vertices, faces)
    share = spherical_triangle_areas(sphere, faces) / (4 * np.pi)
    ratio = share / (area / area.sum())
    distortion = np.maximum(ratio, 1 / ratio)
    angles_sphere = _corner_angles(sphere[faces])
    angles_mesh = _corner_angles(vertices[faces])
    return SphericalParametrization(
        vertices=vertices,
        faces=faces,
        sphere=sphere,
        flipped=0,
        area_distortion=float(distortion.max()),
        area_distortion_p99=float(np.percentile(distortion, 99)),
        angle_error=float(np.degrees(np.abs(angles_sphere - angles_mesh).mean())),
        energy=energy,
        iterations=iterations,
        converged=np.asarray(bool(converged)),
        seconds=time.perf_counter() - start,
    )


def _unit_rows(positions, vertices: np.ndarray, faces: np.ndarray, name: str) -> np.ndarray:
    """``positions (V, 3)``, one per vertex, as unit vectors; an InputError naming ``name``
    for a bad shape, NaN/inf or a zero row at a vertex of a face."""
    p = np.asarray(positions, dtype=np.float64)
    if p.shape != vertices.shape:
        raise InputError(
            f"{name} must have one position per mesh vertex, shape {vertices.shape}; got "
            f"{p.shape} (build the mesh with trimesh's process=False to keep a file's "
            "vertices and their order)"
        )
    if not np.all(np.isfinite(p)):
        raise InputError(f"{name} contains NaN or inf")
    norm = np.linalg.norm(p, axis=1, keepdims=True)
    if np.any(norm[np.unique(faces)] == 0):
        raise InputError(f"{name} has a zero vector at a vertex of the mesh")
    # Vertices no face uses may be zero; any unit vector keeps x / |x| finite there.
    return np.where(norm == 0, [0.0, 0.0, 1.0], p / np.where(norm == 0, 1, norm))


def given_map(vertices: np.ndarray, faces: np.ndarray, sphere) -> SphericalParametrization:
    """A spherical map the caller already has (e.g. FreeSurfer's ?h.sphere), checked.

    Args:
        vertices, faces: a checked mesh, faces wound outward (:func:`check_mesh`).
        sphere: ``(V, 3)`` one position per vertex (same order), on a sphere about the
            origin of any radius: each row is taken as a direction.

    Returns:
        :class:`SphericalParametrization` (energy NaN, iterations 0: nothing optimized).

    Raises:
        InputError: a bad shape, NaN/inf, or a zero row at a vertex of a face.
        ParametrizationError: faces folded over (counted; all of them: the map reverses
            orientation), or spherical triangles that do not tile the sphere once.
    """
    start = time.perf_counter()
    p = _unit_rows(sphere, vertices, faces, "sphere")
    flipped = int(np.sum(_triple(p, faces) <= 0))
    if flipped == len(faces):
        raise ParametrizationError(
            "the given sphere map reverses orientation (every face is turned over): it is "
            "a mirror image of an orientation-preserving map",
            flipped,
        )
    if flipped:
        raise ParametrizationError(
            f"the given sphere map folds {flipped} of {len(faces)} faces over", flipped
        )
    cover = float(spherical_triangle_areas(p, faces).sum()) / (4 * np.pi)
    if abs(cover - 1) > 1e-8:
        raise ParametrizationError(
            f"the given sphere map's triangles cover the sphere {cover:.6g} times, not once",
            0,
        )
    return _record(vertices, faces, p, float("nan"), 0, True, start)


def sample_mesh(par: SphericalParametrization, directions: np.ndarray) -> np.ndarray:
    """Points of the mesh at the given directions of the sphere map.

    Args:
        par: a spherical parametrization.
        directions: ``(R, 3)`` unit vectors.

    Returns:
        ``(R, 3)`` float64: for u in the cone of the map's face (a, b, c), u = sum lam_k
        sphere[k] with lam >= 0, the point sum lam_k vertices[k] / sum lam_k.
    """
    sphere, faces, vertices = par.sphere, par.faces, par.vertices
    centroid = sphere[faces].sum(axis=1)
    centroid /= np.linalg.norm(centroid, axis=1, keepdims=True)
    tree = scipy.spatial.cKDTree(centroid)
    tri = np.transpose(sphere[faces], (0, 2, 1))  # columns are the corners
    out = np.full((len(directions), 3), np.nan)
    todo = np.arange(len(directions))

    def locate(rows: np.ndarray, cand: np.ndarray) -> np.ndarray:
        """Fill ``out[rows]`` where a candidate face ``cand`` (R, k) holds the direction;
        return the mask of rows found."""
        u = directions[rows]
        lam = np.linalg.solve(tri[cand], np.broadcast_to(u[:, None, :, None], (*cand.shape, 3, 1)))
        lam = lam[..., 0]
        # A small negative tolerance: directions on an edge or a vertex belong to both.
        inside = np.all(lam >= -1e-12 * np.abs(lam).sum(-1, keepdims=True), axis=-1)
        inside &= lam.sum(-1) > 0
        found = inside.any(axis=1)
        first = np.argmax(inside, axis=1)[found]
        weights = np.clip(lam[found, first], 0, None)
        weights /= weights.sum(axis=1, keepdims=True)
        face = cand[found, first]
        out[rows[found]] = np.einsum("rk,rkd->rd", weights, vertices[faces[face]])
        return found

    # Nearest face centroids first; long thin spherical triangles can hold a direction
    # whose nearest centroids are elsewhere, so widen, then try every face (one direction
    # at a time, to bound the memory).
    for k in (8, 32, 128):
        k = min(k, len(faces))
        if todo.size == 0:
            break
        _, cand = tree.query(directions[todo], k=k)
        todo = todo[~locate(todo, cand.reshape(len(todo), k))]
    every = np.arange(len(faces))[None, :]
    missing = [r for r in todo if not locate(np.array([r]), every)[0]]
    if missing:  # cannot happen for a map that tiles the sphere
        raise ParametrizationError(
            f"{len(missing)} grid direction(s) lie in no face of the sphere map (first: "
            f"{directions[missing[0]].tolist()}); the map does not cover the sphere",
            0,
        )
    return out
