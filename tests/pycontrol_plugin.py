"""pytest plugin for running python-control's own test files (tests/test_pycontrol.py).

Loaded with ``-p pycontrol_plugin`` in a subprocess whose ``IVDREM_PYCONTROL_ENGINE`` is

* ``none``: python-control's own ``input_output_response``, only counted;
* ``compiled`` / ``reference``: ivdrem's drop-in on that engine, installed for the whole
  session with :func:`ivdrem.pycontrol.replaced` before the test modules are imported (so
  ``from control import input_output_response`` in a test module gets it too).  The tests
  whose node ids start with one of ``IVDREM_PYCONTROL_ON_REFERENCE`` (a JSON list) run on
  the reference engine instead; every test's record names the engine its calls ran on.

Per test it writes to ``IVDREM_PYCONTROL_REPORT`` (JSON): the outcome, the number of calls
that reached the simulator and, on an ivdrem engine, for every call python-control's own
response to the same arguments: the largest difference of the outputs and states scaled by
the solver tolerances (|ivdrem - python-control| / (atol + rtol |python-control|), rtol and
atol those the call asked for, scipy's defaults otherwise).  A call whose difference exceeds
``IVDREM_PYCONTROL_AGREEMENT`` is judged only if its answer is determined that well by its
arguments (:func:`_self_difference`); otherwise it is recorded apart, with the python-control
functions that made it.

Every test starts from the same state whatever ran before it and on whichever engine
(:func:`_fresh_state`): python-control's tests draw random systems from numpy's global
generator (``ct.rss``), unseeded, and its plotting functions draw on the current figure
(``phase_plane_plot`` takes its streamline bounds from the lines already on it); a module
importing draws from a seed of its own too.
"""
from __future__ import annotations

import json
import os
import random
import sys
import warnings
import zlib

import numpy as np
import pytest
import control as ct

# imported now, before pytest puts site-packages first on sys.path for python-control's
# test package (an editable ivdrem would then resolve to another checkout)
import ivdrem.pycontrol as pc

ENGINE = os.environ.get("IVDREM_PYCONTROL_ENGINE", "none")
REPORT = os.environ.get("IVDREM_PYCONTROL_REPORT")
AGREEMENT = float(os.environ.get("IVDREM_PYCONTROL_AGREEMENT", "inf"))
#: node-id prefixes of the tests run on the reference engine whatever ENGINE is
ON_REFERENCE = tuple(json.loads(os.environ.get("IVDREM_PYCONTROL_ON_REFERENCE", "[]")))
#: the size of the initial-state perturbation of _self_difference, in units of
#: atol + rtol |x0|: far below what either solver is asked to resolve
PERTURBATION = 1e-3

_current = {"id": None}
_records = {}
_patch = None


def _tolerances(kwargs):
    opts = dict(kwargs.get("solve_ivp_kwargs") or {})
    return float(opts.get("rtol", 1e-3)), float(np.max(opts.get("atol", 1e-6)))


def _scaled_difference(mine, theirs, rtol, atol):
    worst = 0.0
    for a, b in ((mine.y, theirs.y), (mine.x, theirs.x)):
        if a is None or b is None or np.shape(a) != np.shape(b) or np.size(a) == 0:
            continue
        a, b = np.asarray(a, float), np.asarray(b, float)
        ok = np.isfinite(a) & np.isfinite(b)
        if not ok.any():
            continue
        # the scale of each signal: its largest magnitude over the run (a signal crossing
        # zero has no relative error there)
        scale = np.max(np.abs(b), axis=-1, keepdims=True) if b.ndim > 1 else np.max(np.abs(b))
        d = np.abs(a - b) / (atol + rtol * scale)
        worst = max(worst, float(np.max(d[ok])))
    return worst


def _self_difference(original, args, kwargs, theirs, rtol, atol):
    """How far python-control's own response moves, in units of atol + rtol |y|, when the
    initial state moves by PERTURBATION units of atol + rtol |x0| (a fixed direction of
    random signs); None if the call's initial state is not the response's first sample.

    A well-conditioned call moves by about PERTURBATION.  A call that moves by more than
    the agreement bound amplifies any error (rounding, either solver's local errors) by
    more than AGREEMENT / PERTURBATION: two correct solvers need not agree on it.  Such
    a call is phase_plane_plot's separatrix of a stable node along its slow eigenvector,
    flown backwards in time for log(maxlim / radius) / |slow eigenvalue|: the fast mode,
    absent in exact arithmetic, grows as exp(|fast| t)."""
    timepts = args[1] if len(args) > 1 else kwargs.get("timepts", kwargs.get("T"))
    x = getattr(theirs, "x", None)
    if timepts is None or x is None or np.ndim(x) != 2 or np.size(x) == 0 \
            or theirs.time[0] != np.atleast_1d(timepts)[0]:
        return None
    x0 = np.asarray(x[:, 0], float)
    signs = np.random.default_rng(0).choice([-1.0, 1.0], x0.size)   # not the test's RNG
    moved = x0 + PERTURBATION * (atol + rtol * np.abs(x0)) * signs
    kwargs = {k: v for k, v in kwargs.items() if k not in ("initial_state", "X0", "x0")}
    if len(args) > 3:           # (sys, timepts, inputs, initial_state, ...)
        args = (*args[:3], moved, *args[4:])
    else:
        kwargs["initial_state"] = moved
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        again = original(*args, **kwargs)
    return _scaled_difference(again, theirs, rtol, atol)


def _callers():
    """The python-control functions (outside its tests) on the stack, innermost first."""
    frame, names = sys._getframe(2), []
    while frame is not None:
        module = frame.f_globals.get("__name__", "")
        if module.startswith("control.") and not module.startswith("control.tests"):
            names.append(frame.f_code.co_name)
        frame = frame.f_back
    return names


def _record(nodeid):
    return _records.setdefault(nodeid, {"calls": 0, "diff": [], "ill_conditioned": []})


def engine_of(nodeid, default, on_reference):
    """The engine a test runs on: the reference engine for a node id starting with one of
    `on_reference`, `default` otherwise (one rule, used by tests/test_pycontrol.py too)."""
    return "reference" if nodeid.startswith(tuple(on_reference)) else default


def _per_test(default, on_reference):
    """ivdrem's drop-in on the running test's engine (:func:`engine_of`); the engine is
    recorded with the test's calls, and a response that says it ran on another engine
    (its ``stats``: a system without states has none) fails the test."""
    engines = {e: pc.drop_in(engine=e) for e in {default, "reference"}}

    def input_output_response(*args, **kwargs):
        engine = engine_of(_current["id"] or "", default, on_reference)
        rec = _record(_current["id"])
        if rec.setdefault("engine", engine) != engine:
            raise AssertionError(f"{_current['id']} ran on {rec['engine']} and {engine}")
        resp = engines[engine](*args, **kwargs)
        for r in (resp if isinstance(resp, ct.TimeResponseList) else [resp]):
            ran = (getattr(r, "stats", None) or {}).get("engine", engine)
            if ran != engine:
                raise AssertionError(f"{_current['id']}: asked for {engine}, ran on {ran}")
        return resp
    input_output_response.__doc__ = pc.input_output_response.__doc__
    return input_output_response


def _counted(simulator, original):
    def input_output_response(*args, **kwargs):
        rec = _record(_current["id"])
        rec["calls"] += 1
        resp = simulator(*args, **kwargs)
        if original is not None and not isinstance(args[0] if args else None, (list, tuple)):
            rtol, atol = _tolerances(kwargs)
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    theirs = original(*args, **kwargs)
                if getattr(resp, "success", True) and getattr(theirs, "success", True):
                    diff = _scaled_difference(resp, theirs, rtol, atol)
                    itself = (_self_difference(original, args, kwargs, theirs, rtol, atol)
                              if diff > AGREEMENT else None)
                    if itself is not None and itself > AGREEMENT:
                        rec["ill_conditioned"].append(
                            {"diff": diff, "self": itself, "callers": _callers()})
                    else:
                        rec["diff"].append(diff)
            except Exception:       # noqa: BLE001 - python-control's own failure: no comparison
                pass
        return resp
    input_output_response.__doc__ = simulator.__doc__
    return input_output_response


def pytest_configure(config):
    global _patch
    original = pc.PYTHON_CONTROL_SIMULATOR
    if ENGINE == "none":
        fn = _counted(original, None)
    else:
        fn = _counted(_per_test(ENGINE, ON_REFERENCE), original)
    _patch = pc.replaced(fn)
    _patch.__enter__()


def pytest_unconfigure(config):
    if _patch is not None:
        _patch.__exit__(None, None, None)
    if REPORT:
        with open(REPORT, "w") as f:
            json.dump(_records, f)


def _seed(nodeid):
    """numpy's and Python's global generators seeded from a node id: the node's own seed,
    the same whatever ran before it."""
    seed = zlib.crc32(nodeid.encode())
    np.random.seed(seed)
    random.seed(seed)


def _fresh_state(nodeid):
    """Put the process in the state a test would find alone in a new process, with a
    fixed random seed: without it the harness is neither repeatable nor comparable
    between runs (a random plant of ``ct.rss`` with complex poles has no separatrices for
    ``phase_plane_plot`` to integrate, one with real poles has; a figure left open by an
    earlier test widens the bounds streamlines are integrated to)."""
    _seed(nodeid)
    ct.reset_defaults()
    import matplotlib.pyplot as plt
    plt.close("all")


@pytest.hookimpl(hookwrapper=True)
def pytest_make_collect_report(collector):
    # a test module may draw random systems when it is imported (timeplot_test's
    # parametrize list calls ct.rss): the same seed for it whichever modules came before
    if isinstance(collector, pytest.Module):
        _seed(collector.nodeid)
    yield


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    _current["id"] = item.nodeid
    _fresh_state(item.nodeid)
    yield
    _current["id"] = None


def pytest_runtest_logreport(report):
    rec = _record(report.nodeid)
    if report.when == "call" or report.outcome != "passed":
        if rec.get("outcome") in (None, "passed"):
            rec["outcome"] = report.outcome
            if report.outcome == "failed":
                rec["error"] = str(report.longrepr)[-1500:]
