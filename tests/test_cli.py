"""Command line: ivdrem paper / report / fmu routing, errors before simulation."""
import json
import math
import subprocess
import sys

import pytest

from ivdrem.cli import main


def test_paper_json_short(tmp_path, capsys):
    out = tmp_path / "out.json"
    assert main(["paper", "--t-end", "2", "--json", str(out), "--quiet"]) == 0
    data = json.loads(out.read_text())
    assert set(data) == {"iv-drem", "composite-learning"}
    for law, s in data.items():
        assert s["t_end"] == pytest.approx(2.0)
        assert len(s["theta_hat"]) == 5
        assert s["theta_err_norm"] > 0
        assert s["wall_s"] > 0
    assert "iv-drem" in capsys.readouterr().out


def test_paper_single_law(tmp_path):
    out = tmp_path / "o.json"
    assert main(["paper", "--t-end", "1", "--law", "iv-drem", "--json", str(out), "--quiet"]) == 0
    assert set(json.loads(out.read_text())) == {"iv-drem"}


def test_bad_config_key_is_rejected_before_simulation(tmp_path, capsys):
    cfg = tmp_path / "bad.toml"
    cfg.write_text("[controller]\nKp = [1.0, 1.0]\n")
    assert main(["paper", "--config", str(cfg), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "controller.Kp" in err and "controller.K" in err


def test_unknown_law_rejected(capsys):
    assert main(["paper", "--law", "iv-dream", "--t-end", "1", "--quiet"]) == 2
    assert "iv-dream" in capsys.readouterr().err


def test_fmu_subcommand_is_routed(tmp_path):
    fmu = tmp_path / "Arm.fmu"
    assert main(["fmu", "export", "-o", str(fmu)]) == 0
    assert fmu.exists() and fmu.stat().st_size > 1000


def test_progress_is_silent_when_not_a_terminal(tmp_path):
    """stderr is a pipe here: no progress bar characters may appear."""
    out = tmp_path / "o.json"
    p = subprocess.run([sys.executable, "-m", "ivdrem", "paper", "--t-end", "1",
                        "--law", "iv-drem", "--json", str(out)],
                       capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr
    assert "%|" not in p.stderr and "it/s" not in p.stderr


def test_method_option_brings_its_tolerances(tmp_path):
    """--method dp45 runs DP45 at its own default tolerances, unless the file sets them."""
    from ivdrem.cli.preflight import method_overrides
    from ivdrem.sim.simulator import DEFAULT_TOLERANCES
    assert method_overrides(None) == {}
    o = method_overrides("dp45")
    assert (o["solver.rtol"], o["solver.atol"]) == DEFAULT_TOLERANCES["dp45"]
    f = tmp_path / "c.toml"
    f.write_text("[solver]\nrtol = 3e-7\n")
    o = method_overrides("dp45", f)
    assert "solver.rtol" not in o and o["solver.atol"] == DEFAULT_TOLERANCES["dp45"][1]


def test_version_and_consistent_law_option(capsys):
    import ivdrem
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0 and capsys.readouterr().out.strip() == f"ivdrem {ivdrem.__version__}"
    # paper takes --laws as report does (--law stays as an alias)
    from ivdrem.cli import build_parser
    p = build_parser()
    assert p.parse_args(["paper", "--laws", "drem", "none"]).law == ["drem", "none"]
    assert p.parse_args(["paper", "--law", "drem"]).law == ["drem"]
    assert p.parse_args(["report", "--laws", "drem"]).laws == ["drem"]


def test_method_help_names_the_real_default(capsys):
    from ivdrem.experiments.config import read_config
    default = read_config()["solver"]["method"]
    for cmd in ("paper", "report"):
        with pytest.raises(SystemExit):
            main([cmd, "--help"])
        text = " ".join(capsys.readouterr().out.split())
        assert f"(default from the config: {default})" in text, text


def test_paper_prints_the_conclusions_its_laws_allow(tmp_path, monkeypatch, capsys):
    """examples/instrument.toml runs iv-drem and drem: its own command prints C4, the
    conclusion it is about, and C2 (iv-drem alone), not C1 and C3 (composite learning is
    not run)."""
    import ivdrem.experiments.paper as paper
    from ivdrem.reports.synthetic import synthetic_paper_run
    monkeypatch.setattr(paper, "run_paper",
                        lambda config, **kw: synthetic_paper_run(config, dt=0.05,
                                                                 laws=["iv-drem", "drem"]))
    assert main(["paper", "--laws", "iv-drem", "drem", "--t-end", "30", "--quiet"]) == 0
    out = capsys.readouterr().out
    lines = [ln.split()[0] for ln in out.splitlines() if ln[:2] in ("C1", "C2", "C3", "C4")]
    assert lines == ["C2", "C4"], out


def test_a_missing_optional_extra_is_one_line_not_a_traceback(tmp_path, monkeypatch, capsys):
    """An arm whose URDF package is not installed: the commands print the model layer's
    message (which names the pip extra) and exit 2."""
    import ivdrem.models as models
    msg = "arm 'panda' needs the URDF files of the package 'example-robot-data' (simulated)"

    def missing(name, *a, **k):
        raise ImportError(msg)
    monkeypatch.setattr(models, "get_model", missing)
    assert main(["fmu", "export", "--model", "panda", "-o", str(tmp_path / "p.fmu")]) == 2
    err = capsys.readouterr().err
    assert msg in err and "Traceback" not in err
    assert not (tmp_path / "p.fmu").exists()


def _fresh_calibrations(monkeypatch, where):
    """Calibrations kept in `where` (empty) instead of the shared cache: one made by an
    earlier test run would otherwise be read instead of simulated."""
    import ivdrem.diagrams.gamma_auto as gamma_auto
    real = gamma_auto._calibration_path

    def path(diagram, settings):
        p = real(diagram, settings)
        return None if p is None else where / p.name
    monkeypatch.setattr(gamma_auto, "_calibration_path", path)


def _record_simulations(monkeypatch):
    """Every simulation as (kind, law): "calibration" (a run of the loop with its γ
    overridden, ivdrem.diagrams.gamma_auto) or "run" (a law's run, an Experiment's)."""
    import ivdrem.experiments.experiment as experiment
    import ivdrem.sim as sim
    events = []

    def wrap(real, kind):
        def simulate(diagram, *a, **k):
            events.append((kind, diagram.name.split("[")[1].rstrip("]")))
            return real(diagram, *a, **k)
        return simulate
    monkeypatch.setattr(sim, "simulate", wrap(sim.simulate, "calibration"))
    monkeypatch.setattr(experiment, "simulate", wrap(experiment.simulate, "run"))
    return events


def test_gamma_auto_is_calibrated_once_per_law_before_any_run(tmp_path, monkeypatch):
    """planar-3 (γ "auto" for iv-drem and drem, a number for composite learning): the
    preflight only prices and calibrates nothing; each law with γ "auto" is calibrated
    once, with the run's method, and the laws after the first before any run starts."""
    import ivdrem.diagrams.gamma_auto as gamma_auto
    import ivdrem.experiments.paper as paper
    real, real_run = gamma_auto.calibrate_gamma, paper.run_paper
    methods, at_run = [], []

    def counting(law, *a, **k):
        methods.append(k.get("method"))
        return real(law, *a, **k)

    def run_paper(*a, **k):
        at_run.append(list(events))
        return real_run(*a, **k)
    monkeypatch.setattr(gamma_auto, "calibrate_gamma", counting)
    monkeypatch.setattr(paper, "run_paper", run_paper)
    # the calibration run (the paper's mixing's route): planar-3's "eigen" would take the
    # reference estimate, which simulates nothing (tests/test_gamma_reference.py)
    monkeypatch.setattr(gamma_auto, "REFERENCE_MIXINGS", ())
    _fresh_calibrations(monkeypatch, tmp_path)
    events = _record_simulations(monkeypatch)
    out = tmp_path / "o.json"
    from pathlib import Path
    cfg = Path(__file__).resolve().parents[1] / "examples" / "planar3.toml"
    assert main(["paper", "--config", str(cfg), "--t-end", "1", "--laws", "iv-drem",
                 "composite-learning", "drem", "--json", str(out), "--quiet"]) == 0
    assert at_run == [[]]                                # the preflight simulated nothing
    assert events == [("calibration", "drem"), ("calibration", "iv-drem"), ("run", "iv-drem"),
                      ("run", "composite-learning"), ("run", "drem")]
    assert set(methods) == {"rodas5p"}                   # the run's own method
    data = json.loads(out.read_text())
    for law in ("iv-drem", "drem"):
        assert math.isfinite(data[law]["gamma"]) and data[law]["gamma"] != 1e10
    assert data["composite-learning"]["gamma"] == 1.0


def test_a_gain_its_calibration_refuses_stops_the_command_before_any_run(tmp_path, monkeypatch,
                                                                         capsys):
    """A later law's γ "auto" refused by the rule after its calibration run (not by the
    preflight's estimate): exit 2 naming it, and no law has run (nothing computed lost)."""
    import ivdrem.diagrams.gamma_auto as gamma_auto
    real = gamma_auto.gamma_from_delta

    def refuse_drem(t, delta, *a, **k):
        if events and events[-1] == ("calibration", "drem"):
            raise gamma_auto.GainRuleError("gamma = 'auto' refused for the test (drem)")
        return real(t, delta, *a, **k)
    monkeypatch.setattr(gamma_auto, "gamma_from_delta", refuse_drem)
    monkeypatch.setattr(gamma_auto, "REFERENCE_MIXINGS", ())     # the calibration run's route
    events = _record_simulations(monkeypatch)
    from pathlib import Path
    cfg = Path(__file__).resolve().parents[1] / "examples" / "planar3.toml"
    _fresh_calibrations(monkeypatch, tmp_path)
    assert main(["paper", "--config", str(cfg), "--t-end", "1", "--laws", "iv-drem", "drem",
                 "--json", str(tmp_path / "o.json"), "--quiet"]) == 2
    assert "refused for the test (drem)" in capsys.readouterr().err
    assert [e for e in events if e[0] == "run"] == []


def test_the_preflight_prices_and_simulates_nothing(monkeypatch):
    """check_runs of `paper` and `report` (with the FMU check's horizon), every law on
    planar-3: no simulation, no calibration; the reference estimate of Δ is asked once for
    each law with γ "auto"."""
    import ivdrem.diagrams.gamma_auto as gamma_auto
    import ivdrem.sim as sim
    from pathlib import Path
    from ivdrem.cli.preflight import check_runs
    from ivdrem.experiments.config import read_config

    def never(*a, **k):
        raise AssertionError("simulated")
    real, asked = gamma_auto.check_reference_delta, []

    def estimate(law, *a, **k):
        asked.append(law)
        return real(law, *a, **k)
    monkeypatch.setattr(sim, "simulate", never)     # what a calibration would call
    monkeypatch.setattr(gamma_auto, "calibrate_gamma", never)
    monkeypatch.setattr(gamma_auto, "check_reference_delta", estimate)
    cfg = Path(__file__).resolve().parents[1] / "examples" / "planar3.toml"
    config = read_config(cfg, {"experiment.laws": "all"})
    # it returns the estimated wall time of each run it could price ([(law, seconds)])
    for est in (check_runs(config), check_runs(config, fmu_check_t_end=1.0)):
        assert {law for law, _ in est} <= set(config["experiment"]["laws"])
        assert all(s >= 0.0 for _, s in est)
    assert asked == ["iv-drem", "drem"] * 2


def test_the_preflight_does_not_price_an_fmu_check_predicted_to_diverge():
    """The FMU check's reference is priced (and refused when too long) only if the check is
    going to run: with K = 2000 on the 2-link arm its 1 ms coupling is predicted to diverge
    (ivdrem.fmu.cosim.coupling_stability), so a horizon whose reference would be refused
    does not stop the report."""
    from ivdrem.cli.preflight import check_runs, fmu_check_prediction
    from ivdrem.experiments.config import read_config
    from ivdrem.sim.guards import CostLimitError
    config = read_config(None, {"experiment.t_end": 1.0, "experiment.laws": ["iv-drem"]})
    assert not fmu_check_prediction(config, 40000.0).diverges
    with pytest.raises(CostLimitError, match="the FMU check"):
        check_runs(config, fmu_check_t_end=40000.0)
    stiff = read_config(None, {"experiment.t_end": 1.0, "experiment.laws": ["iv-drem"],
                               "controller.K": [2000.0, 2000.0]})
    assert fmu_check_prediction(stiff, 40000.0).diverges
    assert [law for law, _ in check_runs(stiff, fmu_check_t_end=40000.0)] == ["iv-drem"]


def test_a_delta_below_the_doubles_is_refused_by_the_preflight(tmp_path, monkeypatch, capsys):
    """γ "auto" with a mixing whose reference estimate of mean Δ² is far below the doubles:
    `paper` exits 2 naming the mixing before any run, and nothing is calibrated."""
    import ivdrem.diagrams.gamma_auto as gamma_auto
    import ivdrem.experiments.paper as paper

    def never(*a, **k):
        raise AssertionError("simulated")
    monkeypatch.setattr(gamma_auto, "reference_mean_delta2", lambda *a, **k: [-400.0])
    monkeypatch.setattr(gamma_auto, "_estimate_path", lambda *a: None)   # none kept: computed
    monkeypatch.setattr(gamma_auto, "calibrate_gamma", never)
    monkeypatch.setattr(paper, "run_paper", never)
    from pathlib import Path
    cfg = Path(__file__).resolve().parents[1] / "examples" / "planar3.toml"
    assert main(["paper", "--config", str(cfg), "--t-end", "1", "--laws", "iv-drem",
                 "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "mixing 'eigen' on model 'planar-3'" in err and "before its calibration run" in err
    assert "Traceback" not in err


def test_the_command_line_parser_loads_no_report_machinery():
    """Every command builds the parser of every subcommand; the report's modules
    (matplotlib's PDF backend, 0.2 s of start-up) load only when a report is written."""
    code = ("import sys; from ivdrem.cli import build_parser; build_parser(); "
            "import ivdrem.reports as r; "
            "bad = [m for m in ('ivdrem.reports.report', 'matplotlib.backends.backend_pdf') "
            "if m in sys.modules]; assert not bad, bad; "
            "assert callable(r.write_report) and 'ivdrem.reports.report' in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)


# ---------------------------------------------------------------- the console script's exit
def _console(code, tmp_path, *args):
    """Run `code` (which ends by calling ivdrem.cli.run) in a child process with argv."""
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True,
                          cwd=tmp_path, timeout=600)


_WITH_HANDLER = ("import atexit, gc, sys\n"
                 "atexit.register(lambda: print('handler ran; gc enabled:', gc.isenabled()))\n"
                 "sys.argv[0] = 'ivdrem'\n"
                 "from ivdrem.cli import run\n"
                 "run()\n"
                 "print('not reached')\n")


def test_the_console_script_keeps_every_output_and_its_exit_handlers(tmp_path):
    """run() skips the interpreter's teardown: the command's printed lines, its file and
    the exit handlers must all be there, and the exit status must be the command's."""
    out = tmp_path / "paper.json"
    p = _console(_WITH_HANDLER, tmp_path, "paper", "--t-end", "0.5", "--laws",
                 "composite-learning", "--json", str(out), "--quiet")
    assert p.returncode == 0, p.stderr[-2000:]
    lines = p.stdout.splitlines()
    assert lines[0].strip().startswith("composite-learning: |theta_err|(t_end)")
    assert lines[-2] == f"wrote {out}"                  # the command's last line, flushed
    assert lines[-1] == "handler ran; gc enabled: True"  # then the handlers, GC back on
    assert "not reached" not in p.stdout
    assert set(json.loads(out.read_text())) == {"composite-learning"}


def test_the_console_script_exits_with_the_commands_status(tmp_path):
    p = _console(_WITH_HANDLER, tmp_path, "paper", "--t-end", "-1", "--quiet")
    assert p.returncode == 2
    assert "--t-end must be a finite number of seconds > 0" in p.stderr
    assert p.stdout.splitlines() == ["handler ran; gc enabled: True"]
    # an argparse error is a SystemExit: the ordinary exit, its status and the handlers
    p = _console(_WITH_HANDLER, tmp_path, "paper", "--no-such-option")
    assert p.returncode == 2 and "unrecognized arguments" in p.stderr
    assert p.stdout.splitlines() == ["handler ran; gc enabled: True"]


def test_python_m_ivdrem_is_the_console_script(tmp_path):
    p = subprocess.run([sys.executable, "-m", "ivdrem", "paper", "--t-end", "-1"],
                       capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert p.returncode == 2 and "--t-end" in p.stderr


def test_every_command_line_face_is_in_the_cli_package():
    """argparse is used in ivdrem/cli/ only (every command, its options and the
    preflight), and no module outside it imports it: the library below is usable without
    the command line (ivdrem/__main__.py only starts it)."""
    import ast
    from pathlib import Path

    import ivdrem
    root = Path(ivdrem.__file__).parent
    checked = 0
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root)
        if rel.parts[0] == "cli" or rel.name == "__main__.py":
            continue
        text = path.read_text(encoding="utf-8")
        assert "argparse" not in text, rel
        package = ["ivdrem", *rel.parts[:-1]]
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.ImportFrom):
                base = package[:len(package) - node.level + 1] if node.level else []
                names = [".".join(base + ([node.module] if node.module else []))]
                if not node.module:
                    names = [f"{names[0]}.{a.name}" for a in node.names]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            else:
                continue
            for name in names:
                assert not (name == "ivdrem.cli" or name.startswith("ivdrem.cli.")), (rel, name)
        checked += 1
    assert checked > 50


@pytest.mark.parametrize("command", [
    ["paper"], ["report", "--no-fmu-check"], ["cosim"], ["cosim", "--plant", "mujoco"],
    ["fmu", "export", "-o", "P.fmu"], ["fmu", "export", "--controller", "-o", "C.fmu"]],
    ids=lambda c: " ".join(c[:3]))
def test_every_config_command_refuses_a_wrong_length_before_any_work(command, tmp_path,
                                                                     monkeypatch, capsys):
    """A vector of the wrong length for the arm in --config (only the model knows it:
    read_config takes it as data, Experiment.from_config refuses it) is one line naming the
    key, in the same words, with exit status 2, from every command that takes --config;
    nothing simulated, exported or written."""
    import ivdrem.sim as sim
    import ivdrem.fmu.export as fmu_export
    import ivdrem.controller.fmu_export as controller_export

    def never(*a, **k):
        raise AssertionError("work started")
    monkeypatch.setattr(sim, "simulate", never)
    monkeypatch.setattr(fmu_export, "export_fmu", never)
    monkeypatch.setattr(controller_export, "export_controller_fmu", never)
    monkeypatch.chdir(tmp_path)
    cfg = tmp_path / "arm.toml"
    cfg.write_text('[model]\nname = "planar-3"\n[initial]\nq0 = [0.0, 0.5]\n', encoding="utf-8")
    argv = [*command, "--config", str(cfg)]
    if command[0] == "report":
        argv += ["--out", str(tmp_path / "rep")]
    rc = main(argv)
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "config key 'initial.q0' must have 3 entries (model 'planar-3' has n = 3), got 2" \
        in err
    assert len(err.strip().splitlines()) == 1, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["arm.toml"]


def test_fmu_export_config_exports_the_configured_arm(tmp_path, capsys):
    """`ivdrem fmu export --config FILE` (the plant FMU): the configuration's arm, the
    configuration checked whole against it (its Experiment, no law resolved)."""
    cfg = tmp_path / "arm.toml"
    cfg.write_text('[model]\nname = "planar-3"\n', encoding="utf-8")
    fmu = tmp_path / "P.fmu"
    assert main(["fmu", "export", "--config", str(cfg), "--no-compile", "-o", str(fmu)]) == 0
    assert "(model planar-3, n = 3, ntheta = 6)" in capsys.readouterr().out
    assert fmu.is_file()
