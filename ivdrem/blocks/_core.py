"""The block framework: one kernel pair per subsystem, two ways to run it.

A block is declared once, Drake style: its input, output and state ports with their sizes,
its parameters, and two *kernels*, plain functions written in the numba-compatible subset
of Python::

    update(t, x, u, dx, *params)   # writes dx/dt into dx        (blocks with states)
    output(t, x, u, y, *params)    # writes the outputs into y   (pure, cheap)
    jacobian(t, x, u, jac, *params)  # optional: d(y, dx)/d(x, u), dense (see BlockSpec)

With ``named_ports=True`` (every library block) ``x``, ``u``, ``dx`` and ``y`` carry the
declared states and ports by name (``u.q``, ``x.Phi_f``, ``dx.Phi_f``, ``y.Pi``), each a
1-D float64 view into the engine's flat vector; a size-1 port is a 1-element view
(``u.mu[0]``), matrix-valued signals are flat row-major (``u.Pi.reshape((n, ntheta))``).
No kernel computes offsets.  The reference path passes namedtuples of views; the compiled
path compiles the kernel's flat form, each ``u.q`` a view ``u[a:b]`` made once at the top
of the kernel with the offsets from the declaration (:mod:`ivdrem.blocks._ports`: numba's
namedtuple arguments would cost about as much as the kernels themselves).  Without
``named_ports`` (the default, for adapters of foreign blocks and the FMU plant) the
kernels get the flat vectors; ``jacobian`` kernels always do.  The kernels hold no state
of their own: the state lives in the simulator.  Kernels that need the robot model call it
through the global name
``model`` (``model.Phi_M(q, a, out)``, see :mod:`ivdrem.models`); jacobian kernels too, for
the regressors' generated derivatives (``model.Phi_jac(q, dq, v, dv, out)``).

:func:`make_block` wraps a declaration as a python-control ``NonlinearIOSystem`` (the
reference path: python-control evaluates the kernels in Python), and attaches the
declaration as ``sys.ivdrem`` so that :mod:`ivdrem.sim.compiled` can generate one
numba function for a whole diagram from the same kernels (the compiled path).

Two special kinds of block are fed by the simulator rather than by their kernels:
``delay`` (a transport delay, output = input T seconds ago, from the simulator's dense
history) and ``maxhold`` (output = input at the accepted step that maximised a score).
python-control cannot simulate them; their nlsys output functions say so.
"""
from __future__ import annotations

import threading
import types
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import control as ct

from . import _ports

__all__ = ["BlockSpec", "make_block", "kernel_args", "bind_model", "ParameterError",
           "active_feeds", "flat_kernel", "port_layout"]


class ParameterError(ValueError):
    """A block parameter has a bad value or shape; the message names it."""


@dataclass
class BlockSpec:
    """Declaration of one block: ports, state, parameters and kernels."""
    name: str
    inputs: list            # [(signal name, size)], in kernel order
    outputs: list           # [(signal name, size)]
    states: list            # [(state name, size)]
    x0: np.ndarray
    param_names: tuple      # kernel parameter order (after the fixed arguments)
    output: Callable | None
    update: Callable | None = None
    direct: tuple = ()      # input ports the outputs depend on (direct feedthrough)
    model: object = None    # EulerLagrangeModel whose functions the kernels call
    kind: str = "ode"       # "ode", "delay" or "maxhold"
    validate: Callable | None = None   # params dict -> normalised params dict
    info: dict = field(default_factory=dict)  # kind-specific data (delay T, ...)
    # structural constants passed to the kernels like parameters (sizes, flags); not
    # python-control params, which share one namespace across a whole diagram
    constants: dict = field(default_factory=dict)
    # optional analytic Jacobian kernel jacobian(t, x, u, jac, *params) writing the dense
    # local Jacobian jac[(ny + nx), (nx + nu)]: rows outputs then state derivatives,
    # columns states then inputs.  jac is 0 only at the entries the probe found structural
    # (the only ones read): a kernel sets or adds into those, and writes every one of them
    # that it sets.  Without it the compiled path differentiates the block's update/output
    # kernels by differences (ivdrem.sim.jacobian)
    jacobian: Callable | None = None
    # update/output receive namedtuples of views by port name (ivdrem.blocks._ports)
    # instead of flat vectors; jacobian kernels stay flat
    named_ports: bool = False
    # {port or state name: field name in the kernel's namedtuples}, for ports whose signal
    # name the factory takes as an argument (sliding_window's prefix, ...): the kernel
    # reads u.g whatever the diagram calls that signal
    kernel_names: dict = field(default_factory=dict)
    # set by make_block for a named-port block: {"update": fn, "output": fn} as written;
    # spec.update / spec.output then hold their flat form (see _compile_named_ports)
    named_kernels: dict | None = None

    @property
    def ninputs(self):
        return sum(s for _, s in self.inputs)

    @property
    def noutputs(self):
        return sum(s for _, s in self.outputs)

    @property
    def nstates(self):
        return sum(s for _, s in self.states)

    def port_slices(self, which):
        """{port name: slice} into the flat input ("inputs") or output vector."""
        out, i = {}, 0
        for name, size in getattr(self, which):
            out[name] = slice(i, i + size)
            i += size
        return out


# which declared ports each kernel argument views, by kernel role
_ROLE_PORTS = {"update": ("states", "inputs", "states"), "output": ("states", "inputs", "outputs")}


def port_layout(spec: BlockSpec, role: str):
    """[(field names, [(port name, size)])] for the x, u and out arguments of kernel `role`
    of a named-port block; None for a flat block or the jacobian kernel."""
    if not spec.named_ports or role not in _ROLE_PORTS:
        return None
    out = []
    for which in _ROLE_PORTS[role]:
        ports = getattr(spec, which)
        out.append(([spec.kernel_names.get(p, p) for p, _ in ports], ports))
    return out


def _compile_named_ports(spec: BlockSpec):
    """Keep a named-port block's kernels as written (``spec.named_kernels``, run on
    namedtuples of views by the reference path) and put their flat form in
    ``spec.update`` / ``spec.output``: what the compiled path and the Jacobian's sparsity
    probe call (ivdrem.blocks._ports.flat_form: each ``u.q`` a view ``u[a:b]``)."""
    if not spec.named_ports or spec.named_kernels:
        return
    named = {"update": spec.update, "output": spec.output}
    for role, fn in named.items():
        if fn is not None:
            try:
                setattr(spec, role, _ports.flat_form(fn, role, port_layout(spec, role)))
            except _ports.PortError as exc:
                raise ParameterError(f"block '{spec.name}': {exc}") from None
    spec.named_kernels = named


def check_named_ports(spec: BlockSpec):
    """Clear errors for port names a namedtuple cannot carry (named-port blocks)."""
    if spec.named_ports:
        for which in ("inputs", "outputs", "states"):
            ports = [(spec.kernel_names.get(p, p), s) for p, s in getattr(spec, which)]
            _ports.check_port_names(spec.name, which[:-1], ports)


def flat_kernel(spec: BlockSpec, role: str):
    """Kernel `role` of `spec` as a Python callable of flat vectors,
    ``f(t, x, u, out, *params)``, with its model bound.  A named-port kernel runs as
    written, on namedtuples of views built here (the reference path and the tests; the
    compiled path and the Jacobian's sparsity probe use its flat form, ``spec.<role>``)."""
    named = spec.named_kernels.get(role) if spec.named_kernels else None
    layout = port_layout(spec, role)
    if named is None or layout is None:
        return bind_model(getattr(spec, role), spec.model)
    fn = bind_model(named, spec.model)
    (cx, px), (cu, pu), (co, po) = [(_ports.port_class(f), p) for f, p in layout]
    views = _ports.views

    def flat(t, x, u, out, *params):
        return fn(t, views(cx, px, x), views(cu, pu, u), views(co, po, out), *params)
    flat.__name__ = f"flat_{fn.__name__}"
    flat.__wrapped__ = fn
    return flat


def _labels(ports):
    labels = []
    for name, size in ports:
        labels += [f"{name}[{i}]" for i in range(size)]
    return labels


def kernel_args(spec: BlockSpec, params: dict) -> tuple:
    """The kernel's parameter arguments from a python-control params dict.

    Floats become Python floats, integer-valued ints stay ints, arrays become
    C-contiguous float64 arrays, so that the compiled path sees stable numba types.
    """
    args = []
    for name in spec.param_names:
        if name in spec.constants:
            args.append(spec.constants[name])
            continue
        if name not in params:
            raise ParameterError(f"block '{spec.name}': parameter '{name}' is missing")
        v = params[name]
        if isinstance(v, (bool, np.bool_)):
            raise ParameterError(f"block '{spec.name}': parameter '{name}' must be a number")
        if np.ndim(v) == 0:
            args.append(float(v))
        else:
            args.append(np.ascontiguousarray(v, dtype=np.float64))
    return tuple(args)


def effective_params(sys, diagram=None, params=None) -> dict:
    """The params a block sees in a diagram (python-control's merge order)."""
    local = dict(sys.params)
    if diagram is not None:
        local.update(diagram.params)
    if params:
        local.update(params)
    return local


def bind_model(fn, model):
    """Return ``fn`` with its global name ``model`` bound to the model's functions."""
    if fn is None or model is None:
        return fn
    g = dict(fn.__globals__)
    g["model"] = model.functions
    return types.FunctionType(fn.__code__, g, fn.__name__, fn.__defaults__, fn.__closure__)


# Feeds for delay / max-hold blocks during a reference-path simulation: the simulator
# registers, per block spec id, a callable t -> output vector.  Thread-local so that two
# simulations in two threads do not see each other's history.
_feeds = threading.local()


def active_feeds() -> dict:
    if not hasattr(_feeds, "d"):
        _feeds.d = {}
    return _feeds.d


def make_block(spec: BlockSpec, params: dict | None = None) -> ct.NonlinearIOSystem:
    """Wrap a block declaration as a python-control nonlinear I/O system."""
    params = dict(params or {})
    if spec.validate is not None:
        params = spec.validate(params)
    kernel_args(spec, params)          # fail now, not inside a simulation
    x0 = np.asarray(spec.x0, dtype=float).reshape(-1)
    if x0.size != spec.nstates:
        raise ParameterError(f"block '{spec.name}': initial state has {x0.size} entries, "
                             f"expected {spec.nstates}")
    spec.x0 = x0
    check_named_ports(spec)
    _compile_named_ports(spec)

    upd_k = flat_kernel(spec, "update")
    out_k = flat_kernel(spec, "output")
    nx, ny = spec.nstates, spec.noutputs
    # python-control passes the merged (system + diagram + call) params; re-validate only
    # when they differ from the block's own, so the common case stays cheap.
    cache = {"params": None, "args": None}

    def args_of(p):
        if p is not cache["params"]:
            if spec.validate is not None and p is not params:
                p2 = spec.validate(dict(p))
            else:
                p2 = p
            cache["args"] = kernel_args(spec, p2)
            cache["params"] = p
        return cache["args"]

    if spec.kind == "ode":
        def updfcn(t, x, u, p):
            dx = np.zeros(nx)
            upd_k(t, np.ascontiguousarray(x, float), np.ascontiguousarray(u, float), dx,
                  *args_of(p))
            return dx

        def outfcn(t, x, u, p):
            y = np.zeros(ny)
            out_k(t, np.ascontiguousarray(x, float), np.ascontiguousarray(u, float), y,
                  *args_of(p))
            return y
        upd = updfcn if nx else None
    else:
        sid = id(spec)

        def outfcn(t, x, u, p):
            feed = active_feeds().get(sid)
            if feed is None:
                raise RuntimeError(
                    f"block '{spec.name}' is a {'TransportDelay' if spec.kind == 'delay' else 'MaxHold'}:"
                    " python-control cannot simulate it (it needs the simulator's history of "
                    "accepted steps). Use ivdrem.sim.simulate(diagram, t_end) instead of "
                    "ct.input_output_response.")
            return feed(t)
        upd = None

    sys = ct.nlsys(upd, outfcn, inputs=_labels(spec.inputs), outputs=_labels(spec.outputs),
                   states=_labels(spec.states) if nx else None, params=params, name=spec.name)
    sys.ivdrem = spec
    return sys
