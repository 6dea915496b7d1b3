"""Bad input fails before the work, with a message naming the problem; results are never lost.

One row per bad input: a new case is one line in CLI_CASES (command line, exit status,
a substring of the message) or API_CASES (a call, the exception type, a substring).
Placeholders in the rows are the files of the `inputs` fixture ({latin1}, {flipped}, ...)
and {ro}, a directory that cannot be written (the row is skipped where none can be made).
Every row runs with the `no_work` guard: starting a simulation, a co-simulation or an FMU
export fails the row, so "refused before any work" is what passes.  Rows marked "clean"
also check that no temporary file or extraction directory is left behind.

After the table: the cost guards' arithmetic (small limits, so nothing runs), relative
paths, results kept when the final write fails, the progress rule and the FMU's guard
against a second fmi2FreeInstance.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

import numpy as np
import pytest

from ivdrem.cli import main

ROOT = Path(__file__).resolve().parents[1]


# ----------------------------------------------------------------------------- inputs
def _flip_byte(src: Path, dst: Path, member: str) -> None:
    """Copy the zip `src` to `dst` with one byte of `member`'s compressed data inverted."""
    data = bytearray(src.read_bytes())
    with zipfile.ZipFile(src) as zf:
        info = zf.getinfo(member)
    # local file header: 30 bytes, then the name and the extra field (lengths at 26, 28)
    off = info.header_offset
    name_len = int.from_bytes(data[off + 26:off + 28], "little")
    extra_len = int.from_bytes(data[off + 28:off + 30], "little")
    data[off + 30 + name_len + extra_len + info.compress_size // 2] ^= 0xFF
    dst.write_bytes(bytes(data))


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """The bad files the rows refer to, made once (FMUs without compiling: fast)."""
    from ivdrem.fmu import export_fmu
    from ivdrem.models import get_model

    d = tmp_path_factory.mktemp("bad_input")
    files = {"d": d}

    def toml(name, text):
        (d / name).write_bytes(text if isinstance(text, bytes) else text.encode())
        files[name.split(".")[0]] = d / name

    toml("latin1.toml", b"[experiment]\nt_end = 3.0\n# caf\xe9 (Latin-1, not UTF-8)\n")
    toml("hmax_tiny.toml", "[solver]\nh_max = 1e-9\n")
    toml("dtout_tiny.toml", "[experiment]\ndt_out = 1e-9\n")
    toml("hmax_slow.toml", "[solver]\nh_max = 1e-5\n")          # 3e7 steps over 300 s
    (d / "afile").write_text("a plain file")
    files["afile"] = d / "afile"
    (d / "adir").mkdir()
    files["adir"] = d / "adir"
    (d / "foreign").mkdir()
    (d / "foreign" / "ivdrem-paper.pdf").write_text("the user's own file")
    files["foreign"] = d / "foreign"
    files["p3"] = export_fmu(get_model("planar-3"), d / "p3.fmu", compile=False)
    two = export_fmu(get_model("two-link"), d / "two.fmu", compile=False)
    _flip_byte(two, d / "flipped.fmu", "sources/fmi2_plant.c")
    files["flipped"] = d / "flipped.fmu"
    return files


def _unwritable_dir(base: Path) -> Path | None:
    """A directory that refuses new files: chmod for a normal user, chattr +i for root;
    None where neither works (e.g. root without CAP_LINUX_IMMUTABLE)."""
    d = base / "readonly"
    d.mkdir(exist_ok=True)
    if os.geteuid() != 0:
        d.chmod(0o555)
    elif subprocess.run(["chattr", "+i", str(d)], capture_output=True).returncode != 0:
        return None
    try:
        (d / "probe").write_text("x")
    except OSError:
        return d
    (d / "probe").unlink()
    return None


def _make_writable(d: Path) -> None:
    if os.geteuid() != 0:
        d.chmod(0o755)
    else:
        subprocess.run(["chattr", "-i", str(d)], capture_output=True)


@pytest.fixture
def ro(tmp_path):
    d = _unwritable_dir(tmp_path)
    if d is None:
        pytest.skip("cannot make an unwritable directory here")
    yield d
    _make_writable(d)


@pytest.fixture
def no_work(monkeypatch):
    """Any simulation, co-simulation or FMU generation fails the test."""
    import ivdrem.experiments.paper as paper
    import ivdrem.fmu.cosim as cosim
    import ivdrem.fmu.export as export
    import ivdrem.sim.simulator as simulator

    def refuse(*a, **k):
        raise AssertionError("work started although the input is bad")
    monkeypatch.setattr(paper, "run_paper", refuse)
    monkeypatch.setattr(cosim, "compare_to_python", refuse)
    monkeypatch.setattr(export, "generate_sources", refuse)
    monkeypatch.setattr(simulator, "Simulator", refuse)


@pytest.fixture
def clean_tmp(tmp_path, monkeypatch):
    """A private temporary directory for the row; returns a function listing leftovers."""
    t = tmp_path / "tmpdir"
    t.mkdir()
    monkeypatch.setenv("TMPDIR", str(t))
    monkeypatch.setattr(tempfile, "tempdir", str(t))
    return lambda: sorted(p.name for p in t.iterdir())


def _fill(args, files, request):
    out = []
    for a in args:
        if "{ro}" in a:
            a = a.replace("{ro}", str(request.getfixturevalue("ro")))
        out.append(a.format(**{k: str(v) for k, v in files.items()}))
    return out


# ----------------------------------------------------------------------------- the table
# (id, argv, exit status, substring of stderr, clean: also check no temporaries are left)
CLI_CASES = [
    ("config-not-utf8", ["paper", "--config", "{latin1}"], 2, "is not UTF-8 text", False),
    ("config-missing", ["paper", "--config", "{d}/nope.toml"], 2, "nope.toml' not found", False),
    ("t-end-1e9-memory", ["paper", "--t-end", "1e9"], 2, "TiB of output", False),
    ("t-end-1e9-names-flag", ["report", "--t-end", "1e9", "--out", "{d}/r"], 2, "--allow-long", False),
    ("h-max-below-bound", ["paper", "--config", "{hmax_tiny}"], 2, "'solver.h_max' must be > 0 (at least 1e-06 s)", False),
    ("dt-out-below-bound", ["paper", "--config", "{dtout_tiny}"], 2, "'experiment.dt_out' must be > 0 (at least 1e-06 s)", False),
    ("h-max-too-many-steps", ["paper", "--config", "{hmax_slow}"], 2, "needs at least 3e+07 steps (t_end / h_max = 300 / 1e-05)", False),
    ("method-unknown-paper", ["paper", "--method", "rk9"], 2, "--method 'rk9' is not a method", False),
    ("method-unknown-report", ["report", "--method", "euler", "--out", "{d}/r"], 2, "--method 'euler'", False),
    ("fmu-check-t-end-negative", ["report", "--fmu-check-t-end", "-1", "--out", "{d}/r"], 2, "--fmu-check-t-end must be a finite number of seconds > 0", False),
    ("fmu-check-t-end-not-ms", ["report", "--fmu-check-t-end", "0.0105", "--out", "{d}/r"], 2, "whole number of the check's largest communication step", False),
    ("fmu-check-t-end-huge", ["report", "--fmu-check-t-end", "1e6", "--out", "{d}/r"], 2, "the FMU check", False),
    ("report-out-is-a-file", ["report", "--out", "{afile}"], 2, "is not a directory", False),
    ("report-out-under-a-file", ["report", "--out", "{afile}/sub"], 2, "is not a directory", False),
    ("report-out-unwritable", ["report", "--out", "{ro}/rep"], 2, "report directory", True),
    ("report-foreign-file-names-cli-flag", ["report", "--out", "{foreign}"], 2, "ivdrem report --overwrite", False),
    ("json-is-a-directory", ["paper", "--json", "{adir}"], 2, "is a directory; give a file name", False),
    ("json-unwritable", ["paper", "--json", "{ro}/x.json"], 2, "JSON file", True),
    ("fmu-export-to-directory", ["fmu", "export", "-o", "{adir}"], 2, "is a directory; give a file name", True),
    ("fmu-export-unwritable", ["fmu", "export", "-o", "{ro}/x.fmu"], 2, "FMU file", True),
    ("cosim-t-end-negative", ["cosim", "--t-end", "-1"], 2, "--t-end must be a finite number > 0", False),
    ("cosim-t-end-not-whole-steps", ["cosim", "--t-end", "1.0005"], 2, "whole number of communication steps", False),
    ("cosim-t-end-huge", ["cosim", "--t-end", "1e6"], 2, "the reference run", False),
    ("cosim-fmu-missing", ["cosim", "--fmu", "{d}/missing.fmu"], 2, "FMU file not found", False),
    ("cosim-fmu-bit-flipped", ["cosim", "--fmu", "{flipped}"], 2, "the FMU archive is damaged", True),
    ("cosim-fmu-planar-3", ["cosim", "--fmu", "{p3}"], 2, "has n = 3 degrees of freedom", False),
]


@pytest.mark.parametrize("argv, status, message, clean",
                         [c[1:] for c in CLI_CASES], ids=[c[0] for c in CLI_CASES])
def test_cli_refuses_before_work(inputs, no_work, clean_tmp, request, capsys,
                                 argv, status, message, clean):
    before = sorted(os.listdir(inputs["d"]))
    assert main(_fill(argv + ["--quiet"] if argv[0] in ("paper", "report", "cosim") else argv,
                      inputs, request)) == status
    err = capsys.readouterr().err
    assert message in err, err
    assert "Traceback" not in err
    if clean:
        assert clean_tmp() == []
        assert sorted(os.listdir(inputs["d"])) == before     # no stray .part / .tmp
        for a in _fill(argv, inputs, request):
            p = Path(a)
            if p.is_dir():
                assert [q.name for q in p.iterdir() if q.name.startswith(".")] == []


@pytest.mark.parametrize("argv", [["paper", "--t-end", "1"], ["report", "--t-end", "1"],
                                  ["cosim", "--t-end", "1"]], ids=lambda a: a[0])
def test_cli_refuses_unwritable_cache_dir(inputs, no_work, ro, monkeypatch, capsys, argv):
    monkeypatch.setenv("IVDREM_CACHE_DIR", str(ro / "cache"))
    assert main(argv + ["--quiet"] + (["--out", str(inputs["d"] / "r")]
                                      if argv[0] == "report" else [])) == 2
    err = capsys.readouterr().err
    assert "compile cache directory (IVDREM_CACHE_DIR)" in err and str(ro) in err


def test_overwrite_flag_passes_the_foreign_file_check(inputs, monkeypatch, capsys):
    """The flag the refusal names exists and lets the run start."""
    import ivdrem.experiments.paper as paper

    def started(config, **kw):
        raise SystemExit(17)
    monkeypatch.setattr(paper, "run_paper", started)
    with pytest.raises(SystemExit) as info:
        main(["report", "--out", str(inputs["foreign"]), "--overwrite", "--quiet",
              "--no-fmu-check"])
    assert info.value.code == 17


def _fmu_plant(path, **kw):
    from ivdrem.fmu import fmu_plant
    return fmu_plant(path, **kw)


def _extract(path):
    from ivdrem.fmu.describe import extract_fmu
    return extract_fmu(path)


def _export(path):
    from ivdrem.fmu import export_fmu
    return export_fmu("two-link", path, compile=False)


def _load(path):
    from ivdrem.experiments.config import read_config, resolve_config
    return resolve_config(read_config(path))[0]


def _simulate(t_end, **kw):
    from conftest import build_lab
    from ivdrem.sim import simulate
    return simulate(build_lab(), t_end, progress=False, **kw)


def _simulate_io(**kw):
    """simulate() with python-control's arguments on a loop with inputs r, d and 5 states
    (tests/test_simulate_api.py), over timepts = 5 points of [0, 1] unless kw says."""
    from test_simulate_api import pendulum_loop
    from ivdrem.sim import simulate
    args = dict(timepts=np.linspace(0.0, 1.0, 5))
    args.update(kw)
    return simulate(pendulum_loop(), progress=False, **args)


_NAN_U = np.array([[0.0, 0.0, np.nan, 0.0, 0.0], [0.0] * 5])


def _foreign_report(d):
    from ivdrem.reports.report import report_paths
    return report_paths(d)


# (id, call taking the inputs dict, exception type, substring of the message, clean)
API_CASES = [
    ("load-config-not-utf8", lambda f: _load(f["latin1"]), "ConfigError", "not UTF-8", False),
    ("simulate-output-memory", lambda f: _simulate(1e5, dt_out=1e-4), "CostLimitError", "= 224 GiB of output (t_end = 100000 s, dt_out = 0.0001 s), above the limit of 2 GiB", False),
    ("simulate-t-end-1e9", lambda f: _simulate(1e9), "CostLimitError", "cannot finish: it needs at least 2e+10 steps", False),
    ("simulate-steps-rk4", lambda f: _simulate(1e6, method="rk4", h=1e-3, dt_out=1e3), "CostLimitError", "t_end / h = 1e+06 / 0.001", False),
    ("simulate-h-max-bound", lambda f: _simulate(1.0, h_max=1e-9), "ValueError", "h_max = 1e-09 s is below its lower bound 1e-06 s", False),
    ("simulate-dt-out-bound", lambda f: _simulate(1.0, dt_out=1e-9), "ValueError", "dt_out = 1e-09 s is below its lower bound", False),
    ("simulate-cannot-finish", lambda f: _simulate(100.0, max_steps=10, allow_long=True), "CostLimitError", "cannot finish", False),
    ("simulate-timepts-not-increasing", lambda f: _simulate_io(timepts=[0.0, 0.5, 0.5, 1.0]), "ValueError", "timepts must be strictly increasing: timepts[1] = 0.5, timepts[2] = 0.5", False),
    ("simulate-timepts-nan", lambda f: _simulate_io(timepts=[0.0, np.nan, 1.0]), "ValueError", "timepts[1] is nan: times must be finite", False),
    ("simulate-timepts-one-time", lambda f: _simulate_io(timepts=[1.0]), "ValueError", "timepts must hold at least 2 times", False),
    ("simulate-inputs-shape", lambda f: _simulate_io(inputs=np.zeros((2, 4))), "ValueError", "inputs has shape (2, 4); the diagram has 2 external inputs ['r', 'd']: give a number, a vector of 2 constants or an array of shape (2, 5) over timepts", False),
    ("simulate-inputs-transposed", lambda f: _simulate_io(inputs=np.zeros((5, 2))), "ValueError", "inputs has shape (5, 2) (transposed?)", False),
    ("simulate-inputs-nan", lambda f: _simulate_io(inputs=_NAN_U), "ValueError", "inputs has a non-finite entry (nan) for input r at timepts[2]", False),
    ("simulate-inputs-over-time-end-time", lambda f: _simulate_io(timepts=1.0, inputs=np.zeros((2, 5))), "ValueError", "an input over time needs timepts as an array of times", False),
    ("simulate-inputs-and-u", lambda f: _simulate_io(inputs=[1.0, 0.0], u=[1.0, 0.0]), "TypeError", "give inputs or u (its older name), not both", False),
    ("simulate-initial-state-size", lambda f: _simulate_io(initial_state=np.zeros(3)), "ValueError", "initial_state has 3 entries, the diagram has 5 states", False),
    ("simulate-initial-state-nan", lambda f: _simulate_io(initial_state=[0, 0, 0, np.nan, 0]), "ValueError", "initial_state has a non-finite entry (nan) for state pendulum_theta[0]", False),
    ("simulate-initial-state-subsystem", lambda f: _simulate_io(initial_state=[None, [1.0, 2.0], None]), "ValueError", "initial_state[1] has 2 entries, subsystem 'ctrl' has 1 state(s)", False),
    ("simulate-t-eval-outside", lambda f: _simulate_io(t_eval=[0.5, 2.0]), "ValueError", "t_eval must lie within the simulated interval [0.0, 1.0], got [0.5, 2.0]", False),
    ("simulate-t-eval-and-dt-out", lambda f: _simulate_io(t_eval=[0.5], dt_out=0.1), "TypeError", "give t_eval or dt_out, not both", False),
    ("fmu-plant-bit-flipped", lambda f: _fmu_plant(f["flipped"]), "ValueError", "the FMU archive is damaged", True),
    ("extract-bit-flipped", lambda f: _extract(f["flipped"]), "ValueError", "the FMU archive is damaged", True),
    ("fmu-plant-size-mismatch", lambda f: _fmu_plant(f["p3"], n=2), "ValueError", "has n = 3 degrees of freedom (signals q[0..2], dq, tau, tau_d), the loop's model has n = 2", True),
    ("export-to-directory", lambda f: _export(f["adir"]), "ValueError", "is a directory", True),
    ("report-foreign-file", lambda f: _foreign_report(f["foreign"]), "ReportError", "(command line: ivdrem report --overwrite)", False),
]


@pytest.mark.parametrize("call, exc_name, message, clean",
                         [c[1:] for c in API_CASES], ids=[c[0] for c in API_CASES])
def test_api_refuses_before_work(inputs, no_work, clean_tmp, call, exc_name, message, clean):
    before = sorted(os.listdir(inputs["d"]))
    with pytest.raises(Exception) as info:
        call(inputs)
    assert type(info.value).__name__ == exc_name, repr(info.value)
    assert message in str(info.value)
    if clean:
        assert clean_tmp() == []
        assert sorted(os.listdir(inputs["d"])) == before


def test_planar3_plant_in_two_link_loop_names_the_sizes(inputs):
    """check_plant_fits: what closed_loop's `replace` can call for a given plant block."""
    from ivdrem.fmu.plant import FmuPlantInfo, check_plant_fits

    class Block:
        fmu = FmuPlantInfo(path=inputs["p3"], model_description=None, n=3, x0=np.zeros(6),
                           parameters={}, messages=[], unzipdir=None)
    with pytest.raises(ValueError, match=r"n = 3 degrees of freedom.*model has n = 2"):
        check_plant_fits(Block(), 2)
    check_plant_fits(Block(), 3)
    check_plant_fits(object(), 2)          # not an FMU plant: nothing to check


# ----------------------------------------------------------------------------- cost guards
def test_cost_estimate_counts_what_simulate_allocates(lab):
    """The memory estimate = the arrays simulate() allocates (output times from the
    simulator's own grid), and the step bound = t_end / h_max."""
    from ivdrem.sim.guards import estimate_cost
    from ivdrem.sim.simulator import _output_times

    for t_end, dt_out in [(1.0, 0.01), (2.5, 0.3), (0.7305, 0.1), (3.0, 5.0)]:
        est = estimate_cost(t_end, noutputs=lab.noutputs, nstates=lab.nstates,
                            dt_out=dt_out, h_max=0.01)
        n = _output_times(0.0, t_end, min(dt_out, t_end)).size
        assert est.samples == n
        assert est.bytes == 8 * n * (lab.noutputs + lab.nstates)
        assert est.steps_min == pytest.approx(t_end / 0.01)
        no_states = estimate_cost(t_end, noutputs=lab.noutputs, nstates=lab.nstates,
                                  dt_out=dt_out, return_states=False)
        assert no_states.bytes == 8 * n * lab.noutputs


def test_step_bound_is_below_the_real_count(lab):
    """A lower bound: DP45 never takes more than h_max, RK4 takes exactly t_end / h."""
    from ivdrem.sim import simulate
    from ivdrem.sim.guards import estimate_cost
    r = simulate(lab, 2.0, method="rk4", h=0.01, dt_out=0.5, progress=False)
    est = estimate_cost(2.0, noutputs=1, method="rk4", h=0.01)
    assert r.stats["steps"] == pytest.approx(est.steps_min, abs=1)
    r = simulate(lab, 2.0, h_max=0.05, dt_out=0.5, progress=False)
    assert r.stats["steps"] >= estimate_cost(2.0, noutputs=1, h_max=0.05).steps_min


@pytest.mark.parametrize("kw, message", [
    (dict(max_bytes=1000), "above the limit of 0.000954 MiB"),
    (dict(max_steps_estimate=50), "needs at least 100 steps (t_end / h_max = 1 / 0.01), above the limit of 50"),
    (dict(max_steps_estimate=50, method="rk4", h=1e-3), "t_end / h = 1 / 0.001"),
    (dict(max_steps=10), "cannot finish"),
])
def test_small_limits_refuse_and_allow_long_lifts_them(kw, message):
    from ivdrem.sim.guards import CostLimitError, check_cost
    base = dict(noutputs=10, nstates=5, h_max=0.01, dt_out=0.01)
    with pytest.raises(CostLimitError) as info:
        check_cost(1.0, **base, **kw)
    assert message in str(info.value)
    if "max_steps" not in kw:      # a run that cannot finish stays refused
        check_cost(1.0, **base, **kw, allow_long=True)
        assert "--allow-long" in str(info.value)


def test_config_bounds_equal_the_guards():
    from ivdrem.experiments.config import ConfigError, read_config, resolve_config
    from ivdrem.sim.guards import DT_OUT_MIN, H_MAX_MIN
    resolve_config(read_config(overrides={"solver.h_max": H_MAX_MIN, "experiment.dt_out": DT_OUT_MIN}))[0]
    for key, low in (("solver.h_max", H_MAX_MIN), ("experiment.dt_out", DT_OUT_MIN)):
        with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
            resolve_config(read_config(overrides={key: low * 0.99}))[0]


def test_allow_long_reaches_simulate(monkeypatch, capsys):
    """--allow-long lifts the CLI's check and is passed on to simulate()."""
    import ivdrem.experiments.paper as paper
    seen = {}

    def fake(config, **kw):
        seen.update(kw)
        raise SystemExit(0)
    monkeypatch.setattr(paper, "run_paper", fake)
    with pytest.raises(SystemExit):
        main(["paper", "--t-end", "1e8", "--quiet", "--allow-long", "--law", "iv-drem"])
    assert seen["allow_long"] is True


# ----------------------------------------------------------------------------- paths
def test_relative_paths_are_the_callers(tmp_path, monkeypatch, capsys):
    """IVDREM_CALLER_CWD (set by ./run) is where relative paths start; printed absolute."""
    caller = tmp_path / "caller"
    caller.mkdir()
    (caller / "my.toml").write_text("[controller]\nKp = [1.0, 1.0]\n")   # read => named key
    monkeypatch.setenv("IVDREM_CALLER_CWD", str(caller))
    monkeypatch.chdir(tmp_path)
    assert main(["paper", "--config", "my.toml", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "controller.Kp" in err and "not found" not in err
    assert main(["fmu", "export", "--no-compile", "-o", "rel.fmu"]) == 0
    out = capsys.readouterr().out
    assert (caller / "rel.fmu").is_file() and not (tmp_path / "rel.fmu").exists()
    assert f"wrote {caller / 'rel.fmu'} " in out


def test_run_script_passes_the_callers_directory(tmp_path):
    """./run cds into the clone; a relative -o still lands where the user is."""
    if not (ROOT / ".venv" / "bin" / "ivdrem").exists():
        pytest.skip("no .venv (run the tests through ./run test)")
    p = subprocess.run([str(ROOT / "run"), "fmu", "export", "--no-compile", "-o", "x.fmu"],
                       cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    assert (tmp_path / "x.fmu").is_file() and str(tmp_path / "x.fmu") in p.stdout
    assert not (ROOT / "x.fmu").exists()


# ----------------------------------------------------------------------------- never lost
def _synthetic(config, **kw):
    from ivdrem.reports.synthetic import synthetic_paper_run
    return synthetic_paper_run(config, dt=0.05)


def test_json_kept_when_the_final_write_fails(tmp_path, monkeypatch, capsys):
    import ivdrem._paths as paths
    import ivdrem.experiments.paper as paper
    monkeypatch.setattr(paper, "run_paper", _synthetic)

    def broken(path, text):
        raise PermissionError(13, "Permission denied (simulated)", str(path))
    monkeypatch.setattr(paths, "write_text_atomic", broken)
    target = tmp_path / "out.json"
    assert main(["paper", "--t-end", "30", "--json", str(target), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert f"cannot write {target}" in err and "the results were kept in" in err
    kept = Path(err.split("the results were kept in ")[1].split()[0])
    data = json.loads(kept.read_text())
    assert set(data) == {"iv-drem", "composite-learning"} and not target.exists()
    assert kept.parent == tmp_path          # next to the target: that directory was writable


def test_report_kept_when_the_final_write_fails(tmp_path, monkeypatch, capsys, clean_tmp):
    import ivdrem.experiments.paper as paper
    import ivdrem.reports.report as report
    monkeypatch.setattr(paper, "run_paper", _synthetic)
    real = report.write_report
    calls = []

    def flaky(run, outdir, **kw):
        calls.append(Path(outdir))
        if len(calls) == 1:
            raise PermissionError(13, "Permission denied (simulated)", str(outdir))
        return real(run, outdir, **kw)
    monkeypatch.setattr(report, "write_report", flaky)
    out = tmp_path / "rep"
    assert main(["report", "--out", str(out), "--t-end", "30", "--quiet", "--no-fmu-check"]) == 1
    captured = capsys.readouterr()
    assert "cannot write the report to" in captured.err and "kept in" in captured.err
    keep = calls[1]
    assert (keep / "ivdrem-paper.html").is_file() and (keep / "ivdrem-paper.pdf").is_file()
    assert str(keep / "ivdrem-paper.pdf") in captured.out
    assert Path(tempfile.gettempdir()) in keep.parents


# ----------------------------------------------------------------------------- messages
def test_short_horizon_note(monkeypatch, capsys, tmp_path):
    import ivdrem.experiments.paper as paper
    monkeypatch.setattr(paper, "run_paper", _synthetic)
    assert main(["paper", "--t-end", "30", "--quiet"]) == 0
    assert "shorter than the 300 s horizon that conclusions C1-C3" in capsys.readouterr().err


def test_a_run_shorter_than_the_window_prints_no_conclusion(monkeypatch, capsys):
    """`ivdrem paper --t-end 1`: the window T is not full, so no C1-C3 line (a verdict about
    learning the run cannot show); the diagnostics' note says why.  At 30 s they print."""
    import ivdrem.experiments.paper as paper
    monkeypatch.setattr(paper, "run_paper", _synthetic)
    assert main(["paper", "--t-end", "1", "--quiet"]) == 0
    out = capsys.readouterr()
    lines = (out.out + out.err).splitlines()
    assert not [ln for ln in lines if ln.startswith(("C1 ", "C2 ", "C3 "))]
    assert any("not evaluated: the run ends at t = 1 s, before the window" in ln for ln in lines)
    assert main(["paper", "--t-end", "30", "--quiet"]) == 0
    out = capsys.readouterr()
    assert [ln for ln in (out.out + out.err).splitlines() if ln.startswith("C2 ")]


def test_timing_text_splits_compile_and_simulation():
    from ivdrem.cli.preflight import timing_text
    assert timing_text({"compile_s": 38.6, "sim_s": 0.08, "wall_s": 38.7}) == \
        "compile 38.60 s + simulation 0.08 s"
    assert timing_text({"wall_s": 1.5}) == "1.50 s"


def test_method_override_reaches_the_config(monkeypatch):
    import ivdrem.experiments.paper as paper
    seen = {}

    def fake(experiment, **kw):       # the command's Experiment of its configuration
        seen["method"] = experiment.config["solver"]["method"]
        raise SystemExit(0)
    monkeypatch.setattr(paper, "run_paper", fake)
    with pytest.raises(SystemExit):
        main(["paper", "--method", "rk4", "--t-end", "1", "--quiet", "--law", "iv-drem"])
    assert seen["method"] == "rk4"


# ----------------------------------------------------------------------------- progress
class _Stream:
    def __init__(self, tty):
        self.tty = tty

    def isatty(self):
        return self.tty


@pytest.mark.parametrize("tty, ci, requested, shown", [
    (True, None, None, True), (True, None, True, True), (True, None, False, False),
    (True, "1", None, False), (True, "1", True, False), (False, None, True, False),
    (False, None, None, False),
])
def test_progress_rule(monkeypatch, tty, ci, requested, shown):
    from ivdrem._progress import want_progress
    from ivdrem.fmu import cosim
    if ci is None:
        monkeypatch.delenv("CI", raising=False)
    else:
        monkeypatch.setenv("CI", ci)
    monkeypatch.setattr(sys, "stderr", _Stream(tty))
    assert want_progress(requested) is shown
    assert cosim._want_progress(requested) is shown   # the co-simulation bars: same rule


@pytest.mark.parametrize("requested", [None, True])
def test_a_commands_quiet_silences_every_bar(monkeypatch, requested):
    """A command's --quiet (set_quiet) wins over a bar asked for on a terminal: bars drawn by
    code the command calls without a progress argument (the export's stability prediction)
    stay silent too; the rule is back once the command ends."""
    from ivdrem import _progress
    monkeypatch.delenv("CI", raising=False)
    monkeypatch.setattr(sys, "stderr", _Stream(True))
    monkeypatch.setattr(_progress, "_quiet", False)
    assert _progress.want_progress(requested) is True
    _progress.set_quiet(True)
    assert _progress.want_progress(requested) is False
    _progress.set_quiet(False)
    assert _progress.want_progress(requested) is True


def test_fmu_export_takes_quiet(monkeypatch):
    """`ivdrem fmu export ... --quiet` parses (the controller's export draws the stability
    prediction's bar) and sets the process quiet for the command."""
    from ivdrem import _progress
    from ivdrem.cli import fmu as fcli
    args = fcli._parser().parse_args(["export", "--controller", "-o", "x.fmu", "--quiet"])
    assert args.quiet is True
    seen = {}

    def fake_fmu(argv):
        seen["quiet"] = _progress._quiet
        return 0
    monkeypatch.setattr(fcli, "main_fmu", fake_fmu)
    assert main(["fmu", "export", "--controller", "-o", "x.fmu", "--quiet"]) == 0
    assert seen["quiet"] is True and _progress._quiet is False    # over with the command


# ----------------------------------------------------------------------------- FMU
_DOUBLE_FREE_HOST = r"""
import ctypes, sys
lib = ctypes.CDLL(sys.argv[1])
lib.fmi2Instantiate.restype = ctypes.c_void_p
lib.fmi2Instantiate.argtypes = [ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p,
                                ctypes.c_char_p, ctypes.c_void_p, ctypes.c_int, ctypes.c_int]
lib.fmi2FreeInstance.argtypes = [ctypes.c_void_p]
callbacks = (ctypes.c_void_p * 5)()          # logger, allocate, free, stepFinished, env: NULL
c = lib.fmi2Instantiate(b"x", 0, sys.argv[2].encode(), b"", ctypes.addressof(callbacks), 0, 0)
assert c, "fmi2Instantiate failed"
lib.fmi2FreeInstance(c)
lib.fmi2FreeInstance(c)                       # undefined in FMI 2.0; must not abort
print("survived")
"""


def test_second_free_instance_does_not_abort(tmp_path):
    from fmpy import read_model_description

    from ivdrem.fmu import export_fmu
    from ivdrem.fmu.describe import extract_fmu
    fmu = export_fmu("two-link", tmp_path / "p.fmu")
    d = Path(extract_fmu(fmu))
    try:
        md = read_model_description(str(fmu))
        (so,) = list((d / "binaries").rglob("*.so"))
        p = subprocess.run([sys.executable, "-c", _DOUBLE_FREE_HOST, str(so), md.guid],
                           capture_output=True, text=True, timeout=60)
    finally:
        import shutil
        shutil.rmtree(d)
    assert p.returncode == 0, (p.returncode, p.stderr)
    assert "survived" in p.stdout


def test_fmu_export_failing_mid_write_leaves_nothing(tmp_path, monkeypatch):
    """A write error while zipping (disk full, say) leaves neither a partial FMU nor the
    hidden temporary, and an FMU already at the target stays as it was."""
    from ivdrem.fmu import export_fmu
    target = tmp_path / "Plant.fmu"
    target.write_bytes(b"the previous FMU")

    def full(self, *a, **k):
        raise OSError(28, "No space left on device (simulated)")
    monkeypatch.setattr(zipfile.ZipFile, "write", full)
    with pytest.raises(OSError, match="No space left"):
        export_fmu("two-link", target, compile=False, overwrite=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["Plant.fmu"]
    assert target.read_bytes() == b"the previous FMU"


# ----------------------------------------------------------------------------- run time
def test_run_time_guard_from_the_measured_cost_of_the_paper_loop():
    """`paper`/`report --engine reference` at the default horizon: refused before any run
    with the estimate from measured step counts and times per step (about 19 + 22 min),
    not the lower bound t_end / h_max (tens of steps); the paper's default runs on the
    compiled engine, one law on the reference engine and --allow-long are accepted."""
    from ivdrem.cli.preflight import check_runs
    from ivdrem.experiments.config import read_config, resolve_config
    from ivdrem.sim.guards import CostLimitError
    config = resolve_config(read_config(None))[0]
    with pytest.raises(CostLimitError, match=r"the 2 runs would take about 40 min on the "
                       r"reference engine \(iv-drem 19 min \+ composite-learning 22 min"):
        check_runs(config, engine="reference")
    check_runs(config, engine="compiled")
    check_runs(config, engine="reference", allow_long=True)
    check_runs(resolve_config(read_config(None, {"experiment.laws": ["iv-drem"]}))[0], engine="reference")
    with pytest.raises(CostLimitError, match=r"the iv-drem run \(900 s\) would take about 56 "
                       "min on the reference engine"):
        check_runs(resolve_config(read_config(None, {"experiment.laws": ["iv-drem"],
                                      "experiment.t_end": 900.0}))[0], engine="reference")


@pytest.mark.parametrize("law", ["iv-drem", "composite-learning"])
def test_the_measured_step_table_matches_a_run(law):
    """The table's step counts against a fresh 300 s run with the configuration's
    defaults (Rodas5P, the paper's loop): implicit and explicit steps within 10 %."""
    from ivdrem.sim import simulate
    from ivdrem.sim.guards import paper_loop_steps
    from conftest import paper_loop
    run = simulate(paper_loop(law), 300.0, progress=False)
    (steps, explicit), _ = paper_loop_steps(law, "rodas5p", 300.0)
    st = run.stats
    assert st["steps"] - st["explicit_steps"] == pytest.approx(steps, rel=0.1)
    assert st["explicit_steps"] == pytest.approx(explicit, rel=0.1, abs=10)
