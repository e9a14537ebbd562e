"""The one validation layer for options and surface arrays, shared by the library and the CLI.

This module imports only the leaf ``_errors``, so every module can import it (the
immersion check, which needs the differential, lives in ``_validation``). Every check
raises :class:`InputError`, a ValueError that names the option or the argument; the
command line turns it into exit code 2 and one line on stderr.
"""

from __future__ import annotations

import math
import numbers

import jax
import jax.numpy as jnp
import numpy as np

from ._errors import InputError


def check_choice(name: str, value, allowed: tuple[str, ...]) -> str:
    """``value`` if it is one of ``allowed``; else an InputError that names both."""
    if not isinstance(value, str) or value not in allowed:
        raise InputError(f"{name} must be one of {allowed}; got {value!r}")
    return value


def check_int(name: str, value, minimum: int) -> int:
    """A Python int >= minimum (numpy integers accepted; bools, floats and strings refused)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise InputError(f"{name} must be an integer >= {minimum}; got {value!r}")
    if value < minimum:
        raise InputError(f"{name} must be an integer >= {minimum}; got {value!r}")
    return int(value)


def check_positive(name: str, value) -> float:
    """A finite float > 0 (ints accepted; NaN, inf, zero, negatives and non-numbers refused)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise InputError(f"{name} must be a positive finite number; got {value!r}")
    value = float(value)
    if not (math.isfinite(value) and value > 0):
        raise InputError(f"{name} must be a positive finite number; got {value!r}")
    return value


def check_bool(name: str, value) -> bool:
    """``value`` if it is True or False (numpy bools accepted)."""
    if not isinstance(value, bool | np.bool_):
        raise InputError(f"{name} must be True or False; got {value!r}")
    return bool(value)


def is_concrete(*values) -> bool:
    """Whether no leaf of ``values`` is a tracer (so it can be read back as numbers)."""
    return not any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(values))


def check_progress(progress):
    """``progress``: None or a callable (the solves call it with a dict of numbers)."""
    if progress is not None and not callable(progress):
        raise InputError(f"progress must be a callable taking a dict; got {progress!r}")
    return progress


def check_grid_shape(shape: tuple[int, ...], name: str) -> tuple[int, int]:
    """Check that ``shape`` is ``(..., 3, m, n)`` with odd n and m, n >= 5; return (m, n)."""
    if len(shape) < 3 or shape[-3] != 3:
        raise InputError(f"{name} must have shape (..., 3, m, n); got shape {shape}")
    m, n = shape[-2:]
    if m < 5 or n < 5:
        raise InputError(f"{name} needs at least 5 rows and 5 columns; got m={m}, n={n}")
    if n % 2 == 0:
        raise InputError(
            f"{name} has an even number of columns n={n}; n must be odd so that "
            "theta + pi is again a grid column (documentation: Mathematics, section 1)"
        )
    return m, n


def real_array(x, name: str) -> jax.Array:
    """``x`` as a JAX array of float32 or float64 (integers become the default float).

    Complex input is refused (its imaginary part would be dropped), and so is float16
    and bfloat16: the metric squares first derivatives twice (det g ~ |df|^4), which
    leaves their 3 significant digits with nothing.
    """
    if not isinstance(x, jax.Array):
        dtype = np.asarray(x).dtype if not hasattr(x, "dtype") else x.dtype
        if np.issubdtype(dtype, np.complexfloating):
            raise InputError(f"{name} is complex ({dtype}); surfaces are real arrays")
        x = jnp.asarray(x)
    if jnp.issubdtype(x.dtype, jnp.complexfloating):
        raise InputError(f"{name} is complex ({x.dtype}); surfaces are real arrays")
    if jnp.issubdtype(x.dtype, jnp.floating):
        if jnp.finfo(x.dtype).bits < 32:
            raise InputError(
                f"{name} has dtype {x.dtype}, which has too few digits for the metric; "
                "use float32 or float64"
            )
        return x
    if x.dtype == jnp.bool_ or not jnp.issubdtype(x.dtype, jnp.integer):
        raise InputError(f"{name} must hold real numbers; got dtype {x.dtype}")
    return x.astype(jnp.result_type(float))


def check_finite(x, name: str) -> None:
    """InputError naming ``name`` and the first position if a concrete ``x`` holds NaN/inf."""
    if not is_concrete(x):
        return
    bad = ~np.isfinite(np.asarray(x))
    if bad.any():
        where = tuple(int(i) for i in np.argwhere(bad)[0])
        raise InputError(
            f"{name} contains {int(bad.sum())} non-finite value(s) (NaN or inf), the first "
            f"at index {where}"
        )


def item_suffix(batch_shape: tuple[int, ...], flat_index: int) -> str:
    if not batch_shape:
        return ""
    index = tuple(int(i) for i in np.unravel_index(flat_index, batch_shape))
    return f" of item {index[0] if len(index) == 1 else index}"


def grid_array(f, name: str) -> jax.Array:
    """A real ``(..., 3, m, n)`` JAX array whose values fit the grid (math §1).

    Shape checks always run. Value checks (finite; constant pole rows; seam column equal
    to column 0, to sqrt(eps) times the surface's extent) run only on concrete arrays, so
    that the public functions stay usable inside ``jax.jit`` and ``jax.vmap``. The
    immersion check is :func:`elastic_jax._geometry.validation.as_surface`'s.
    """
    f = real_array(f, name)
    m, n = check_grid_shape(f.shape, name)
    if not is_concrete(f):
        return f
    x = np.asarray(f)
    batch = x.shape[:-3]
    flat = x.reshape((-1, 3, m, n))
    bad = ~np.isfinite(flat)
    if bad.any():
        k, c, i, j = np.argwhere(bad)[0]
        raise InputError(
            f"{name} contains {int(bad.sum())} non-finite value(s) (NaN or inf); the first "
            f"is coordinate {c} at row i={i}, column j={j}{item_suffix(batch, k)}"
        )
    eps = np.finfo(x.dtype).eps
    extent = extents(flat)
    for k in range(flat.shape[0]):
        if extent[k] == 0:
            raise InputError(f"{name} is a single point{item_suffix(batch, k)}: not an immersion")
    tol = np.sqrt(eps) * extent
    for row, pole in ((0, "north"), (m - 1, "south")):
        dev = np.max(np.abs(flat[:, :, row, :] - flat[:, :, row, :1]), axis=(1, 2))
        k = int(np.argmax(dev / tol))
        if dev[k] > tol[k]:
            j = int(np.argmax(np.max(np.abs(flat[k, :, row, :] - flat[k, :, row, :1]), axis=0)))
            raise InputError(
                f"{name}: the {pole} pole row (i={row}) is not constant{item_suffix(batch, k)}: "
                f"column j={j} differs from column 0 by {dev[k]:.3g}, more than {tol[k]:.3g} "
                "(sqrt(eps) times the surface's extent)"
            )
    dev = np.max(np.abs(flat[..., -1] - flat[..., 0]), axis=(1, 2))
    k = int(np.argmax(dev / tol))
    if dev[k] > tol[k]:
        i = int(np.argmax(np.max(np.abs(flat[k, :, :, -1] - flat[k, :, :, 0]), axis=0)))
        raise InputError(
            f"{name}: the seam column j={n - 1} does not repeat column 0{item_suffix(batch, k)}: "
            f"they differ by {dev[k]:.3g} at row i={i}, more than {tol[k]:.3g}"
        )
    return f


def extents(flat: np.ndarray) -> np.ndarray:
    """``(K,)`` the largest coordinate range of each surface of ``flat (K, 3, m, n)``."""
    return np.max(np.ptp(flat.reshape(flat.shape[0], 3, -1), axis=-1), axis=-1)
