"""The immersion check at the public boundary (outside jit), on top of ``_checks``."""

from __future__ import annotations

import jax
import numpy as np
from jaxtyping import Array

from .._checks import check_grid_shape, extents, grid_array, is_concrete, item_suffix
from .._errors import InputError
from .._options import ShapeOptions
from .differential import area_element, interior_frame
from .harmonics import degree_within

__all__ = [
    "as_surface",
    "check_grid_options",
    "check_grid_shape",
    "check_pair",
    "validate_surface",
    "well_formed",
]


def as_surface(f, name: str, *, check_immersion: bool = True) -> jax.Array:
    """Convert to a real JAX array and check it is a well-formed surface on the grid.

    :func:`elastic_jax._checks.grid_array`'s checks (shape, dtype, finite values, pole
    rows, seam), the pole rows and seam made exact (:func:`well_formed`) and, on concrete
    arrays, a nonzero area element at every interior grid point. The area is measured on
    the surface moved to its bounding box's centre and divided by its extent, so the check
    means the same at every scale.

    Raises:
        InputError: naming the problem, the argument and the grid point.
    """
    f = well_formed(grid_array(f, name))
    if not check_immersion or not is_concrete(f):
        return f
    m, n = f.shape[-2:]
    x = np.asarray(f)
    batch = x.shape[:-3]
    flat = x.reshape((-1, 3, m, n))
    lower = flat.reshape(flat.shape[0], 3, -1).min(axis=-1)
    upper = flat.reshape(flat.shape[0], 3, -1).max(axis=-1)
    centre = (0.5 * lower + 0.5 * upper)[..., None, None]
    unit = ((flat - centre) / extents(flat)[:, None, None, None]).astype(x.dtype)
    # In numpy: no program to compile on a process's first call, and none traced when a
    # concrete array is closed over inside a caller's jit.
    area = area_element(*interior_frame(unit))
    # Zero to working precision: the cross product of columns of size ~1 has rounding
    # error ~eps; thin real features stay far above this.
    eps = np.finfo(x.dtype).eps
    degenerate = area <= 100 * eps
    if degenerate.any():
        k, i, j = np.argwhere(degenerate)[0]
        phi, theta = (i + 1) * np.pi / (m - 1), j * 2 * np.pi / (n - 1)
        raise InputError(
            f"{name} is not an immersion{item_suffix(batch, k)}: the area element vanishes at "
            f"{int(degenerate.sum())} interior grid point(s), the first at row i={i + 1}, "
            f"column j={j} (phi={phi:.4f}, theta={theta:.4f})"
        )
    return f


def well_formed(f: jax.Array) -> jax.Array:
    """``f (..., 3, m, n)`` with each pole row set to its column 0 and the seam column to
    column 0 (math §1's well-formed input, made exact).

    The checks allow these values to differ by up to sqrt(eps) times the surface's extent
    (rounding in a user's sampling), but a pole row that is not one point has a derivative
    along the row, which reads of the surface divide by sin(phi): with cat1's north pole
    row perturbed by 1e-10 (relative), 10 of the 60 start searches of cat1 -> cat2 at
    13 x 25 did not move from their icosahedral rotation (their L2 values off by up to
    3.2 against the exact row's). Exact inputs are returned bitwise unchanged.
    """
    f = f.at[..., 0, :].set(f[..., 0, :1])
    f = f.at[..., -1, :].set(f[..., -1, :1])
    return f.at[..., :, -1].set(f[..., :, 0])


def validate_surface(f, name: str = "f") -> jax.Array:
    """Check that ``f`` is a well-formed surface ``(..., 3, m, n)`` on the grid
    (:ref:`math §1 <math-1>`).

    Raises :class:`elastic_jax.InputError` (a ValueError) naming the problem and the grid
    point for: a wrong shape, an even n, fewer than 5 rows or columns, complex or float16
    values, NaN/inf, pole rows that are not constant or a seam column that does not
    repeat column 0 (beyond sqrt(eps) times the surface's extent), and a vanishing area
    element at an interior grid point (not an immersion; judged relative to the
    surface's extent, so at any scale). Every public function runs these checks on
    concrete input; call this to check data early.

    Args:
        f: array-like ``(..., 3, m, n)``.
        name: the name used in error messages.

    Returns:
        ``f`` as a floating JAX array, its pole rows and seam column made exact (each pole
        row set to its column 0, column n - 1 to column 0; within the tolerance above).

    Example:
        >>> import numpy as np
        >>> from elastic_jax import shapes, validate_surface
        >>> f = np.array(shapes.sample(shapes.sphere, 13, 25))
        >>> f[0, 5, 7] = np.nan
        >>> validate_surface(f)  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        elastic_jax.InputError: f contains 1 non-finite value(s) (NaN or inf); ...
    """
    return as_surface(f, name)


def check_pair(f1, f2, same_grid: bool = True) -> tuple[Array, Array]:
    """Two single surfaces with one dtype, on one grid unless ``same_grid`` is False
    (shape_geodesic reads each through its interpolant, math §10)."""
    f1 = as_surface(f1, "f1")
    f2 = as_surface(f2, "f2")
    for name, f in (("f1", f1), ("f2", f2)):
        if f.ndim != 3:
            raise InputError(
                f"{name} must be one surface (3, m, n); got {f.shape}. Batch with jax.vmap."
            )
    if not same_grid:
        if f1.dtype != f2.dtype:
            raise InputError(f"f1 and f2 must share one dtype; got {f1.dtype} and {f2.dtype}")
        return f1, f2
    if f1.shape != f2.shape or f1.dtype != f2.dtype:
        raise InputError(
            "f1 and f2 must share grid and dtype (the same grid, the same dtype); got "
            f"{f1.shape} {f1.dtype} and {f2.shape} {f2.dtype}"
        )
    return f1, f2


def check_grid_options(options: ShapeOptions, m: int, n: int) -> None:
    """The grid-dependent limits of ``options`` on an m x n grid: ``degree`` and
    ``vf_degree`` each at most :func:`~elastic_jax._geometry.harmonics.max_degree` (m, n).

    Raises:
        InputError: naming the option, its value and the grid's limit.
    """
    # The record made both ints >= 1 already; the grid sets their ceiling.
    degree_within(options.degree, m, n)
    degree_within(options.vf_degree, m, n, "vf_degree")


def check_levels(options: ShapeOptions) -> None:
    """:func:`check_grid_options` on every level of ``options.levels``, each with that
    level's own options (``options.on_level``: its Diff step degree).

    Raises:
        InputError: naming the level's grid and the option over its limit.
    """
    for m, n in options.levels:
        try:
            check_grid_options(options.on_level((m, n)), m, n)
        except InputError as error:
            raise InputError(f"levels: the {m} x {n} level: {error}") from None
