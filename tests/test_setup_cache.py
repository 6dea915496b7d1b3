"""The compiled engine's tables kept across simulate calls and processes (ivdrem.sim.compiled
.diagram_tables, keyed by ivdrem.sim.jacobian.structure_digest): a second call of the same
diagram builds nothing, a changed parameter or diagram is a new key, and what is read back
is what a build gives, bit for bit."""
from __future__ import annotations

import numpy as np
import pytest

from ivdrem.diagrams import closed_loop
from ivdrem.sim import compiled, jacobian, simulate
from ivdrem.sim.plan import DiagramPlan

#: a full Γ: none of the adaptation law's Jacobian entries is an exact zero, where the
#: paper's diagonal Γ makes _parameter_zeros leave its off-diagonal products out
GAMMA_FULL = 0.01 * np.eye(5) + 0.001 * (np.ones((5, 5)) - np.eye(5))
T_END = 0.5


def _never(*a, **k):
    raise AssertionError("the tables were built or read again")


@pytest.fixture
def loop():
    d = closed_loop("iv-drem")
    simulate(d, 0.01, progress=False)      # its kernels imported (from the usual cache)
    return d


@pytest.fixture
def fresh_cache(tmp_path, monkeypatch):
    """An empty compile cache (the kernels stay imported in this process) and no tables
    kept in the process."""
    monkeypatch.setenv("IVDREM_CACHE_DIR", str(tmp_path))
    compiled._TABLES.clear()
    jacobian._PATTERNS.clear()
    jacobian._PROGRAMS.clear()
    from ivdrem.sim import sparse_lu
    sparse_lu._SYMBOLIC.clear()
    return tmp_path


def _same_run(a, b):
    assert a.stats["steps"] == b.stats["steps"]
    assert np.array_equal(a.outputs, b.outputs) and np.array_equal(a.states, b.states)


def _built(d, params=None):
    """The run of `d` with its tables built (none kept in the process or read from disk)."""
    compiled._TABLES.clear()
    load = compiled.load_tables
    compiled.load_tables = lambda path: None
    try:
        return simulate(d, T_END, params=params, progress=False)
    finally:
        compiled.load_tables = load


def test_a_second_call_builds_nothing_and_a_changed_parameter_is_seen(loop, monkeypatch):
    compiled._TABLES.clear()
    first = simulate(loop, T_END, progress=False)
    assert len(compiled._TABLES) == 1
    with monkeypatch.context() as m:
        m.setattr(compiled, "JacobianProgram", _never)
        m.setattr(compiled, "load_tables", _never)
        _same_run(simulate(loop, T_END, progress=False), first)
    # a gain changed: the run sees it (a new key: the probe reads the parameter values)
    k3 = simulate(loop, T_END, params={"K": 3.0 * np.eye(2)}, progress=False)
    assert not np.array_equal(k3.outputs, first.outputs)
    # a parameter the tables depend on (the exact zeros of Γ): new tables, as a build
    full = simulate(loop, T_END, params={"Gamma": GAMMA_FULL}, progress=False)
    assert len(compiled._TABLES) == 3
    assert not np.array_equal(full.outputs, first.outputs)
    _same_run(full, _built(loop, {"Gamma": GAMMA_FULL}))
    _same_run(k3, _built(loop, {"K": 3.0 * np.eye(2)}))
    _same_run(first, _built(loop))


def test_the_diagram_changed_in_place_between_calls_is_seen(loop):
    """A block's parameter changed in the diagram itself (not passed to simulate) between
    two calls: the second call runs the new value with the tables it needs."""
    compiled._TABLES.clear()
    first = simulate(loop, T_END, progress=False)
    law = next(s for s in loop.syslist if s.name == "adaptation_law")
    law.params = {**law.params, "Gamma": GAMMA_FULL}
    loop.params = {**loop.params, "Gamma": GAMMA_FULL}
    changed = simulate(loop, T_END, progress=False)
    assert len(compiled._TABLES) == 2
    assert not np.array_equal(changed.outputs, first.outputs)
    _same_run(changed, simulate(closed_loop("iv-drem"), T_END,
                                params={"Gamma": GAMMA_FULL}, progress=False))


def test_a_new_process_reads_the_tables_from_one_file_equal_to_a_build(loop, fresh_cache,
                                                                       monkeypatch):
    plan = DiagramPlan.from_diagram(loop)
    modules = compiled.kernel_modules(plan)
    built = compiled.diagram_tables(plan, modules)
    files = list((fresh_cache / "tables").glob("*.npz"))
    assert len(files) == 1
    compiled._TABLES.clear()                           # another process: from the file
    with monkeypatch.context() as m:
        m.setattr(compiled, "JacobianProgram", _never)
        read = compiled.diagram_tables(plan, modules)
    for name in built._fields:
        a, b = getattr(built, name), getattr(read, name)
        assert a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b), name
        assert not b.flags.writeable, name
    # a damaged file is built again and rewritten
    files[0].write_bytes(b"not an npz")
    compiled._TABLES.clear()
    again = compiled.diagram_tables(plan, modules)
    assert all(np.array_equal(getattr(again, f), getattr(built, f)) for f in built._fields)
    assert compiled.load_tables(files[0]) is not None


def test_the_key_follows_what_the_tables_are_built_from(loop):
    """structure_digest changes with a parameter value, a connection's gain and the probe's
    seed; it is the same for an equal diagram built again."""
    import control as ct
    base = jacobian.structure_digest(DiagramPlan.from_diagram(loop))
    assert base == jacobian.structure_digest(DiagramPlan.from_diagram(closed_loop("iv-drem")))
    assert base != jacobian.structure_digest(
        DiagramPlan.from_diagram(loop, params={"Gamma": GAMMA_FULL}))
    assert base != jacobian.structure_digest(DiagramPlan.from_diagram(loop), seed=1)
    plan = DiagramPlan.from_diagram(loop)
    C = plan.maps[0].copy()
    C.data[0] *= 2.0                          # a gain of the connection map
    plan.maps = (C,) + tuple(plan.maps[1:])
    assert base != jacobian.structure_digest(plan)
    # a user's nlsys: no key, built every time
    lag = ct.nlsys(lambda t, x, u, p: -x + u, lambda t, x, u, p: x, inputs=1, outputs=1,
                   states=1, name="lag")
    d = ct.interconnect([lag], inputs=["u[0]"], outputs=["y[0]"])
    plan = DiagramPlan.from_diagram(d)
    compiled._check_kernels(plan)
    assert compiled.tables_key(plan, compiled.kernel_modules(plan)) is None


def test_the_kept_tables_are_pruned_least_recently_used_first(tmp_path):
    """A study at many parameter values keeps one file per value: beyond the limit the
    files read or written longest ago go first."""
    import os
    from ivdrem.sim.tables import prune_kept_tables
    for k in range(5):
        f = tmp_path / f"{k}.npz"
        f.write_bytes(b"x" * 1000)
        os.utime(f, (1000.0 + k, 1000.0 + k))        # 0 the oldest, 4 the newest
    os.utime(tmp_path / "1.npz", (2000.0, 2000.0))    # 1 read last
    (tmp_path / "other.txt").write_bytes(b"y" * 10_000)   # not a kept table: left alone
    prune_kept_tables(tmp_path, limit=2500)
    assert sorted(f.name for f in tmp_path.iterdir()) == ["1.npz", "4.npz", "other.txt"]
    prune_kept_tables(tmp_path, limit=10_000)         # under the limit: nothing removed
    assert len(list(tmp_path.glob("*.npz"))) == 2
