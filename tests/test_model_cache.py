"""The on-disk cache of a symbolic model's generated source (``model.source``).

Generating a model's code is sympy printing (35 s for planar-6 on this machine); it is kept
in the compile cache by the model's content key and ivdrem's version.  Each test checks the
cache against the uncached generator (``generate_source``), or that a stale entry is never
read.
"""
from __future__ import annotations

import errno
import io
import subprocess
import sys
from pathlib import Path

import pytest

import ivdrem
from ivdrem import _progress
from ivdrem.models import planar_arm, two_link
from ivdrem.models.base import linalg_import


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("IVDREM_CACHE_DIR", str(tmp_path))
    return tmp_path / "models"


def _refuse_generation(monkeypatch):
    """Make any regeneration fail loudly: what follows must come from the disk."""
    def boom(self, prefix=""):
        raise AssertionError("regenerated although the cache holds this model")
    monkeypatch.setattr(type(two_link()), "generate_source", boom)


def test_a_second_model_object_reads_the_same_source_from_disk(cache, monkeypatch):
    first = two_link().source("")
    assert first == two_link().generate_source("")
    assert len(list(cache.glob("*.py"))) == 1
    prefixed = two_link().source("p_")       # another prefix is another entry
    assert prefixed == two_link().generate_source("p_") != first
    _refuse_generation(monkeypatch)
    again = two_link()                       # a new object: its in-memory cache is empty
    assert again.source("") == first and again.source("p_") == prefixed


def test_a_changed_model_never_reads_another_models_entry(cache):
    base = two_link().source("")
    other_g = two_link(g=9.0)                # a constant of the source changed
    assert other_g.key != two_link().key
    assert other_g.source("") == other_g.generate_source("") != base
    one = planar_arm(1)                      # another structure
    assert one.source("") == one.generate_source("")
    assert len(list(cache.glob("*.py"))) == 3


def test_a_new_ivdrem_version_regenerates(cache, monkeypatch):
    two_link().source("")
    calls = []
    # the printing itself (source and generate_source both call it; the disk keeps its text)
    real = type(two_link())._generate_body

    def counted(self, prefix=""):
        calls.append(prefix)
        return real(self, prefix)
    monkeypatch.setattr(type(two_link()), "_generate_body", counted)
    monkeypatch.setattr(ivdrem, "__version__", "99.0.0")
    assert two_link().source("") == two_link().generate_source("")
    assert calls == ["", ""]                 # once by source (not read), once by the check
    assert len(list(cache.glob("*.py"))) == 2


def test_an_entry_whose_header_does_not_match_is_not_read(cache):
    model = two_link()
    model.source("")
    (path,) = cache.glob("*.py")
    text = path.read_text()
    header, body = text.split("\n", 1)
    # same file name, another key in its first line (a truncated hash collision or a
    # hand-edited file): regenerated and rewritten
    path.write_text(header.replace(model.key, "0" * 64) + "\nGARBAGE = 1\n")
    assert two_link().source("") == linalg_import("") + body   # the kernels' import line first
    assert path.read_text() == text


def test_an_unwritable_cache_still_gives_the_source(cache, monkeypatch):
    import ivdrem._atomic

    def full(path, text, *a, **k):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))
    monkeypatch.setattr(ivdrem._atomic, "write_text_atomic", full)
    assert two_link().source("") == two_link().generate_source("")
    assert not list(cache.glob("*.py"))


def test_two_processes_filling_the_cache_at_once_both_succeed(tmp_path):
    code = ("import sys; from ivdrem.models import planar_arm; "
            "sys.stdout.write(planar_arm(2).source(''))")
    env = {**__import__("os").environ, "IVDREM_CACHE_DIR": str(tmp_path)}
    procs = [subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, env=env, text=True) for _ in range(2)]
    outs = [p.communicate(timeout=120) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], [e for _, e in outs]
    expected = planar_arm(2).generate_source("")
    assert outs[0][0] == outs[1][0] == expected
    (path,) = (tmp_path / "models").glob("*.py")
    # the file keeps the functions; source() puts the kernels' import line before them
    assert linalg_import("") + path.read_text().split("\n", 1)[1] == expected
    assert not list((tmp_path / "models").glob(".*.tmp"))


class _Terminal(io.StringIO):
    def isatty(self):
        return True


def test_generation_says_what_it_does_on_a_terminal_only(cache, monkeypatch):
    monkeypatch.delenv("CI", raising=False)
    tty = _Terminal()
    monkeypatch.setattr(sys, "stderr", tty)
    planar_arm(2).source("")
    said = tty.getvalue()
    assert "generating the code of model planar-2" in said and str(cache) in said
    assert "done in" in said
    # cached now: nothing to say
    tty.truncate(0), tty.seek(0)
    planar_arm(2).source("")
    assert tty.getvalue() == ""
    # --quiet, CI, a log file: never a note
    _progress.set_quiet(True)
    try:
        two_link(g=2.0).source("")
    finally:
        _progress.set_quiet(False)
    monkeypatch.setenv("CI", "1")
    planar_arm(1).source("")
    assert tty.getvalue() == ""
    monkeypatch.delenv("CI")
    log = io.StringIO()
    monkeypatch.setattr(sys, "stderr", log)
    two_link(g=1.0).source("")
    assert log.getvalue() == ""


def test_quiet_option_silences_notes_for_the_process(monkeypatch):
    from ivdrem import cli
    seen = []
    monkeypatch.setattr(cli, "_cmd_paper", lambda args: seen.append(_progress._quiet) or 0)
    try:
        assert cli.main(["paper", "--quiet"]) == 0
        assert seen == [True]
    finally:
        _progress.set_quiet(False)


def test_a_changed_kernel_helper_is_a_new_generated_module(tmp_path):
    """numba's cache sees a change in a cached function's own file only: a kernel that calls
    a changed helper of ivdrem.blocks._kernels would load machine code built from the old
    helper.  The helpers' digest stands in every generated module's text, so changing a
    helper file changes the digest, hence the module's name: compiled afresh."""
    from ivdrem import compile_cache
    from ivdrem.sim.compiled import _kernel_module
    from ivdrem.blocks.mixing import mixing_output
    root = tmp_path / "pkg"
    for rel in compile_cache.HELPER_FILES:
        dst = root / rel
        dst.parent.mkdir(parents=True, exist_ok=True)
        dst.write_bytes((Path(compile_cache.__file__).resolve().parent / rel).read_bytes())
    same = compile_cache.helpers_digest(root)
    assert same == compile_cache.helpers_digest()
    assert f"# helpers {same}" in compile_cache.GENERATED_HEADER
    name, src = _kernel_module(mixing_output, "def mixing_output(): pass\n", None)
    assert f"# helpers {same}" in src
    helper = root / compile_cache.HELPER_FILES[0]
    helper.write_text(helper.read_text() + "\n# a changed helper\n")
    assert compile_cache.helpers_digest(root) != same
