"""enable_compilation_cache: opt-in, effective after earlier compilations, and the only
place the library touches JAX's configuration."""

import json
import os
import pathlib
import subprocess
import sys
import warnings

import jax
import jax.numpy as jnp
import pytest

from .conftest import traced_functions

SCRIPT = """
import json, pathlib, sys
import jax
import jax.numpy as jnp
import elastic_jax as ej
before = jax.config.jax_compilation_cache_dir  # importing the library set nothing
jax.jit(lambda x: jnp.sin(x) * 2)(1.0)  # JAX settles on "no cache" here
first = ej.enable_compilation_cache(sys.argv[1] + "/a", min_compile_time_s=0)
jax.jit(lambda x: jnp.cos(x) + 3)(1.0)
path = ej.enable_compilation_cache(sys.argv[1] + "/b", min_compile_time_s=0)
jax.jit(lambda x: jnp.tan(x) - 4)(1.0)
print(json.dumps({"before": before, "after": jax.config.jax_compilation_cache_dir,
                  "path": str(path), "entries": len(list(pathlib.Path(path).iterdir())),
                  "first": len(list(first.iterdir()))}))
"""


def test_the_cache_is_opt_in_and_works_after_earlier_compilations(tmp_path):
    run = subprocess.run(
        [sys.executable, "-c", SCRIPT, str(tmp_path / "cache")],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 0, run.stderr[-2000:]
    out = json.loads(run.stdout.strip().splitlines()[-1])
    assert out["before"] is None
    assert out["after"] == out["path"] == str((tmp_path / "cache" / "b").resolve())
    # Each directory holds what was compiled while it was the cache: a second call moves
    # the cache (JAX alone would keep the directory it opened first).
    assert out["first"] >= 1 and out["entries"] >= 1


def _solve(target, scale, *, max_steps):
    """A small optimistix solve whose result holds a RESULTS code, as a shape solve's does."""
    from elastic_jax._geodesics.solvers import minimize

    return minimize(
        lambda y: scale * jnp.sum((y - target) ** 2) + jnp.sum(y**4),
        jnp.zeros_like(target),
        solver="bfgs",
        max_steps=max_steps,
        tol=1e-8,
    )


def test_an_exported_program_is_the_jitted_one_and_is_not_traced_again(tmp_path, monkeypatch):
    from elastic_jax._geodesics.solvers import Minimum
    from elastic_jax._results import RESULTS
    from elastic_jax._runtime import cache as _cache

    jitted = _cache.solver_jit(_solve, static_argnames=("max_steps",))
    skeleton = Minimum(0, RESULTS.successful, 0, 0, 0)
    target = jnp.linspace(-1.0, 2.0, 5)
    args, static = (target, 0.5), {"max_steps": 50}

    def call():
        return _cache.exported_call("solve", _solve, jitted, args, static, skeleton)

    monkeypatch.setattr(_cache, "_EXPORTED", {})
    monkeypatch.setattr(_cache, "_EXPORT_DIR", None)
    plain = call()  # the cache off: the jitted call
    assert not (tmp_path / "exported").exists()
    monkeypatch.setattr(_cache, "_EXPORT_DIR", tmp_path / "exported")
    first = call()
    # The exported program, and (CPU) its executable for this machine.
    files = {f.suffix: f.name for f in (tmp_path / "exported").iterdir()}
    key = files[".jax"].removesuffix(".jax")
    assert len(files) == 2 and key.startswith("solve-")
    assert files[".xla"] == f"{key}-{_cache._host_key('cpu', False)}.xla"
    # A new process: nothing in memory, the program on disk.
    monkeypatch.setattr(_cache, "_EXPORTED", {})
    again, traced = traced_functions(call)
    assert "_solve" not in traced and "flat" not in traced
    for result in (first, again):
        assert type(result) is Minimum and result.result == RESULTS.successful
        for a, b in zip(
            jax.tree_util.tree_leaves(result), jax.tree_util.tree_leaves(plain), strict=True
        ):
            assert a.dtype == b.dtype and bool(jnp.all(a == b))
    assert float(jnp.max(jnp.abs(plain.x - first.x))) == 0.0 and int(plain.num_steps) > 3

    # Under a transformation the arguments are tracers: the jitted call, nothing exported.
    traced_x = jax.jit(
        lambda t: _cache.exported_call("solve", _solve, jitted, (t, 0.5), static, skeleton).x
    )(target)
    assert bool(jnp.all(traced_x == plain.x)) and len(list((tmp_path / "exported").iterdir())) == 2

    # What changes the program changes the key: options, dtypes, a Python number for an
    # array (weakly typed), the package's source.
    leaves, treedef = jax.tree_util.tree_flatten(args)
    key = _cache._key("solve", static, treedef, leaves)
    assert key != _cache._key("solve", {"max_steps": 51}, treedef, leaves)
    assert key != _cache._key("solve", static, treedef, [target.astype(jnp.float32), 0.5])
    assert key != _cache._key("solve", static, treedef, [target, jnp.asarray(0.5, target.dtype)])
    monkeypatch.setattr(_cache, "_source_digest", lambda: "another version")
    assert key != _cache._key("solve", static, treedef, leaves)


EDITED = """
import json, pathlib, sys
import jax
import jax.numpy as jnp
import elastic_jax as ej
from elastic_jax._runtime import cache as _cache

ej.enable_compilation_cache(sys.argv[1])
program = lambda x: {"y": jnp.sin(x) * 2.0}
out = _cache.exported_call("edit", program, _cache.solver_jit(program), (jnp.ones(3),), {},
                           {"y": 0})
files = sorted(p.name for p in (pathlib.Path(sys.argv[1]) / "exported").iterdir())
print(json.dumps({"package": ej.__file__, "y": float(out["y"][0]), "files": files}))
"""


def test_an_edit_anywhere_in_the_package_gives_new_exported_programs(tmp_path):
    """A copy of the package, edited in a subpackage the runtime never imports directly
    (the registration's coarse phase): a new process exports under a new key, while an
    unedited copy finds its own programs again (the key is the source, not the process)."""
    import shutil

    import elastic_jax

    copy = tmp_path / "site"
    shutil.copytree(
        pathlib.Path(elastic_jax.__file__).parent,
        copy / "elastic_jax",
        ignore=shutil.ignore_patterns("__pycache__"),
    )
    env = {**os.environ, "PYTHONPATH": str(copy)}

    def run():
        done = subprocess.run(
            [sys.executable, "-c", EDITED, str(tmp_path / "cache")],
            capture_output=True,
            text=True,
            timeout=300,
            env=env,
            cwd=tmp_path,  # not the repository, whose elastic_jax would come first
        )
        assert done.returncode == 0, done.stderr[-2000:]
        return json.loads(done.stdout.strip().splitlines()[-1])

    first, again = run(), run()
    assert first["package"] == str(copy / "elastic_jax" / "__init__.py")
    keys = {name.split("-")[1].split(".")[0] for name in first["files"]}
    assert len(keys) == 1 and again["files"] == first["files"]  # the same key, found again
    with open(copy / "elastic_jax" / "_registration" / "coarse.py", "a") as source:
        source.write("# an edit that changes no program\n")
    edited = run()
    new = {name.split("-")[1].split(".")[0] for name in edited["files"]} - keys
    assert len(new) == 1 and set(first["files"]) < set(edited["files"])
    assert edited["y"] == first["y"]


WARM = """
import json, sys
import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import elastic_jax as ej
from elastic_jax._runtime import cache as _cache


def program(a, shift):
    # A symmetric eigensolver (a LAPACK kernel), as in the shape solve's saddle checks.
    w, v = jnp.linalg.eigh(a @ a.T + shift * jnp.eye(a.shape[0], dtype=a.dtype))
    return {"w": w, "v0": jnp.abs(v[:, 0])}


ej.enable_compilation_cache(sys.argv[1])
read = []  # exported programs deserialized or exported in this process
_cache._exported = (lambda f: lambda *x: read.append(x[0]) or f(*x))(_cache._exported)
a = jnp.arange(12.0).reshape(4, 3) / 7.0
jitted = _cache.solver_jit(program)
out = _cache.exported_call("eig", program, jitted, (a, 0.5), {}, {"w": 0, "v0": 0})
values = {k: [float(x) for x in v] for k, v in out.items()}  # runs it: LAPACK must be ready
plain = jax.jit(program)(a, 0.5)  # only now is an eigensolver lowered in this process
print(json.dumps({"read": read, "values": values,
                  "equal": all(bool(jnp.all(out[k] == plain[k])) for k in plain)}))
"""


def test_a_new_process_runs_the_stored_executable_with_identical_results(tmp_path):
    """The second process loads the executable the first compiled: it reads no exported
    program (so lowers nothing), sets up LAPACK itself (a kernel left unset would crash
    it) and gets the jitted program's results to the last bit."""
    runs = []
    for _ in range(2):
        run = subprocess.run(
            [sys.executable, "-c", WARM, str(tmp_path / "cache")],
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert run.returncode == 0, (run.returncode, run.stderr[-2000:])
        runs.append(json.loads(run.stdout.strip().splitlines()[-1]))
    first, second = runs
    assert first["read"] == ["eig"] and second["read"] == []
    assert first["equal"] and second["equal"] and second["values"] == first["values"]
    assert len(list((tmp_path / "cache" / "exported").glob("eig-*.xla"))) == 1


def test_executables_are_kept_only_for_plain_programs_and_per_machine(monkeypatch):
    """Stored executables: only programs without effects whose custom calls are all
    LAPACK kernels (the ones _lapack_ready sets up); keyed on the compiler options and
    XLA_FLAGS as well as the program."""
    from types import SimpleNamespace

    from elastic_jax._runtime import cache as _cache

    def program(text, effects=()):
        return SimpleNamespace(
            mlir_module=lambda: text, ordered_effects=effects, unordered_effects=()
        )

    lapack = "%0 = stablehlo.custom_call @lapack_dsyevd_ffi(%arg0) : ..."
    other = lapack + "\n%1 = stablehlo.custom_call @my_kernel(%0) : ..."
    assert _cache._storable(program("%0 = stablehlo.add %arg0, %arg0"))
    assert _cache._storable(program(lapack))
    assert not _cache._storable(program(other))
    assert not _cache._storable(program(lapack, effects=("an effect",)))

    keys = {_cache._host_key("cpu", False), _cache._host_key("cpu", True)}
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_enable_fast_math=false")
    _cache._host_key.cache_clear()
    keys.add(_cache._host_key("cpu", False))
    monkeypatch.delenv("XLA_FLAGS")
    _cache._host_key.cache_clear()
    assert len(keys) == 3


def test_exported_must_be_a_bool(tmp_path):
    import pytest

    import elastic_jax as ej

    # Refused before anything is set or created.
    with pytest.raises(ej.InputError, match="exported must be True or False; got 1"):
        ej.enable_compilation_cache(tmp_path / "cache", exported=1)
    for bad in (-1.0, float("nan"), "abc", True):
        with pytest.raises(ej.InputError, match="min_compile_time_s must be a positive"):
            ej.enable_compilation_cache(tmp_path / "cache", min_compile_time_s=bad)
    assert not (tmp_path / "cache").exists()


def test_the_shape_solve_phases_are_rebuilt_with_their_own_structures():
    """The skeletons that rebuild an exported phase's result have the structure the phase
    returns (leaf count and node types: a mismatch would scramble the fields)."""
    import elastic_jax as ej
    from elastic_jax._geometry.bases import make_bases
    from elastic_jax._registration import phases as _phases

    f1 = ej.sphere_points(7, 13)
    cfg = ej.ShapeOptions(degree=2, vf_degree=2, n_times=3, tol=1e-6, outer_steps=1, rtol=None)
    bases = make_bases(7, 13, cfg, f1.dtype)
    metric = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)
    for rigid in (False, True):
        carried = ()
        for _, function, skeleton in _phases.PHASES:
            out = jax.eval_shape(
                lambda a, b, c, function=function, rigid=rigid: function(
                    metric, a, b, bases, *c, cfg, rigid
                ),
                f1,
                2.0 * f1,
                carried,
            )
            assert jax.tree_util.tree_structure(out) == jax.tree_util.tree_structure(skeleton)
            carried = (out,)


@pytest.mark.slow
def test_the_solve_in_phases_is_the_solve_in_one_program():
    """The compiled phases compute what the one-program solve computes (the program a
    caller's batch compiles): every field of the result, on a pair that takes rounds.
    The last phase's diagnostics (gradient norm, refinement) are compiled without LLVM's
    optimizations, so they round differently: a gradient norm near a minimum is a small
    difference of large terms. Grid differences: with spline reads the two programs
    round the splines' FFTs differently and the rounds carry that to 3e-6 in the path
    (measured; the rounding sensitivity of docs/guides/limitations.md)."""
    import numpy as np

    import elastic_jax as ej
    from elastic_jax import shapes
    from elastic_jax._geometry.bases import make_bases
    from elastic_jax._registration import phases as _phases
    from elastic_jax._runtime import cache as _cache

    m, n = 9, 17
    f1 = jnp.asarray(shapes.sample(shapes.bumpy, m, n))
    f2 = jnp.asarray(shapes.sample(shapes.bumpy, m, n, rotation=shapes.random_rotation(3)))
    cfg = ej.ShapeOptions(
        degree=3,
        vf_degree=3,
        n_times=4,
        tol=1e-8,
        outer_steps=3,
        differential="grid",
        interpolation="bicubic",
    )
    bases = make_bases(m, n, cfg, f1.dtype)
    args = (ej.SplitMetric(1.0, 1.0, 0.1, 0.0), f1, f2, bases)
    phased = _phases.solve_in_phases(args, cfg, False)
    whole = _cache.solver_jit(_phases.shape_solve, static_argnames=("options", "rigid"))(
        *args, options=cfg, rigid=False
    )
    assert int(phased.rounds) >= 1
    for field in phased._fields:
        rtol = 1e-9 if field in ("grad_norm", "refinement") else 1e-12
        for a, b in zip(
            jax.tree_util.tree_leaves(getattr(phased, field)),
            jax.tree_util.tree_leaves(getattr(whole, field)),
            strict=True,
        ):
            a, b = np.asarray(a, float), np.asarray(b, float)
            scale = max(float(np.nanmax(np.abs(b), initial=0.0)), 1e-300)
            np.testing.assert_allclose(a, b, rtol=0, atol=rtol * scale, err_msg=field)


def test_around_the_solve_a_first_call_compiles_one_program_on_each_side(monkeypatch):
    """Into the solve's units and back out (with the path's energy evaluated again) are
    one compiled program each. Done op by op, a process's first shape_geodesic compiled
    some thirty small programs around the solve (about 1 s of a first call on 2 cores).
    The solve itself is replaced by a stand-in here; its own programs are the exported phases."""
    import numpy as np

    import elastic_jax as ej
    from elastic_jax import shapes
    from elastic_jax._geometry.bases import make_bases
    from elastic_jax._registration import one_grid as _one_grid
    from elastic_jax._registration import phases as _phases

    m, n = 9, 15  # a grid no other test uses: nothing is compiled for it yet
    f1 = np.asarray(shapes.sample(shapes.bumpy, m, n))
    f2 = np.asarray(shapes.sample(shapes.ellipsoid, m, n))
    # Grid differences: the stand-in's straight line is then path_energy's own.
    cfg = ej.ShapeOptions(
        degree=2,
        vf_degree=2,
        n_times=3,
        tol=1e-6,
        outer_steps=1,
        differential="grid",
        rtol=None,
    )
    bases = make_bases(m, n, cfg, f1.dtype)
    metric = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)
    layout = jax.eval_shape(
        lambda a, b: _phases.shape_solve(metric, a, b, bases, cfg, False), f1, f2
    )
    solved = jax.tree_util.tree_map(lambda s: np.zeros(s.shape, s.dtype), layout)._replace(
        gamma=np.asarray(ej.sphere_points(m, n)), rotation=np.eye(3), converged=np.True_
    )
    monkeypatch.setattr(_one_grid, "solve_in_phases", lambda *args: solved)
    result, names = traced_functions(
        lambda: ej.shape_geodesic(f1, f2, metric, options=cfg).distance.block_until_ready()
    )
    assert names == ["in_units", "shape_finish"]
    # The stand-in's identity registration and zero perturbation: the straight line.
    straight = ej.path_energy(metric, ej.straight_path(f1, f2, 3))
    np.testing.assert_allclose(float(result) ** 2, float(straight), rtol=1e-12)


def test_solver_options_apply_at_the_top_and_give_way_inside_a_callers_trace():
    # JAX accepts compiler options only on the outermost jit: inside the caller's jit
    # (traced arguments, or concrete constants traced all the same) and vmap the solve
    # is part of the caller's program. Every way gives the solve's value.
    from elastic_jax._runtime import cache as _cache

    options = dict(_cache._compiler_options(jax.default_backend()))
    if jax.default_backend() == "cpu":
        # The jaxlib this was written against knows the options: the probe keeps them.
        assert options == {
            "xla_cpu_use_fusion_emitters": False,
            "xla_cpu_experimental_ynn_fusion_type": "",
        }
        quick = dict(_cache._compiler_options(jax.default_backend(), True))
        assert quick == {**options, "xla_backend_optimization_level": 0}
    solve = _cache.solver_jit(_solve, static_argnames=("max_steps",))
    target = jnp.linspace(-1.0, 2.0, 5)
    top = solve(target, 0.5, max_steps=50).x
    inside = jax.jit(lambda t: solve(t, 0.5, max_steps=50).x)(target)
    constants = jax.jit(lambda: solve(target, 0.5, max_steps=50).x)()
    batched = jax.vmap(lambda s: solve(target, s, max_steps=50).x)(jnp.asarray([0.5, 2.0]))
    plain = jax.jit(_solve, static_argnames=("max_steps",))(target, 0.5, max_steps=50).x
    for x in (top, inside, constants, batched[0]):
        assert float(jnp.max(jnp.abs(x - plain))) <= 1e-12 * float(jnp.max(jnp.abs(plain)))
    # The minimizer: 2 s (y - t) + 4 y^3 = 0 per coordinate, at s = 0.5.
    assert float(jnp.max(jnp.abs(top - target + 4 * top**3))) < 1e-7


def test_clear_caches_empties_every_cache_and_changes_no_result():
    import numpy as np

    import elastic_jax as ej
    from elastic_jax._runtime import cache as _cache

    basis = ej.surface_basis(9, 17, 3)
    weights = ej.quadrature_weights(9, 17)
    assert sum(w.cache_info().currsize for w in _cache._CACHED) > 0
    ej.clear_caches()
    assert sum(w.cache_info().currsize for w in _cache._CACHED) == 0
    assert _cache._EXPORTED == {}
    # Rebuilt from the arguments alone: the same numbers, bit for bit.
    np.testing.assert_array_equal(ej.surface_basis(9, 17, 3), basis)
    np.testing.assert_array_equal(ej.quadrature_weights(9, 17), weights)


def _tiny_levels():
    """Options whose programs compile fast: the warmup test's, whose first level the
    phases test solves too (the compiled programs are then shared through the cache)."""
    import elastic_jax as ej

    return ej.ShapeOptions(
        degree=2, vf_degree=2, n_times=3, tol=1e-6, outer_steps=1, levels=((7, 13), (9, 17))
    )


def _warmup_then_solve(options, grids):
    """warmup on inputs at 9 x 17, then a solve of another pair on the same settings:
    the solve and a second warmup compile nothing; the report names the grids."""
    import elastic_jax as ej
    from elastic_jax import shapes
    from elastic_jax._runtime.cache import CompileCounter

    report = ej.warmup((9, 17), options=options)
    assert report.grids == grids and report.input_grid == (9, 17)
    assert report.programs > 0
    f1 = shapes.sample(shapes.bumpy, 9, 17)
    f2 = 1.2 * shapes.sample(shapes.bumpy, 9, 17, rotation=shapes.random_rotation(3))
    with CompileCounter() as counter, warnings.catch_warnings():
        warnings.simplefilter("ignore", ej.ConvergenceWarning)
        res = ej.shape_geodesic(f1, f2, ej.SplitMetric(1.0, 0.5, 0.2, 0.0), options=options)
    assert counter.count == 0
    assert ej.warmup((9, 17), options=options).programs == 0
    return res


def test_warmup_compiles_every_program_a_later_solve_on_one_grid_runs():
    # One working grid: the programs of
    # test_the_phases_compiled_concurrently_are_the_jitted_phases.
    options = _tiny_levels().replace(grid=(7, 13), rtol=None)
    res = _warmup_then_solve(options, ((7, 13),))
    assert res.path.shape[-2:] == (7, 13) and res.levels is None


@pytest.mark.slow  # about 130 s on 2 cores: every program of two levels compiles
def test_warmup_compiles_every_program_a_later_solve_runs():
    """After warmup (levels 7 x 13 and 9 x 17, inputs on 9 x 17), a resolved solve of
    another pair on the same settings compiles nothing, and warmup again compiles
    nothing; the report names the grids."""
    res = _warmup_then_solve(_tiny_levels(), ((7, 13), (9, 17)))
    assert res.levels.grids.tolist() == [[7, 13], [9, 17]]


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"modulo": "none"}, "modulo"),
        ({"modulo": ()}, "modulo"),
        ({"input_grid": (9, 16)}, "odd n"),
        ({"input_grid": "big"}, "input_grid"),
        ({"dtype": "int32"}, "dtype"),
        ({"dtype": "float16"}, "dtype"),
        ({"degree": 0}, "degree"),
    ],
)
def test_warmup_refuses_bad_settings_before_compiling(kwargs, message):
    import elastic_jax as ej
    from elastic_jax._runtime.cache import CompileCounter

    with CompileCounter() as counter, pytest.raises(ej.InputError, match=message):
        ej.warmup(**kwargs)
    assert counter.count == 0


def test_the_phases_compiled_concurrently_are_the_jitted_phases():
    """phase_chain traces each phase from the shapes of the one before and compiles them
    in threads: the same programs as the jitted calls, so every field of the result is
    the same to the last bit; and a second solve compiles nothing."""
    import numpy as np

    import elastic_jax as ej
    from elastic_jax import shapes
    from elastic_jax._geometry.bases import make_bases
    from elastic_jax._registration import phases as _phases
    from elastic_jax._runtime.cache import CompileCounter

    # The one-grid warmup test's options (its programs, when that ran first).
    cfg = _tiny_levels().replace(grid=(7, 13), rtol=None)
    bases = make_bases(7, 13, cfg, jnp.float64)
    f1 = shapes.sample(shapes.bumpy, 9, 17)
    f2 = 1.2 * shapes.sample(shapes.bumpy, 9, 17, rotation=shapes.random_rotation(5))
    args = (ej.SplitMetric(1.0, 1.0, 0.1, 0.0), f1, f2, bases)
    chained = _phases.solve_in_phases(args, cfg, False)
    carried = ()
    for name, _, _ in _phases.PHASES:
        carried = (_phases.PHASE_JITS[name](*args, *carried, options=cfg, rigid=False),)
    leaves = jax.tree_util.tree_leaves(chained), jax.tree_util.tree_leaves(carried[0])
    for a, b in zip(*leaves, strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert int(chained.rounds) >= 1 and float(chained.energy) > 0
    with CompileCounter() as counter:
        again = _phases.solve_in_phases(args, cfg, False)
    assert counter.count == 0 and float(again.energy) == float(chained.energy)
