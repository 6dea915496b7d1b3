"""Progress is reported from inside the run without touching the step sequence: a run with
a progress bar and one without take the same steps and give the same numbers, bit for bit
(docs/simulation.md, "Progress and Ctrl-C")."""
from __future__ import annotations

import numpy as np
import pytest

import ivdrem.sim.simulator as simulator_module
from ivdrem.sim import Simulator, simulate

from conftest import build_lab, paper_loop

CASES = [("compiled", "rodas5p"), ("compiled", "dp45"), ("compiled", "rk4"),
         ("reference", "rodas5p"), ("reference", "dp45"), ("reference", "rk4")]


def _spy_bar(monkeypatch):
    """Replace the progress bar by a list of the times it is given."""
    seen = []
    monkeypatch.setattr(simulator_module, "_progress_bar",
                        lambda enabled, t0, t_end, desc: (None, seen.append) if enabled
                        else (None, None))
    return seen


def _same_run(a, b):
    for key in ("steps", "rejected", "rhs_calls", "jacobians", "factorizations",
                "hold_cuts", "hold_samples"):
        assert a.stats[key] == b.stats[key], key
    assert np.array_equal(np.asarray(a.outputs), np.asarray(b.outputs))
    assert np.array_equal(np.asarray(a.states), np.asarray(b.states))
    assert np.array_equal(a.hold_times, b.hold_times, equal_nan=True)


@pytest.mark.parametrize("engine,method", CASES)
def test_progress_does_not_change_the_run(monkeypatch, engine, method):
    """The lab diagram (delay, window, max-hold): with and without progress, every counter,
    output, state and hold time equal; the reports are monotone, end at t_end, and there
    is at most one in each of the 200 equal intervals of the run (a step may pass several)."""
    lab = build_lab()
    t_end = 2.0
    kw = dict(method=method, engine=engine, h=2e-3, dt_out=0.05)
    quiet = simulate(lab, t_end, progress=False, **kw)
    seen = _spy_bar(monkeypatch)
    shown = simulate(lab, t_end, progress=True, **kw)
    _same_run(quiet, shown)
    assert seen and seen[-1] == pytest.approx(t_end, abs=1e-12)
    assert np.all(np.diff(seen) > 0)
    assert 0.0 < seen[0] <= t_end / 200 + 0.05
    interval = np.floor(np.asarray(seen[:-1]) / (t_end / 200) + 1e-9)
    assert np.all(np.diff(interval) > 0) and len(seen) >= 10


@pytest.mark.parametrize("engine,method", [("compiled", "rodas5p"), ("compiled", "dp45"),
                                           ("reference", "rk4")])
def test_reports_by_wall_time_do_not_change_the_run(monkeypatch, engine, method):
    """Between the 200 reports the stepper returns to Python about every REPORT_WALL_S of
    wall time (where a pending Ctrl-C is handled); with REPORT_WALL_S = 1 µs that is after
    nearly every accepted step: every counter, output, state and hold time the same as with
    the 200 reports alone (REPORT_WALL_S = inf), and the progress bar still given one time
    in each of the 200 intervals."""
    lab = build_lab()
    t_end = 2.0
    kw = dict(method=method, engine=engine, h=2e-3, dt_out=0.05)
    calls = {}
    real = simulator_module.Simulator._report_trampoline
    runs = {}
    for every in (float("inf"), 1e-6):
        monkeypatch.setattr(simulator_module, "REPORT_WALL_S", every)

        def counted(self, t, every=every):
            calls[every] = calls.get(every, 0) + 1
            return real(self, t)
        monkeypatch.setattr(simulator_module.Simulator, "_report_trampoline", counted)
        seen = _spy_bar(monkeypatch)
        runs[every] = (simulate(lab, t_end, progress=True, **kw), seen)
    _same_run(runs[float("inf")][0], runs[1e-6][0])
    assert runs[float("inf")][1] == runs[1e-6][1] and len(runs[1e-6][1]) >= 10
    assert calls[1e-6] > 2 * calls[float("inf")]     # the reports by wall time did happen


def test_progress_does_not_change_the_paper_loop(monkeypatch):
    """IV-DREM on the paper's loop (Rodas5P, 30 s): the steps (and so theta_hat) do not
    depend on the progress bar; before, 200 chunks each ending a step changed them."""
    loop = paper_loop("iv-drem")
    quiet = simulate(loop, 30.0, progress=False)
    seen = _spy_bar(monkeypatch)
    shown = simulate(loop, 30.0, progress=True)
    _same_run(quiet, shown)
    assert len(seen) == 200 and seen[-1] == 30.0


def test_advance_progress_callback_and_its_exception():
    """Simulator.advance(progress=f) calls f with increasing times up to t_to; an exception
    of f stops the run at an accepted step, is raised as it is, and the simulator goes on
    from there to the same end state as an uninterrupted run."""
    lab = build_lab()
    ref = Simulator(lab, method="rodas5p", h=2e-3)
    ref.advance(1.5)
    times = []
    sim = Simulator(lab, method="rodas5p", h=2e-3)
    sim.advance(1.5, progress=times.append)
    assert times[-1] == 1.5 and np.all(np.diff(times) > 0)
    assert np.array_equal(sim.x, ref.x)

    class Stop(Exception):
        pass

    def stop_once(t):
        if t > 0.5 and not stopped:
            stopped.append(t)
            raise Stop
    stopped = []
    sim = Simulator(lab, method="rodas5p", h=2e-3)
    with pytest.raises(Stop):
        sim.advance(1.5, progress=stop_once)
    assert sim.t == stopped[0] and 0.5 < sim.t < 1.5
    sim.advance(1.5)
    assert sim.t == 1.5
    assert np.allclose(sim.x, ref.x, rtol=1e-6, atol=1e-8)
    for s in (ref, sim):
        s.close()
