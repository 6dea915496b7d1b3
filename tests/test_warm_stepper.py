"""The shared stepper compiled in a child process while the parent compiles its kernels
(ivdrem/sim/_warm_stepper.py)."""
import numpy as np

from ivdrem.sim import _warm_stepper, simulate
from ivdrem.sim.compiled import _import, cache_dir, stepper_module


def _stepper():
    name, src = stepper_module()
    return _import(cache_dir(), name, src)


def test_a_compiled_run_leaves_the_stepper_in_numbas_cache():
    import control as ct
    lag = ct.ss([[-2.0]], [[1.0]], [[1.0]], [[0.0]], inputs="u", outputs="y", name="lag2")
    loop = ct.interconnect([lag], inputs="u", outputs="y", name="lag_loop")
    r = simulate(loop, [0.0, 0.5], inputs=1.0, progress=False)
    # y' = -2 y + 1 from 0: y(0.5) = (1 - e^-1) / 2
    np.testing.assert_allclose(r.outputs[-1], (1.0 - np.exp(-1.0)) / 2.0, rtol=1e-6)
    assert _warm_stepper.stepper_cached(_stepper())
    # nothing to do then: no child process
    assert _warm_stepper.start(_stepper()).proc is None


def test_the_child_runs_and_the_parent_waits_for_it(monkeypatch):
    # pretend the cache is cold: the child starts, compiles (here: loads) the stepper and
    # exits cleanly; the parent's wait reports it
    monkeypatch.setattr(_warm_stepper, "stepper_cached", lambda module: False)
    w = _warm_stepper.start(_stepper())
    assert w.proc is not None
    assert w.wait(limit=600) is True
    assert w.proc is None and w.wait() is False       # waited once; nothing left


def test_no_child_from_a_child_or_when_switched_off(monkeypatch):
    monkeypatch.setattr(_warm_stepper, "stepper_cached", lambda module: False)
    monkeypatch.setenv("IVDREM_STEPPER_CHILD", "1")
    assert _warm_stepper.start(_stepper()).proc is None
    monkeypatch.delenv("IVDREM_STEPPER_CHILD")
    monkeypatch.setenv("IVDREM_STEPPER_PREFETCH", "0")
    assert _warm_stepper.start(_stepper()).proc is None
