"""The documentation site builds with warnings as errors and holds what it promises.

One build per test session (about 10-20 s): every public name has an API entry on its
group's page and a row in the reference's summary tables, every notebook page shows a
figure, every link inside the site resolves (file and anchor), the command-line reference
lists every option of the parser, and the gallery's tables carry the stored benchmark
numbers.
"""

import html.parser
import io
import json
import pathlib
import re
import subprocess
import sys
import tokenize
import urllib.parse

import pytest

pytest.importorskip("sphinx")
pytest.importorskip("myst_nb")
pytest.importorskip("pydata_sphinx_theme")

ROOT = pathlib.Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
sys.path.insert(0, str(DOCS))
import _generate  # noqa: E402


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> pathlib.Path:
    out = tmp_path_factory.mktemp("site")
    # The command README and docs/contributing.md give, into a temporary folder.
    command = [sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b", "html"]
    done = subprocess.run(
        [*command, str(DOCS), str(out)], capture_output=True, text=True, cwd=ROOT, timeout=600
    )
    assert done.returncode == 0, done.stderr[-4000:]
    assert done.stderr.strip() == "", done.stderr[-4000:]
    return out


class _Links(html.parser.HTMLParser):
    def __init__(self):
        super().__init__()
        self.ids, self.links, self.images = set(), [], []

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        if "id" in attrs:
            self.ids.add(attrs["id"])
        if tag == "a" and attrs.get("href"):
            self.links.append(attrs["href"])
        if tag in ("img", "script") and attrs.get("src"):
            self.links.append(attrs["src"])
            if tag == "img":
                self.images.append(attrs["src"])
        if tag == "link" and attrs.get("href"):
            self.links.append(attrs["href"])


def _parse(page: pathlib.Path) -> _Links:
    parser = _Links()
    parser.feed(page.read_text())
    return parser


def _posix_join(*parts):
    return "/".join(p.strip("/") for p in parts if p)


def test_every_public_name_has_an_api_entry(site):
    from sphinx.util.inventory import InventoryFile

    with open(site / "objects.inv", "rb") as f:
        inventory = InventoryFile.load(f, "", _posix_join)
    documented = {
        name for kind, entries in inventory.items() if kind.startswith("py:") for name in entries
    }
    names = _generate.public_names()
    assert len(names) >= 100  # 71 in elastic_jax, the rest in io, plot and shapes
    assert [n for n in names if n not in documented] == []
    # ...each entry is on the page of the API reference its directive is on, with its anchor...
    entries = _generate.api_entries(DOCS / "api")
    placed = [n for page_names in entries.values() for n in page_names]
    assert sorted(placed) == sorted(set(placed))  # one entry per name
    for page, page_names in entries.items():
        ids = _parse(site / "api" / f"{page}.html").ids
        assert [n for n in page_names if n not in ids] == [], page
    assert [n for n in names if n not in placed] == []
    # ...and the reference's index lists it in its group's table, linked to the entry.
    index = _parse(site / "api" / "index.html").links
    for page, page_names in entries.items():
        linked = {link.partition("#")[2] for link in index if link.startswith(f"{page}.html#")}
        assert [n for n in page_names if n not in linked] == [], page


def test_a_missing_api_entry_names_its_page():
    assert _generate.api_page_for("elastic_jax.io.load_surface") == "docs/api/io.md"
    assert _generate.api_page_for("elastic_jax.io.a_new_name") == "docs/api/io.md"
    # A name of elastic_jax belongs on the page that documents its neighbours.
    entries = _generate.api_entries(DOCS / "api")
    for name in _generate.public_names():
        (page,) = [p for p, page_names in entries.items() if name in page_names]
        assert _generate.api_page_for(name) == f"docs/api/{page}.md", name


def test_every_notebook_page_shows_a_figure(site):
    notebooks = sorted((ROOT / "notebooks").glob("*.ipynb"))
    assert len(notebooks) == 7
    for notebook in notebooks:
        page = site / "examples" / "notebooks" / f"{notebook.stem}.html"
        images = [
            s
            for s in _parse(page).images
            if s.startswith("data:image/png") or not s.startswith(("http", "data:"))
        ]
        assert images, f"{page.name} shows no figure"
        for src in images:
            if not src.startswith("data:"):
                assert (page.parent / urllib.parse.unquote(src)).is_file(), (page.name, src)


def test_no_link_inside_the_site_is_broken(site):
    # _static holds the theme's templates, not pages of the site.
    pages = sorted(p for p in site.rglob("*.html") if "_static" not in p.parts)
    ids = {page: None for page in pages}
    broken, checked = [], 0
    for page in pages:
        for link in _parse(page).links:
            parsed = urllib.parse.urlsplit(link)
            if parsed.scheme or link.startswith(("//", "mailto:", "data:", "javascript:")):
                continue
            target = (
                (page.parent / urllib.parse.unquote(parsed.path)).resolve() if parsed.path else page
            )
            if target.is_dir():
                target = target / "index.html"
            checked += 1
            if not target.exists():
                broken.append(f"{page.relative_to(site)} -> {link}")
                continue
            if parsed.fragment and target.suffix == ".html":
                if ids.get(target) is None:
                    ids[target] = _parse(target).ids
                if parsed.fragment not in ids[target]:
                    broken.append(f"{page.relative_to(site)} -> {link} (no such anchor)")
    assert checked > 1000
    assert broken == []


def test_the_cli_reference_lists_every_command_and_option(site):
    from elastic_jax import cli

    text = (site / "guides" / "cli.html").read_text()
    commands = _generate.subcommands(cli.build_parser())
    missing = []
    for name, command in commands.items():
        if f"elastic-jax {name}" not in text:
            missing.append(name)
        for action in command._actions:
            missing += [f"{name} {o}" for o in action.option_strings if o not in text]
    assert len(commands) >= 9
    assert missing == []


def test_the_gallery_tables_carry_the_stored_benchmark_numbers(site):
    text = (site / "gallery.html").read_text()
    records = [
        json.loads(line)
        for line in (DOCS / "gallery" / "bench" / "bench_shape.jsonl").read_text().splitlines()
    ]
    solves = [r for r in records if r.get("benchmark") == "shape_geodesic"]
    assert len(solves) >= 6  # three rows, two pairs
    for r in solves:
        assert f"d {r['distance']:.4g}" in text, r["settings"]
    tables = [
        json.loads(line)
        for line in (DOCS / "gallery" / "bench" / "bench_statistics_tables.jsonl")
        .read_text()
        .splitlines()
    ]
    table2 = [r for r in tables if r.get("benchmark") == "statistics.table2"]
    assert len(table2) >= 2
    for r in table2:
        assert f"{r['lengths']['L_g']:.4f}" in text
        assert f"{r['lengths']['L2']:.4f}" in text
    # The paper's values stand beside them (Tables 1, 2 and 3).
    for paper in ("0.8932", "0.7948", "1.1442", "0.6130", "0.00502", "39.7", "842"):
        assert paper in text
    figures = json.loads((DOCS / "gallery" / "figures.json").read_text())
    for part in ("geodesics", "multires", "karcher"):
        assert figures[part]["measured"]
    gallery = _parse(site / "gallery.html")
    assert sum(src.startswith("_images/") for src in gallery.images) >= 10


def test_every_gallery_figure_has_a_title_or_labels():
    """Issue 52: every plot_* call of the gallery script names what it shows (a title, one
    title per panel or a figure title), none is left with the defaults ("t = 0/2")."""
    import ast

    script = DOCS / "gallery" / "make_gallery.py"
    calls = [
        node
        for node in ast.walk(ast.parse(script.read_text()))
        if isinstance(node, ast.Call)
        and isinstance(node.func, ast.Attribute)
        and isinstance(node.func.value, ast.Name)
        and node.func.value.id == "plot"
        and node.func.attr.startswith("plot_")
    ]
    untitled = [
        f"line {call.lineno}: plot.{call.func.attr}"
        for call in calls
        if not {"title", "titles", "suptitle"} & {k.arg for k in call.keywords}
    ]
    # Geodesics (paths, energies), multiresolution paths, and the Karcher figures (inputs,
    # registered inputs, mean, history, modes).
    assert len(calls) == 8
    assert untitled == []
    # The surfaces are drawn with the camera that fills the panels.
    drawn = [c for c in calls if c.func.attr in ("plot_path", "plot_modes")]
    assert len(drawn) == 6
    assert all(
        any(k.arg == "view" and getattr(k.value, "value", None) == "fit" for k in c.keywords)
        for c in drawn
    )


def test_docstrings_cite_the_site_not_a_missing_file():
    # Every "math §N" in the package is a link into docs/math.md, whose labels exist.
    package = ROOT / "elastic_jax"
    sources = "".join(p.read_text() for p in package.rglob("*.py"))
    assert "MATH.md" not in sources
    math = (DOCS / "math.md").read_text()
    for n in range(1, 11):
        assert f"(math-{n})=" in math
    assert sources.count("<math-") >= 20  # the public docstrings' references


# A file of the repository named in prose: a path under one of its folders, or a top-level
# Markdown file (MATH.md was one, before docs/math.md). Sphinx's output (docs/_build) is
# made by the build, not stored.
_REPO_PATH = re.compile(
    r"(?<![\w./-])((?:docs|benchmarks|elastic_jax|tests|notebooks|\.ci|shared)/[\w./-]*?\w"
    r"\.(?:md|py|ipynb|json|npz|npy|toml|ya?ml|txt|csv|png|html))(?![\w/])"
    r"|(?<![\w./-])([A-Z][A-Z_]*\.md)(?![\w/])"
)
# A Markdown link to a file by a relative address: [text](guides/settings.md#anchor).
_LINK = re.compile(r"\]\((?![a-z]+:|#|/)([^)\s#]+)(?:#[^)\s]*)?\)")


def _python_texts(path: pathlib.Path):
    """(line, text) of every comment and string (docstrings included) of a Python file."""
    kinds = {tokenize.COMMENT, tokenize.STRING, getattr(tokenize, "FSTRING_MIDDLE", None)}
    for token in tokenize.generate_tokens(io.StringIO(path.read_text()).readline):
        if token.type in kinds:
            yield token.start[0], token.string


def _prose():
    """(file, where in it, text, links relative to the file?) of the package's, the docs' and the
    benchmarks' comments and strings, every Markdown page of docs/ and README.md, and the
    notebooks' Markdown cells (rendered from a copy under docs/: their links not checked)."""
    for folder in ("elastic_jax", "docs", "benchmarks"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            for line, text in _python_texts(path):
                yield path, f"line {line}", text, False
    for path in [ROOT / "README.md", *sorted(DOCS.rglob("*.md"))]:
        for line, text in enumerate(path.read_text().splitlines(), 1):
            yield path, f"line {line}", text, True
    for path in sorted((ROOT / "notebooks").glob("*.ipynb")):
        cells = json.loads(path.read_text())["cells"]
        for k, cell in enumerate(cells):
            if cell["cell_type"] == "markdown":
                yield path, f"cell {k}", "".join(cell["source"]), False


def test_every_file_path_in_the_prose_exists():
    """Docstrings, comments and pages name files that exist (issue 48: the settings guide
    cited docs/registration.md, renamed docs/guides/registration_notes.md long before)."""
    missing, checked = [], 0
    for path, place, text, links in _prose():
        where = f"{path.relative_to(ROOT)}, {place}"
        for match in _REPO_PATH.finditer(text):
            name = match.group(1) or match.group(2)
            if "/_build/" in f"/{name}":
                continue
            checked += 1
            if not (ROOT / name).exists():
                missing.append(f"{where}: {name}")
        for match in _LINK.finditer(text) if links else ():
            target = urllib.parse.unquote(match.group(1))
            if "." not in pathlib.PurePosixPath(target).name:
                continue  # a Sphinx reference (a label or a page without suffix)
            checked += 1
            if not (path.parent / target).exists():
                missing.append(f"{where}: {target} (relative to {path.parent.name}/)")
    assert checked >= 50  # the scan sees the references it is meant to
    assert not missing, "paths that do not exist:\n" + "\n".join(missing)
