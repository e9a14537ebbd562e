"""README's example runs and prints the closed form; README and CI run the same test command;
the site's front page shows README's commands and example; every command line shown parses."""

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
    # the 25 x 49 discretization error (docs/math.md §3)
    assert abs(distance - closed) / closed < 5e-3
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
    for fence in ("```bash\n", "```python\n"):
        block = readme.split(fence)[1].split("```")[0]
        assert block in index, fence
    # README's links into the site point at pages that exist.
    links = re.findall(r"\]\((docs/[^)#]+)", readme)
    assert len(links) >= 8
    assert [link for link in links if not (ROOT / link).is_file()] == []
