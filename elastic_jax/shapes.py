"""Analytic test surfaces, evaluated at any point of the parameter sphere.

Each shape is a function ``F(x, **params)`` from unit vectors ``x (3, ...)`` to points
``(3, ...)`` of R^3 (component axis first, as in the package's ``(3, m, n)`` layout), smooth
on all of S^2. :func:`sample` evaluates one on the grid, optionally composed with a
rotation h of the parameter sphere: ``sample(F, m, n, rotation=R)`` is f o h with
h(x) = R x sampled exactly, so reparametrization tests need no interpolation.

Example:
    >>> from elastic_jax import shapes
    >>> f = shapes.sample(shapes.bumpy, 25, 49)
    >>> f.shape
    (3, 25, 49)
"""

from __future__ import annotations

from collections.abc import Callable

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._checks import check_int
from ._errors import InputError
from ._geometry.grid import sphere_points
from ._geometry.reparam import moebius as _moebius_map
from ._runtime.precision import full_precision

__all__ = [
    "sphere",
    "ellipsoid",
    "bumpy",
    "bent_cylinder",
    "sample",
    "random_rotation",
    "two_classes",
    "geodesic_sphere",
]


def sphere(x: Float[ArrayLike, "3 ..."], radius: float = 1.0) -> Float[Array, "3 ..."]:
    """The round sphere of the given radius about the origin: F(x) = radius x."""
    return radius * x


def ellipsoid(
    x: Float[ArrayLike, "3 ..."], axes: tuple[float, float, float] = (1.0, 0.75, 0.5)
) -> Float[Array, "3 ..."]:
    """The ellipsoid with semi-axes ``axes``: F(x) = diag(axes) x."""
    return jnp.stack([ax * xi for ax, xi in zip(axes, x, strict=True)])


# Bump directions, amplitudes and concentrations chosen with no common symmetry axis.
_BUMPS = (
    ((0.36, 0.48, 0.80), 0.35, 6.0),
    ((-0.70, 0.10, -0.20), 0.25, 4.0),
    ((0.15, -0.90, 0.30), 0.20, 8.0),
    ((-0.20, -0.35, -0.90), 0.15, 3.0),
)


def bumpy(x: Float[ArrayLike, "3 ..."], scale: float = 1.0) -> Float[Array, "3 ..."]:
    """A star-shaped surface with four unequal bumps and no symmetry: F(x) = r(x) diag(1, .9, .8) x.

    r(x) = scale (1 + sum_i A_i exp(kappa_i (<x, c_i> - 1))): von Mises bumps, smooth on S^2.
    """
    r = 1.0
    for c, amp, kappa in _BUMPS:
        c = np.asarray(c) / np.linalg.norm(c)
        r = r + amp * jnp.exp(kappa * (c[0] * x[0] + c[1] * x[1] + c[2] * x[2] - 1.0))
    return scale * r[None] * jnp.stack([x[0], 0.9 * x[1], 0.8 * x[2]])


def bent_cylinder(
    x: Float[ArrayLike, "3 ..."],
    half_length: float = 1.5,
    radius: float = 0.5,
    curvature: float = 0.4,
    sharpness: float = 6.0,
) -> Float[Array, "3 ..."]:
    """A cylinder with round caps, bent along a circular arc (the paper's Figure 1 kind).

    The unit sphere is first stretched along its axis, z -> z + half_length tanh(sharpness z),
    a diffeomorphism of R^3 that turns the equatorial band into a straight tube with
    hemispherical-looking caps; then scaled by ``radius`` across the axis and bent so that
    the axis becomes an arc of the given curvature in the x-z plane (curvature 0: straight).
    Needs curvature * radius < 1.
    """
    z = x[2] + half_length * jnp.tanh(sharpness * x[2])
    u, v = radius * x[0], radius * x[1]
    beta = curvature * z
    # sin(beta)/curvature and (1 - cos beta)/curvature written to stay exact at curvature 0.
    along = z * jnp.sinc(beta / np.pi)
    sideways = z * jnp.sin(0.5 * beta) * jnp.sinc(beta / (2.0 * np.pi))
    return jnp.stack([u * jnp.cos(beta) + sideways, v, along - u * jnp.sin(beta)])


@full_precision  # the rotation's product at float32's precision on GPUs
def sample(
    shape: Callable[..., Array],
    m: int,
    n: int,
    rotation: Float[ArrayLike, "3 3"] | None = None,
    dtype=None,
    moebius: Float[ArrayLike, " 3"] | None = None,
    **params,
) -> Float[Array, "3 m n"]:
    """Sample ``shape`` on the m x n grid, composed with h(x) = R phi_a(x) if given.

    Args:
        shape: one of this module's surfaces (or any F: S^2 -> R^3 with the same layout).
        m, n: grid size (:ref:`math §1 <math-1>`).
        rotation: optional ``(3, 3)`` rotation R; the result is F(R e1(phi_i, theta_j)).
        dtype: floating dtype of the result.
        moebius: optional ``(3,)`` a, ‖a‖ < 1: the Moebius map phi_a
            (:func:`elastic_jax.moebius`) is applied before the rotation, so that
            F(R phi_a(x)) is sampled exactly.
        **params: passed to ``shape``.

    Returns:
        ``(3, m, n)`` with exactly constant pole rows and an exact seam column.
    """
    x = sphere_points(m, n, dtype=dtype)
    if moebius is not None:
        x = _moebius_map(x, jnp.asarray(moebius, dtype=x.dtype))
    if rotation is not None:
        x = jnp.einsum("ij,jmn->imn", jnp.asarray(rotation, dtype=x.dtype), x)
    f = shape(x, **params)
    # Rotated grids reach the pole rows by different rounding in each column.
    f = f.at[:, 0, :].set(f[:, 0, :1]).at[:, -1, :].set(f[:, -1, :1])
    return f.at[:, :, -1].set(f[:, :, 0])


def random_rotation(seed: int) -> np.ndarray:
    """A rotation matrix drawn uniformly from SO(3) (QR of a Gaussian matrix), ``(3, 3)``."""
    rng = np.random.default_rng(seed)
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


# The families of two_classes: what separates the classes, and what varies in both.
FAMILIES = ("bending", "elongation", "length")


def two_classes(
    family: str, count: int, m: int, n: int, seed: int = 0
) -> tuple[Float[np.ndarray, "K 3 m n"], np.ndarray]:
    """Two classes of surfaces that one kind of deformation separates while another varies
    at random in both: a test of learning the metric from data (:func:`elastic_jax.fit_metric`).

    - ``"bending"``: bent cylinders (:func:`bent_cylinder`) of curvature 0.2 (class 0) or
      0.4 (class 1), each +-0.03; half-length uniform in [0.8, 2] and radius in [0.3, 0.7]
      (the nuisance is stretching: length and thickness). The split metric weighs bending
      with c; the default (1, 1, 0.1, 0) weighs the nuisance more.
    - ``"elongation"``: spheroids elongated at fixed volume, semi-axes
      (z^-1/2, z^-1/2, z) with z = 1 (class 0) or 1.15 (class 1), each times
      exp(+-0.03); every surface scaled by exp(u), u uniform in [-0.6, 0.6] (the nuisance
      is change of volume, the b term; the signal is mostly shear, the a term).
    - ``"length"``: bent cylinders of half-length 1.15 (class 0) or 1.45 (class 1), each
      +-0.03, radius 0.5, curvature uniform in [0, 1.1] (the signal is stretching, the
      nuisance bending: the default metric already weighs it this way).

    Every surface is sampled on one parametrization (no rotation): modulo="none" compares
    them as they correspond.

    Args:
        family: ``"bending"``, ``"elongation"`` or ``"length"``.
        count: surfaces, alternately class 0 and class 1.
        m, n: grid size; seed: the random draw.

    Returns:
        surfaces ``(count, 3, m, n)`` (numpy float64; computed in JAX's default float) and
        labels ``(count,)`` (0 or 1).
    """
    if family not in FAMILIES:
        raise InputError(f"family must be one of {FAMILIES}; got {family!r}")
    rng = np.random.default_rng(seed)
    labels = np.arange(count) % 2
    out = []
    x = np.asarray(sphere_points(m, n), np.float64)
    for label in labels:
        if family == "length":
            f = sample(
                bent_cylinder,
                m,
                n,
                half_length=(1.15, 1.45)[label] + rng.uniform(-0.03, 0.03),
                curvature=rng.uniform(0.0, 1.1),
                radius=0.5,
            )
        elif family == "bending":
            f = sample(
                bent_cylinder,
                m,
                n,
                curvature=(0.2, 0.4)[label] + rng.uniform(-0.03, 0.03),
                half_length=rng.uniform(0.8, 2.0),
                radius=rng.uniform(0.3, 0.7),
            )
        else:
            z = (1.0, 1.15)[label] * np.exp(rng.uniform(-0.03, 0.03))
            size = np.exp(rng.uniform(-0.6, 0.6))
            f = size * x * np.array([z**-0.5, z**-0.5, z])[:, None, None]
        out.append(np.asarray(f, np.float64))
    return np.stack(out), labels


def geodesic_sphere(frequency: int) -> tuple[np.ndarray, np.ndarray]:
    """The geodesic sphere of the given frequency: a triangle mesh of S^2 of any size whose
    triangles are all close to equilateral.

    Each face of the icosahedron is cut into frequency^2 triangles by the lines parallel
    to its edges, and the points are pushed onto the unit sphere (the class-I geodesic
    polyhedron {3,5+}_(nu,0)): 20 nu^2 faces, 10 nu^2 + 2 vertices. Evaluate a shape at
    its points for a mesh of that surface of any size, e.g.
    ``trimesh.Trimesh(np.asarray(shapes.bent_cylinder(points)).T, faces)``.

    Args:
        frequency: nu >= 1 (1 is the icosahedron).

    Returns:
        ``(points (3, V), faces (F, 3))``: unit vectors, component axis first as in the
        package's layout, and int64 faces wound counterclockwise seen from outside.
    """
    import scipy.spatial
    import trimesh

    nu = check_int("frequency", frequency, 1)
    ico = trimesh.creation.icosahedron()
    corners = np.asarray(ico.vertices)[np.asarray(ico.faces)]  # (20, 3, 3)
    i, j = (a.ravel() for a in np.meshgrid(np.arange(nu + 1), np.arange(nu + 1), indexing="ij"))
    keep = i + j <= nu
    i, j = i[keep], j[keep]
    local = np.full((nu + 2, nu + 2), -1)
    local[i, j] = np.arange(i.size)
    up = i + j <= nu - 1
    down = i + j <= nu - 2
    triangles = np.concatenate(
        [
            np.stack([local[i, j], local[i + 1, j], local[i, j + 1]], axis=1)[up],
            np.stack([local[i + 1, j], local[i + 1, j + 1], local[i, j + 1]], axis=1)[down],
        ]
    )
    a, b, c = corners[:, 0, None], corners[:, 1, None], corners[:, 2, None]
    points = a + (b - a) * (i / nu)[:, None] + (c - a) * (j / nu)[:, None]  # (20, K, 3)
    points = (points / np.linalg.norm(points, axis=-1, keepdims=True)).reshape(-1, 3)
    faces = (triangles[None] + i.size * np.arange(20)[:, None, None]).reshape(-1, 3)
    # Points on an edge or a corner of the icosahedron were made by each of its faces
    # (equal up to rounding); every copy takes the lowest index among them.
    pairs = scipy.spatial.cKDTree(points).query_pairs(1e-9 / nu, output_type="ndarray")
    first = np.arange(len(points))
    np.minimum.at(first, pairs.max(axis=1), pairs.min(axis=1))
    kept, index = np.unique(first, return_inverse=True)
    return points[kept].T.copy(), index[faces].astype(np.int64)
