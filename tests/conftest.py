"""Shared fixtures for tests/test_blocks.py and tests/test_sim.py.

The "lab" diagram feeds analytic signals into the sliding window, a plain (non-Hermite)
transport delay, the averaging filter and the max-hold, so that every output has a closed
form.  Its source block is declared here with module-level kernels (the compiled path
copies their source), using only ``np``.

Compile budget: every distinct diagram costs one numba compilation the first time (cached
on disk afterwards).  The tests use exactly four compiled diagrams: the lab diagram, the
observer lab of test_blocks.py, and closed_loop("iv-drem") / closed_loop("composite-learning")
with default arguments.  Parameter overrides (``params=``) and initial states do not change
the generated source, so they reuse the same compiled module.
"""
from __future__ import annotations

import functools
import signal

import numpy as np
import pytest

import ivdrem.blocks as block_library
from ivdrem.blocks import BlockSpec, make_block
from ivdrem.diagrams import assemble

# ----------------------------------------------------------------------------- lab source
LAB_OMEGA = 2.0          # g_0 = sin(omega t)
LAB_T = 0.7305           # window / delay length: not a multiple of any step used
LAB_NVEC, LAB_NMAT = 2, 2
LAB_DECAY = 0.3          # lambda(t) = exp(-0.3 t) sin(pi t) - 0.1
LAB_SKEW = 0.7           # antisymmetric part of A(t): max-hold must use the symmetric part


def lab_source_update(t, x, u, dx, omega, a_grow):
    # state "blow": d blow/dt = a_grow * blow, blow(0) = 1 (a_grow = 0 unless a test wants
    # a diverging run)
    dx[0] = a_grow * x[0]


def lab_source_output(t, x, u, y, omega, a_grow):
    # ext_g (3) = [sin(omega t), t^2, exp(-t/2) cos(3 t)]
    y[0] = np.sin(omega * t)
    y[1] = t * t
    y[2] = np.exp(-0.5 * t) * np.cos(3.0 * t)
    # mh_in (2 + 2*2) = [v, A], v = [t, sin t],
    # A = R(t) diag(lam, lam + 1) R(t)^T + [[0, k], [-k, 0]],  k = 0.7 t
    lam = np.exp(-0.3 * t) * np.sin(np.pi * t) - 0.1
    c = np.cos(t)
    s = np.sin(t)
    k = 0.7 * t
    y[3] = t
    y[4] = s
    y[5] = lam * c * c + (lam + 1.0) * s * s
    y[6] = -c * s + k
    y[7] = -c * s - k
    y[8] = lam * s * s + (lam + 1.0) * c * c
    # blow (1)
    y[9] = x[0]


def lab_source(omega=LAB_OMEGA, a_grow=0.0, name="lab_source"):
    spec = BlockSpec(name=name, inputs=[],
                     outputs=[("ext_g", 3), ("mh_in", LAB_NVEC + LAB_NMAT ** 2), ("blow", 1)],
                     states=[("blow", 1)], x0=np.ones(1), param_names=("omega", "a_grow"),
                     update=lab_source_update, output=lab_source_output)
    return make_block(spec, {"omega": omega, "a_grow": a_grow})


# analytic counterparts ----------------------------------------------------------------
def lab_g(t):
    t = np.asarray(t, float)
    return np.stack([np.sin(LAB_OMEGA * t), t * t, np.exp(-0.5 * t) * np.cos(3.0 * t)])


def lab_lambda(t):
    t = np.asarray(t, float)
    return np.exp(-LAB_DECAY * t) * np.sin(np.pi * t) - 0.1


def lab_mh_in(t):
    t = np.asarray(t, float)
    lam = lab_lambda(t)
    c, s, k = np.cos(t), np.sin(t), LAB_SKEW * t
    return np.stack([t, s, lam * c * c + (lam + 1) * s * s, -c * s + k, -c * s - k,
                     lam * s * s + (lam + 1) * c * c])


LAB_OUTPUTS = ["ext_g", "window_y", "window_I", "g_delayed", "avg", "held", "lambda_min_held",
               "blow"]


def lab_blocks():
    """lab source -> windowed integral (Hermite delay), plain delay, averaging, max-hold."""
    win, dly = block_library.windowed_integral(3, LAB_T, input="ext_g")
    return [lab_source(), win, dly,
            block_library.transport_delay(3, LAB_T, input="ext_g", output="g_delayed", name="plain_delay"),
            block_library.averaging(3, p=2.0, F0=1.0, input="ext_g", output="avg"),
            block_library.max_hold(LAB_NVEC, LAB_NMAT, 1e-9, input="mh_in", output="held")]


def build_lab():
    """The lab diagram of lab_blocks()."""
    return assemble(lab_blocks(), LAB_OUTPUTS, name="lab")


@pytest.fixture(scope="session")
def lab():
    return build_lab()


# ----------------------------------------------------------------------------- helpers
def sig(resp, name):
    """Rows of the signal `name` (all its indices) as a plain (k, nt) array."""
    labels = list(resp.output_labels)
    idx = [i for i, lab_ in enumerate(labels) if lab_.split("[")[0] == name]
    if not idx:
        raise KeyError(f"no output {name!r} in {labels}")
    return np.asarray(resp.outputs)[idx]


def state(resp, prefix):
    """Rows of the states whose label starts with `prefix` (e.g. 'torque_observer_Phi_f')."""
    labels = list(resp.state_labels)
    idx = [i for i, lab_ in enumerate(labels) if lab_.split("[")[0] == prefix]
    if not idx:
        raise KeyError(f"no state {prefix!r} in {labels}")
    return np.asarray(resp.states)[idx]


@functools.lru_cache(maxsize=None)
def paper_loop(law):
    """closed_loop(law) with default arguments (the diagrams other tests compile too)."""
    from ivdrem.diagrams import closed_loop
    return closed_loop(law)


@functools.lru_cache(maxsize=None)
def paper_run(law, t_end, method, engine, h=1e-3, rtol=1e-6, atol=1e-8, dt_out=0.01):
    """One cached simulation of paper_loop(law), shared by the tests of a session."""
    from ivdrem.sim import simulate
    return simulate(paper_loop(law), t_end, method=method, engine=engine, h=h, rtol=rtol,
                    atol=atol, dt_out=dt_out, progress=False)


@pytest.fixture(scope="module")
def plant_fmu(tmp_path_factory):
    """ivdrem's plant FMU of the 2-link arm (the controller loops close around it)."""
    from ivdrem.fmu import export_fmu
    from ivdrem.models import two_link
    return export_fmu(two_link(), tmp_path_factory.mktemp("plant") / "Plant.fmu")


@pytest.fixture
def ctrl_c_delivered():
    """Python's Ctrl-C handler for a test that sends itself SIGINT, also where the test
    process was started with SIGINT ignored: a shell's background job (``( pytest ... & )``
    in a script) inherits that, Python then installs no handler, and the SIGINT would be
    dropped while the long run it is meant to stop goes on for hours (reproduced so)."""
    before = signal.getsignal(signal.SIGINT)
    if before in (signal.SIG_IGN, signal.SIG_DFL, None):
        signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield
    finally:
        if before is not None:
            signal.signal(signal.SIGINT, before)
