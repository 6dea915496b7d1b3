"""The compiled path: one numba module generated from a diagram, cached on disk.

The generator reads the diagram's subsystem list and connection map (through
:class:`~ivdrem.sim.plan.DiagramPlan`) and emits:

* imports of the robot models' functions (``model.source()``, generated from sympy) and of
  every block's own kernels (their source, unchanged), each in a cached module of its own
  shared by all diagrams that use it (so a second diagram compiles only its own code),
* the stepping template ``_template.py`` verbatim (the same code the reference path runs),
* ``diagram_eval``: block outputs in topological order of direct feedthrough, inputs
  gathered from the connection map, delay outputs from the history, max-hold outputs from
  the held values; then, by mode, the state derivatives, the after-step update of the
  history and holds, or the diagram outputs,
* ``diagram_jacobian`` (df/dx: each block differenced alone, or its own ``jacobian``
  kernel, chained through the connection map in the same order; sparsity probed at
  generation time, :mod:`ivdrem.sim.jacobian`) and ``newton_factor`` / ``newton_solve``
  (an LU of c I - J whose ordering and filled pattern are fixed at generation time,
  :mod:`ivdrem.sim.sparse_lu`, run by the shared kernels of :mod:`ivdrem.sim._jit_sparse`).

Nothing is fused by hand: a rewired diagram, another law or another robot model compiles
the same way.  A block without kernels (a plain nlsys) cannot be compiled; the error says
so and points to ``engine="reference"``.

Modules are written to ``$IVDREM_CACHE_DIR`` (default ``~/.cache/ivdrem``) under the hash
of their source, and numba caches their machine code beside them, so a second process
loads them without compiling.
"""
from __future__ import annotations

import hashlib
import importlib.util
import inspect
import os
import re
import sys
import textwrap
from pathlib import Path

import numpy as np

from .. import __version__
from ..blocks import _kernels
from .._atomic import write_text_atomic
from ..blocks._core import kernel_args
from . import _template
from .jacobian import JacobianProgram, generated_source as jacobian_source
from .sparse_lu import symbolic_lu
from .stepper import stepper_source, wrapper_source, TRAMPOLINES, BLOCK_RAISED
from .simulator import WORKSPACE_LAYOUT

_W = {name: i for i, (name, _, _) in enumerate(WORKSPACE_LAYOUT)}

__all__ = ["CompiledEngine", "generate_source", "cache_dir", "CompileError"]

# what a kernel may name besides its arguments: numpy, math, its robot model, the shared
# helpers, and call_c (C functions by address: FMU calls, Python callbacks)
_ALLOWED_GLOBALS = ({"np", "math", "model", "call_c"}
                    | {k for k in dir(_kernels) if not k.startswith("_")})
_modules = {}


class CompileError(ValueError):
    """A diagram that the compiled path cannot turn into numba code."""


def cache_dir() -> Path:
    d = os.environ.get("IVDREM_CACHE_DIR")
    if d:
        return Path(d)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "ivdrem"


def _kernel_source(fn, block_name, has_model):
    """Source of a block kernel, after checking it only uses what its module provides."""
    cv = inspect.getclosurevars(fn)
    if cv.nonlocals:
        raise CompileError(f"kernel {fn.__name__} of block '{block_name}' is a closure "
                           f"(uses {sorted(cv.nonlocals)}); kernels must be module-level functions")
    for g, val in cv.globals.items():
        if g not in _ALLOWED_GLOBALS:
            raise CompileError(
                f"kernel {fn.__name__} of block '{block_name}' uses the global {g!r}, which the "
                f"compiled path cannot see (allowed: np, math, model and ivdrem.blocks._kernels "
                f"helpers). Pass it as a parameter, or simulate with engine='reference'.")
        if g not in ("np", "math", "model", "call_c") and val is not getattr(_kernels, g, None):
            raise CompileError(f"kernel {fn.__name__} of block '{block_name}': global {g!r} "
                               "shadows an ivdrem.blocks._kernels helper")
    src = textwrap.dedent(inspect.getsource(fn))
    if not re.search(r"^def\s+" + re.escape(fn.__name__) + r"\s*\(", src, flags=re.M):
        raise CompileError(f"cannot read the source of kernel {fn.__name__} of block '{block_name}'")
    if not has_model and re.search(r"\bmodel\.", src):
        raise CompileError(f"kernel {fn.__name__} of block '{block_name}' calls model "
                           "functions but the block has no model")
    return src


_HEADER = ["import math", "import numpy as np", "from numba import njit",
           "from ivdrem.blocks._kernels import *", "from ivdrem.sim._native import call_c"]


def _model_module(model):
    """(module name, source) of a robot model's numeric functions."""
    src = model.source("")
    names = re.findall(r"^def\s+(\w+)\s*\(", src, flags=re.M)
    body = "\n".join([f"# Generated by ivdrem {__version__}: model {model.name}. Do not edit.",
                      *_HEADER, "", src, "",
                      f"for _n in {names!r}:",
                      "    globals()[_n] = njit(cache=True)(globals()[_n])", ""])
    return f"ivdrem_model_{_hash(body)}", body


def _kernel_module(fn, src, model_module):
    """(module name, source) of one block kernel, importing its model's module as `model`."""
    lines = [f"# Generated by ivdrem {__version__}: kernel {fn.__module__}.{fn.__qualname__}.",
             *_HEADER]
    if model_module is not None:
        lines.append(f"import {model_module} as model")
    lines += ["", src, "", f"{fn.__name__} = njit(cache=True)({fn.__name__})", ""]
    body = "\n".join(lines)
    return f"ivdrem_kernel_{_hash(body)}", body


def _hash(text):
    return hashlib.sha256(text.encode()).hexdigest()[:20]


def _i(v):
    """An integer argument of a generated helper call, typed int64 rather than as a literal:
    numba compiles a helper once per combination of literal arguments, once per call site."""
    return f"np.int64({int(v)})"


def _runs(pairs):
    """Group [(dst, src)] with unit gain into contiguous runs (dst0, src0, length)."""
    runs = []
    for d, s in pairs:
        if runs and runs[-1][0] + runs[-1][2] == d and runs[-1][1] + runs[-1][2] == s:
            runs[-1][2] += 1
        else:
            runs.append([d, s, 1])
    return runs


def _fill_inputs(plan, indices, ny, lines, ind="    "):
    """Emit us[k] = sum_j C[k, j] ys[j] (+ input_map u_ext) for the given input indices."""
    Cin = np.asarray(plan.diagram.input_map)
    simple, other = [], []
    for k in indices:
        srcs = plan.conn[k]
        ext = np.flatnonzero(Cin[k]) if Cin.size else []
        if len(srcs) == 1 and srcs[0][1] == 1.0 and len(ext) == 0:
            simple.append((k, srcs[0][0]))
        else:
            terms = [f"{g!r} * ys[{j}]" for j, g in srcs]
            terms += [f"{float(Cin[k, j])!r} * ue[{j}]" for j in ext]
            other.append(f"{ind}us[{k}] = " + (" + ".join(terms) if terms else "0.0"))
    for d, s, n in _runs(simple):
        if n == 1:
            lines.append(f"{ind}us[{d}] = ys[{s}]")
        else:
            lines.append(f"{ind}copy_into(us, {_i(d)}, ys, {_i(s)}, {_i(n)})")
    lines += other


def kernel_call(b, role, kernel, t, x, u, out, pargs):
    """Source of one call of block b's kernel `role` ("update", "output", "jacobian").

    `kernel` is the kernel's local name in the generated module; `x`, `u` and `out` are
    expressions for the block's flat state, input and output (or derivative, or local
    Jacobian) vectors; `pargs` the parameter arguments, each preceded by ", ".  Every
    kernel call of the generated code is built here, so the calling convention lives in
    one place.
    """
    return f"{kernel}({t}, {x}, {u}, {out}{pargs})"


_P_INDEX = re.compile(r"\bP\[(\d+)(?::(\d+))?\]")


def _relative_params(exprs):
    """(base, size, expressions on the block's own slice p) of a block's P expressions."""
    spans = [(int(a), int(b) if b else int(a) + 1) for e in exprs
             for a, b in _P_INDEX.findall(e)]
    if not spans:
        return 0, 0, list(exprs)
    base = min(a for a, _ in spans)
    size = max(b for _, b in spans) - base

    def rel(m):
        a = int(m.group(1)) - base
        return f"p[{a}:{int(m.group(2)) - base}]" if m.group(2) else f"p[{a}]"
    return base, size, [_P_INDEX.sub(rel, e) for e in exprs]


def _wrapper_module(b, role, kmod, fn_name, rel_exprs, npar):
    """(module name, source) of the C-callable wrapper of block b's kernel `role`.

    The wrapper takes pointers to the block's states, inputs, outputs (or derivatives, or
    local Jacobian) and parameters, so the diagram's code calls it by address: numba
    compiles each kernel once per block shape, cached, not again inside every diagram
    that uses it.  It returns 1 if the kernel raised (an exception cannot cross C).
    """
    nx, nu, ny = b.sys.nstates, b.sys.ninputs, b.sys.noutputs
    out_shape = {"output": f"({ny},)", "update": f"({nx},)",
                 "jacobian": f"({ny + nx}, {nx + nu})"}[role]
    pargs = "".join(", " + a for a in rel_exprs)
    call = kernel_call(b, role, "kernel", "t", "x", "u", "out", pargs)
    lines = [f"# Generated by ivdrem {__version__}: C-callable {role} kernel "
             f"{kmod}.{fn_name} (nx={nx}, nu={nu}, ny={ny}). Do not edit.",
             *_HEADER, "from numba import cfunc, carray",
             "from ivdrem.sim._native import float_pointer",
             f"from {kmod} import {fn_name} as kernel", "", "",
             '@cfunc("int32(float64, int64, int64, int64, int64)", cache=True)',
             "def wrapper(t, xp, up, outp, pp):",
             f"    x = carray(float_pointer(xp), ({nx},))",
             f"    u = carray(float_pointer(up), ({nu},))",
             f"    out = carray(float_pointer(outp), {out_shape})",
             f"    p = carray(float_pointer(pp), ({npar},))",
             "    try:", f"        {call}", "    except Exception:", "        return 1",
             "    return 0", ""]
    body = "\n".join(lines)
    return f"ivdrem_wrapper_{_hash(body)}", body


def generate_source(plan, param_exprs=None):
    """Source of the diagram module and of the model/kernel modules it imports.

    `param_exprs` is the first half of ``_param_layout(plan)``, if already computed.

    Returns (diagram source, [(module name, source), ...] in import order).  Kernels and
    model functions get modules of their own, shared by every diagram that uses them, so
    numba compiles each once (and caches it), not once per diagram.
    """
    _check_kernels(plan)
    d = plan.diagram
    ny = sum(b.sys.noutputs for b in plan.blocks)
    deps = {}                      # module name -> source, in dependency order
    kernels = {}                   # (module, qualname, model key) -> local name
    imports = []
    for b in plan.blocks:
        spec = b.spec
        if spec.kind != "ode":
            continue
        mmod = None
        if spec.model is not None:
            mmod, msrc = _model_module(spec.model)
            deps.setdefault(mmod, msrc)
        for role in ("update", "output", "jacobian"):
            fn = getattr(spec, role)
            if fn is None:
                continue
            kk = (fn.__module__, fn.__qualname__, spec.model.key if spec.model else None)
            if kk not in kernels:
                src = _kernel_source(fn, b.sys.name, spec.model is not None)
                kmod, ksrc = _kernel_module(fn, src, mmod)
                deps.setdefault(kmod, ksrc)
                kernels[kk] = kmod
    # playout: all parameters live in one flat float64 vector P (shapes are baked into the
    # code, the values are not: changing a gain does not recompile); structural constants
    # are literals
    playout = _param_layout(plan)[0] if param_exprs is None else param_exprs
    # every kernel of every block gets a C-callable wrapper (its own cached module) and an
    # index into the workspace field `kernels`, which holds the wrappers' addresses
    wrappers = []                  # [(block index, role, module name)], index = position
    windex = {}                    # (block index, role) -> index
    pbase = {}
    for b in plan.blocks:
        if b.spec.kind != "ode":
            continue
        base, npar, rel = _relative_params(playout[b.index])
        pbase[b.index] = base
        for role in ("output", "update", "jacobian"):
            fn = getattr(b.spec, role)
            if fn is None or (role == "update" and not b.sys.nstates):
                continue
            kmod = kernels[(fn.__module__, fn.__qualname__,
                            b.spec.model.key if b.spec.model else None)]
            wmod, wsrc = _wrapper_module(b, role, kmod, fn.__name__, rel, npar)
            deps.setdefault(wmod, wsrc)
            windex[(b.index, role)] = len(wrappers)
            wrappers.append((b.index, role, wmod))
    smod, ssrc = stepper_module()
    deps[smod] = ssrc
    out = [f"# Generated by ivdrem {__version__} from diagram {d.name!r}. Do not edit.",
           *_HEADER, *imports, "from numba import cfunc, carray",
           "from ivdrem.sim._native import float_pointer, int_pointer, element_address",
           "# the stepping template's helpers and constants (compiled once, shared)",
           f"from {smod} import *", ""]
    jit_names = []

    kf = _W["kernels"]

    fw = _W["failure"]

    def kcall(b, role, x, x0, u, u0, out, o0, ind):
        """Lines calling block b's kernel wrapper on x[x0:], u[u0:], out[o0:] (pointers);
        if it raised: record [wrapper index, t, the block's states] in W.failure (inline,
        not a call: a helper taking literal offsets would compile once per call site)."""
        j = windex[(b.index, role)]
        nx = b.sys.nstates
        return [f"{ind}if call_c(W[{kf}][{j}], (t, element_address({x}, {x0}), "
                f"element_address({u}, {u0}), element_address({out}, {o0}), "
                f"element_address(P, {pbase[b.index]}))) != 0:",
                f"{ind}    W[{fw}][0] = {j}", f"{ind}    W[{fw}][1] = t",
                f"{ind}    for _i in range({nx}):",
                f"{ind}        W[{fw}][2 + _i] = {x}[{x0} + _i]",
                f"{ind}    return BLOCK_RAISED"]

    def sl(s):
        return f"{s.start}:{s.stop}"

    # one function for the three modes (see _template): signals first, in topological order
    # of direct feedthrough, then the mode's work
    lines = ["def diagram_eval_body(mode, t, x, P, W, out):", "    ys = W[6]", "    us = W[7]",
             "    ue = W[8]", "    if mode == AFTER_STEP_EVALUATED:", "        mode = AFTER_STEP",
             "    else:"]
    body_start = len(lines)
    filled = set()
    for k in plan.order:
        b = plan.blocks[k]
        spec = b.spec
        direct = [int(i) for i in b.direct_inputs] if spec.kind == "ode" else []
        _fill_inputs(plan, direct, ny, lines)
        filled |= set(direct)
        if spec.kind == "ode":
            lines += kcall(b, "output", "x", b.x.start, "us", b.u.start, "ys", b.y.start, "    ")
        elif spec.kind == "delay":
            dl = next(x for x in plan.delays if x["block"] == k)
            lines.append(f"    hist_lookup(W, t - {playout[k][0]}, {_i(dl['off'])}, "
                         f"{_i(dl['size'])}, ys[{sl(b.y)}])")
        else:
            hd = next(x for x in plan.holds if x["block"] == k)
            y0 = b.y.start
            lines.append(f"    copy_into(ys, {_i(y0)}, W[4], {_i(hd['off'])}, {_i(hd['size'])})")
            lines.append(f"    ys[{y0 + hd['size']}] = W[5][{hd['k']}]")
    rest = [i for b in plan.blocks for i in range(b.u.start, b.u.stop) if i not in filled]
    _fill_inputs(plan, rest, ny, lines)
    if len(lines) == body_start:
        lines.append("        pass")
    else:   # the signal sweep sits under the else: above
        lines[body_start:] = ["    " + ln.replace("\n", "\n    ") for ln in lines[body_start:]]

    # mode RHS: state derivatives into out
    lines.append("    if mode == RHS:")
    n_upd = 0
    for b in plan.blocks:
        if b.spec.kind == "ode" and b.spec.update is not None and b.sys.nstates:
            lines += kcall(b, "update", "x", b.x.start, "us", b.u.start, "out", b.x.start,
                           "        ")
            n_upd += 1
    lines.append("        return OK")

    # mode AFTER_STEP: push the delay history, update the max-holds
    lines.append("    if mode == AFTER_STEP:")
    if plan.delays:
        lines += [f"        v = np.empty({plan.nd})", f"        dv = np.zeros({plan.nd})",
                  f"        est = np.zeros({plan.nd}, dtype=np.int64)"]
        tmax = []
        for dl in plan.delays:
            a, s = dl["off"], dl["size"]
            lines.append(f"        copy_into(v, {_i(a)}, us, {_i(dl['u'])}, {_i(s)})")
            if dl["hermite"]:
                lines.append(f"        copy_into(dv, {_i(a)}, us, {_i(dl['du'])}, {_i(s)})")
            else:
                lines.append(f"        for _i in range({a}, {a + s}):\n            est[_i] = 1")
            tmax.append(playout[dl["block"]][0])
        lines += ["        st = hist_push(W, t, v, dv, est)", "        if st != OK:",
                  "            return st",
                  f"        hist_trim(W, t - max({', '.join(tmax + ['0.0'])}))"]
    lines.append("        upd = 0")
    for hd in plan.holds:
        lines.append(f"        upd |= hold_update(W, {_i(hd['k'])}, {_i(hd['off'])}, "
                     f"{_i(hd['size'])}, {_i(hd['nvec'])}, {_i(hd['nmat'])}, us[{hd['u']}:{hd['u'] + hd['size']}], "
                     f"{playout[hd['block']][0]})")
    lines.append("        return HOLD_UPDATED if upd else OK")

    # mode RECORD: diagram outputs (output_map over [block outputs, block inputs])
    Om = np.asarray(d.output_map)
    for r in range(Om.shape[0]):
        terms = []
        for j in np.flatnonzero(Om[r]):
            src = f"ys[{j}]" if j < ny else f"us[{j - ny}]"
            g = float(Om[r, j])
            terms.append(src if g == 1.0 else f"{g!r} * {src}")
        lines.append(f"    out[{r}] = " + (" + ".join(terms) if terms else "0.0"))
    lines.append("    return OK")
    out.append("\n".join(lines) + "\n")
    # The template calls diagram_eval with its mode constants, which numba types as
    # literals and would compile the whole body once per mode; mode + 0 is a plain int64,
    # so the body compiles once and only this wrapper is specialised.
    out.append("def diagram_eval(mode, t, x, P, W, out):\n"
               "    return diagram_eval_body(mode + 0, t, x, P, W, out)\n")
    jit_names += ["diagram_eval_body", "diagram_eval"]

    # the Jacobian and Newton-matrix entry points of the implicit methods (df/dx of mode
    # RHS; factor / solve of c I - J); the template's dense fd_jacobian, dense_factor and
    # dense_solve stay available beside them
    prog = JacobianProgram(plan)
    slu = symbolic_lu(prog.pattern)
    calls = []
    for b in prog.fd_blocks:
        ny = b.sys.noutputs
        c_out = kcall(b, "output", "xb", 0, "ub", 0, "yf", 0, "            ",
                      )
        c_upd = []
        if b.spec.update is not None and b.sys.nstates:
            c_upd = kcall(b, "update", "xb", 0, "ub", 0, "yf", ny, "            ")
        calls.append((c_out, c_upd))
    supplied = []
    for b in prog.fd_blocks:
        if b.spec.jacobian is None:
            supplied.append(None)
        else:
            supplied.append(kcall(b, "jacobian", "xb", 0, "ub", 0, "jl", 0, "        "))
    out.append(jacobian_source(prog, slu, calls, supplied))
    jit_names += ["block_eval", "block_jacobian", "diagram_jacobian", "sparse_factor",
                  "sparse_solve", "newton_factor", "newton_solve"]

    out.append("# ---- compile everything with numba, machine code cached beside this file")
    out.append(f"_JIT = {sorted(set(jit_names))!r}")
    out.append("for _n in _JIT:\n    globals()[_n] = njit(cache=True)(globals()[_n])\n")
    out.append(wrapper_source())
    out.append("# the kernel wrappers, in the order of the workspace field `kernels`")
    out.append(f"KERNEL_WRAPPERS = {[(plan.blocks[k].sys.name, role, m) for k, role, m in wrappers]!r}")
    return "\n".join(out), list(deps.items())


_stepper = {}


def stepper_module():
    """(module name, source) of the shared stepper (ivdrem.sim.stepper), one per version
    of the template: every diagram module imports it instead of compiling its own."""
    if "src" not in _stepper:
        src = stepper_source()
        _stepper["src"] = (f"ivdrem_stepper_{_hash(src)}", src)
    return _stepper["src"]


def _param_values(plan, b):
    """The kernel arguments of block b, as _param_layout flattens them."""
    if b.spec.kind == "ode":
        return kernel_args(b.spec, plan.block_params(b))
    if b.spec.kind == "delay":
        return (float(next(x["T"] for x in plan.delays if x["block"] == b.index)),)
    return (float(next(x["eps"] for x in plan.holds if x["block"] == b.index)),)


def _check_kernels(plan):
    for b in plan.blocks:
        if b.spec is None:
            raise CompileError(f"block '{b.sys.name}' is a plain nlsys without ivdrem kernels; "
                               "the compiled path cannot run it. Use engine='reference' (slow "
                               "but general), or declare the block with ivdrem.blocks.BlockSpec.")


def _param_layout(plan):
    """The kernels' parameters in one flat float64 vector P.

    Returns ({block index: [argument expression]}, P): arrays and floats become slices or
    entries of P (with their shapes baked into the expressions), structural constants
    become literals.
    """
    _check_kernels(plan)
    exprs_by_block, values, off = {}, [], 0
    for b in plan.blocks:
        exprs = []
        names = b.spec.param_names if b.spec.kind == "ode" else ("p",)
        for name, v in zip(names, _param_values(plan, b)):
            if b.spec.kind == "ode" and name in b.spec.constants:
                exprs.append(repr(v))
                continue
            if np.ndim(v) > 2:
                raise CompileError(f"block '{b.sys.name}': parameter {name!r} has "
                                   f"{np.ndim(v)} dimensions; the compiled path takes <= 2")
            flat = np.asarray(v, float).reshape(-1)
            if np.ndim(v) == 0:
                exprs.append(f"P[{off}]")
            elif np.ndim(v) == 1:
                exprs.append(f"P[{off}:{off + flat.size}]")
            else:
                exprs.append(f"P[{off}:{off + flat.size}].reshape({np.shape(v)!r})")
            values.append(flat)
            off += flat.size
        exprs_by_block[b.index] = exprs
    P = np.concatenate(values) if values else np.zeros(0)
    return exprs_by_block, P


def _write(cdir, name, src):
    path = cdir / f"{name}.py"
    if not path.exists() or path.read_text() != src:
        write_text_atomic(path, src)   # a concurrent process never sees half a file
    return path


def _import(cdir, name, src):
    if name in sys.modules:
        return sys.modules[name]
    path = _write(cdir, name, src)
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    try:
        spec.loader.exec_module(mod)
    except BaseException:
        sys.modules.pop(name, None)
        raise
    return mod


def _load(src, deps):
    h = _hash(src)
    if h in _modules:
        return _modules[h]
    cdir = cache_dir()
    cdir.mkdir(parents=True, exist_ok=True)
    for name, dsrc in deps:            # models before the kernels that import them
        _import(cdir, name, dsrc)
    mod = _import(cdir, f"ivdrem_diagram_{h}", src)
    _modules[h] = mod
    return mod


class CompiledEngine:
    """Runs the generated module; same interface as the reference engine."""

    name = "compiled"

    def __init__(self, plan, params=None):
        self.plan = plan
        param_exprs, self.P = _param_layout(plan)
        self.source, self.deps = generate_source(plan, param_exprs)
        self.module = _load(self.source, self.deps)
        self.stepper = sys.modules[stepper_module()[0]]
        self.integrate = self.stepper.integrate
        self.wrappers = list(self.module.KERNEL_WRAPPERS)
        self.n_kernels = len(self.wrappers)
        self._fns = np.array([getattr(self.module, f"{n}_c").address for n in TRAMPOLINES],
                             dtype=np.int64)
        self._kernels = np.array([sys.modules[m].wrapper.address for _, _, m in self.wrappers],
                                 dtype=np.int64)

    def bind(self, W):
        """Put the addresses of this diagram's functions and kernels into workspace W."""
        W.fns[:] = self._fns
        W.kernels[:self.n_kernels] = self._kernels

    def failed_kernel(self, W):
        """(block name, kernel role, t) of the kernel that raised, from W.failure."""
        j, t = int(W.failure[0]), float(W.failure[1])
        name, role, _ = self.wrappers[j]
        return name, role, t

    def block_error(self, W):
        """The SimulationError for the kernel recorded in W.failure, with the block's own
        exception if re-running its Python function at the failing point reproduces it."""
        from .simulator import SimulationError
        name, role, t = self.failed_kernel(W)
        b = next(b for b in self.plan.blocks if b.sys.name == name)
        x = np.array(W.failure[2:2 + b.sys.nstates])
        u = np.array(W.us[b.u])
        what = {"output": "output", "update": "update (state derivative)",
                "jacobian": "Jacobian"}[role]
        head = f"block '{name}' raised in its {what} function at t = {t:.6g} s"
        fn = b.sys.outfcn if role != "update" else b.sys.updfcn
        try:
            fn(t, x, u, self.plan.block_params(b))
        except Exception as exc:      # the block's own error, re-raised from Python
            return SimulationError(f"{head}: {type(exc).__name__}: {exc}"), exc
        return SimulationError(f"{head} (compiled kernel; re-running it in Python at the "
                               "recorded states did not reproduce the error)"), None

    def _checked(self, st, W):
        if st == BLOCK_RAISED:
            err, cause = self.block_error(W)
            raise err from cause
        return st

    def after_step(self, t, x, W):
        return self._checked(
            self.module.diagram_eval(_template.AFTER_STEP, t, x, self.P, W, x), W)

    def record(self, t, x, W, row):
        self._checked(self.module.diagram_eval(_template.RECORD, t, x, self.P, W, row), W)

    def rhs(self, t, x, W):
        dx = np.zeros_like(x)
        self._checked(self.module.diagram_eval(_template.RHS, t, x, self.P, W, dx), W)
        return dx

    # ---- Jacobian and Newton matrix, callable from Python (tests, benchmarks)
    def jacobian(self, t, x, W, *, dense=False):
        """df/dx at (t, x) as the generated diagram_jacobian computes it (n x n array);
        dense=True: the whole-system forward-difference fallback fd_jacobian instead."""
        x = np.ascontiguousarray(x, dtype=float)
        J = np.zeros((x.size, x.size))
        fn = self.module.fd_jacobian if dense else self.module.diagram_jacobian
        st = fn(float(t), x, self.P, W, J)
        if st != _template.OK:
            raise RuntimeError(f"diagram_jacobian returned status {st}")
        return J

    def factor(self, J, c, *, dense=False):
        """Factor c I - J with the generated newton_factor (the static-pattern sparse LU),
        or with dense=True the partial-pivoting dense_factor: (status, LU, piv)."""
        J = np.ascontiguousarray(J, dtype=float)
        n = J.shape[0]
        LU = np.zeros((n, n))
        piv = np.zeros(n, dtype=np.int64)
        fn = self.module.dense_factor if dense else self.module.sparse_factor
        st = fn(J, float(c), LU, piv)
        return int(st), LU, piv

    def solve(self, LU, piv, b, *, dense=False):
        """(c I - J)^{-1} b for a factorisation from :meth:`factor` (b is not modified)."""
        out = np.array(b, dtype=float)
        fn = self.module.dense_solve if dense else self.module.sparse_solve
        fn(LU, piv, out)
        return out
