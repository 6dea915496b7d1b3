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
the same way.  A block ivdrem did not write (``ct.ss``, ``ct.tf``, a summing junction, a
plain ``ct.nlsys``) is turned into kernels first by :mod:`ivdrem.sim.foreign`: linear
kernels from its matrices, the user's own functions compiled by numba, or, when numba
cannot compile them, a call back into Python for that block alone (a
:class:`~ivdrem.sim.foreign.PythonBlockNotice` names those blocks).

Before each block call the generated code writes the block's index and the time into two
bookkeeping entries at the end of P, so that an exception raised inside a block (a numba
kernel's ``raise``, or a Python block's exception) is reported as a
:class:`BlockError` naming the block and the simulated time.

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
import warnings
from pathlib import Path

import numpy as np

from .. import __version__
from ..blocks import _kernels
from .._atomic import write_text_atomic
from ..blocks._core import effective_params, kernel_args
from . import _template
from .jacobian import JacobianProgram, generated_source as jacobian_source
from .sparse_lu import symbolic_lu
from . import foreign
from .simulator import SimulationError

__all__ = ["CompiledEngine", "generate_source", "cache_dir", "CompileError", "BlockError"]

# what a kernel may name besides its arguments: numpy, math, its robot model, the shared
# helpers, and call_c (C functions by address: FMU calls, Python callbacks)
_ALLOWED_GLOBALS = ({"np", "math", "model", "call_c"}
                    | {k for k in dir(_kernels) if not k.startswith("_")})
_modules = {}


class CompileError(ValueError):
    """A diagram that the compiled path cannot turn into numba code."""


class BlockError(SimulationError):
    """A block's own function raised during a run; the message names the block and the
    simulated time, the block's exception is chained (``__cause__``)."""


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


def _foreign_module(fname, src):
    """(module name, source) of a generated kernel source of ivdrem.sim.foreign: every
    function it defines compiled by numba."""
    names = re.findall(r"^def\s+(\w+)\s*\(", src, flags=re.M)
    lines = [f"# Generated by ivdrem {__version__}: kernel {fname} of a block ivdrem did not "
             "write.", *_HEADER, "", src, ""]
    lines += [f"{n} = njit(cache=True)({n})" for n in names] + [""]
    body = "\n".join(lines)
    return f"ivdrem_foreign_{_hash(body)}", body


def _kernel_key(spec, role):
    fn = getattr(spec, role)
    if isinstance(spec, foreign.ForeignSpec):
        return spec.kernel_key(role)
    return (fn.__module__, fn.__qualname__, spec.model.key if spec.model else None)


def _hash(text):
    return hashlib.sha256(text.encode()).hexdigest()[:20]


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
            lines.append(f"{ind}copy_into(us, {d}, ys, {s}, {n})")
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
            kk = _kernel_key(spec, role)
            if kk not in kernels:
                if isinstance(spec, foreign.ForeignSpec):
                    fname, src = spec.sources[role]
                    kmod, ksrc = _foreign_module(fname, src)
                else:
                    fname = fn.__name__
                    src = _kernel_source(fn, b.sys.name, spec.model is not None)
                    kmod, ksrc = _kernel_module(fn, src, mmod)
                deps.setdefault(kmod, ksrc)
                local = f"k{len(kernels)}_{fname}"
                kernels[kk] = local
                imports.append(f"from {kmod} import {fname} as {local}")
    out = [f"# Generated by ivdrem {__version__} from diagram {d.name!r}. Do not edit.",
           *_HEADER, *imports, ""]
    jit_names = []
    out.append("# ---- stepping template (ivdrem/sim/_template.py, verbatim)")
    tsrc = Path(_template.__file__).read_text()
    out.append(tsrc)
    jit_names += [n for n in re.findall(r"^def\s+(\w+)\s*\(", tsrc, flags=re.M)]

    def kname(b, role):
        return kernels[_kernel_key(b.spec, role)]

    # all parameters live in one flat float64 vector P (shapes are baked into the code, the
    # values are not: changing a gain does not recompile); structural constants are literals
    playout = _param_layout(plan)[0] if param_exprs is None else param_exprs
    nb = plan.param_size        # P[nb]: index of the block being called, P[nb + 1]: its t

    def mark(b, ind, with_t=False):
        line = f"{ind}P[{nb}] = {float(b.index)!r}"
        return line + (f"\n{ind}P[{nb + 1}] = t" if with_t else "")

    def pargs(b):
        return "".join(", " + a for a in playout[b.index])

    def sl(s):
        return f"{s.start}:{s.stop}"

    # one function for the three modes (see _template): signals first, in topological order
    # of direct feedthrough, then the mode's work
    lines = ["def diagram_eval_body(mode, t, x, P, W, out):", "    ys = W[6]", "    us = W[7]",
             "    ue = W[8]", f"    P[{nb + 1}] = t",
             "    if mode == AFTER_STEP_EVALUATED:", "        mode = AFTER_STEP", "    else:"]
    body_start = len(lines)
    filled = set()
    for k in plan.order:
        b = plan.blocks[k]
        spec = b.spec
        direct = [int(i) for i in b.direct_inputs] if spec.kind == "ode" else []
        _fill_inputs(plan, direct, ny, lines)
        filled |= set(direct)
        if spec.kind == "ode":
            lines.append(mark(b, "    "))
            lines.append("    " + kernel_call(b, "output", kname(b, "output"), "t",
                                             f"x[{sl(b.x)}]", f"us[{sl(b.u)}]",
                                             f"ys[{sl(b.y)}]", pargs(b)))
        elif spec.kind == "delay":
            dl = next(x for x in plan.delays if x["block"] == k)
            lines.append(f"    hist_lookup(W, t - {playout[k][0]}, {dl['off']}, "
                         f"{dl['size']}, ys[{sl(b.y)}])")
        else:
            hd = next(x for x in plan.holds if x["block"] == k)
            y0 = b.y.start
            lines.append(f"    copy_into(ys, {y0}, W[4], {hd['off']}, {hd['size']})")
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
            lines.append(mark(b, "        "))
            lines.append("        " + kernel_call(b, "update", kname(b, "update"), "t",
                                                 f"x[{sl(b.x)}]", f"us[{sl(b.u)}]",
                                                 f"out[{sl(b.x)}]", pargs(b)))
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
            lines.append(f"        copy_into(v, {a}, us, {dl['u']}, {s})")
            if dl["hermite"]:
                lines.append(f"        copy_into(dv, {a}, us, {dl['du']}, {s})")
            else:
                lines.append(f"        for _i in range({a}, {a + s}):\n            est[_i] = 1")
            tmax.append(playout[dl["block"]][0])
        lines += ["        st = hist_push(W, t, v, dv, est)", "        if st != OK:",
                  "            return st",
                  f"        hist_trim(W, t - max({', '.join(tmax + ['0.0'])}))"]
    lines.append("        upd = 0")
    for hd in plan.holds:
        lines.append(f"        upd |= hold_update(W, {hd['k']}, {hd['off']}, {hd['size']}, "
                     f"{hd['nvec']}, {hd['nmat']}, us[{hd['u']}:{hd['u'] + hd['size']}], "
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
    # P[nb] = -1 after a normal return: an exception outside any block is not blamed on one
    out.append("def diagram_eval(mode, t, x, P, W, out):\n"
               "    st = diagram_eval_body(mode + 0, t, x, P, W, out)\n"
               f"    P[{nb}] = -1.0\n"
               "    return st\n")
    jit_names += ["diagram_eval_body", "diagram_eval"]

    # the Jacobian and Newton-matrix entry points of the implicit methods (df/dx of mode
    # RHS; factor / solve of c I - J); the template's dense fd_jacobian, dense_factor and
    # dense_solve stay available beside them
    prog = JacobianProgram(plan)
    slu = symbolic_lu(prog.pattern)
    calls = []
    for b in prog.fd_blocks:
        nx, nu, ny = b.sys.nstates, b.sys.ninputs, b.sys.noutputs
        c_out = [mark(b, "            ", True),
                 "            " + kernel_call(b, "output", kname(b, "output"), "t",
                                                 f"xb[0:{nx}]", f"ub[0:{nu}]", f"yf[0:{ny}]",
                                                 pargs(b)),
                 f"            P[{nb}] = -1.0"]
        c_upd = []
        if b.spec.update is not None and nx:
            c_upd += [mark(b, "            ", True),
                      "            " + kernel_call(b, "update", kname(b, "update"), "t",
                                                         f"xb[0:{nx}]", f"ub[0:{nu}]",
                                                         f"yf[{ny}:{ny + nx}]", pargs(b)),
                      f"            P[{nb}] = -1.0"]
        calls.append((c_out, c_upd))
    supplied = []
    for b in prog.fd_blocks:
        if b.spec.jacobian is None:
            supplied.append(None)
        else:
            nx, nu = b.sys.nstates, b.sys.ninputs
            ny = b.sys.noutputs
            supplied.append([mark(b, "        ", True),
                             "        " + kernel_call(b, "jacobian", kname(b, "jacobian"), "t",
                                                         f"xb[0:{nx}]", f"ub[0:{nu}]",
                                                         f"jl[0:{ny + nx}, 0:{nx + nu}]",
                                                         pargs(b)),
                             f"        P[{nb}] = -1.0"])
    out.append(jacobian_source(prog, slu, calls, supplied))
    jit_names += ["block_eval", "block_jacobian", "diagram_jacobian", "newton_factor",
                  "newton_solve"]

    out.append("# ---- compile everything with numba, machine code cached beside this file")
    out.append(f"_JIT = {sorted(set(jit_names))!r}")
    out.append("for _n in _JIT:\n    globals()[_n] = njit(cache=True)(globals()[_n])\n")
    return "\n".join(out), list(deps.items())


def _param_values(plan, b):
    """The kernel arguments of block b, as _param_layout flattens them."""
    if b.spec.kind == "ode":
        return kernel_args(b.spec, plan.block_params(b))
    if b.spec.kind == "delay":
        return (float(next(x["T"] for x in plan.delays if x["block"] == b.index)),)
    return (float(next(x["eps"] for x in plan.holds if x["block"] == b.index)),)


def _check_kernels(plan):
    """Give every block ivdrem did not write its kernels (ivdrem.sim.foreign.adapt_block),
    once per plan; then every block has a BlockSpec."""
    for b in plan.blocks:
        if b.spec is None:
            try:
                b.spec = foreign.adapt_block(b.sys, effective_params(b.sys, plan.diagram,
                                                                     plan.params))
            except (TypeError, ValueError) as e:
                raise CompileError(f"{e}. Use engine='reference', or declare the block "
                                   "with ivdrem.blocks.BlockSpec.") from e


def python_blocks(plan):
    """[(block name, reason)] of the blocks that run in Python (called back)."""
    return [(b.sys.name, b.spec.reason) for b in plan.blocks
            if isinstance(b.spec, foreign.ForeignSpec) and b.spec.runs == "python"]


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
    plan.param_size = off
    values.append(np.array([-1.0, 0.0]))    # bookkeeping: block being called, its t
    P = np.concatenate(values)
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
        self.python_blocks = python_blocks(plan)
        if self.python_blocks:
            names = ", ".join(f"'{n}' ({why})" for n, why in self.python_blocks)
            warnings.warn(f"diagram {plan.diagram.name!r}: block(s) {names} run in Python, "
                          "called back from the compiled loop", foreign.PythonBlockNotice,
                          stacklevel=3)

    def block_failure(self, exc):
        """A BlockError naming the block that was running when `exc` was raised inside the
        compiled code (and the time), with the block's own exception as its cause; None
        when no block was running (the exception is the loop's own)."""
        k = int(self.P[self.plan.param_size])
        if not 0 <= k < len(self.plan.blocks):
            return None
        t = float(self.P[self.plan.param_size + 1])
        b = self.plan.blocks[k]
        cause = exc
        errs = getattr(b.spec, "error", None)
        if errs:                       # a Python block: its own exception, kept by the callback
            cause, t = errs[0]
            errs.clear()
        self.P[self.plan.param_size] = -1.0
        kind = " (running in Python)" if getattr(b.spec, "runs", "") == "python" else ""
        err = BlockError(f"block '{b.sys.name}'{kind} raised at t = {t:.9g} s: "
                         f"{type(cause).__name__}: {cause}")
        err.block, err.t = b.sys.name, t
        return err, cause

    def _guarded(self, mode, t, x, W, out):
        try:
            return self.module.diagram_eval(mode, t, x, self.P, W, out)
        except Exception as e:
            named = self.block_failure(e)
            if named is None:
                raise
            raise named[0] from named[1]

    def after_step(self, t, x, W):
        return self._guarded(_template.AFTER_STEP, t, x, W, x)

    def record(self, t, x, W, row):
        self._guarded(_template.RECORD, t, x, W, row)

    def rhs(self, t, x, W):
        dx = np.zeros_like(x)
        self._guarded(_template.RHS, t, x, W, dx)
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
        fn = self.module.dense_factor if dense else self.module.newton_factor
        st = fn(J, float(c), LU, piv)
        return int(st), LU, piv

    def solve(self, LU, piv, b, *, dense=False):
        """(c I - J)^{-1} b for a factorisation from :meth:`factor` (b is not modified)."""
        out = np.array(b, dtype=float)
        fn = self.module.dense_solve if dense else self.module.newton_solve
        fn(LU, piv, out)
        return out
