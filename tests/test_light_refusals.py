"""A command refuses bad input before it imports python-control, SciPy or Matplotlib.

Those imports cost 2-3 s of CPU (``python -X importtime -m ivdrem paper``); the argument
parsing and the checks of files, output locations and option values need none of them
(ivdrem.cli imports them with :func:`ivdrem.cli.import_library` once the checks passed).
Each refusal runs in a child process under ``-X importtime``, whose report names every
module the process imported: the refusal's message and exit status must be the ones the
command always gave, and none of the heavy packages may be in that report.
"""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

#: the packages a refusal must not import (top-level names in -X importtime's report)
HEAVY = ("control", "scipy", "matplotlib", "sympy", "dask", "numba")


def _imported(stderr: str) -> set[str]:
    """The modules -X importtime reports as imported (its last column)."""
    return {line.rsplit("|", 1)[-1].strip() for line in stderr.splitlines()
            if line.startswith("import time:")}


def _refuse(tmp_path, *argv):
    p = subprocess.run([sys.executable, "-X", "importtime", "-m", "ivdrem", *argv],
                       capture_output=True, text=True, cwd=tmp_path, timeout=600,
                       stdin=subprocess.DEVNULL)
    lines = [ln for ln in p.stderr.splitlines() if not ln.startswith("import time:")]
    return p.returncode, "\n".join(lines), _imported(p.stderr)


@pytest.fixture
def places(tmp_path):
    """A FIFO, a regular file (a path under it cannot be a directory), a missing file."""
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    plain = tmp_path / "plain.toml"
    plain.write_text("[experiment]\nt_end = 1.0\n")
    return {"fifo": str(fifo), "under_file": str(plain / "x"), "missing": str(tmp_path / "no.toml")}


CASES = {   # name: (argv with {placeholders}, what the one line says)
    "paper, missing --config": (["paper", "--config", "{missing}"], "config file '{missing}' not found"),
    "paper, FIFO as --config": (["paper", "--config", "{fifo}"], "is a FIFO (named pipe), not a regular file"),
    "paper, device as --config": (["paper", "--config", "/dev/zero"], "is a character device, not a regular file"),
    "paper, FIFO as --json": (["paper", "--json", "{fifo}"], "JSON file {fifo} is a FIFO"),
    "paper, --json under a file": (["paper", "--json", "{under_file}.json"], "cannot be written"),
    "paper, bad --t-end": (["paper", "--t-end", "-1"], "--t-end must be a finite number of seconds > 0"),
    "paper, unknown --method": (["paper", "--method", "bogus"], "--method 'bogus' is not a method of the simulator"),
    "paper, unknown --engine": (["paper", "--engine", "bogus"], "argument --engine: invalid choice: 'bogus'"),
    "report, missing --config": (["report", "--config", "{missing}"], "config file '{missing}' not found"),
    "report, --out under a file": (["report", "--out", "{under_file}"], "report directory {under_file} cannot be written"),
    "report, unknown --method": (["report", "--method", "bogus"], "--method 'bogus' is not a method"),
    "study, missing file": (["study", "{missing}"], "study file '{missing}' not found"),
    "study, FIFO": (["study", "{fifo}"], "is a FIFO (named pipe)"),
    "cosim, bad --t-end": (["cosim", "--t-end", "-1"], "--t-end must be a finite number > 0"),
    "cosim, bad --comm-step": (["cosim", "--comm-step", "0"], "--comm-step must be in (0, t_end]"),
    "cosim, unknown --engine": (["cosim", "--engine", "bogus"], "argument --engine: invalid choice: 'bogus'"),
}


@pytest.mark.parametrize("name", list(CASES))
def test_a_refusal_imports_none_of_the_heavy_packages(tmp_path, places, name):
    argv, said = CASES[name]
    code, err, imported = _refuse(tmp_path, *(a.format(**places) for a in argv))
    assert code == 2, err
    assert "Traceback" not in err, err
    assert said.format(**places) in err.splitlines()[-1], err      # the error's own line, last
    assert "ivdrem" in imported, "the child's -X importtime report was not read"
    heavy = sorted(m for m in imported if m.split(".")[0] in HEAVY and "." not in m)
    assert heavy == [], f"{name}: imported {heavy} before refusing"


def test_fmu_export_refuses_a_missing_config_before_python_control(tmp_path, places):
    """ivdrem fmu export parses with the FMU exporter's default sub-step (a module of its own:
    SymPy, the exporter's, was imported for it) and refuses a missing --config before any
    heavy import."""
    code, err, imported = _refuse(tmp_path, "fmu", "export", "--config", places["missing"],
                                  "-o", str(tmp_path / "x.fmu"))
    assert code == 2 and f"config file '{places['missing']}' not found" in err, err
    heavy = sorted(m for m in imported if m.split(".")[0] in HEAVY and "." not in m)
    assert heavy == [], f"imported {heavy} before refusing"


@pytest.mark.parametrize("option, value, said", [
    ("--model", "{missing}.urdf", "URDF file '{missing}.urdf' not found"),
    ("--model", "{fifo}.urdf", "URDF file '{fifo}.urdf' is a FIFO (named pipe), not a regular file"),
    ("--config", "{missing}", "config file '{missing}' not found"),
])
def test_controller_export_refuses_its_input_files_before_python_control(tmp_path, places,
                                                                         option, value, said):
    """`fmu export --controller`: a missing or FIFO URDF file given as --model (a FIFO was
    "not found" before, after the library's import) and a missing --config are refused
    before any heavy import (SymPy included); no FMU is written."""
    os.mkfifo(places["fifo"] + ".urdf")
    out = tmp_path / "x.fmu"
    code, err, imported = _refuse(tmp_path, "fmu", "export", "--controller", option,
                                  value.format(**places), "-o", str(out))
    assert code == 2 and err.splitlines()[-1] == f"ivdrem fmu export: error: {said.format(**places)}", err
    heavy = sorted(m for m in imported if m.split(".")[0] in HEAVY and "." not in m)
    assert heavy == [], f"imported {heavy} before refusing"
    assert not out.exists()


def test_the_help_still_lists_the_registered_laws(tmp_path):
    """The --laws help names the laws of the registry, read only when the help is printed."""
    from ivdrem.laws import law_names
    for command in ("paper", "report"):
        p = subprocess.run([sys.executable, "-m", "ivdrem", command, "--help"],
                           capture_output=True, text=True, cwd=tmp_path, timeout=600)
        assert p.returncode == 0, p.stderr
        text = "".join(p.stdout.split())            # argparse wraps the lines (at hyphens too)
        assert "anyof:" + ",".join(law_names()) in text, p.stdout


def test_a_refusal_through_main_leaves_python_control_unimported():
    """The same in a fresh interpreter calling ivdrem.cli.main (a caller in Python)."""
    code = ("import sys; from ivdrem.cli import main; "
            "rc = main(['paper', '--t-end', '-1']); "
            "assert rc == 2, rc; "
            "bad = [m for m in ('control', 'scipy', 'matplotlib') if m in sys.modules]; "
            "assert not bad, bad")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr
    assert "--t-end must be a finite number of seconds > 0" in p.stderr


def test_the_sim_package_loads_its_names_when_used():
    """ivdrem.sim imports a submodule when one of its names is first read (the method
    table alone stays light); every name of its __all__ is the submodule's own object."""
    code = ("import sys, importlib; import ivdrem.sim.methods as m; import ivdrem.sim as s; "
            "assert 'control' not in sys.modules and 'ivdrem.sim.simulator' not in sys.modules; "
            "assert s.METHODS is m.METHODS; "
            "homes = dict(s._HOME); "
            "assert sorted(s.__all__) == sorted(homes); "
            "bad = [n for n in s.__all__ if getattr(s, n) is not "
            "getattr(importlib.import_module('ivdrem.sim.' + homes[n]), n)]; "
            "assert not bad, bad; "
            "assert s.guards is importlib.import_module('ivdrem.sim.guards'); "
            "ok = False\n"
            "try:\n    s.no_such_name\nexcept AttributeError:\n    ok = True\n"
            "assert ok")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr


def test_the_console_script_freezes_what_the_library_import_allocated():
    """In the console script, import_library pauses the garbage collector during the heavy
    imports, then freezes what they allocated and turns it back on; from a caller of main
    it leaves the collector alone."""
    code = ("import gc, sys, ivdrem.cli as c\n"
            "c.import_library()\n"
            "assert 'control' in sys.modules and gc.get_freeze_count() == 0\n"
            "c._freeze_imports = True\n"        # as run() sets it
            "c.import_library()\n"
            "assert gc.isenabled() and gc.get_freeze_count() > 1000, gc.get_freeze_count()\n")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr


def test_cosim_checks_a_law_name_against_the_registry(tmp_path):
    """cosim's --law is checked against the registered laws, read only then (the registry
    imports python-control): an unknown name is refused listing every law."""
    from ivdrem.laws import law_names
    code, err, _ = _refuse(tmp_path, "cosim", "--law", "bogus")
    assert code == 2 and "argument --law: invalid choice: 'bogus'" in err, err
    assert all(repr(name) in err for name in law_names()), err
