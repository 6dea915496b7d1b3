"""One generic suite for every law of the registry (ivdrem.laws), as tests/test_methods.py
is for the methods of the simulator.

Each test is parametrized over the registered laws (``law_names()``), so a new law is
covered by registering it: nothing here names a law.  Every law

* builds: its ``build`` returns blocks and the names of the outputs it records, and
  ``closed_loop`` wires them into the paper's loop;
* runs 0.1 s on both engines (RK4, h = 1 ms: the reference engine's python-control
  evaluation and the compiled engine's kernels): every output finite, the two equal to
  1e-12 of each signal's scale (a second evaluation path of the same loop; measured:
  bit-identical);
* records what it declares: the outputs its ``build`` names, ``Delta`` and ``calY`` where
  it says it has the mixed regression (17) (``uses_delta``), its ``instrument`` signal;
* keeps its own look in the figures: its own colour, its own (colour, line style) pair,
  and a line style of its own against any law whose colour has nearly the same grey.
* where it has a sampled form: each of its gains is an entry of the sampled controller's
  parameter table as its registry declaration (``Key``) says: size, unit, doc, structural
  or tunable (the table is made from the registry; nothing to add for a new law).

Its configuration section is checked from its registry entry in tests/test_laws.py.
"""
from __future__ import annotations

import numpy as np
import pytest

from ivdrem import laws as registry
from ivdrem.diagrams import closed_loop
from ivdrem.experiments.metrics import signal_names
from ivdrem.models import two_link
from ivdrem.sim import simulate

MODEL = two_link()
T_RUN = 0.1
LAWS = registry.law_names()


def _declared_outputs(law):
    """The outputs `law`'s build says it records, on the paper's arm with its defaults."""
    params = dict(registry.resolve_params(law, {}), l=50.0)
    blocks, outputs = law.build(registry.LawContext(MODEL, MODEL.n, MODEL.ntheta, params))
    assert blocks, law.name
    return outputs


@pytest.fixture(scope="module")
def runs():
    """{(law, engine): response} of 0.1 s, filled on first use."""
    return {}


def _run(runs, name, engine):
    if (name, engine) not in runs:
        runs[name, engine] = simulate(closed_loop(name, MODEL), T_RUN, method="rk4", h=1e-3,
                                      engine=engine, progress=False)
    return runs[name, engine]


@pytest.mark.parametrize("name", LAWS)
@pytest.mark.parametrize("engine", ["reference", "compiled"])
def test_runs_on_both_engines_and_records_its_outputs(runs, name, engine):
    law = registry.get_law(name)
    r = _run(runs, name, engine)
    assert r.stats["engine"] == engine
    assert r.time[-1] == pytest.approx(T_RUN)
    assert np.all(np.isfinite(np.asarray(r.outputs))), name
    names = set(signal_names(r))
    want = set(_declared_outputs(law)) | {"theta_hat", "tau", "q"}
    if law.uses_delta:
        want |= {"Delta", "calY"}
    if law.instrument:
        want.add(law.instrument)
    assert want <= names, (name, sorted(want - names))


@pytest.mark.parametrize("name", LAWS)
def test_the_engines_agree(runs, name):
    a, b = _run(runs, name, "reference"), _run(runs, name, "compiled")
    assert list(a.output_labels) == list(b.output_labels)
    A, B = np.asarray(a.outputs), np.asarray(b.outputs)
    scale = np.maximum(np.abs(A).max(axis=1), 1e-300)
    rel = np.abs(A - B).max(axis=1) / scale
    assert rel.max() <= 1e-12, (name, dict(zip(a.output_labels, rel)))
    # the law acts within 0.1 s: theta_hat moves away from theta_hat(0) = 0
    assert np.abs(A[[i for i, s in enumerate(a.output_labels) if s.startswith("theta_hat")],
                    -1]).max() > 0


def _grey(colour):
    r, g, b = (int(colour[i:i + 2], 16) / 255 for i in (1, 3, 5))
    return 0.299 * r + 0.587 * g + 0.114 * b


@pytest.mark.parametrize("name", LAWS)
def test_has_its_own_colour_and_line_style(name):
    """No other law has its colour; one whose colour prints nearly the same grey (within
    0.1) has another line style."""
    from ivdrem.reports.figures import law_color, law_label, law_linestyle
    law = registry.get_law(name)
    assert law_color(name) == law.color and law_linestyle(name) == law.linestyle
    assert law_label(name) == law.label and law.label
    for other in LAWS:
        if other == name:
            continue
        o = registry.get_law(other)
        assert o.color.lower() != law.color.lower(), (name, other)
        if abs(_grey(o.color) - _grey(law.color)) < 0.1:
            assert o.linestyle != law.linestyle, (name, other)


@pytest.mark.parametrize("name", registry.sampled_laws())
def test_its_gains_are_entries_of_the_sampled_controller_s_table(name):
    from ivdrem.controller.parameters import PARAMETERS
    law = registry.get_law(name)
    rows = {p.name: p for p in PARAMETERS}
    for gain in law.defaults:
        key = law.keys[gain]
        # a choice ("str", the mixing) is a coded entry of the table's own
        assert gain in rows, (name, gain)
        if key.kind not in registry.NUMERIC_KINDS:
            continue
        p = rows[gain]
        assert p.size == ("1" if key.kind != "vec" else key.length), (name, gain)
        assert (p.structural, p.tunable) == (key.structural, not key.structural), (name, gain)
        unit, doc = p.declared()
        # a gain several laws declare has their docs joined ("... (21) or (35)")
        assert unit == key.unit and key.doc and key.doc[:key.doc.rfind(" ")] in doc, (name, gain)
