"""A child process compiling the kernel wrappers numba's cache does not hold while the parent
builds the tables and compiles the others (ivdrem/sim/_compile_child.py, compiled.start_kernels)."""
import math
import signal
import subprocess
import sys

import numpy as np
import pytest

from ivdrem.sim import _compile_child, simulate
from ivdrem.sim import compiled
from ivdrem.compile_cache import cache_dir


def test_the_child_refuses_any_other_job():
    with pytest.raises(SystemExit, match="--modules"):
        _compile_child._job([])


# ---- half the uncached kernel wrappers compiled in a child (ivdrem/sim/compiled._load)


def _lags(n, name):
    """n first-order lags x_i' = -(i + 1) x_i + u, y = sum x_i: a diagram whose wrappers
    (their shapes) no other test of this module imports."""
    import control as ct
    k = np.arange(1.0, n + 1.0)
    sys_ = ct.ss(-np.diag(k), np.ones((n, 1)), np.ones((1, n)), [[0.0]], inputs="u",
                 outputs="y", name=f"{name}_lags")
    return ct.interconnect([sys_], inputs="u", outputs="y", name=name), k


def _check(loop, k):
    r = simulate(loop, [0.0, 0.5], inputs=1.0, progress=False)
    np.testing.assert_allclose(r.outputs[-1], np.sum((1.0 - np.exp(-k * 0.5)) / k),
                               rtol=1e-6)


def _pretend_uncached(monkeypatch):
    """Every generated function counts as not in numba's cache, and the child starts
    without a head start and takes any share: a small diagram then gets a child for some
    of its wrappers."""
    monkeypatch.setattr(_compile_child, "function_cached", lambda path, qualname: False)
    monkeypatch.setattr(compiled, "_CHILD_START_S", 0.0)
    monkeypatch.setattr(compiled, "_CHILD_MIN_S", 0.0)
    monkeypatch.delenv("IVDREM_STEPPER_CHILD", raising=False)
    monkeypatch.delenv("IVDREM_STEPPER_PREFETCH", raising=False)
    monkeypatch.delenv("IVDREM_COMPILE_CHILD", raising=False)
    # nor imported by an earlier test of this process (a process that imported every module
    # of a loop compiles nothing): generated modules out of sys.modules until the test ends
    for name in [m for m in sys.modules if m.startswith("ivdrem_")]:
        monkeypatch.delitem(sys.modules, name)


def _spy(monkeypatch):
    """[[Warmup, its process, what wait answered]] of the children _load starts."""
    seen = []
    start, wait = _compile_child.start_modules, _compile_child.Warmup.wait

    def spy_start(names):
        w = start(names)
        seen.append([w, w.proc, None])
        return w

    def spy_wait(self, limit=_compile_child.WAIT_LIMIT_S):
        ok = wait(self, limit)
        for s in seen:
            if s[0] is self:
                s[2] = ok
        return ok

    monkeypatch.setattr(_compile_child, "start_modules", spy_start)
    monkeypatch.setattr(_compile_child.Warmup, "wait", spy_wait)
    return seen


def test_a_cfuncs_cache_is_found_without_importing_it():
    # the wrappers of a finished run: numba's cfunc exposes its cache as a dispatcher does,
    # and the check from the source file alone names the same index file
    import control as ct
    lag = ct.ss([[-2.0]], [[1.0]], [[1.0]], [[0.0]], inputs="u", outputs="y", name="lag2")
    loop = ct.interconnect([lag], inputs="u", outputs="y", name="lag_loop")
    simulate(loop, [0.0, 0.1], inputs=1.0, progress=False)
    from ivdrem.sim.plan import DiagramPlan
    wrappers = [sys.modules[w] for _, _, w in
                compiled.generate_source(DiagramPlan.from_diagram(loop, None, None)).wrappers]
    assert len(wrappers) == 3
    for mod in wrappers:
        assert _compile_child.index_exists(mod.wrapper._cache)
        assert _compile_child.function_cached(mod.__file__, "wrapper")
    # a source file numba never compiled is not cached
    fresh = cache_dir() / "ivdrem_test_never_compiled.py"
    fresh.write_text("def wrapper(t):\n    return t\n")
    try:
        assert not _compile_child.function_cached(fresh, "wrapper")
    finally:
        fresh.unlink()


def test_the_split_is_balanced_and_covers_every_uncached_wrapper_once(monkeypatch):
    from ivdrem.diagrams import closed_loop
    from ivdrem.sim.plan import DiagramPlan
    monkeypatch.setattr(_compile_child, "function_cached", lambda path, qualname: False)
    plan = DiagramPlan.from_diagram(closed_loop(law="iv-drem"), None, None)
    deps = compiled.generate_source(plan).deps
    cdir = cache_dir()
    for name, src in deps:
        compiled._write(cdir, name, src)
        monkeypatch.delitem(sys.modules, name, raising=False)   # imported by another test
    costs = compiled._uncached_wrappers(cdir, deps)
    wrappers = [n for n, _ in deps if n.startswith("ivdrem_wrapper_")]
    assert len(wrappers) == len(compiled.generate_source(plan).wrappers) > 20
    assert sorted(costs) == sorted(wrappers)
    head = compiled._CHILD_START_S
    parent, child = compiled._split(costs, head)
    assert sorted(parent + child) == sorted(wrappers)          # each exactly once
    assert len(set(parent + child)) == len(wrappers)

    def load(names):
        callees = {}
        for n in names:
            callees.update(costs[n][1])
        return sum(costs[n][0] for n in names) + sum(callees.values())

    dearest = max(c[0] + sum(c[1].values()) for c in costs.values())
    assert abs(load(parent) - (head + load(child))) <= dearest
    assert 0.3 < load(child) / load(parent) < 1.0              # the child starts late
    # the child's job: its wrappers after the kernel and model modules they import
    job = compiled._with_imports(child, deps)
    order = [n for n, _ in deps]
    assert job[-len(child):] == child                          # in the split's order
    assert job[:-len(child)] == sorted(job[:-len(child)], key=order.index)
    for w in child:
        kernel = compiled._GENERATED_IMPORT.findall(dict(deps)[w])[0]
        assert job.index(kernel) < job.index(w)
    # nothing uncached: nothing for a child
    assert compiled._split({}) == ([], [])
    # this process busy first (the probe, the Jacobian program, the LU: the engine's case):
    # the child gets every wrapper, the dearest first, and this process takes back the
    # cheapest from the end (_import_all)
    parent, child = compiled._split(costs, head, math.inf)
    assert parent == [] and sorted(child) == sorted(wrappers)
    totals = [costs[n][0] + sum(costs[n][1].values()) for n in child]
    assert totals == sorted(totals, reverse=True)


def test_a_child_compiles_half_the_wrappers(monkeypatch):
    _pretend_uncached(monkeypatch)
    seen = _spy(monkeypatch)
    loop, k = _lags(4, "split_ok")
    _check(loop, k)
    assert len(seen) == 1
    w, proc, ok = seen[0]
    assert ok is True and proc.returncode == 0
    assert w.modules and all(m in sys.modules for m in w.modules)


def test_a_failing_child_leaves_the_parent_compiling_everything(monkeypatch):
    _pretend_uncached(monkeypatch)
    seen = _spy(monkeypatch)
    real = compiled._with_imports
    # the child fails at once, on a module that does not exist
    monkeypatch.setattr(compiled, "_with_imports",
                        lambda names, deps: ["ivdrem_no_such_module"] + real(names, deps))
    loop, k = _lags(2, "split_fails")
    _check(loop, k)
    assert len(seen) == 1
    w, proc, ok = seen[0]
    assert ok is False and proc.returncode != 0
    assert "ivdrem_no_such_module" in w.modules
    assert all(m in sys.modules for m in w.modules if m != "ivdrem_no_such_module")


def test_an_interrupted_parent_kills_its_child(monkeypatch):
    _pretend_uncached(monkeypatch)
    seen = _spy(monkeypatch)
    real = compiled._import

    def interrupted(cdir, name, src):
        if name.startswith("ivdrem_wrapper_"):
            raise KeyboardInterrupt
        return real(cdir, name, src)

    monkeypatch.setattr(compiled, "_import", interrupted)
    loop, _ = _lags(3, "split_interrupted")
    with pytest.raises(KeyboardInterrupt):
        simulate(loop, [0.0, 0.5], inputs=1.0, progress=False)
    assert len(seen) == 1
    w, proc, _ = seen[0]
    assert w.proc is None and proc.returncode == -signal.SIGKILL    # killed, not finished


def test_no_split_child_from_a_child_or_when_switched_off(monkeypatch):
    _pretend_uncached(monkeypatch)
    for env in ("IVDREM_STEPPER_CHILD=1", "IVDREM_COMPILE_CHILD=0",
                "IVDREM_STEPPER_PREFETCH=0"):
        name, value = env.split("=")
        monkeypatch.setenv(name, value)
        assert not _compile_child.enabled()
        assert _compile_child.start_modules(["ivdrem_anything"]).proc is None
        monkeypatch.delenv(name)
    assert _compile_child.enabled()
    assert _compile_child.start_modules([]).proc is None            # nothing to do


def test_no_child_for_a_small_share(monkeypatch):
    # a few cheap wrappers: the child's start would cost what it saves
    _pretend_uncached(monkeypatch)
    monkeypatch.setattr(compiled, "_CHILD_START_S", 0.75)
    monkeypatch.setattr(compiled, "_CHILD_MIN_S", 1.0)
    monkeypatch.setattr(_compile_child, "start_modules", lambda names: 1 / 0)
    loop, k = _lags(6, "small_share")
    _check(loop, k)


def test_the_child_starts_before_the_probe_and_a_failing_probe_kills_it(monkeypatch):
    # the kernels' compile starts before the tables are built; an error in the probe (or
    # the Jacobian program, or the LU) reaches the user as it is and leaves no child
    _pretend_uncached(monkeypatch)
    seen = _spy(monkeypatch)
    running = []

    def failing_probe(plan, **kw):
        running.extend(s[1].poll() is None for s in seen)   # the child, compiling now
        raise ValueError("the probe failed")

    monkeypatch.setattr(compiled, "JacobianProgram", failing_probe)
    loop, _ = _lags(5, "probe_fails")
    with pytest.raises(ValueError, match="the probe failed"):
        simulate(loop, [0.0, 0.5], inputs=1.0, progress=False)
    assert len(seen) == 1 and running == [True]
    w, proc, _ = seen[0]
    assert w.proc is None and proc.returncode == -signal.SIGKILL    # killed and reaped


def test_the_parent_takes_back_what_the_child_has_not_reached(monkeypatch):
    # a child that compiles nothing (it sleeps): the parent, its tables built, compiles the
    # child's whole share itself, from the last back, then joins the child
    _pretend_uncached(monkeypatch)
    given = []

    def idle_child(names):
        given.extend(names)
        proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(2)"])
        return _compile_child.Warmup(proc, names)

    monkeypatch.setattr(_compile_child, "start_modules", idle_child)
    imported = []
    real = compiled._import
    monkeypatch.setattr(compiled, "_import",
                        lambda cdir, name, src: imported.append(name) or real(cdir, name, src))
    loop, k = _lags(7, "child_idle")
    _check(loop, k)
    wrappers = [n for n in given if n.startswith("ivdrem_wrapper_")]
    assert len(wrappers) == 3                       # output, update, jacobian: all of them
    assert [n for n in imported if n in wrappers] == wrappers[::-1]
    assert all(n in sys.modules for n in given)
