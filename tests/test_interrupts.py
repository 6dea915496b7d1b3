"""Ctrl-C and absurd solver settings (docs/simulation.md, "Progress and Ctrl-C"): a Ctrl-C
inside `simulate` is a KeyboardInterrupt on every engine, never a BlockError blaming a
block; the commands print one line and exit 130; solver settings outside a sensible range
are refused naming the key before anything is compiled."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import threading
import time

import control as ct
import numpy as np
import pytest

import ivdrem.cli as cli
from ivdrem.sim import simulate
from ivdrem.sim.errors import BlockError

from conftest import build_lab


def _slow_python_plant():
    """A plain nlsys that numba cannot compile (it sleeps): it runs in Python, called back
    from the compiled loop."""
    def update(t, x, u, params):
        time.sleep(2e-5)
        return np.array([-x[0] + 1.0])
    plant = ct.nlsys(update, lambda t, x, u, p: x, inputs=0, outputs=["y"], states=1,
                     name="slow_plant")
    return ct.interconnect([plant], inplist=[], outlist=["y"], name="slow")


def _interrupt_after(seconds):
    timer = threading.Timer(seconds, os.kill, (os.getpid(), signal.SIGINT))
    timer.start()
    return timer


@pytest.mark.parametrize("case", ["compiled", "compiled-python-block", "reference"])
def test_ctrl_c_inside_simulate_is_a_keyboard_interrupt(case, ctrl_c_delivered):
    """The compiled loop without Python blocks handles a pending Ctrl-C at its reports
    (200 per run); a Python block's or the reference engine's callback raises it; either
    way simulate raises KeyboardInterrupt, soon, and not as a BlockError."""
    if case == "compiled-python-block":
        diagram, kw = _slow_python_plant(), dict(method="rk4", h=1e-4)
    else:
        diagram, kw = build_lab(), dict(engine=case, method="rk4", h=1e-4)
    simulate(diagram, 0.01, progress=False, **kw)            # compiled before the clock
    timer = _interrupt_after(1.0)
    t0 = time.perf_counter()
    try:
        with pytest.raises(KeyboardInterrupt) as info:
            simulate(diagram, 1e4, progress=False, allow_long=True, **kw)
    finally:
        timer.cancel()
    assert not isinstance(info.value, BlockError)
    assert time.perf_counter() - t0 < 30.0


#: another process that sends SIGINT to argv[1] after argv[2] seconds and prints when (a
#: thread of this process would wait for the GIL, which the compiled loop holds)
_KILLER = ("import os, signal, sys, time; time.sleep(float(sys.argv[2])); "
           "print(repr(time.time()), flush=True); os.kill(int(sys.argv[1]), signal.SIGINT)")


def test_ctrl_c_stops_a_long_compiled_run_within_a_second(ctrl_c_delivered):
    """The compiled loop without Python blocks returns to Python at its 200 reports and
    about every REPORT_WALL_S = 0.1 s of wall time between them: a 1e4 s run at h = 1e-4
    (1e8 steps; a 200th of it is tens of seconds) stops within a second of a SIGINT sent
    by another process (1.6 s with the 200 reports alone, measured)."""
    diagram, kw = build_lab(), dict(engine="compiled", method="rk4", h=1e-4)
    simulate(diagram, 0.01, progress=False, **kw)            # compiled before the clock
    killer = subprocess.Popen([sys.executable, "-c", _KILLER, str(os.getpid()), "1.0"],
                              stdout=subprocess.PIPE, text=True)
    try:
        with pytest.raises(KeyboardInterrupt):
            simulate(diagram, 1e4, progress=False, allow_long=True, **kw)
        stopped = time.time()
    finally:
        out, _ = killer.communicate(timeout=60)
    assert stopped - float(out) < 1.0, stopped - float(out)


def test_a_ctrl_c_at_a_callbacks_entry_stops_the_run_as_a_keyboard_interrupt(capfd):
    """Python may raise a pending Ctrl-C as the stepper's report callback is entered, before
    its own try: ctypes hands it to sys.unraisablehook ("Exception ignored ...") and the C
    loop goes on.  The simulator's hook takes it: the run stops with KeyboardInterrupt,
    nothing is printed, and the hook leaves everyone else's unraisable exceptions alone."""
    import types
    from ivdrem.sim import simulator as simulator_module
    diagram = build_lab()
    sim = simulator_module.Simulator(diagram, method="rk4", h=1e-3)
    calls = []

    def progress_entry_interrupted(t):
        # what CPython does when SIGINT arrives as the callback is called
        calls.append(t)
        sys.unraisablehook(types.SimpleNamespace(
            object=sim._report_trampoline, exc_value=KeyboardInterrupt(),
            exc_type=KeyboardInterrupt, exc_traceback=None, err_msg=None))
    out_t = np.linspace(0.0, 100.0, 11)
    with pytest.raises(KeyboardInterrupt):
        sim.advance(100.0, out_t=out_t, out_y=np.zeros((11, diagram.noutputs)),
                    out_x=np.zeros((11, 0)), progress=progress_entry_interrupted)
    assert len(calls) == 1 and sim.t < 100.0
    seen = []
    previous = sys.unraisablehook
    try:      # an unraisable exception of someone else's object is passed on
        sys.unraisablehook = lambda u, _p=previous: seen.append(u) if u.object == "other" \
            else _p(u)
        simulator_module._catch_callback_interrupts()
        sys.unraisablehook(types.SimpleNamespace(object="other", exc_value=ValueError()))
    finally:
        sys.unraisablehook = previous
    assert len(seen) == 1
    assert "Exception ignored" not in capfd.readouterr().err


@pytest.mark.parametrize("argv", [["paper", "--laws", "iv-drem", "--t-end", "5"],
                                  ["report", "--t-end", "5"]])
def test_commands_exit_130_with_one_line_on_ctrl_c(argv, monkeypatch, capsys, tmp_path):
    """A Ctrl-C anywhere in a command: one line on stderr, exit status 130, no traceback."""
    import ivdrem.sim.simulator as simulator_module

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt
    monkeypatch.setattr(simulator_module.Simulator, "advance", interrupted)
    monkeypatch.chdir(tmp_path)
    assert cli.main(argv) == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == "ivdrem: interrupted (Ctrl-C)"
    assert not any("Traceback" in line for line in err)


def test_a_real_ctrl_c_during_the_paper_run_exits_130(tmp_path):
    """SIGINT sent 1 s into the paper run of a real `ivdrem paper` process."""
    driver = textwrap.dedent("""
        import os, signal, sys, threading
        import ivdrem.cli
        import ivdrem.sim.simulator as S
        advance = S.Simulator.advance
        def advance_then_ctrl_c(self, *args, **kwargs):
            threading.Timer(1.0, os.kill, (os.getpid(), signal.SIGINT)).start()
            return advance(self, *args, **kwargs)
        S.Simulator.advance = advance_then_ctrl_c
        sys.exit(ivdrem.cli.main(["paper", "--laws", "iv-drem", "--engine", "reference",
                                  "--t-end", "60", "--allow-long", "--quiet"]))
    """)
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, PYTHONPATH=root)
    # started as a terminal starts it: SIGINT at its default, so that Python installs its
    # Ctrl-C handler even where this test process inherited SIGINT ignored
    res = subprocess.run([sys.executable, "-c", driver], capture_output=True, text=True,
                         env=env, cwd=tmp_path, timeout=300,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    assert res.returncode == 130, res.stderr[-2000:]
    assert res.stderr.strip().splitlines()[-1] == "ivdrem: interrupted (Ctrl-C)"
    assert "Traceback" not in res.stderr


@pytest.mark.parametrize("key,value,message", [
    ("rtol", 0.0, "rtol must be a finite number > 0"),
    ("rtol", -1e-6, "rtol must be a finite number > 0"),
    ("rtol", 1.0, "rtol must be below 1"),
    ("rtol", 5.0, "rtol must be below 1"),
    ("rtol", float("nan"), "rtol must be a finite number > 0"),
    ("atol", 0.0, "atol must be a finite number > 0"),
    ("atol", float("inf"), "atol must be a finite number > 0"),
    ("h", float("nan"), "h must be a finite number > 0"),
    ("h", -1e-3, "h must be a finite number > 0"),
    ("h_max", 1e-4, r"h_max = 0.0001 s is below h = 0.001 s"),
    ("h_max", float("nan"), "h_max must be a finite number > 0"),
    ("x_limit", 0.0, "x_limit must be a finite number > 0"),
    ("max_steps", 0, "max_steps must be a whole number >= 1"),
    ("rtol", True, "rtol must be a number"),
])
def test_absurd_solver_settings_are_refused_before_compiling(key, value, message,
                                                             monkeypatch):
    """Refused by name before the plan, the compile or the run (the engines are never
    built: building one would fail here)."""
    import ivdrem.sim.simulator as simulator_module

    def no_engine(*args, **kwargs):
        raise AssertionError("an engine was built before the settings were checked")
    monkeypatch.setattr(simulator_module, "CompiledEngine", no_engine)
    with pytest.raises(ValueError, match=message):
        simulate(build_lab(), 0.1, progress=False, **{key: value})


def test_sensible_settings_at_the_edges_still_run():
    """A tiny rtol, h_max = h and h_max = inf without delays are accepted."""
    r = simulate(_slow_python_plant(), 0.05, progress=False, rtol=1e-12, atol=1e-14,
                 h_max=float("inf"))
    assert r.stats["steps"] > 0
    r = simulate(_slow_python_plant(), 0.05, progress=False, method="rk4", h=1e-2,
                 h_max=1e-2)
    assert np.asarray(r.outputs).reshape(-1)[-1] == pytest.approx(1 - np.exp(-0.05), rel=1e-6)


# ----------------------------------------------------------------------------- NaN
def _nan_loop(where):
    """src -> plant; `where` = "output": src's output is NaN after t = 0.2 s; "update":
    the plant's derivative is NaN once its state passes 0.3."""
    def src_out(t, x, u, params):
        return np.array([np.nan if (where == "output" and t > 0.2) else 1.0])

    def plant_update(t, x, u, params):
        if where == "update" and x[0] > 0.3:
            return np.array([np.nan])
        return np.array([-x[0] + u[0]])
    src = ct.nlsys(None, src_out, inputs=0, outputs=["s"], name="src")
    plant = ct.nlsys(plant_update, lambda t, x, u, p: x, inputs=["s"], outputs=["y"],
                     states=1, name="plant")
    return ct.interconnect([src, plant], inplist=[], outlist=["y"], name=f"nan_{where}")


@pytest.mark.parametrize("engine", ["compiled", "reference"])
@pytest.mark.parametrize("method", ["rodas5p", "dp45"])
@pytest.mark.parametrize("where,block,function", [("output", "src", "output function"),
                                                   ("update", "plant", "update function")])
def test_a_nan_from_a_block_is_called_a_nan_naming_the_block(engine, method, where, block,
                                                             function):
    """Not "above the limit", "stiffness" or "step size fell below 1e-13 s": the block
    whose output or derivative is NaN with finite inputs, and the time; the plant is
    downstream of a NaN source and not blamed."""
    with pytest.raises(Exception) as info:
        simulate(_nan_loop(where), 1.0, engine=engine, method=method, progress=False)
    msg = str(info.value)
    assert f"block '{block}'" in msg and "not a number" in msg and function in msg, msg
    t_nan = 0.2 if where == "output" else -np.log(0.7)      # x(t) = 1 - exp(-t) = 0.3
    t_said = float(msg.split("at t = ")[-1].split(" s")[0])
    assert t_said == pytest.approx(t_nan, abs=1e-3)
    assert "limit" not in msg and "stiff" not in msg and "1e-13" not in msg


# ----------------------------------------------------------------------------- raising
@pytest.mark.parametrize("engine", ["compiled", "reference"])
def test_an_exception_in_any_evaluation_stops_the_run_naming_the_block(engine, capfd):
    """A Python block that raises from its n-th call on, for n across the first steps: the
    call that raises is a stage, an output, an after-step or a column of the Jacobian's
    forward differences; every time the run stops with a BlockError naming the block, the
    exception chained, and nothing printed ("Exception ignored" from a callback)."""
    for n_ok in (1, 2, 3, 4, 5, 7, 9, 12, 17, 30, 61):
        calls = [0]

        def update(t, x, u, params, calls=calls, n_ok=n_ok):
            calls[0] += 1
            if calls[0] > n_ok:
                raise ZeroDivisionError(f"call {calls[0]}")
            return np.array([-x[0] + x[1], -2.0 * x[1]])
        plant = ct.nlsys(update, lambda t, x, u, p: x, inputs=0, outputs=2, states=2,
                         name="raiser")
        d = ct.interconnect([plant], inplist=[], outlist=["raiser.y[0]", "raiser.y[1]"],
                            name="raising")
        with pytest.raises(BlockError, match="block 'raiser'") as info:
            simulate(d, 1.0, initial_state=[1.0, 1.0], engine=engine, progress=False)
        assert isinstance(info.value.__cause__, ZeroDivisionError), n_ok
    out, err = capfd.readouterr()
    assert "Exception ignored" not in err and "Traceback" not in err, err[-2000:]


@pytest.mark.parametrize("engine", ["compiled", "reference"])
def test_an_exception_in_an_output_function_names_the_block(engine, capfd):
    """A Python block whose output function raises (at t = 0, and from the n-th call on):
    a BlockError naming the block, the exception chained, on both engines (the compiled
    engine once looked for its workspace in the wrong argument and gave an AttributeError)."""
    for n_ok in (0, 1, 3, 10):
        calls = [0]

        def output(t, x, u, params, calls=calls, n_ok=n_ok):
            calls[0] += 1
            if calls[0] > n_ok:
                raise KeyError("boom")
            return x
        plant = ct.nlsys(lambda t, x, u, p: -x, output, inputs=0, outputs=1, states=1,
                         name="bad")
        d = ct.interconnect([plant], inplist=[], outlist=["bad.y[0]"], name="bad_output")
        with pytest.raises(BlockError, match="block 'bad'") as info:
            simulate(d, 1.0, initial_state=[1.0], engine=engine, progress=False)
        assert isinstance(info.value.__cause__, KeyError), n_ok
    assert "Exception ignored" not in capfd.readouterr().err
