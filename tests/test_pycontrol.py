"""python-control's own tests, run with ivdrem's simulator in place of
``ct.input_output_response`` (ivdrem.pycontrol; docs/simulation.md, "A drop-in for
python-control").

The test files ship with python-control (``control/tests``).  They run in a subprocess with
tests/pycontrol_plugin.py, once on python-control's own simulator and once on ivdrem's, and
the tests are compared one by one.  ``tests/data/pycontrol_reaching.txt`` lists the tests
that reach the simulator and pass on python-control; the default suite runs those of
QUICK_FILES once, each on one engine (ON_REFERENCE: the tests of a response's conventions on
the reference engine, the others on the compiled one); ``IVDREM_PYCONTROL_FULL=1`` runs all
of them (about 8 minutes per engine), on both engines, and checks the list against the whole
files.

Numerical agreement: every call of a test is also run on python-control, and the outputs
and states must agree within a multiple of the tolerances the call asked for (both
solvers' global errors are of that order; a wrong formula would be far outside).  A call
beyond that bound whose own answer is not determined to it (python-control's response moves
by more than the bound when the initial state moves by 1e-3 of the tolerance) is not
judged; the only such calls are phase_plane_plot's separatrices of a stable node along its
slow direction (test_ill_conditioned_separatrix_is_set_apart).

Every test runs from the same state (tests/pycontrol_plugin.py: its own random seed,
python-control's defaults, no open figure), so two runs give the same table and numbers.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import control as ct

from ivdrem import pycontrol as pc
import pycontrol_plugin as plugin

HERE = Path(__file__).resolve().parent
CT_TESTS = Path(ct.__file__).resolve().parent / "tests"
REACHING = HERE / "data" / "pycontrol_reaching.txt"
FULL = bool(os.environ.get("IVDREM_PYCONTROL_FULL"))

#: python-control's test files that call input_output_response (directly or through
#: control.optimal, forced_response on a nonlinear system, phase_plane_plot, stochsys)
FILES = ("ctrlplot_test.py", "descfcn_test.py", "flatsys_test.py", "interconnect_test.py",
         "iosys_test.py", "kwargs_test.py", "namedio_test.py", "nlsys_test.py",
         "optimal_test.py", "phaseplot_test.py", "response_test.py", "statefbk_test.py",
         "stochsys_test.py", "timeplot_test.py", "timeresp_test.py", "trdata_test.py")

#: the files the default suite runs (every file with IVDREM_PYCONTROL_FULL=1)
QUICK_FILES = ("flatsys_test.py", "interconnect_test.py", "kwargs_test.py", "nlsys_test.py",
               "statefbk_test.py", "timeresp_test.py", "trdata_test.py")

#: the tests of QUICK_FILES the default suite runs on the reference engine (node-id
#: prefixes; the others run on the compiled engine): python-control's checks of a
#: response's conventions (squeeze and shapes, aliases, pandas, labels) on random linear
#: systems of many sizes.  The drop-in wraps either engine's run in the same code
#: (ivdrem.pycontrol.input_output_response), and on the compiled engine each new size is a
#: new compile: from an empty compile cache the harness compiled 53 kernels of blocks it
#: did not write with every test on the compiled engine, 17 with these on the reference one
#: (186 s → 110 s at load 5; docs/performance.md, "The test suite").  The compiled engine
#: keeps the nonlinear, interconnected, flat and gain-scheduled systems, the LTI systems of
#: nlsys_test and trdata's params; IVDREM_PYCONTROL_FULL=1 runs every test on each engine.
ON_REFERENCE = ("timeresp_test.py", "trdata_test.py::test_trdata_labels")

#: tests that fail with ivdrem on purpose: ivdrem is stricter (docs/simulation.md,
#: "Where the drop-in differs"); node id -> the difference
_PARAMS = ("a params name no block declares is refused (python-control passes it on to "
           "functions that read it)")
_X0 = "an initial state of the wrong size is refused (python-control pads it with zeros)"
DELIBERATE = {
    "iosys_test.py::TestIOSys::test_params": _PARAMS,
    "iosys_test.py::TestIOSys::test_discrete_iosys": _PARAMS,
    "phaseplot_test.py::test_basic_phase_plots": _PARAMS,
    "phaseplot_test.py::test_system_types": _PARAMS,
    **{f"stochsys_test.py::test_indices[{k}]": _PARAMS for k in (
        "3-None", "None-2", "ctrl_indices0-None", "ctrl_indices3-None",
        "ctrl_indices4-None", "ctrl_indices5-dist_indices5", "ctrl_indices6-dist_indices6")},
    "iosys_test.py::test_find_size": _X0 + "; the message is ivdrem's",
    "iosys_test.py::test_input_output_broadcasting": _X0,
    "iosys_test.py::TestIOSys::test_algebraic_loop":
        "an algebraic loop is refused before the run (AlgebraicLoopError, a ValueError; "
        "python-control raises RuntimeError while simulating)",
    "iosys_test.py::TestIOSys::test_discrete":
        "a state beyond 1e10 stops the run (an unstable discrete system grows to 1e30 "
        "in python-control's run)",
}

#: per file: (reach the simulator and pass on python-control, pass on ivdrem, deliberate
#: differences, other failures), measured on both engines (docs/simulation.md)
EXPECTED_TABLE = {
    "ctrlplot_test.py": (11, 11, 0, 0), "flatsys_test.py": (5, 5, 0, 0),
    "interconnect_test.py": (1, 1, 0, 0), "iosys_test.py": (36, 30, 6, 0),
    "kwargs_test.py": (4, 4, 0, 0), "nlsys_test.py": (6, 6, 0, 0),
    "optimal_test.py": (26, 26, 0, 0), "phaseplot_test.py": (13, 11, 2, 0),
    "statefbk_test.py": (7, 7, 0, 0), "stochsys_test.py": (14, 7, 7, 0),
    "timeplot_test.py": (33, 33, 0, 0), "timeresp_test.py": (14, 14, 0, 0),
    "trdata_test.py": (9, 9, 0, 0)}

#: the agreement bound, in units of atol + rtol |y| (see the module docstring)
AGREEMENT = 100.0


def _run(engine, targets, tmp_path, name, on_reference=()):
    """Run python-control's tests `targets` with the plugin on `engine` ("none":
    python-control's simulator), those whose node ids start with one of `on_reference` on
    the reference engine; returns {node id: record}."""
    report = tmp_path / f"{name}.json"
    ini = tmp_path / "pytest.ini"
    ini.write_text("[pytest]\n")      # not ivdrem's pyproject.toml (its pythonpath)
    env = dict(os.environ, IVDREM_PYCONTROL_ENGINE=engine,
               IVDREM_PYCONTROL_REPORT=str(report), MPLBACKEND="Agg",
               IVDREM_PYCONTROL_AGREEMENT=str(AGREEMENT),
               IVDREM_PYCONTROL_ON_REFERENCE=json.dumps(list(on_reference)),
               PYTHONPATH=os.pathsep.join([str(HERE.parent), str(HERE)]))
    cmd = [sys.executable, "-m", "pytest", "-c", str(ini), "-p", "pycontrol_plugin",
           "-p", "no:cacheprovider", "-q", "--rootdir", str(CT_TESTS), "-W",
           "ignore::DeprecationWarning", *targets]
    proc = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=1800)
    if not report.exists():
        raise AssertionError(f"the harness did not run:\n{proc.stdout[-3000:]}\n"
                             f"{proc.stderr[-3000:]}")
    return json.loads(report.read_text())


def _reaching():
    return [line.strip() for line in REACHING.read_text().splitlines()
            if line.strip() and not line.startswith("#")]


def _targets(ids):
    return [str(CT_TESTS / i.split("::", 1)[0]) + "::" + i.split("::", 1)[1] for i in ids]


def _file(node):
    return node.split("::", 1)[0]


def _count_table(ids, passed):
    """{file: (listed, passed, deliberate differences, other failures)} of the tests `ids`."""
    rows = {}
    for i in ids:
        row = rows.setdefault(_file(i), [0, 0, 0, 0])
        row[0] += 1
        row[1 if i in passed else 2 if i in DELIBERATE else 3] += 1
    return {f: tuple(rows[f]) for f in sorted(rows)}


def _passed_and_reached(records):
    return {k for k, r in records.items() if r.get("outcome") == "passed" and r["calls"]}


def test_release_is_the_supported_one():
    # the drop-in reads python-control's private argument helpers, and the harness's list
    # is that release's: another release needs both checked again
    assert ct.__version__ == pc.SUPPORTED_RELEASE


_FULL_ONLY = pytest.mark.skipif(not FULL, reason="every file on both engines: "
                                "IVDREM_PYCONTROL_FULL=1")


@pytest.mark.parametrize("engine", [
    pytest.param("quick", marks=pytest.mark.skipif(FULL, reason="the full run instead")),
    pytest.param("compiled", marks=_FULL_ONLY), pytest.param("reference", marks=_FULL_ONLY)])
def test_python_control_tests_pass_on_ivdrem(engine, tmp_path):
    # the whole list takes about 8 minutes on one engine (python-control's optimal tests
    # alone are minutes): the default suite runs the files of QUICK_FILES, once
    ids = [i for i in _reaching() if FULL or _file(i) in QUICK_FILES]
    # the list is python-control's own passing tests that reach the simulator
    # (test_reaching_list_is_current)
    base = set(ids)
    default, on_reference = ("compiled", ON_REFERENCE) if engine == "quick" else (engine, ())
    mine = _run(default, _targets(ids), tmp_path, engine, on_reference)
    ok = {k for k, r in mine.items() if r.get("outcome") == "passed"}
    ran = {i: mine[i].get("engine") for i in ok}
    table = _count_table(ids, ok)
    print(f"\npython-control's tests on ivdrem ({engine}): per file, the tests that reach "
          "the simulator and pass on python-control, those passing here, the deliberate "
          "differences, other failures, the engine")
    for f, row in table.items():
        on = "/".join(sorted({ran[i] for i in ok if _file(i) == f}))
        print(f"  {f:24s} {row[0]:4d} {row[1]:4d} {row[2]:4d} {row[3]:4d}  {on}")
    print(f"  {'total':24s} " + " ".join(f"{sum(r[k] for r in table.values()):4d}"
                                          for k in range(4)))
    failed = {i: mine.get(i, {}).get("error", "not run") for i in ids if i not in ok}
    unexpected = {i: e for i, e in failed.items() if i not in DELIBERATE}
    assert not unexpected, "\n\n".join(f"{i}:\n{e}" for i, e in unexpected.items())
    # every test's calls ran on its engine, and the quick run has both
    expected = {i: plugin.engine_of(i, default, on_reference) for i in ok}
    assert ran == expected, {i: (ran[i], e) for i, e in expected.items() if ran[i] != e}
    if engine == "quick":
        assert set(ran.values()) == {"compiled", "reference"}, set(ran.values())
    # the table of docs/simulation.md is this run's (the same on both engines)
    assert table == {f: row for f, row in EXPECTED_TABLE.items()
                     if FULL or f in QUICK_FILES}, table
    if FULL:
        assert len(ok & base) >= 150
    # numerical agreement with python-control, call by call
    diffs = [(d, i) for i in ok for d in mine[i]["diff"]]
    assert diffs, "no call was compared"
    worst = max(diffs)
    print(f"  {len(diffs)} calls compared; largest difference {worst[0]:.3g} "
          f"(atol + rtol |y|) in {worst[1]}")
    assert worst[0] <= AGREEMENT, worst
    # the calls set apart as ill-conditioned: only the kind documented
    apart = [(c["diff"], c["self"], i) for i in ok for c in mine[i]["ill_conditioned"]]
    print(f"  {len(apart)} ill-conditioned calls set apart"
          + (f" (largest difference {max(apart)[0]:.3g}, python-control against itself "
             f"{max(a[1] for a in apart):.3g})" if apart else ""))
    assert all("separatrices" in c["callers"] for i in ok
               for c in mine[i]["ill_conditioned"]), apart


@pytest.mark.skipif(not FULL, reason="the whole test files: IVDREM_PYCONTROL_FULL=1")
def test_reaching_list_is_current(tmp_path):
    """The listed tests are exactly those of FILES that reach the simulator and pass on
    python-control."""
    records = _run("none", [str(CT_TESTS / f) for f in FILES], tmp_path, "plain-all")
    found = _passed_and_reached(records)
    assert found == set(_reaching()), sorted(found ^ set(_reaching()))


# --------------------------------------------------------------------------- the drop-in
def _lin(name, a=-1.0):
    return ct.ss([[a, 1.0], [0.0, -2.0]], [[0.0], [1.0]], [[1.0, 0.0]], [[0.3]], name=name)


def test_flatten_evaluates_as_python_control_does():
    # a nested interconnection: the inner one's output reads its subsystem's input (a
    # pass-through), the outer one's output reads a subsystem input and a nested output;
    # the one-level diagram must give python-control's own right-hand side and outputs
    sq = ct.nlsys(None, lambda t, x, u, p: u * u, inputs=1, outputs=1, name="sq")
    inner = ct.interconnect([_lin("p1"), sq], connections=[["sq.u[0]", "p1.y[0]"]],
                            inplist=["p1.u[0]"], outlist=["sq.y[0]", "p1.u[0]"],
                            outputs=["ysq", "upass"], name="inner")
    outer = ct.interconnect([inner, _lin("p2", -3.0)],
                            connections=[["p2.u[0]", "inner.upass"]],
                            inplist=["inner.u[0]"], outlist=["p2.y[0]", "inner.ysq",
                                                             "p2.u[0]"], name="outer")
    flat = pc.flatten(outer)
    assert [s.name for s in flat.syslist] == ["p1", "sq", "p2"]
    assert flat.nstates == outer.nstates == 4
    rng = np.random.default_rng(1)
    for _ in range(5):
        t, x, u = rng.random(), rng.normal(size=4), rng.normal(size=1)
        np.testing.assert_allclose(flat._rhs(t, x, u), outer._rhs(t, x, u), atol=1e-12)
        np.testing.assert_allclose(flat._out(t, x, u), outer._out(t, x, u), atol=1e-12)


def test_solve_ivp_settings_are_mapped_or_refused():
    sys = _lin("p")
    T = np.linspace(0, 1, 11)
    r = pc.input_output_response(sys, T, 1.0)
    assert (r.stats["method"], r.stats["rtol"], r.stats["atol"]) == ("dp45", 1e-3, 1e-6)
    r = pc.input_output_response(sys, T, 1.0, solve_ivp_method="Radau",
                                 solve_ivp_kwargs={"rtol": 1e-8, "atol": 1e-10})
    assert (r.stats["method"], r.stats["rtol"], r.stats["atol"]) == ("rodas5p", 1e-8, 1e-10)
    with pytest.raises(ValueError, match=r"solve_ivp_kwargs\['dense_output'\].*PYTHON_CON"):
        pc.input_output_response(sys, T, solve_ivp_kwargs={"dense_output": True})
    with pytest.raises(ValueError, match="atol'] must be a number"):
        pc.input_output_response(sys, T, solve_ivp_kwargs={"atol": [1e-6, 1e-6]})
    with pytest.raises(ValueError, match="solve_ivp_method 'Euler'"):
        pc.input_output_response(sys, T, method="Euler")
    with pytest.raises(TypeError, match="unrecognized keyword"):
        pc.input_output_response(sys, T, rtol=1e-3)


def test_linear_response_is_exact_to_the_tolerance():
    # forced_response discretizes a linear system exactly (matrix exponential, inputs
    # linear between the timepts): an independent solution
    sys = _lin("p")
    T = np.linspace(0, 5, 101)
    U = np.sin(2 * T)
    exact = ct.forced_response(sys, T, U, [1.0, -1.0])
    for engine in ("compiled", "reference"):
        r = pc.input_output_response(sys, T, U, [1.0, -1.0], engine=engine,
                                     solve_ivp_kwargs={"rtol": 1e-9, "atol": 1e-12})
        assert np.max(np.abs(r.outputs - exact.outputs)) < 1e-8
    # a transfer function runs as its state-space form
    tf = ct.tf([2.0], [1.0, 3.0, 2.0])
    r = pc.input_output_response(tf, T, U, solve_ivp_kwargs={"rtol": 1e-9, "atol": 1e-12})
    assert np.max(np.abs(r.outputs - ct.forced_response(tf, T, U).outputs)) < 1e-8


def test_conventions_of_the_response():
    sys = _lin("p")
    T = np.linspace(0, 1, 11)
    t, y = pc.input_output_response(sys, T, 1.0)
    t, y, x = pc.input_output_response(sys, T=T, U=1.0, X0=0, return_x=True)
    assert x.shape == (2, 11) and y.shape == (11,)
    r = pc.input_output_response(sys, T, 1.0, squeeze=False, transpose=True)
    assert r.outputs.shape == (11, 1)
    both = pc.input_output_response([sys, _lin("q", -2.0)], T, 1.0)
    assert isinstance(both, ct.TimeResponseList) and len(both) == 2
    # a system without states: its outputs, -u^2 here
    st = -ct.nlsys(None, lambda t, x, u, p: u * u, inputs=1, outputs=1, name="st")
    r = pc.input_output_response(st, T, np.sin(T))
    np.testing.assert_allclose(r.outputs, -np.sin(T) ** 2, atol=1e-15)
    # a discrete-time system: python-control's recursion, exactly
    d = ct.ss([[0.9, 0.1], [0.0, 0.8]], [[0.0], [1.0]], [[1.0, 0.0]], [[0.5]], dt=0.1)
    Td = np.arange(0, 2.0001, 0.1)
    x, ys = np.array([1.0, 0.0]), []
    for tk in Td:
        ys.append((d.C @ x + d.D[:, 0] * np.sin(tk))[0])
        x = d.A @ x + d.B[:, 0] * np.sin(tk)
    r = pc.input_output_response(d, Td, np.sin(Td), [1.0, 0.0])
    np.testing.assert_allclose(r.outputs, ys, atol=1e-12)
    with pytest.raises(ValueError, match="equal to sampling time"):
        pc.input_output_response(d, np.linspace(0, 1, 21), 0.0)


def test_ignore_errors_returns_the_samples_before_the_stop():
    blow = ct.nlsys(lambda t, x, u, p: x * x, None, states=1, inputs=0, outputs=1,
                    name="blow")             # x(t) = 1 / (1 - t): no solution past t = 1
    T = np.linspace(0, 2, 21)
    r = pc.input_output_response(blow, T, 0, 1.0, ignore_errors=True)
    assert not r.success and r.message.startswith("solve_ivp failed")
    assert 0.5 < r.time[-1] < 1.0 and r.states.shape == (1, r.time.size)
    np.testing.assert_allclose(r.states[0], 1 / (1 - r.time), rtol=1e-2)
    with pytest.raises(RuntimeError):
        pc.input_output_response(blow, T, 0, 1.0)


def test_installed_replaces_every_binding_and_restores_them():
    import control.timeresp  # noqa: F401
    nlsys_module = sys.modules["control.nlsys"]
    plant = ct.nlsys(lambda t, x, u, p: -x + u, None, states=1, inputs=1, outputs=1,
                     name="plant")
    T = np.linspace(0, 1, 11)
    with pc.installed(engine="reference") as fn:
        assert ct.input_output_response is fn and nlsys_module.input_output_response is fn
        # forced_response on a nonlinear system goes through it
        r = ct.forced_response(plant, T, 1.0)
        assert r.stats["engine"] == "reference"
    assert ct.input_output_response is pc.PYTHON_CONTROL_SIMULATOR
    assert nlsys_module.input_output_response is pc.PYTHON_CONTROL_SIMULATOR
    assert not hasattr(ct.forced_response(plant, T, 1.0), "stats")


def test_ill_conditioned_separatrix_is_set_apart(monkeypatch):
    # a stable node with eigenvalues -0.65 and -10 (eigenvectors not along the axes, so
    # rounding puts some fast mode in the initial state): the separatrix along the slow
    # direction is flown backwards for log(2 / 0.1) / 0.65 = 4.6 s, where the fast mode
    # grows by exp(46); along the fast direction for 0.3 s, well-conditioned
    V = np.array([[1.0, 1.0], [0.3, 1.0]])
    node = ct.ss(V @ np.diag([-0.65, -10.0]) @ np.linalg.inv(V), [[0.0], [1.0]],
                 [[1.0, 0.0]], [[0.0]], name="node")
    monkeypatch.setattr(plugin, "AGREEMENT", AGREEMENT)
    monkeypatch.setattr(plugin, "_records", {})
    monkeypatch.setitem(plugin._current, "id", "node")
    wrapped = plugin._counted(pc.drop_in(engine="reference"), pc.PYTHON_CONTROL_SIMULATOR)
    import matplotlib
    matplotlib.use("Agg")
    with pc.replaced(wrapped):
        ct.phaseplot.separatrices(node, [-1, 1, -1, 1], suppress_warnings=True)
    rec = plugin._records["node"]
    assert rec["calls"] == 4
    apart = rec["ill_conditioned"]
    # the two slow-direction calls: far apart, and python-control far from itself
    assert len(apart) == 2 and len(rec["diff"]) == 2
    assert all(c["diff"] > AGREEMENT and c["self"] > 1e6 for c in apart), apart
    assert all(c["callers"][:2] == ["_create_trajectory", "separatrices"] for c in apart)
    assert max(rec["diff"]) < 1.0
    # a well-conditioned call moves by about the perturbation
    T = np.linspace(0, 1, 21)
    theirs = pc.PYTHON_CONTROL_SIMULATOR(node, T, 0.0, [0.5, -0.2])
    moved = plugin._self_difference(pc.PYTHON_CONTROL_SIMULATOR, (node, T, 0.0, [0.5, -0.2]),
                                    {}, theirs, 1e-3, 1e-6)
    assert plugin.PERTURBATION / 10 < moved < plugin.PERTURBATION * 10
