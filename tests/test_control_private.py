"""python-control's private evaluation, as ivdrem.sim._control uses it, pinned to the
supported release: rerun on a python-control upgrade before widening the pin."""
import numpy as np
import pytest
import control as ct

from ivdrem.sim import _control
from ivdrem.sim.simulator import simulate


def _diagram():
    """A two-block loop with parameters: dx/dt = -k x + u, u = g * y (y = x)."""
    plant = ct.nlsys(lambda t, x, u, p: -p["k"] * x + u, lambda t, x, u, p: x,
                     inputs="u", outputs="y", states="x", params={"k": 1.0}, name="plant")
    gain = ct.nlsys(None, lambda t, x, u, p: p["g"] * u, inputs="e", outputs="v",
                    params={"g": 0.5}, name="gain")
    return ct.interconnect([plant, gain], connections=[["plant.u", "gain.v"],
                                                       ["gain.e", "plant.y"]],
                           outlist=["plant.y"], outputs=["y"], name="loop")


def test_supported_version():
    assert _control.control_version_supported(), (
        f"python-control {ct.__version__} is not one ivdrem.sim._control is checked "
        f"against ({', '.join(_control.SUPPORTED_CONTROL)})")
    for name in ("_rhs", "_out", "_compute_static_io", "_update_params"):
        assert callable(getattr(ct.InterconnectedSystem, name))
    for name in _control.BLOCK_FRAMES:
        assert callable(getattr(ct.NonlinearIOSystem, name))


def test_private_evaluation_equals_public_dynamics():
    d, public = _diagram(), _diagram()
    params = {"k": 3.0, "g": 2.0}
    pc = _control.PrivateDiagram(d, params)
    x, u = np.array([0.7]), np.zeros(0)
    # public API, by hand: dx/dt = -k x + g x
    assert pc.rhs(0.0, x, u) == pytest.approx(public.dynamics(0.0, x, u, params))
    assert pc.rhs(0.0, x, u)[0] == pytest.approx(-3.0 * 0.7 + 2.0 * 0.7)
    assert pc.out(0.0, x, u) == pytest.approx(public.output(0.0, x, u, params))
    # the caller's blocks keep their own parameters
    assert [s._current_params for s in d.syslist] == [{"k": 1.0}, {"g": 0.5}]


def test_reference_run_leaves_the_callers_diagram_alone():
    d = _diagram()
    before = [dict(s._current_params) for s in d.syslist]
    # x(t) = x0 exp((g - k) t)
    r = simulate(d, 0.5, engine="reference", params={"k": 3.0, "g": 2.0}, h=1e-3,
                 dt_out=0.5, x0=[1.0])
    assert r.states[0, -1] == pytest.approx(np.exp(-0.5), rel=1e-6)
    assert [dict(s._current_params) for s in d.syslist] == before
