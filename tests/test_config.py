"""Tests of the experiment configuration (ivdrem.experiments.config)."""
import math
import re
from pathlib import Path

import numpy as np
import pytest

from ivdrem.laws import get_law
from ivdrem.experiments.config import (
    LAWS,
    ConfigError,
    closed_loop_kwargs,
    law_gains,
    default_config,
    dump_toml,
    read_config,
    resolve_config,
    schema,
    solver_kwargs,
)

ROOT = Path(__file__).resolve().parents[1]
PI = math.pi


def resolved_config(path=None, overrides=None):
    """The configuration resolved against its model: read_config, then resolve_config
    (what Experiment.from_config holds as ``config``)."""
    return resolve_config(read_config(path, overrides))[0]


def write(tmp_path, text, name="user.toml"):
    p = tmp_path / name
    p.write_text(text, encoding="utf-8")
    return p


def test_default_is_section_8_of_spec():
    c = resolved_config()
    assert c["experiment"] == {"t_end": 300.0, "laws": ["iv-drem", "composite-learning"], "dt_out": 0.01}
    assert c["model"] == {"name": "two-link", "theta": [1.3, 0.28, 0.32, 0.4, 1.4], "g": 9.81}
    assert c["initial"]["q0"] == [0.0, pytest.approx(0.3 * PI, abs=1e-15)]
    assert c["initial"]["dq0"] == [0.0, 0.0]
    assert c["initial"]["theta_hat0"] == [0.0] * 5
    assert c["controller"] == {
        "alpha": 1.0, "K": [2.0, 2.0], "delta_mu": 0.8, "Gamma": 0.01,
        "mu0": 1.0, "mu1": 15.0, "observer_variant": "corrected",
    }
    assert c["filters"] == {"l": 50.0}
    assert c["iv_drem"] == {"T": 20.0, "p": 2.0, "F0": 1.0, "gamma": 1e10, "mixing": "paper"}
    assert c["composite_learning"] == {"T": 20.0, "gamma": 1.0, "epsilon": 1e-9}
    assert c["sigma_modification"] == {"sigma": 0.1, "theta_star": [1.0, 0.2, 0.3, 0.3, 1.0]}
    tr = c["trajectory"]
    np.testing.assert_allclose(tr["amplitude"], [0.4 * PI, 0.3 * PI], rtol=0, atol=1e-15)
    np.testing.assert_allclose(tr["omega"], [2.0, 0.3])
    np.testing.assert_allclose(tr["phase"], [0.0, PI / 2], rtol=0, atol=1e-15)
    np.testing.assert_allclose(tr["offset"], [0.2 * PI, 0.3 * PI], rtol=0, atol=1e-15)
    d = c["disturbance"]
    np.testing.assert_allclose(d["amplitude"], [7.5, 1.5])
    np.testing.assert_allclose(d["omega"], [0.5 * PI, 0.05 * PI], rtol=0, atol=1e-15)
    assert d["phase"] == [0.0, 0.0] and d["offset"] == [0.0, 0.0]
    assert c["solver"] == {"method": "rodas5p", "rtol": 2e-4, "atol": 2e-6, "h": 1e-3, "h_max": 5.0}
    assert list(c) == list(schema())
    for s, keys in schema().items():
        assert list(c[s]) == list(keys)


#: overrides of the snapshot's planar-3 case: every key that does not follow the model
_PLANAR3 = {"model.name": "planar-3", "initial.q0": [0.1, 0.2, 0.3],
            "trajectory.amplitude": [0.1, 0.2, 0.3], "trajectory.omega": [1.0, 1.5, 2.0],
            "trajectory.phase": [0.0, 0.0, 0.0], "trajectory.offset": [0.0, 0.0, 0.0],
            "disturbance.amplitude": [1.0, 1.0, 1.0], "disturbance.omega": [0.5, 0.6, 0.7],
            "disturbance.phase": [0.0, 0.0, 0.0], "disturbance.offset": [0.0, 0.0, 0.0]}


def test_effective_configurations_equal_the_snapshot():
    """default_config() and resolved_config() of the default, the example files and a
    planar-3 arm (the keys that follow the model) are the values, sections and key order
    recorded in tests/data/config_snapshot.json, whatever file or registry they come from."""
    import json
    snap = json.loads((ROOT / "tests" / "data" / "config_snapshot.json").read_text("utf-8"))
    got = {"default_config": default_config(), "load_config": resolved_config(),
           "overrides planar-3": resolved_config(overrides=_PLANAR3)}
    for name in ("paper", "planar3", "instrument"):
        got[f"examples/{name}.toml"] = resolved_config(ROOT / "examples" / f"{name}.toml")
    assert set(got) == set(snap)
    for case, cfg in got.items():
        plain = json.loads(json.dumps(cfg))
        assert plain == snap[case], case
        assert [(s, list(t)) for s, t in plain.items()] == \
            [(s, list(t)) for s, t in snap[case].items()], case


def test_read_config_is_data_and_builds_no_model(monkeypatch):
    """read_config of a real arm's configuration (examples/panda.toml) builds no model and
    designs no reference (both would raise here); the keys that follow the model are
    absent from the data, and resolve_config fills them: the same configuration as the
    snapshot-checked resolved configuration, whose keys are exactly those the data lacks."""
    from ivdrem import models
    from ivdrem.diagrams import arm_reference
    import ivdrem.experiments.config as config_module

    def refuse(*args, **kwargs):
        raise AssertionError("read_config built a model or designed a reference")
    for owner, name in ((models, "from_urdf"), (models, "get_model"),
                        (config_module, "model_from_config"),
                        (arm_reference, "design_trajectory"),
                        (arm_reference, "design_disturbance"),
                        (arm_reference, "design_gains"), (arm_reference, "design_window")):
        monkeypatch.setattr(owner, name, refuse)
    panda = ROOT / "examples" / "panda.toml"
    data = read_config(panda)
    assert data["model"]["name"] == "panda" and "theta" not in data["model"]
    assert data["trajectory"]["kind"] == "fourier"
    assert "a" not in data["trajectory"] and "K" not in data["controller"]
    monkeypatch.undo()
    resolved, model = resolve_config(data)
    assert resolved == resolved_config(panda)
    assert len(resolved["controller"]["K"]) == model.n
    absent = {(s, k) for s, t in resolved.items() for k in t if k not in data[s]}
    assert ("trajectory", "a") in absent and ("initial", "q0") in absent
    assert {(s, k) for s, t in data.items() for k in t if k not in resolved[s]} == set()
    # a resolved configuration resolves to itself; the paper's data is already complete
    assert resolve_config(resolved, model)[0] == resolved
    assert resolve_config(read_config())[0] == read_config() == resolved_config()


def test_a_wrong_length_is_refused_when_resolved_with_the_same_message():
    """A vector of the wrong length for the arm needs the model: read_config takes it as
    data, resolving it (Experiment.from_config) refuses it naming the key."""
    from ivdrem.experiments.experiment import Experiment
    ov = {"model": {"name": "planar-3"}, "initial": {"q0": [0.0, 0.0]}}
    data = read_config(overrides=ov)
    assert data["initial"]["q0"] == [0.0, 0.0]
    with pytest.raises(ConfigError, match=r"^config key 'initial.q0' must have 3 entries "
                       r"\(model 'planar-3' has n = 3\), got 2$"):
        Experiment.from_config(data)
    with pytest.raises(ConfigError, match="'initial.q0' must have 3 entries"):
        resolve_config(data)


def test_default_is_a_fresh_copy():
    a = resolved_config()
    a["controller"]["K"][0] = 99.0
    assert resolved_config()["controller"]["K"] == [2.0, 2.0]
    assert default_config()["controller"]["K"] == [2.0, 2.0]


def _toml(path):
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib
    return tomllib.loads(Path(path).read_text("utf-8"))


def test_example_paper_toml_is_the_effective_default_key_by_key():
    """examples/paper.toml documents the embedded default: it sets every key of every
    section (the laws' sections too), each to the value the default has (default.toml's,
    or the law registry's), so neither can change without the other."""
    example = ROOT / "examples" / "paper.toml"
    raw, default = _toml(example), default_config()
    assert list(raw) == list(default) == list(schema())
    drift = [f"{s}.{k}: paper.toml {raw[s].get(k)!r}, default {v!r}"
             for s, table in default.items() for k, v in table.items() if raw[s].get(k) != v]
    extra = [f"{s}.{k}" for s, table in raw.items() for k in table if k not in default[s]]
    assert not drift and not extra, "\n".join(drift + extra)
    assert resolved_config(example) == resolved_config()


def test_default_toml_has_no_law_section():
    """A law's gains have one source, its registry entry (Law.keys, Law.defaults): the
    packaged default.toml holds only the sections every run reads."""
    from ivdrem.experiments.config import SECTIONS
    raw = _toml(ROOT / "ivdrem" / "experiments" / "default.toml")
    assert list(raw) == list(SECTIONS)
    assert {s for s in schema() if s not in SECTIONS} == \
        {"iv_drem", "composite_learning", "sigma_modification"}


def test_user_file_is_merged_key_by_key(tmp_path):
    p = write(tmp_path, "[experiment]\nt_end = 60\n[controller]\nK = [3, 4]\nGamma = [0.1, 0.2, 0.3, 0.4, 0.5]\n")
    c = resolved_config(p)
    assert c["experiment"]["t_end"] == 60.0 and isinstance(c["experiment"]["t_end"], float)
    assert c["experiment"]["laws"] == ["iv-drem", "composite-learning"]
    assert c["controller"]["K"] == [3.0, 4.0]
    assert c["controller"]["alpha"] == 1.0
    kw = closed_loop_kwargs(c, "iv-drem")
    np.testing.assert_array_equal(kw["K"], np.diag([3.0, 4.0]))
    np.testing.assert_array_equal(kw["Gamma"], np.diag([0.1, 0.2, 0.3, 0.4, 0.5]))


def test_overrides_nested_and_dotted(tmp_path):
    p = write(tmp_path, "[experiment]\nt_end = 60\n")
    c = resolved_config(p, overrides={"experiment": {"t_end": 5.0}, "experiment.laws": ["drem"]})
    assert c["experiment"]["t_end"] == 5.0
    assert c["experiment"]["laws"] == ["drem"]


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("[controller]\nKp = [1, 1]\n", "config key 'controller.Kp' is not known (did you mean 'controller.K'?)"),
        ("[contoller]\nK = [1, 1]\n", "config section 'contoller' is not known (did you mean 'controller'?)"),
        ("[iv_drem]\ngama = 1.0\n", "did you mean 'iv_drem.gamma'?"),
        ("[controller]\nalpha = 'big'\n", "'controller.alpha' must be a number"),
        ("[controller]\nalpha = true\n", "'controller.alpha' must be a number"),
        ("[controller]\nK = 2.0\n", "'controller.K' must be a list of numbers"),
        ("[controller]\nK = [2.0, 2.0, 2.0]\n", "'controller.K' must have 2 entries"),
        ("[initial]\ntheta_hat0 = [0, 0]\n", "'initial.theta_hat0' must have 5 entries"),
        ("[controller]\nGamma = [1, 1]\n", "'controller.Gamma' must have 5 entries"),
        ("[trajectory]\nomega = [1.0]\n", "'trajectory.omega' must have 2 entries"),
        ("[controller]\nalpha = 0\n", "'controller.alpha' must be > 0"),
        ("[controller]\nK = [2.0, -1.0]\n", "'controller.K' entries must be > 0"),
        ("[controller]\nGamma = 0\n", "'controller.Gamma' must be > 0"),
        ("[controller]\nGamma = [1, 1, 0, 1, 1]\n", "'controller.Gamma' entries must be > 0"),
        ("[controller]\nmu1 = 0\n", "'controller.mu1' must be > 0"),
        ("[controller]\nmu0 = -0.5\n", "'controller.mu0' must be >= 0"),
        ("[controller]\ndelta_mu = 1.0\n", "'controller.delta_mu' must be in (0, 1)"),
        ("[controller]\ndelta_mu = 0\n", "'controller.delta_mu' must be in (0, 1)"),
        ("[controller]\nobserver_variant = 'literally'\n", "'controller.observer_variant'"),
        ("[controller]\ninjection = 'theta'\n", "'controller.injection'"),
        ("[filters]\nl = -50\n", "'filters.l' must be > 0"),
        ("[iv_drem]\nT = 0\n", "'iv_drem.T' must be > 0"),
        ("[iv_drem]\np = 0.5\n", "'iv_drem.p' must be >= 1"),
        ("[iv_drem]\nF0 = 0\n", "'iv_drem.F0' must be > 0"),
        ("[iv_drem]\ngamma = -1e10\n", "'iv_drem.gamma' must be > 0"),
        ("[composite_learning]\nT = -20\n", "'composite_learning.T' must be > 0"),
        ("[composite_learning]\ngamma = 0\n", "'composite_learning.gamma' must be > 0"),
        ("[experiment]\nlaws = ['iv-drem', 'composit-learning']\n", "did you mean 'composite-learning'?"),
        ("[experiment]\nlaws = []\n", "at least one law"),
        ("[experiment]\nlaws = ['drem', 'drem']\n", "lists a law twice"),
        ("[solver]\nmethod = 'rk45'\n", "'solver.method' = 'rk45' is not valid"),
        ("[solver]\nrtol = 0\n", "'solver.rtol' must be > 0"),
        ("[experiment]\nt_end = 0\n", "'experiment.t_end' must be > 0"),
        ("[experiment]\nt_end = -3\n", "'experiment.t_end' must be > 0"),
        ("[experiment]\ndt_out = 0\n", "'experiment.dt_out' must be > 0"),
        ("[experiment]\nt_end = inf\n", "must be finite"),
        ("[model]\nname = 'tow-link'\n", "did you mean 'two-link'?"),
        ("experiment = 3\n", "config section 'experiment' must be a table"),
    ],
)
def test_bad_configs_are_rejected(tmp_path, text, fragment):
    p = write(tmp_path, text)
    with pytest.raises(ConfigError) as exc:
        resolved_config(p)
    assert fragment in str(exc.value)
    assert isinstance(exc.value, ValueError)


def test_unknown_key_lists_valid_keys(tmp_path):
    with pytest.raises(ConfigError) as exc:
        resolved_config(write(tmp_path, "[controller]\nKp = 1\n"))
    for key in schema()["controller"]:
        assert key in str(exc.value)


def test_missing_file_and_bad_toml(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        resolved_config(tmp_path / "nope.toml")
    with pytest.raises(ConfigError, match="not valid TOML"):
        resolved_config(write(tmp_path, "[experiment\nt_end = 1\n"))


def test_planar_model_checks_n_and_ntheta():
    vec3 = [0.0, 0.0, 0.0]
    with pytest.raises(ConfigError, match="'initial.q0' must have 3 entries"):
        resolved_config(overrides={"model": {"name": "planar-3"}, "initial": {"q0": [0.0, 0.0]}})
    ov = {
        "model": {"name": "planar-3", "theta": [1.0] * 6},
        "initial": {"q0": vec3, "dq0": vec3, "theta_hat0": [0.0] * 6},
        "controller": {"K": [1.0, 1.0, 1.0]},
        "sigma_modification": {"theta_star": [1.0] * 6},
        "trajectory": {k: vec3 for k in ("amplitude", "omega", "phase", "offset")},
        "disturbance": {k: vec3 for k in ("amplitude", "omega", "phase", "offset")},
    }
    c = resolved_config(overrides=ov)
    assert c["model"]["name"] == "planar-3"
    kw = closed_loop_kwargs(c, "iv-drem")
    assert kw["K"].shape == (3, 3) and kw["Gamma"].shape == (6, 6)
    # nθ of the model (6 for a planar 3-link arm) is checked
    ov["initial"] = dict(ov["initial"], theta_hat0=[0.0] * 4)
    with pytest.raises(ConfigError, match="'initial.theta_hat0' must have 6 entries"):
        resolved_config(overrides=ov)


def test_another_robot_needs_only_what_differs():
    """Defaults that are zeros, the per-joint gain or the model's own values follow the
    model's n and nθ; what the user sets is kept."""
    from ivdrem.models import get_model
    vec3 = [0.1, 0.2, 0.3]
    ov = {"model": {"name": "planar-3"}, "initial": {"q0": vec3},
          "trajectory": {k: vec3 for k in ("amplitude", "omega", "phase", "offset")},
          "disturbance": {k: vec3 for k in ("amplitude", "omega", "phase", "offset")},
          "controller": {"K": [3.0, 3.0, 3.0]}}
    c = resolved_config(overrides=ov)
    m = get_model("planar-3")
    np.testing.assert_allclose(c["model"]["theta"], m.theta_values)
    assert c["initial"]["dq0"] == [0.0] * 3 and c["initial"]["theta_hat0"] == [0.0] * 6
    assert c["controller"]["K"] == [3.0] * 3                      # set by the user: kept
    assert c["sigma_modification"]["theta_star"] == [0.0] * 6
    assert c["iv_drem"]["gamma"] == "auto"
    assert closed_loop_kwargs(c, "iv-drem")["gains"]["gamma"] == "auto"
    # the paper's arm keeps the paper's numbers
    d = resolved_config()
    assert d["iv_drem"]["gamma"] == 1e10 and d["controller"]["K"] == [2.0, 2.0]
    # a number or "auto", nothing else
    assert resolved_config(overrides={"iv_drem.gamma": "auto"})["iv_drem"]["gamma"] == "auto"
    with pytest.raises(ConfigError, match="iv_drem.gamma' must be a number or \"auto\""):
        resolved_config(overrides={"iv_drem.gamma": "big"})


def test_laws_all_expands_to_every_registered_law():
    c = resolved_config(overrides={"experiment.laws": "all"})
    assert c["experiment"]["laws"] == list(LAWS)
    with pytest.raises(ConfigError, match="or 'all'"):
        resolved_config(overrides={"experiment.laws": ["al"]})


def test_closed_loop_kwargs_per_law():
    """The loop's keywords are the same for every law; the law's gains come in one dict,
    ``gains``, by the names its registry entry declares."""
    c = resolved_config()
    common = {"alpha", "K", "delta_mu", "Gamma", "mu0", "mu1", "observer_variant", "l",
              "theta_hat0", "q0", "dq0", "theta", "trajectory", "disturbance", "gains"}
    expect = {
        "iv-drem": {"T", "p", "F0", "gamma", "mixing"},
        "drem": {"T", "p", "F0", "gamma", "mixing"},
        "composite-learning": {"T", "gamma", "epsilon"},
        "sigma-modification": {"sigma", "theta_star"},    # no window: no T
        "none": set(),
    }
    assert set(expect) == set(LAWS)
    for law, gains in expect.items():
        kw = closed_loop_kwargs(c, law)
        assert set(kw) == common and set(kw["gains"]) == gains, law
        again = law_gains(c, law)
        assert set(again) == gains
        for name in gains:
            np.testing.assert_array_equal(kw["gains"][name], again[name])
        # each gain is read from the configuration key the registry names
        for name, key in get_law(law).config.items():
            section, k = key.split(".")
            np.testing.assert_array_equal(kw["gains"][name], c[section][k])
    iv = closed_loop_kwargs(c, "iv-drem")
    cl = closed_loop_kwargs(c, "composite-learning")["gains"]
    assert iv["gains"]["gamma"] == 1e10 and cl["gamma"] == 1.0 and cl["epsilon"] == 1e-9
    assert (iv["gains"]["T"], iv["gains"]["p"], iv["gains"]["F0"]) == (20.0, 2.0, 1.0)
    np.testing.assert_array_equal(iv["K"], 2.0 * np.eye(2))
    np.testing.assert_array_equal(iv["Gamma"], 0.01 * np.eye(5))
    np.testing.assert_array_equal(iv["theta"], [1.3, 0.28, 0.32, 0.4, 1.4])
    np.testing.assert_allclose(iv["q0"], [0.0, 0.3 * PI])
    assert set(iv["trajectory"]) == {"amplitude", "omega", "phase", "offset"}
    assert isinstance(iv["trajectory"]["omega"], np.ndarray)
    np.testing.assert_allclose(iv["disturbance"]["omega"], [0.5 * PI, 0.05 * PI])
    sm = closed_loop_kwargs(c, "sigma-modification")["gains"]
    assert sm["sigma"] == 0.1
    np.testing.assert_array_equal(sm["theta_star"], [1.0, 0.2, 0.3, 0.3, 1.0])
    with pytest.raises(ConfigError, match="did you mean 'iv-drem'"):
        closed_loop_kwargs(c, "ivdrem")


def test_solver_kwargs():
    assert solver_kwargs(resolved_config()) == {"method": "rodas5p", "rtol": 2e-4, "atol": 2e-6, "h": 1e-3, "h_max": 5.0}


def test_solver_h_max_is_held_below_each_laws_window():
    """A step must not read a window's delay history beyond t: h_max <= T/2 of the law's
    window (eq. 14).  The paper's h_max = 5 s is below its T/2 = 10 s: unchanged."""
    c = resolved_config()
    for law in ("iv-drem", "composite-learning", "drem"):
        assert solver_kwargs(c, law)["h_max"] == 5.0
    assert solver_kwargs(c, "none")["h_max"] == 5.0
    short = resolved_config(overrides={"iv_drem.T": 5.0})
    assert solver_kwargs(short, "iv-drem")["h_max"] == 2.5
    assert solver_kwargs(short, "drem")["h_max"] == 2.5
    # composite learning has its own window: it is not held by iv_drem.T
    assert solver_kwargs(short, "composite-learning")["h_max"] == 5.0
    assert solver_kwargs(short)["h_max"] == 5.0


def test_a_short_window_runs(tmp_path):
    """iv_drem.T = 5 s with the default h_max = 5 s ran into "the step must stay below the
    shortest transport delay" before any step; now it simulates past one window."""
    from ivdrem.experiments.paper import run_law
    c = resolved_config(overrides={"iv_drem.T": 5.0, "experiment.t_end": 6.0})
    run = run_law(c, "iv-drem", progress=False)
    assert run.stats["h_max"] == 2.5
    assert np.all(np.isfinite(run.response.states[:, -1]))


def test_dump_toml_round_trip(tmp_path):
    c = resolved_config(overrides={"controller": {"Gamma": [0.1, 0.2, 0.3, 0.4, 0.5]}, "experiment": {"laws": ["drem"]}})
    p = write(tmp_path, dump_toml(c))
    assert resolved_config(p) == c


def test_a_configuration_names_the_module_that_registers_its_laws(tmp_path):
    """experiment.plugins: a Python file (relative to the configuration file) that
    registers a law; the configuration then takes the law and its own table."""
    import shutil
    from ivdrem.cli.preflight import check_runs
    from ivdrem.laws import LAWS
    shutil.copy(Path(__file__).resolve().parents[1] / "examples" / "custom_law.py",
                tmp_path / "my_laws.py")
    cfg = write(tmp_path, '[experiment]\nplugins = ["my_laws.py"]\n'
                          'laws = ["normalised-iv-drem", "iv-drem"]\nt_end = 2.0\n'
                          '[normalised_iv_drem]\nnu = 2.5\n')
    from ivdrem.experiments import config as config_module
    try:
        c = resolved_config(cfg)
        assert "normalised-iv-drem" in LAWS
        assert c["experiment"]["plugins"] == [str(tmp_path / "my_laws.py")]
        kw = closed_loop_kwargs(c, "normalised-iv-drem")
        assert kw["gains"]["nu"] == 2.5
        check_runs(c)                                 # the preflight prices its loop
        # a worker validating the (absolute) configuration imports it the same way
        from ivdrem.experiments.config import validate_config
        assert validate_config(c)["experiment"]["plugins"] == c["experiment"]["plugins"]
    finally:   # the rest of the suite sees the built-in laws only
        LAWS.pop("normalised-iv-drem", None)
        config_module._LOADED_PLUGINS.clear()


@pytest.mark.parametrize("plugins, fragment", [
    ('["missing.py"]', "file '"),
    ('["no_such_module_ivdrem"]', "importing 'no_such_module_ivdrem' failed: ModuleNotFoundError"),
    ('[1]', "must be a list"),
])
def test_bad_plugins_are_named(tmp_path, plugins, fragment):
    cfg = write(tmp_path, f"[experiment]\nplugins = {plugins}\n")
    with pytest.raises(ConfigError, match=re.escape(fragment)):
        resolved_config(cfg)


def test_a_plugin_that_raises_is_named(tmp_path):
    (tmp_path / "broken.py").write_text("raise RuntimeError('my bug')\n")
    cfg = write(tmp_path, '[experiment]\nplugins = ["broken.py"]\n')
    with pytest.raises(ConfigError, match=r"importing '.*broken\.py' failed: RuntimeError: my bug"):
        resolved_config(cfg)


def test_the_injection_key_reaches_the_loop_and_the_sampled_controller(tmp_path):
    """[controller] injection: the continuous loop's argument and the exported controller's
    option; absent, neither is set (each design's default then: docs/controller.md)."""
    from ivdrem.controller.fmu_export import controller_design
    from ivdrem.experiments.config import closed_loop_kwargs
    base = "[controller]\ndesign = 'inertia-scaled'\n"
    plain = resolved_config(write(tmp_path, base))
    assert "injection" not in closed_loop_kwargs(plain, "iv-drem")
    assert "injection" not in controller_design(plain, "iv-drem")
    cfg = resolved_config(write(tmp_path, base + "injection = 'estimate'\n"))
    assert closed_loop_kwargs(cfg, "iv-drem")["injection"] == "estimate"
    assert controller_design(cfg, "iv-drem")["injection"] == "estimate"


def test_load_config_is_a_deprecated_alias_that_nothing_in_the_package_calls():
    """load_config (deprecated, docs/experiment.md) warns, naming what replaces it, and gives
    the configuration an Experiment of the data holds; no module of the package calls it."""
    from ivdrem.experiments.config import load_config
    from ivdrem.experiments.experiment import Experiment
    for path, over in ((None, None),
                       (ROOT / "examples" / "planar3.toml", {"experiment.t_end": 2.0})):
        with pytest.warns(DeprecationWarning, match=r"read_config.*Experiment\.from_config"):
            old = load_config(path, over)
        assert old == Experiment.from_config(read_config(path, over)).config
    callers = [str(p.relative_to(ROOT)) for p in (ROOT / "ivdrem").rglob("*.py")
               if re.search(r"\bload_config\(", p.read_text(encoding="utf-8"))]
    assert callers == ["ivdrem/experiments/config.py"]          # its definition alone
    text = (ROOT / "ivdrem" / "experiments" / "config.py").read_text(encoding="utf-8")
    assert len(re.findall(r"\bload_config\(", text)) == 1
