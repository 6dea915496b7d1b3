"""The compiled engine: the diagram as tables, its blocks' kernels as cached C-callable
wrappers (numba ``cfunc``, one module per kernel, for every size of a block without a
robot model (:func:`generic_block`), per arm for a block with one; shared by every diagram
that uses it), run by the C stepper (docs/simulation.md: "Blocks ivdrem did not write" and
the layout of ``ivdrem/sim/``).  Generated modules live in :func:`cache_dir`, named by the
hash of their source, with numba's machine code beside them.
"""
from __future__ import annotations

import hashlib
import inspect
import math
import re
import sys
import textwrap
import warnings
import weakref
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from functools import lru_cache
from typing import NamedTuple

import numpy as np

from .. import __version__
from ..blocks import _kernels
from ..blocks import _ports
from ..blocks._core import effective_params, flat_kernel, kernel_args, port_layout
from . import _stepper_codes
from ._diagram import LU_WORK_ROWS
from .._progress import preparing
from ..compile_cache import (GENERATED_HEADER, cache_dir, import_generated as _import,  # noqa: F401
                    source_hash as _hash, write_generated as _write)
from .errors import BLOCK_RAISED_MESSAGE, BlockError, CompileError  # noqa: F401
from .jacobian import (JacobianProgram, helpers_cache_as_now, kernel_code_ids,
                       probe_wrappers, structure_digest)
from ..models._jit_module import model_module, module_source as _model_module  # noqa: F401
from .sparse_lu import symbolic_lu
from .tables import (build_tables, dense_to_sparse, load_tables, prune_kept_tables,
                     save_tables, sparse_to_dense)
from . import foreign
from .sampled import SAMPLED_ATTRIBUTE, kernel_spec
from .foreign import foreign_module as _foreign_module
from . import _compile_child
from . import _cstepper

__all__ = ["CompiledEngine", "generate_source", "cache_dir", "CompileError", "BlockError"]

# what a kernel may name besides its arguments: numpy, math, its robot model, the shared
# helpers, and call_c (C functions by address: FMU calls, Python callbacks)
_ALLOWED_GLOBALS = ({"np", "math", "model", "call_c"}
                    | {k for k in dir(_kernels) if not k.startswith("_")})


#: a kernel's dedented source, read once per function object: every ``simulate`` builds
#: its engine's source again, and reading the 2-link loop's 33 kernels with inspect
#: (tokenizing their files) was about half of a warm engine's set-up (53 -> 24 ms CPU)
_SOURCES = weakref.WeakKeyDictionary()


def _read_source(fn):
    src = _SOURCES.get(fn)
    if src is None:
        src = _SOURCES[fn] = textwrap.dedent(inspect.getsource(fn))
    return src


#: a kernel's checked source, per function object and whether its block has a model: the
#: checks read the function's globals and source again on every simulate (a third of the
#: paper's loop's per-call set-up once its tables are kept)
_CHECKED = weakref.WeakKeyDictionary()


def _kernel_source(fn, block_name, has_model):
    """Source of a block kernel, after checking it only uses what its module provides."""
    checked = _CHECKED.setdefault(fn, {})
    if has_model not in checked:
        checked[has_model] = _checked_kernel_source(fn, block_name, has_model)
    return checked[has_model]


def _checked_kernel_source(fn, block_name, has_model):
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
    src = _read_source(fn)
    if not re.search(r"^def\s+" + re.escape(fn.__name__) + r"\s*\(", src, flags=re.M):
        raise CompileError(f"cannot read the source of kernel {fn.__name__} of block '{block_name}'")
    if not has_model and re.search(r"\bmodel\.", src):
        raise CompileError(f"kernel {fn.__name__} of block '{block_name}' calls model "
                           "functions but the block has no model")
    return src


# kept per kernel, source and model module: every simulate asks again (the paper's loop's 33
# kernels: 1.7 ms of each call's set-up)
@lru_cache(maxsize=512)
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
    lines = [f"# Generated by ivdrem {__version__}: C-callable {role} kernel "
             f"{kmod}.{fn_name} (nx={nx}, nu={nu}, ny={ny}). Do not edit.",
             *GENERATED_HEADER, "from numba import cfunc, carray",
             "from ivdrem._native_call import float_pointer",
             f"from {kmod} import {fn_name} as kernel", "", "",
             '@cfunc("int32(float64, int64, int64, int64, int64)", cache=True)',
             "def wrapper(t, xp, up, outp, pp):",
             f"    x = carray(float_pointer(xp), ({nx},))",
             f"    u = carray(float_pointer(up), ({nu},))",
             f"    out = carray(float_pointer(outp), {out_shape})",
             f"    p = carray(float_pointer(pp), ({npar},))",
             "    try:", f"        kernel(t, x, u, out{pargs})", "    except Exception:",
             "        return 1",
             "    return 0", ""]
    body = "\n".join(lines)
    return f"ivdrem_wrapper_{_hash(body)}", body


#: the layout of the wrappers' parameters in P, part of the tables' key: tables kept on
#: disk by a version with another layout are never read as this one's
WRAPPER_LAYOUT = "generic wrappers: header at the block's base, 1"

#: whether the blocks without a robot model get generic wrappers (:func:`generic_block`);
#: False: every wrapper specialised to its block's sizes (benchmarks compare the two)
GENERIC_WRAPPERS = True

#: a float64 header carries integers exactly up to here (sizes, offsets, int constants)
_EXACT_INT = 2 ** 53


class GenericSlots(NamedTuple):
    """The parameter layout of a block whose wrapper is the same for every size
    (:func:`generic_block`): a header of `size` float64 entries at P[header] (its sizes,
    port bounds, parameter slots and scalar constants: :func:`_header`), then its
    parameters; `args` the kernel arguments as :func:`_param_layout` gives them (a
    ParamSlot, or a constant's value)."""
    header: int
    size: int
    args: list


def _selector_constants(spec):
    """The constants a kernel passes as the variant code of a helper compiled per variant
    (``mixing_values(variant, ...)``: ivdrem.blocks._kernels): they stay literals in the
    wrapper, so numba compiles the block's variant alone (one wrapper per variant, not
    per size)."""
    helpers = [f for f in _ALLOWED_GLOBALS - {"np", "math", "model", "call_c"}
               if hasattr(getattr(_kernels, f), "variants")]
    if not helpers or not spec.constants:
        return frozenset()
    pattern = re.compile(rf"(?<![\w.])(?:{'|'.join(helpers)})\s*\(\s*(\w+)\s*,")
    names = set()
    for role in ("update", "output", "jacobian"):
        fn = (spec.named_kernels or {}).get(role) or getattr(spec, role)
        if fn is not None:
            names.update(pattern.findall(_read_source(fn)))
    return frozenset(names & spec.constants.keys())


def generic_block(b):
    """Whether block b's wrappers read its sizes, port offsets, parameter slots and
    scalar constants at run time (one compiled wrapper for every arm): an ode block
    without a robot model, declared with ivdrem's BlockSpec (not a foreign or sampled
    block), whose scalar constants are int or float numbers.  A block with a model
    imports its arm's model module, so its wrappers are per arm anyway and keep theirs
    specialised (literal sizes, offsets and constants)."""
    spec = b.spec
    if (spec is None or spec.kind != "ode" or spec.model is not None
            or isinstance(spec, foreign.ForeignSpec)
            or getattr(b.sys, SAMPLED_ATTRIBUTE, None) is not None):
        return False
    selectors = _selector_constants(spec)
    for name, v in spec.constants.items():
        if name in selectors or np.ndim(v) != 0:
            continue
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.integer,
                                                                  np.floating)):
            return False
        if isinstance(v, (int, np.integer)) and abs(int(v)) >= _EXACT_INT:
            return False
    return True


def _arg_kind(spec, name, v, selectors):
    """How a generic block's kernel argument travels: "float", "vector", "matrix" (a
    ParamSlot of P), "int" or "number" (a scalar constant in the header) or "literal" (a
    selector constant, :func:`_selector_constants`)."""
    if isinstance(v, ParamSlot):
        return ("float", "vector", "matrix")[len(v.shape)]
    if name in selectors:
        return "literal"
    return "int" if isinstance(v, (int, np.integer)) else "number"


#: header entries per kind of argument: a slot's offset in the block's P and its shape
_HEADER_ENTRIES = {"float": 1, "vector": 2, "matrix": 3, "int": 1, "number": 1, "literal": 0}


def _port_counts(spec):
    """(states, inputs, outputs) port counts of a named-port block (their bounds are in the
    header), else (0, 0, 0)."""
    if not spec.named_ports:
        return 0, 0, 0
    return len(spec.states), len(spec.inputs), len(spec.outputs)


def _header(spec, args, base, selectors):
    """(kinds, header values) of a generic block whose header starts at P[base], `args` its
    kernel arguments (absolute ParamSlots, constants).  The header is, in order:
    [length of the block's P (header and parameters), nx, nu, ny, the cumulative bounds
    of its states, inputs and outputs (named ports: each from 0 to the vector's size),
    then per argument: a float's offset; a vector's offset and length; a matrix's offset,
    rows and columns (offsets relative to `base`); an int or float constant's value].
    :func:`_generic_wrapper_module` reads it by the same rule."""
    kinds = tuple(_arg_kind(spec, n, v, selectors) for n, v in zip(spec.param_names, args))
    head = [0.0, float(spec.nstates), float(spec.ninputs), float(spec.noutputs)]
    if spec.named_ports:
        for ports in (spec.states, spec.inputs, spec.outputs):
            head += [0.0] + [float(c) for c in np.cumsum([n for _, n in ports])]
    for kind, v in zip(kinds, args):
        if kind in ("float", "vector", "matrix"):
            head += [float(v.offset - base), *(float(n) for n in v.shape)]
        elif kind != "literal":
            head.append(float(v))
    end = max([base + len(head)] + [v.offset + v.size for v in args
                                     if isinstance(v, ParamSlot)])
    head[0] = float(end - base)
    return kinds, head


def _generic_wrapper_module(role, kmod, fn_name, kinds, ports, literals, pass_bounds):
    """(module name, source) of the C-callable wrapper of a generic block's kernel `role`
    (:func:`generic_block`): the same text for every size, the block's header
    (:func:`_header`) at its parameter pointer read at the top.  `kinds` the kernel
    arguments' kinds, `ports` the (states, inputs, outputs) port counts of a named-port
    block (None for a flat one: no bounds in its header), `literals` the selector
    constants' values; `pass_bounds`: the kernel takes the port bounds (a named-port
    kernel's flat form, not a jacobian kernel)."""
    hlen = 4 + (sum(c + 1 for c in ports) if ports else 0) + sum(
        _HEADER_ENTRIES[k] for k in kinds)
    out_shape = {"output": "(ny,)", "update": "(nx,)", "jacobian": "(ny + nx, nx + nu)"}[role]
    body = ["    h = carray(float_pointer(pp), (%d,))" % hlen,
            "    nx, nu, ny = int(h[1]), int(h[2]), int(h[3])",
            "    x = carray(float_pointer(xp), (nx,))",
            "    u = carray(float_pointer(up), (nu,))",
            f"    out = carray(float_pointer(outp), {out_shape})",
            "    p = carray(float_pointer(pp), (int(h[0]),))"]
    call, k = [], 4
    if ports:
        starts, at = [], k
        for c in ports:                       # states, inputs, outputs bounds
            starts.append(at)
            at += c + 1
        k = at
        # the kernel's x, u and out: states, inputs and (update) states or (output) outputs
        if pass_bounds:
            for w in (0, 1, 0 if role == "update" else 2):
                call += [f"int(h[{starts[w] + j}])" for j in range(ports[w] + 1)]
    lits = iter(literals)
    for i, kind in enumerate(kinds):
        a = f"a{i}"
        if kind == "float":
            body.append(f"    {a} = p[int(h[{k}])]")
        elif kind == "vector":
            body.append(f"    {a} = p[int(h[{k}]):int(h[{k}]) + int(h[{k + 1}])]")
        elif kind == "matrix":
            body.append(f"    {a} = p[int(h[{k}]):int(h[{k}]) + int(h[{k + 1}]) * "
                        f"int(h[{k + 2}])].reshape((int(h[{k + 1}]), int(h[{k + 2}])))")
        elif kind == "int":
            body.append(f"    {a} = int(h[{k}])")
        elif kind == "number":
            body.append(f"    {a} = h[{k}]")
        else:
            a = repr(next(lits))
        k += _HEADER_ENTRIES[kind]
        call.append(a)
    if ports and pass_bounds:                 # many bounds: one per line
        bound_lines = []
        nb = sum(ports[w] + 1 for w in (0, 1, 0 if role == "update" else 2))
        for j in range(nb):
            body.append(f"    b{j} = {call[j]}")
            bound_lines.append(f"b{j}")
        call = bound_lines + call[nb:]
    pargs = "".join(", " + a for a in call)
    lines = [f"# Generated by ivdrem {__version__}: C-callable {role} kernel "
             f"{kmod}.{fn_name}, for every size: sizes, port bounds, parameter slots and "
             "constants read from the block's header in P. Do not edit.",
             *GENERATED_HEADER, "from numba import cfunc, carray",
             "from ivdrem._native_call import float_pointer",
             f"from {kmod} import {fn_name} as kernel", "", "",
             '@cfunc("int32(float64, int64, int64, int64, int64)", cache=True)',
             "def wrapper(t, xp, up, outp, pp):", *body,
             "    try:", f"        kernel(t, x, u, out{pargs})", "    except Exception:",
             "        return 1",
             "    return 0", ""]
    src = "\n".join(lines)
    return f"ivdrem_wrapper_{_hash(src)}", src


def _generic_kernel(spec, role):
    """The function a generic block's wrapper calls for `role`: a named-port kernel's
    flat form with its port bounds as arguments (:func:`ivdrem.blocks._ports.flat_form`),
    else the kernel itself."""
    named = (spec.named_kernels or {}).get(role)
    layout = port_layout(spec, role)
    if named is None or layout is None:
        return getattr(spec, role)
    return _ports.flat_form(named, role, layout, runtime_offsets=True)


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
    modules = kernel_modules(plan, param_slots)
    return DiagramProgram(modules.deps, modules.wrappers, diagram_tables(plan, modules))


class KernelModules(NamedTuple):
    """A diagram's generated modules, known before its tables: `deps` [(module name,
    source)] in import order, `wrappers` [(block name, role, wrapper module)], and where the
    tables find them (`windex` {(block index, role): wrapper index}, `wrapper_nx`, the
    parameter layout `playout` and each block's parameter base `pbase`)."""
    deps: list
    wrappers: list
    windex: dict
    wrapper_nx: list
    playout: dict
    pbase: dict


def kernel_modules(plan, param_slots=None):
    """The models', kernels' and wrappers' modules of a diagram (:class:`KernelModules`):
    their sources depend on the blocks' kernels, shapes and parameter layout only, not on
    the sparsity probe, the Jacobian program or the LU, so their compile can start first."""
    _check_kernels(plan)
    # all parameters live in one flat float64 vector P (the values are not in the wrappers:
    # changing a gain does not recompile); a generic block's sizes, port bounds, slots and
    # scalar constants are in its header in P (one wrapper for every size), a model
    # block's shapes and structural constants are literals in its wrappers
    playout = _param_layout(plan)[0] if param_slots is None else param_slots
    deps = {}                      # module name -> source, in dependency order
    kernels = {}                   # (module, qualname, model key) -> (module, function)
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
            generic = isinstance(playout[b.index], GenericSlots)
            if generic:
                fn = _generic_kernel(spec, role)
            kk = (fn.__module__, fn.__qualname__, None) if generic else _kernel_key(spec, role)
            if kk not in kernels:
                if isinstance(spec, foreign.ForeignSpec):
                    fname, src = spec.sources[role]
                    kmod, ksrc = _foreign_module(fname, src)
                else:
                    fname = fn.__name__
                    src = _kernel_source(fn, b.sys.name, spec.model is not None)
                    kmod, ksrc = _kernel_module(fn, src, mmod)
                deps.setdefault(kmod, ksrc)
                kernels[kk] = kmod, fname
    # every kernel of every block gets a C-callable wrapper (its own cached module) and an
    # index into the workspace field `kernels`, which holds the wrappers' addresses
    wrappers, wrapper_nx = [], []
    windex, pbase = {}, {}
    for b in plan.blocks:
        if b.spec.kind != "ode":
            continue
        layout = playout[b.index]
        if isinstance(layout, GenericSlots):
            pbase[b.index] = layout.header
            selectors = _selector_constants(b.spec)
            kinds, _ = _header(b.spec, layout.args, layout.header, selectors)
            literals = [v for n, v in zip(b.spec.param_names, layout.args) if n in selectors
                        and not isinstance(v, ParamSlot)]
        else:
            base, npar, rel = _relative_params(layout)
            pbase[b.index] = base
        for role in ("output", "update", "jacobian"):
            fn = getattr(b.spec, role)
            if fn is None or (role == "update" and not b.sys.nstates):
                continue
            if isinstance(layout, GenericSlots):
                gfn = _generic_kernel(b.spec, role)
                kmod, fname = kernels[(gfn.__module__, gfn.__qualname__, None)]
                wmod, wsrc = _generic_wrapper_module(
                    role, kmod, fname, kinds,
                    _port_counts(b.spec) if b.spec.named_ports else None, literals,
                    pass_bounds=port_layout(b.spec, role) is not None)
            else:
                kmod, fname = kernels[_kernel_key(b.spec, role)]
                wmod, wsrc = _wrapper_module(b, role, kmod, fname, rel, npar)
            deps.setdefault(wmod, wsrc)
            windex[(b.index, role)] = len(wrappers)
            wrappers.append((b.sys.name, role, wmod))
            wrapper_nx.append(b.sys.nstates)
    return KernelModules(list(deps.items()), wrappers, windex, wrapper_nx, playout, pbase)


#: the tables of the diagrams simulated in this process, by what they are built from: a
#: study or a benchmark simulates one diagram many times (the Panda's loop: 0.5-0.8 s of
#: set-up a call; the paper's loop: most of a call's set-up)
_TABLES: OrderedDict = OrderedDict()
_TABLES_MAX = 8


def tables_key(plan, modules):
    """The key of `plan`'s tables: (the digest of :func:`~ivdrem.sim.jacobian.
    structure_digest` and of where `modules` put the kernels and parameters, which names
    the file on disk; the kernels' code objects, which this process's keeping adds); None
    where the diagram's blocks cannot be keyed (a user's nlsys, an FMU: their tables are
    built every time)."""
    digest = structure_digest(plan)
    if digest is None:
        return None
    layout = (WRAPPER_LAYOUT, sorted(modules.playout.items()), sorted(modules.pbase.items()),
              sorted(modules.windex.items()), list(modules.wrapper_nx))
    return (hashlib.sha256(f"{digest} {layout!r}".encode()).hexdigest(),
            kernel_code_ids(plan))


def _tables_path(key):
    return cache_dir() / "tables" / f"{key[:40]}.npz"


def kept_tables(key):
    """The tables kept under `key` (:func:`tables_key`) in this process or on disk, or None
    (then :func:`diagram_tables` builds them)."""
    if key is None:
        return None
    tables = _TABLES.get(key)
    if tables is None:
        tables = load_tables(_tables_path(key[0]))
        if tables is None:
            return None
        _keep(key, tables)
    _TABLES.move_to_end(key)
    return tables


def _keep(key, tables):
    _TABLES[key] = tables
    while len(_TABLES) > _TABLES_MAX:
        _TABLES.popitem(last=False)


def diagram_tables(plan, modules, key=None):
    """The diagram's tables: the Jacobian's FD program (after the sparsity probe) and the
    Newton matrix's static LU pattern, with where `modules` put the kernels.  Kept in this
    process and on disk by :func:`tables_key` (`key`, if the caller has it; the same inputs
    give the same tables, bit for bit): a warm run reads one file instead of the blocks'
    patterns, the program and the LU order and building the tables from them (the Panda's
    loop: 1.7 s of CPU), a second call of the same diagram reads nothing."""
    key = tables_key(plan, modules) if key is None else key
    tables = kept_tables(key)
    if tables is not None:
        return tables
    prog = JacobianProgram(plan, modules=modules)
    slu = symbolic_lu(prog.pattern, plan.state_groups())
    tables = build_tables(plan, modules.playout, modules.pbase, modules.windex,
                          modules.wrapper_nx, prog, slu)
    if key is not None:
        path = _tables_path(key[0])
        save_tables(path, tables)
        prune_kept_tables(path.parent)
        for a in tables:
            a.flags.writeable = False       # shared by every later call
        _keep(key, tables)
    return tables


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
        if b.spec is None and getattr(b.sys, SAMPLED_ATTRIBUTE, None) is not None:
            b.spec = kernel_spec(b.sys, plan.sampling.address(b))
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


def _param_layout(plan, *, generic=None):
    """The kernels' parameters in one flat float64 vector P.

    Returns ({block index: [ParamSlot or constant]}, P): arrays and floats get a slot of P,
    structural constants stay literals; a generic block (:func:`generic_block`) gets
    :class:`GenericSlots`, its header (:func:`_header`) in P before its parameters
    (``generic=False``: every block specialised; None: :data:`GENERIC_WRAPPERS`).
    """
    _check_kernels(plan)
    slots_by_block, values, off = {}, [], 0
    for b in plan.blocks:
        slots = []
        names = b.spec.param_names if b.spec.kind == "ode" else ("p",)
        args = _param_values(plan, b)
        header_first = (GENERIC_WRAPPERS if generic is None else generic) and generic_block(b)
        if header_first:    # the header's place, filled below when the slots are known
            selectors = _selector_constants(b.spec)
            pending = [ParamSlot(0, np.shape(v)) if not (name in b.spec.constants
                                                         and np.ndim(v) == 0) else v
                       for name, v in zip(names, args)]
            header, hlen = off, len(_header(b.spec, pending, 0, selectors)[1])
            hindex = len(values)
            values.append(np.zeros(hlen))
            off += hlen
        for name, v in zip(names, args):
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
        if header_first:
            _, head = _header(b.spec, slots, header, selectors)
            values[hindex][:] = head
            slots = GenericSlots(header, hlen, slots)
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
            if not _compile_child.function_cached(cdir / f"{mname}.py", f):
                out[(mname, f)] = _S_PER_CHAR * len(defs[f].group(0))
    for f in sorted(_ALLOWED_GLOBALS - {"np", "math", "model", "call_c"}):
        helper = getattr(_kernels, f)
        # a mixing function compiles one variant (its njit functions: .variants), the
        # run's; priced as one when none is cached
        compiled = (helper,) if hasattr(helper, "py_func") else getattr(helper, "variants", ())
        if not (compiled and re.search(rf"(?<![\w.]){f}\s*\(", ksrc)):
            continue
        try:
            if not any(_compile_child.index_exists(c._cache) for c in compiled):
                out[("_kernels", f)] = _S_PER_CHAR * len(inspect.getsource(compiled[0].py_func))
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
        if _compile_child.function_cached(cdir / f"{name}.py", "wrapper"):
            continue
        kernel = _GENERATED_IMPORT.findall(src)[0]
        ksrc = sources[kernel]
        out[name] = (_S_PER_WRAPPER + _S_PER_CHAR * len(ksrc), _callees(cdir, ksrc, sources))
    return out


def _split(costs, head_start=_CHILD_START_S, parent_busy=0.0):
    """(this process's, the child's) shares of the modules `costs` ({name: (seconds,
    {callee: seconds})}): the dearest first, each to the process that would finish it
    first (the child starting `head_start` late, this process `parent_busy` seconds busy
    with other work first, ``math.inf`` giving the child everything; a callee costs a
    process only once), so both finish together."""
    load, have, shares = [parent_busy, head_start], [set(), set()], ([], [])

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
    """The generated modules `names` import (recursively; models, kernels: importing them
    compiles nothing) in the order of deps, then `names` in their order (the order the child
    compiles them in, and this process takes them back in reverse)."""
    sources = dict(deps)
    need, todo = set(), [m for n in names for m in _GENERATED_IMPORT.findall(sources[n])]
    while todo:
        n = todo.pop()
        if n not in need:
            need.add(n)
            todo += _GENERATED_IMPORT.findall(sources[n])
    named = set(names)
    return [n for n, _ in deps if n in need and n not in named] + list(names)


def _start_split(cdir, deps, parent_busy=0.0, first=()):
    """(a child compiling about half the wrappers of deps that numba's cache does not hold,
    the wrappers this process imports last); deps: models, kernels and wrappers.  With
    `parent_busy` (:func:`_split`) ``math.inf`` the child gets every uncached wrapper, the
    dearest first, and this process takes the cheapest back when its other work is done
    (:func:`_import_all`); the uncached wrappers of the list `first` head the child's list,
    in that order (the sparsity probe runs them: this process waits for them, or
    loads them, after probing the other blocks)."""
    if not _compile_child.enabled():
        return _compile_child.Warmup(), []
    # a process that has imported every module (a second simulate of a loop) has nothing
    # to compile or to write: reading its 67 files back was about 20 ms of each warm call
    if all(name in sys.modules for name, _ in deps):
        return _compile_child.Warmup(), []
    for name, src in deps:
        _write(cdir, name, src)
    costs = _uncached_wrappers(cdir, deps)
    later = _split(costs, _CHILD_START_S, parent_busy)[1]
    head = [n for n in first if n in set(later)]
    later = head + [n for n in later if n not in set(head)]
    if sum(costs[n][0] + sum(costs[n][1].values()) for n in later) < _CHILD_MIN_S:
        return _compile_child.Warmup(), []
    return _compile_child.start_modules(_with_imports(later, deps)), later


def _import_all(cdir, deps, warmup, later=()):
    """Import deps in order, then those in `later` (the child `warmup`'s, which it compiles
    in order) from the last back: each under its module's lock, so a module the child is
    compiling is waited for and then loaded from numba's cache, one the child has done is
    loaded, one it has not reached is compiled here (and the child loads it), so the two
    processes finish together however long this one was busy before; then the child is
    waited for.  A failure or an interrupt here kills the child."""
    sources = dict(deps)
    order = [name for name, _ in deps if name not in set(later)] + list(reversed(later))
    try:
        for name in order:
            _import(cdir, name, sources[name])
    except BaseException:
        warmup.cancel()
        raise
    warmup.wait()


class KernelCompile(NamedTuple):
    """Kernel modules whose compile has started (:func:`start_kernels`): the child
    `warmup`, the wrappers it was given (`later`), the cache directory and the modules."""
    cdir: object
    deps: list
    warmup: object
    later: list

    def finish(self):
        """Import every module (this process's share compiled here, the child's loaded or
        taken back), the child joined; an error or an interrupt kills the child."""
        _import_all(self.cdir, self.deps, self.warmup, self.later)

    def cancel(self):
        """Kill the child (the work between start and finish failed or was interrupted)."""
        self.warmup.cancel()


def start_kernels(deps, parent_busy=0.0, first=()):
    """Write the models, kernels and wrappers `deps` and start a child compiling the
    wrappers numba's cache does not hold (its share by :func:`_split`; ``math.inf``: all of
    them, this process being busy first with work of unknown length; those of the list
    `first` at the head of its list); :meth:`KernelCompile.finish` imports them."""
    cdir = cache_dir()
    cdir.mkdir(parents=True, exist_ok=True)
    return KernelCompile(cdir, deps, *_start_split(cdir, deps, parent_busy, list(first)))


def _load_kernels(deps):
    """Import the models, kernels and wrappers `deps` (their import compiles
    the wrappers), about half the wrappers numba's cache does not hold compiled by a child
    process meanwhile (:mod:`ivdrem.sim._compile_child`)."""
    start_kernels(deps).finish()


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
    except _cstepper.CStepperBuildFailed as e:
        # a compiler that runs but refuses ivdrem's C: installing one would not help
        raise RuntimeError(f"the C compiler did not build ivdrem's stepper; please report "
                           f"this with the compiler's output. ({e})") from e
    except _cstepper.CStepperUnavailable as e:
        raise CCompilerMissing(f"{C_COMPILER_HINT}. ({e})") from e


class CompiledEngine:
    """Runs the shared compiled stepper on this diagram's tables and kernel wrappers; same
    interface as the reference engine."""

    name = "compiled"

    def __init__(self, plan, params=None):
        self.plan = plan
        param_slots, self.P = _param_layout(plan)
        # a first run generates and compiles for minutes: said, on a terminal or in a log
        with preparing(f"generating and compiling the kernels of diagram "
                       f"{plan.diagram.name!r} (numba; loaded from the cache when they are "
                       "there)", cached_in=cache_dir(), only_if_slow=True):
            modules = kernel_modules(plan, param_slots)
            # a helper child (γ "auto"'s estimate started one) done: its functions are in
            # numba's cache before the probe reads that cache and the wrappers load them
            _compile_child.join_helpers()
            key = tables_key(plan, modules)
            tables = kept_tables(key)
            if tables is not None:      # a warm run, or a second call of the same diagram
                compiling = start_kernels(modules.deps)
            else:
                # the kernels' sources do not depend on the probe, the Jacobian program or
                # the LU: a child compiles the wrappers (all those not cached, the dearest
                # first) while this process builds the tables (on a first run 10-25 s of
                # CPU), then takes back those the child has not reached; the helpers'
                # cache as it stands now decides which blocks the probe reads from their
                # Jacobian kernels (the child's compiles must not change the probe's way,
                # docs/performance.md)
                # (the robot-model blocks' update/output wrappers first: the probe runs
                # them after probing the other blocks, docs/performance.md)
                with helpers_cache_as_now():
                    compiling = start_kernels(modules.deps, parent_busy=math.inf,
                                              first=probe_wrappers(plan, modules))
                    try:
                        tables = diagram_tables(plan, modules, key)
                    except BaseException:
                        compiling.cancel()
                        raise
            self.program = DiagramProgram(modules.deps, modules.wrappers, tables)
            if all(name in sys.modules for name, _ in modules.deps):
                self.module = load_c_stepper()      # nothing to compile: no thread
            else:
                # the C stepper is built (or loaded) on a thread while this process
                # compiles its kernels: the C compiler is a process of its own
                with ThreadPoolExecutor(1, thread_name_prefix="ivdrem-cstepper") as pool:
                    pending = pool.submit(load_c_stepper)
                    try:
                        compiling.finish()
                    finally:
                        self.module = pending.result()
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

    def bind(self, W):
        """Put this diagram's kernel addresses into workspace W (its tables are W.tables)."""
        W.kernels[:self.n_kernels] = self._kernels

    def block_failure(self, exc, W):
        """(BlockError, cause) for a kernel that raised inside the compiled code (recorded in
        W.failure by the diagram functions), or None if `exc` is not that.  The cause is the
        block's own exception: kept by a Python block's callback, or reproduced by running
        the block's Python function at the recorded point."""
        if not (isinstance(exc, RuntimeError) and str(exc) == BLOCK_RAISED_MESSAGE):
            return None
        name, role, _ = self.wrappers[int(W.failure[0])]
        t = float(W.failure[1])
        b = next(b for b in self.plan.blocks if b.sys.name == name)
        errs = getattr(b.spec, "error", None)
        cause = None
        if errs:                       # a Python block: its own exception, kept by the callback
            cause, t = errs[0]
            errs.clear()
        else:
            x = np.array(W.failure[2:2 + b.sys.nstates])
            u = np.array(W.us[b.u])
            params = effective_params(b.sys, self.plan.diagram, self.plan.params)
            try:
                if role == "jacobian":     # its Python kernel into a buffer of its own shape
                    ny, nx, nu = b.sys.noutputs, b.sys.nstates, b.sys.ninputs
                    flat_kernel(b.spec, "jacobian")(t, x, u, np.zeros((ny + nx, nx + nu)),
                                                    *kernel_args(b.spec, params))
                else:
                    fn = b.sys.updfcn if role == "update" else b.sys.outfcn
                    fn(t, x, u, params)
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
            named = self.block_failure(e, args[0])      # every caller passes W first
            if named is None:
                raise
            if named[1] is not None and not isinstance(named[1], Exception):
                raise named[1]      # Ctrl-C (KeyboardInterrupt), SystemExit: not the block's
            raise named[0] from named[1]

    def after_step(self, t, x, W):
        return self._run(self.module.diagram_eval, W, self.P, _stepper_codes.AFTER_STEP, t, x, x)

    def record(self, t, x, W, row):
        self._run(self.module.diagram_eval, W, self.P, _stepper_codes.RECORD, t, x, row)

    def rhs(self, t, x, W):
        dx = np.zeros_like(x)
        self._run(self.module.diagram_eval, W, self.P, _stepper_codes.RHS, t, x, dx)
        return dx

    # ---- Jacobian and Newton matrix, callable from Python (tests, benchmarks)
    def jacobian(self, t, x, W, *, dense=False):
        """df/dx at (t, x) as the generated diagram_jacobian computes it (n x n array; the
        stepper keeps it in the LU pattern's order, tables.jacobian_positions);
        dense=True: the whole-system forward-difference fallback fd_jacobian instead."""
        x = np.ascontiguousarray(x, dtype=float)
        tb = self.tables
        if dense:
            J = np.zeros((x.size, x.size))
            st = self._run(self.module.fd_jacobian, W, self.P, float(t), x, J)
        else:
            J = np.zeros(int(tb.lu_rowptr[-1]))
            st = self._run(self.module.diagram_jacobian, W, self.P, float(t), x, J)
        if st != _stepper_codes.OK:
            raise RuntimeError(f"diagram_jacobian returned status {st}")
        return J if dense else sparse_to_dense(J, tb.lu_perm, tb.lu_rowptr, tb.lu_colidx)

    def factor(self, J, c, *, dense=False):
        """Factor c I - J (J: n x n) with the generated newton_factor (the static-pattern
        sparse LU, which sees J only at its pattern's positions), or with dense=True the
        partial-pivoting dense_factor: (status, LU, piv)."""
        J = np.ascontiguousarray(J, dtype=float)
        n = J.shape[0]
        piv = np.zeros(n, dtype=np.int64)
        tb = self.tables
        if dense:
            LU = np.zeros((n + 2, n))
            st = self.module.dense_factor(J, float(c), LU, piv)
        else:
            LU = np.zeros(int(tb.lu_rowptr[-1]) + LU_WORK_ROWS * n)
            st = self.module.slu_factor(dense_to_sparse(J, tb.lu_perm, tb.lu_rowptr,
                                                        tb.lu_colidx), n, float(c), LU, piv,
                                        tb.lu_perm, tb.lu_rowptr, tb.lu_colidx, tb.lu_diagp,
                                        tb.lu_panel_rows, tb.lu_panel_kptr, tb.lu_panel_k)
        return int(st), LU, piv

    def solve(self, LU, piv, b, *, dense=False):
        """(c I - J)^{-1} b for a factorisation from :meth:`factor` (b is not modified)."""
        out = np.array(b, dtype=float)
        tb = self.tables
        if dense:
            self.module.dense_solve(LU, piv, out)
        else:
            self.module.slu_solve(LU, out.size, tb.lu_perm, tb.lu_rowptr, tb.lu_colidx,
                                  tb.lu_diagp, out)
        return out
