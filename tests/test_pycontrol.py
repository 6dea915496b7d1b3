"""python-control's own tests, run with ivdrem's simulator in place of
``ct.input_output_response`` (ivdrem.pycontrol; docs/simulation.md, "A drop-in for
python-control").

The test files ship with python-control (``control/tests``).  They run in a subprocess with
tests/pycontrol_plugin.py, once on python-control's own simulator and once on ivdrem's, and
the tests are compared one by one.  ``tests/data/pycontrol_reaching.txt`` lists the tests
that reach the simulator and pass on python-control; the default suite runs those (on
python-control and on the compiled engine); ``IVDREM_PYCONTROL_FULL=1`` also runs the
reference engine and checks the list against the whole files.

Numerical agreement: every call of a test is also run on python-control, and the outputs
and states must agree within a multiple of the tolerances the call asked for (both
solvers' global errors are of that order; a wrong formula would be far outside).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import control as ct

from ivdrem import pycontrol as pc

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

#: tests that fail with ivdrem on purpose: ivdrem is stricter (docs/simulation.md,
#: "Where the drop-in differs"); node id -> the difference
DELIBERATE = {}

#: the agreement bound, in units of atol + rtol |y| (see the module docstring)
AGREEMENT = 50.0


def _run(engine, targets, tmp_path, name):
    """Run python-control's tests `targets` with the plugin on `engine` ("none":
    python-control's simulator); returns {node id: record}."""
    report = tmp_path / f"{name}.json"
    ini = tmp_path / "pytest.ini"
    ini.write_text("[pytest]\n")      # not ivdrem's pyproject.toml (its pythonpath)
    env = dict(os.environ, IVDREM_PYCONTROL_ENGINE=engine,
               IVDREM_PYCONTROL_REPORT=str(report), MPLBACKEND="Agg",
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


def _passed_and_reached(records):
    return {k for k, r in records.items() if r.get("outcome") == "passed" and r["calls"]}


def test_release_is_the_supported_one():
    # the drop-in reads python-control's private argument helpers, and the harness's list
    # is that release's: another release needs both checked again
    assert ct.__version__ == pc.SUPPORTED_RELEASE


@pytest.mark.parametrize("engine", [
    "compiled",
    pytest.param("reference", marks=pytest.mark.skipif(
        not FULL, reason="both engines: IVDREM_PYCONTROL_FULL=1"))])
def test_python_control_tests_pass_on_ivdrem(engine, tmp_path):
    ids = _reaching()
    # the list is python-control's own passing tests that reach the simulator
    # (test_reaching_list_is_current)
    base = set(ids)
    mine = _run(engine, _targets(ids), tmp_path, engine)
    ok = _passed_and_reached(mine)
    table = Counter(), Counter()
    for i in ids:
        table[0][_file(i)] += 1
        table[1][_file(i)] += i in ok
    print(f"\npython-control's tests on ivdrem ({engine}): passed / reached and passed "
          "on python-control")
    for f in sorted(table[0]):
        print(f"  {f}: {table[1][f]} / {table[0][f]}")
    print(f"  total: {len(ok & base)} / {len(base)}")
    failed = {i: mine.get(i, {}).get("error", "not run") for i in ids if i not in ok}
    unexpected = {i: e for i, e in failed.items() if i not in DELIBERATE}
    assert not unexpected, "\n\n".join(f"{i}:\n{e}" for i, e in unexpected.items())
    assert len(ok & base) >= 150
    # numerical agreement with python-control, call by call
    diffs = [(d, i) for i in ok for d in mine[i]["diff"]]
    assert diffs, "no call was compared"
    worst = max(diffs)
    print(f"  {len(diffs)} calls compared; largest difference {worst[0]:.3g} "
          f"(atol + rtol |y|) in {worst[1]}")
    assert worst[0] <= AGREEMENT, worst


@pytest.mark.skipif(not FULL, reason="the whole test files: IVDREM_PYCONTROL_FULL=1")
def test_reaching_list_is_current(tmp_path):
    """The listed tests are exactly those of FILES that reach the simulator and pass on
    python-control."""
    records = _run("none", [str(CT_TESTS / f) for f in FILES], tmp_path, "plain-all")
    found = _passed_and_reached(records)
    assert found == set(_reaching()), sorted(found ^ set(_reaching()))
