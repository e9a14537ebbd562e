"""README's example runs and prints the closed form; README and CI run the same test command."""

import pathlib
import re

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_readme_example_prints_the_closed_form(capsys):
    text = (ROOT / "README.md").read_text()
    code = re.search(r"```python\n(.*?)```", text, re.S).group(1)
    assert len(code.strip().splitlines()) <= 15
    exec(compile(code, "README.md", "exec"), {})
    out = capsys.readouterr().out
    distance, closed = map(
        float, re.search(r"distance ([\d.]+), closed form ([\d.]+)", out).groups()
    )
    assert abs(distance - closed) / closed < 5e-3  # the 25 x 49 discretization error (MATH.md 3)
    energy, straight = map(
        float, re.search(r"energy ([\d.]+) < straight line ([\d.]+)", out).groups()
    )
    assert energy < 0.9 * straight


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

    readme = (ROOT / "README.md").read_text()
    lines = [
        line.split("#")[0]
        for block in re.findall(r"```bash\n(.*?)```", readme, re.S)
        for line in block.splitlines()
        if line.startswith("elastic-jax ")
    ]
    commands = {shlex.split(line)[1] for line in lines}
    assert {"pca", "shoot", "karcher", "distances"} <= commands
    parser = cli.build_parser()
    for line in lines:
        args = parser.parse_args(shlex.split(line)[1:])
        assert args.command in cli.COMMANDS, line
