"""The documentation site (docs/, ``./run docs``): built with warnings as errors, every public
name in the API reference with a docstring, every page reachable from the index, the
gallery's examples run with their figures, README.md a front door of at most 12 KB.

The build is the one ``./run docs`` does (``sphinx -W --keep-going``), into a temporary
folder; it runs every gallery example and imports every public module.  The page and
docstring checks below read the sources and the built inventory, so each names what is
missing.
"""
from __future__ import annotations

import importlib
import inspect
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"
sys.path.insert(0, str(DOCS / "_ext"))
import apipages  # noqa: E402  (docs/_ext: the API pages' generator, one list of modules)
from test_docs import doc_pages  # noqa: E402

README_LIMIT = 12_000
BUILD_LIMIT_S = 300


# --------------------------------------------------------------------- the build
@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """The HTML site built as ``./run docs`` builds it (-W: a warning fails the build)."""
    out = tmp_path_factory.mktemp("site")
    env = dict(os.environ, MPLBACKEND="Agg", CI="true", PYTHONPATH=str(REPO))
    start = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b", "html",
         "-d", str(out / "doctrees"), str(DOCS), str(out / "html")],
        cwd=REPO, env=env, capture_output=True, text=True, timeout=2 * BUILD_LIMIT_S)
    seconds = time.perf_counter() - start
    return proc, out / "html", seconds


def test_the_site_builds_without_a_warning(site):
    proc, html, seconds = site
    assert proc.returncode == 0, (f"the site's build failed (warnings are errors):\n"
                                  f"{proc.stderr[-8000:]}\n{proc.stdout[-2000:]}")
    assert (html / "index.html").is_file()
    assert seconds < BUILD_LIMIT_S, f"the build took {seconds:.0f} s (limit {BUILD_LIMIT_S} s)"


def _inventory(html: Path) -> set[str]:
    from sphinx.util.inventory import InventoryFile
    with open(html / "objects.inv", "rb") as f:
        inv = InventoryFile.load(f, "", os.path.join)
    names = set()
    for role, entries in inv.items():
        if role.startswith("py:"):
            names.update(entries)
    return names


def public_names():
    """[(module, name)] of every name in the __all__ of every public module of ivdrem."""
    out = []
    for module_name in apipages.public_modules():
        module = importlib.import_module(module_name)
        for name in getattr(module, "__all__", ()):
            out.append((module_name, name))
    return out


def missing_entries(documented: set[str]) -> list[str]:
    """Public names with no entry among `documented` (dotted names of the API reference).

    A name re-exported by a package counts as documented by the entry of its home module
    (:func:`apipages.home_module`), which the package's page links to."""
    missing = []
    for module_name, name in public_names():
        home = apipages.home_module(module_name, name)
        if f"{home}.{name}" not in documented:
            missing.append(f"{module_name}.{name}")
    return missing


def test_every_public_name_has_an_entry_in_the_api_reference(site):
    proc, html, _ = site
    assert proc.returncode == 0, "the site did not build"
    documented = _inventory(html)
    modules = [m for m in apipages.public_modules() if m not in documented]
    assert not modules, f"public modules without a page in the API reference: {modules}"
    missing = missing_entries(documented)
    assert not missing, (f"{len(missing)} public names without an entry in the API reference "
                         f"(a docstring or a #: comment is missing?): {missing}")


def test_a_name_missing_from_the_reference_is_caught():
    module_name, name = "ivdrem.sim", "simulate"
    home = apipages.home_module(module_name, name)
    everything = {f"{apipages.home_module(m, n)}.{n}" for m, n in public_names()}
    assert missing_entries(everything) == []
    assert f"{module_name}.{name}" in missing_entries(everything - {f"{home}.{name}"})


# --------------------------------------------------------------------- docstrings
def undocumented():
    """Public names (module.name) without a docstring of their own."""
    out = []
    for module_name, name in public_names():
        home = apipages.home_module(module_name, name)
        if home != module_name:
            continue                               # checked where it is documented
        obj = getattr(importlib.import_module(module_name), name)
        if inspect.isclass(obj) or inspect.isroutine(obj) or callable(obj):
            doc = obj.__doc__ if inspect.isclass(obj) else inspect.getdoc(obj)
            # a dataclass's generated docstring is its signature: not a description
            if doc and inspect.isclass(obj) and doc.startswith(f"{obj.__name__}("):
                doc = None
        else:
            doc = apipages.data_doc(module_name, name)
        if not (doc or "").strip():
            out.append(f"{module_name}.{name}")
    for module_name in apipages.public_modules():
        if not (importlib.import_module(module_name).__doc__ or "").strip():
            out.append(f"{module_name} (the module)")
    return out


def test_every_public_name_has_a_docstring():
    missing = undocumented()
    assert not missing, f"{len(missing)} public names without a docstring: {missing}"


# --------------------------------------------------------------------- pages
_TOCTREE = re.compile(r"^```\{toctree\}\s*$(.*?)^```\s*$", re.S | re.M)
_LINK = re.compile(r"\]\(([^)#\s]+\.md)(?:#[^)]*)?\)")


def reachable_pages() -> set[Path]:
    """Pages reached from docs/index.md through toctrees and Markdown links."""
    seen, todo = set(), [DOCS / "index.md"]
    while todo:
        page = todo.pop()
        if page in seen or not page.is_file():
            continue
        seen.add(page)
        text = page.read_text(encoding="utf-8")
        for block in _TOCTREE.findall(text):
            glob = ":glob:" in block
            for line in block.splitlines():
                entry = line.strip()
                if not entry or entry.startswith(":"):
                    continue
                if glob and "*" in entry:
                    todo.extend(page.parent.glob(entry + ".md"))
                else:
                    todo.append(page.parent / (entry + ".md"))
        for target in _LINK.findall(text):
            todo.append((page.parent / target).resolve())
    return seen


def test_no_page_is_an_orphan():
    reached = reachable_pages()
    orphans = [str(p.relative_to(REPO)) for p in doc_pages() if p not in reached]
    assert not orphans, f"pages no link or toctree of the index reaches: {orphans}"


def test_the_orphan_check_finds_an_orphan(tmp_path, monkeypatch):
    (tmp_path / "index.md").write_text("```{toctree}\n:maxdepth: 1\n\nshown\n```\n"
                                       "see [other](linked.md#a)\n", encoding="utf-8")
    for name in ("shown", "linked", "lost"):
        (tmp_path / f"{name}.md").write_text("# x\n", encoding="utf-8")
    monkeypatch.setattr(sys.modules[__name__], "DOCS", tmp_path)
    assert {p.name for p in reachable_pages()} == {"index.md", "shown.md", "linked.md"}


def test_the_changelog_and_benchmarks_notes_are_pages():
    assert "../CHANGELOG.md" in (DOCS / "changelog.md").read_text(encoding="utf-8")
    assert "../benchmarks/README.md" in (DOCS / "benchmarks.md").read_text(encoding="utf-8")


# --------------------------------------------------------------------- the front door
def test_readme_is_a_front_door():
    size = (REPO / "README.md").stat().st_size
    assert size <= README_LIMIT, f"README.md is {size} bytes (at most {README_LIMIT})"


_ANY_LINK = re.compile(r"\]\(([^)\s]+)\)")


@pytest.mark.parametrize("page", ["README.md", "CHANGELOG.md"])
def test_links_of_the_front_door_resolve(page):
    """Relative links of pages outside the site point at files of the repository; the
    README (also the package's long description) links the site's pages by address."""
    text = (REPO / page).read_text(encoding="utf-8")
    for target in _ANY_LINK.findall(text):
        if re.match(r"[a-z]+:", target) or target.startswith("#"):
            continue
        path = target.split("#")[0]
        assert (REPO / path).exists(), f"{page}: the link {target} points at nothing"


# --------------------------------------------------------------------- gallery
GALLERY = sorted((REPO / "examples").glob("plot_*.py"))


def test_the_gallery_has_examples():
    assert len(GALLERY) >= 3


@pytest.mark.parametrize("script", GALLERY, ids=lambda p: p.stem)
def test_every_gallery_example_ran_and_drew_a_figure(site, script):
    proc, html, _ = site
    assert proc.returncode == 0, "the site did not build"
    page = html / "gallery" / f"{script.stem}.html"
    assert page.is_file(), f"no gallery page for {script.name}"
    images = list((html / "_images").glob(f"sphx_glr_{script.stem}_*.png"))
    assert images, f"{script.name} drew no figure in the gallery"
