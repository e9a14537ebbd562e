"""One driver for the collection jobs: Karcher means, distance matrices and metric fits
are iterations (init / step / terminate) run by one loop, ``run``, which owns the pool,
the checkpoint, the progress reports, the step limit, the non-finite stop and the
warning; the six keywords of how a job runs are one record, ``JobOptions``.

The driver is tested here on a job of its own (a counter, no solves), so that what the
loop promises is checked apart from any solver: a kill between two steps loses nothing
that was reported, a resume continues from the file, a foreign file is refused, and the
warning names the user's line. The three real jobs keep their own tests of the same
promises (tests/test_karcher.py, test_fit_metric.py, test_distributed.py).
"""

from __future__ import annotations

import ast
import inspect
import pathlib
import warnings
from typing import NamedTuple

import numpy as np
import pytest

import elastic_jax as ej
from elastic_jax._statistics.driver import Job, run

PACKAGE = pathlib.Path(__file__).resolve().parents[1] / "elastic_jax"
JOB_KEYWORDS = {"batch_size", "strategy", "checkpoint", "resume", "progress", "client"}
COLLECTIONS = {
    "karcher_mean": "_statistics/karcher.py",
    "distance_matrix": "_statistics/distances.py",
    "fit_metric": "_statistics/fit.py",
}


class _Record(NamedTuple):
    total: int
    converged: np.ndarray
    steps: int
    result: object


class _Counter(NamedTuple):
    """Adds 1, 2, 3, ... until the sum reaches ``goal`` (the driver stops it at its
    ``max_steps``); its value turns NaN once the sum passes ``poison``."""

    goal: int
    fingerprint: str = "counter"
    pool: object = None
    poison: float = np.inf

    def pool_inputs(self):
        return ()

    def restore(self, saved):
        return (int(saved["total"]), int(saved["steps"]))

    def init(self, saved, sink):
        return (0, 0)

    def step(self, state):
        total, steps = state
        return (total + steps + 1, steps + 1), True

    def steps(self, state):
        return state[1]

    def value(self, state):
        return np.nan if state[0] > self.poison else float(state[0])

    def terminate(self, state):
        return ej.RESULTS.successful if state[0] >= self.goal else None

    def arrays(self, state):
        return {"total": state[0], "steps": state[1]}

    def report(self, state, seconds):
        return {"total": state[0], "steps": state[1]}

    def result(self, state, code):
        return _Record(state[0], np.asarray(code == ej.RESULTS.successful), state[1], code)

    def warning(self, record):
        return f"counter: stopped at {record.total}"


def test_a_killed_job_resumes_from_its_last_report(tmp_path):
    path = tmp_path / "counter.npz"
    whole = run(_Counter(goal=20), max_steps=10)
    assert (whole.total, whole.steps) == (21, 6)  # 1 + 2 + ... + 6
    assert whole.result == ej.RESULTS.successful

    def kill_at_three(info):
        if info["steps"] == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run(_Counter(goal=20), ej.JobOptions(checkpoint=path, progress=kill_at_three), 10)
    saved = np.load(path)
    # The state the last report told of is on disk: nothing reported is lost.
    assert (int(saved["total"]), int(saved["steps"])) == (6, 3)
    reports = []
    options = ej.JobOptions(checkpoint=path, resume=True, progress=reports.append)
    resumed = run(_Counter(goal=20), options, max_steps=10)
    assert resumed[:3] == whole[:3] and resumed.result == whole.result
    # A resumed job reports the steps it takes, not the ones restored.
    assert [r["steps"] for r in reports] == [4, 5, 6]
    assert all(r["seconds"] >= 0 for r in reports)
    with pytest.raises(ej.InputError, match="other shapes or settings"):
        run(_Counter(goal=20, fingerprint="another"), ej.JobOptions(checkpoint=path, resume=True))


def test_an_unconverged_job_warns_at_the_callers_line():
    # The warning names the first line outside the package that led to it: here this
    # call (a user's call of karcher_mean, past the public wrapper and the job module).
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        line = inspect.currentframe().f_lineno + 1
        record = run(_Counter(goal=100), max_steps=2)
    assert (record.total, record.steps, bool(record.converged)) == (3, 2, False)
    assert ej.RESULTS.name(record.result) == "nonlinear_max_steps_reached"
    assert len(caught) == 1 and issubclass(caught[0].category, ej.ConvergenceWarning)
    assert str(caught[0].message) == "counter: stopped at 3"
    assert (caught[0].filename, caught[0].lineno) == (__file__, line)


def test_the_driver_stops_a_non_finite_job_and_refuses_what_is_not_a_job():
    # 1, 3, 6, 10: the value turns NaN after the fourth step, before the goal (21) and
    # before the step limit.
    with pytest.warns(ej.ConvergenceWarning, match="stopped at 10"):
        record = run(_Counter(goal=20, poison=8), max_steps=10)
    assert (record.total, record.steps) == (10, 4)
    assert ej.RESULTS.name(record.result) == "nonfinite"
    # Without a value that turns, the limit stops it, and before the goal.
    with pytest.warns(ej.ConvergenceWarning, match="stopped at 6"):
        assert run(_Counter(goal=20), max_steps=3).steps == 3

    class Partial(NamedTuple):
        fingerprint: str = "partial"
        pool: object = None

    assert not isinstance(Partial(), Job) and isinstance(_Counter(goal=1), Job)
    with pytest.raises(TypeError, match=r"not a Job .*'init'.*'terminate'"):
        run(Partial())


@pytest.mark.parametrize(
    "fields, message",
    [
        ({"strategy": "fast"}, "strategy"),
        ({"batch_size": 0}, "batch_size"),
        ({"batch_size": 2.5}, "batch_size"),
        ({"resume": "yes"}, "resume"),
        ({"progress": "print"}, "progress"),
        ({"checkpoint": 3}, "checkpoint"),
    ],
)
def test_bad_job_options_are_refused_naming_the_field(fields, message):
    with pytest.raises(ej.InputError, match=message):
        ej.JobOptions(**fields)
    with pytest.raises(TypeError, match="no field"):
        ej.JobOptions().replace(workers=2)
    for name in COLLECTIONS:
        with pytest.raises(ej.InputError, match="JobOptions"):
            getattr(ej, name)(np.zeros((3, 3, 13, 25)), ej.SplitMetric(1, 1, 0.1, 0), job={})


def test_the_three_collections_run_on_the_one_driver():
    for name, module in COLLECTIONS.items():
        parameters = inspect.signature(getattr(ej, name)).parameters
        assert parameters["job"].default is None
        assert not JOB_KEYWORDS & set(parameters), name
        tree = ast.parse((PACKAGE / module).read_text())
        # The one loop is the driver's: no job module iterates its steps itself.
        assert not [n for n in ast.walk(tree) if isinstance(n, ast.While)], module
        function = next(n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == name)
        calls = [
            n.func.id
            for n in ast.walk(function)
            if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)
        ]
        assert calls.count("run") == 1, name
    karcher = next(
        n
        for n in ast.parse((PACKAGE / COLLECTIONS["karcher_mean"]).read_text()).body
        if isinstance(n, ast.FunctionDef) and n.name == "karcher_mean"
    )
    source = (PACKAGE / COLLECTIONS["karcher_mean"]).read_text().splitlines()
    code = {
        line
        for statement in karcher.body[1:]  # the docstring is not code
        for line in range(statement.lineno, statement.end_lineno + 1)
        if source[line - 1].strip() and not source[line - 1].strip().startswith("#")
    }
    assert len(code) < 80
