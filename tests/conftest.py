"""Test configuration: float64 and strict promotion for the tests only (never on import)."""

from __future__ import annotations

import atexit
import os
import pathlib
import shutil
import tempfile

# The suite is mostly XLA compiling small solves: LLVM's optimization level 1 instead of
# XLA's default compiles them faster than it slows them. README's resolved example on 2
# cores: 117 s of compiling -> 91 s, the call 88 s -> 73 s, its distance moved by 1e-6
# (relative). Set before JAX starts its backend; an XLA_FLAGS that sets it wins, and the
# command line's subprocesses inherit it (their programs are the in-process ones).
_FLAGS = os.environ.get("XLA_FLAGS", "")
if "xla_backend_optimization_level" not in _FLAGS:
    os.environ["XLA_FLAGS"] = f"{_FLAGS} --xla_backend_optimization_level=1".strip()

import jax  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
jax.config.update("jax_numpy_dtype_promotion", "strict")
# One persistent compilation cache for the whole run: the command line's subprocesses
# (tests/test_cli.py passes --cache-dir COMPILATION_CACHE) and the in-process calls that
# check them compile the same solves, and so do test files that pytest-xdist hands to
# different workers; a shape solve compiles for 30-60 s on 2 cores. The process that
# imports this first (xdist's controller, or the only process with -n 0) makes the
# directory and removes it at exit; the workers it starts inherit its path.
_SHARED = "ELASTIC_JAX_TEST_COMPILATION_CACHE"
if _SHARED not in os.environ:
    os.environ[_SHARED] = tempfile.mkdtemp(prefix="elastic-jax-tests-")
    atexit.register(shutil.rmtree, os.environ[_SHARED], ignore_errors=True)
COMPILATION_CACHE = pathlib.Path(os.environ[_SHARED])
jax.config.update("jax_compilation_cache_dir", str(COMPILATION_CACHE))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)


@pytest.fixture(autouse=True, scope="module")
def _fresh_jit_caches():
    """Drop this module's compiled executables when it ends (the persistent cache keeps
    them for later modules): a process that held the whole suite's executables aborted
    inside XLA late in the suite (in compilation and in cache serialization; each test
    passes in a fresh process). The package's own caches too: its compiled solve phases
    (phase_chain) are held apart from JAX's."""
    yield
    from elastic_jax import clear_caches

    clear_caches()


@pytest.fixture(autouse=True)
def _no_exported_programs_after_a_test():
    """A test that turns the exported shape solve on (enable_compilation_cache, the
    command line in process) leaves it off for the next one: the suite's in-process
    solves share the compiled programs of the plain jitted path."""
    from elastic_jax._runtime import cache as _cache

    yield
    _cache._EXPORT_DIR = None


@pytest.fixture(autouse=True)
def _internals_trace_as_the_public_functions(request):
    """Each test runs under the matmul precision that the public functions trace at
    (elastic_jax/_runtime/precision.py), so that a test calling an internal solve shares
    the compiled programs of the public calls beside it: the precision keys JAX's caches,
    and a level's solve called outside it compiled afresh (30 s at 9 x 17). On CPU the
    numbers are the same. A test marked ``caller_precision`` sees JAX's default."""
    if request.node.get_closest_marker("caller_precision"):
        yield
        return
    from elastic_jax._runtime.precision import full_products

    with full_products():
        yield


DATA = pathlib.Path(__file__).resolve().parents[1].parent / "shared" / "data"
# The authors' files beside the repository: elastic_jax.datasets reads them from here and
# the tests never download (a test whose file is not here skips).
SHAPE_DATA = DATA / "ShapeData"
os.environ.setdefault("ELASTIC_JAX_DATA", str(SHAPE_DATA))

# Tolerances for float64 identities and for float32, in one place.
RTOL = {np.dtype("float64"): 1e-12, np.dtype("float32"): 1e-5}


def load_shape(name: str) -> np.ndarray:
    """One of the authors' surfaces by name (elastic_jax.datasets), (3, 50, 99) float64,
    from $ELASTIC_JAX_DATA; skips the test when the file is not there."""
    from elastic_jax import datasets

    folder = pathlib.Path(os.environ["ELASTIC_JAX_DATA"])
    if not (folder / f"{name}_50_99.mat").is_file():
        pytest.skip(f"{name}_50_99.mat is not in {folder}")
    return datasets.load(name)


def fsaverage5(name: str) -> str:
    """A file of nilearn's fsaverage5 (``pial_left``, ``sphere_right``, ...; in its wheel);
    skips the test without nilearn or nibabel."""
    pytest.importorskip("nibabel")
    pytest.importorskip("nilearn")
    import importlib.util

    folder = pathlib.Path(importlib.util.find_spec("nilearn").origin).parent
    return str(folder / "datasets" / "data" / "fsaverage5" / f"{name}.gii.gz")


@pytest.fixture
def cats() -> tuple[np.ndarray, np.ndarray]:
    return load_shape("cat1"), load_shape("cat2")


def relerr(x, y) -> float:
    x, y = np.asarray(x), np.asarray(y)
    return float(np.max(np.abs(x - y)) / np.max(np.abs(y)))


def assert_area_bound(distance, f1, f2, metric, slack: float = 0.01, areas=None) -> float:
    """docs/math.md §9: d(f1, f2) >= sqrt(2 b) |sqrt(A(f2)) - sqrt(A(f1))| for every quotient.

    Area is invariant under reparametrization and rigid motion; Cauchy-Schwarz on the
    b-term of the energy gives the bound. The areas are the continuum's, estimated on the
    inputs' interpolants 4 times finer (bicubic): on the working grid a stretched
    parametrization of a surface loses area that the surface has (a unit sphere under a
    Moebius map with |a| = 0.6 loses 2.7 % at 25 x 49). A distance more than ``slack``
    below the bound is an exploited discretization. ``areas`` gives the continuum areas
    when the test knows them (a surface and its reparametrization: equal areas, a bound
    of 0, though the grid samples of a stretched parametrization lose area). Returns the
    bound.
    """
    import elastic_jax as ej

    def area(f):
        m, n = f.shape[-2:]
        fine = ej.sphere_points(4 * m - 3, 4 * n - 3, dtype=f.dtype)
        return float(ej.surface_area(ej.reparametrize(f, fine, "bicubic")))

    a1, a2 = (area(f1), area(f2)) if areas is None else areas
    bound = float(np.sqrt(2.0 * float(metric.b))) * abs(np.sqrt(a2) - np.sqrt(a1))
    assert float(distance) >= (1.0 - slack) * bound, (float(distance), bound)
    return bound


def traced_functions(call):
    """``(call(), names)``: the functions JAX traced for new compiled programs while
    ``call()`` ran (JAX's trace events)."""
    names = []

    def listener(event, duration_secs, **kwargs):
        if event == "/jax/core/compile/jaxpr_trace_duration":
            names.append(kwargs.get("fun_name"))

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        out = call()
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)
    return out, names
