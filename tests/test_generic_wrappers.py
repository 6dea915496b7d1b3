"""Generic kernel wrappers: the blocks without a robot model get one C-callable wrapper for
every size, their sizes, port bounds, parameter slots and scalar constants read at run
time from a header in P (ivdrem.sim.compiled: generic_block, _header); a block with a
model keeps the wrapper specialised to its arm.

Checked: the wrapper text is the same for the paper's 2-link arm and planar-3 (and a
model block's is not); one compiled wrapper gives, bit for bit, what the wrapper
specialised to the block's sizes gives, and what the kernel's reference path gives, on
both arms; a constant port index out of range is still refused when the source is
generated; two instances of one block at different sizes run in one diagram.
"""
from __future__ import annotations

import sys
import warnings

import numpy as np
import pytest

import ivdrem.blocks as block_library
from ivdrem._native_call import call_c
from ivdrem.blocks import BlockSpec, make_block
from ivdrem.blocks._core import ParameterError, flat_kernel, kernel_args, effective_params
from ivdrem.blocks._ports import PortError, flat_form
from ivdrem.diagrams import assemble, closed_loop
from ivdrem.models import get_model
from ivdrem.sim import compiled, simulate
from ivdrem.sim.plan import DiagramPlan

# the planar-3 experiment (benchmarks/bench_arms.py: planar_experiment(3))
PI = np.pi
PLANAR3 = dict(trajectory=dict(amplitude=[0.4 * PI, 0.3 * PI, 0.2 * PI],
                               omega=[1.0, 1.3, 1.7], phase=[0.0, PI / 2, 0.0],
                               offset=[0.2 * PI, 0.3 * PI, 0.0]),
               disturbance=dict(amplitude=[7.5, 1.5, 0.5], omega=[0.5, 0.7, 0.9],
                                phase=[0.0] * 3, offset=[0.0] * 3),
               q0=[0.0, 0.3 * PI, 0.0], dq0=[0.0] * 3)
#: blocks whose wrappers the compile-and-call test imports (cheap to compile, and the heavy
#: ones of the extended regression: the averaging and the extension)
CALLED = ("tracking_error", "control_law", "adaptation_law", "extension",
          "window_integrator", "averaging", "term_start", "drem_term")


def _plans():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        two = closed_loop("iv-drem")
        three = closed_loop("iv-drem", get_model("planar-3"),
                            gains={"gamma": 1.0, "mixing": "paper"},
                            theta_hat0=np.zeros(get_model("planar-3").ntheta), **PLANAR3)
    return [DiagramPlan.from_diagram(d, None, None) for d in (two, three)]


@pytest.fixture(scope="module")
def plans():
    return _plans()


def _wrapper_sources(plan):
    mods = compiled.kernel_modules(plan)
    src = dict(mods.deps)
    return {(name, role): src[w] for name, role, w in mods.wrappers}, mods


def test_wrapper_source_is_the_same_for_every_size(plans):
    (two, _), (three, _) = [_wrapper_sources(p) for p in plans]
    generic = {b.sys.name for b in plans[0].blocks if compiled.generic_block(b)}
    model_blocks = {b.sys.name for b in plans[0].blocks
                    if b.spec.kind == "ode" and b.spec.model is not None}
    assert {"averaging", "extension", "mixing", "control_law", "adaptation_law"} <= generic
    assert {"plant", "torque_observer", "regression_filter", "instrument"} <= model_blocks
    sizes = {p.blocks[0].sys.nstates for p in plans}
    assert len(sizes) == 2                      # the two arms differ in size
    same = [k for k in two if k[0] in generic]
    assert len(same) >= 15
    for k in same:
        assert two[k] == three[k], k
        assert "for every size" in two[k]
    # a model block's wrapper is its arm's: literal sizes, its own text per arm
    for k in two:
        if k[0] in model_blocks:
            assert two[k] != three[k], k
            assert "for every size" not in two[k]


def _call(address, t, x, u, out, p):
    return call_c(address, (float(t), x.ctypes.data, u.ctypes.data, out.ctypes.data,
                            p.ctypes.data))


def test_one_generic_wrapper_gives_the_specialised_and_reference_results(plans):
    rng = np.random.default_rng(7)
    addresses = {}
    for plan in plans:
        forms = {}
        for generic in (True, False):
            slots, P = compiled._param_layout(plan, generic=generic)
            mods = compiled.kernel_modules(plan, slots)
            keep = [(n, r, w) for n, r, w in mods.wrappers if n in CALLED]
            deps = compiled._with_imports([w for _, _, w in keep], mods.deps)
            compiled._load_kernels([(n, s) for n, s in mods.deps if n in set(deps)])
            forms[generic] = mods, P
        for b in plan.blocks:
            if b.sys.name not in CALLED:
                continue
            assert compiled.generic_block(b)
            params = effective_params(b.sys, plan.diagram, plan.params)
            args = kernel_args(b.spec, params)
            x = rng.standard_normal(b.sys.nstates)
            u = rng.standard_normal(b.sys.ninputs)
            ny, nx, nu = b.sys.noutputs, b.sys.nstates, b.sys.ninputs
            for role in ("output", "update", "jacobian"):
                if (b.index, role) not in forms[True][0].windex:
                    continue
                shape = {"output": (ny,), "update": (nx,),
                         "jacobian": (ny + nx, nx + nu)}[role]
                got = {}
                for generic, (mods, P) in forms.items():
                    w = mods.wrappers[mods.windex[(b.index, role)]][2]
                    addr = sys.modules[w].wrapper.address
                    if generic:
                        addresses.setdefault((b.sys.name, role), set()).add(w)
                    out = np.zeros(shape)
                    assert _call(addr, 0.83, x, u, out, P[mods.pbase[b.index]:]) == 0
                    got[generic] = out
                ref = np.zeros(shape)
                flat_kernel(b.spec, role)(0.83, x, u, ref, *args)
                assert np.array_equal(got[True], got[False]), (b.sys.name, role)
                np.testing.assert_array_equal(got[True], ref, err_msg=f"{b.sys.name} {role}")
    # one wrapper module (one compile) for both arms
    for key, mods in addresses.items():
        assert len(mods) == 1, key


def _indexing_output(t, x, u, y, k):
    # a named-port kernel reading u.a at constant indices
    y.b[0] = u.a[2] + k * u.a[-1]


def test_constant_index_out_of_range_is_refused_at_generation():
    layout = [([], []), (["a"], [("a", 3)]), (["b"], [("b", 1)])]
    fn = flat_form(_indexing_output, "output", layout, runtime_offsets=True)
    y = np.zeros(1)
    # the bounds (x: 0; u: 0, 3; y: 0, 1) are arguments; -1 counts from the port's end
    fn(0.0, np.zeros(0), np.array([1.0, 2.0, 5.0]), y, 0, 0, 3, 0, 1, 10.0)
    assert y[0] == 5.0 + 10.0 * 5.0
    # the same source for another size, the index checked against each layout
    bigger = [([], []), (["a"], [("a", 4)]), (["b"], [("b", 1)])]
    assert flat_form(_indexing_output, "output", bigger, runtime_offsets=True) is fn
    small = [([], []), (["a"], [("a", 2)]), (["b"], [("b", 1)])]
    with pytest.raises(PortError, match=r"index 2 out of range for u.a \(size 2\)"):
        flat_form(_indexing_output, "output", small, runtime_offsets=True)
    spec = BlockSpec(name="too_small", inputs=[("a", 2)], outputs=[("b", 1)], states=[],
                     x0=np.zeros(0), param_names=("k",), output=_indexing_output,
                     named_ports=True)
    with pytest.raises(ParameterError, match="too_small.*index 2 out of range"):
        make_block(spec, {"k": 1.0})


def const_source_output(t, x, u, y, c):
    for i in range(c.shape[0]):
        y[i] = c[i]


def _const_source(values, name):
    values = np.asarray(values, float)
    # c a constant (python-control's params share one namespace across a diagram): an
    # array constant travels in P
    spec = BlockSpec(name=name, inputs=[], outputs=[(f"{name}_y", values.size)], states=[],
                     x0=np.zeros(0), param_names=("c",), output=const_source_output,
                     constants={"c": values})
    return make_block(spec, {})


def test_two_sizes_of_one_block_in_one_diagram():
    c2, c5 = np.array([1.0, -2.0]), np.array([0.5, 1.5, -3.0, 4.0, 2.5])
    blocks = [_const_source(c2, "source_a"), _const_source(c5, "source_b"),
              block_library.averaging(2, p=2.0, F0=1.0, input="source_a_y", output="avg_a",
                                      name="averaging_a"),
              block_library.averaging(5, p=2.0, F0=1.0, input="source_b_y", output="avg_b",
                                      name="averaging_b")]
    d = assemble(blocks, ["avg_a", "avg_b"], name="two_sizes")
    plan = DiagramPlan.from_diagram(d, None, None)
    mods = compiled.kernel_modules(plan)
    by_block = {}
    for name, role, w in mods.wrappers:
        by_block.setdefault(role, {})[name] = w
    # one wrapper module per role for both sizes
    assert by_block["update"]["averaging_a"] == by_block["update"]["averaging_b"]
    assert by_block["output"]["averaging_a"] == by_block["output"]["averaging_b"]
    r = simulate(d, 2.0, method="rodas5p", rtol=1e-10, atol=1e-12, engine="compiled",
                 t_eval=np.linspace(0.0, 2.0, 9), progress=False)
    t = np.asarray(r.time)
    labels = [s.split("[")[0] for s in r.output_labels]
    assert labels.count("avg_a") == 2 and labels.count("avg_b") == 5
    rows = {n: np.asarray(r.outputs)[[i for i, m in enumerate(labels) if m == n]]
            for n in ("avg_a", "avg_b")}
    # Y(t) = c t^p / (t^p + F0) for a constant input c and Y(0) = 0 (15b)
    exact2 = c2[:, None] * (t ** 2 / (t ** 2 + 1.0))
    exact5 = c5[:, None] * (t ** 2 / (t ** 2 + 1.0))
    np.testing.assert_allclose(rows["avg_a"], exact2, rtol=0, atol=1e-8)
    np.testing.assert_allclose(rows["avg_b"], exact5, rtol=0, atol=1e-8)
