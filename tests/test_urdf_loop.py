"""A URDF arm in the paper's closed loop: ``closed_loop("none", arm("panda"), ...)`` builds
and simulates 0.5 s on the default (compiled) engine, the arm tracking its reference."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pinocchio")

from ivdrem.models import arm  # noqa: E402
from ivdrem.models import urdf as urdf_mod  # noqa: E402


@pytest.mark.slow
def test_panda_in_the_closed_loop():
    try:
        urdf_mod.arm_urdf("panda")
    except ImportError:
        pytest.skip("arms extra missing")
    from ivdrem.diagrams.closed_loop import closed_loop
    from ivdrem.sim.simulator import simulate
    m = arm("panda")
    n = m.n
    mid = np.mean(m.position_limits, axis=1)
    traj = dict(amplitude=[0.3] * n, omega=[1.0 + 0.1 * i for i in range(n)], phase=[0.0] * n,
                offset=list(mid))
    dist = dict(amplitude=[1.0] * n, omega=[2.0] * n, phase=[0.0] * n, offset=[0.0] * n)
    d = closed_loop("none", m, trajectory=traj, disturbance=dist, q0=list(mid),
                    theta_hat0=np.asarray(m.theta_values) * 0.9)
    res = simulate(d, np.linspace(0.0, 0.5, 11))
    assert res.stats["engine"] == "compiled"
    q = res.outputs[[res.output_labels.index(f"q[{i}]") for i in range(n)]]
    e = res.outputs[[res.output_labels.index(f"e[{i}]") for i in range(n)]]
    assert np.all(np.isfinite(res.outputs))
    assert np.allclose(q[:, 0], mid)
    # tracking: the error stays well below the reference's amplitude
    assert np.max(np.abs(e)) < 0.1, np.max(np.abs(e), axis=1)
