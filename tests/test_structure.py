"""The package's import structure (issue 31): a graph without cycles, no module reaching
into another's underscore names, and a runtime layer that knows no shape analysis.

Read from the source with ``ast`` (nothing is imported), so the counts are exact.
"""

from __future__ import annotations

import ast
import pathlib
import re

PACKAGE = pathlib.Path(__file__).resolve().parents[1] / "elastic_jax"
# Each module's layer is its subpackage (or, for a top-level module, its own name). A
# layer imports only layers of a lower rank and itself: the tree shows the architecture.
LEAVES = {"_errors", "_checks", "_options", "_results", "_version"}
RANKS = {
    "leaves": 0,  # errors, argument checks, options, result codes, the version
    "_runtime": 1,  # atomic writes, compilation caches, the Dask pool: below every solver
    "_geometry": 2,
    "_geodesics": 3,
    "_meshes": 3,
    "_registration": 4,
    "_statistics": 5,
    "public": 6,
}
PUBLIC_MODULES = {"io", "plot", "shapes", "datasets", "cli", "__init__", "__main__"}


def _module_name(path: pathlib.Path) -> str:
    """``_geometry.grid`` for elastic_jax/_geometry/grid.py; a package by its name."""
    parts = path.relative_to(PACKAGE).with_suffix("").parts
    if parts[-1] == "__init__" and len(parts) > 1:
        parts = parts[:-1]
    return ".".join(parts)


def _relative_imports(path: pathlib.Path) -> list[tuple[str, str]]:
    """(module, name) for every relative import in the file, inside functions too, the
    module resolved to its dotted name within the package (``from .. import io`` gives
    ("io", "io"): a module imported by name; ``from .. import shoot``, a name of the
    package's ``__init__``, gives ("__init__", "shoot"))."""
    here = path.relative_to(PACKAGE).parent.parts
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level >= 1:
            base = here[: len(here) - (node.level - 1)]
            for alias in node.names:
                if node.module:
                    out.append((".".join([*base, node.module]), alias.name))
                else:
                    dotted = ".".join([*base, alias.name])
                    is_module = (PACKAGE.joinpath(*base, alias.name)).exists() or (
                        PACKAGE.joinpath(*base, alias.name + ".py")
                    ).exists()
                    if is_module:
                        out.append((dotted, alias.name))
                    else:  # a name the package (or subpackage) defines
                        out.append((".".join(base) or "__init__", alias.name))
    return out


def _graph() -> dict[str, set[str]]:
    graph = {_module_name(p): set() for p in PACKAGE.rglob("*.py")}
    for p in PACKAGE.rglob("*.py"):
        for module, name in _relative_imports(p):
            # `from .pkg import module` names the module, not the package's __init__.
            target = f"{module}.{name}" if f"{module}.{name}" in graph else module
            graph[_module_name(p)].add(target)
    return graph


def _layer(module: str) -> str:
    top = module.split(".")[0]
    if top in LEAVES:
        return "leaves"
    return "public" if top in PUBLIC_MODULES else top


def _upward(graph: dict[str, set[str]]) -> list[str]:
    """Every import of a module in another layer of the same or a higher rank."""
    return sorted(
        f"{module} -> {target}"
        for module, targets in graph.items()
        for target in targets
        if _layer(target) != _layer(module) and RANKS[_layer(target)] >= RANKS[_layer(module)]
    )


def _cycles(graph: dict[str, set[str]]) -> list[set[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in graph:
                continue
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = set()
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.add(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(component)

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_the_cycle_finder_finds_a_cycle():
    # The check below would pass vacuously with a finder that never reports one.
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [{"a", "b", "c"}]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_imports_have_no_cycles():
    graph = _graph()
    assert len(graph) >= 40  # the whole package was read, subpackages included
    assert _cycles(graph) == []


def test_no_module_imports_another_modules_underscore_names():
    private = [
        f"{path.name}: from .{module} import {name}"
        for path in sorted(PACKAGE.rglob("*.py"))
        for module, name in _relative_imports(path)
        # A module by name is fine, and so is a dunder (the package's __version__).
        if name.startswith("_") and not module.endswith(name) and not name.endswith("__")
    ]
    assert private == []


def test_every_module_has_a_layer():
    assert {_layer(m) for m in _graph()} == set(RANKS)


def test_layers_import_only_lower_layers():
    # The runtime knows no shape analysis, the geometry no solver, the solvers no
    # registration, registration no statistics; the public modules sit on top.
    assert _upward(_graph()) == []


def test_the_layer_check_sees_an_upward_or_sideways_import():
    # A control: a geometry module importing a solver, and the meshes importing the
    # solvers (same rank, another layer), are both flagged; a downward import is not.
    graph = {
        "_geometry.energy": {"_geodesics.geodesic", "_geometry.grid"},
        "_meshes.sphere_map": {"_geodesics.solvers"},
        "_statistics.pca": {"_geodesics.shooting"},
    }
    assert _upward(graph) == [
        "_geometry.energy -> _geodesics.geodesic",
        "_meshes.sphere_map -> _geodesics.solvers",
    ]


def test_leaf_modules_import_only_errors():
    graph = _graph()
    for module in LEAVES - {"_options"}:
        assert graph[module] <= {"_errors"}, module


def test_every_cache_is_registered_for_clear_caches():
    # functools.cache / lru_cache only through _runtime.cache.cached, which registers the
    # cache with elastic_jax.clear_caches (issue 31: state behind one public call).
    direct = []
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Attribute) and node.attr in ("cache", "lru_cache"):
                if isinstance(node.value, ast.Name) and node.value.id == "functools":
                    direct.append(f"{_module_name(path)}:{node.lineno}")
    assert direct == ["_runtime.cache:" + str(_cached_line())]


def _cached_line() -> int:
    """The one direct use: inside cached() itself."""
    source = (PACKAGE / "_runtime" / "cache.py").read_text().splitlines()
    return next(i for i, line in enumerate(source, 1) if "= functools.cache(function)" in line)


# The public API as users import it; a rename or a removal is a decision, not an accident
# of moving code (issue 31: the tree may change, these names may not).
PUBLIC = {
    "elastic_jax": """ConvergenceWarning DistanceMatrixResult EnergyDensity GeodesicResult
        InputError JobOptions
        KarcherResult Levels LogResult MetricFit RESULTS Refinement ShapeGeodesicResult ShapeOptions
        RetrievalScores ShootingResult SphericalHarmonics SplitMetric SrnfGeodesic
        SrnfInversion TangentPCA TransportResult WarmupReport base_inner center clear_caches
        diffeomorphism diffeomorphism_bound differential distance_matrix
        elastic_metric_inner enable_compilation_cache energy_density exp fit_metric geodesic
        grid_angles
        hat icosahedral_group integrate jacobian_determinant karcher_mean log max_degree
        metric_inner mode_path moebius parallel_transport path_energy path_length
        quadrature_weights real_sph_harm reparametrize resample retrieval_scores
        rotate_parametrization shape_geodesic shoot sigmas_reached smooth_surface so3_exp
        so3_log sphere_points split_inner split_parts srnf srnf_distance srnf_geodesic srnf_invert
        srnf_path_length straight_path surface_area surface_basis tangent_pca
        upsample_coefficients validate_surface vector_field_basis vee warmup""",
    "elastic_jax.io": """MESH_FORMATS DegenerateFaceError FrameWarning InconsistentWindingError
        MeshError MeshFrame mesh_frame NonManifoldVertexError NotGenusZeroError
        NotStarShapedError NotWatertightError
        ParametrizationError SphericalParametrization VertexMap grid_to_mesh grid_to_vertices
        load_surface mesh_to_grid normalize_scale save_path save_surface
        spherical_parametrization star_center surface_files
        atomic_path save_npz_atomic write_text_atomic stale_temporaries""",
    "elastic_jax.plot": """parametrization_colors plot_path plot_field plot_modes plot_energy
        plot_distance_matrix save_figure""",
    "elastic_jax.shapes": "sphere ellipsoid bumpy bent_cylinder sample random_rotation two_classes "
    "geodesic_sphere",
    "elastic_jax.datasets": "REPOSITORY COMMIT cache_dir load names path",
}


def test_the_public_api_is_pinned():
    import importlib

    for name, expected in PUBLIC.items():
        module = importlib.import_module(name)
        found = set(module.__all__)
        assert all(hasattr(module, n) for n in found), name
        if name == "elastic_jax":
            # __all__ is every name the package defines and exports, the modules aside.
            defined = {
                n
                for n in dir(module)
                if not n.startswith("_")
                and getattr(getattr(module, n), "__module__", "").startswith("elastic_jax")
            }
            assert found == defined - {"shapes"}, found ^ (defined - {"shapes"})
        assert found == set(expected.split()), (name, found ^ set(expected.split()))


def test_every_error_is_an_input_error():
    # One hierarchy: the mesh errors and the command line's bad input are InputErrors,
    # which are ValueErrors.
    from elastic_jax import InputError, cli, io

    errors = [getattr(io, n) for n in io.__all__ if n.endswith("Error")] + [cli.BadInput]
    assert len(errors) == 9
    assert all(issubclass(e, InputError) and issubclass(e, ValueError) for e in errors)


def test_the_documented_layout_names_every_subpackage():
    # The contributing page's table is the map a newcomer reads; it names each subpackage once.
    page = (PACKAGE.parent / "docs" / "contributing.md").read_text()
    table = page.split("## Package layout")[1].split("\n## ")[0]
    named = {cell.strip("`/") for cell in re.findall(r"`(\w+)/`", table)}
    subpackages = {p.parent.name for p in PACKAGE.glob("*/__init__.py")}
    assert named == subpackages
    assert set(RANKS) - {"leaves", "public"} == subpackages - {"cli"}


# The grid services that geodesics, registration and statistics all call live on the
# geometry floor (issue 53): a surface checked, a path built from its basis, a square root
# safe at zero. Each name is defined in its home and imported from nowhere else, so data
# handed to them never climbs through the geodesics floor and back.
SERVICES = {
    "basis_np": "_geometry.bases",
    "frames_between": "_geometry.bases",
    "perturbed_frames": "_geometry.bases",
    "path_from_coefficients": "_geometry.bases",
    # A solve's per-grid tables (registration, logs and metric fits build on them) and
    # the grid-dependent checks of the options.
    "make_bases": "_geometry.bases",
    "field_scale_np": "_geometry.bases",
    "grid_area_np": "_geometry.bases",
    "resolution_np": "_geometry.bases",
    "check_grid_options": "_geometry.validation",
    "check_pair": "_geometry.validation",
    "safe_sqrt": "_geometry.numerics",
    "constant": "_geometry.numerics",
    "sqrt_inverse_pair": "_geometry.numerics",
    "default_tol": "_geometry.numerics",
}


def test_grid_services_live_on_the_geometry_floor_and_are_imported_from_there():
    defined = {}
    for p in PACKAGE.rglob("*.py"):
        for node in ast.parse(p.read_text()).body:
            if isinstance(node, ast.FunctionDef) and node.name in SERVICES:
                defined.setdefault(node.name, []).append(_module_name(p))
    assert defined == {name: [home] for name, home in SERVICES.items()}
    wrong = sorted(
        f"{_module_name(p)} imports {name} from {module}"
        for p in PACKAGE.rglob("*.py")
        for module, name in _relative_imports(p)
        if name in SERVICES and module != SERVICES[name]
    )
    assert wrong == []


def test_no_library_module_outside_the_commands_silences_warnings():
    """The package's own callers use solves that do not warn (solve_shapes,
    solve_geodesic) and report each solve's status in their records: nothing below the
    command line filters a warning, so a user's filters are the only ones."""
    silencing = sorted(
        f"{_module_name(p)}:{node.lineno}"
        for p in PACKAGE.rglob("*.py")
        if "cli" not in p.relative_to(PACKAGE).parts
        for node in ast.walk(ast.parse(p.read_text()))
        if isinstance(node, ast.Attribute)
        and node.attr in {"catch_warnings", "simplefilter", "filterwarnings"}
    )
    assert silencing == []


def test_jaxopt_is_used_through_its_public_api_only():
    """solver="lbfgs" is jaxopt's LBFGS as published (issue 53): no subclass overriding its
    private members, no private attribute read, no warning of its silenced in the package."""
    offences = []
    for p in PACKAGE.rglob("*.py"):
        tree = ast.parse(p.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.ClassDef):
                bases = [ast.unparse(b) for b in node.bases]
                if any("jaxopt" in b or "LBFGS" in b and "optx" not in b for b in bases):
                    offences.append(f"{_module_name(p)}: class {node.name}({', '.join(bases)})")
            if isinstance(node, ast.Attribute) and node.attr.startswith("_"):
                if "jaxopt" in ast.unparse(node.value):
                    offences.append(f"{_module_name(p)}: {ast.unparse(node)}")
            if isinstance(node, ast.Constant) and isinstance(node.value, str):
                if "JAXopt is no longer maintained" in node.value:
                    offences.append(f"{_module_name(p)}: silences jaxopt's warning")
    assert offences == []


def test_the_options_record_has_one_name():
    """A ShapeOptions (or a record resolved from one) is called ``options`` in every
    signature (issue 53: it was ``cfg`` in 37 and ``options`` in 26)."""
    named_cfg = sorted(
        f"{_module_name(p)}.{node.name}"
        for p in PACKAGE.rglob("*.py")
        for node in ast.walk(ast.parse(p.read_text()))
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
        and "cfg" in {a.arg for a in ast.walk(node.args) if isinstance(a, ast.arg)}
    )
    assert named_cfg == []


def test_cli_commands_are_clients_of_the_public_results():
    """A command learns what a solve did from its result, not from the library's warnings
    (the entry point alone silences them, once) nor by re-slicing a record (issue 53)."""
    offences = sorted(
        f"{_module_name(p)}: {ast.unparse(node)[:60]}"
        for p in (PACKAGE / "cli").glob("*.py")
        if p.name != "__init__.py"
        for node in ast.walk(ast.parse(p.read_text()))
        if isinstance(node, ast.Attribute) and node.attr in ("catch_warnings", "_replace")
    )
    assert offences == []


def test_each_command_owns_its_arguments_and_uses_the_public_functions():
    """Each cli/<command>.py adds its own arguments (its COMMAND record); the parser only
    loops over them; a command takes every name the package exports from the package
    itself (the public functions, with their precision wrapper and their checks), not
    from the module behind it."""
    import elastic_jax as ej
    from elastic_jax.cli.parser import COMMANDS, build_parser

    tree = ast.parse((PACKAGE / "cli" / "parser.py").read_text())
    function = next(
        n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == "build_parser"
    )
    body = function.body[1:]  # the docstring is not code
    lines = {
        line for statement in body for line in range(statement.lineno, statement.end_lineno + 1)
    }
    assert len(lines) <= 40
    names = [command.name for command in COMMANDS]
    assert len(set(names)) == len(names) == 10
    parser = build_parser()
    subparsers = next(a for a in parser._actions if a.dest == "command")
    assert sorted(subparsers.choices) == sorted(names)
    exported = set(ej.__all__)
    imports = [
        (p.name, node)
        for p in (PACKAGE / "cli").glob("*.py")
        for node in ast.walk(ast.parse(p.read_text()))
        if isinstance(node, ast.ImportFrom) and node.level == 2
    ]
    around = sorted(
        f"{name}: {alias.name} from {node.module}"
        for name, node in imports
        if node.module
        for alias in node.names
        if alias.name in exported
    )
    assert around == []
    # Commands import only public names: the package's, and its public modules' (io's
    # atomic writes), never a private module's helpers.
    private = sorted(
        f"{name}: {', '.join(a.name for a in node.names)} from {node.module or '..'}"
        for name, node in imports
        if (node.module or "").startswith("_")
        or any(a.name.startswith("_") and not a.name.endswith("__") for a in node.names)
    )
    assert private == []


def test_a_concrete_only_check_is_spelled_one_way():
    """Whether a value is traced is asked through _checks.is_concrete (issue 53: two
    spellings in 20 branches); _results, a leaf that imports only the errors, has its own."""
    spelled = sorted(
        _module_name(p) for p in PACKAGE.rglob("*.py") if "core.Tracer" in p.read_text()
    )
    assert spelled == ["_checks", "_results"]


def test_cli_imports_at_call_time_only_what_the_package_has_not_loaded():
    """``import elastic_jax.cli`` runs elastic_jax/__init__ first, which loads jax, numpy and
    every solver: importing those inside a command saves nothing (issue 53 counted 28).
    What a command may import when it runs: plot (matplotlib, about 0.3 s that
    ``elastic_jax`` alone does not load; io, which the commands' atomic writes come from,
    is loaded with them), the optional Dask and the POSIX-only fcntl."""
    allowed = {
        "from .. import plot",
        "import distributed",
        "import fcntl",
    }
    late = sorted(
        f"{p.name}: {ast.unparse(node)}"
        for p in (PACKAGE / "cli").glob("*.py")
        for function in ast.walk(ast.parse(p.read_text()))
        if isinstance(function, ast.FunctionDef)
        for node in ast.walk(function)
        if isinstance(node, ast.Import | ast.ImportFrom) and ast.unparse(node) not in allowed
    )
    assert late == []


# What users read says what the package does, not how its work was organised.
_PROCESS_WORDING = re.compile(r"\bthis stop\b|\bstops? \d+\b|\bissues? #?\d+\b", re.IGNORECASE)


def _user_texts() -> list[pathlib.Path]:
    root = PACKAGE.parent
    docs = [
        p
        for p in (root / "docs").rglob("*")
        if p.suffix in (".md", ".py", ".ipynb") and "_build" not in p.parts
    ]
    benchmarks = sorted((root / "benchmarks").glob("*.py"))
    notebooks = sorted((root / "notebooks").glob("*"))
    package = sorted(PACKAGE.rglob("*.py"))
    return [root / "README.md", root / "CHANGELOG.md", *docs, *benchmarks, *notebooks, *package]


def test_user_texts_carry_no_process_wording():
    found = []
    for path in _user_texts():
        if not path.is_file():
            continue
        for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            if _PROCESS_WORDING.search(line):
                found.append(f"{path.relative_to(PACKAGE.parent)}:{number}: {line.strip()[:80]}")
    assert found == []


def test_no_wheel_is_tracked():
    import shutil
    import subprocess

    root = PACKAGE.parent
    if shutil.which("git") is None or not (root / ".git").exists():
        return  # an unpacked source tree: nothing is tracked
    tracked = subprocess.run(
        ["git", "ls-files", "*.whl"], cwd=root, capture_output=True, text=True, check=True
    ).stdout.split()
    assert tracked == []
