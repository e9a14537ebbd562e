"""An opt-in persistent compilation cache (the library never changes JAX's configuration
by itself: importing it, or calling a solver, leaves every setting as it was), and the
exported (ahead-of-time traced) shape solve kept beside it.

A warm process (compiled programs on disk) still traces and lowers the shape solve
before JAX can look its executables up. ``jax.export`` serializes the lowered programs
(one per phase of the solve) once; a later process deserializes them. On CPU the
compiled executables are kept beside them as well, so that a later process on the same
kind of machine loads them directly, without lowering and hashing the programs first.
Measured at the paper's low row (12 x 25, degree 5 / 5, N 5, 2 cores, cats), from
process start to the result: 1.9-2.0 s with the stored executables, 2.1-2.3 s with the
exported programs alone, 4.5-4.9 s with neither. The rest is imports (0.6 s), loading
the executables (XLA rebuilds each program's HLO, so it grows with the programs; JAX's
asynchronous dispatch loads a phase while the one before runs) and running them. The
stored programs are the ones the jitted path compiles, so the results are identical
(measured: largest difference 0.0 over every field of the result)."""

from __future__ import annotations

import functools
import hashlib
import numbers
import os
import pathlib
import threading
from concurrent.futures import ThreadPoolExecutor

import jax

from .._checks import check_bool, check_positive, is_concrete
from .atomic import atomic_path
from .precision import chosen

# XLA:CPU compiles fusions with its MLIR fusion emitters by default. On the shape solve
# (about 2000 fusions) they hold about 780 MB more while compiling (peak RSS 1445 MB
# against 664 MB, 25 x 49 at the defaults) and compile slower (XLA's part of the low
# row's first call 15.7 s against 12.6 s), for code no faster (bench_shape's synthetic
# pair, middle row: 3.0-3.2 s against 2.5 s). The same for one geodesic (the cats at
# 25 x 49, degree 7, N 13: compile 10.4 -> 7.9 s, the solve 3.0 s both). Given to the
# large solver programs only (solver_jit: the shape solve's phases, the batches, geodesic,
# shoot, parallel_transport, srnf_invert), never to JAX's configuration.
#
# XLA:CPU hands matrix products to YNNPACK by default; for the wide products of these
# programs (a few dozen coefficients times a basis over every grid point) its float64
# kernels were 1.6-3x slower than XLA's own (Eigen) and float32 3-10x ((24, 63) x (63,
# 36480): 4.6 against 1.6 ms in float64, 3.2 against 0.3 ms in float32), and in a
# registration objective its fusions kept XLA from fusing around them: the rounds' joint
# objective, cats, degree 7 / 8, N 10, value and gradient 2.15 -> 1.64 ms at 25 x 49 and
# 64.5 -> 51.4 ms at 97 x 193 (2 cores); the parametrized geodesics unchanged (6.1 against
# 5.9 ms per step, cats, 50 x 99).
_CPU_COMPILER_OPTIONS = {
    "xla_cpu_use_fusion_emitters": False,
    "xla_cpu_experimental_ynn_fusion_type": "",
}
# Added for programs that run for milliseconds once per solve (solver_jit(quick=True)):
# LLVM's optimizations cost more than they save there. The shape solve's last phase (the
# result's gradient norm and refinement check, 25 x 49, degree 7 / 8, N 10): compile
# 1.35 -> 0.69 s, run 0.085 -> 0.115 s. The search phases run 4-7 times slower so.
_QUICK_CPU_OPTIONS = {"xla_backend_optimization_level": 0}
# Where exported programs are kept: set by enable_compilation_cache, None when off.
_EXPORT_DIR: pathlib.Path | None = None
# Exported programs of this process (jitted), by key: a second call deserializes nothing.
_EXPORTED: dict[str, object] = {}
# The compiled phases of phase_chain, by phase, options and argument shapes: (a future
# of the compiled program, the shapes of its result).
_PHASE_PROGRAMS: dict[tuple, tuple] = {}
# Every functools.cache of the package (cached() registers them), for clear_caches().
_CACHED: list = []


def cached(function):
    """``functools.cache(function)``, emptied by :func:`clear_caches` with the others.

    Every cache of the package is one of these: bases and quadratures per grid, compiled
    variants per option set, exported programs; nothing else keeps state between calls.
    """
    wrapped = functools.cache(function)
    _CACHED.append(wrapped)
    return wrapped


def clear_caches() -> None:
    """Empty every cache the package keeps, and JAX's own (``jax.clear_caches``).

    What is cached is derived from arguments alone (a grid's harmonics, a compiled
    program), so clearing changes no result; it frees memory in a long session, and the
    next call rebuilds what it needs (compiling again). The persistent compilation cache
    on disk (:func:`enable_compilation_cache`) is kept: remove its directory to empty it.
    """
    for wrapped in _CACHED:
        wrapped.cache_clear()
    _EXPORTED.clear()
    _PHASE_PROGRAMS.clear()
    jax.clear_caches()


@cached
def _compiler_options(backend: str, quick: bool = False) -> tuple:
    """_CPU_COMPILER_OPTIONS (and _QUICK_CPU_OPTIONS when quick) on the CPU backend,
    less any this jaxlib does not know."""
    if backend != "cpu":
        return ()
    known = []
    options = {**_CPU_COMPILER_OPTIONS, **(_QUICK_CPU_OPTIONS if quick else {})}
    for key, value in options.items():
        try:  # a jaxlib that lacks the option rejects it at compile time
            jax.jit(lambda x: x + 1, compiler_options={key: value}).lower(1.0).compile()
        except Exception:
            continue
        known.append((key, value))
    return tuple(known)


def solver_jit(function, static_argnames=(), quick: bool = False):
    """``jax.jit(function, static_argnames=...)`` compiled with _CPU_COMPILER_OPTIONS
    (and _QUICK_CPU_OPTIONS when ``quick``: a program that runs briefly, once).

    The options are chosen at the call, for the default backend (one compiled variant
    per backend). A call inside the caller's own jit, vmap or grad is part of the
    caller's program, which JAX compiles with the caller's options (it accepts options
    only on the outermost jit): there this is the plain jitted function.
    """

    @cached
    def variant(options: tuple):
        return jax.jit(
            function, static_argnames=static_argnames, compiler_options=dict(options) or None
        )

    @functools.wraps(function)
    def call(*args, **kwargs):
        if not is_concrete(args, kwargs):
            return variant(())(*args, **kwargs)
        try:
            return current()(*args, **kwargs)
        except ValueError as error:
            # Concrete arguments, but traced all the same (constants under an outer jit).
            if "compiler_options" not in str(error):
                raise
            return variant(())(*args, **kwargs)

    def current():
        return variant(_compiler_options(jax.default_backend(), quick))

    call.jitted = current  # the jitted function itself (for .lower, .trace)
    call.quick = quick
    return call


def enable_here(path: str, min_compile_time_s: float, exported: bool = True) -> None:
    from jax.experimental.compilation_cache import compilation_cache

    global _EXPORT_DIR
    _EXPORT_DIR = pathlib.Path(path) / "exported" if exported else None
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
    min_compile_time_s: float = 0.0,
    exported: bool = True,
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
        min_compile_time_s: programs that compile faster are not stored. The default
            (0) stores every program: reading one back is faster than compiling even
            the small ones around a solve, which JAX's own default (1 s) would compile
            again in every process (the paper's low row, a warm first call before the
            solve's executables were stored: 2.2 s with 0, 3.2 s with 1 s).
        exported: also keep the traced and lowered shape solve (``jax.export``) under
            ``path/exported``, so that a new process skips tracing it, and on CPU its
            compiled executables, so that a new process skips lowering it too (a warm
            first call at the paper's low row: 1.9-2.0 s with them, 4.5-4.9 s without).
            Keyed on the solve's options, the arrays' shapes and dtypes, the versions of
            jax and jaxlib and a digest of this package's source (a changed package
            never runs an old program); the executables also on the compiler's options,
            ``XLA_FLAGS`` and the processor's model and instruction set. Like JAX's own
            cache, ``path`` then holds machine code that later processes run: give a
            directory that only you (or your job) can write.

    Returns:
        The directory, absolute.
    """
    path = pathlib.Path(path).expanduser().resolve()
    zero = (
        isinstance(min_compile_time_s, numbers.Real)
        and not isinstance(min_compile_time_s, bool)
        and min_compile_time_s == 0
    )
    # 0 stores every program; anything else must be a positive number of seconds.
    min_compile_time_s = 0.0 if zero else check_positive("min_compile_time_s", min_compile_time_s)
    exported = check_bool("exported", exported)
    path.mkdir(parents=True, exist_ok=True)
    enable_here(str(path), min_compile_time_s, exported)
    if client is not None:
        from .distributed import CompilationCache, connect

        client, _ = connect(client)
        client.register_plugin(
            CompilationCache(enable_here, str(path), min_compile_time_s, exported),
            name="elastic-jax-cache",
        )
    return path


@cached
def _source_digest() -> str:
    """A digest of the package's version and of every source file of the package, in
    every subpackage (an exported program is only as new as the code it was traced from:
    a phase of the shape solve calls into _registration, _geodesics and _geometry, so a
    digest of one folder would let a stored program outlive a change elsewhere)."""
    from importlib import metadata

    try:  # the installed distribution's version (the package's __init__.py is hashed too)
        version = metadata.version("elastic-jax")
    except metadata.PackageNotFoundError:
        version = ""
    root = pathlib.Path(__file__).resolve().parents[1]
    digest = hashlib.sha256(version.encode())
    for file in sorted(root.rglob("*.py")):
        digest.update(b"\0" + file.relative_to(root).as_posix().encode() + b"\0")
        digest.update(file.read_bytes())
    return digest.hexdigest()


def _avals(leaves) -> tuple:
    """(shape, dtype, weak type) of each leaf: arrays, Python numbers (weakly typed
    scalars: a different program from arrays) or ShapeDtypeStructs."""
    return tuple(
        (
            tuple(getattr(x, "shape", ())),
            str(getattr(x, "dtype", None) or jax.numpy.result_type(x)),
            bool(getattr(x, "weak_type", isinstance(x, int | float))),
        )
        for x in leaves
    )


def _key(name: str, static: dict, treedef, leaves) -> str:
    import jaxlib

    parts = [
        name,
        repr(sorted(static.items())),
        str(treedef),
        repr(_avals(leaves)),
        jax.__version__,
        jaxlib.__version__,
        str(jax.config.jax_enable_x64),
        str(chosen()),  # the matmul precision the program was traced under
        jax.default_backend(),
        _source_digest(),
    ]
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()[:40]


def exported_call(name: str, function, jitted, args: tuple, static: dict, skeleton):
    """``jitted(*args, **static)``, through an exported program when the cache is on.

    ``jitted`` is ``solver_jit(function)`` with ``static``'s names static; the exported
    program is compiled with the same options (``quick`` included). Off (no
    :func:`enable_compilation_cache`), or when any argument is being traced (inside jit,
    vmap or grad), this is the jitted call itself. Otherwise the program is exported once
    (traced and lowered: the work a jit call does before compiling), written to the cache
    directory atomically, and later processes deserialize it. On CPU its compiled
    executable is written beside it (:func:`_compiled`): a later process on the same
    kind of machine loads that and skips lowering the program as well. A directory that
    cannot be written only loses the file: the program still runs. ``skeleton`` is a
    pytree with the structure of the result (any leaves): it rebuilds the result from the
    program's flat outputs without tracing anything.
    """
    leaves, treedef = jax.tree_util.tree_flatten(args)
    if _EXPORT_DIR is None or not is_concrete(leaves):
        return jitted(*args, **static)
    key = _key(name, static, treedef, leaves)
    out_tree = jax.tree_util.tree_structure(skeleton)
    call = _EXPORTED.get(key)
    if call is None:
        call = _EXPORTED[key] = _compiled(
            name, key, function, jitted.quick, static, treedef, leaves, out_tree.num_leaves
        )
    return jax.tree_util.tree_unflatten(out_tree, call(*leaves))


def phase_chain(phases, args: tuple, carried: tuple, static: dict, after=None):
    """Run ``phases`` in turn, each ``(name, function, jitted, skeleton)`` called as
    ``jitted(*args, *carried, **static)`` with ``carried`` the previous phase's result
    (given for the first); the last phase's result. ``after(name, result)`` is called
    after each phase on concrete arguments (a progress report; never inside a trace).

    Inside a caller's trace, the phases are part of its program. With the exported
    programs on, each phase goes through :func:`exported_call`. Otherwise the phases'
    programs come from :func:`compile_phases` and are called directly; they are the
    jitted functions' own (same program, same compiler options): the results are
    identical.
    """
    leaves = jax.tree_util.tree_leaves((args, carried))
    if _EXPORT_DIR is not None and is_concrete(leaves):
        for name, function, jitted, skeleton in phases:
            carried = (exported_call(name, function, jitted, (*args, *carried), static, skeleton),)
            if after is not None:
                after(name, carried[0])
        return carried[0]
    # From a thread other than the main one (a Dask worker's task) the compilations in
    # worker threads hung: a distances run on a local Dask cluster never finished its
    # first pair (tests/test_cli.py's Ctrl-C test). There each phase compiles when called.
    if not is_concrete(leaves) or threading.current_thread() is not threading.main_thread():
        for name, _, jitted, _ in phases:
            carried = (jitted(*args, *carried, **static),)
            if after is not None and is_concrete(leaves):
                after(name, carried[0])
        return carried[0]
    programs = compile_phases(phases, args, carried, static)
    for (name, *_), (key, program) in zip(phases, programs, strict=True):
        try:
            compiled = program.result()
        except BaseException:
            _PHASE_PROGRAMS.pop(key, None)  # compiled again next time
            raise
        carried = (compiled(*args, *carried),)
        if after is not None:
            after(name, carried[0])
    return carried[0]


def compile_phases(phases, args: tuple, carried: tuple, static: dict) -> list:
    """Start compiling the programs of :func:`phase_chain`'s ``phases``; returns
    ``[(key, future of the compiled program)]``.

    The phases are traced here one after the other, each from the shapes of the one
    before's result (``args`` and ``carried`` may be arrays or ``jax.ShapeDtypeStruct``),
    and each is compiled in a worker thread as soon as it is traced: XLA compiles
    without Python's lock, so tracing the next phase and compiling the earlier ones
    overlap (the paper's low row, cats, 2 cores: tracing and compiling the five phases
    25.3 s one after the other, 19.2 s so). The programs are kept by phase, options and
    argument shapes: a phase traced before is not traced or compiled again. (Compiling
    a resolved distance's second level while its first solves, from shapes alone, was
    measured too: 36.1 s against 36.8 s for the cats' two levels on 2 cores, whose
    compilations already keep both cores busy; not kept.)
    """
    programs = []
    shapes = carried
    for name, _, jitted, _ in phases:
        flat, treedef = jax.tree_util.tree_flatten((args, shapes))
        key = (name, jax.default_backend(), chosen(), tuple(sorted(static.items())), str(treedef))
        key += _avals(flat)
        entry = _PHASE_PROGRAMS.get(key)
        if entry is None:
            traced = jitted.jitted().trace(*args, *shapes, **static)
            entry = (_compiler_pool().submit(lambda t=traced: t.lower().compile()), traced.out_info)
            _PHASE_PROGRAMS[key] = entry
        programs.append((key, entry[0]))
        shapes = (entry[1],)
    return programs


@cached
def _compiler_pool() -> ThreadPoolExecutor:
    """The worker threads that compile phases, one per core, first come first served."""
    return ThreadPoolExecutor(max_workers=os.cpu_count() or 1, thread_name_prefix="ej-compile")


def _compiled(name, key, function, quick, static, treedef, leaves, n_outputs):
    """The exported program of ``function``, callable on the flat ``leaves``.

    On CPU, its compiled executable from the cache directory when one was written for
    this machine (:func:`_host_key`), else compiled now and written there. Loading it
    skips what a jitted call of the exported program still does before JAX finds its
    executable in the persistent cache: lowering the program and hashing it (the paper's
    low row, a warm first call: 2.15 -> 1.9 s). The executable is the one that call
    compiles (same program, same options), so the results are identical. Elsewhere, or
    for a program with a custom call other than LAPACK's (set up by :func:`_lapack_ready`;
    a host callback cannot be stored), the jitted exported program.
    """
    from jax.experimental import serialize_executable

    cpu = jax.default_backend() == "cpu"
    file = _EXPORT_DIR / f"{name}-{key}-{_host_key('cpu', quick)}.xla" if cpu else None
    # How the stored executable's arguments and results were flattened: the leaves.
    trees = (
        jax.tree_util.tree_structure((tuple(range(len(leaves))), {})),
        jax.tree_util.tree_structure(tuple(range(n_outputs))),
    )
    if cpu and file.exists():
        try:
            _lapack_ready()
            return serialize_executable.deserialize_and_load(file.read_bytes(), *trees)
        except Exception:  # damaged, or from another jaxlib: compile it again
            pass
    program = _exported(name, key, function, static, treedef, leaves)
    # The jitted path's compiler options: both compile the same program alike.
    jitted = solver_jit(program.call, quick=quick)
    if not cpu or not _storable(program):
        return jitted
    compiled = jitted.jitted().lower(*leaves).compile()
    try:
        blob, *stored_trees = serialize_executable.serialize(compiled)
    except (ValueError, NotImplementedError):  # constants or mutable state in the program
        return compiled
    if tuple(stored_trees) == trees:
        _store(file, blob)
    return compiled


def _store(file: pathlib.Path, data: bytes) -> None:
    """Write ``data`` to ``file`` atomically; a directory that cannot be written only
    loses the file (the program still runs)."""
    try:
        with atomic_path(file) as tmp:
            tmp.write_bytes(data)
    except OSError:
        pass


def _storable(program) -> bool:
    """Whether ``program`` (an export.Exported) may run from a stored executable: no
    effects, and no custom calls but LAPACK's kernels."""
    import re

    if program.ordered_effects or program.unordered_effects:
        return False
    targets = re.findall(r"custom_call @([\w.$]+)", program.mlir_module())
    return all(t.startswith("lapack_") for t in targets)


@cached
def _lapack_ready() -> None:
    """Set up JAX's LAPACK kernels in this process.

    JAX loads them when it lowers a program that calls one (an SVD, an eigensolver);
    an executable loaded from disk calls them without any lowering here, and would find
    them missing (a segmentation fault, measured with the shape solve's eigensolver).
    Lowering one small SVD sets up all of them.
    """
    import numpy as np

    jax.jit(jax.numpy.linalg.svd).lower(np.eye(2, dtype=np.float32))


@cached
def _host_key(backend: str, quick: bool) -> str:
    """What a compiled executable depends on beyond its program: the backend and its
    version, the compiler options and XLA_FLAGS, the default device, and the processor
    (XLA:CPU generates code for this machine's instruction set: a cache directory shared
    by machines of several kinds keeps one executable per kind)."""
    import platform

    processor = [platform.machine(), platform.processor()]
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as info:
            lines = info.read().splitlines()
        # The first core's model and instruction set extensions (x86 "flags", Arm
        # "Features").
        for label in ("model name", "flags", "Features"):
            processor += [line for line in lines if line.startswith(label)][:1]
    except OSError:
        pass
    device = jax.devices(backend)[0]
    parts = [
        backend,
        device.device_kind,
        device.client.platform_version,
        repr(_compiler_options(backend, quick)),
        os.environ.get("XLA_FLAGS", ""),
        str(jax.config.jax_default_device),
        *processor,
    ]
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()[:16]


def _exported(name: str, key: str, function, static: dict, treedef, leaves):
    """The program of ``function`` from the cache directory, or exported and written there."""
    from jax import export

    file = _EXPORT_DIR / f"{name}-{key}.jax"
    if file.exists():
        try:
            return export.deserialize(bytearray(file.read_bytes()))
        except Exception:  # a file from another version, or damaged: export again
            pass

    def flat(*xs):
        # The function itself, not its jitted form: the program is then the one a
        # jitted call lowers, not a call nested in it.
        out = function(*jax.tree_util.tree_unflatten(treedef, xs), **static)
        return tuple(jax.tree_util.tree_leaves(out))

    program = export.export(jax.jit(flat))(*leaves)
    _store(file, program.serialize())
    return program


class CompileCounter:
    """``with CompileCounter() as c: ...``: ``c.count`` programs XLA compiled meanwhile.

    Through JAX's monitoring events: each program JAX compiles or finds in the
    persistent cache records a backend-compile duration, one found there also a cache
    hit. Programs found in this process's own caches, and the stored shape-solve
    executables (:func:`exported_call`), record neither: they are not compiled."""

    _LOOKUP = "/jax/core/compile/backend_compile_duration"
    _HIT = "/jax/compilation_cache/cache_hits"

    def __init__(self):
        self.lookups = self.hits = 0

    @property
    def count(self) -> int:
        return self.lookups - self.hits

    def _duration(self, event: str, _duration: float, **_kwargs) -> None:
        self.lookups += event == self._LOOKUP

    def _event(self, event: str, **_kwargs) -> None:
        self.hits += event == self._HIT

    def __enter__(self):
        jax.monitoring.register_event_duration_secs_listener(self._duration)
        jax.monitoring.register_event_listener(self._event)
        return self

    def __exit__(self, *exc):
        jax.monitoring.unregister_event_duration_listener(self._duration)
        jax.monitoring.unregister_event_listener(self._event)
        return False
