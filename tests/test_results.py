"""The result protocol (issue 31): every result record carries ``converged``, ``result`` (an
``elastic_jax.RESULTS``, printed by name), ``message`` and ``num_steps``, and they agree:
converged exactly when the code is a converged one, a message exactly when it is not
(a Karcher mean always says which criterion stopped it), and ``num_steps`` the sum of the
solves the record is made of, counted independently.

One case per record, converged and (where a limit forces it cheaply) not, at 13 x 25 in
the configurations of tests/test_karcher.py, test_shooting.py, test_transport.py and
test_srnf_inverse.py: the same compiled programs (the suite's compilation cache holds
them), so that the protocol costs little more than the solves themselves.
"""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import elastic_jax as ej
from elastic_jax import io, shapes

M, N = 13, 25
METRIC = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)
FAST = ej.ShapeOptions(degree=3, n_times=5)
SHAPE = ej.ShapeOptions(degree=4, vf_degree=4, n_times=5, rtol=None)
KARCHER_CONVERGED = {"distances_at_rounding", "mean_velocity_small", "sum_sq_stalled"}


def _pair():
    return shapes.sample(shapes.sphere, M, N), shapes.sample(shapes.ellipsoid, M, N)


def _quiet(call):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ej.ConvergenceWarning)
        return call()


def _geodesic(**changes):
    f1, f2 = _pair()
    res = _quiet(lambda: ej.geodesic(f1, f2, METRIC, degree=3, n_times=5, **changes))
    return res, int(res.num_steps)


def _shape_geodesic():
    f1 = shapes.sample(shapes.sphere, M, N)
    f2 = shapes.sample(shapes.sphere, M, N, radius=2.0, rotation=shapes.random_rotation(3))
    res = ej.shape_geodesic(f1, f2, METRIC, modulo="rigid", options=SHAPE)
    return res, None  # its steps are the rounds' and the final solves', counted inside


def _shoot():
    f1, f2 = _pair()
    res = ej.shoot(f1, 0.2 * (f2 - f1), METRIC, degree=3, n_times=5)
    return res, int(np.sum(res.newton_steps))


def _transport():
    f1, f2 = _pair()
    path = ej.straight_path(f1, f2, 5)
    res = ej.parallel_transport(0.1 * (f2 - f1), path, METRIC, degree=3)
    return res, None


def _srnf_invert(degrees=(2, 3), **changes):
    f = shapes.sample(shapes.ellipsoid, M, N)
    res = _quiet(lambda: ej.srnf_invert(ej.srnf(f), degrees=degrees, **changes))
    return res, None


def _srnf_geodesic(**changes):
    f1, f2 = _pair()
    res = _quiet(lambda: ej.srnf_geodesic(f1, f2, 5, degrees=(2, 4), **changes))
    return res, int(np.sum(res.node_steps))


def _log():
    f1, f2 = _pair()
    res = ej.log(f1, f2, METRIC, options=FAST)
    return res, int(ej.geodesic(f1, f2, METRIC, **FAST.geodesic_kwargs()).num_steps)


def _karcher(**changes):
    spheres = jnp.stack([shapes.sample(shapes.sphere, M, N, radius=r) for r in (1.0, 1.5, 2.2)])
    res = _quiet(lambda: ej.karcher_mean(spheres, METRIC, modulo="none", options=FAST, **changes))
    return res, None


def _distance_matrix():
    f1, f2 = _pair()
    coll = jnp.stack([f1, f2, 1.5 * f1])
    res = ej.distance_matrix(coll, METRIC, modulo="none", options=FAST)
    singles = [
        ej.geodesic(coll[i], coll[j], METRIC, **FAST.geodesic_kwargs())
        for i, j in [(0, 1), (0, 2), (1, 2)]
    ]
    return res, sum(int(s.num_steps) for s in singles)


def _fit_metric(**changes):
    coll = jnp.stack(
        [
            shapes.sample(shapes.bent_cylinder, M, N, curvature=k, half_length=h)
            for k, h in [(0.1, 1.0), (0.1, 1.4), (0.5, 1.0), (0.5, 1.4)]
        ]
    )
    res = _quiet(
        lambda: ej.fit_metric(
            coll,
            [0, 0, 1, 1],
            modulo="none",
            options=FAST,
            **changes,
            job=ej.JobOptions(strategy="loop"),
        )
    )
    return res, None


def _sphere_map():
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=2)
    mesh.vertices *= np.asarray([1.0, 1.2, 0.8])
    res = io.spherical_parametrization(mesh, frame="input")  # symmetric: no principal frame
    return res, None


CASES = {
    "geodesic": (_geodesic, "successful"),
    "geodesic capped": (lambda: _geodesic(max_steps=1), "nonlinear_max_steps_reached"),
    "shape_geodesic": (_shape_geodesic, "successful"),
    "shoot": (_shoot, "successful"),
    "parallel_transport": (_transport, "successful"),
    "srnf_invert": (_srnf_invert, "successful"),
    "srnf_invert capped": (
        lambda: _srnf_invert(degrees=(2,), max_steps=2),
        "nonlinear_max_steps_reached",
    ),
    "srnf_geodesic": (_srnf_geodesic, "successful"),
    "srnf_geodesic capped": (lambda: _srnf_geodesic(max_steps=2), "nonlinear_max_steps_reached"),
    "log": (_log, "successful"),
    "karcher_mean": (_karcher, "mean_velocity_small"),
    "karcher_mean capped": (lambda: _karcher(max_steps=0), "nonlinear_max_steps_reached"),
    "distance_matrix": (_distance_matrix, "successful"),
    "spherical_parametrization": (_sphere_map, "successful"),
    "fit_metric": (_fit_metric, "successful"),
    "fit_metric capped": (lambda: _fit_metric(max_steps=0), "nonlinear_max_steps_reached"),
}


# The transport and shooting cases (35 s and 45 s on 2 cores: configurations of their
# own) run in the slow tier.
SLOW_CASES = {"parallel_transport", "shoot"}


@pytest.mark.parametrize(
    "case",
    [pytest.param(c, marks=pytest.mark.slow) if c in SLOW_CASES else c for c in CASES],
)
def test_every_result_record_follows_the_protocol(case):
    make, expected = CASES[case]
    res, steps = make()
    # The code: an item of elastic_jax.RESULTS, printed by its name.
    assert isinstance(res.result, ej.RESULTS)
    name = ej.RESULTS.name(res.result)
    assert name == expected, (name, res.message)
    assert repr(res.result).startswith(f"elastic_jax.RESULTS<{name}")
    # converged exactly when the code is a converged one.
    karcher = isinstance(res, ej.KarcherResult)
    converged_codes = KARCHER_CONVERGED if karcher else {"successful"}
    assert bool(np.all(res.converged)) == (name in converged_codes)
    # converged: a 0-d bool array in every record (issue 53), not a Python bool.
    assert np.asarray(res.converged).dtype == np.bool_ and np.ndim(res.converged) == 0
    assert not isinstance(res.converged, bool)
    # A message exactly when it did not converge; a Karcher mean names its criterion.
    assert isinstance(res.message, str)
    if karcher:
        assert res.message.startswith("converged" if res.converged else "stopped")
    else:
        assert (res.message == "") == (name == "successful"), res.message
    # num_steps: a count, and the sum of the record's own solves where they are listed.
    assert int(res.num_steps) >= (1 if name == "successful" and not karcher else 0)
    if steps is not None:
        assert int(res.num_steps) == steps


# --- How records print (issue 48): at most 2,000 characters, arrays as dtype[shape] -------


def _f64(*shape):
    return jnp.linspace(0.0, 1.0, int(np.prod(shape))).reshape(shape)


def _scalar(value):
    return jnp.asarray(value)


def _shape_geodesic_record():
    """A ShapeGeodesicResult with the arrays of a solve at 25 x 49 with N = 13 (the size of
    the issue's 40k-character repr), built without a solve."""
    refinement = ej.Refinement(_scalar(0.7366), _scalar(0.7412), _scalar(0.0083))
    return ej.ShapeGeodesicResult(
        path=_f64(13, 3, 25, 49),
        distance=_scalar(0.7351234),
        energy=_scalar(0.7351234**2),
        parametrized_distance=_scalar(1.2034),
        f1_registered=_f64(3, 25, 49),
        gamma=_f64(3, 25, 49),
        rotation=jnp.eye(3),
        coefficients=_f64(11, 3 * ((4 + 1) ** 2 - 1)),
        parametrized_coefficients=_f64(11, 3 * ((4 + 1) ** 2 - 1)),
        energy_history=_f64(12),
        rounds=_scalar(7),
        num_steps=_scalar(412),
        converged=_scalar(True),
        result=ej.RESULTS.successful,
        grad_norm=_scalar(3.1e-9),
        min_curvature=_scalar(0.42),
        refinement=refinement,
        levels=None,
    )


def _metric_fit():
    metric, start = ej.SplitMetric(0.4, 0.3, 0.2, 0.1), ej.SplitMetric(0.25, 0.25, 0.25, 0.25)
    k = 4
    return ej.MetricFit(
        metric=metric,
        initial_metric=start,
        objective_before=_scalar(0.61),
        objective_after=_scalar(0.4321),
        history=_f64(21),
        grad_norm=_scalar(2e-7),
        gradient=_f64(4),
        distances=_f64(k, k),
        distances_before=_f64(k, k),
        pairs_converged=jnp.ones((k, k), bool),
        grids=jnp.full((k, k, 2), 13, jnp.int32),
        converged=_scalar(True),
        result=ej.RESULTS.successful,
        num_steps=_scalar(9),
        evaluations=_scalar(10),
    )


def _mesh_records():
    from elastic_jax._meshes.frame import MeshFrame
    from elastic_jax._meshes.sphere_map import SphericalParametrization

    v, f = np.linspace(0.0, 1.0, 642 * 3).reshape(642, 3), np.zeros((1280, 3), np.int64)
    frame = MeshFrame(np.zeros(3), 1.25, np.eye(3), np.full(3, 1 / 3), np.zeros(3), "x" * 300)
    sphere_map = SphericalParametrization(v, f, v, 0, 1.84, 1.52, 6.25, 2.0871, 311, 4.2, True)
    return {"MeshFrame": frame, "SphericalParametrization": sphere_map}


def _records():
    """Every public result record: real solves where they are cheap (the 13 x 25 geodesic
    of the protocol test above: compiled once), else built with realistic arrays. Each with
    the texts its repr must show."""
    n = (M, N)
    geodesic = _geodesic()[0]
    surface, path5 = _f64(3, *n), _f64(5, 3, *n)
    ok, successful = _scalar(True), ej.RESULTS.successful
    records = {
        "GeodesicResult": (geodesic, ["f64[5,3,13,25]", f"{float(geodesic.distance):.6g}"]),
        "ShapeGeodesicResult": (_shape_geodesic_record(), ["f64[13,3,25,49]", "0.735123"]),
        "Refinement": (
            ej.Refinement(_scalar(0.7366), _scalar(0.7412), _f64(3)),
            ["distance_time=0.7366", "relative_change=f64[3]"],
        ),
        "ShootingResult": (
            ej.ShootingResult(
                path5,
                surface,
                surface,
                _f64(4),
                _f64(3),
                _f64(3, 45),
                jnp.full(3, 4),
                _scalar(5),
                ok,
                successful,
                _scalar(12),
            ),
            ["path=f64[5,3,13,25]", "newton_steps=i64[3]", "n_valid=5"],
        ),
        "TransportResult": (
            ej.TransportResult(
                vector=surface,
                vectors=path5,
                norms=_f64(5),
                norm_drift=_scalar(-1.5e-4),
                residuals=_f64(4, 2),
                n_valid=_scalar(5),
                converged=ok,
                result=successful,
                num_steps=_scalar(17),
                frame=_f64(2, 3, 11, 24),
            ),
            ["vectors=f64[5,3,13,25]", "norm_drift=-0.00015"],
        ),
        "LogResult": (
            ej.LogResult(
                velocity=surface,
                target=surface,
                distance=_scalar(0.5123),
                path=path5,
                converged=ok,
                result=successful,
                num_steps=_scalar(30),
                frames=_f64(2, 2, 3, 11, 24),
                path_frames=_f64(5, 2, 3, 11, 24),
                base=surface,
                levels=None,
            ),
            ["path=f64[5,3,13,25]", "distance=0.5123", "frames=f64[2,2,3,11,24]", "levels=None"],
        ),
        "SrnfInversion": (
            ej.SrnfInversion(
                surface=surface,
                residual=_scalar(0.0123),
                relative_residual=_scalar(0.004),
                coefficients=_f64(45),
                num_steps=_scalar(80),
                converged=ok,
                result=successful,
                grad_norm=_scalar(1e-8),
                level_residuals=_f64(2),
            ),
            ["surface=f64[3,13,25]", "residual=0.0123"],
        ),
        "SrnfGeodesic": (
            ej.SrnfGeodesic(
                path5,
                _f64(5),
                _f64(5),
                _scalar(1.234),
                _scalar(1.2),
                jnp.zeros(5, int),
                jnp.array([True, True, False, True, True]),
                _scalar(False),
                ej.RESULTS.nonlinear_max_steps_reached,
                _scalar(40),
            ),
            [
                "srnf_distance=1.2",
                "nodes_converged=bool[5](4 of 5 True)",
                "result=nonlinear_max_steps_reached",
            ],
        ),
        "KarcherResult": (
            ej.KarcherResult(
                mean=surface,
                distances=_f64(3),
                registered=_f64(3, 3, *n),
                velocities=_f64(3, 3, *n),
                geodesics_converged=jnp.ones(3, bool),
                geodesics_resolution_limited=jnp.zeros(3, bool),
                history=np.zeros((5, 3)),
                converged=True,
                num_steps=4,
                num_solves=6,
                result=ej.RESULTS.mean_velocity_small,
                level_distances=None,
            ),
            ["history=f64[5,3]", "num_steps=4", "result=mean_velocity_small"],
        ),
        "DistanceMatrixResult": (
            ej.DistanceMatrixResult(
                _f64(30, 30),
                jnp.ones((30, 30), bool),
                _f64(30, 30),
                _f64(30, 30),
                jnp.zeros((30, 30, 2), jnp.int32),
                _f64(30, 30),
                ok,
                successful,
                _scalar(9000),
            ),
            ["distances=f64[30,30]", "pairs_converged=bool[30,30](all True)"],
        ),
        "TangentPCA": (
            ej.TangentPCA(surface, _f64(4, 3, *n), _f64(4), _f64(4), _f64(6, 4), surface),
            ["modes=f64[4,3,13,25]", "scores=f64[6,4]"],
        ),
        "MetricFit": (_metric_fit(), ["metric=SplitMetric(a=0.4", "objective_after=0.4321"]),
        "RetrievalScores": (
            ej.RetrievalScores(2 / 3, 0.48333333333333334, 0.9333333333333335),
            ["nearest_neighbour=0.666667", "second_tier=0.933333"],
        ),
    }
    records["Levels"] = (
        ej.Levels(
            jnp.asarray([[13, 25], [25, 49], [49, 97]], jnp.int32),
            jnp.asarray([0.8, 0.9, 0.92]),
            jnp.asarray([0.8, 0.95, 0.92]),
            jnp.asarray([0.9, 0.97, 0.93]),
            jnp.asarray([10.0, 20.0, 60.0]),
            _scalar(0.0217),
            _scalar(0.03),
            jnp.asarray([0.92, 0.95]),
            _scalar(0.0326),
        ),
        ["grids=i32[3,2]", "estimate=0.0217", "rtol=0.03", "spread=0.0326"],
    )
    for name, record in _mesh_records().items():
        records[name] = (record, ["f64[642,3]" if name != "MeshFrame" else "scale=1.25"])
    return records


def _bespoke_repr(name: str) -> bool:
    """Whether the class prints the package's way (its __repr__ is record_repr)."""
    import elastic_jax._meshes.frame
    import elastic_jax._meshes.sphere_map
    from elastic_jax._results import record_repr

    for module in (ej, elastic_jax._meshes.frame, elastic_jax._meshes.sphere_map):
        if hasattr(module, name):
            return getattr(module, name).__repr__ is record_repr
    return False


RECORDS = [
    "GeodesicResult", "ShapeGeodesicResult", "Refinement", "ShootingResult", "TransportResult",
    "LogResult", "SrnfInversion", "SrnfGeodesic", "KarcherResult", "DistanceMatrixResult",
    "TangentPCA", "MetricFit", "RetrievalScores", "MeshFrame", "SphericalParametrization",
    "Levels",
]  # fmt: skip


@pytest.mark.parametrize("name", RECORDS)
def test_every_result_record_prints_briefly(name):
    assert _bespoke_repr(name), f"{name} does not set __repr__ = record_repr"
    record, expected = _records()[name]
    text = repr(record)
    assert len(text) <= 2000, (len(text), text[:300])
    assert text.startswith(f"{name}("), text[:100]
    assert str(record) == text  # print() shows the same
    for field in type(record)._fields:
        assert f"{field}=" in text, (field, text)
    if hasattr(record, "result"):  # the result protocol: both, the code by its name
        assert "converged=" in text and f"result={ej.RESULTS.name(record.result)}" in text
    for part in expected:
        assert part in text, (part, text)
    # Scalars by value, the distance-like ones included.
    for field in ("distance", "energy", "parametrized_distance", "objective_after"):
        if field in type(record)._fields:
            assert f"{field}={float(getattr(record, field)):.6g}" in text, text


def test_batched_and_traced_records_print_as_summaries():
    """A vmapped record prints its codes and flags as counts; a traced one its shapes."""

    def solved(ok):
        res = _shape_geodesic_record()
        code = ej.RESULTS.where(ok, ej.RESULTS.successful, ej.RESULTS.resolution_limited)
        return res._replace(converged=ok, result=code)

    batch = jax.vmap(solved)(jnp.array([True, False, True]))
    text = repr(batch)
    assert len(text) <= 2000
    assert "path=f64[3,13,3,25,49]" in text and "distance=f64[3]" in text
    assert "converged=bool[3](2 of 3 True)" in text
    assert "result=RESULTS[3](2 successful, 1 resolution_limited)" in text
    traced = []
    jax.vmap(lambda res: traced.append(repr(res)) or res.distance)(batch)
    jax.jit(lambda res: traced.append(repr(res)) or res.distance)(batch)
    assert "path=f64[13,3,25,49]" in traced[0] and "converged=bool[]" in traced[0]
    assert "result=RESULTS(traced)" in traced[0] and "refinement=Refinement(" in traced[0]
    assert "result=RESULTS[3](traced)" in traced[1] and "distance=f64[3]" in traced[1]


def test_every_result_record_shares_one_status_protocol():
    """Every record with a ``converged`` field gets ``message`` and its repr from one place
    (``status_record``): no hand-written message property, the code's words from RESULTS;
    and one code per cause: a step limit is ``nonlinear_max_steps_reached`` everywhere."""
    import ast
    import pathlib

    from elastic_jax import _results

    records = [
        obj
        for module in (ej, io)
        for obj in vars(module).values()
        if isinstance(obj, type) and "converged" in getattr(obj, "_fields", ())
    ]
    assert len(records) == 11
    for cls in records:
        assert isinstance(vars(cls)["message"], property), cls.__name__
        assert cls.__repr__ is _results.record_repr, cls.__name__
        # One order: the protocol's fields end every record (a mesh's map derives
        # result and num_steps from its own fields).
        held = [k for k in ("converged", "result", "num_steps") if k in cls._fields]
        assert list(cls._fields[-len(held) :]) == held, cls.__name__
    # A record that breaks the order or the annotation is refused where it is defined.
    from typing import NamedTuple

    from jaxtyping import Array, Bool, Int

    class Misordered(NamedTuple):
        converged: Bool[Array, ""]
        result: ej.RESULTS
        num_steps: Int[Array, ""]
        extra: int

    class Misannotated(NamedTuple):
        converged: Array
        result: ej.RESULTS
        num_steps: Int[Array, ""]

    with pytest.raises(TypeError, match=r"must end the record in that order"):
        _results.status_record(Misordered)
    with pytest.raises(TypeError, match=r"converged must be annotated Bool\[Array"):
        _results.status_record(Misannotated)
    # Karcher's words are RESULTS' words: a converged criterion prints them unchanged, a
    # stop says "stopped: " before them.
    mean = np.zeros((3, M, N))
    for name in ("distances_at_rounding", "mean_velocity_small", "sum_sq_stalled"):
        code = getattr(ej.RESULTS, name)
        record = ej.KarcherResult(
            mean=mean,
            distances=[],
            registered=[],
            velocities=[],
            geodesics_converged=[],
            geodesics_resolution_limited=[],
            history=[],
            converged=np.asarray(True),
            num_steps=2,
            num_solves=3,
            result=code,
            level_distances=None,
        )
        assert record.message == ej.RESULTS.message(code) and record.message
    code = ej.RESULTS.line_search_failed
    record = ej.KarcherResult(
        mean=mean,
        distances=[],
        registered=[],
        velocities=[],
        geodesics_converged=[],
        geodesics_resolution_limited=[],
        history=[],
        converged=np.asarray(False),
        num_steps=2,
        num_solves=3,
        result=code,
        level_distances=None,
    )
    assert record.message == "stopped: " + ej.RESULTS.message(code)
    package = pathlib.Path(ej.__file__).parent
    limits = sorted(
        str(path.relative_to(package))
        for path in package.rglob("*.py")
        for node in ast.walk(ast.parse(path.read_text()))
        if isinstance(node, ast.Attribute) and node.attr == "max_steps_reached"
    )
    assert limits == []
