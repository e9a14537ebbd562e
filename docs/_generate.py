"""The site's generated parts: the public names, the command-line reference, the gallery's tables.

Imported by conf.py and by tests/test_docs.py; nothing here solves anything.
"""

from __future__ import annotations

import argparse
import importlib
import io as _io
import json
import os
import pathlib
import re

# The modules whose public names the API reference must cover (``__all__`` of each).
PUBLIC_MODULES = (
    "elastic_jax",
    "elastic_jax.io",
    "elastic_jax.plot",
    "elastic_jax.shapes",
    "elastic_jax.datasets",
)


def public_names() -> list[str]:
    """Every public name, fully qualified (``elastic_jax.io.mesh_to_grid``)."""
    names = []
    for module_name in PUBLIC_MODULES:
        module = importlib.import_module(module_name)
        names += [f"{module_name}.{name}" for name in module.__all__]
    return names


# The API reference: docs/api/index.md (the summary tables) and one page per group, listed in
# the index's toctree. A page's entries are its autodoc directives (".. autofunction:: name").
_DIRECTIVE = re.compile(r"^\.\. auto(?:function|class|exception|data)::\s+(\S+)\s*$", re.M)
_TOCTREE = re.compile(r"```\{toctree\}\n(.*?)```", re.S)


def api_pages(api: pathlib.Path) -> list[str]:
    """The group pages of the API reference, in the order of ``api/index.md``'s toctree."""
    block = _TOCTREE.search((api / "index.md").read_text()).group(1)
    return [line.strip() for line in block.splitlines() if line.strip() and ":" not in line]


def api_entries(api: pathlib.Path) -> dict[str, list[str]]:
    """The names each page of the API reference documents, page by page, in page order."""
    return {page: _DIRECTIVE.findall((api / f"{page}.md").read_text()) for page in api_pages(api)}


# Where a new public name of elastic_jax belongs, by the module that defines it (first
# match); io, plot and shapes have a page each. Only the missing-entry message uses it.
_PAGE_OF_DEFINITION = (
    ("elastic_jax._geometry.metric", "metric"),
    ("elastic_jax._geometry.differential", "metric"),
    ("elastic_jax._geometry.energy", "geodesics"),
    ("elastic_jax._geodesics.geodesic", "geodesics"),
    ("elastic_jax._registration.warmup", "runtime"),
    ("elastic_jax._registration", "registration"),
    ("elastic_jax._geometry.reparam", "registration"),
    ("elastic_jax._geometry.so3", "registration"),
    ("elastic_jax._geometry.srnf", "shooting"),
    ("elastic_jax._geodesics", "shooting"),
    ("elastic_jax._statistics.log", "shooting"),
    ("elastic_jax._statistics", "statistics"),
    ("elastic_jax._geometry", "discretization"),
    ("elastic_jax._runtime", "runtime"),
    ("elastic_jax._options", "records"),
)


def api_page_for(name: str) -> str:
    """The page of the API reference a public name belongs on (``docs/api/io.md``)."""
    module_name, _, attr = name.rpartition(".")
    if module_name != "elastic_jax":
        return f"docs/api/{module_name.rpartition('.')[2]}.md"
    obj = getattr(importlib.import_module(module_name), attr)
    defined = getattr(obj, "__module__", "") or ""
    solver = defined.startswith(("elastic_jax._geodesics", "elastic_jax._statistics"))
    if defined == "elastic_jax" or (isinstance(obj, type) and issubclass(obj, Warning)):
        page = "errors"  # the error classes and the result codes
    elif isinstance(obj, type) and issubclass(obj, Exception):
        page = "errors"
    elif hasattr(obj, "_fields") and (solver or defined.endswith(".records")):
        page = "records"  # a solve's record (a NamedTuple)
    else:
        page = next((p for prefix, p in _PAGE_OF_DEFINITION if defined.startswith(prefix)), "index")
    return f"docs/api/{page}.md"


def _first_sentence(text: str) -> str:
    """The first sentence of a docstring's first paragraph: up to a full stop outside
    parentheses and inline markup ("eq. (3.4)" and ``a.b`` do not end it)."""
    paragraph = " ".join(text.strip().split("\n\n")[0].split())
    depth, code = 0, False
    for k, char in enumerate(paragraph):
        if char == "`":
            code = not code
        elif not code and char in "([{":
            depth += 1
        elif not code and char in ")]}":
            depth -= 1
        elif char == "." and not code and depth == 0 and paragraph[k + 1 : k + 2] in ("", " "):
            return paragraph[: k + 1]
    return paragraph


def api_summary(name: str) -> str:
    """The summary of a public name in the API tables: its docstring's first sentence (a
    constant, which has no docstring of its own, by its value)."""
    import inspect

    module_name, _, attr = name.rpartition(".")
    obj = getattr(importlib.import_module(module_name), attr)
    if inspect.isclass(obj) or inspect.isroutine(obj) or inspect.ismodule(obj):
        return _first_sentence(inspect.getdoc(obj) or "")
    return f"The constant ``{obj!r}``."


def api_summaries(api: pathlib.Path) -> None:
    """``api/_summaries.md``: one table per page of the reference (name, the docstring's first
    sentence), read from the pages' own directives, so a table cannot list a name its page
    does not document, nor miss one it does."""
    parts = ["<!-- generated by docs/_generate.py from the pages of docs/api/ -->\n"]
    for page, names in api_entries(api).items():
        title = (api / f"{page}.md").read_text().splitlines()[0].removeprefix("# ")
        parts.append(f"\n## [{title}]({page}.md)\n\n```{{eval-rst}}\n")
        # One table per module: the docstrings' short references (:func:`shoot`) resolve
        # in the module they are written for.
        for module in dict.fromkeys(name.rpartition(".")[0] for name in names):
            rows = "".join(
                f"   * - :py:obj:`{n.rpartition('.')[2]}`\n     - {api_summary(n)}\n"
                for n in names
                if n.rpartition(".")[0] == module
            )
            parts.append(
                f".. currentmodule:: {module}\n\n.. list-table::\n   :widths: 25 75\n"
                f"   :class: autosummary\n\n{rows}\n"
            )
        parts.append("```\n")
    _write_if_changed(api / "_summaries.md", "".join(parts))


def _write_if_changed(path: pathlib.Path, text: str) -> None:
    # Sphinx rereads a source whose mtime moved: leave an unchanged page alone.
    if not path.exists() or path.read_text() != text:
        path.write_text(text)


def subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """The parser of each ``elastic-jax`` command, by name."""
    return next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices


def cli_reference(path: pathlib.Path) -> None:
    """Every command and option of ``elastic-jax``, printed by its own parser."""
    from elastic_jax import cli

    previous = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = "90"  # argparse wraps to the terminal: one width for the site
    try:
        parser = cli.build_parser()
        home = str(pathlib.Path.home())
        parts = [
            "<!-- generated by docs/_generate.py from elastic_jax.cli.build_parser -->\n",
            "```text\n" + parser.format_help().replace(home, "~") + "```\n",
        ]
        for name, command in subcommands(parser).items():
            text = command.format_help().replace(home, "~")
            parts.append(f"\n### `elastic-jax {name}`\n\n```text\n{text}```\n")
    finally:
        if previous is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = previous
    _write_if_changed(path, "".join(parts))


def _cell(value, digits: int = 4) -> str:
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.{digits}g}"
    return str(value)


def markdown_table(header: list[str], rows: list[list]) -> str:
    out = _io.StringIO()
    out.write("| " + " | ".join(header) + " |\n")
    out.write("|" + " --- |" * len(header) + "\n")
    for row in rows:
        out.write("| " + " | ".join(_cell(v) for v in row) + " |\n")
    return out.getvalue()


# The paper's values (Su et al. 2020): Table 3's three example pairs per resolution
# (iterations, run time on a laptop without GPU), Table 1's cat / horse row (relative gap
# between the (0, 1/2, 1, 0) length of the straight line and the L2 length of its SRNF
# image, by time steps) and Table 2's cat / horse row.
PAPER_TABLE3 = {
    "low": "114 / 42 / 88 its; 39.7 / 40.7 / 32.5 s",
    "middle": "237 / 113 / 220 its; 183 / 95 / 142 s",
    "high": "235 / 139 / 193 its; 842 / 505 / 627 s",
}
PAPER_TABLE1_CAT_HORSE = {13: 0.00502, 20: 0.00494, 99: 0.00002}
PAPER_TABLE2_CAT_HORSE = {"L_l": 0.8932, "L_g": 0.7948, "L_i": 1.1442, "L2": 0.6130}


def _records(path: pathlib.Path, benchmark: str) -> list[dict]:
    lines = path.read_text().splitlines() if path.exists() else []
    return [r for r in map(json.loads, lines) if r.get("benchmark") == benchmark]


def _table3(bench: pathlib.Path) -> str:
    records = _records(bench / "bench_shape.jsonl", "shape_geodesic")
    rows = []
    for row in ("low", "middle", "high"):
        found = {r["settings"]["pair"]: r for r in records if r["settings"]["row"] == row}
        if not found:
            continue
        settings = next(iter(found.values()))["settings"]
        o, m, n = settings["options"], settings["m"], settings["n"]
        cells = [f"{row}: {m} x {n}, degree {o['degree']} / {o['vf_degree']}, N {o['n_times']}"]
        cells.append(PAPER_TABLE3[row])
        for pair in ("synthetic", "cats"):
            r = found.get(pair)
            if r is None:
                cells.append("-")
                continue
            status = "converged" if r["converged"] else "not converged"
            cells.append(
                f"{r['solve_s']:.3g} s, {r['num_steps']} steps, {r['rounds']} rounds; "
                f"d {r['distance']:.4g} ({r['refinement']['distance_grid']:.4g} on the finer "
                f"grid), {status}"
            )
        rows.append(cells)
    header = ["row", "paper (3 pairs)", "synthetic pair", "cat1 -> cat2"]
    return markdown_table(header, rows)


def _table1(bench: pathlib.Path) -> str:
    rows = []
    for r in _records(bench / "bench_statistics_tables.jsonl", "statistics.table2"):
        pair, m, n = r["settings"]["pair"], r["settings"]["m"], r["settings"]["n"]
        for row in r["isometry_straight_line"]:
            k = row["n_times"]
            rows.append(
                [
                    f"{pair}, {m} x {n}",
                    k,
                    row["forward_relative_error"],
                    row["midpoint_relative_error"],
                    # the paper's row is its cat / horse pair: beside ours only
                    PAPER_TABLE1_CAT_HORSE.get(k) if pair == "cat1-horse0" else None,
                ]
            )
    rows.append(["paper, cat / horse", 20, None, None, PAPER_TABLE1_CAT_HORSE[20]])
    header = ["pair", "N", "forward (the paper's)", "midpoint (the default)", "paper"]
    return markdown_table(header, rows)


def _table2(bench: pathlib.Path) -> str:
    rows = []
    for r in _records(bench / "bench_statistics_tables.jsonl", "statistics.table2"):
        lengths, ratio = r["lengths"], r["ratios_to_L2"]
        label = f"{r['settings']['pair']}, {r['settings']['m']} x {r['settings']['n']}"
        rows.append(
            [label]
            + [
                f"{lengths[k]:.4f} ({ratio[k]:.3f})"
                for k in ("L_l", "L_g", "L_i", "L_i_subdivided")
            ]
            + [f"{lengths['L2']:.4f}", "yes" if r["geodesic"]["converged"] else "no"]
        )
    p = PAPER_TABLE2_CAT_HORSE
    rows.append(
        ["paper, cat / horse"]
        + [f"{p[k]:.4f} ({p[k] / p['L2']:.3f})" for k in ("L_l", "L_g", "L_i")]
        + ["-", f"{p['L2']:.4f}", "-"]
    )
    header = ["pair", "L_l", "L_g", "L_i (7 nodes)", "L_i (steps cut in 4)", "L2", "L_g converged"]
    return markdown_table(header, rows)


def _figures(gallery: pathlib.Path) -> dict[str, str]:
    stored = json.loads((gallery / "figures.json").read_text())
    geo = stored["geodesics"]
    pairs = [k for k, v in geo.items() if isinstance(v, dict) and "distance" in v]

    def levels(record) -> str:
        # Each working grid's distance, coarse to fine: how the distance was resolved.
        if not record.get("levels"):
            return "one grid"
        grids, distances = record["levels"]["grids"], record["levels"]["distances"]
        return ", ".join(f"{g[0]} x {g[1]}: {d:.4g}" for g, d in zip(grids, distances, strict=True))

    geodesics = markdown_table(
        ["pair", "d (shape)", "levels", "result", "d (parametrized)", "rounds", "refinement"],
        [
            [
                k.replace("-", " -> "),
                geo[k]["distance"],
                levels(geo[k]),
                geo[k].get("result", "successful" if geo[k]["converged"] else "not converged"),
                geo[k]["parametrized_distance"],
                geo[k]["rounds"],
                geo[k]["refinement_relative_change"],
            ]
            for k in pairs
        ],
    )
    levels = stored["multires"]["levels"]
    multires = markdown_table(
        ["level", "grid", "degree", "N", "distance", "straight line", "steps", "converged"],
        [
            [
                k + 1,
                f"{v['grid'][0]} x {v['grid'][1]}",
                v["degree"],
                v["n_times"],
                v["distance"],
                v["straight_distance"],
                v["num_steps"],
                v["converged"],
            ]
            for k, v in enumerate(levels)
        ],
    )
    karcher = stored["karcher"]
    shapes = markdown_table(
        ["shape", "distance to the mean"],
        [[name, d] for name, d in zip(karcher["shapes"], karcher["distances"], strict=True)],
    )
    return {"geodesics": geodesics, "multires": multires, "karcher": shapes}


def gallery_tables(gallery: pathlib.Path) -> None:
    """``gallery/_table_*.md`` from the stored benchmark JSON and ``figures.json``."""
    bench = gallery / "bench"
    tables = {"table1": _table1(bench), "table2": _table2(bench), "table3": _table3(bench)}
    tables.update(_figures(gallery))
    for name, table in tables.items():
        text = f"<!-- generated by docs/_generate.py from docs/gallery/ ({name}) -->\n\n{table}"
        _write_if_changed(gallery / f"_table_{name}.md", text)
