"""The stepper's functions compiled without reference counts (``NO_REFCOUNT`` in
ivdrem.sim._template and _diagram) neither take nor drop a reference.

A count taken and never released keeps an array alive for ever; one dropped frees it under
the caller.  The check: every array the simulator hands to compiled code has the same
reference count before and after a run that goes through every path (Rosenbrock and
explicit steps, max-hold probes and commits, the delay history, outputs)."""
import sys

import numpy as np
import pytest
from numba import njit

from ivdrem.diagrams import closed_loop
from ivdrem.sim import _diagram, _template
from ivdrem.sim.simulator import Simulator


def _arrays(sim):
    return [a for a in sim.W if isinstance(a, np.ndarray)] + [sim.engine.P]


@njit(cache=False, _nrt=True)    # (explicit: a callee inherits an unset _nrt from its caller)
def _field(tup):
    return tup[0]                 # a new reference to the caller ...


@njit(cache=False, _nrt=False)
def _drops_the_reference(tup):
    return _field(tup)[0]         # ... which a caller without reference counts never drops


@njit(cache=False, _nrt=True)
def _entry(tup):
    # counted, like integrate (arrays from Python get their counts only in counted code)
    return _drops_the_reference(tup)


def test_the_check_sees_a_reference_taken_and_not_released():
    """The counts below would notice the mistake NO_REFCOUNT must avoid: a function
    without reference counts calling one that returns an array."""
    a = np.zeros(3)
    tup = (a,)
    _entry(tup)                               # (compiling takes references of its own)
    before = sys.getrefcount(a)
    _entry(tup)
    assert sys.getrefcount(a) == before + 1


@pytest.mark.parametrize("law, method, t_end", [("composite-learning", "rodas5p", 22.0),
                                                ("iv-drem", "dp45", 3.0),
                                                ("iv-drem", "rodas5p", 25.0)])
@pytest.mark.parametrize("stepper", ["numba", "c"])
def test_a_run_leaves_every_count_as_it_was(law, method, t_end, stepper, monkeypatch):
    monkeypatch.setenv("IVDREM_STEPPER", stepper)
    sim = Simulator(closed_loop(law), method=method)
    assert sim.engine.stepper == stepper
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
        assert d[_template.S_PROBES] > 0 and d[_template.S_EXPLICIT] > 0
        assert np.isfinite(sim.W.hold_time).all()


def test_declared_functions_are_compiled_so(monkeypatch):
    """The numba stepper module compiles exactly the declared functions without reference
    counts and inlines the declared ones (Drake-style: test the declarations)."""
    monkeypatch.setenv("IVDREM_STEPPER", "numba")
    sim = Simulator(closed_loop("iv-drem"))
    mod = sim.engine.module
    no_rc = set(_template.NO_REFCOUNT) | set(_diagram.NO_REFCOUNT)
    inline = set(_template.INLINE) | set(_diagram.INLINE)
    for name in mod._JIT:
        opts = getattr(mod, name).targetoptions
        assert opts["_nrt"] is (name not in no_rc), name
        assert opts["inline"] == ("always" if name in inline else "never"), name
    # integrate only allocates the loop's work arrays: plain Python, calling the loop
    for name in _template.PYTHON_LEVEL:
        assert name not in mod._JIT and not hasattr(getattr(mod, name), "targetoptions")
    assert "step_loop" in mod._JIT and "step_loop" in no_rc
    # what allocates keeps its counts
    for name in ("integrate", "diagram_jacobian", "fd_jacobian"):
        assert name not in no_rc


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
