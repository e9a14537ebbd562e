"""The package's import structure (issue 31): a graph without cycles, no module reaching
into another's underscore names, and a runtime layer that knows no shape analysis.

Read from the source with ``ast`` (nothing is imported), so the counts are exact.
"""

from __future__ import annotations

import ast
import pathlib

PACKAGE = pathlib.Path(__file__).resolve().parents[1] / "elastic_jax"
# Atomic writes, compilation caches and the Dask pool: below every solver.
RUNTIME = {"_atomic", "_cache", "_distributed"}
LEAVES = {"_errors", "_checks"}


def _relative_imports(path: pathlib.Path) -> list[tuple[str, str]]:
    """(module, name) for every ``from .module import name`` and ``from . import name`` in
    the file, inside functions too."""
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level == 1:
            for alias in node.names:
                out.append((node.module or alias.name, alias.name))
    return out


def _graph() -> dict[str, set[str]]:
    return {
        p.stem: {module.split(".")[0] for module, _ in _relative_imports(p)}
        for p in PACKAGE.glob("*.py")
    }


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
    assert len(graph) >= 30  # the whole package was read
    assert _cycles(graph) == []


def test_no_module_imports_another_modules_underscore_names():
    private = [
        f"{path.name}: from .{module} import {name}"
        for path in sorted(PACKAGE.glob("*.py"))
        for module, name in _relative_imports(path)
        if name.startswith("_") and module != name  # `from . import _module` is fine
    ]
    assert private == []


def test_runtime_and_leaf_modules_import_no_domain_code():
    graph = _graph()
    for module in LEAVES:
        assert graph[module] <= {"_errors"}, module
    for module in RUNTIME:
        assert graph[module] <= RUNTIME | LEAVES, (module, graph[module] - RUNTIME - LEAVES)


# The public API as users import it; a rename or a removal is a decision, not an accident
# of moving code (issue 31: the tree may change, these names may not).
PUBLIC = {
    "elastic_jax": """ConvergenceWarning DistanceMatrixResult GeodesicResult InputError
        KarcherResult LogResult RESULTS Refinement ShapeGeodesicResult ShapeOptions
        ShootingResult SphericalHarmonics SplitMetric SrnfGeodesic SrnfInversion TangentPCA
        TransportResult base_inner center diffeomorphism diffeomorphism_bound differential
        distance_matrix elastic_metric_inner enable_compilation_cache exp geodesic
        grid_angles hat icosahedral_group integrate jacobian_determinant karcher_mean log
        max_degree metric_inner mode_path moebius parallel_transport path_energy path_length
        quadrature_weights real_sph_harm reparametrize resample rotate_parametrization
        shape_geodesic shoot so3_exp so3_log sphere_points split_inner split_parts srnf
        srnf_distance srnf_geodesic srnf_invert srnf_path_length straight_path surface_area
        surface_basis tangent_pca upsample_coefficients validate_surface vector_field_basis
        vee""",
    "elastic_jax.io": """MESH_FORMATS DegenerateFaceError InconsistentWindingError MeshError
        NonManifoldVertexError NotGenusZeroError NotStarShapedError NotWatertightError
        ParametrizationError SphericalParametrization grid_to_mesh load_surface mesh_to_grid
        save_path save_surface spherical_parametrization star_center surface_files""",
    "elastic_jax.plot": """parametrization_colors plot_path plot_modes plot_energy
        plot_distance_matrix save_figure""",
    "elastic_jax.shapes": "sphere ellipsoid bumpy bent_cylinder sample random_rotation",
}


def test_the_public_api_is_pinned():
    import importlib

    for name, expected in PUBLIC.items():
        module = importlib.import_module(name)
        if name == "elastic_jax":
            found = {
                n
                for n in dir(module)
                if not n.startswith("_")
                and getattr(getattr(module, n), "__module__", "").startswith("elastic_jax")
            }
        else:
            found = set(module.__all__)
            assert all(hasattr(module, n) for n in found), name
        assert found == set(expected.split()), (name, found ^ set(expected.split()))


def test_every_error_is_an_input_error():
    # One hierarchy: the mesh errors and the command line's bad input are InputErrors,
    # which are ValueErrors.
    from elastic_jax import cli, io
    from elastic_jax._errors import InputError

    errors = [getattr(io, n) for n in io.__all__ if n.endswith("Error")] + [cli.BadInput]
    assert len(errors) == 9
    assert all(issubclass(e, InputError) and issubclass(e, ValueError) for e in errors)
