"""Input checks at the public boundary (outside jit), with messages that say what and where."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ._differential import area_element, interior_frame

_area_element = jax.jit(lambda f: area_element(*interior_frame(f)))


def _where(batch_shape: tuple[int, ...], flat_index: int) -> str:
    if not batch_shape:
        return ""
    index = tuple(int(i) for i in np.unravel_index(flat_index, batch_shape))
    return f" of item {index[0] if len(index) == 1 else index}"


def check_grid_shape(shape: tuple[int, ...], name: str) -> tuple[int, int]:
    """Check that ``shape`` is ``(..., 3, m, n)`` with odd n and m, n >= 5; return (m, n)."""
    if len(shape) < 3 or shape[-3] != 3:
        raise ValueError(f"{name} must have shape (..., 3, m, n); got shape {shape}")
    m, n = shape[-2:]
    if m < 5 or n < 5:
        raise ValueError(f"{name} needs at least 5 rows and 5 columns; got m={m}, n={n}")
    if n % 2 == 0:
        raise ValueError(
            f"{name} has an even number of columns n={n}; n must be odd so that "
            "theta + pi is again a grid column (MATH.md 1)"
        )
    return m, n


def as_surface(f, name: str, *, check_immersion: bool = True) -> jax.Array:
    """Convert to a floating JAX array and check it is a well-formed surface on the grid.

    Shape checks always run. Value checks (finite; constant pole rows; seam column equal
    to column 0, to sqrt(eps) times the surface's extent; nonzero area element at every
    interior grid point) run only on concrete arrays, so that the public functions stay
    usable inside ``jax.jit`` and ``jax.vmap``.

    Raises:
        ValueError: naming the problem, the argument and the grid point.
    """
    if not isinstance(f, jax.Array):
        f = jnp.asarray(f)
    if not jnp.issubdtype(f.dtype, jnp.floating):
        f = f.astype(jnp.result_type(float))
    m, n = check_grid_shape(f.shape, name)
    if isinstance(f, jax.core.Tracer):
        return f

    x = np.asarray(f)
    batch = x.shape[:-3]
    flat = x.reshape((-1, 3, m, n))
    bad = ~np.isfinite(flat)
    if bad.any():
        k, c, i, j = np.argwhere(bad)[0]
        raise ValueError(
            f"{name} contains {int(bad.sum())} non-finite value(s) (NaN or inf); the first "
            f"is coordinate {c} at row i={i}, column j={j}{_where(batch, k)}"
        )
    eps = np.finfo(x.dtype).eps
    extent = np.max(np.ptp(flat.reshape(flat.shape[0], 3, -1), axis=-1), axis=-1)
    for k in range(flat.shape[0]):
        if extent[k] == 0:
            raise ValueError(f"{name} is a single point{_where(batch, k)}: not an immersion")
    tol = np.sqrt(eps) * extent
    for row, pole in ((0, "north"), (m - 1, "south")):
        dev = np.max(np.abs(flat[:, :, row, :] - flat[:, :, row, :1]), axis=(1, 2))
        k = int(np.argmax(dev / tol))
        if dev[k] > tol[k]:
            j = int(np.argmax(np.max(np.abs(flat[k, :, row, :] - flat[k, :, row, :1]), axis=0)))
            raise ValueError(
                f"{name}: the {pole} pole row (i={row}) is not constant{_where(batch, k)}: "
                f"column j={j} differs from column 0 by {dev[k]:.3g}, more than {tol[k]:.3g} "
                "(sqrt(eps) times the surface's extent)"
            )
    dev = np.max(np.abs(flat[..., -1] - flat[..., 0]), axis=(1, 2))
    k = int(np.argmax(dev / tol))
    if dev[k] > tol[k]:
        i = int(np.argmax(np.max(np.abs(flat[k, :, :, -1] - flat[k, :, :, 0]), axis=0)))
        raise ValueError(
            f"{name}: the seam column j={n - 1} does not repeat column 0{_where(batch, k)}: "
            f"they differ by {dev[k]:.3g} at row i={i}, more than {tol[k]:.3g}"
        )
    if check_immersion:
        # Evaluate now even when a concrete array is closed over inside a caller's jit.
        with jax.ensure_compile_time_eval():
            area = np.asarray(_area_element(jnp.asarray(flat)))
        # Zero to working precision: the cross product of columns of size ~extent has
        # rounding error ~eps * extent^2; thin real features stay far above this.
        degenerate = area <= 100 * eps * extent[:, None, None] ** 2
        if degenerate.any():
            k, i, j = np.argwhere(degenerate)[0]
            phi, theta = (i + 1) * np.pi / (m - 1), j * 2 * np.pi / (n - 1)
            raise ValueError(
                f"{name} is not an immersion{_where(batch, k)}: the area element vanishes at "
                f"{int(degenerate.sum())} interior grid point(s), the first at row i={i + 1}, "
                f"column j={j} (phi={phi:.4f}, theta={theta:.4f})"
            )
    return f


def validate_surface(f, name: str = "f") -> jax.Array:
    """Check that ``f`` is a well-formed surface ``(..., 3, m, n)`` on the grid (MATH.md 1).

    Raises ``ValueError`` naming the problem and the grid point for: a wrong shape, an even
    n, fewer than 5 rows or columns, NaN/inf, pole rows that are not constant or a seam
    column that does not repeat column 0 (beyond sqrt(eps) times the surface's extent),
    and a vanishing area element at an interior grid point (not an immersion). Every
    public function runs these checks on concrete input; call this to check data early.

    Args:
        f: array-like ``(..., 3, m, n)``.
        name: the name used in error messages.

    Returns:
        ``f`` as a floating JAX array.
    """
    return as_surface(f, name)
