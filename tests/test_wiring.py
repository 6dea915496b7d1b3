"""Blocks wired by name with sparse maps (ivdrem.diagrams.wiring) against python-control's
``ct.interconnect`` of the same blocks, and the sparse maps' python-control face
(ivdrem.sim._control.SparseInterconnect, sparse_maps)."""
from __future__ import annotations

import copy

import numpy as np
import pytest
import control as ct
from scipy import sparse

from ivdrem.diagrams import closed_loop
from ivdrem.diagrams.closed_loop import assemble
from ivdrem.diagrams.wiring import NOT_PLAIN, wire_by_name
from ivdrem.models import planar_arm
from ivdrem.sim._control import MAP_NAMES, SparseInterconnect, sparse_maps


def _names(labels):
    """The signal names a diagram was assembled with, from its labels (q[0], q[1] -> q)."""
    return list(dict.fromkeys(lab.partition("[")[0] for lab in labels))


def _python_control(d):
    """python-control's own diagram of `d`'s blocks, wired by the same names."""
    return ct.interconnect(d.syslist, inputs=_names(d.input_labels),
                           outputs=_names(d.output_labels), name=d.name, check_unused=False)


@pytest.mark.parametrize("law, kw", [
    ("iv-drem", {}),
    ("composite-learning", {}),
    ("iv-drem", {"external_plant": True}),          # diagram inputs q, dq
    ("iv-drem", {"model": "planar-3", "gains": {"gamma": 1.0, "mixing": "eigen"}}),
])
def test_the_paper_loops_equal_python_controls_wiring(law, kw):
    kw = dict(kw)
    if "model" in kw:
        kw["model"] = planar_arm(int(kw["model"].split("-")[1]))
    d = closed_loop(law, **kw)
    assert isinstance(d, SparseInterconnect)
    ref = _python_control(d)
    assert type(ref) is ct.InterconnectedSystem
    for attr in ("input_labels", "output_labels", "state_labels", "params", "name",
                 "connection_type", "dt", "nstates"):
        assert getattr(d, attr) == getattr(ref, attr), attr
    for name, m in zip(MAP_NAMES, sparse_maps(d)):
        dense = getattr(ref, name)
        assert m.shape == dense.shape and np.array_equal(m.toarray(), dense), name
        # the sparse maps hold the dense maps' entries and nothing else
        assert m.nnz == np.count_nonzero(dense)


def test_names_summed_and_split_as_python_control_does():
    """A diagram output found in two blocks is their sum; a vector signal becomes one
    external signal per entry, named by the block's labels; a diagram input feeds every
    block input of its name."""
    a = ct.nlsys(lambda t, x, u, p: -x + u, lambda t, x, u, p: x, states=2,
                 inputs=["w[0]", "w[1]"], outputs=["y[0]", "y[1]"], name="a")
    b = ct.nlsys(None, lambda t, x, u, p: 2.0 * u, inputs=["y[0]", "y[1]", "w[0]", "w[1]"],
                 outputs=["z[0]", "z[1]", "s", "y2"], name="b")
    c = ct.nlsys(None, lambda t, x, u, p: u, inputs=["w[0]", "w[1]"], outputs=["s", "k"],
                 name="c")
    blocks = [a, b, c]
    d = wire_by_name(blocks, ["w"], ["y", "z", "s", "k"], name="sums")
    ref = ct.interconnect(blocks, inputs=["w"], outputs=["y", "z", "s", "k"], name="sums",
                          check_unused=False)
    assert d.input_labels == ref.input_labels == ["w[0]", "w[1]"]
    assert d.output_labels == ref.output_labels == ["y[0]", "y[1]", "z[0]", "z[1]", "s", "k"]
    for name, m in zip(MAP_NAMES, sparse_maps(d)):
        assert np.array_equal(m.toarray(), getattr(ref, name)), name
    assert sparse_maps(d)[2].toarray()[4].tolist().count(1.0) == 2    # s = b.s + c.s
    # the same dynamics, evaluated by python-control on both (the sparse diagram asks for
    # its dense maps here: python-control's evaluation reads them)
    x, u = np.array([0.3, -1.1]), np.array([0.7, 2.0])
    assert np.array_equal(d._rhs(0.5, x, u), ref._rhs(0.5, x, u))
    assert np.array_equal(d._out(0.5, x, u), ref._out(0.5, x, u))
    assert d._out(0.5, x, u)[4] == 2.0 * 0.7 + 0.7         # b.s = 2 w[0], c.s = w[0]


@pytest.mark.parametrize("inputs, outputs", [
    ([], ["nowhere"]),              # found nowhere: python-control's error
    ([], ["a"]),                    # a block's name
    ([], ["a.y"]),                  # a block-qualified name
    ([], ["-y"]),                   # a negated signal
    (["nowhere"], ["y"]),
])
def test_other_names_are_left_to_python_control(inputs, outputs):
    a = ct.nlsys(lambda t, x, u, p: -x, lambda t, x, u, p: x, states=1, inputs=0,
                 outputs="y", name="a")
    assert wire_by_name([a], inputs, outputs) is NOT_PLAIN
    try:
        want = ct.interconnect([a], inputs=inputs, outputs=outputs, check_unused=False)
    except (ValueError, IndexError) as exc:      # python-control's own error, as it words it
        with pytest.raises(type(exc)) as got:
            assemble([a], outputs, name="x", inputs=inputs)
        assert str(got.value) == str(exc)
    else:
        got = assemble([a], outputs, name="x", inputs=inputs)
        assert type(got) is ct.InterconnectedSystem
        assert np.array_equal(got.output_map, want.output_map)


def test_dense_maps_only_when_asked_and_then_as_python_controls():
    d = closed_loop("iv-drem")
    ref = _python_control(d)
    kept = d.__dict__["_connect_map"]
    assert sparse.issparse(kept)
    twin = copy.copy(d)
    # reading the attribute gives python-control's array, which is the map from then on
    dense = d.connect_map
    assert isinstance(dense, np.ndarray) and np.array_equal(dense, ref.connect_map)
    assert d.connect_map is dense
    dense[0, :] = 0.0                                  # written into, as python-control's
    assert sparse_maps(d)[0].nnz == kept.nnz - kept[[0]].nnz
    # the copy taken before keeps its own sparse map
    assert sparse.issparse(twin.__dict__["_connect_map"])
    assert np.array_equal(sparse_maps(twin)[0].toarray(), ref.connect_map)
    # python-control's setters keep what is given
    twin.set_output_map(ref.output_map * 2.0)
    assert np.array_equal(twin.output_map, 2.0 * ref.output_map)
    assert np.array_equal(sparse_maps(twin)[2].toarray(), 2.0 * ref.output_map)


def test_a_run_never_reads_the_dense_maps():
    """The simulator, the plan and the diagram checks read the maps sparse: after a run of
    the paper's loop the diagram still holds no dense map, and the run is the run of
    python-control's own diagram of the same blocks, bit for bit."""
    from ivdrem.sim import simulate
    d = closed_loop("iv-drem")
    ref = _python_control(d)
    a = simulate(d, 0.5, dt_out=0.1)
    b = simulate(ref, 0.5, dt_out=0.1)
    assert all(sparse.issparse(d.__dict__["_" + name]) for name in MAP_NAMES)
    assert np.array_equal(a.outputs, b.outputs) and np.array_equal(a.states, b.states)
    assert a.stats["steps"] == b.stats["steps"]


def test_a_shape_that_does_not_fit_the_blocks_is_refused():
    a = ct.nlsys(None, lambda t, x, u, p: u, inputs="u", outputs="y", name="a")
    with pytest.raises(ValueError, match="connect_map has shape"):
        SparseInterconnect([a], sparse.csr_array((2, 1)), sparse.csr_array((1, 0)),
                           sparse.csr_array((1, 2)), inputs=[], outputs=["y"])
