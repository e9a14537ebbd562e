"""Compiling a batch job's shape solves ahead of it : ``warmup``.

A shape solve's programs depend on the static options, the working grids, the inputs'
grid, the dtype and modulo, not on the surfaces' values or the metric's coefficients
(traced). Solving any pair with the same settings therefore compiles (and, with the
persistent cache on, stores) every program a job's pairs will run.
"""

from __future__ import annotations

import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._checks import check_choice
from .._errors import InputError
from .._geometry.grid import sphere_points_np
from .._geometry.metric import SplitMetric
from .._options import ShapeOptions, options_with
from .._runtime.cache import CompileCounter
from .records import MODULI
from .shape import solve_shapes

# Every level runs: two levels' distances never agree within this.
_EVERY_LEVEL = 1e-300
_DTYPES = ("float64", "float32")


class WarmupReport(NamedTuple):
    """What :func:`warmup` compiled.

    Attributes:
        grids: the working grids whose programs were compiled, coarse to fine.
        input_grid: the inputs' grid ``(m, n)`` the programs read from.
        moduli: the quotients compiled (``"diff"``, ``"rigid"``).
        dtype: ``"float64"`` or ``"float32"``.
        programs: XLA programs compiled meanwhile; those JAX found in this process or
            loaded from the persistent cache are not counted (0: nothing was missing).
        seconds: wall time.
        cache_dir: JAX's persistent cache directory, or None (the programs are then kept
            by this process only).
    """

    grids: tuple[tuple[int, int], ...]
    input_grid: tuple[int, int]
    moduli: tuple[str, ...]
    dtype: str
    programs: int
    seconds: float
    cache_dir: str | None


def _pair(m: int, n: int, dtype) -> tuple[np.ndarray, np.ndarray]:
    """A sphere and an ellipsoid turned by a fixed rotation: a pair whose registration is
    not the identity (so no phase is skipped), solved quickly at any grid."""
    e1 = sphere_points_np(m, n)
    c, s = np.cos(0.4), np.sin(0.4)
    turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    stretch = np.diag([1.0, 0.85, 1.2]) @ turn
    return e1.astype(dtype), np.einsum("ij,jmn->imn", stretch, e1).astype(dtype)


def warmup(
    input_grid: tuple[int, int] = (50, 99),
    *,
    modulo: str | tuple[str, ...] = "diff",
    options: ShapeOptions | None = None,
    dtype="float64",
    **changes,
) -> WarmupReport:
    """Compile the shape solves of a batch job before it runs.

    Solves a built-in pair (a sphere and a turned ellipsoid) on ``input_grid`` with the
    job's options: with ``options.rtol`` (the default) on every working grid of
    ``options.levels``, whatever the distances, so that each level's programs are
    compiled; with one working grid, on that grid. With the persistent compilation cache
    on (:func:`enable_compilation_cache`; the ``elastic-jax`` commands' default), the
    programs are stored there and every later process loads them instead of compiling:
    ``elastic-jax warmup`` does this for the CLI's cache. Without it, only this process
    keeps them.

    The programs are those of :func:`shape_geodesic` (and so of :func:`distance_matrix`'s
    and the resolved :func:`karcher_mean`'s first step, which solve pairs alike) for the
    same options, dtype, modulo and inputs' grid; the metric's coefficients are traced
    and do not matter. Not covered: a level that searches its own start because the
    registration carried from below folds there, the second solve from the pair as given
    (``RESULTS.not_registered``), and the batched programs of ``strategy="map"`` and
    ``"vmap"`` (their batch size is the job's).

    Args:
        input_grid: ``(m, n)``, the grid of the job's surfaces (odd n).
        modulo: ``"diff"``, ``"rigid"``, or a tuple of them.
        options: the job's :class:`ShapeOptions` (default ``ShapeOptions()``). Its
            ``rtol`` only says whether the job solves by levels: the warmup solves every
            level whatever the distances.
        dtype: ``"float64"`` (needs ``jax_enable_x64``) or ``"float32"``.
        **changes: fields of ShapeOptions as keywords (``degree=5``): without
            ``options`` each sets that field of the default record; beside ``options``
            each must equal the record's field (an equal one is accepted, another is an
            InputError: change the record with ``options.replace(...)``).

    Returns:
        :class:`WarmupReport`.

    Raises:
        InputError: a bad grid, modulo, dtype or option, or float64 without
            ``jax_enable_x64``.
    """
    moduli = (modulo,) if isinstance(modulo, str) else tuple(modulo)
    if not moduli:
        raise InputError("modulo: give at least one of 'diff', 'rigid'")
    for name in moduli:
        check_choice("modulo", name, MODULI)
    resolved = options_with("warmup", options, changes)
    try:
        m, n = (int(k) for k in input_grid)
    except (TypeError, ValueError):
        raise InputError(f"input_grid must be (m, n); got {input_grid!r}") from None
    if m < 3 or n < 5 or n % 2 == 0:
        raise InputError(f"input_grid must be (m, n) with m >= 3 and odd n >= 5; got {(m, n)}")
    try:
        dtype = str(jnp.dtype(dtype))
    except TypeError:
        raise InputError(f"dtype must be one of {_DTYPES}; got {dtype!r}") from None
    check_choice("dtype", dtype, _DTYPES)
    if dtype == "float64" and not jax.config.jax_enable_x64:
        raise InputError(
            "dtype='float64' needs jax.config.update('jax_enable_x64', True) first "
            "(the CLI sets it for --dtype float64)"
        )
    grids = resolved.working_grids((m, n))
    if resolved.resolves:
        # Every level, with the rounds' stop the job's rtol gives its levels (a static
        # setting of their programs).
        resolved = resolved.replace(rtol=_EVERY_LEVEL, rounds_tol=resolved.level_rounds_tol)
    f1, f2 = _pair(m, n, dtype)
    metric = SplitMetric(1.0, 1.0, 0.1, 0.0)
    counter = CompileCounter()
    begin = time.perf_counter()
    with counter:
        for name in moduli:
            jax.block_until_ready(solve_shapes(f1, f2, metric, name, resolved))
    return WarmupReport(
        grids=tuple(grids),
        input_grid=(m, n),
        moduli=moduli,
        dtype=dtype,
        programs=counter.count,
        seconds=time.perf_counter() - begin,
        cache_dir=jax.config.jax_compilation_cache_dir,
    )
