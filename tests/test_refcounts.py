"""A run leaves the reference count of every array it hands to the stepper as it was.

A count taken and never released keeps an array alive for ever; one dropped frees it under
the caller.  The check: every array the simulator hands to the C stepper (the workspace,
P) has the same reference count before and after a run that goes through every path
(Rosenbrock and explicit steps, max-hold probes and commits, the delay history, outputs),
on the compiled engine (numba kernels called from C) and the reference engine
(python-control called back from C).  And the kernels' compiled form (inlined into their
wrappers)."""
import sys

import numpy as np
import pytest

from ivdrem.diagrams import closed_loop
from ivdrem.sim import _stepper_codes
from ivdrem.sim.simulator import Simulator


def _arrays(sim):
    return [a for a in sim.W if isinstance(a, np.ndarray)] + [sim.engine.P]


@pytest.mark.parametrize("law, method, t_end, engine", [
    ("composite-learning", "rodas5p", 22.0, "compiled"), ("iv-drem", "dp45", 3.0, "compiled"),
    ("iv-drem", "rodas5p", 25.0, "compiled"),
    ("iv-drem", "dp45", 3.0, "reference")])    # (python-control: ~100x slower per step)
def test_a_run_leaves_every_count_as_it_was(law, method, t_end, engine):
    sim = Simulator(closed_loop(law), method=method, engine=engine)
    assert sim.engine.stepper == "c"
    sim.advance(0.05)                                      # compiled, started
    arrays = _arrays(sim)
    history = {id(getattr(sim.W, f)) for f in ("hist_t", "hist_v", "hist_d", "hist_meta")}
    before = [sys.getrefcount(a) for a in arrays]
    stats0 = sim.stats.copy()
    sim.advance(t_end)
    kept = {id(a) for a in _arrays(sim)}     # (a history that grew is a new array)
    after = [sys.getrefcount(a) for a in arrays]
    assert [b for a, b in zip(arrays, before) if id(a) in kept] == \
           [b for a, b in zip(arrays, after) if id(a) in kept]
    assert {id(a) for a in arrays} - history <= kept    # all but a grown history compared
    d = sim.stats - stats0
    if law == "composite-learning":       # the paths the run was meant to cover
        assert d[_stepper_codes.S_PROBES] > 0 and d[_stepper_codes.S_EXPLICIT] > 0
        assert np.isfinite(sim.W.hold_time).all()


def test_kernels_are_inlined_into_their_wrappers_unless_they_raise():
    """Each block kernel is compiled inside its C-callable wrapper only (inline='always'),
    but a kernel with a raise of its own is compiled apart (numba cannot raise an exception
    with runtime arguments directly inside the wrapper's try)."""
    import re
    import sys as _sys
    sim = Simulator(closed_loop("iv-drem"))
    kernels = [_sys.modules[name] for name, _ in sim.engine.program.deps
               if name.startswith("ivdrem_kernel_")]
    assert len(kernels) > 10
    inlined = 0
    for mod in kernels:
        src = open(mod.__file__).read()
        fn_name = re.findall(r"^(\w+) = njit\(", src, flags=re.M)[-1]
        opts = getattr(mod, fn_name).targetoptions
        body = src.split(f"def {fn_name}(", 1)[1].split(f"\n{fn_name} = njit(", 1)[0]
        expect = "never" if re.search(r"\braise\b", body) else "always"
        assert opts["inline"] == expect, (fn_name, opts["inline"])
        inlined += expect == "always"
    assert inlined > 10
