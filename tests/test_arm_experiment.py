"""The model rule of the configuration ([model] name or urdf, one model_from_config) and
the default experiment for an arm other than the paper's (ivdrem.diagrams.arm_reference)."""
import math
from pathlib import Path

import numpy as np
import pytest

import ivdrem.models as models
from ivdrem.blocks.sources import fourier_series
from ivdrem.diagrams import arm_reference as arm
from ivdrem.experiments.config import (ConfigError, closed_loop_kwargs, dump_toml, read_config, resolve_config,
                                       model_from_config)
from ivdrem.models import planar_arm


def write(tmp_path, text, name="user.toml"):
    p = tmp_path / name
    p.write_text(text, encoding="utf-8")
    return p


class _Limited:
    """A planar arm carrying URDF-style limits (what ivdrem.models.from_urdf gives)."""
    def __init__(self, n=2, lo=(-1.0, -0.5), hi=(1.5, 2.0), vel=(1.2, 1.5), eff=(30.0, 10.0)):
        self._m = planar_arm(n)
        self.joint_names = [f"j{i + 1}" for i in range(n)]
        self.position_limits = np.column_stack([lo, hi])
        self.velocity_limits = np.asarray(vel, float)
        self.effort_limits = np.asarray(eff, float)

    def __getattr__(self, name):
        return getattr(self._m, name)


@pytest.fixture
def fake_urdf(monkeypatch):
    """ivdrem.models.from_urdf replaced by a recorder returning a limited planar arm: the
    configuration's resolution of the path and options is what is tested here."""
    calls = []

    def from_urdf(path, **opts):
        calls.append((Path(path), opts))
        if Path(path).read_text() == "bad":
            raise ValueError(f"{path} is not URDF")
        return _Limited()
    monkeypatch.setattr(models, "from_urdf", from_urdf)
    return calls


# --------------------------------------------------------------------------- the model rule
def test_name_resolves_through_the_models_package():
    c = resolve_config(read_config(overrides={"model.name": "planar-2"}))[0]
    m = model_from_config(c)
    assert (m.name, m.n, m.ntheta) == ("planar-2", 2, 4)
    assert model_from_config(c) is m                       # built once
    assert model_from_config(resolve_config(read_config())[0]).name == "two-link"


@pytest.mark.parametrize("name, fragment", [
    ("tow-link", "did you mean 'two-link'?"),
    ("panda-arm-9000", "config key 'model.name' = 'panda-arm-9000' is not a known model"),
    ("planar-0", "'model.name' = 'planar-0'"),
])
def test_bad_model_names_are_named_with_the_valid_ones(name, fragment):
    with pytest.raises(ConfigError) as exc:
        resolve_config(read_config(overrides={"model.name": name}))[0]
    assert fragment in str(exc.value)
    if "not a known model" in str(exc.value):
        assert "two-link" in str(exc.value)                # the valid names are listed


def test_urdf_path_is_relative_to_the_config_file(tmp_path, fake_urdf, monkeypatch):
    (tmp_path / "robots").mkdir()
    (tmp_path / "robots" / "arm.urdf").write_text("<robot/>")
    cfg_dir = tmp_path / "configs"
    cfg_dir.mkdir()
    p = write(cfg_dir, '[model]\nurdf = "../robots/arm.urdf"\nfriction = "viscous"\n'
                       'joints = ["j1", "j2"]\n[experiment]\nt_end = 2.0\n')
    monkeypatch.chdir(tmp_path / "robots")               # not the file's directory
    c = resolve_config(read_config(p))[0]
    assert "name" not in c["model"]
    assert Path(c["model"]["urdf"]) == (tmp_path / "robots" / "arm.urdf").resolve()
    assert fake_urdf[-1] == ((tmp_path / "robots" / "arm.urdf").resolve(),
                             {"friction": "viscous", "joints": ["j1", "j2"], "gravity": 9.81})
    # the dumped configuration loads again to the same one (absolute path)
    again = resolve_config(read_config(write(tmp_path, dump_toml(c), "dumped.toml")))[0]
    assert again == c
    # overrides: relative to the caller's directory
    c2 = resolve_config(read_config(overrides={"model.urdf": "arm.urdf"}))[0]
    assert Path(c2["model"]["urdf"]) == (tmp_path / "robots" / "arm.urdf").resolve()


@pytest.mark.parametrize("text, fragment", [
    ('[model]\nurdf = "missing.urdf"\n', "config key 'model.urdf': file"),
    ('[model]\nurdf = "bad.urdf"\n', "config key 'model.urdf'"),
    ('[model]\nurdf = "arm.urdf"\nname = "planar-2"\n', "'model.name' and 'model.urdf' are both set"),
    ('[model]\nurdf = "arm.urdf"\nfriction = "dry"\n', "'model.friction' = 'dry' is not valid"),
    ('[model]\nurdf = "arm.urdf"\njoints = "j1"\n', "'model.joints' must be a non-empty list of names"),
    ('[model]\nurdf = "arm.urdf"\nfrcition = "viscous"\n', "did you mean 'model.friction'?"),
    ('[model]\nname = "two-link"\nfriction = "viscous"\n', "model 'two-link' does not take model.friction"),
])
def test_bad_model_sections_name_the_key(tmp_path, fake_urdf, text, fragment):
    (tmp_path / "arm.urdf").write_text("<robot/>")
    (tmp_path / "bad.urdf").write_text("bad")
    with pytest.raises(ConfigError) as exc:
        resolve_config(read_config(write(tmp_path, text)))[0]
    assert fragment in str(exc.value)


# --------------------------------------------------------------------------- the experiment
def test_planar_arm_gets_the_real_arm_experiment():
    c = resolve_config(read_config(overrides={"model.name": "planar-2"}))[0]
    m = model_from_config(c)
    tr = c["trajectory"]
    assert tr["kind"] == "fourier" and set(tr) == {"kind", "omega_f", "a", "b", "offset"}
    assert tr["omega_f"] == pytest.approx(2 * math.pi / arm.PERIOD)
    assert np.shape(tr["a"]) == (2, arm.HARMONICS)
    q0, dq0, _ = fourier_series([0.0], tr["omega_f"], tr["a"], tr["b"], tr["offset"])
    np.testing.assert_allclose(c["initial"]["q0"], q0[0], atol=1e-15)  # q(0) on q_d
    np.testing.assert_allclose(dq0[0], 0.0, atol=1e-12)                # Σ a = 0
    assert c["initial"]["dq0"] == [0.0, 0.0]
    # K_i = 2 max(1, M_ii(q0))
    M = np.empty((2, 2))
    m.functions.M(np.asarray(q0[0]), np.asarray(c["model"]["theta"]), M)
    np.testing.assert_allclose(c["controller"]["K"], 2 * np.maximum(1.0, np.diag(M)))
    # disturbance: the paper's frequencies, none a harmonic of omega_f
    d = c["disturbance"]
    np.testing.assert_allclose(d["omega"], [0.5 * math.pi, 0.05 * math.pi])
    harmonics = tr["omega_f"] * np.arange(1, arm.HARMONICS + 1)
    assert np.min(np.abs(np.subtract.outer(d["omega"], harmonics))) > 0.02
    # amplitude 0.4 of the largest torque along one period (inverse dynamics, own check)
    t = np.linspace(0, arm.PERIOD, 2001)
    q, dq, ddq = fourier_series(t, tr["omega_f"], tr["a"], tr["b"], tr["offset"])
    tau = np.array([m.inverse_dynamics(q[k], dq[k], ddq[k]) for k in range(t.size)])
    np.testing.assert_allclose(d["amplitude"], 0.4 * np.abs(tau).max(axis=0), rtol=2e-3)
    # the closed loop takes it: the reference is the Fourier block
    kw = closed_loop_kwargs(c, "none")
    assert kw["trajectory"].name == "trajectory"


def test_a_user_sinusoid_keeps_the_previous_rules():
    vec = [0.1, 0.2]
    c = resolve_config(read_config(overrides={"model.name": "planar-2", "initial.q0": vec,
                               "trajectory": {k: vec for k in ("amplitude", "omega", "phase", "offset")}}))[0]
    assert "kind" not in c["trajectory"] and c["controller"]["K"] == [2.0, 2.0]
    assert c["disturbance"]["amplitude"] == [7.5, 1.5]          # the paper's


def test_design_excites_every_parameter_and_keeps_the_margins():
    m = _Limited()
    d = arm.design_trajectory(m)
    assert d["rank"] == m.ntheta and d["cond"] < 1e3
    # an independent check of the rank: the regressor stacked at 400 other times
    t = np.linspace(0.05, 3 * arm.PERIOD, 400)
    q, dq, ddq = fourier_series(t, d["omega_f"], d["a"], d["b"], d["offset"])
    W = np.vstack([m.regressor(q[k], dq[k], dq[k], ddq[k]) for k in range(t.size)])
    assert np.linalg.matrix_rank(W) == m.ntheta
    lo, hi = m.position_limits.T
    half = 0.5 * (hi - lo) * arm.LIMIT_MARGIN
    assert np.all(q >= lo + half - 1e-12) and np.all(q <= hi - half + 1e-12)
    assert np.all(np.abs(dq) <= (1 - arm.LIMIT_MARGIN) * m.velocity_limits + 1e-12)
    # the effort cap: amplitude <= 0.2 effort
    dist = arm.design_disturbance(m, d)
    assert np.all(np.asarray(dist["amplitude"]) <= 0.2 * m.effort_limits + 1e-12)


def test_limit_violation_names_the_joint_and_the_time():
    m = _Limited()
    # joint 2 (lo -0.5): q_d,2 = 0.6 sin(t) reaches -0.5 first at t = π + asin(0.5/0.6)
    tr = {"amplitude": [0.1, 0.6], "omega": [1.0, 1.0], "phase": [0.0, 0.0], "offset": [0.0, 0.0]}
    with pytest.raises(arm.LimitError) as exc:
        arm.check_limits(m, tr, 10.0)
    msg = str(exc.value)
    assert "joint 2 ('j2')" in msg and "position limits [-0.5, 2]" in msg
    t_hit = float(msg.rsplit("t = ", 1)[1].split(" s")[0])
    assert t_hit == pytest.approx(math.pi + math.asin(0.5 / 0.6), abs=2 * math.pi / 200)
    arm.check_limits(m, tr, 3.0)                 # not reached before t_end = 3 s
    # velocity: joint 1 at 1.3 rad/s > 1.2 at t = 0
    tr_v = dict(tr, amplitude=[1.3, 0.1])
    with pytest.raises(arm.LimitError, match=r"velocity limit 1.2 rad/s .* joint 1 \('j1'\) at t = 0 s"):
        arm.check_limits(m, tr_v, 10.0)
    arm.check_limits(planar_arm(2), tr_v, 10.0)  # no limits: passes


def test_configured_reference_outside_the_limits_is_refused_before_the_run(tmp_path, fake_urdf):
    (tmp_path / "arm.urdf").write_text("<robot/>")
    ok = resolve_config(read_config(write(tmp_path, '[model]\nurdf = "arm.urdf"\n')))[0]   # the designed one
    assert ok["trajectory"]["kind"] == "fourier"
    a = np.array(ok["trajectory"]["a"]) * 3.0
    text = ('[model]\nurdf = "arm.urdf"\n[trajectory]\nkind = "fourier"\n'
            f'a = {a.tolist()}\n')
    with pytest.raises(ConfigError, match=r"\[trajectory\]: the reference trajectory leaves .* "
                                          r"at joint \d \('j\d'\) at t = "):
        resolve_config(read_config(write(tmp_path, text, "fast.toml")))[0]
    with pytest.raises(ConfigError, match="'trajectory.amplitude' is not a key of trajectory.kind = 'fourier'"):
        resolve_config(read_config(write(tmp_path, '[model]\nname = "planar-2"\n[trajectory]\nkind = "fourier"\n'
                                    'amplitude = [1.0, 1.0]\n', "mixed.toml")))[0]
    with pytest.raises(ConfigError, match="'trajectory.a' must have 2 rows"):
        resolve_config(read_config(write(tmp_path, '[model]\nname = "planar-2"\n[trajectory]\nkind = "fourier"\n'
                                    'a = [[0.1, 0.2]]\nb = [[0.1, 0.2]]\n', "rows.toml")))[0]


@pytest.mark.parametrize("law", ["none", "sigma-modification"])
def test_short_closed_loop_on_a_planar_arm(law):
    """The real-arm experiment of planar-2 runs 1.5 s on the default engine; the arm starts
    on its reference and stays near it."""
    from ivdrem.experiments.paper import run_law
    c = resolve_config(read_config(overrides={"model.name": "planar-2", "experiment.t_end": 1.5,
                               "experiment.laws": [law]}))[0]
    run = run_law(c, law, progress=False)
    r = run.response
    out = np.asarray(r.outputs)
    assert np.all(np.isfinite(out))
    lab = list(r.output_labels)
    e = out[[lab.index(f"e[{i}]") for i in range(2)]]
    assert np.max(np.abs(e[:, 0])) < 1e-12                     # q(0) = q_d(0)
    assert np.max(np.abs(e)) < 0.2                              # rad, over 1.5 s


# --------------------------------------------------------------------------- report
def _run_of(config, model=None):
    class Run:
        pass
    r = Run()
    r.config, r.theta = config, np.asarray(config["model"]["theta"], float)
    r.model = model_from_config(config) if model is None else model
    return r


def test_report_model_table_of_the_paper_arm():
    """The paper's Section 4: M = [[θ1 + 2θ2 c2, θ3 + θ2 c2], [., θ3]],
    G = [θ4 g c12 + θ5 g c1, θ4 g c12]: where each θ enters, read off by hand."""
    from ivdrem.reports.content import _model_table
    t = _model_table(_run_of(resolve_config(read_config())[0]))
    assert t.key == "model" and "two-link" in t.title and "nθ = 5" in t.title
    assert [r[1:] for r in t.rows] == [["θ1", "M11", "1.3"], ["θ2", "M11, M12", "0.28"],
                                       ["θ3", "M12, M22", "0.32"], ["θ4", "G1, G2", "0.4"],
                                       ["θ5", "G1", "1.4"]]


def test_report_model_table_takes_the_models_own_table():
    from ivdrem.reports.content import _model_table

    class WithTable(_Limited):
        parameter_names = ["a1", "b1", "a2", "b2"]

        def parameter_table(self):
            return [("a1", ["m1", "m2"]), ("b1", "I1"), ("a2", 0.5, "kg m", [(1.0, "mx2")]),
                    ("b2", 0.1, "kg m2", [(1.0, "I2")] + [(0.25, f"m{k}") for k in range(7)])]
    t = _model_table(_run_of(resolve_config(read_config(overrides={"model.name": "planar-2"}))[0], WithTable()))
    assert t.header[2] == "standard parameters it groups"
    assert [r[1:3] for r in t.rows] == [
        ["a1", "m1 + m2"], ["b1", "I1"], ["a2", "mx2"],
        ["b2", "I2 + 0.25 m0 + 0.25 m1 + 0.25 m2 + 0.25 m3 + 0.25 m4 + … (2 more)"]]
    from ivdrem.reports.content import _terms
    assert _terms([(1.0, "Izz1"), (0.9999999999999999, "Ixx2"), (-1.0, "Izz2"), (-0.5, "m")]) == "Izz1 + Ixx2 − Izz2 − 0.5 m"
    assert _terms([(-1.0, "my2"), (0.316, "m3")]) == "−my2 + 0.316 m3"


# --------------------------------------------------------------------------- named arms
def _arm_available(name):
    try:
        models.get_model(name)
    except ImportError:          # the URDF package (the `arms` extra) is not installed
        return False
    return True


ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("name, ntheta", [("panda", 43), ("ur5", 36)])
def test_example_of_a_named_arm_loads_inside_its_limits(name, ntheta):
    if not _arm_available(name):
        pytest.skip(f"arm {name!r} not available (ivdrem.models / the arms extra)")
    c = resolve_config(read_config(ROOT / "examples" / f"{name}.toml"))[0]
    m = model_from_config(c)
    assert (m.ntheta, c["trajectory"]["kind"]) == (ntheta, "fourier")
    d = arm.design_trajectory(m)
    assert d["rank"] == ntheta                       # every base parameter excited
    t = np.linspace(0.0, arm.PERIOD, 5001)
    q, dq, _ = fourier_series(t, d["omega_f"], d["a"], d["b"], d["offset"])
    lo, hi = np.asarray(m.position_limits, float).T
    assert np.all(q >= lo) and np.all(q <= hi)
    assert np.all(np.abs(dq) <= np.asarray(m.velocity_limits, float))
    assert np.all(np.asarray(c["disturbance"]["amplitude"])
                  <= arm.EFFORT_FRACTION * np.asarray(m.effort_limits, float) + 1e-12)
    np.testing.assert_allclose(c["initial"]["q0"], q[0], atol=1e-14)


@pytest.mark.slow
def test_short_closed_loop_on_the_panda():
    """1 s of law `none` on the Panda (the compile of its 7-DoF loop dominates)."""
    if not _arm_available("panda"):
        pytest.skip("arm 'panda' not available (ivdrem.models / the arms extra)")
    from ivdrem.experiments.paper import run_law
    c = resolve_config(read_config(ROOT / "examples" / "panda.toml",
                    overrides={"experiment.t_end": 1.0, "experiment.laws": ["none"]}))[0]
    r = run_law(c, "none", progress=False).response
    out = np.asarray(r.outputs)
    assert np.all(np.isfinite(out))
    lab = list(r.output_labels)
    e = out[[lab.index(f"e[{i}]") for i in range(7)]]
    assert np.max(np.abs(e[:, 0])) < 1e-12 and np.max(np.abs(e)) < 0.3


def test_a_real_urdf_file_relative_to_the_config(tmp_path):
    """A URDF written by others (example-robot-data's UR5), copied next to the
    configuration, with the from_urdf options."""
    try:
        src = models.urdf.arm_urdf("ur5")
    except ImportError:
        pytest.skip("example-robot-data (the arms extra) is not installed")
    (tmp_path / "robots").mkdir()
    (tmp_path / "robots" / "ur5.urdf").write_bytes(Path(src).read_bytes())
    (tmp_path / "cfg").mkdir()
    p = write(tmp_path / "cfg", '[model]\nurdf = "../robots/ur5.urdf"\nfriction = "viscous"\n'
                                '[experiment]\nt_end = 5.0\nlaws = ["none"]\n')
    c = resolve_config(read_config(p))[0]
    m = model_from_config(c)
    assert (m.n, m.ntheta) == (6, 36 + 6)              # 36 base parameters + viscous friction
    assert c["trajectory"]["kind"] == "fourier" and len(c["model"]["theta"]) == 42
    with pytest.raises(ConfigError, match="config key 'model.joints'.*no_such_joint.*shoulder_pan_joint"):
        resolve_config(read_config(p, overrides={"model.joints": ["no_such_joint"]}))[0]


def test_fmu_export_model_help_names_every_model():
    from ivdrem.cli.fmu import _parser
    action = next(a for a in _parser()._subparsers._group_actions[0].choices["export"]._actions
                  if "--model" in a.option_strings)
    for name in models.model_names():
        assert name in action.help


def test_validate_config_alone_checks_the_limits(tmp_path, fake_urdf):
    """A study validates varied configurations with validate_config: the limits too."""
    from ivdrem.experiments.config import validate_config
    (tmp_path / "arm.urdf").write_text("<robot/>")
    c = resolve_config(read_config(write(tmp_path, '[model]\nurdf = "arm.urdf"\n')))[0]
    c["trajectory"]["offset"] = [1.4, 0.0]             # joint 1's upper limit is 1.5 rad
    with pytest.raises(ConfigError, match=r"joint 1 \('j1'\) at t = "):
        validate_config(c)


def test_window_is_a_common_period_of_reference_and_disturbance():
    """design_window: the shortest common period of ω_f and the disturbance's frequencies of
    at least 20 s (40 s for the design: reference period 10 s, disturbance on the π/20 rad/s
    grid); none for incommensurate frequencies or a sinusoid reference; the configuration
    takes it for both windowed laws unless the user sets T."""
    c = resolve_config(read_config(overrides={"model.name": "planar-2"}))[0]
    tr, d = c["trajectory"], c["disturbance"]
    assert arm.design_window(tr, d) == pytest.approx(40.0)
    assert c["iv_drem"]["T"] == pytest.approx(40.0)
    assert c["composite_learning"]["T"] == pytest.approx(40.0)
    for w in [tr["omega_f"]] + list(d["omega"]):          # a whole number of cycles each
        assert w * 40.0 / (2 * math.pi) == pytest.approx(round(w * 40.0 / (2 * math.pi)), abs=1e-9)
    detuned = dict(d, omega=[1.037 * w for w in d["omega"]])
    assert arm.design_window(tr, detuned) is None
    fast = dict(d, omega=[tr["omega_f"] * 2.5, tr["omega_f"] * 1.5])   # period 4 s: 20 s
    assert arm.design_window(tr, fast) == pytest.approx(20.0)
    assert arm.design_window(tr, fast, t_min=25.0) == pytest.approx(40.0)   # next multiple
    off = dict(d, amplitude=[d["amplitude"][0], 0.0])      # a zero sinusoid does not count
    assert arm.design_window(tr, off) == pytest.approx(20.0)
    assert arm.design_window({"amplitude": [1, 1], "omega": [1, 2], "phase": [0, 0],
                              "offset": [0, 0]}, d) is None
    user = resolve_config(read_config(overrides={"model.name": "planar-2", "iv_drem.T": 25.0}))[0]
    assert user["iv_drem"]["T"] == 25.0 and user["composite_learning"]["T"] == pytest.approx(40.0)
    assert resolve_config(read_config())[0]["iv_drem"]["T"] == 20.0                              # the paper's


def test_over_a_common_period_the_instrument_is_blind_to_the_disturbance():
    """Why the window is a common period: the extension (15a)'s disturbance part
    ∫_{t-T}^t ζ w ds (W of (16) before the averaging; KA3's integral (19)) vanishes once the
    window is full, while over T = 20 s it does not.  ζ of (14) and w of (13) integrated
    here by their exact first-order-hold updates along the reference (no closed loop)."""
    c = resolve_config(read_config(overrides={"model.name": "planar-2"}))[0]
    from scipy.integrate import trapezoid
    m = model_from_config(c)
    tr, d = c["trajectory"], c["disturbance"]
    n, nth, l, dt = m.n, m.ntheta, 50.0, 2e-3
    t = np.arange(0.0, 100.0 + dt / 2, dt)
    q, dq, ddq = fourier_series(t, tr["omega_f"], tr["a"], tr["b"], tr["offset"])
    Phi = np.empty((t.size, n, nth))
    for k in range(t.size):
        m.functions.Phi(q[k], dq[k], dq[k], ddq[k], Phi[k])
    taud = np.asarray(d["amplitude"]) * np.sin(np.outer(t, d["omega"]))
    e = math.exp(-l * dt)
    b2 = 1.0 - (1.0 - e) / (l * dt)

    def filt(X):                       # x' = l (u - x), u linear between samples
        Z = np.zeros_like(X)
        for k in range(1, X.shape[0]):
            Z[k] = e * Z[k - 1] + (1 - e) * X[k - 1] + b2 * (X[k] - X[k - 1])
        return Z

    Z, w = filt(Phi), filt(-taud)
    g = np.einsum("tja,tj->ta", Z, w)                 # ζ w, the integrand of (15a)
    G = np.einsum("tja,tjb->tab", Z, Z)               # ζ ζ^T: the excitation's scale
    end = t.size - 1

    def window(X, T):
        k0 = end - int(round(T / dt))
        return trapezoid(X[k0:], dx=dt, axis=0)

    scale = np.linalg.norm(window(G, 40.0))
    assert np.linalg.norm(window(g, 40.0)) <= 1e-10 * scale    # measured 2.8e-16
    assert np.linalg.norm(window(g, 20.0)) >= 1e-2 * scale     # measured 0.068
