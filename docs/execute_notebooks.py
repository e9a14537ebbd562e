"""Execute the notebooks in place, so that the site shows their figures without running them.

    python docs/execute_notebooks.py            # every notebook
    python docs/execute_notebooks.py 03 05      # those whose names start so

The stored outputs are what the documentation renders (``nb_execution_mode = "off"``);
``tests/test_notebooks.py`` (slow tier) executes each notebook afresh and checks that the
results it prints agree with the stored ones, so a change that moves a figure's numbers
shows up there.
"""

import os
import pathlib
import sys
import time

import nbclient
import nbformat

NOTEBOOKS = pathlib.Path(__file__).resolve().parents[1] / "notebooks"
# The kernels inherit this environment. tests/test_notebooks.py runs them at the tests'
# XLA level (tests/conftest.py), and a Karcher stop or a rounding-sensitive minimum can
# fall differently at another level: store what the test will recompute.
_FLAGS = os.environ.get("XLA_FLAGS", "")
if "xla_backend_optimization_level" not in _FLAGS:
    os.environ["XLA_FLAGS"] = f"{_FLAGS} --xla_backend_optimization_level=1".strip()


def main(prefixes: list[str]) -> None:
    for path in sorted(NOTEBOOKS.glob("*.ipynb")):
        if prefixes and not any(path.name.startswith(p) for p in prefixes):
            continue
        start = time.perf_counter()
        nb = nbformat.read(path, as_version=4)
        nbclient.NotebookClient(nb, timeout=1800, kernel_name="python3").execute()
        # Execution counts and timings change on every run; keep the diff to real changes.
        for cell in nb.cells:
            cell.metadata.pop("execution", None)
        nbformat.write(nb, path)
        print(f"{path.name}: {time.perf_counter() - start:.0f} s", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
