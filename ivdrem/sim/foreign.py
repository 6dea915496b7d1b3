"""Blocks ivdrem did not write: python-control's own systems in an ivdrem diagram.

For a block without an ivdrem declaration (``sys.ivdrem``, a
:class:`~ivdrem.blocks.BlockSpec`) this reads its direct feedthrough (:func:`direct_inputs`:
D of a StateSpace, :func:`declare_feedthrough`, else :func:`probe_feedthrough`) and makes its
kernels for the compiled engine (:func:`adapt_block`: linear, compiled by numba, or called
back into Python).  docs/simulation.md, "Blocks ivdrem did not write", says the same for
users.
"""
from __future__ import annotations

import ast
import ctypes
import inspect
import math
import re
import textwrap
import types
import warnings
from dataclasses import dataclass, field

import numpy as np
import control as ct

from .. import __version__
from ..blocks._core import BlockSpec
from ..compile_cache import GENERATED_HEADER, cache_dir, import_generated, source_hash

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
    fn = getattr(sys, "outfcn", None)      # None: the outputs are the states
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


# --------------------------------------------------------------------------- adapters
@dataclass
class ForeignSpec(BlockSpec):
    """A BlockSpec made for a block ivdrem did not write (see :func:`adapt_block`).

    `sources` maps a kernel role ("update", "output", "jacobian") to (function name,
    module source): the compiled path imports the function from that source instead of
    reading a library kernel's.  `update` / `output` / `jacobian` are Python callables with
    the same flat signature, used where the engine evaluates kernels in Python (the
    Jacobian's sparsity probe).  `runs` is "linear", "numba" or "python" (called back);
    `reason` says why a block runs in Python.
    """
    sources: dict = field(default_factory=dict)
    runs: str = "linear"
    reason: str = ""
    convention: str = "flat"        # kernels take flat x, u, out vectors
    keepalive: list = field(default_factory=list)   # ctypes callbacks, exceptions
    error: list = field(default_factory=list)       # [(exception, t)] raised in Python

    def kernel_key(self, role):
        return ("foreign", source_hash(self.sources[role][1]))


def _exec_functions(src):
    """The functions a generated kernel source defines, as plain Python functions."""
    ns = {"np": np, "math": math}
    exec(compile(src, "<ivdrem foreign kernel>", "exec"), ns)
    return ns


def _ports(sys):
    """(inputs, outputs, states) as BlockSpec ports: one port per signal label."""
    return tuple([(lab, 1) for lab in getattr(sys, f"{kind}_labels")]
                 for kind in ("input", "output", "state"))


def _linear_spec(sys):
    """Kernels y = C x + D u, dx = A x + B u with the matrices as parameters; D only
    over its nonzero columns, so the declared feedthrough is exactly what the code reads."""
    nx, nu, ny = sys.nstates, sys.ninputs, sys.noutputs
    mats = {k: np.asarray(getattr(sys, k), dtype=float).reshape(shape) for k, shape in
            (("A", (nx, nx)), ("B", (nx, nu)), ("C", (ny, nx)), ("D", (ny, nu)))}
    dcols = tuple(int(i) for i in np.flatnonzero(np.any(mats["D"] != 0.0, axis=0)))
    tag = source_hash(f"{nx},{nu},{ny},{dcols}")
    dloop = (f"        for j in {dcols!r}:\n            s += D[i, j] * u[j]\n"
             if dcols else "")
    out_src = (f"def linear_output_{tag}(t, x, u, y, A, B, C, D):\n"
               f"    for i in range({ny}):\n"
               "        s = 0.0\n"
               f"        for j in range({nx}):\n            s += C[i, j] * x[j]\n"
               f"{dloop}"
               "        y[i] = s\n")
    upd_src = (f"def linear_update_{tag}(t, x, u, dx, A, B, C, D):\n"
               f"    for i in range({nx}):\n"
               "        s = 0.0\n"
               f"        for j in range({nx}):\n            s += A[i, j] * x[j]\n"
               f"        for j in range({nu}):\n            s += B[i, j] * u[j]\n"
               "        dx[i] = s\n")
    # exact local Jacobian: rows outputs then derivatives, columns states then inputs
    jac_src = (f"def linear_jacobian_{tag}(t, x, u, jac, A, B, C, D):\n"
               f"    for i in range({ny}):\n"
               f"        for j in range({nx}):\n            jac[i, j] = C[i, j]\n"
               f"        for j in range({nu}):\n            jac[i, {nx} + j] = D[i, j]\n"
               f"    for i in range({nx}):\n"
               f"        for j in range({nx}):\n            jac[{ny} + i, j] = A[i, j]\n"
               f"        for j in range({nu}):\n            jac[{ny} + i, {nx} + j] = B[i, j]\n")
    sources = {"output": (f"linear_output_{tag}", out_src),
               "jacobian": (f"linear_jacobian_{tag}", jac_src)}
    if nx:
        sources["update"] = (f"linear_update_{tag}", upd_src)
    py = {role: _exec_functions(src)[name] for role, (name, src) in sources.items()}
    ins, outs, states = _ports(sys)
    return ForeignSpec(
        name=sys.name, inputs=ins, outputs=outs, states=states, x0=np.zeros(nx),
        param_names=("A", "B", "C", "D"), output=py["output"], update=py.get("update"),
        jacobian=py["jacobian"], direct=tuple(ins[i][0] for i in dcols),
        validate=lambda p, m=mats: dict(m), sources=sources, runs="linear")


class _NotCompilable(Exception):
    """Why a user function cannot be compiled by numba (the block runs in Python)."""


class _ParamsToArgs(ast.NodeTransformer):
    """params["k"] and params.get("k", default) -> a kernel argument (or the default when
    the block has no parameter k); any other use of params is not compilable."""

    def __init__(self, pname, params):
        self.pname, self.params = pname, params
        self.keys = []            # in argument order
        self.other_use = False

    def arg(self, key):
        if key not in self.keys:
            self.keys.append(key)
        return ast.Name(id=f"_param_{self.keys.index(key)}", ctx=ast.Load())

    def visit_Subscript(self, node):
        if (isinstance(node.value, ast.Name) and node.value.id == self.pname
                and isinstance(node.slice, ast.Constant) and isinstance(node.slice.value, str)
                and isinstance(node.ctx, ast.Load)):
            if node.slice.value not in self.params:
                raise _NotCompilable(f"reads params[{node.slice.value!r}], which the block "
                                     "does not have")
            return self.arg(node.slice.value)
        return self.generic_visit(node)

    def visit_Call(self, node):
        f = node.func
        if (isinstance(f, ast.Attribute) and f.attr == "get" and isinstance(f.value, ast.Name)
                and f.value.id == self.pname and node.args
                and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)
                and not node.keywords and len(node.args) <= 2):
            key = node.args[0].value
            if key in self.params:
                return self.arg(key)
            if len(node.args) == 2:
                return self.visit(node.args[1])
            return ast.Constant(value=None)
        return self.generic_visit(node)

    def visit_Name(self, node):
        if node.id == self.pname:
            self.other_use = True
        return node


def _function_node(fn, role):
    try:
        src = textwrap.dedent(inspect.getsource(fn))
    except (OSError, TypeError) as e:
        raise _NotCompilable(f"the source of its {role} function is not available ({e})")
    tree = ast.parse(src)
    defs = [n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == fn.__name__]
    if len(defs) != 1:
        raise _NotCompilable(f"cannot read the source of its {role} function")
    defs[0].decorator_list = []
    return defs[0]


def _globals_lines(fn, role, extra, seen):
    """Module lines giving `fn` its globals: numpy / math imports, numeric constants as
    literals, and the user's own helper functions (their source, recursively)."""
    if fn.__closure__:
        raise _NotCompilable(f"{fn.__name__} (used by its {role} function) is a closure")
    cv = inspect.getclosurevars(fn)
    for g, val in sorted(cv.globals.items()):
        val = getattr(val, "py_func", val)      # a helper already decorated with njit
        if val is np:
            line = f"import numpy as {g}"
        elif val is math:
            line = f"import math as {g}"
        elif isinstance(val, (bool, int, float)):
            line = f"{g} = {val!r}"
        elif isinstance(val, types.FunctionType) and val.__name__ == g \
                and val.__name__ != "<lambda>":
            if g in seen:
                continue
            seen.add(g)
            _globals_lines(val, role, extra, seen)
            line = ast.unparse(_function_node(val, role))
        else:
            raise _NotCompilable(f"its {role} function uses the global {g!r} "
                                 f"({type(val).__name__})")
        if line not in extra:
            extra.append(line)


def _user_function_source(fn, role, params):
    """(source of the renamed user function taking its parameters as arguments, parameter
    keys, extra module lines); raises _NotCompilable with the reason."""
    fn = getattr(fn, "py_func", fn)      # a function the user already decorated with njit
    if not isinstance(fn, types.FunctionType):
        raise _NotCompilable(f"its {role} function is a {type(fn).__name__}, not a def")
    if fn.__name__ == "<lambda>":
        raise _NotCompilable(f"its {role} function is a lambda")
    extra = []
    _globals_lines(fn, role, extra, set())
    node = _function_node(fn, role)
    a = node.args
    if (len(a.args) != 4 or a.vararg or a.kwarg or a.kwonlyargs or a.posonlyargs
            or a.defaults):
        raise _NotCompilable(f"its {role} function does not have the signature "
                             "(t, x, u, params)")
    pname = a.args[3].arg
    tr = _ParamsToArgs(pname, params)
    node.body = [tr.visit(stmt) for stmt in node.body]
    if tr.other_use:
        raise _NotCompilable(f"its {role} function uses {pname!r} other than as "
                             f"{pname}['name'] or {pname}.get('name', default)")
    for k in tr.keys:
        v = params[k]
        if isinstance(v, (bool, np.bool_)) or np.asarray(v).dtype.kind not in "iuf" \
                or np.ndim(v) > 2:
            raise _NotCompilable(f"its parameter {k!r} is not a number or numeric array")
    node.name = f"_user_{role}"
    node.decorator_list = []
    a.args = a.args[:3] + [ast.arg(arg=f"_param_{i}") for i in range(len(tr.keys))]
    ast.fix_missing_locations(node)
    return ast.unparse(node), list(tr.keys), extra


def _nlsys_numba_spec(sys, params):
    """Kernels that call the user's own update/output code, compiled by numba."""
    nx, ny = sys.nstates, sys.noutputs
    roles = {}
    keys = []
    extra = []
    if nx:
        roles["update"] = (sys.updfcn, nx)
    if sys.outfcn is not None:
        roles["output"] = (sys.outfcn, ny)
    parts = {}
    for role, (fn, n) in roles.items():
        src, k, ex = _user_function_source(fn, role, params)
        parts[role] = (src, k, n)
        keys += [x for x in k if x not in keys]
        extra += [x for x in ex if x not in extra]
    pnames = tuple(f"p{i}" for i in range(len(keys)))
    sig = "".join(", " + p for p in pnames)
    sources = {}
    for role in ("update", "output"):
        if role == "update" and not nx:
            continue
        if role in parts:
            src, k, n = parts[role]
            call_args = "".join(", " + pnames[keys.index(x)] for x in k)
            body = (f"    r = np.asarray(_user_{role}(t, x, u{call_args}))\n"
                    f"    for i in range({n}):\n        out[i] = r.flat[i]\n")
            fsrc = "\n\n".join(extra) + "\n\n" + src + "\n\n"
        else:           # python-control: no output function means y = x
            body = f"    for i in range({ny}):\n        out[i] = x[i]\n"
            fsrc = ""
        tag = source_hash(fsrc + body + sig)
        name = f"nlsys_{role}_{tag}"
        sources[role] = (name, fsrc + f"def {name}(t, x, u, out{sig}):\n" + body)

    def python_kernel(role):
        fn = sys.updfcn if role == "update" else sys.outfcn
        n = nx if role == "update" else ny

        def kernel(t, x, u, out, *args):
            if fn is None:
                out[:] = x[:n]
                return
            p = dict(params)
            p.update(zip(keys, args))
            try:        # see _nlsys_python_spec: the sparsity probe skips such a point
                out[:] = np.asarray(fn(t, x, u, p), dtype=float).reshape(-1)
            except (ValueError, ArithmeticError):
                raise
            except Exception as e:
                raise ValueError(f"block '{sys.name}' raised {type(e).__name__}") from e
        return kernel
    ins, outs, states = _ports(sys)
    direct_idx = direct_inputs(sys, params)
    return ForeignSpec(
        name=sys.name, inputs=ins, outputs=outs, states=states, x0=np.zeros(nx),
        param_names=pnames, output=python_kernel("output"),
        update=python_kernel("update") if nx else None,
        direct=tuple(ins[i][0] for i in direct_idx),
        validate=lambda p: {pn: p[k] for pn, k in zip(pnames, keys)},
        sources=sources, runs="numba")


# a Python block's kernel, called from compiled code: int32 f(t, x*, u*, out*)
_CALLBACK = ctypes.CFUNCTYPE(ctypes.c_int32, ctypes.c_double, ctypes.c_int64, ctypes.c_int64,
                             ctypes.c_int64)


def _view(address, n):
    if n == 0:
        return np.zeros(0)
    return np.ctypeslib.as_array((ctypes.c_double * n).from_address(address))


def _nlsys_python_spec(sys, params, reason):
    """Kernels that call back into the block's Python functions through call_c."""
    nx, nu, ny = sys.nstates, sys.ninputs, sys.noutputs
    spec_box = []

    def make(role):
        fn = sys.updfcn if role == "update" else sys.outfcn
        n = nx if role == "update" else ny

        def evaluate(t, x, u, out):
            if fn is None:
                out[:] = x[:n]
            else:
                r = np.asarray(fn(t, x, u, params), dtype=float).reshape(-1)
                if r.size != n:
                    raise ValueError(f"block '{sys.name}': its {role} function returned "
                                     f"{r.size} values, expected {n}")
                out[:] = r

        def callback(t, px, pu, pout):
            try:
                evaluate(t, _view(px, nx).copy(), _view(pu, nu).copy(), _view(pout, n))
                return 0
            except BaseException as e:      # noqa: BLE001 - re-raised by the engine
                spec_box[0].error[:] = [(e, t)]
                return 1

        def python_kernel(t, x, u, out, *addresses):
            # evaluated in Python only by the Jacobian's sparsity probe, which skips a
            # point where a block refuses to evaluate (ValueError)
            try:
                evaluate(t, np.array(x, dtype=float), np.array(u, dtype=float), out)
            except (ValueError, ArithmeticError):
                raise
            except Exception as e:
                raise ValueError(f"block '{sys.name}' raised {type(e).__name__}") from e
        return callback, python_kernel

    sources, keep, py, addresses = {}, [], {}, {"update": 0.0, "output": 0.0}
    for role in ("update", "output"):
        if role == "update" and not nx:
            continue
        cb, pk = make(role)
        c = _CALLBACK(cb)
        keep.append(c)
        addresses[role] = float(ctypes.cast(c, ctypes.c_void_p).value)  # < 2**53: exact
        py[role] = pk
        name = f"python_{role}"
        sources[role] = (name, f"def {name}(t, x, u, out, address_update, address_output):\n"
                         f"    if call_c(np.int64(address_{role}), (t, x.ctypes.data, "
                         "u.ctypes.data, out.ctypes.data)) != 0:\n"
                         "        raise RuntimeError('a block running in Python raised')\n")
    ins, outs, states = _ports(sys)
    direct_idx = direct_inputs(sys, params)
    spec = ForeignSpec(
        name=sys.name, inputs=ins, outputs=outs, states=states, x0=np.zeros(nx),
        param_names=("address_update", "address_output"), output=py["output"],
        update=py.get("update"), direct=tuple(ins[i][0] for i in direct_idx),
        validate=lambda p: {"address_update": addresses["update"],
                            "address_output": addresses["output"]},
        sources=sources, runs="python", reason=reason, keepalive=keep)
    spec_box.append(spec)
    return spec


def foreign_module(fname, src):
    """(module name, source) of a generated kernel source of this module: every function
    it defines compiled by numba."""
    names = re.findall(r"^def\s+(\w+)\s*\(", src, flags=re.M)
    lines = [f"# Generated by ivdrem {__version__}: kernel {fname} of a block ivdrem did not "
             "write.", *GENERATED_HEADER, "", src, ""]
    lines += [f"{n} = njit(cache=True)({n})" for n in names] + [""]
    body = "\n".join(lines)
    return f"ivdrem_foreign_{source_hash(body)}", body


def _try_compile(spec, sys, params):
    """Compile the block's kernels now and call them once: any numba error means the
    block runs in Python instead.  Returns None, or the reason."""
    cdir = cache_dir()
    cdir.mkdir(parents=True, exist_ok=True)
    args = tuple(np.asarray(v, dtype=float) if np.ndim(v) else float(v)
                 for v in (spec.validate(dict(params)).values()))
    x = np.zeros(sys.nstates)
    u = np.zeros(sys.ninputs)
    for role, (fname, src) in spec.sources.items():
        mname, msrc = foreign_module(fname, src)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                mod = import_generated(cdir, mname, msrc)
                out = np.zeros(sys.nstates if role == "update" else sys.noutputs)
                getattr(mod, fname)(0.0, x, u, out, *args)
        except Exception as e:          # numba's typing errors, or the function itself
            first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            return f"numba cannot compile its {role} function ({first[:120]})"
    return None


def _check_returned_sizes(sys, params):
    """The block's functions return as many values as it declares states / outputs (the
    compiled kernels copy exactly that many).  A function failing at the zero point is
    not judged here: the run reports it, naming the block."""
    for role, fn, n, what in (("update", sys.updfcn, sys.nstates, "states"),
                              ("output", sys.outfcn, sys.noutputs, "outputs")):
        if fn is None or (role == "update" and not n):
            continue
        try:
            with np.errstate(all="ignore"):
                r = np.asarray(fn(0.0, np.zeros(sys.nstates), np.zeros(sys.ninputs),
                                  dict(params)), dtype=float).reshape(-1)
        except Exception:
            continue
        if r.size != n:
            raise ValueError(f"block '{sys.name}': its {role} function returns {r.size} "
                             f"values, but the block has {n} {what}")


def adapt_block(sys, params):
    """A ForeignSpec for a block without an ivdrem declaration (see the module doc)."""
    if isinstance(sys, ct.TransferFunction):
        sys = ct.ss(sys)
    if not (isinstance(sys, ct.StateSpace) or _is_plain_nlsys(sys)):
        raise TypeError(f"block '{sys.name}' is a {type(sys).__name__}; the compiled "
                        "path runs ivdrem blocks, StateSpace blocks and plain nlsys blocks")
    if not ct.isctime(sys) and sys.dt not in (None, 0):
        raise ValueError(f"block '{sys.name}' is a discrete-time system (dt = {sys.dt}); "
                         "the simulator integrates continuous-time diagrams")
    if isinstance(sys, ct.StateSpace):
        return _linear_spec(sys)
    params = dict(params)
    _check_returned_sizes(sys, params)
    try:
        spec = _nlsys_numba_spec(sys, params)
        reason = _try_compile(spec, sys, params)
        if reason is None:
            return spec
    except _NotCompilable as e:
        reason = str(e)
    return _nlsys_python_spec(sys, params, reason)
