"""The options protocol (issue 31): one record, ``ShapeOptions``, holds the path and solver
settings of every solve; each function that solves takes it as ``options=``, a keyword
changes one setting, and a limit has one name and one default wherever it appears.

The solves use the 13 x 25 configurations of tests/test_results.py (degree 3, N 5), so
that the suite's compilation cache already holds their programs.
"""

from __future__ import annotations

import dataclasses
import inspect

import numpy as np
import pytest

import elastic_jax as ej
from elastic_jax import shapes
from elastic_jax._options import FROM_OPTIONS, options_with

M, N = 13, 25
METRIC = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)
FAST = ej.ShapeOptions(degree=3, n_times=5)
FIELDS = {f.name for f in dataclasses.fields(ej.ShapeOptions)}
# Limits and settings that belong to one algorithm and keep their own meaning
# (docs/guides/settings.md,
# "Example"): Newton's tolerance and iterations, the Karcher iteration's.
OWN = {
    # geodesic's init is a warm start (coefficients), not the registration's search.
    "geodesic": {"init"},
    "shoot": {"tol"},
    "parallel_transport": {"tol"},
    "karcher_mean": {"max_steps", "tol", "init"},
}
TAKES_OPTIONS = (
    "geodesic",
    "shoot",
    "parallel_transport",
    "shape_geodesic",
    "log",
    "karcher_mean",
    "distance_matrix",
    "srnf_invert",
    "srnf_geodesic",
)


def _pair():
    return shapes.sample(shapes.sphere, M, N), shapes.sample(shapes.ellipsoid, M, N)


@pytest.mark.parametrize("name", TAKES_OPTIONS)
def test_every_solve_takes_the_record_and_no_keyword_has_a_default_of_its_own(name):
    parameters = inspect.signature(getattr(ej, name)).parameters
    assert parameters["options"].default is None
    shared = (FIELDS & set(parameters)) - OWN.get(name, set())
    for field in shared:
        # A second default for a record's field is what made geodesic's step limit 1000
        # against the record's 500.
        assert parameters[field].default is FROM_OPTIONS, (name, field)


def test_srnf_inversion_reads_the_record_with_its_own_precision_default():
    # The record's tol=None is each objective's own precision default: the SRNF
    # mismatch's is 1e-8 in float64 (inversion_tol), a geodesic's 1e-6.
    f1, f2 = _pair()
    q = ej.srnf(f2)
    by_keywords = ej.srnf_invert(q, degrees=(2,), solver="lbfgs", max_steps=40)
    by_record = ej.srnf_invert(q, degrees=(2,), options=FAST.replace(solver="lbfgs", max_steps=40))
    np.testing.assert_array_equal(np.asarray(by_record.surface), np.asarray(by_keywords.surface))
    assert int(by_record.num_steps) == int(by_keywords.num_steps)
    default = ej.srnf_invert(q, degrees=(2,))
    assert float(default.grad_norm) <= 1e-8
    # A record's tol is a tol: looser than the inversion's own default, fewer steps.
    loose = ej.srnf_invert(q, degrees=(2,), options=FAST.replace(tol=1e-3))
    assert 1e-8 < float(loose.grad_norm) <= 1e-3
    assert int(loose.num_steps) < int(default.num_steps)
    with pytest.raises(ej.InputError, match=r"srnf_geodesic: n_times=7 given.*n_times=5"):
        ej.srnf_geodesic(f1, f2, 7, options=FAST)


def test_a_record_and_its_keywords_give_the_same_geodesic():
    f1, f2 = _pair()
    by_keywords = ej.geodesic(f1, f2, METRIC, degree=3, n_times=5)
    by_record = ej.geodesic(f1, f2, METRIC, options=FAST)
    # A keyword that agrees with the record is accepted.
    both = ej.geodesic(f1, f2, METRIC, degree=3, options=FAST)
    for res in (by_record, both):
        assert float(res.distance) == float(by_keywords.distance)
        assert int(res.num_steps) == int(by_keywords.num_steps)
    # The record's step limit is the solve's (test_results.py's capped configuration).
    with pytest.warns(ej.ConvergenceWarning, match="stopped after 1 steps"):
        capped = ej.geodesic(f1, f2, METRIC, options=FAST.replace(max_steps=1))
    assert int(capped.num_steps) == 1 and not bool(capped.converged)


def test_a_record_and_its_keywords_give_the_same_shot_path_and_transport():
    f1, f2 = _pair()
    v = 0.2 * (f2 - f1)
    by_keywords = ej.shoot(f1, v, METRIC, degree=3, n_times=5)
    by_record = ej.shoot(f1, v, METRIC, options=FAST)
    np.testing.assert_array_equal(np.asarray(by_record.path), np.asarray(by_keywords.path))
    carried = ej.parallel_transport(v, by_record.path, METRIC, degree=3)
    carried_by_record = ej.parallel_transport(v, by_record.path, METRIC, options=FAST)
    np.testing.assert_array_equal(np.asarray(carried_by_record.vector), np.asarray(carried.vector))


def test_a_keyword_that_contradicts_the_record_is_refused():
    f1, f2 = _pair()
    with pytest.raises(ej.InputError, match=r"degree=5 given as a keyword.*degree=3"):
        ej.geodesic(f1, f2, METRIC, degree=5, options=FAST)
    with pytest.raises(ej.InputError, match=r"n_times=7 given as a keyword.*n_times=5"):
        ej.shoot(f1, f2 - f1, METRIC, n_times=7, options=FAST)
    with pytest.raises(ej.InputError, match="options must be an elastic_jax.ShapeOptions"):
        ej.geodesic(f1, f2, METRIC, options={"degree": 3})


def test_shape_geodesic_log_and_warmup_refuse_a_contradicting_keyword_as_geodesic_does():
    """One rule beside the record everywhere (issue 53): the keyword changes of
    shape_geodesic, log and warmup no longer apply on top of a record that says
    otherwise. Refused before any solve, with geodesic's message."""
    f1 = shapes.sample(shapes.sphere, M, N)
    f2 = shapes.sample(shapes.ellipsoid, M, N)
    with pytest.raises(ej.InputError) as by_geodesic:
        ej.geodesic(f1, f2, METRIC, degree=5, options=FAST)
    expected = str(by_geodesic.value).removeprefix("geodesic: ")
    assert expected.startswith("degree=5 given as a keyword, and options has degree=3")
    calls = {
        "shape_geodesic": lambda: ej.shape_geodesic(f1, f2, METRIC, degree=5, options=FAST),
        "log": lambda: ej.log(f1, f2, METRIC, degree=5, options=FAST),
        "warmup": lambda: ej.warmup((M, N), degree=5, options=FAST),
    }
    for name, call in calls.items():
        with pytest.raises(ej.InputError) as refused:
            call()
        assert str(refused.value) == f"{name}: {expected}"
    with pytest.raises(TypeError, match="no field"):
        ej.log(f1, f2, METRIC, degrees=3, options=FAST)


def test_an_agreeing_keyword_beside_the_record_is_accepted():
    """An equal value (also in another form: a grid as a list) passes the rule; shown
    without a solve by the first error after it (the pair's dtypes, warmup's grid)."""
    f1 = shapes.sample(shapes.sphere, M, N)
    f2 = shapes.sample(shapes.ellipsoid, M, N).astype(np.float32)
    record = FAST.replace(grid=(M, N))
    with pytest.raises(ej.InputError, match="share one dtype"):
        ej.shape_geodesic(f1, f2, METRIC, degree=3, grid=[M, N], options=record)
    with pytest.raises(ej.InputError, match="input_grid must be"):
        ej.warmup((M, 4), n_times=5, options=FAST)
    assert options_with("f", record, {"degree": 3, "grid": [M, N]}) == record
    # Without a record a keyword sets that field of the default one.
    assert options_with("f", None, {"degree": 5}) == ej.ShapeOptions(degree=5)
    assert options_with("f", FAST, {}) is FAST


def test_the_levels_stop_their_rounds_at_a_fifth_of_rtol():
    # A level's distance is asked to rtol; rounds that change the energy by less than
    # rtol / 5 no longer move it at that scale (docs/guides/settings.md).
    default = ej.ShapeOptions()
    assert default.round_stop == default.outer_tol == 1e-3
    level = default.on_level((25, 49))
    assert level.rounds_tol == pytest.approx(0.03 / 5) and level.round_stop == level.rounds_tol
    assert level.outer_tol == default.outer_tol  # the coarse rounds and checks keep theirs
    assert ej.ShapeOptions(rtol=1e-4).on_level((25, 49)).round_stop == 1e-3
    assert ej.ShapeOptions(rounds_tol=2e-3).on_level((25, 49)).round_stop == 2e-3
    one_grid = ej.ShapeOptions(grid=(25, 49))
    assert one_grid.on_level((25, 49)).round_stop == 1e-3
    with pytest.raises(ej.InputError, match="rounds_tol must be a positive finite number"):
        ej.ShapeOptions(rounds_tol=0.0)


def test_each_level_takes_its_own_diff_step_degree():
    levels = ((13, 25), (25, 49), (49, 97))
    options = ej.ShapeOptions(levels=levels, level_vf_degrees=[6, 12, 24])
    assert options.level_vf_degrees == (6, 12, 24)
    assert [options.on_level(grid).vf_degree for grid in levels] == [6, 12, 24]
    # A grid that is not a level, and one working grid, keep vf_degree.
    assert options.on_level((9, 17)).vf_degree == options.vf_degree == 8
    assert options.replace(rtol=None).on_level((25, 49)).vf_degree == 8
    assert ej.ShapeOptions().on_level((49, 97)).vf_degree == 8
    with pytest.raises(ej.InputError, match="one degree per level: 3 levels, got 2"):
        ej.ShapeOptions(levels=levels, level_vf_degrees=(6, 12))
    with pytest.raises(ej.InputError, match="level_vf_degrees"):
        ej.ShapeOptions(levels=levels, level_vf_degrees=(6, 0, 24))
    # A degree beyond what a level's grid holds (min(m - 3, (n - 3) // 2): 10 at 13 x 25)
    # is refused before any solve, naming the level.
    f = shapes.sample(shapes.sphere, 13, 25)
    too_fine = ej.ShapeOptions(levels=levels, level_vf_degrees=(11, 12, 24))
    with pytest.raises(ej.InputError, match="the 13 x 25 level: vf_degree"):
        ej.shape_geodesic(f, f, METRIC, options=too_fine)
    with pytest.raises(ej.InputError, match="the 13 x 25 level: vf_degree"):
        ej.distance_matrix(np.stack([f, 1.5 * f]), METRIC, options=too_fine)
