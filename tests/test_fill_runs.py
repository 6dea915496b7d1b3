"""The block inputs filled by runs (ivdrem.sim.tables.with_fill_runs, the C stepper's
fill_runs, written out below) equal the row-by-row fill over the connection map, entry for entry,
for every fill sequence of the paper's loops and for a map with sums, unconnected rows,
diagram inputs and gains other than one."""
import numpy as np
import pytest

from ivdrem.diagrams import closed_loop
from ivdrem.sim import _diagram
from ivdrem.sim.simulator import Simulator
from ivdrem.sim.tables import _runs, with_fill_runs


def _fill_input(in_ptr, in_src, in_gain, k, ys, us, ue):
    """us[k] from the connection map's row k: the sum of gain * source (a source j >= 0 is
    block output ys[j], a negative one diagram input ue[-1 - j])."""
    s = 0.0
    for e in range(in_ptr[k], in_ptr[k + 1]):
        j = in_src[e]
        s += in_gain[e] * (ys[j] if j >= 0 else ue[-1 - j])
    us[k] = s


def _fill_runs(runs, gains, r0, r1, in_ptr, in_src, in_gain, ys, us, ue):
    """What the C stepper's fill_runs does with runs r0..r1-1: a run copies consecutive
    sources times its gain (0.0 + g y, as the row sum gives it), a RUN_ROW sums its row."""
    C = _diagram.N_RUN_COLUMNS
    for r in range(r0, r1):
        kind, d0, s0, n = (int(runs[r * C + c]) for c in (_diagram.RUN_KIND, _diagram.RUN_D0,
                                                           _diagram.RUN_S0, _diagram.RUN_N))
        if kind in (_diagram.RUN_SIGNALS, _diagram.RUN_INPUTS):
            src = ys if kind == _diagram.RUN_SIGNALS else ue
            for i in range(n):
                us[d0 + i] = 0.0 + gains[r] * src[s0 + i]
        else:
            _fill_input(in_ptr, in_src, in_gain, d0, ys, us, ue)


def _by_rows(seq, ptr, src, gain, ys, ue, nu):
    us = np.full(nu, np.nan)
    for k in seq:
        _fill_input(ptr, src, gain, int(k), ys, us, ue)
    return us


def _by_runs(seq, ptr, src, gain, ys, ue, nu):
    runs, gains = _runs(seq, ptr, src, gain)
    us = np.full(nu, np.nan)
    _fill_runs(np.asarray(runs, dtype=np.int64).reshape(-1), np.asarray(gains),
                       0, len(runs), ptr, src, gain, ys, us, ue)
    return us, len(runs)


@pytest.mark.parametrize("law", ["iv-drem", "composite-learning"])
def test_every_sequence_of_the_paper_loops(law):
    tb = Simulator(closed_loop(law)).engine.tables
    rng = np.random.default_rng(3)
    nu = tb.in_ptr.size - 1
    ys = rng.normal(size=tb.in_src.max() + 1)
    ue = rng.normal(size=4)
    B = tb.blocks
    seqs = [tb.fill_order[B[k, _diagram.B_FILL0]:B[k, _diagram.B_FILL1]] for k in range(len(B))]
    seqs += [tb.fill_rest, tb.probe_fill, tb.record_fill, tb.history_fill]
    n_entries = n_runs = 0
    for seq in seqs:
        a = _by_rows(seq, tb.in_ptr, tb.in_src, tb.in_gain, ys, ue, nu)
        b, nr = _by_runs(seq, tb.in_ptr, tb.in_src, tb.in_gain, ys, ue, nu)
        np.testing.assert_array_equal(a, b)
        n_entries += len(seq)
        n_runs += nr
    # the block inputs are wired as vectors: few runs (IV-DREM 295 entries, 27 runs)
    assert n_runs * 5 < n_entries
    # the tables the engine packed are these runs
    again = with_fill_runs(tb)
    np.testing.assert_array_equal(again.fill_runs, tb.fill_runs)
    assert tb.fill_run_ranges.size == 2 * len(B) + 8


def test_sums_unconnected_rows_inputs_and_gains():
    # rows: 0-2 from signals 4..6 (gain 2), 3 a sum, 4 unconnected, 5-6 from diagram
    # inputs 1..2, 7 from signal 7 with gain -1 (a new run), 8 from signal 0 (gain 1)
    rows = [[(4, 2.0)], [(5, 2.0)], [(6, 2.0)], [(1, 1.0), (2, -3.0)], [],
            [(-2, 1.0)], [(-3, 1.0)], [(7, -1.0)], [(0, 1.0)]]
    ptr, src, gain = [0], [], []
    for r in rows:
        for j, g in r:
            src.append(j)
            gain.append(g)
        ptr.append(len(src))
    ptr, src, gain = (np.asarray(ptr, dtype=np.int64), np.asarray(src, dtype=np.int64),
                      np.asarray(gain))
    rng = np.random.default_rng(4)
    ys, ue = rng.normal(size=8), rng.normal(size=3)
    ys[7] = 0.0                             # -1 * 0.0: the row sum gives +0.0
    for seq in (np.arange(9), np.array([8, 0, 1, 2, 7, 5, 6, 4, 3]), np.array([1, 2, 5])):
        a = _by_rows(seq, ptr, src, gain, ys, ue, 9)
        b, nr = _by_runs(seq, ptr, src, gain, ys, ue, 9)
        np.testing.assert_array_equal(a, b)
        assert np.array_equal(np.signbit(a), np.signbit(b))
    runs, gains = _runs(np.arange(9), ptr, src, gain)
    kinds = [r[0] for r in runs]
    assert runs[0] == [_diagram.RUN_SIGNALS, 0, 4, 3] and gains[0] == 2.0
    assert kinds.count(_diagram.RUN_ROW) == 2 and [_diagram.RUN_INPUTS, 5, 1, 2] in runs
