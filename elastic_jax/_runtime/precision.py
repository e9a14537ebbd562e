"""float32 matrix products at float32's precision on every device.

JAX computes a float32 ``dot`` (matmul, einsum, convolution) with reduced-precision inputs
on recent GPUs (TensorFloat-32: a 10-bit mantissa, relative errors ~1e-3) unless told
otherwise. Basis expansions, rotations and spline reads here are such products, and a
shape solve with them is another problem: on an H200, float32 cat1 -> cat2 gave levels
1.337, 1.902, 2.309 with them against 1.518, 1.925, 2.102 at full precision (float64:
1.466-1.502, 1.883-1.891, 2.160-2.170). The public functions (and the CLI, and Dask
tasks, under their caller's setting) therefore trace under
``jax.default_matmul_precision("highest")`` (a context, not JAX's global config), unless
the caller has chosen a precision, which is kept; the compiled-program caches key on it.
On CPU and in float64 nothing changes.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable, Iterator

import jax

FULL = "highest"


def chosen() -> str | None:
    """The matmul precision in force here (None: JAX's default, TF32 on recent GPUs)."""
    return jax.config.jax_default_matmul_precision


@contextlib.contextmanager
def full_products() -> Iterator[None]:
    """Trace (and run) the block with float32 products at full precision, unless a
    precision is already in force, which is kept."""
    if chosen() is not None:
        yield
        return
    with jax.default_matmul_precision(FULL):
        yield


def full_precision(fn: Callable) -> Callable:
    """``fn`` called under :func:`full_products` (the public functions' wrapper)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with full_products():
            return fn(*args, **kwargs)

    return wrapper


def trace_public_at_full_precision(namespace: dict, names) -> None:
    """Replace each function among ``names`` in a module's ``namespace`` by its
    :func:`full_precision` wrapper (classes and constants are left as they are)."""
    for name in names:
        obj = namespace[name]
        if callable(obj) and not isinstance(obj, type):
            namespace[name] = full_precision(obj)
