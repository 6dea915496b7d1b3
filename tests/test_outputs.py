"""One rule for every output file, and nothing lost when a write fails.

ivdrem replaces an existing file only if ivdrem wrote it (its own JSON, FMU, report);
anything else is refused before any work unless ``--overwrite``.  A result whose final
write fails is kept next to the target or in the temporary directory, with no empty file
left behind; temporaries a killed process left are removed by the next write.
"""
import errno
import json
import os
import tempfile
from pathlib import Path

import pytest

import ivdrem._paths as paths
from ivdrem._atomic import new_tempfile, write_text_atomic
from ivdrem.cli import main


def _synthetic(config, **kw):
    from ivdrem.reports.synthetic import synthetic_paper_run
    return synthetic_paper_run(config, dt=0.05)


@pytest.fixture
def fast_paper(monkeypatch):
    import ivdrem.experiments.paper as paper
    monkeypatch.setattr(paper, "run_paper", _synthetic)


# ----------------------------------------------------------------------------- the rule
def test_json_refuses_a_file_ivdrem_did_not_write(tmp_path, fast_paper, capsys):
    target = tmp_path / "notes.json"
    target.write_text('{"mine": 1}\n', encoding="utf-8")
    assert main(["paper", "--t-end", "30", "--json", str(target), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"refusing to overwrite {target}" in err and "--overwrite" in err
    assert target.read_text(encoding="utf-8") == '{"mine": 1}\n'
    # with --overwrite it is replaced by the results
    assert main(["paper", "--t-end", "30", "--json", str(target), "--quiet", "--overwrite"]) == 0
    assert set(json.loads(target.read_text())) == {"iv-drem", "composite-learning"}


def test_json_replaces_its_own_earlier_results(tmp_path, fast_paper):
    target = tmp_path / "out.json"
    assert main(["paper", "--t-end", "30", "--json", str(target), "--quiet"]) == 0
    first = target.stat().st_mtime_ns
    assert main(["paper", "--t-end", "30", "--json", str(target), "--quiet"]) == 0
    assert set(json.loads(target.read_text())) == {"iv-drem", "composite-learning"}
    assert target.stat().st_mtime_ns >= first


def test_fmu_export_refuses_a_file_ivdrem_did_not_write(tmp_path, capsys):
    target = tmp_path / "Plant.fmu"
    target.write_bytes(b"someone else's FMU")
    assert main(["fmu", "export", "--no-compile", "-o", str(target)]) == 2
    err = capsys.readouterr().err
    assert f"refusing to overwrite {target}" in err and "--overwrite" in err
    assert target.read_bytes() == b"someone else's FMU"
    assert main(["fmu", "export", "--no-compile", "-o", str(target), "--overwrite"]) == 0
    from ivdrem.fmu.export import is_ivdrem_fmu
    assert is_ivdrem_fmu(target)
    # an FMU ivdrem exported is replaced by the next export without the flag
    assert main(["fmu", "export", "--no-compile", "-o", str(target)]) == 0
    assert is_ivdrem_fmu(target)


# ----------------------------------------------------------------------------- never lost
def test_full_disk_keeps_the_results_in_tmpdir_and_leaves_no_empty_file(tmp_path, monkeypatch):
    """The target's directory is full: the atomic write fails there, and so does the
    fallback next to it; the text lands in $TMPDIR and nothing empty is left."""
    full = tmp_path / "full"
    full.mkdir()
    spare = tmp_path / "tmpdir"
    spare.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(spare))

    def no_space(path, text):
        raise OSError(errno.ENOSPC, "No space left on device (simulated)", str(path))
    monkeypatch.setattr(paths, "write_text_atomic", no_space)

    real_fdopen = os.fdopen

    class FullFile:
        def __init__(self, f):
            self.f = f

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.f.close()

        def write(self, text):
            raise OSError(errno.ENOSPC, "No space left on device (simulated)")

    def fdopen(fd, *a, **kw):
        f = real_fdopen(fd, *a, **kw)
        if Path(os.readlink(f"/proc/self/fd/{fd}")).parent == full:
            return FullFile(f)
        return f
    monkeypatch.setattr(paths.os, "fdopen", fdopen)

    where, err = paths.write_text_or_keep(full / "out.json", '{"iv-drem": {}}\n')
    assert err is not None and err.errno == errno.ENOSPC
    assert where.parent == spare and where.read_text(encoding="utf-8") == '{"iv-drem": {}}\n'
    assert list(full.iterdir()) == []          # no 0-byte fallback next to the target


def test_no_place_at_all_is_an_error_not_an_empty_file(tmp_path, monkeypatch):
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "missing"))

    def no_space(path, text):
        raise OSError(errno.ENOSPC, "No space left on device (simulated)", str(path))
    monkeypatch.setattr(paths, "write_text_atomic", no_space)
    monkeypatch.setattr(paths.tempfile, "mkstemp",
                        lambda **kw: (_ for _ in ()).throw(OSError(errno.ENOSPC, "full")))
    with pytest.raises(OSError, match="no writable place for the results"):
        paths.write_text_or_keep(tmp_path / "out.json", "x")
    assert list(tmp_path.iterdir()) == []


def test_a_killed_writers_temporaries_are_removed_by_the_next_write(tmp_path):
    dead = 2 ** 22 + 12345        # above the default pid_max: no such process
    with pytest.raises(ProcessLookupError):
        os.kill(dead, 0)
    stale = tmp_path / f".out.json.{dead}.abc123.tmp"
    stale.write_bytes(b"")
    alive = tmp_path / f".out.json.{os.getppid()}.def456.tmp"   # a running writer's
    alive.write_bytes(b"")
    other = tmp_path / f".other.json.{dead}.xyz.tmp"             # another target's
    other.write_bytes(b"")
    write_text_atomic(tmp_path / "out.json", "{}\n")
    assert not stale.exists()
    assert alive.exists() and other.exists()
    assert (tmp_path / "out.json").read_text() == "{}\n"
    # the temporaries themselves carry the writer's PID
    t = new_tempfile(tmp_path, "x.pdf")
    assert t.name.startswith(f".x.pdf.{os.getpid()}.") and t.name.endswith(".tmp")


def test_a_report_on_a_full_disk_is_kept_elsewhere_even_through_zlib(tmp_path, monkeypatch):
    """matplotlib's PDF writer, closing its file on a full disk, raises zlib.error on top of
    the ENOSPC: the report command still finds the OSError and writes the report elsewhere."""
    import zlib
    from ivdrem._atomic import os_error_behind
    import ivdrem.reports.report as report
    from ivdrem.cli.report import _write_or_keep
    calls = []

    def write_report(run, outdir, fmu_check=None, overwrite=False):
        calls.append(Path(outdir))
        if len(calls) == 1:
            try:
                raise OSError(errno.ENOSPC, "No space left on device")
            except OSError:
                raise zlib.error("Error -2 while flushing: buffer error")
        return Path(outdir) / "ivdrem-paper.html", Path(outdir) / "ivdrem-paper.pdf"
    monkeypatch.setattr(report, "write_report", write_report)
    html, pdf, failed = _write_or_keep(object(), tmp_path / "full", None, False)
    assert failed.errno == errno.ENOSPC and calls[0] == tmp_path / "full"
    assert html.parent == calls[1] != calls[0]
    assert os_error_behind(ValueError("no OSError in its chain")) is None
    with pytest.raises(KeyError):     # not a write failure: not hidden
        monkeypatch.setattr(report, "write_report", lambda *a, **k: {}["x"])
        _write_or_keep(object(), tmp_path / "full", None, False)
