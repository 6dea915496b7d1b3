"""Blocks ivdrem did not write: python-control's own systems in an ivdrem diagram.

Two things the simulator needs from every block are read here for a block without an
ivdrem declaration (``sys.ivdrem``, a :class:`~ivdrem.blocks.BlockSpec`):

* **direct feedthrough** (which inputs the outputs read at the same instant; the plan
  orders the blocks by it and finds algebraic loops with it): a ``StateSpace`` block
  (``ct.ss``, a ``ct.tf`` that ``ct.interconnect`` has turned into one, a summing junction,
  a gain) from the nonzero columns of D; a plain ``ct.nlsys`` from
  :func:`declare_feedthrough` if the user declared it, else probed numerically
  (:func:`probe_feedthrough`);
* **kernels for the compiled engine** (:func:`adapt_block`): a StateSpace block becomes a
  linear kernel pair with A, B, C, D as parameters (and its exact Jacobian
  [[C, D], [A, B]]); a plain nlsys whose update/output functions numba can compile is
  compiled (its source, with ``params["name"]`` read as a kernel parameter); any other
  nlsys is called back into Python through a C function pointer (``call_c``) while the
  rest of the loop stays compiled.

docs/simulation.md, "Blocks ivdrem did not write", says the same for users.
"""
from __future__ import annotations

import ast
import ctypes
import hashlib
import inspect
import math
import textwrap
import types
import warnings
from dataclasses import dataclass, field

import numpy as np
import control as ct

from ..blocks._core import BlockSpec

__all__ = ["declare_feedthrough", "direct_inputs", "probe_feedthrough", "adapt_block",
           "ForeignSpec", "PythonBlockNotice", "FEEDTHROUGH_ATTRIBUTE"]

#: attribute :func:`declare_feedthrough` sets on a system: a tuple of input indices
FEEDTHROUGH_ATTRIBUTE = "ivdrem_feedthrough"

#: seed of the feedthrough probe, so the same diagram always gets the same plan
PROBE_SEED = 20240


class PythonBlockNotice(UserWarning):
    """Some blocks of a compiled diagram run in Python (called back from the loop)."""


# --------------------------------------------------------------------------- feedthrough
def _input_indices(sys, inputs):
    """Input indices of `inputs`: labels ('tau[1]'), vector names ('tau' covers tau[0..]),
    or integer indices."""
    labels = list(sys.input_labels)
    out = set()
    for item in inputs:
        if isinstance(item, (int, np.integer)) and not isinstance(item, bool):
            if not 0 <= int(item) < len(labels):
                raise ValueError(f"declare_feedthrough: block '{sys.name}' has "
                                 f"{len(labels)} inputs, no input index {item}")
            out.add(int(item))
            continue
        if not isinstance(item, str):
            raise TypeError(f"declare_feedthrough: inputs are labels or indices, got {item!r}")
        hits = [i for i, lab in enumerate(labels)
                if lab == item or lab.split("[", 1)[0] == item]
        if not hits:
            raise ValueError(f"declare_feedthrough: block '{sys.name}' has no input "
                             f"{item!r}; its inputs are {labels}")
        out.update(hits)
    return tuple(sorted(out))


def declare_feedthrough(sys, inputs=()):
    """Declare which inputs of a plain nlsys its output function reads (direct feedthrough).

    `inputs` lists input labels (``"tau[1]"``), vector names (``"tau"`` covers every
    ``tau[i]``) or indices; ``[]`` (the default) declares that the outputs depend on the
    state and time only, as for a plant whose outputs are its states.  Without a
    declaration the simulator probes the output function numerically.  Returns `sys`.
    """
    if not _is_plain_nlsys(sys):
        raise TypeError("declare_feedthrough takes a ct.nlsys block (a StateSpace block's "
                        f"feedthrough is its D), got {type(sys).__name__}")
    if getattr(sys, "ivdrem", None) is not None:
        raise ValueError(f"block '{sys.name}' is an ivdrem block: its feedthrough is "
                         "BlockSpec.direct")
    if isinstance(inputs, str):
        inputs = [inputs]
    setattr(sys, FEEDTHROUGH_ATTRIBUTE, _input_indices(sys, inputs))
    return sys


def _is_plain_nlsys(sys):
    return (isinstance(sys, ct.NonlinearIOSystem)
            and not isinstance(sys, (ct.InterconnectedSystem, ct.StateSpace)))


def _output_function(sys):
    """f(t, x, u, params) -> outputs of a plain nlsys (None: the outputs are the states)."""
    if isinstance(sys, ct.NonlinearIOSystem) and getattr(sys, "outfcn", None) is not None:
        return sys.outfcn
    return None


def probe_feedthrough(sys, params=None, *, seed=PROBE_SEED, n_points=4):
    """Input indices that move some output of a plain nlsys, found numerically.

    The output function is evaluated at `n_points` random (t, x, u) points (fixed seed:
    the same block always gets the same answer); at each, one input at a time is moved
    to another random value, and an input that changes any output (by any amount) is
    marked direct.  A point where the function fails or returns non-finite values is
    replaced by another; if no point evaluates, every input is taken as direct (always
    correct, at worst a false algebraic loop, which :func:`declare_feedthrough` fixes).
    """
    nx, nu = sys.nstates, sys.ninputs
    fn = _output_function(sys)
    if nu == 0 or fn is None:
        return ()
    p = dict(sys.params) if params is None else dict(params)
    rng = np.random.default_rng(seed)
    direct = set()
    good = 0
    for _attempt in range(4 * n_points):
        if good >= n_points:
            break
        t = float(rng.uniform(0.1, 2.0))
        x = rng.uniform(0.2, 1.2, nx) * rng.choice([-1.0, 1.0], nx)
        u = rng.uniform(0.2, 1.2, nu) * rng.choice([-1.0, 1.0], nu)
        try:
            with np.errstate(all="ignore"):
                y0 = np.asarray(fn(t, x.copy(), u.copy(), p), dtype=float).reshape(-1)
                if not np.all(np.isfinite(y0)):
                    continue
                moved = set()
                for i in range(nu):
                    up = u.copy()
                    up[i] = u[i] + (0.5 + rng.uniform()) * max(1.0, abs(u[i]))
                    y1 = np.asarray(fn(t, x.copy(), up, p), dtype=float).reshape(-1)
                    if not np.all(np.isfinite(y1)):
                        raise ArithmeticError
                    if np.any(y1 != y0):
                        moved.add(i)
        except Exception:       # a user function refusing a random point: try another
            continue
        direct |= moved
        good += 1
    if good == 0:
        return tuple(range(nu))
    return tuple(sorted(direct))


def direct_inputs(sys, params=None):
    """Local indices of the inputs that block `sys`'s outputs read directly.

    ivdrem blocks: their declaration (``BlockSpec.direct``); StateSpace blocks: the nonzero
    columns of D; a plain nlsys: its :func:`declare_feedthrough` declaration, else
    :func:`probe_feedthrough`.  Any other kind of system: every input (conservative).
    """
    spec = getattr(sys, "ivdrem", None)
    if spec is not None:
        out = []
        sl = spec.port_slices("inputs")
        for port in spec.direct:
            out += list(range(sl[port].start, sl[port].stop))
        return tuple(sorted(out))
    if isinstance(sys, ct.TransferFunction):    # ct.interconnect turns it into this ss
        sys = ct.ss(sys)
    if isinstance(sys, ct.StateSpace):
        D = np.asarray(sys.D, dtype=float).reshape(sys.noutputs, sys.ninputs)
        return tuple(int(i) for i in np.flatnonzero(np.any(D != 0.0, axis=0)))
    declared = getattr(sys, FEEDTHROUGH_ATTRIBUTE, None)
    if declared is not None:
        return tuple(declared)
    if _is_plain_nlsys(sys):
        return probe_feedthrough(sys, params)
    return tuple(range(sys.ninputs))
