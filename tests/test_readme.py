"""README's example runs and prints the closed form; README and CI run the same test command."""

import pathlib
import re

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_readme_example_prints_the_closed_form(capsys):
    text = (ROOT / "README.md").read_text()
    code = re.search(r"```python\n(.*?)```", text, re.S).group(1)
    assert len(code.strip().splitlines()) <= 15
    exec(compile(code, "README.md", "exec"), {})
    out = capsys.readouterr().out
    energy, closed = map(float, re.search(r"energy ([\d.]+), closed form ([\d.]+)", out).groups())
    assert abs(energy - closed) / closed < 2e-3  # the 50 x 99 discretization error (MATH.md 3)
    srnf = float(re.search(r"SRNF distance ([\d.]+)", out).group(1))
    assert abs(srnf - np.sqrt(4 * np.pi)) / np.sqrt(4 * np.pi) < 2e-3


def test_ci_runs_the_readme_test_command():
    readme = (ROOT / "README.md").read_text()
    ci_lines = (ROOT / ".ci" / "run").read_text().strip().splitlines()
    test_command = ci_lines[-1]
    assert test_command.startswith("python -m pytest")
    assert test_command in readme.split("# run the tests")[1].splitlines()[1]
