"""A user who types absurd values, and file systems that refuse writes: each case listed
with what it must do (a clear message naming the key or option, exit status 2, before any
run starts; nothing lost, no traceback).

Cases covered elsewhere, not repeated here: bad files, read-only report / JSON / FMU
locations and the unwritable compile cache (test_bad_input.py), a full disk at the final
write of ``paper --json`` and ``report`` (test_bad_input.py), a full or read-only cache for
a model's generated source (test_model_cache.py), study files (test_study.py).
"""
from __future__ import annotations

import errno
import math
import tempfile
import time

import pytest

from ivdrem.cli import main
from ivdrem.experiments.config import ConfigError, read_config, resolve_config

#: what the sweep tries in every numeric key (the first entry of a vector key)
ABSURD = (0.0, -1.0, 1e-300, 1e300, math.nan, math.inf, -math.inf)

#: the keys where zero and negative values are meaningful (an angle, an offset, a signed
#: gain of the reference, a start value, the sign of gravity, σ = 0 and μ0 = 0); every other
#: numeric key must refuse 0 and -1
SIGNED_OR_ZERO = {
    "model.g", "initial.q0", "initial.dq0", "initial.theta_hat0", "controller.mu0",
    "sigma_modification.theta_star",
    *(f"{s}.{k}" for s in ("trajectory", "disturbance")
      for k in ("amplitude", "omega", "phase", "offset")),
    # model.theta: refused by the commands' preflight (M(q0) not positive definite)
    "model.theta",
}


def _numeric_keys():
    """Every numeric key of the embedded configuration, vector keys too (a new key is swept
    without editing this file)."""
    out = []
    for section, table in resolve_config(read_config())[0].items():
        if not isinstance(table, dict):
            continue
        for key, value in table.items():
            num = lambda v: isinstance(v, (int, float)) and not isinstance(v, bool)
            if num(value) or (isinstance(value, list) and value and all(map(num, value))):
                out.append((section, key, value))
    return out


def _with(value, bad):
    return [bad] + list(value[1:]) if isinstance(value, list) else bad


def test_every_numeric_config_key_refuses_absurd_values_naming_the_key():
    keys = _numeric_keys()
    assert len(keys) >= 30            # the sweep really walks the configuration
    wrong = []
    for section, key, value in keys:
        name = f"{section}.{key}"
        for bad in ABSURD:
            t0 = time.perf_counter()
            try:
                resolve_config(read_config(overrides={name: _with(value, bad)}))[0]
                outcome = "accepted"
            except ConfigError as exc:
                outcome = "refused" if name in str(exc) else f"key not named: {exc}"
            except Exception as exc:           # noqa: BLE001 - the point of the sweep
                outcome = f"{type(exc).__name__}: {exc}"
            must_refuse = (not math.isfinite(bad)
                           or (bad <= 0 and name not in SIGNED_OR_ZERO))
            if outcome not in ("accepted", "refused") or (must_refuse and outcome != "refused"):
                wrong.append(f"{name} = {bad!r}: {outcome}")
            assert time.perf_counter() - t0 < 5.0, f"{name} = {bad!r} took long to check"
    assert not wrong, "\n".join(wrong)


@pytest.fixture
def runs_refused(monkeypatch):
    """Reaching a run, a study's cluster or a co-simulation is recorded as 'work'."""
    import dask.distributed
    import ivdrem.experiments.paper as paper
    import ivdrem.fmu.cosim as cosim

    class Work(Exception):
        pass

    def refuse(*a, **k):
        raise Work()
    monkeypatch.setattr(paper, "run_paper", refuse)
    monkeypatch.setattr(dask.distributed, "LocalCluster", refuse)   # after --workers' checks
    monkeypatch.setattr(dask.distributed, "Client", refuse)
    monkeypatch.setattr(cosim, "compare_to_python", refuse)
    return Work


def _cli(argv, capsys, work):
    try:
        status = main(argv)
    except work:
        status = "work"
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return status, err


def _toml(tmp_path, text, name="c.toml"):
    p = tmp_path / name
    p.write_text(text)
    return str(p)


# (argv, the message's words); every row: exit status 2 before any work
OPTION_CASES = [
    *[(["paper", "--t-end", v], "--t-end must be a finite number of seconds > 0")
      for v in ("0", "-1", "nan", "inf")],
    (["paper", "--t-end", "1e-300"], "--t-end 1e-300 s: config key 'experiment.dt_out'"),
    (["paper", "--t-end", "1e300"], "TiB of output"),
    *[(["report", "--fmu-check-t-end", v, "--out", "{tmp}/r"], "--fmu-check-t-end") for v in
      ("0", "-1", "nan", "inf", "1e-300", "1e300")],
    *[(["cosim", "--t-end", v], "--t-end must be a finite number > 0") for v in ("0", "-1", "nan", "inf")],
    (["cosim", "--t-end", "1e300"], "the reference run"),
    *[(["study", "{study}", "--workers", v, "--out", "{tmp}/s"], "--workers") for v in
      ("0", "-1", "1000000")],
]


@pytest.mark.parametrize("argv, words", OPTION_CASES,
                         ids=[" ".join(a[:1] + a[-2:] if a[0] == "study" and "--out" in a
                                       else a[:3]) for a, _ in OPTION_CASES])
def test_absurd_option_values_are_refused_before_work(argv, words, tmp_path, capsys,
                                                      runs_refused, monkeypatch):
    import ivdrem.experiments.study as study
    monkeypatch.setattr(study.os, "cpu_count", lambda: 2)    # a 2-core machine
    spec = _toml(tmp_path, '[experiment]\nt_end = 1.0\nlaws = ["iv-drem"]\n'
                           '[study.grid]\n"controller.alpha" = [1.0]\n', "s.toml")
    argv = [a.format(tmp=tmp_path, study=spec) for a in argv] + ["--quiet"]
    status, err = _cli(argv, capsys, runs_refused)
    assert status == 2, err
    assert words in err, err


def test_a_physically_impossible_theta_is_refused_before_the_run(tmp_path, capsys, runs_refused):
    for theta in ("[0.0, 0.28, 0.32, 0.4, 1.4]", "[-1.0, 0.28, 0.32, 0.4, 1.4]"):
        cfg = _toml(tmp_path, f"[model]\ntheta = {theta}\n")
        status, err = _cli(["paper", "--quiet", "--config", cfg], capsys, runs_refused)
        assert status == 2
        assert "'model.theta'" in err and "not positive definite" in err
    # the paper's θ passes the same check and reaches the run
    cfg = _toml(tmp_path, "[model]\ntheta = [1.3, 0.28, 0.32, 0.4, 1.4]\n")
    assert _cli(["paper", "--quiet", "--config", cfg], capsys, runs_refused)[0] == "work"


def test_a_study_whose_runs_are_too_big_is_refused_before_the_cluster(tmp_path, capsys,
                                                                      runs_refused):
    spec = _toml(tmp_path, '[experiment]\nlaws = ["iv-drem"]\n'
                           '[study.grid]\n"experiment.t_end" = [10.0, 1e12]\n', "big.toml")
    status, err = _cli(["study", spec, "--out", str(tmp_path / "s"), "--quiet"], capsys,
                       runs_refused)
    assert status == 2
    assert "experiment.t_end = 1e+12" in err and "TiB of output" in err
    assert "has no --allow-long" in err
    assert "command line: --allow-long" not in err     # no remedy the command lacks
    assert not (tmp_path / "s").exists()
    # the same study without the absurd point reaches the cluster
    ok = _toml(tmp_path, '[experiment]\nlaws = ["iv-drem"]\n'
                         '[study.grid]\n"experiment.t_end" = [10.0, 20.0]\n', "ok.toml")
    assert _cli(["study", ok, "--out", str(tmp_path / "s2"), "--quiet"], capsys,
                runs_refused)[0] == "work"


@pytest.mark.parametrize("code, words", [(errno.EROFS, "Read-only file system"),
                                         (errno.ENOSPC, "No space left on device")])
def test_an_unwritable_study_directory_is_refused_before_the_cluster(tmp_path, capsys,
                                                                     runs_refused, monkeypatch,
                                                                     code, words):
    import os
    real = tempfile.mkstemp
    parent = tmp_path / "mount"
    parent.mkdir()

    def refusing(*a, dir=None, **k):   # the probe of the output location fails there
        if dir is not None and str(dir).startswith(str(parent)):
            raise OSError(code, os.strerror(code))
        return real(*a, dir=dir, **k)
    monkeypatch.setattr(tempfile, "mkstemp", refusing)
    spec = _toml(tmp_path, '[experiment]\nt_end = 1.0\nlaws = ["iv-drem"]\n'
                           '[study.grid]\n"controller.alpha" = [1.0]\n', "s.toml")
    status, err = _cli(["study", spec, "--out", str(parent / "s"), "--quiet"], capsys,
                       runs_refused)
    assert status == 2
    assert "study directory (--out)" in err and words in err
    assert list(parent.iterdir()) == []


def _schema_numeric_keys():
    """Every numeric key of the configuration schema (a new key is swept automatically)."""
    from ivdrem.experiments.config import schema
    return sorted(f"{section}.{key}" for section, keys in schema().items()
                  for key, spec in keys.items()
                  if spec.kind in ("float", "float_or_auto", "float_or_vec", "vec"))


#: keys where a value of 1e-300 divides by almost zero or asks for endless steps: refused
TINY_REFUSED = {"experiment.t_end", "experiment.dt_out", "controller.mu1", "iv_drem.T",
                "iv_drem.p", "composite_learning.T", "solver.rtol", "solver.atol", "solver.h",
                "solver.h_max"}


@pytest.mark.parametrize("name", _schema_numeric_keys())
def test_absurd_magnitudes_are_refused_naming_the_key_and_its_range(name):
    """1e300 overflows the loop's first products and 1e-300 in a divisor gives inf: both are
    refused by the configuration, with the key and the accepted range, before any run
    (experiment.t_end = 1e300 is refused by the cost guard, test above)."""
    section, key = name.split(".")
    value = resolve_config(read_config())[0][section][key]
    cases = [1e300] if name != "experiment.t_end" else []
    if name in TINY_REFUSED:
        cases.append(1e-300)
    for bad in cases:
        with pytest.raises(ConfigError) as exc:
            resolve_config(read_config(overrides={name: _with(value, bad)}))[0]
        text = str(exc.value)      # its range, or the other key it must stay below
        assert name in text and ("must be" in text or "exceeds" in text), text


def test_the_paper_values_and_documented_examples_stay_inside_the_ranges():
    """The ranges refuse absurd values only: the paper's γ = 1e10, and every example file."""
    from pathlib import Path
    resolve_config(read_config(overrides={"iv_drem.gamma": 1e10, "controller.mu1": 15.0}))[0]
    for p in sorted(Path(__file__).parent.parent.joinpath("examples").glob("*.toml")):
        # study files (study-*.toml, and the MuJoCo robustness study's [robustness]) are
        # not configurations of one run
        if not p.name.startswith("study") and "[robustness]" not in p.read_text():
            resolve_config(read_config(p))[0]


def test_a_tiny_observer_weight_is_refused_not_run_into_numba_noise(capsys, runs_refused,
                                                                      tmp_path):
    cfg = _toml(tmp_path, "[controller]\nmu1 = 1e-300\n")
    status, err = _cli(["paper", "--quiet", "--config", cfg], capsys, runs_refused)
    assert status == 2 and "'controller.mu1' must be > 0 (at least 1e-06)" in err
    assert "Exception ignored" not in err


def test_an_absurd_theta_is_refused_naming_the_key(capsys, runs_refused, tmp_path):
    cfg = _toml(tmp_path, "[model]\ntheta = [1e300, 0.28, 0.32, 0.4, 1.4]\n")
    status, err = _cli(["paper", "--quiet", "--config", cfg], capsys, runs_refused)
    assert status == 2 and "'model.theta" in err and "at most 1e+06" in err


# ----------------------------------------------------------------------------- steps
@pytest.mark.parametrize("text, words", [
    ('[solver]\nmethod = "rk4"\nh = 10.0\n',
     "'solver.h' = 10 s (the fixed step of rk4) exceeds solver.h_max = 5 s"),
    ('[solver]\nmethod = "rk4"\nh = 12.0\nh_max = 20.0\n',
     "exceeds 10 s, half the sliding window iv_drem.T of law 'iv-drem'"),
    ('[solver]\nmethod = "rk4"\nh = 4.0\n[composite_learning]\nT = 6.0\n',
     "half the sliding window composite_learning.T of law 'composite-learning'"),
])
def test_a_step_above_its_bounds_is_refused_naming_both_keys(text, words, tmp_path, capsys,
                                                            runs_refused):
    """A fixed step solver.h above solver.h_max or above half a law's window T (eq. 14) is
    a configuration error naming both keys, not the simulator's ValueError after the build."""
    cfg = _toml(tmp_path, text)
    status, err = _cli(["paper", "--quiet", "--config", cfg], capsys, runs_refused)
    assert status == 2, err
    assert words in err, err


def test_a_fast_disturbance_is_priced_from_its_periods(tmp_path, capsys, runs_refused):
    """ω = 5e3 rad/s: at least one step per period (2.4e5 steps over 300 s) prices the
    reference engine's run at hours, refused before any run naming ω; the compiled
    engine's estimate stays under the limit and the run is reached."""
    from ivdrem.cli.preflight import check_runs, fastest_omega
    from ivdrem.sim.guards import CostLimitError, oscillation_steps
    (steps, _), _ = oscillation_steps(5000.0, 300.0)
    assert steps == pytest.approx(5000.0 * 300.0 / (2 * math.pi))
    config = resolve_config(read_config(None, {"disturbance.omega": [5000.0, 500.0],
                                "experiment.laws": ["iv-drem"]}))[0]
    assert fastest_omega(config) == 5000.0
    paper = resolve_config(read_config(None))[0]     # the paper's fastest sinusoid: the reference, 2 rad/s
    assert fastest_omega(paper) == max(paper["trajectory"]["omega"] + paper["disturbance"]["omega"])
    with pytest.raises(CostLimitError, match=r"12.6 h on the reference engine .*ω = 5000 rad/s"):
        check_runs(config, engine="reference")
    cfg = _toml(tmp_path, "[disturbance]\nomega = [5000.0, 500.0]\n")
    status, err = _cli(["paper", "--quiet", "--engine", "reference", "--config", cfg], capsys,
                       runs_refused)
    assert status == 2 and "ω = 5000 rad/s" in err, err
    status, err = _cli(["paper", "--quiet", "--config", cfg], capsys, runs_refused)
    assert status == "work", err


def test_an_adaptive_first_step_is_held_under_the_step_bound():
    """An adaptive method's h is only its first step: a small h_max (or window) lowers it
    instead of refusing the configuration."""
    from ivdrem.experiments.config import solver_kwargs
    c = resolve_config(read_config(None, {"solver.h_max": 1e-4}))[0]
    assert solver_kwargs(c, "iv-drem")["h"] == 1e-4
    c = resolve_config(read_config(None, {"solver.h": 4.0, "iv_drem.T": 6.0}))[0]
    kw = solver_kwargs(c, "iv-drem")
    assert kw["h"] == kw["h_max"] == 3.0
    assert solver_kwargs(resolve_config(read_config(None))[0], "iv-drem")["h"] == 1e-3     # the paper's, as set
