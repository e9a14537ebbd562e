"""An opt-in persistent compilation cache (the library never changes JAX's configuration
by itself: importing it, or calling a solver, leaves every setting as it was)."""

from __future__ import annotations

import os
import pathlib

import jax

from ._checks import check_positive


def _enable_here(path: str, min_compile_time_s: float) -> None:
    from jax.experimental.compilation_cache import compilation_cache

    if jax.config.jax_compilation_cache_dir != path:
        jax.config.update("jax_compilation_cache_dir", path)
        # JAX opens the cache directory once, at the first compilation that uses it, and
        # keeps it: a new directory needs the cache started again.
        compilation_cache.reset_cache()
    jax.config.update("jax_persistent_cache_min_compile_time_secs", min_compile_time_s)


def enable_compilation_cache(
    path: str | os.PathLike,
    *,
    client=None,
    min_compile_time_s: float = 0.5,
) -> pathlib.Path:
    """Keep compiled solves on disk at ``path`` (JAX's persistent compilation cache), so
    that a new process loads them instead of compiling again.

    A shape solve compiles for 15-60 s on 2 CPU cores and loads from the cache in about
    a second. This sets two global JAX options of this process
    (``jax_compilation_cache_dir`` and ``jax_persistent_cache_min_compile_time_secs``);
    it is the one place where the library does, and only when called. Programs compiled
    before the call are not stored; later ones are.

    Args:
        path: a directory (created). With ``client``, a path every worker can reach
            (a shared file system on a cluster).
        client: a ``dask.distributed.Client`` (or None): the cache is also turned on in
            each of its workers, present and future (a worker plugin), so that each
            worker machine compiles a job's solves once between them.
        min_compile_time_s: programs that compile faster are not stored.

    Returns:
        The directory, absolute.
    """
    path = pathlib.Path(path).expanduser().resolve()
    min_compile_time_s = float(min_compile_time_s)
    if min_compile_time_s != 0.0:
        check_positive("min_compile_time_s", min_compile_time_s)
    path.mkdir(parents=True, exist_ok=True)
    _enable_here(str(path), min_compile_time_s)
    if client is not None:
        from ._distributed import CompilationCache, connect

        client, _ = connect(client)
        client.register_plugin(
            CompilationCache(str(path), min_compile_time_s), name="elastic-jax-cache"
        )
    return path
