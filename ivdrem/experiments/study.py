"""Parameter studies on Dask: every run of a study file is one task (one closed loop, one law).

:func:`run_study` validates every run (``ivdrem.experiments.study_spec``), connects to a
Dask cluster (a ``dask.distributed.LocalCluster`` of single-threaded worker processes by
default, or a running scheduler), submits one task per run and collects the results as
they finish (docs/studies.md):

* ``DIR/runs/<hash>.json``: one file per finished run, written atomically the moment it
  arrives (``<hash>`` identifies the run's full configuration); a run that fails records
  its error message there and the study goes on;
* ``DIR/results.parquet`` and ``DIR/results.csv``: one row per run (varied keys, law,
  metrics of ``ivdrem paper --json``, θ̂(t_end), C1-C3 numbers and verdicts per point,
  steps, wall times, status, error), rebuilt atomically from the run files;
* ``DIR/curves.parquet``: ‖θ̃(t)‖, ‖e(t)‖ and |Δ(t)| on a 1 s grid per run;
* ``DIR/study.toml``: the study definition as given.

``resume=True`` skips the runs whose file is already in ``DIR/runs``; the table is always
in the study's run order, so a resumed study ends with the table of an uninterrupted one.
A worker that dies mid-task loses nothing: the scheduler runs the task again elsewhere.

Compiled code: runs of one law share one generated module (parameter values are not baked
into the code), so each worker process builds (or loads from the on-disk cache,
``ivdrem.sim.compiled.cache_dir``) each law's code once, at its first run of that law, and
keeps it in memory.  A local worker imports the engine as it starts (``WORKER_PRELOAD``).
Runs are submitted with the laws interleaved; on an empty cache the laws' shared kernels
are compiled once in all, by whichever worker comes first, the others waiting for it
(``ivdrem.compile_cache.compile_lock``).  A warm-up task per law (``warm_up_laws=True``) was
measured not to pay: see docs/studies.md.
"""
from __future__ import annotations

import copy
import json
import math
import os
import socket
import sys
import time
import uuid
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from .._atomic import write_text_atomic, new_tempfile, fsync_file, os_error_behind
from .._paths import OutputLocationError, check_writable_dir
from .._progress import want_progress
from .study_spec import RunSpec, StudyError, StudySpec, expand_study, read_study

__all__ = ["run_study", "StudyResult", "StudyError", "run_one", "results_table", "CURVE_DT",
           "SCHEDULER_TIMEOUT_S", "METRICS"]

#: time step of DIR/curves.parquet, s
CURVE_DT = 1.0
#: how long to try reaching a --scheduler before giving up, s
SCHEDULER_TIMEOUT_S = 5.0
#: how often a task is re-submitted after an exception outside the simulation
TASK_RETRIES = 2
#: per-run metrics of ``ivdrem.experiments.metrics.summary`` kept in the table
METRICS = ("theta_err_norm", "e_max_last20", "tau_d_err_rms_last20")
#: file marking a directory as written by ivdrem study (only such files are replaced)
_MARKER = ".ivdrem-study"
#: minimal interval between two rebuilds of the result tables while runs arrive, s
_REBUILD_EVERY_S = 2.0
#: what a local worker imports as it starts (python-control, numba, the engine), before
#: its first task: measured 1.5 s, paid while the scheduler starts instead of in a run
WORKER_PRELOAD = ("ivdrem.experiments.paper",)


# --------------------------------------------------------------------------- one run (worker side)
def run_one(config: Mapping, law: str) -> dict:
    """Simulate one law of one configuration; the record written to ``DIR/runs/<hash>.json``.

    Runs on a Dask worker.  Never raises for a failing simulation (divergence, singular
    inertia, a compile error): the record has ``status = "failed"`` and the message.
    """
    from . import metrics
    from .experiment import Experiment
    from .paper import PaperRun

    t0 = time.perf_counter()
    rec: dict[str, Any] = {"law": law, "status": "ok", "error": "", "pid": os.getpid(),
                           "host": socket.gethostname()}
    try:
        experiment = Experiment.from_config(config, laws=[law])   # resolved once
        model = experiment.model
        lr = experiment.run(law, progress=False)
        experiment.release(law)
        task_s = time.perf_counter() - t0
        theta = np.asarray(config["model"]["theta"], dtype=float)
        s = metrics.summary(lr, theta)
        stats = dict(lr.stats)
        sim_s = stats.get("sim_s", stats.get("wall_s"))
        compile_s = stats.get("compile_s")
        if compile_s is None:  # diagram build + loading (or compiling) its code
            compile_s = max(task_s - float(sim_s), 0.0)
        rec.update(
            summary={k: s[k] for k in ("t_end", "theta_hat") + METRICS},
            steps=int(stats.get("steps", 0)), rejected=int(stats.get("rejected", 0)),
            sim_s=float(sim_s), compile_s=float(compile_s),
            conclusions=_own_conclusions(PaperRun(config=dict(config), theta=theta, model=model,
                                                  runs={law: lr})),
            horizon_note=metrics.law_horizon_note(lr, config),
            curves=_curves(lr, theta),
        )
    except Exception as exc:  # noqa: BLE001 - a failed run is a result, the study goes on
        rec.update(status="failed", error=f"{type(exc).__name__}: {exc}")
    rec["task_s"] = time.perf_counter() - t0
    return rec


def _own_conclusions(run) -> dict:
    """The conclusions one law decides alone: C1 for composite learning, C2 for IV-DREM,
    with their numbers; the verdict None where the run ends before the law's composite term
    could act (:func:`ivdrem.experiments.metrics.law_horizon_note`)."""
    from . import metrics
    out = {}
    for c in metrics.conclusions(run):
        if c["measured"]:                     # not a conclusion of a law this run lacks
            out[c["id"]] = {"measured": c["measured"],
                            "verdict": None if c["verdict"] is None else bool(c["verdict"]),
                            "note": c["note"]}
    return out


def _curves(lawrun, theta) -> dict:
    """‖θ̃‖, ‖e‖ and |Δ| (NaN for laws without Δ) at t = 0, CURVE_DT, 2 CURVE_DT, ..."""
    from . import metrics
    t = np.asarray(lawrun.response.time, dtype=float)
    grid = np.arange(0.0, t[-1] + 1e-9, CURVE_DT)
    idx = np.clip(np.searchsorted(t, grid - 1e-9 * max(1.0, t[-1])), 0, t.size - 1)
    th = metrics.norm(metrics.theta_error(lawrun, theta))
    e = metrics.norm(metrics.signal(lawrun, "e"))
    try:
        delta = np.min(np.abs(np.atleast_2d(metrics.signal(lawrun, "Delta"))), axis=0)  # weakest Δ_i
    except KeyError:
        delta = np.full(t.shape, np.nan)
    return {"t": [float(v) for v in t[idx]], "theta_err_norm": [float(v) for v in th[idx]],
            "e_norm": [float(v) for v in e[idx]], "Delta_abs": [float(v) for v in delta[idx]]}


def warm_up(config: Mapping, law: str) -> float:
    """Build and compile one law's closed loop (a 2-sample run); returns the wall time, s.

    Runs as a task before the runs of its law, so that they find the code in the disk cache.
    """
    from .paper import run_law
    t0 = time.perf_counter()
    cfg = copy.deepcopy(dict(config))
    dt = min(float(cfg["experiment"]["dt_out"]), float(cfg["experiment"]["t_end"]))
    cfg["experiment"]["t_end"] = dt
    cfg["experiment"]["dt_out"] = dt
    try:
        run_law(cfg, law, progress=False)
    except Exception:  # noqa: BLE001 - the real run reports the error
        pass
    return time.perf_counter() - t0


# --------------------------------------------------------------------------- results
def _c3(iv: Mapping, cl: Mapping) -> dict:
    """C3 of one point from the two runs' RMS ‖τ̃_d‖ over the last 20 % (metrics.summary);
    no verdict where either run ended before its composite term could act (the run's
    ``horizon_note``, as ``metrics.conclusions`` decides).

    Same numbers as ``metrics.conclusions`` (a test compares them on full runs).
    """
    from .metrics import C3_RMS_RATIO
    r_iv = iv["summary"]["tau_d_err_rms_last20"]
    r_cl = cl["summary"]["tau_d_err_rms_last20"]
    ratio = r_iv / r_cl if r_cl > 0 else (0.0 if r_iv == 0 else math.inf)
    short = iv.get("horizon_note") or cl.get("horizon_note")
    return {"ratio": ratio, "verdict": None if short else bool(r_iv <= C3_RMS_RATIO * r_cl)}


def results_table(runs: list[RunSpec], records: Mapping[str, dict], spec: StudySpec | None = None):
    """(results, curves) DataFrames of the runs that have a record, in run order."""
    import pandas as pd

    by_point: dict[int, dict[str, dict]] = {}
    for r in runs:
        rec = records.get(r.hash)
        if rec is not None and rec.get("status") == "ok":
            by_point.setdefault(r.point, {})[r.law] = rec
    varied = []
    for r in runs:
        for k in r.values:
            if k not in varied:
                varied.append(k)
    rows, curves = [], []
    ntheta = max((len(r.config["model"]["theta"]) for r in runs), default=0)
    for r in runs:
        rec = records.get(r.hash)
        if rec is None:
            continue
        row: dict[str, Any] = {"run": r.index, "point": r.point}
        for k in varied:
            row[k] = r.values.get(k)
        row.update(law=r.law, sample=r.sample, seed=None if spec is None else spec.seed,
                   t_end=float(r.config["experiment"]["t_end"]), status=rec["status"],
                   error=rec.get("error", ""))
        s = rec.get("summary") or {}
        for m in METRICS:
            row[m] = s.get(m, math.nan)
        th = s.get("theta_hat") or []
        for i in range(ntheta):
            row[f"theta_hat[{i}]"] = th[i] if i < len(th) else math.nan
        group = by_point.get(r.point, {})
        c1 = group.get("composite-learning", {}).get("conclusions", {}).get("C1")
        c2 = group.get("iv-drem", {}).get("conclusions", {}).get("C2")
        row["C1_max_rel_deviation"] = c1["measured"]["max_rel_deviation_last_half"] if c1 else math.nan
        row["C1_end_ratio"] = c1["measured"]["end_to_initial_ratio"] if c1 else math.nan
        row["C1"] = c1["verdict"] if c1 else None
        row["C2_end_ratio"] = c2["measured"]["end_to_initial_ratio"] if c2 else math.nan
        row["C2_quarter_ratio"] = (c2["measured"]["theta_err_norm_max_last_quarter"]
                                   / c2["measured"]["theta_err_norm_max_second_quarter"]
                                   if c2 and c2["measured"]["theta_err_norm_max_second_quarter"] > 0
                                   else math.nan)
        row["C2"] = c2["verdict"] if c2 else None
        if "iv-drem" in group and "composite-learning" in group:
            c3 = _c3(group["iv-drem"], group["composite-learning"])
            row["C3_ratio"], row["C3"] = c3["ratio"], c3["verdict"]
        else:
            row["C3_ratio"], row["C3"] = math.nan, None
        row.update(steps=rec.get("steps"), sim_s=rec.get("sim_s", math.nan),
                   compile_s=rec.get("compile_s", math.nan), task_s=rec.get("task_s", math.nan),
                   hash=r.hash)
        rows.append(row)
        cv = rec.get("curves")
        if cv:
            for j, t in enumerate(cv["t"]):
                curves.append({"run": r.index, "law": r.law, "t": t,
                               "theta_err_norm": cv["theta_err_norm"][j],
                               "e_norm": cv["e_norm"][j], "Delta_abs": cv["Delta_abs"][j]})
    df = pd.DataFrame(rows)
    if not df.empty:
        for c in ("C1", "C2", "C3"):
            df[c] = df[c].astype("boolean")
        df["sample"] = df["sample"].astype("Int64")
        df["seed"] = df["seed"].astype("Int64")
        df["steps"] = df["steps"].astype("Int64")
    cf = pd.DataFrame(curves, columns=["run", "law", "t", "theta_err_norm", "e_norm", "Delta_abs"])
    return df, cf


def _write_df_atomic(df, path: Path, kind: str) -> None:
    tmp = new_tempfile(path.parent, path.name)
    try:
        if kind == "parquet":
            df.to_parquet(tmp, index=False)
        else:
            df.to_csv(tmp, index=False)
        fsync_file(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _write_tables(out: Path, runs, records, spec):
    df, cf = results_table(runs, records, spec)
    _write_df_atomic(df, out / "results.parquet", "parquet")
    _write_df_atomic(df, out / "results.csv", "csv")
    _write_df_atomic(cf, out / "curves.parquet", "parquet")
    return df, cf


# --------------------------------------------------------------------------- the store
class RunStore:
    """``DIR/runs/<hash>.json``: one file per finished run, each written atomically."""

    def __init__(self, out: Path):
        self.dir = Path(out) / "runs"

    def load(self) -> dict[str, dict]:
        out = {}
        if not self.dir.is_dir():
            return out
        for p in sorted(self.dir.glob("*.json")):  # temp files are hidden .*.tmp
            try:
                rec = json.loads(p.read_text("utf-8"))
            except (OSError, ValueError):
                continue  # not one of ours / unreadable: the run is done again
            if isinstance(rec, dict) and rec.get("hash") == p.stem:
                out[p.stem] = rec
        return out

    def save(self, rec: dict) -> None:
        self.dir.mkdir(parents=True, exist_ok=True)
        write_text_atomic(self.dir / f"{rec['hash']}.json", json.dumps(rec) + "\n")


# --------------------------------------------------------------------------- the cluster
def probe_scheduler(address: str, timeout: float = SCHEDULER_TIMEOUT_S) -> None:
    """Raise :class:`StudyError` (one line) unless a Dask scheduler answers at the tcp
    `address` within `timeout` seconds in all: Dask's own connection (its handshake) and
    an ``identity`` request whose reply names a scheduler.  A port that accepts and stays
    silent, one that answers HTTP (a dashboard) or another Dask server (a worker) are told
    apart here; ``Client`` alone waits forever for the first and gives a raw TimeoutError
    for the second."""
    import asyncio

    from distributed.comm import connect, parse_address, parse_host_port

    stage = ["connect"]

    async def ask():
        # a plain TCP connection first: "nothing listens" and "listens but is silent" differ
        host, port = parse_host_port(parse_address(address)[1])
        _, writer = await asyncio.open_connection(host, port)
        writer.close()
        stage[0] = "answer"
        comm = await connect(address, timeout=timeout)
        try:
            await comm.write({"op": "identity"})
            return await comm.read()
        finally:
            comm.abort()

    hint = "is it running, and is the address right? (`dask scheduler` listens on 8786)"
    try:
        reply = asyncio.run(asyncio.wait_for(ask(), timeout))
    except (asyncio.TimeoutError, TimeoutError):
        what = ("the port accepted the connection but nothing answered Dask's handshake "
                "(not a Dask scheduler?)" if stage[0] == "answer" else
                "no answer to the connection (a firewall, or a host that is down?)")
        raise StudyError(f"cannot reach the Dask scheduler at {address} within "
                         f"{timeout:g} s: {what}; {hint}") from None
    except Exception as exc:     # noqa: BLE001 - every failure of the probe is one line
        text = " ".join(str(exc).split()) or type(exc).__name__
        if len(text) > 200:
            text = text[:200] + "..."
        what = ("the server there does not speak Dask's protocol (an HTTP dashboard?)"
                if stage[0] == "answer" else f"{type(exc).__name__}: {text}")
        raise StudyError(f"cannot reach the Dask scheduler at {address} within "
                         f"{timeout:g} s ({what}); {hint}") from None
    kind = reply.get("type") if isinstance(reply, dict) else None
    if kind != "Scheduler":
        raise StudyError(f"the server at {address} is " + (
            f"a Dask {kind}, not a scheduler" if kind else
            "not a Dask scheduler (its answer is not Dask's)") + f"; {hint}")


def _check_scheduler(workers: int | None, scheduler: str | None) -> str | None:
    """The --scheduler address made whole (``tcp://`` added), checked and probed
    (:func:`probe_scheduler`), or None for the local cluster.  Called first in a study,
    so a wrong address fails within :data:`SCHEDULER_TIMEOUT_S`, before any other work."""
    if scheduler is None:
        return None
    if workers is not None:
        raise StudyError("--workers applies to the local cluster only; a --scheduler "
                         "has the workers its cluster started")
    if "://" not in scheduler:
        scheduler = "tcp://" + scheduler
    from distributed.comm import parse_address, parse_host_port
    try:   # a malformed address is refused before a client exists (no late traceback)
        protocol, loc = parse_address(scheduler)
        if protocol in ("tcp", "tls"):
            parse_host_port(loc)
    except ValueError as exc:
        raise StudyError(f"--scheduler {scheduler!r} is not a Dask scheduler address "
                         f"({exc}); give e.g. tcp://HOST:8786") from None
    if protocol == "tcp":   # tls needs the cluster's certificates: Client's own check
        probe_scheduler(scheduler)
    return scheduler


def _connect(workers: int | None, scheduler: str | None):
    """(client, cluster or None) for a scheduler address checked by
    :func:`_check_scheduler`, or a local cluster of `workers` processes."""
    import logging

    from dask.distributed import Client, LocalCluster

    if scheduler is not None:
        try:
            client = Client(scheduler, timeout=f"{SCHEDULER_TIMEOUT_S}s",
                            set_as_default=False)
        except (OSError, TimeoutError) as exc:
            raise StudyError(f"cannot reach the Dask scheduler at {scheduler} within "
                             f"{SCHEDULER_TIMEOUT_S:g} s ({type(exc).__name__}: {exc}); "
                             "is it running, and is the address right?") from None
        return client, None
    cores = os.cpu_count() or 1
    n = cores if workers is None else int(workers)
    if n < 1:
        raise StudyError(f"--workers must be >= 1, got {workers}")
    if n > cores:
        # each worker is a process with its own compiled engine: more than one per core
        # only adds memory and start-up, never speed
        raise StudyError(f"--workers {n} exceeds the {cores} cores of this machine; the local "
                         f"cluster runs one worker process per core at most (use --scheduler "
                         "for a larger cluster)")
    with warnings.catch_warnings():
        # "Port 8787 is already in use": the scheduler's HTTP endpoint moves to a free port
        warnings.filterwarnings("ignore", message="Port .* is already in use")
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                               host="127.0.0.1", dashboard_address=None,
                               silence_logs=logging.ERROR, preload=list(WORKER_PRELOAD))
    client = Client(cluster, set_as_default=False)
    return client, cluster


def check_study_cost(runs: list[RunSpec]) -> None:
    """Refuse a study one of whose runs is above the cost limits of ivdrem.sim.guards
    (output memory, step count: a worker would refuse it after the cluster started, or
    fill its memory), naming the run.  One pricing diagram per model structure and law:
    the cost depends on the diagram's size, not on its parameter values."""
    from .experiment import Experiment
    priced = {}
    for run in runs:
        model_key = json.dumps({k: v for k, v in run.config["model"].items() if k != "theta"},
                               sort_keys=True)
        key = (run.law, model_key, json.dumps(run.config.get("iv_drem", {}).get("mixing")))
        try:
            experiment = Experiment.from_config(run.config, laws=[run.law], model=run.model)
            if key not in priced:
                priced[key] = experiment.loop(run.law)
                experiment.release(run.law)
            # this run's horizon and solver on the loop of its structure
            experiment.check_cost(run.law, priced[key], what=run.label)
        except ValueError as exc:    # CostLimitError, a bound of h_max / dt_out
            # the guard's remedy "--allow-long" is an option of paper and report, not of
            # a study: name the remedy that exists
            text = str(exc).replace(", or allow it with allow_long=True (command line: "
                                    "--allow-long)", "")
            raise StudyError(f"{text}; ivdrem study has no --allow-long: change the "
                             "study's values") from None


# --------------------------------------------------------------------------- the study
@dataclass
class StudyResult:
    """What :func:`run_study` returns: the study's results, in its run order.

    ``results``: one row per run with a record (the study's varied keys, law, status,
    metrics, C1-C3, steps, wall times; the table of ``DIR/results.parquet``); ``curves``:
    ‖θ̃‖, ‖e‖, |Δ| per run on a ``CURVE_DT`` grid (``DIR/curves.parquet``); ``lost``: the
    runs whose task was lost (hash -> message; ``--resume`` runs them again); ``spec`` and
    ``runs``: the study as read and expanded; ``out``: its directory; ``wall_s``: this
    session's wall time, s; ``scheduler``: the address of the Dask scheduler that ran them
    (``None`` when every run was already there).
    """
    results: Any
    curves: Any
    lost: dict[str, str]
    spec: StudySpec
    runs: list[RunSpec]
    out: Path
    wall_s: float
    scheduler: str | None = None


def run_study(study, out=None, *, workers: int | None = None, scheduler: str | None = None,
              resume: bool = False, progress: bool | None = None,
              warm_up_laws: bool = False, on_run: Callable[[RunSpec, dict], None] | None = None,
              ) -> StudyResult:
    """Run a study file (path) or dict; returns its results (:class:`StudyResult`).

    Everything is checked before the first run starts: the study file, every run's
    configuration, the output directory and the scheduler (:class:`StudyError`).  Writes
    the run files and the tables in `out`, not the report: ``ivdrem study`` writes
    ``study.html`` / ``study.pdf`` from the result
    (:func:`ivdrem.reports.study_report.write_study_report`).

    Parameters
    ----------
    study : str, Path or dict
        The study file (docs/studies.md), or the same as a nested dict (then `out` is
        required).
    out : str or Path, optional
        Output directory (default: ``studies/<name of the study file>``).
    workers : int, optional
        Worker processes of the local cluster (default: one per core).
    scheduler : str, optional
        Address of a running Dask scheduler (``tcp://HOST:PORT``) instead.
    resume : bool
        Skip the runs whose record is already in ``out/runs``.
    progress : bool, optional
        A bar over runs on stderr (default: when stderr is a terminal).
    warm_up_laws : bool
        Compile each law in one task before its runs start (default: no; the first run of
        a law on each worker loads it from the disk cache, or compiles it).
    on_run : callable, optional
        Called as ``on_run(run, record)`` after each run's record is saved.

    Returns
    -------
    StudyResult
        ``results`` (pandas.DataFrame, one row per run: the study's keys, the status and
        the metrics), ``curves``, ``lost``, ``spec``, ``runs``, ``out``, ``wall_s``,
        ``scheduler``.
    """
    scheduler = _check_scheduler(workers, scheduler)    # within 5 s, before any other work
    spec = read_study(study)
    runs = expand_study(spec)
    if out is None:
        if isinstance(study, Mapping):
            raise StudyError("run_study of a dict needs out=DIR")
        out = Path("studies") / Path(study).stem
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise StudyError(f"--out {out} exists and is not a directory")
    if out.is_dir() and any(out.iterdir()) and not (out / _MARKER).exists() \
            and not (out / "runs").is_dir():
        raise StudyError(f"--out {out} is a directory with other files in it, not one of "
                         "ivdrem's study directories; choose a new or empty directory")
    store = RunStore(out)
    have = store.load()
    if have and not resume:
        raise StudyError(f"{out} already holds {len(have)} finished run(s) of a study; pass "
                         "--resume to continue it, or choose another --out")
    wanted = {r.hash: r for r in runs}
    todo = [h for h in dict.fromkeys(r.hash for r in runs) if h not in have]
    records = {h: rec for h, rec in have.items() if h in wanted}
    try:   # before a cluster starts: the output directory, the C compiler, then what each
        # run will cost
        check_writable_dir(out, "study directory (--out)")
        from ..sim import _cstepper
        from ..sim.compiled import C_COMPILER_HINT
        try:    # both engines step in C (ivdrem/sim/stepper.c)
            _cstepper._compiler()
        except _cstepper.CStepperUnavailable as exc:
            raise StudyError(f"{exc}; {C_COMPILER_HINT}") from None
    except (OutputLocationError, ValueError) as exc:
        raise StudyError(str(exc)) from None
    check_study_cost([wanted[h] for h in todo])

    if todo:
        client, cluster = _connect(workers, scheduler)
        scheduler_address = client.scheduler.address
    else:
        client = cluster = scheduler_address = None
    out.mkdir(parents=True, exist_ok=True)
    (out / _MARKER).touch()
    write_text_atomic(out / ("study.json" if spec.source == "<dict>" else "study.toml"), spec.text)
    show = want_progress() if progress is None else bool(progress)
    lost: dict[str, str] = {}
    t_start = time.perf_counter()
    try:
        try:
            if todo:
                _execute(client, [wanted[h] for h in todo], store, records, runs, spec, out,
                         lost, show, on_run, warm_up_laws)
        finally:
            if client is not None:
                client.close()
            if cluster is not None:
                cluster.close()
        wall = time.perf_counter() - t_start
        df, cf = _write_tables(out, runs, records, spec)
    except Exception as exc:
        cause = os_error_behind(exc)
        if cause is None:
            raise
        raise StudyError(_kept_elsewhere(out, records, cause)) from None
    return StudyResult(results=df, curves=cf, lost=dict(lost), spec=spec, runs=runs, out=out,
                       wall_s=wall, scheduler=scheduler_address)


def _kept_elsewhere(out: Path, records: dict, cause: OSError) -> str:
    """After a write to `out` failed: the finished runs' records saved in a new temporary
    directory (nothing computed is lost), and the message saying where."""
    import tempfile
    what = f"cannot write the study to {out}: {cause.strerror or cause}"
    if not records:
        return what
    try:
        keep = Path(tempfile.mkdtemp(prefix="ivdrem-study-"))
        kept = RunStore(keep)
        for rec in records.values():
            kept.save(rec)
    except OSError as again:
        return f"{what}; keeping the {len(records)} finished run(s) elsewhere failed too: {again}"
    return (f"{what}; the {len(records)} finished run(s) were kept in {kept.dir}: copy them "
            f"to {out / 'runs'} once it can be written, and continue with --resume")


def _execute(client, todo: list[RunSpec], store, records, runs, spec, out, lost, show, on_run,
             warm_up_laws=False):
    from dask.distributed import as_completed

    # optional warm-up task per law (its code is shared by every run of that law): the runs
    # of a law then start once the code is in the disk cache
    session = uuid.uuid4().hex[:8]  # keys of an interrupted session may still be cancelling
    warm = {}
    for r in todo:
        if not warm_up_laws:
            warm[r.law] = None
        elif r.law not in warm:
            warm[r.law] = client.submit(warm_up, r.config, r.law, key=f"warm-up-{r.law}-{session}",
                                        pure=False, retries=TASK_RETRIES)
    futures = {}
    # laws interleaved: on an empty cache the first tasks compile different laws at once
    for r in _interleave(todo):
        f = client.submit(_run_after, r.config, r.law, warm[r.law], key=f"run-{r.hash}-{session}",
                          pure=False, retries=TASK_RETRIES)
        futures[f] = r
    bar = None
    if show:
        from tqdm import tqdm
        total = len({r.hash for r in runs})  # runs shared by several points count once
        bar = tqdm(total=total, initial=total - len(todo), unit="run", desc="study",
                   file=sys.stderr, dynamic_ncols=True)
    last_rebuild = 0.0
    failed = 0
    unsaved = None
    try:
        for fut in as_completed(list(futures), loop=client.loop):
            r = futures[fut]
            try:
                rec = fut.result()
            except Exception as exc:  # noqa: BLE001 - e.g. KilledWorker after too many deaths
                lost[r.hash] = f"{type(exc).__name__}: {exc}"
                if bar is not None:
                    bar.update(1)
                continue
            rec["hash"] = r.hash
            rec["config"] = r.config
            records[r.hash] = rec
            if unsaved is None:
                try:
                    store.save(rec)
                except OSError as exc:   # a full disk: every run still finishes, in memory,
                    unsaved = exc        # and run_study keeps the records elsewhere
            failed += rec["status"] != "ok"
            if on_run is not None:
                on_run(r, rec)
            now = time.perf_counter()
            if unsaved is None and now - last_rebuild >= _REBUILD_EVERY_S:
                _write_tables(out, runs, records, spec)
                last_rebuild = now
            if bar is not None:
                bar.update(1)
                if failed:
                    bar.set_postfix(failed=failed)
    finally:
        if bar is not None:
            bar.close()
        for fut in futures:
            if not fut.done():
                fut.cancel()
    if unsaved is not None:
        raise unsaved


def _run_after(config, law, _warmed):
    return run_one(config, law)


def _interleave(todo: list[RunSpec]) -> list[RunSpec]:
    by_law: dict[str, list[RunSpec]] = {}
    for r in todo:
        by_law.setdefault(r.law, []).append(r)
    out = []
    for i in range(max(len(v) for v in by_law.values())):
        for v in by_law.values():
            if i < len(v):
                out.append(v[i])
    return out
