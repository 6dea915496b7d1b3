"""The compiled path: the diagram as tables, its kernels as cached C-callable wrappers.

Nothing here is compiled per diagram.  The generator reads the diagram's subsystem list and
connection map (through :class:`~ivdrem.sim.plan.DiagramPlan`) and produces:

* modules of the robot models' functions (``model.source()``, generated from sympy) and of
  every block's own kernels (their source, unchanged), each cached and shared by every
  diagram that uses it;
* for every kernel of every block, a C-callable wrapper (numba ``cfunc``, one module per
  kernel and block shape, cached) that takes pointers to the block's states, inputs,
  outputs and parameters;
* the diagram's tables (:mod:`ivdrem.sim.tables`): blocks, evaluation order of direct
  feedthrough, connection map, delays, max-holds, diagram outputs, the structured
  Jacobian's finite-difference program (:mod:`ivdrem.sim.jacobian`) and the static LU
  pattern of c I - J (:mod:`ivdrem.sim.sparse_lu`).

The C stepper (``stepper.c``, built once by :mod:`ivdrem.sim._cstepper`; a C compiler is
required, :class:`CCompilerMissing` says what to install) runs any diagram from its
tables, calling the wrappers by address.  A rewired diagram, another law or another robot compiles
only the kernels it is the first to use.  A block ivdrem did not write (``ct.ss``,
``ct.tf``, a summing junction, a plain ``ct.nlsys``) is turned into kernels first by
:mod:`ivdrem.sim.foreign`: linear kernels from its matrices, the user's own functions
compiled by numba, or, when numba cannot compile them, a call back into Python for that
block alone (a :class:`~ivdrem.sim.foreign.PythonBlockNotice` names those blocks).

A kernel that raises (a numba kernel's ``raise``, a Python block's exception, an FMU error)
returns a status from its wrapper (an exception cannot cross C); the diagram functions
record the wrapper and the time in the workspace and stop the run, and the engine reports
a :class:`BlockError` naming the block and the simulated time, with the block's own
exception as its cause.

Modules are written to ``$IVDREM_CACHE_DIR`` (default ``~/.cache/ivdrem``) under the hash
of their source, and numba caches their machine code beside them, so a second process
loads them without compiling.
"""
from __future__ import annotations

import inspect
import re
import sys
import textwrap
import threading
import warnings
from typing import NamedTuple

import numpy as np

from .. import __version__
from ..blocks import _kernels
from ..blocks._core import effective_params, kernel_args
from . import _template
from .cache import (GENERATED_HEADER, cache_dir, import_generated as _import,  # noqa: F401
                    source_hash as _hash, write_generated as _write)
from .errors import BLOCK_RAISED_MESSAGE, BlockError, CompileError  # noqa: F401
from .jacobian import JacobianProgram
from .sparse_lu import symbolic_lu
from .tables import build_tables
from . import foreign, sampled
from .foreign import foreign_module as _foreign_module
from . import _warm_stepper
from . import _cstepper

__all__ = ["CompiledEngine", "generate_source", "cache_dir", "CompileError", "BlockError"]

# what a kernel may name besides its arguments: numpy, math, its robot model, the shared
# helpers, and call_c (C functions by address: FMU calls, Python callbacks)
_ALLOWED_GLOBALS = ({"np", "math", "model", "call_c"}
                    | {k for k in dir(_kernels) if not k.startswith("_")})
_modules = {}


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


def _model_module(model):
    """(module name, source) of a robot model's numeric functions."""
    src = model.source("")
    names = re.findall(r"^def\s+(\w+)\s*\(", src, flags=re.M)
    body = "\n".join([f"# Generated by ivdrem {__version__}: model {model.name}. Do not edit.",
                      *GENERATED_HEADER, "", src, "",
                      f"for _n in {names!r}:",
                      "    globals()[_n] = njit(cache=True)(globals()[_n])", ""])
    return f"ivdrem_model_{_hash(body)}", body


def _kernel_module(fn, src, model_module):
    """(module name, source) of one block kernel, importing its model's module as `model`."""
    lines = [f"# Generated by ivdrem {__version__}: kernel {fn.__module__}.{fn.__qualname__}.",
             *GENERATED_HEADER]
    if model_module is not None:
        lines.append(f"import {model_module} as model")
    # inlined into its one caller, the C-callable wrapper (compiled alone, it would be
    # compiled to machine code twice: by itself and again inside the wrapper); not a kernel
    # that raises: numba cannot build an exception with runtime arguments raised directly
    # inside the wrapper's try (a kernel compiled apart hands it over as a status)
    inline = "never" if re.search(r"\braise\b", src) else "always"
    lines += ["", src, "", f"{fn.__name__} = njit(cache=True, inline={inline!r})({fn.__name__})",
              ""]
    body = "\n".join(lines)
    return f"ivdrem_kernel_{_hash(body)}", body


def _kernel_key(spec, role):
    fn = getattr(spec, role)
    if isinstance(spec, foreign.ForeignSpec):
        return spec.kernel_key(role)
    return (fn.__module__, fn.__qualname__, spec.model.key if spec.model else None)


def kernel_call(b, role, kernel, t, x, u, out, pargs):
    """Source of one call of block b's kernel `role` ("update", "output", "jacobian").

    `kernel` is the kernel's local name in the wrapper module; `x`, `u` and `out` are
    expressions for the block's flat state, input and output (or derivative, or local
    Jacobian) vectors; `pargs` the parameter arguments, each preceded by ", ".  Every
    kernel call of the generated wrappers is built here, so the calling convention lives in
    one place.
    """
    return f"{kernel}({t}, {x}, {u}, {out}{pargs})"


class ParamSlot(NamedTuple):
    """Where a kernel argument lives in the flat parameter vector P: `offset` and `shape`
    (() for a float, (n,) or (m, n) for an array), carried as numbers from the layout to
    the wrappers and the tables."""
    offset: int
    shape: tuple

    @property
    def size(self):
        return int(np.prod(self.shape, dtype=np.int64))


def _relative_params(slots):
    """(base, size, argument expressions on the block's own slice p) of a block's kernel
    arguments: a ParamSlot becomes an entry or slice of p, a constant its literal."""
    spans = [(a.offset, a.offset + a.size) for a in slots if isinstance(a, ParamSlot)]
    base = min((a for a, _ in spans), default=0)
    size = max((b for _, b in spans), default=base) - base

    def expr(a):
        if not isinstance(a, ParamSlot):
            return repr(a)
        lo = a.offset - base
        if not a.shape:
            return f"p[{lo}]"
        sl = f"p[{lo}:{lo + a.size}]"
        return sl if len(a.shape) == 1 else f"{sl}.reshape({a.shape!r})"
    return base, size, [expr(a) for a in slots]


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
             *GENERATED_HEADER, "from numba import cfunc, carray",
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


class DiagramProgram:
    """What the compiled engine needs for one diagram: the modules to load (robot models,
    kernels, the kernels' C-callable wrappers) and the diagram's tables."""

    def __init__(self, deps, wrappers, tables):
        self.deps = deps              # [(module name, source)], in import order
        self.wrappers = wrappers      # [(block name, role, wrapper module name)]
        self.tables = tables          # DiagramTables

    @property
    def source(self):
        """All generated source, for inspection (and its hash identifies the program)."""
        return "\n".join(src for _, src in self.deps)


def generate_source(plan, param_slots=None):
    """The modules and tables of a diagram (see :class:`DiagramProgram`).

    `param_slots` is the first half of ``_param_layout(plan)``, if already computed.  Kernels,
    model functions and wrappers get modules of their own, shared by every diagram that uses
    them, so numba compiles each once (and caches it); the diagram itself is data.
    """
    _check_kernels(plan)
    deps = {}                      # module name -> source, in dependency order
    kernels = {}                   # (module, qualname, model key) -> kernel module
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
                kernels[kk] = kmod
    # all parameters live in one flat float64 vector P (shapes are baked into the wrappers,
    # the values are not: changing a gain does not recompile); structural constants are
    # literals in the wrappers
    playout = _param_layout(plan)[0] if param_slots is None else param_slots
    # every kernel of every block gets a C-callable wrapper (its own cached module) and an
    # index into the workspace field `kernels`, which holds the wrappers' addresses
    wrappers, wrapper_nx = [], []
    windex, pbase = {}, {}
    for b in plan.blocks:
        if b.spec.kind != "ode":
            continue
        base, npar, rel = _relative_params(playout[b.index])
        pbase[b.index] = base
        for role in ("output", "update", "jacobian"):
            fn = getattr(b.spec, role)
            if fn is None or (role == "update" and not b.sys.nstates):
                continue
            kmod = kernels[_kernel_key(b.spec, role)]
            fname = (b.spec.sources[role][0] if isinstance(b.spec, foreign.ForeignSpec)
                     else fn.__name__)
            wmod, wsrc = _wrapper_module(b, role, kmod, fname, rel, npar)
            deps.setdefault(wmod, wsrc)
            windex[(b.index, role)] = len(wrappers)
            wrappers.append((b.sys.name, role, wmod))
            wrapper_nx.append(b.sys.nstates)
    # the Jacobian's FD program and the Newton matrix's static LU pattern
    prog = JacobianProgram(plan)
    slu = symbolic_lu(prog.pattern)
    tables = build_tables(plan, playout, pbase, windex, wrapper_nx, prog, slu)
    return DiagramProgram(list(deps.items()), wrappers, tables)


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
        if b.spec is None and getattr(b.sys, sampled.SAMPLED_ATTRIBUTE, None) is not None:
            b.spec = sampled.kernel_spec(b.sys, plan.sampling.address(b))
        elif b.spec is None:
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

    Returns ({block index: [ParamSlot or constant]}, P): arrays and floats get a slot of P,
    structural constants stay literals.
    """
    _check_kernels(plan)
    slots_by_block, values, off = {}, [], 0
    for b in plan.blocks:
        slots = []
        names = b.spec.param_names if b.spec.kind == "ode" else ("p",)
        for name, v in zip(names, _param_values(plan, b)):
            # scalar constants are literals; array constants (e.g. an FMU's C addresses,
            # different in every process) travel in P so the source stays the same
            if b.spec.kind == "ode" and name in b.spec.constants and np.ndim(v) == 0:
                slots.append(v)
                continue
            if np.ndim(v) > 2:
                raise CompileError(f"block '{b.sys.name}': parameter {name!r} has "
                                   f"{np.ndim(v)} dimensions; the compiled path takes <= 2")
            flat = np.asarray(v, float).reshape(-1)
            slots.append(ParamSlot(off, tuple(int(n) for n in np.shape(v))))
            values.append(flat)
            off += flat.size
        slots_by_block[b.index] = slots
    P = np.concatenate(values) if values else np.zeros(0)
    return slots_by_block, P


# A wrapper's compile time, estimated: measured for IV-DREM's 31 wrappers on the 2-core
# development machine, about 0.11 s plus 0.33 ms per character of its kernel's module (a
# Jacobian kernel no dearer than its size says).  A function the kernel calls that numba
# compiles on its own (a robot-model function, an ivdrem.blocks._kernels helper) costs
# the same per character, once in every process that compiles a caller.
_S_PER_WRAPPER, _S_PER_CHAR = 0.11, 3.3e-4
#: the child's late start, in the same units: its interpreter, numba, its first compile
_CHILD_START_S = 0.75
#: no child for a smaller share than this: its start would eat what it saves
_CHILD_MIN_S = 1.0
_GENERATED_IMPORT = re.compile(r"^(?:from|import) (ivdrem_\w+)", flags=re.M)


def _callees(cdir, ksrc, sources):
    """{callee: estimated seconds} of the separately compiled functions a kernel module's
    source calls that numba's cache does not hold yet."""
    out = {}
    model = re.search(r"^import (ivdrem_model_\w+) as model$", ksrc, flags=re.M)
    if model:
        mname = model.group(1)
        defs = {m.group(1): m for m in re.finditer(r"^def (\w+)\(.*?(?=^def |^\S|\Z)",
                                                    sources[mname], flags=re.M | re.S)}
        for f in sorted(set(re.findall(r"\bmodel\.(\w+)", ksrc)) & defs.keys()):
            if not _warm_stepper.function_cached(cdir / f"{mname}.py", f):
                out[(mname, f)] = _S_PER_CHAR * len(defs[f].group(0))
    for f in sorted(_ALLOWED_GLOBALS - {"np", "math", "model", "call_c"}):
        helper = getattr(_kernels, f)
        if not (hasattr(helper, "py_func") and re.search(rf"(?<![\w.]){f}\s*\(", ksrc)):
            continue
        try:
            if not _warm_stepper.index_exists(helper._cache):
                out[("_kernels", f)] = _S_PER_CHAR * len(inspect.getsource(helper.py_func))
        except Exception:     # pragma: no cover - numba internals changed
            pass
    return out


def _uncached_wrappers(cdir, deps):
    """{wrapper module: (estimated seconds, {callee: estimated seconds})} of the written
    wrapper modules in deps that numba's cache does not hold yet."""
    sources = dict(deps)
    out = {}
    for name, src in deps:
        if not name.startswith("ivdrem_wrapper_") or name in sys.modules:
            continue
        if _warm_stepper.function_cached(cdir / f"{name}.py", "wrapper"):
            continue
        kernel = _GENERATED_IMPORT.findall(src)[0]
        ksrc = sources[kernel]
        out[name] = (_S_PER_WRAPPER + _S_PER_CHAR * len(ksrc), _callees(cdir, ksrc, sources))
    return out


def _split(costs, head_start=_CHILD_START_S):
    """(this process's, the child's) shares of the modules `costs` ({name: (seconds,
    {callee: seconds})}): the dearest first, each to the process that would finish it
    first (the child starting `head_start` late; a callee costs a process only once), so
    both finish together."""
    load, have, shares = [0.0, head_start], [set(), set()], ([], [])

    def total(name):
        own, callees = costs[name]
        return own + sum(callees.values())

    for name in sorted(costs, key=lambda n: (-total(n), n)):
        own, callees = costs[name]
        ends = [load[k] + own + sum(c for f, c in callees.items() if f not in have[k])
                for k in (0, 1)]
        k = int(ends[1] < ends[0])
        load[k] = ends[k]
        have[k].update(callees)
        shares[k].append(name)
    return shares


def _with_imports(names, deps):
    """`names` and the generated modules they import (recursively), in the order of deps."""
    sources = dict(deps)
    need, todo = set(), list(names)
    while todo:
        n = todo.pop()
        if n not in need:
            need.add(n)
            todo += _GENERATED_IMPORT.findall(sources[n])
    return [n for n, _ in deps if n in need]


def _start_split(cdir, deps):
    """(a child compiling about half the wrappers of deps that numba's cache does not hold,
    the wrappers this process imports only after the child); deps: models, kernels and
    wrappers."""
    if not _warm_stepper.enabled():
        return _warm_stepper.Warmup(), []
    for name, src in deps:
        _write(cdir, name, src)
    costs = _uncached_wrappers(cdir, deps)
    later = _split(costs, _CHILD_START_S)[1]
    if sum(costs[n][0] + sum(costs[n][1].values()) for n in later) < _CHILD_MIN_S:
        return _warm_stepper.Warmup(), []
    return _warm_stepper.start_modules(_with_imports(later, deps)), later


def _import_all(cdir, deps, warmup, later=()):
    """Import deps in order, those in `later` only after the child `warmup` has finished
    (from numba's cache then, or compiled here if it failed); a failure or an interrupt
    here kills the child."""
    later = set(later)
    try:
        for name, dsrc in deps:
            if name not in later:
                _import(cdir, name, dsrc)
    except BaseException:
        warmup.cancel()
        raise
    warmup.wait()
    for name, dsrc in deps:
        if name in later:
            _import(cdir, name, dsrc)


def _load_kernels(deps):
    """Import the models, kernels and wrappers `deps` (their import compiles
    the wrappers), about half the wrappers numba's cache does not hold compiled by a child
    process meanwhile (:mod:`ivdrem.sim._warm_stepper`)."""
    cdir = cache_dir()
    cdir.mkdir(parents=True, exist_ok=True)
    _import_all(cdir, deps, *_start_split(cdir, deps))


#: what to install where no C compiler builds the stepper
C_COMPILER_HINT = ("ivdrem needs a C compiler to simulate (it builds ivdrem/sim/stepper.c "
                   "once into its cache): install one (Debian/Ubuntu: apt-get install gcc; "
                   "Fedora: dnf install gcc; macOS: xcode-select --install; conda: conda "
                   "install c-compiler) or point $CC at one")


class CCompilerMissing(RuntimeError):
    """No C compiler builds the stepper here (the message says what to install)."""


def load_c_stepper():
    """The C stepper (ivdrem.sim._cstepper), built into the cache on first use; no C
    compiler is a :class:`CCompilerMissing` naming what to install."""
    try:
        return _cstepper.load(cache_dir())
    except _cstepper.CStepperUnavailable as e:
        raise CCompilerMissing(f"{C_COMPILER_HINT}. ({e})") from e


def _c_stepper_pending():
    """A thread building (or loading) the C stepper while this process compiles its
    kernels (the C compiler is a process of its own)."""
    box = {}

    def build():
        try:
            box["stepper"] = load_c_stepper()
        except BaseException as e:       # handed to the caller by _c_stepper
            box["error"] = e
    th = threading.Thread(target=build, name="ivdrem-cstepper", daemon=True)
    th.start()
    return th, box


def _c_stepper(pending):
    """The C stepper of `pending` (see _c_stepper_pending), its error raised here."""
    th, box = pending
    th.join()
    if "error" in box:
        raise box["error"]
    return box["stepper"]


class CompiledEngine:
    """Runs the shared compiled stepper on this diagram's tables and kernel wrappers; same
    interface as the reference engine."""

    name = "compiled"

    def __init__(self, plan, params=None):
        self.plan = plan
        param_slots, self.P = _param_layout(plan)
        self.program = generate_source(plan, param_slots)
        pending = _c_stepper_pending()
        try:
            _load_kernels(self.program.deps)
        finally:
            self.module = _c_stepper(pending)
        self.stepper = self.module.name
        self.integrate = self.module.integrate
        self.tables = self.program.tables
        self.wrappers = self.program.wrappers
        self.n_kernels = len(self.wrappers)
        self._kernels = np.array([sys.modules[m].wrapper.address for _, _, m in self.wrappers],
                                 dtype=np.int64)
        self.python_blocks = python_blocks(plan)
        if self.python_blocks:
            names = ", ".join(f"'{n}' ({why})" for n, why in self.python_blocks)
            warnings.warn(f"diagram {plan.diagram.name!r}: block(s) {names} run in Python, "
                          "called back from the compiled loop", foreign.PythonBlockNotice,
                          stacklevel=3)

    @property
    def source(self):
        return self.program.source

    def bind(self, W):
        """Put this diagram's kernel addresses into workspace W (its tables are W.tables)."""
        W.kernels[:self.n_kernels] = self._kernels

    def failed_kernel(self, W):
        """(block name, kernel role, t) of the kernel that raised, from W.failure."""
        j, t = int(W.failure[0]), float(W.failure[1])
        name, role, _ = self.wrappers[j]
        return name, role, t

    def block_failure(self, exc, W):
        """(BlockError, cause) for a kernel that raised inside the compiled code (recorded in
        W.failure by the diagram functions), or None if `exc` is not that.  The cause is the
        block's own exception: kept by a Python block's callback, or reproduced by running
        the block's Python function at the recorded point."""
        if not (isinstance(exc, RuntimeError) and str(exc) == BLOCK_RAISED_MESSAGE):
            return None
        name, role, t = self.failed_kernel(W)
        b = next(b for b in self.plan.blocks if b.sys.name == name)
        errs = getattr(b.spec, "error", None)
        cause = None
        if errs:                       # a Python block: its own exception, kept by the callback
            cause, t = errs[0]
            errs.clear()
        else:
            x = np.array(W.failure[2:2 + b.sys.nstates])
            u = np.array(W.us[b.u])
            fn = b.sys.updfcn if role == "update" else b.sys.outfcn
            try:
                fn(t, x, u, effective_params(b.sys, self.plan.diagram, self.plan.params))
            except Exception as e:     # the block's own error, re-raised from Python
                cause = e
        kind = " (running in Python)" if getattr(b.spec, "runs", "") == "python" else ""
        what = f"{type(cause).__name__}: {cause}" if cause is not None else (
            f"its compiled {role} kernel raised (re-running it in Python at the recorded "
            "states did not reproduce the error)")
        err = BlockError(f"block '{name}'{kind} raised at t = {t:.9g} s: {what} (in its "
                         f"{role} function)")
        err.block, err.t, err.role = name, t, role
        return err, cause

    def _run(self, fn, *args):
        """fn(*args), a kernel that raised inside reported as a BlockError naming the
        block and the time."""
        try:
            return fn(*args)
        except RuntimeError as e:
            W = args[4] if len(args) > 4 else args[3]
            named = self.block_failure(e, W)
            if named is None:
                raise
            if named[1] is not None and not isinstance(named[1], Exception):
                raise named[1]      # Ctrl-C (KeyboardInterrupt), SystemExit: not the block's
            raise named[0] from named[1]

    def after_step(self, t, x, W):
        return self._run(self.module.diagram_eval, W, self.P, _template.AFTER_STEP, t, x, x)

    def record(self, t, x, W, row):
        self._run(self.module.diagram_eval, W, self.P, _template.RECORD, t, x, row)

    def rhs(self, t, x, W):
        dx = np.zeros_like(x)
        self._run(self.module.diagram_eval, W, self.P, _template.RHS, t, x, dx)
        return dx

    # ---- Jacobian and Newton matrix, callable from Python (tests, benchmarks)
    def jacobian(self, t, x, W, *, dense=False):
        """df/dx at (t, x) as the generated diagram_jacobian computes it (n x n array);
        dense=True: the whole-system forward-difference fallback fd_jacobian instead."""
        x = np.ascontiguousarray(x, dtype=float)
        J = np.zeros((x.size, x.size))
        fn = self.module.fd_jacobian if dense else self.module.diagram_jacobian
        st = self._run(fn, W, self.P, float(t), x, J)
        if st != _template.OK:
            raise RuntimeError(f"diagram_jacobian returned status {st}")
        return J

    def factor(self, J, c, *, dense=False):
        """Factor c I - J with the generated newton_factor (the static-pattern sparse LU),
        or with dense=True the partial-pivoting dense_factor: (status, LU, piv)."""
        J = np.ascontiguousarray(J, dtype=float)
        n = J.shape[0]
        LU = np.zeros((n + 2, n))     # rows n, n + 1: the sparse LU's inverse pivots, work row
        piv = np.zeros(n, dtype=np.int64)
        tb = self.tables
        if dense:
            st = self.module.dense_factor(J, float(c), LU, piv)
        else:
            st = self.module.slu_factor(J, float(c), LU, piv, tb.lu_perm, tb.lu_rowptr,
                                        tb.lu_colidx, tb.lu_diagp)
        return int(st), LU, piv

    def solve(self, LU, piv, b, *, dense=False):
        """(c I - J)^{-1} b for a factorisation from :meth:`factor` (b is not modified)."""
        out = np.array(b, dtype=float)
        tb = self.tables
        if dense:
            self.module.dense_solve(LU, piv, out)
        else:
            self.module.slu_solve(LU, tb.lu_perm, tb.lu_rowptr, tb.lu_colidx, tb.lu_diagp, out)
        return out
