"""Parameter studies: study files, validation, execution on dask.distributed, resume, report.

Compile budget: the studies here use closed_loop("iv-drem") and
closed_loop("composite-learning") with the default structure (only parameter values vary),
the two diagrams the rest of the suite compiles too; the module fixture `paper_runs`
compiles them in this process before any cluster starts, so the workers load them from
the shared disk cache.
"""
from __future__ import annotations

import json
import re
import math
import os
import signal
import socket
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from ivdrem.cli import main
from ivdrem.experiments import metrics
from ivdrem.experiments.config import dump_toml, read_config
from ivdrem.experiments.paper import run_paper
from ivdrem.experiments.study import RunStore, run_study
from ivdrem.reports.study_report import write_study_report_of
from ivdrem.experiments.study_spec import StudyError, expand_study, read_study

T_END = 5.0
#: both laws' windows shorter than the horizon, so that C1-C3 are judged (a run ending
#: before its window is full gives them no verdict)
WINDOW = 2.0
GRID = {"experiment": {"t_end": T_END}, "iv_drem": {"T": WINDOW},
        "composite_learning": {"T": WINDOW},
        "study": {"grid": {"controller.alpha": [1.0, 1.5]}}}  # both laws read alpha: 4 runs
TIMING = ["sim_s", "compile_s", "task_s"]


def _point_configs():
    """The two configurations of GRID, each written out and read back as `--config` would."""
    return [read_config(None, {"experiment.t_end": T_END, "iv_drem.T": WINDOW,
                               "composite_learning.T": WINDOW, "controller.alpha": a})
            for a in (1.0, 1.5)]


@pytest.fixture(scope="module")
def paper_runs(tmp_path_factory):
    """The GRID runs through the code path of `ivdrem paper --config FILE` (in-process)."""
    out = []
    for i, cfg in enumerate(_point_configs()):
        path = tmp_path_factory.mktemp("cfg") / f"point{i}.toml"
        path.write_text(dump_toml(cfg), encoding="utf-8")
        out.append(run_paper(read_config(path), progress=False))
    return out


@pytest.fixture(scope="module")
def grid_study(paper_runs, tmp_path_factory):
    """GRID on the default local cluster: 2 single-threaded worker processes (one per core),
    TCP on 127.0.0.1."""
    out = tmp_path_factory.mktemp("grid")
    result = run_study(GRID, out, workers=min(2, os.cpu_count() or 1), progress=False)
    return out, result.results, result


@pytest.fixture(scope="module")
def cluster(paper_runs):
    """A running cluster for the --scheduler path: 2 worker processes behind nannies."""
    import logging

    from dask.distributed import LocalCluster
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Port .* is already in use")
        c = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                         dashboard_address=None, silence_logs=logging.ERROR)
    yield c
    c.close()


def _comparable(df):
    return df.drop(columns=TIMING).reset_index(drop=True)


# --------------------------------------------------------------------------- same numbers as `paper`
def test_grid_study_equals_paper_runs_bit_for_bit(grid_study, paper_runs):
    out, df, result = grid_study
    assert result.scheduler.startswith("tcp://127.0.0.1:")
    assert result.lost == {} and result.out == out and len(result.runs) == 4
    assert not (out / "study.html").exists()    # a study returns results, writes no report
    assert list(df["run"]) == [0, 1, 2, 3]
    assert (df["status"] == "ok").all(), df["error"].tolist()
    assert str(df["status"].iloc[0]) == "ok"
    for _, row in df.iterrows():
        run = paper_runs[row["point"]]
        assert row["controller.alpha"] == run.config["controller"]["alpha"]
        lr = run.runs[row["law"]]
        s = metrics.summary(lr, run.theta)
        for key in ("theta_err_norm", "e_max_last20", "tau_d_err_rms_last20"):
            assert row[key] == s[key], key  # bit for bit
        for i, v in enumerate(s["theta_hat"]):
            assert row[f"theta_hat[{i}]"] == v
        assert row["steps"] == lr.stats["steps"]
        # conclusions: the study's per-point numbers are those of the paper's conclusions()
        concl = {c["id"]: c for c in metrics.conclusions(run)}
        assert row["C1_max_rel_deviation"] == concl["C1"]["measured"]["max_rel_deviation_last_half"]
        assert row["C1_end_ratio"] == concl["C1"]["measured"]["end_to_initial_ratio"]
        assert row["C2_end_ratio"] == concl["C2"]["measured"]["end_to_initial_ratio"]
        assert row["C3_ratio"] == concl["C3"]["measured"]["ratio"]
        for cid in ("C1", "C2", "C3"):
            assert concl[cid]["verdict"] is not None and bool(row[cid]) is concl[cid]["verdict"]
    # the files hold the same table
    pq = pd.read_parquet(out / "results.parquet")
    pd.testing.assert_frame_equal(pq, df, check_dtype=False)
    csv = pd.read_csv(out / "results.csv")
    assert np.array_equal(csv["theta_err_norm"].to_numpy(), df["theta_err_norm"].to_numpy())
    assert len(list((out / "runs").glob("*.json"))) == 4


def test_curves_on_a_one_second_grid(grid_study, paper_runs):
    out, df, result = grid_study
    cv = pd.read_parquet(out / "curves.parquet")
    pd.testing.assert_frame_equal(cv, result.curves, check_dtype=False)
    assert sorted(set(cv["run"])) == [0, 1, 2, 3]
    one = cv[cv["run"] == 0]
    assert one["t"].tolist() == [float(k) for k in range(int(T_END) + 1)]
    run = paper_runs[0]
    lr = run.runs["iv-drem"]
    t = np.asarray(lr.response.time)
    k = np.searchsorted(t, 3.0 - 1e-9)
    assert t[k] == pytest.approx(3.0, abs=1e-12)
    expect = metrics.norm(metrics.theta_error(lr, run.theta))[k]
    assert one[one["t"] == 3.0]["theta_err_norm"].item() == expect
    assert one[one["t"] == 3.0]["Delta_abs"].item() == abs(metrics.signal(lr, "Delta")[k])
    cl = cv[cv["run"] == 1]
    assert cl["Delta_abs"].isna().all()  # composite learning has no Δ


def test_report_is_written_and_self_contained(grid_study):
    out, df, result = grid_study
    assert write_study_report_of(result) == (out / "study.html", out / "study.pdf")
    html = (out / "study.html").read_text("utf-8")
    assert "<svg" in html and "Metrics against controller.alpha" in html
    assert "Envelope of" in html and "Failed runs" in html
    assert "http://" not in html.replace("http://www.w3.org", "") and "src=" not in html
    assert (out / "study.pdf").read_bytes().startswith(b"%PDF")


def test_the_command_writes_the_report_from_the_results(tmp_path, cluster, capsys):
    """`ivdrem study` writes study.html / study.pdf from what run_study returns (run_study
    itself writes none); --no-report leaves them out."""
    from ivdrem.reports.study_report import GENERATOR
    study = tmp_path / "s.toml"
    study.write_text('[experiment]\nt_end = 5.0\nlaws = ["iv-drem"]\n'
                     '[study.grid]\n"controller.alpha" = [1.0, 1.5]\n', encoding="utf-8")
    rc = main(["study", str(study), "--out", str(tmp_path / "out"), "--quiet",
               "--scheduler", cluster.scheduler_address])
    assert rc == 0
    html = (tmp_path / "out" / "study.html").read_text("utf-8")
    assert GENERATOR in html and "ivdrem study: s.toml" in html
    assert "Metrics against controller.alpha" in html
    assert (tmp_path / "out" / "study.pdf").read_bytes().startswith(b"%PDF")
    assert "study.html, study.pdf" in capsys.readouterr().out
    # t_end = 5 s ends before the window T = 20 s is full: C2's numbers kept, no verdict
    df = pd.read_csv(tmp_path / "out" / "results.csv")
    assert df["C2"].isna().all() and np.isfinite(df["C2_end_ratio"]).all()
    rc = main(["study", str(study), "--out", str(tmp_path / "bare"), "--quiet", "--no-report",
               "--scheduler", cluster.scheduler_address])
    assert rc == 0
    assert len(list((tmp_path / "bare" / "runs").glob("*.json"))) == 2
    assert not (tmp_path / "bare" / "study.html").exists()


def test_the_command_refuses_a_foreign_report_before_any_run(tmp_path, capsys):
    study = tmp_path / "s.toml"
    study.write_text('[experiment]\nt_end = 5.0\n[study.grid]\n"iv_drem.T" = [5.0]\n',
                     encoding="utf-8")
    out = tmp_path / "out"
    out.mkdir()
    (out / "study.html").write_text("mine\n", encoding="utf-8")
    rc = main(["study", str(study), "--out", str(out), "--quiet", "--workers", "1"])
    assert rc == 2
    assert "refusing to overwrite" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["study.html"]      # nothing ran
    assert (out / "study.html").read_text(encoding="utf-8") == "mine\n"


# --------------------------------------------------------------------------- random draws
RANDOM = {
    "study": {"random": {
        "samples": 400, "seed": 7,
        "disturbance.amplitude": [{"uniform": [2.0, 10.0]}, 1.5],
        "iv_drem.gamma": {"loguniform": [1e8, 1e12]},
        "initial.q0[1]": {"normal": [0.9, 0.05]},
        "controller.observer_variant": {"choice": ["corrected", "literal"]},
    }},
}


def _draws(study):
    return [(r.values, r.config) for r in expand_study(read_study(study))]


def test_random_same_seed_same_runs_other_seed_other_runs():
    a, b = _draws(RANDOM), _draws(RANDOM)
    assert a == b
    other = json.loads(json.dumps(RANDOM))
    other["study"]["random"]["seed"] = 8
    c = _draws(other)
    assert [v for v, _ in a] != [v for v, _ in c]
    assert len(a) == 400 * 2  # two laws per sample


def test_random_draws_follow_their_distributions():
    runs = expand_study(read_study(RANDOM))[::2]  # one law per sample
    amp = np.array([r.config["disturbance"]["amplitude"][0] for r in runs])
    assert all(r.config["disturbance"]["amplitude"][1] == 1.5 for r in runs)  # fixed element
    assert amp.min() >= 2.0 and amp.max() < 10.0
    # mean of U(2, 10) is 6 with standard error 8/sqrt(12 * 400) = 0.115
    assert abs(amp.mean() - 6.0) < 4 * 0.115
    lg = np.log10([r.config["iv_drem"]["gamma"] for r in runs])
    assert lg.min() >= 8 and lg.max() < 12 and abs(lg.mean() - 10.0) < 4 * (4 / math.sqrt(12 * 400))
    q = np.array([r.config["initial"]["q0"][1] for r in runs])
    assert abs(q.mean() - 0.9) < 4 * 0.05 / 20 and abs(q.std() - 0.05) < 0.01
    assert all(r.config["initial"]["q0"][0] == 0.0 for r in runs)
    kinds = {r.config["controller"]["observer_variant"] for r in runs}
    assert kinds == {"corrected", "literal"}


def test_adding_a_key_does_not_change_the_draws_of_the_others():
    more = json.loads(json.dumps(RANDOM))
    more["study"]["random"]["filters.l"] = {"uniform": [40.0, 60.0]}
    a = [v["iv_drem.gamma"] for v, _ in _draws(RANDOM)]
    b = [v["iv_drem.gamma"] for v, _ in _draws(more)]
    assert a == b


def test_fewer_samples_are_the_first_draws_of_more():
    few = json.loads(json.dumps(RANDOM))
    few["study"]["random"]["samples"] = 10
    assert [r.hash for r in expand_study(read_study(few))] == \
        [r.hash for r in expand_study(read_study(RANDOM))][:20]


def test_grid_and_random_combine_and_laws_are_a_dimension():
    study = {"study": {"grid": {"iv_drem.T": [5.0, 10.0], "experiment.laws": ["iv-drem", "drem"]},
                       "random": {"samples": 3, "seed": 1,
                                  "disturbance.phase[0]": {"uniform": [0.0, 1.0]}}}}
    runs = expand_study(read_study(study))
    assert len(runs) == 2 * 2 * 3
    assert [r.law for r in runs[:3]] == ["iv-drem"] * 3
    assert {r.law for r in runs} == {"iv-drem", "drem"}
    # every grid point sees the same three draws
    phases = {}
    for r in runs:
        phases.setdefault((r.values["iv_drem.T"], r.law), []).append(r.values["disturbance.phase[0]"])
    assert len({tuple(v) for v in phases.values()}) == 1


def test_base_file_is_relative_to_the_study_file(tmp_path):
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "mine.toml").write_text("[experiment]\nt_end = 7.0\n", encoding="utf-8")
    study = tmp_path / "sub" / "s.toml"
    study.write_text('base = "mine.toml"\n[controller]\nalpha = 2.0\n'
                     '[study.grid]\n"iv_drem.p" = [1.0, 3.0]\n', encoding="utf-8")
    runs = expand_study(read_study(study))
    assert {r.config["experiment"]["t_end"] for r in runs} == {7.0}
    assert {r.config["controller"]["alpha"] for r in runs} == {2.0}
    assert [r.config["iv_drem"]["p"] for r in runs] == [1.0, 1.0, 3.0, 3.0]
    # composite learning does not read iv_drem.p: one simulation for both points
    cl = [r.hash for r in runs if r.law == "composite-learning"]
    iv = [r.hash for r in runs if r.law == "iv-drem"]
    assert cl[0] == cl[1] and iv[0] != iv[1]


# --------------------------------------------------------------------------- bad input
@pytest.mark.parametrize("study, words", [
    ({"study": {"grid": {"iv_drem.TT": [1.0]}}}, ["iv_drem.TT", "not known", "iv_drem.T"]),
    ({"study": {"grid": {"iv_drem.T": []}}}, ["iv_drem.T", "empty list"]),
    ({"study": {"random": {"samples": 2, "seed": 0, "iv_drem.T": {"uniform": [3.0, 1.0]}}}},
     ["iv_drem.T", "a < b", "a = 3", "b = 1"]),
    ({"study": {"random": {"samples": 2, "seed": 0, "iv_drem.T": {"loguniform": [0.0, 1.0]}}}},
     ["loguniform", "0 < a"]),
    ({"study": {"random": {"samples": 2, "seed": 0, "iv_drem.T": {"normal": [1.0, -1.0]}}}},
     ["s > 0"]),
    ({"study": {"random": {"samples": 2, "seed": 0, "iv_drem.T": {"gauss": [1.0, 1.0]}}}},
     ["iv_drem.T", "uniform, loguniform, normal, choice"]),
    ({"study": {"random": {"seed": 0, "iv_drem.T": {"uniform": [1.0, 2.0]}}}}, ["samples"]),
    ({"study": {"grid": {"iv_drem.T": [10.0, -1.0, 20.0]}}},
     ["study point 1", "iv_drem.T = -1", "config key 'iv_drem.T' must be > 0"]),
    ({"study": {"grid": {"disturbance.omega[2]": [1.0]}}}, ["disturbance.omega", "2 entries"]),
    ({"study": {"grid": {"iv_drem.T": [1.0, 1.0]}}}, ["twice"]),
    ({"study": {}}, ["varies nothing"]),
    ({"iv_drem": {"q": 1.0}, "study": {"grid": {"iv_drem.T": [1.0]}}}, ["iv_drem.q", "not known"]),
])
def test_bad_study_is_a_clear_error_before_any_run(tmp_path, study, words):
    out = tmp_path / "out"
    with pytest.raises(StudyError) as err:
        run_study(study, out, workers=1, progress=False)
    for w in words:
        assert w in str(err.value), (w, str(err.value))
    assert not out.exists()  # nothing started, nothing written


def test_unreachable_scheduler_is_a_clear_error_before_any_run(tmp_path, capsys):
    with socket.socket() as s:  # a free port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    study = tmp_path / "s.toml"
    study.write_text('[experiment]\nt_end = 5.0\n[study.grid]\n"iv_drem.T" = [5.0]\n', encoding="utf-8")
    t0 = time.perf_counter()
    rc = main(["study", str(study), "--out", str(tmp_path / "out"), "--quiet",
               "--scheduler", f"tcp://127.0.0.1:{port}"])
    assert rc == 2
    assert time.perf_counter() - t0 < 30
    msg = capsys.readouterr().err
    assert f"cannot reach the Dask scheduler at tcp://127.0.0.1:{port}" in msg
    assert not (tmp_path / "out" / "runs").exists()


def test_a_directory_of_other_files_is_refused(tmp_path):
    (tmp_path / "results.csv").write_text("mine\n", encoding="utf-8")
    with pytest.raises(StudyError, match="not one of ivdrem's study directories"):
        run_study(GRID, tmp_path, workers=1, progress=False)
    assert (tmp_path / "results.csv").read_text(encoding="utf-8") == "mine\n"


def test_a_directory_with_runs_needs_resume(grid_study):
    out, _, _ = grid_study
    with pytest.raises(StudyError, match="--resume"):
        run_study(GRID, out, workers=1, progress=False)


# --------------------------------------------------------------------------- nothing lost
def test_failed_run_records_its_error_and_the_study_goes_on(tmp_path, cluster):
    study = {"experiment": {"t_end": T_END, "laws": ["iv-drem"]},
             # θ1 < 0: M(q) is not positive definite at t = 0 -> SimulationError
             "study": {"grid": {"model.theta[0]": [1.3, -1.0]}}}
    result = run_study(study, tmp_path, scheduler=cluster.scheduler_address, progress=False)
    write_study_report_of(result)
    df = result.results
    assert df["status"].tolist() == ["ok", "failed"]
    assert "not positive definite" in df["error"].iloc[1]
    assert math.isnan(df["theta_err_norm"].iloc[1])
    html = (tmp_path / "study.html").read_text("utf-8")
    assert "not positive definite" in html


class _Stop(Exception):
    pass


def test_resume_after_interruption_gives_the_uninterrupted_table(tmp_path, grid_study, cluster):
    _, full, _ = grid_study
    seen = []

    def stop_after_two(run, rec):
        seen.append(run.index)
        if len(seen) == 2:
            raise _Stop

    with pytest.raises(_Stop):
        run_study(GRID, tmp_path, scheduler=cluster.scheduler_address, progress=False,
                  on_run=stop_after_two)
    saved = RunStore(tmp_path).load()
    assert len(saved) == 2
    # a half-written record (killed mid-write) is a hidden temp file: ignored on resume
    (tmp_path / "runs" / ".deadbeef.json.1234.tmp").write_text("{", encoding="utf-8")
    again = []
    df = run_study(GRID, tmp_path, scheduler=cluster.scheduler_address, progress=False,
                   resume=True, on_run=lambda run, rec: again.append(run.index)).results
    assert sorted(again) == sorted(set(range(4)) - set(seen))  # only the missing ones ran
    pd.testing.assert_frame_equal(_comparable(df), _comparable(full))


def test_a_full_disk_keeps_every_finished_run_elsewhere(tmp_path, grid_study, cluster,
                                                         monkeypatch):
    """The study directory fills up at the first record: every run still finishes, the
    records land in a new temporary directory the error names, and copied back they
    resume to the uninterrupted table without running anything again."""
    import errno
    import shutil
    import tempfile
    _, full, _ = grid_study
    out, spare = tmp_path / "out", tmp_path / "spare"
    spare.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(spare))
    real_save = RunStore.save

    def save(self, rec):
        if out in self.dir.parents:
            raise OSError(errno.ENOSPC, "No space left on device")
        real_save(self, rec)
    monkeypatch.setattr(RunStore, "save", save)
    with pytest.raises(StudyError, match=r"No space left on device; the 4 finished run\(s\) "
                                         r"were kept in .*continue with --resume") as info:
        run_study(GRID, out, scheduler=cluster.scheduler_address, progress=False)
    kept = Path(re.search(r"kept in (\S+):", str(info.value)).group(1))
    assert kept.parent.parent == spare and len(list(kept.glob("*.json"))) == 4
    monkeypatch.setattr(RunStore, "save", real_save)
    shutil.copytree(kept, out / "runs", dirs_exist_ok=True)
    again = []
    df = run_study(GRID, out, scheduler=cluster.scheduler_address, progress=False,
                   resume=True, on_run=lambda run, rec: again.append(run.index)).results
    assert again == []
    pd.testing.assert_frame_equal(_comparable(df), _comparable(full))


@pytest.mark.slow
def test_killed_worker_loses_no_run(tmp_path, cluster):
    """SIGKILL a worker process while it runs a task: the study completes, each run once."""
    from dask.distributed import Client

    study = {"experiment": {"t_end": 20.0, "laws": ["iv-drem"]},
             "solver": {"rtol": 1e-10, "atol": 1e-12},  # same code, ~10x the steps: seconds per task
             "study": {"grid": {"controller.alpha": [1.0, 1.1, 1.2, 1.3]}}}
    client = Client(cluster.scheduler_address, set_as_default=False)
    pids = client.run(os.getpid)
    result, killed = {}, {}

    def study_thread():
        result["study"] = run_study(study, tmp_path, scheduler=cluster.scheduler_address,
                                    progress=False)

    th = threading.Thread(target=study_thread)
    th.start()
    deadline = time.time() + 240
    while not killed and time.time() < deadline and th.is_alive():
        for addr, keys in client.processing().items():
            if any(str(k).startswith("run-") for k in keys) and addr in pids:
                time.sleep(0.5)  # let it start simulating
                os.kill(pids[addr], signal.SIGKILL)
                killed["pid"] = pids[addr]
                break
        time.sleep(0.05)
    th.join(timeout=300)
    client.close()
    assert killed, "no task seen running"
    df = result["study"].results
    assert len(df) == 4 and df["hash"].is_unique and (df["status"] == "ok").all()
    assert len(list((tmp_path / "runs").glob("*.json"))) == 4
    assert not result["study"].lost
    with pytest.raises(ProcessLookupError):
        os.kill(killed["pid"], 0)  # it really died


def test_non_utf8_study_file_is_a_clear_error(tmp_path):
    """A study file read like a config file: not UTF-8 is refused naming the byte."""
    from ivdrem.experiments.study_spec import StudyError, read_study
    f = tmp_path / "s.toml"
    f.write_bytes(b"[study.grid]\n# caf\xe9\n")
    with pytest.raises(StudyError, match=r"study file .* is not UTF-8 text.*0xe9"):
        read_study(f)


def test_study_paths_are_the_callers(tmp_path, monkeypatch, capsys):
    """`ivdrem study FILE --out DIR` resolves both against the directory the user started
    from (IVDREM_CALLER_CWD, set by ./run), as every other command does, not against the
    clone ./run changes into."""
    caller = tmp_path / "caller"
    (caller / "mine").mkdir(parents=True)
    (caller / "s.toml").write_text('[experiment]\nt_end = 5.0\n[study.grid]\n"iv_drem.T" = [5.0]\n',
                                   encoding="utf-8")
    (caller / "mine" / "results.csv").write_text("mine\n", encoding="utf-8")
    elsewhere = tmp_path / "clone"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    monkeypatch.setenv("IVDREM_CALLER_CWD", str(caller))
    # the study file is found in the caller's directory, and --out names the caller's
    # directory `mine`, whose foreign file is refused (nothing is run or written)
    rc = main(["study", "s.toml", "--out", "mine", "--quiet", "--workers", "1"])
    assert rc == 2
    msg = capsys.readouterr().err
    assert "not one of ivdrem's study directories" in msg, msg
    assert str(caller / "mine") in msg
    assert (caller / "mine" / "results.csv").read_text(encoding="utf-8") == "mine\n"
    assert list(elsewhere.iterdir()) == []


@pytest.mark.parametrize("address, fragment", [
    ("notaurl", "missing port number"),
    ("tcp://host:notaport", "notaport"),
])
def test_a_malformed_scheduler_address_is_one_clear_line(tmp_path, capsys, address, fragment):
    study = tmp_path / "s.toml"
    study.write_text('[experiment]\nt_end = 5.0\n[study.grid]\n"iv_drem.T" = [5.0]\n',
                     encoding="utf-8")
    t0 = time.perf_counter()
    rc = main(["study", str(study), "--out", str(tmp_path / "out"), "--quiet",
               "--scheduler", address])
    assert rc == 2
    assert time.perf_counter() - t0 < 10       # refused before any client is made
    err = capsys.readouterr().err
    assert "is not a Dask scheduler address" in err and fragment in err, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "out" / "runs").exists()


def test_more_workers_than_cores_is_refused(tmp_path, capsys):
    study = tmp_path / "s.toml"
    study.write_text('[experiment]\nt_end = 5.0\n[study.grid]\n"iv_drem.T" = [5.0]\n',
                     encoding="utf-8")
    n = (os.cpu_count() or 1) * 32
    rc = main(["study", str(study), "--out", str(tmp_path / "out"), "--quiet",
               "--workers", str(n)])
    assert rc == 2
    err = capsys.readouterr().err
    assert f"--workers {n} exceeds the {os.cpu_count() or 1} cores" in err, err
    assert not (tmp_path / "out" / "runs").exists()


@pytest.mark.parametrize("table, fragment", [
    ('[study.random]\nsamples = 1000000000\n[study.random."controller.alpha"]\n'
     'distribution = "uniform"\nlow = 1.0\nhigh = 2.0\n', "'samples' = 1000000000 exceeds 100000"),
    ('[study.grid]\n"controller.alpha" = [' + ", ".join(f"{1 + k / 1000}" for k in range(400))
     + ']\n"iv_drem.p" = [' + ", ".join(f"{1 + k / 100}" for k in range(400)) + ']\n',
     "the study has 320000 runs (400 x 400"),
])
def test_an_absurd_study_size_is_refused_at_once(tmp_path, table, fragment):
    from ivdrem.experiments.study_spec import expand_study, read_study
    study = tmp_path / "s.toml"
    study.write_text('[experiment]\nt_end = 5.0\n' + table, encoding="utf-8")
    t0 = time.perf_counter()
    with pytest.raises(StudyError, match=re.escape(fragment)):
        expand_study(read_study(study))
    assert time.perf_counter() - t0 < 5
