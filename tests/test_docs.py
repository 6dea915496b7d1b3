"""Every code block in README.md, CHANGELOG.md, the pages of docs/ and benchmarks/README.md
runs as written (the site's own build and API checks are in tests/test_site.py).

* ``python`` blocks of one page run in order, as one script (a reader pastes them into one
  session), in a fresh process whose working directory is an empty folder holding a link
  to the clone's ``examples/`` (so files a snippet writes land there, not in the clone).
* ``bash`` blocks: every ``./run`` / ``ivdrem`` command line is parsed by ivdrem's own
  command-line parsers (an unknown option or a missing argument fails here, not for the
  reader), and every ``.toml`` file it reads exists; ``./run python SCRIPT ...`` needs the
  script to exist and to know every ``--option`` the line gives (from its ``--help``).
* ``toml`` blocks parse.
Blocks without a language are program output or usage lines and are not run.
"""
from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from functools import lru_cache
from pathlib import Path

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

import pytest

REPO = Path(__file__).resolve().parents[1]
#: folders of docs/ that the site's build writes (git-ignored), not pages anyone wrote
GENERATED = ("_build", "gallery", "api/generated")


def doc_pages():
    """The Markdown pages of docs/ written by hand (the site's sources), sorted."""
    docs = REPO / "docs"
    return sorted(p for p in docs.rglob("*.md")
                  if not any(p.is_relative_to(docs / g) for g in GENERATED))


PAGES = sorted([REPO / "README.md", REPO / "CHANGELOG.md", REPO / "benchmarks" / "README.md",
                *doc_pages()])
# a language (```python) or a MyST directive with its argument (```{include} ../CHANGELOG.md)
_FENCE = re.compile(r"^```(\{[A-Za-z0-9_:-]+\}|[A-Za-z0-9_+-]*)(?:\s.*)?$")


def code_blocks(path: Path):
    """[(language, first line number, text)] of the fenced blocks of a Markdown page."""
    out, lang, start, buf = [], None, 0, []
    for i, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        m = _FENCE.match(line.strip())
        if lang is None and m:
            lang, start, buf = m.group(1).lower(), i + 1, []
        elif lang is not None and line.strip() == "```":
            out.append((lang, start, "\n".join(buf)))
            lang = None
        elif lang is not None:
            buf.append(line)
    assert lang is None, f"{path.name}: a code block opened at line {start - 1} is not closed"
    return out


def _rel(p: Path) -> str:
    return str(p.relative_to(REPO))


def test_the_block_reader_sees_every_fence(tmp_path):
    page = tmp_path / "p.md"
    page.write_text("a\n```python\nx = 1\n```\ntext\n```\nout\n```\n```bash\nls\n```\n"
                    "```{toctree}\n:maxdepth: 1\n\npage\n```\n```{include} ../x.md\n```\n",
                    encoding="utf-8")
    assert code_blocks(page) == [("python", 3, "x = 1"), ("", 7, "out"), ("bash", 10, "ls"),
                                 ("{toctree}", 13, ":maxdepth: 1\n\npage"), ("{include}", 18, "")]
    page.write_text("```python\nx = 1\n", encoding="utf-8")
    with pytest.raises(AssertionError, match="not closed"):
        code_blocks(page)


PYTHON_PAGES = [p for p in PAGES if any(lang == "python" for lang, _, _ in code_blocks(p))]


@pytest.mark.parametrize("page", PYTHON_PAGES, ids=_rel)
def test_python_blocks_run_as_written(page, tmp_path):
    parts = []
    for lang, line, text in code_blocks(page):
        if lang == "python":
            parts.append(f"# --- {page.name}, line {line}\n{text}\n")
    script = tmp_path / f"{page.stem}_blocks.py"
    script.write_text("\n".join(parts), encoding="utf-8")
    (tmp_path / "examples").symlink_to(REPO / "examples")
    env = dict(os.environ, MPLBACKEND="Agg", PYTHONPATH=str(REPO), CI="true")
    proc = subprocess.run([sys.executable, str(script)], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, (f"the python blocks of {_rel(page)} fail:\n"
                                  f"{proc.stdout[-3000:]}\n{proc.stderr[-5000:]}")


def _shell_commands(text):
    """Command lines of a bash block: comments stripped, continuation lines joined."""
    text = text.replace("\\\n", " ")
    for line in text.splitlines():
        words = shlex.split(line, comments=True)
        if words:
            yield line.strip(), words


def _parse_ivdrem(words):
    """Parse an ivdrem command line with ivdrem's own parsers; SystemExit on an error."""
    from ivdrem import cli
    from ivdrem.cli import fmu as fmu_cli
    if words[0] == "fmu":
        fmu_cli._parser().parse_args(words[1:])
    elif words[0] == "cosim":
        fmu_cli._cosim_parser().parse_args(words[1:])
    else:
        cli.build_parser().parse_args(words)


@lru_cache(maxsize=None)
def _script_help(script):
    """(exit code, stdout, stderr) of `python script --help`: once per script, as a block
    often shows one script with several options (each child imports ivdrem, 3-4 s)."""
    proc = subprocess.run([sys.executable, str(script), "--help"], cwd=REPO,
                          capture_output=True, text=True, timeout=300,
                          env=dict(os.environ, PYTHONPATH=str(REPO)))
    return proc.returncode, proc.stdout, proc.stderr


def _check_command(page, line, words):
    if words[0] == "./run":
        words = words[1:] or ["report"]
        if words[0] in ("test", "docs"):     # the set-up, then pytest / sphinx (run's own)
            return
        if words[0] == "python":
            script = REPO / words[1]
            assert script.is_file(), f"{_rel(page)}: `{line}`: no file {words[1]}"
            returncode, stdout, stderr = _script_help(script)
            assert returncode == 0, f"{_rel(page)}: `{words[1]} --help` fails: {stderr}"
            for w in words[2:]:
                if w.startswith("--"):
                    opt = w.split("=")[0]
                    assert opt in stdout, f"{_rel(page)}: `{line}`: {words[1]} has no {opt}"
            return
    elif words[0] == "ivdrem":
        words = words[1:]
    else:
        pytest.fail(f"{_rel(page)}: `{line}`: commands in the docs start with ./run or ivdrem "
                    "(the ./run entry point does its own set-up from a fresh clone)")
    try:
        _parse_ivdrem(words)
    except SystemExit as exc:
        pytest.fail(f"{_rel(page)}: `{line}` is refused by ivdrem's parser (exit {exc.code})")
    for i, w in enumerate(words):
        if w.endswith(".toml") and not (i and words[i - 1] in ("--json", "-o", "--out")):
            assert (REPO / w).is_file(), f"{_rel(page)}: `{line}` reads {w}, which does not exist"


BASH = [(p, line, text) for p in PAGES for lang, line, text in code_blocks(p)
        if lang in ("bash", "sh", "shell", "console")]


@pytest.mark.parametrize("page,line,text", BASH, ids=[f"{_rel(p)}:{n}" for p, n, _ in BASH])
def test_shell_blocks_are_valid_commands(page, line, text, capsys):
    for cmd, words in _shell_commands(text):
        _check_command(page, cmd, words)


def test_a_wrong_command_in_the_docs_is_caught():
    page = REPO / "README.md"
    with pytest.raises(pytest.fail.Exception, match="refused by ivdrem's parser"):
        _check_command(page, "./run paper --no-such-option", ["./run", "paper", "--no-such-option"])
    with pytest.raises(AssertionError, match="does not exist"):
        _check_command(page, "./run paper --config nope.toml", ["./run", "paper", "--config", "nope.toml"])
    with pytest.raises(pytest.fail.Exception, match="start with ./run"):
        _check_command(page, "python benchmarks/bench_paper.py", ["python", "benchmarks/bench_paper.py"])


TOML = [(p, line, text) for p in PAGES for lang, line, text in code_blocks(p) if lang == "toml"]


@pytest.mark.parametrize("page,line,text", TOML, ids=[f"{_rel(p)}:{n}" for p, n, _ in TOML])
def test_toml_blocks_parse(page, line, text):
    tomllib.loads(text)
