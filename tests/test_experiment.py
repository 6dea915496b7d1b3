"""An experiment resolved once (ivdrem.experiments.experiment) and a law's gains through one
channel (closed_loop(law, model, gains={...})): counted on a real `ivdrem paper`, and a law
registered here with a gain of its own run from closed_loop and from a configuration."""
from __future__ import annotations

import collections
import importlib
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from ivdrem import blocks as block_library
from ivdrem import laws as registry
from ivdrem.cli import main
from ivdrem.diagrams import closed_loop
from ivdrem.experiments.config import read_config, resolve_config
from ivdrem.experiments.experiment import Experiment
from ivdrem.sim import simulate

ROOT = Path(__file__).resolve().parents[1]
closed_loop_module = importlib.import_module("ivdrem.diagrams.closed_loop")
config_module = importlib.import_module("ivdrem.experiments.config")


def resolved(path=None, overrides=None):
    """The configuration resolved against its model (read_config, then resolve_config)."""
    return resolve_config(read_config(path, overrides))[0]


def _count_calls(functions, run):
    """How many times each of `functions` is entered while `run()` runs (by code object,
    so that a call through any imported name counts)."""
    codes = {f.__code__: f.__name__ for f in functions}
    counts = collections.Counter()

    def profile(frame, event, arg):
        if event == "call" and frame.f_code in codes:
            counts[codes[frame.f_code]] += 1
    previous = sys.getprofile()
    sys.setprofile(profile)
    try:
        result = run()
    finally:
        sys.setprofile(previous)
    return result, counts


def test_ivdrem_paper_resolves_each_law_once_and_builds_its_loop_once(tmp_path):
    """`ivdrem paper` of the default configuration (two laws): the configuration turned
    into closed_loop's arguments once per law (13 times before the Experiment: 8 in the
    preflight, 5 in the runs), each law's loop built once (twice before: priced, then
    built again to run), the model built once."""
    out = tmp_path / "o.json"
    rc, counts = _count_calls(
        [config_module.closed_loop_kwargs, closed_loop_module.build_resolved,
         closed_loop_module.resolve_loop, config_module._build.__wrapped__],
        lambda: main(["paper", "--t-end", "0.2", "--quiet", "--json", str(out)]))
    assert rc == 0 and out.is_file()
    assert counts["closed_loop_kwargs"] == 2          # iv-drem, composite-learning
    assert counts["resolve_loop"] == 2
    assert counts["build_resolved"] == 2
    assert counts["_build"] <= 1                     # the model (0: built by an earlier test)


def test_the_preflight_prices_the_loop_the_run_simulates():
    from ivdrem.cli.preflight import check_runs
    experiment = Experiment.from_config(resolved(overrides={"experiment.t_end": 0.1,
                                                               "experiment.laws": ["iv-drem"]}))
    check_runs(experiment)
    priced = experiment.loop("iv-drem")
    assert experiment.loop("iv-drem") is priced                  # kept, not built again
    _, counts = _count_calls([closed_loop_module.build_resolved],
                             lambda: experiment.run("iv-drem", progress=False))
    assert counts["build_resolved"] == 0
    experiment.release("iv-drem")
    assert experiment.law("iv-drem").diagram is None


def test_an_experiment_reads_the_configuration_once_per_law():
    c = resolved(overrides={"iv_drem.T": 10.0, "controller.K": [3.0, 4.0]})
    experiment, counts = _count_calls([config_module.closed_loop_kwargs],
                                      lambda: Experiment.from_config(c))
    assert counts["closed_loop_kwargs"] == 2                      # one per configured law
    _, counts = _count_calls([config_module.closed_loop_kwargs],
                             lambda: [experiment.law(law) for law in experiment.laws * 3])
    assert counts["closed_loop_kwargs"] == 0                      # kept
    setup = experiment.law("iv-drem")
    assert setup.gains == {"T": 10.0, "p": 2.0, "F0": 1.0, "gamma": 1e10, "mixing": "paper"}
    np.testing.assert_array_equal(setup.loop["K"], np.diag([3.0, 4.0]))
    assert setup.solver["h_max"] == 5.0 and setup.gamma == 1e10 and not setup.auto


def test_an_experiment_of_data_builds_the_model_once_and_designs_the_reference_once():
    """Configuration data of an arm other than the paper's (the real-arm reference follows
    the model): Experiment.from_config builds the model once and designs the reference,
    its disturbance and window once; the laws' loops use that design (closed_loop designs
    nothing more), and the experiment's configuration is the resolved data's."""
    from ivdrem.diagrams import arm_reference
    data = read_config(overrides={"model.name": "planar-3", "experiment.t_end": 0.1})
    assert "a" not in data["trajectory"]                   # data: nothing designed yet
    config_module._build.cache_clear()
    designs = [arm_reference.design_trajectory, arm_reference.design_disturbance,
               arm_reference.design_window, arm_reference.design_gains]
    experiment, counts = _count_calls([config_module._build.__wrapped__, *designs],
                                      lambda: Experiment.from_config(data))
    assert counts["_build"] == 1
    assert {f.__name__: counts[f.__name__] for f in designs} == \
        {f.__name__: 1 for f in designs}
    assert experiment.config == resolved(overrides={"model.name": "planar-3",
                                                       "experiment.t_end": 0.1})
    assert experiment.model.n == 3 and experiment.laws == ["iv-drem", "composite-learning"]
    _, counts = _count_calls(designs, lambda: [experiment.loop(law) for law in experiment.laws])
    assert sum(counts.values()) == 0


def test_the_paper_arm_defaults_come_from_the_default_configuration():
    """q(0) = (0, 0.3π), the reference and the disturbance of the paper are written in
    ivdrem/experiments/default.toml; closed_loop's defaults on the 2-link arm are those."""
    from ivdrem._default_config import paper_experiment
    text = (ROOT / "ivdrem" / "experiments" / "default.toml").read_text()
    assert "q0 = [0.0, 0.9424777960769379]" in text
    paper = paper_experiment()
    assert paper["q0"] == [0.0, 0.3 * np.pi]
    d = closed_loop("none")
    plant = next(s for s in d.syslist if s.name == "plant")
    np.testing.assert_array_equal(plant.ivdrem.x0[:2], paper["q0"])
    traj = next(s for s in d.syslist if s.name == "trajectory")
    for key in ("amplitude", "omega", "phase", "offset"):
        np.testing.assert_array_equal(traj.params[f"q_d_{key}"], paper["trajectory"][key])
    # the values are written once: not again in the loop, the configuration or the cosim
    literal = re.compile(r"0\.3\s*\*\s*(np\.|math\.)?pi\b|0\.9424777960769379")
    for path in [*(ROOT / "ivdrem" / "diagrams").glob("*.py"),
                 *(ROOT / "ivdrem" / "experiments").glob("*.py"),
                 ROOT / "ivdrem" / "fmu" / "cosim.py"]:
        assert not literal.search(path.read_text()), path


# ----------------------------------------------------------------- one channel for gains
def _leak_law(name="leak-kappa"):
    """A law with a gain no built-in law has (kappa): ϑ_c = κ(θ* − θ̂), θ* the model's θ."""
    def build(ctx):
        return [block_library.sigma_modification_term(
            ctx.ntheta, ctx.params["kappa"], ctx.model.theta_values)], []
    return registry.Law(name, build, "leak with kappa", "#135790", section="leak_kappa",
                        defaults={"kappa": 0.25})


def test_a_law_with_a_new_gain_runs_from_closed_loop_and_from_a_configuration(tmp_path):
    registry.register_law(_leak_law())
    try:
        d = closed_loop("leak-kappa", gains={"kappa": 0.5})
        term = next(s for s in d.syslist if s.name == "sigma_modification_term")
        assert term.params["sigma"] == 0.5
        default = closed_loop("leak-kappa")
        assert next(s for s in default.syslist
                    if s.name == "sigma_modification_term").params["sigma"] == 0.25
        with pytest.raises(ValueError, match=r"law 'leak-kappa' has no gain\(s\) 'kapa'; "
                                             r"its gains .*: kappa"):
            closed_loop("leak-kappa", gains={"kapa": 0.5})
        with pytest.raises(TypeError, match=r"a law's gains go in gains=\{\.\.\.\} \(kappa\)"):
            closed_loop("leak-kappa", kappa=0.5)
        # from a configuration: its table [leak_kappa], through the Experiment
        f = tmp_path / "c.toml"
        f.write_text('[experiment]\nlaws = ["leak-kappa"]\nt_end = 0.1\n'
                     '[leak_kappa]\nkappa = 0.75\n')
        experiment = Experiment.from_config(resolved(f))
        assert experiment.law("leak-kappa").gains == {"kappa": 0.75}
        loop = experiment.loop("leak-kappa")
        assert next(s for s in loop.syslist
                    if s.name == "sigma_modification_term").params["sigma"] == 0.75
        run = experiment.run("leak-kappa", progress=False)
        assert run.response.time[-1] == pytest.approx(0.1)
        # the same loop and run as closed_loop given the same gain by hand
        by_hand = simulate(closed_loop("leak-kappa", gains={"kappa": 0.75}), 0.1,
                           dt_out=float(experiment.dt_out), progress=False,
                           **experiment.law("leak-kappa").solver)
        np.testing.assert_array_equal(by_hand.outputs, run.response.outputs)
    finally:
        registry.LAWS.pop("leak-kappa")


def test_gamma_auto_is_chosen_outside_closed_loop():
    """closed_loop takes numbers: γ "auto" is refused naming where it is chosen;
    calibrated_loop chooses it (ivdrem.diagrams.gamma_auto) and builds the same loop as
    closed_loop with that number."""
    from ivdrem.diagrams import calibrated_loop
    from ivdrem.models import planar_arm
    with pytest.raises(ValueError, match="calibrated_loop.*Experiment"):
        closed_loop("iv-drem", gains={"gamma": "auto"})
    with pytest.raises(ValueError, match="calibrated_loop"):      # the rule of a real arm
        closed_loop("iv-drem", planar_arm(3))
    d = calibrated_loop("iv-drem", planar_arm(3))                  # "eigen": the estimate
    assert d.gamma_choice["source"] == "reference"
    same = closed_loop("iv-drem", planar_arm(3), gains={"gamma": d.gamma_choice["gamma"]})
    term = [next(s for s in x.syslist if s.name == "drem_term") for x in (d, same)]
    assert term[0].params["gamma"] == term[1].params["gamma"] == d.gamma_choice["gamma"]


def _assert_same_design(got, want):
    """Two SampledController designs equal key by key (arrays and the reference's table
    compared element for element)."""
    assert set(got) == set(want)
    for key, value in want.items():
        if isinstance(value, dict):
            _assert_same_design(got[key], value)
        elif isinstance(value, (np.ndarray, list)):
            np.testing.assert_array_equal(got[key], value, err_msg=key)
        else:
            assert got[key] == value, key


def test_fmu_export_controller_config_makes_one_experiment(tmp_path, monkeypatch):
    """`ivdrem fmu export --controller --config` of an arm whose reference follows the model
    (planar-3): the configuration read as data and its Experiment made once: the model asked
    for once, the reference designed once, the law's arguments resolved once; the FMU gets
    that experiment's design (controller_design, γ "auto" resolved on its loop) with h the
    configuration's [solver] h."""
    from ivdrem.diagrams import arm_reference
    fmu_export = importlib.import_module("ivdrem.controller.fmu_export")
    got = {}

    def export(model, path, *, law, cc=None, overwrite=False, fmi_version=2, **design):
        got.update(design, model=model)          # the design the FMU would be written with
        assert law == "iv-drem"
        Path(path).write_bytes(b"not an FMU")
        return Path(path)
    monkeypatch.setattr(fmu_export, "export_controller_fmu", export)
    cfg = tmp_path / "arm.toml"
    cfg.write_text('[model]\nname = "planar-3"\n[solver]\nh = 5e-4\n', encoding="utf-8")
    rc, counts = _count_calls(
        [config_module.model_from_config, config_module.resolve_config,
         config_module.closed_loop_kwargs, arm_reference.design_trajectory],
        lambda: main(["fmu", "export", "--controller", "--config", str(cfg), "-o",
                      str(tmp_path / "c.fmu"), "--despite-prediction"]))
    assert rc == 0
    assert dict(counts) == {"model_from_config": 1, "resolve_config": 1,
                            "closed_loop_kwargs": 1, "design_trajectory": 1}
    model = got.pop("model")
    experiment = Experiment.from_config(read_config(cfg), laws=["iv-drem"])
    assert model is experiment.model and experiment.h == 5e-4
    want = fmu_export.controller_design(experiment, "iv-drem", h=experiment.h, mu_max=135.0)
    want, choice = fmu_export.resolve_gamma(model, "iv-drem", want, experiment)
    assert choice is not None and got["h"] == 5e-4
    _assert_same_design(got, want)


def test_a_study_builds_its_model_once_and_designs_its_reference_once():
    """A study of an arm whose reference follows the model: reading it, expanding a 2 x 2
    grid and pricing its runs ask for the model once and design the reference once (the
    base's Experiment); the runs' hashes (what --resume matches) are those of their
    configurations alone."""
    from ivdrem.diagrams import arm_reference
    from ivdrem.experiments.study import check_study_cost
    from ivdrem.experiments.study_spec import config_hash, expand_study, read_study
    study = {"model": {"name": "planar-3"},
             "experiment": {"t_end": 0.5, "laws": ["iv-drem"]},
             "study": {"grid": {"controller.alpha": [1.0, 1.5], "iv_drem.T": [5.0, 10.0]}}}

    def read_expand_price():
        runs = expand_study(read_study(study))
        check_study_cost(runs)
        return runs
    runs, counts = _count_calls([config_module.model_from_config,
                                 arm_reference.design_trajectory], read_expand_price)
    assert len(runs) == 4
    assert dict(counts) == {"model_from_config": 1, "design_trajectory": 1}
    model = runs[0].model
    assert model is not None and all(r.model is model for r in runs)
    assert [r.hash for r in runs] == [config_hash(r.config, r.law) for r in runs]
    assert [r.config["iv_drem"]["T"] for r in runs] == [5.0, 10.0, 5.0, 10.0]


def test_an_experiment_travels_to_another_process_as_its_configuration():
    """An Experiment pickles as its resolved configuration (a study's Dask worker gets it):
    unpickled, the same configuration, engine, laws and h, its model from that
    configuration."""
    import pickle
    experiment = Experiment.from_config(read_config(None, {"experiment.t_end": 0.5}),
                                        engine="reference", laws=["iv-drem"])
    again = pickle.loads(pickle.dumps(experiment))
    assert isinstance(again, Experiment) and again is not experiment
    assert again.config == experiment.config and again.engine == "reference"
    assert again.laws == ["iv-drem"] and again.h == experiment.h == 1e-3
    assert (again.model.name, again.model.n, again.model.ntheta) == ("two-link", 2, 5)
