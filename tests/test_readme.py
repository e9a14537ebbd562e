"""README's examples run: the closed form, and (slow) a shape distance converged at the defaults;
README and CI run the same test command; the site's front page shows README's commands and
examples; every command line shown parses."""

import pathlib
import re

import numpy as np
import pytest

import elastic_jax as ej

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _readme_examples() -> tuple[str, str]:
    first, second = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), re.S)
    return first, second


def _run_first_example(capsys) -> dict:
    """README's first block, run: it prints the spheres' distance against its closed form
    and a bent cylinder's geodesic energy below the straight line's."""
    first, _ = _readme_examples()
    assert len(first.strip().splitlines()) <= 15
    namespace = {}
    exec(compile(first, "README.md", "exec"), namespace)
    out = capsys.readouterr().out
    distance, closed = map(
        float, re.search(r"distance ([\d.]+), closed form ([\d.]+)", out).groups()
    )
    # the 25 x 49 discretization error (docs/math.md §3)
    assert abs(distance - closed) / closed < 5e-3
    energy, straight = map(
        float, re.search(r"energy ([\d.]+) < straight line ([\d.]+)", out).groups()
    )
    assert energy < 0.9 * straight
    return namespace


def test_readme_first_example_prints_the_closed_form_and_a_lower_energy(capsys):
    _run_first_example(capsys)


# About 150 s on 2 cores (210 s beside another test worker): both default levels' programs
# compile and 49 x 97 solves. The default tier resolves distances on small levels
# (tests/test_levels.py).
@pytest.mark.slow
def test_readme_second_example_prints_a_shape_distance_converged_at_the_defaults(capsys):
    namespace = _run_first_example(capsys)
    _, second = _readme_examples()
    # The second block continues the first: a shape distance resolved at the defaults.
    exec(compile(second, "README.md", "exec"), namespace)
    out = capsys.readouterr().out
    res = namespace["res"]
    assert bool(res.converged) and res.result == ej.RESULTS.successful
    assert out.strip() == repr(res) and len(out) <= 2000
    levels = np.asarray(res.levels.distances)
    assert abs(levels[-1] - levels[-2]) <= 0.03 * levels[-1]
    # The comment's figures are this run's, to the printed digits.
    claimed, agree = map(
        float, re.search(r"# distance ([\d.]+), converged: .* within ([\d.]+) %", second).groups()
    )
    assert float(res.distance) == pytest.approx(claimed, abs=1e-5)
    assert 100 * float(res.levels.estimate) == pytest.approx(agree, abs=0.05)


def test_ci_runs_the_readme_test_command():
    readme = (ROOT / "README.md").read_text()
    ci_lines = (ROOT / ".ci" / "run").read_text().strip().splitlines()
    test_command = ci_lines[-1]
    assert test_command.startswith("python -m pytest")
    assert test_command in readme.split("# run the tests")[1].splitlines()[1]


def test_readme_first_command_is_the_installed_demo():
    import importlib
    import tomllib

    readme = (ROOT / "README.md").read_text()
    first = readme.split("```bash\n")[1].splitlines()
    install = next(line for line in first if line.startswith("python -m pip install"))
    assert install.endswith("elastic-jax demo --out demo")
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    module, name = scripts["elastic-jax"].split(":")
    main = getattr(importlib.import_module(module), name)
    assert "demo" in main.__globals__["COMMANDS"]


def test_readme_command_lines_parse():
    """Every ``elastic-jax ...`` line README shows is accepted by the parser (no flag or
    command that was renamed or never existed)."""
    import shlex

    from elastic_jax import cli

    pages = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    lines = [
        line.split("#")[0]
        for page in pages
        for block in re.findall(r"```bash\n(.*?)```", page.read_text(), re.S)
        for line in block.splitlines()
        if line.startswith("elastic-jax ")
    ]
    commands = {shlex.split(line)[1] for line in lines}
    assert {"pca", "shoot", "karcher", "distances"} <= commands
    parser = cli.build_parser()
    for line in lines:
        args = parser.parse_args(shlex.split(line)[1:])
        assert args.command in cli.COMMANDS, line


def test_readme_is_short_and_the_site_front_page_repeats_it():
    readme = (ROOT / "README.md").read_text()
    assert len(readme) <= 8000  # the pitch, the commands, the example; the rest is the site
    index = (ROOT / "docs" / "index.md").read_text()
    # The install-and-test commands and both examples (the site's own build command is
    # on its contributing page).
    blocks = [readme.split("```bash\n")[1], *readme.split("```python\n")[1:]]
    for block in blocks:
        assert block.split("```")[0] in index
    # README's links into the site point at pages that exist.
    links = re.findall(r"\]\((docs/[^)#]+)", readme)
    assert len(links) >= 8
    assert [link for link in links if not (ROOT / link).is_file()] == []
