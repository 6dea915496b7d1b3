"""A URDF model's functions from its C face, compiled once instead of by numba.

numba compiling the recursive Newton-Euler kernels (:mod:`ivdrem.models.rigid_body`, float64
and complex128) was most of a new machine's first run on a real arm (docs/performance.md,
"First run").  The same kernels printed to C (``RigidBodyModel.engine_c_source``: the C face
and the regressors' derivatives) compile in a few seconds with the machine's C compiler
(:mod:`ivdrem._cc`), once per model: the library is kept in the compile cache
(``models/<key>-<ivdrem version>-engine.so``) and

* :func:`python_functions` calls it through ctypes (``model.functions``: the reference
  engine, the sparsity probe, the γ "auto" estimate);
* :func:`numba_source` is the compiled engine's model module: thin numba functions calling
  the library's functions by symbol name (``numba.types.ExternalFunction``; the library is
  registered with LLVM by :func:`load` before the module compiles or loads its cached machine
  code, so the cache never holds an address of another process).  Symbols are named by the
  model's key (``ivdrem_<key>_Phi``), so two models never share one.

Without a C compiler (:class:`ivdrem._cc.CompilerNotFound`) :func:`load` returns None and
the model keeps its numba path (``RigidBodyModel.source``): the same numbers
(tests/test_c_engine.py), compiled by numba on the first run instead.  A compiler that is
there but fails to build the library (:class:`ivdrem._cc.CompilerError`: a broken
installation, a missing header) does the same, once per process and library, with a
warning that quotes the compiler's first error.
"""
from __future__ import annotations

import ctypes
import os
import tempfile
import warnings

import numpy as np

from .base import C_FUNCTION_ARGS, SINGULAR_INERTIA_MESSAGE

__all__ = ["load", "library_path", "symbol_prefix", "python_functions", "numba_source",
           "ENGINE_FUNCTIONS"]

#: the library's functions and their array arguments (the last one written), in order
ENGINE_FUNCTIONS = {**{k: v for k, v in C_FUNCTION_ARGS.items() if k != "forward_dynamics_k"},
                    "Phi_M_jac": ("q", "a", "out"), "Phi_C_jac": ("q", "dq", "v", "out"),
                    "Phi_dM_jac": ("q", "dq", "a", "out"), "Phi_G_jac": ("q", "out"),
                    "Phi_F_jac": ("dq", "out"), "Phi_jac": ("q", "dq", "v", "dv", "out")}

_LOADED: dict = {}          # library path -> ctypes.CDLL (registered with LLVM too)
_FAILED: dict = {}          # library path -> the CompilerError of this process's build


def symbol_prefix(key: str) -> str:
    """The prefix of the library's symbols for the model of key `key`."""
    return f"ivdrem_{key[:16]}_"


def library_path(key: str):
    """Where the library of the model of key `key` is kept (named by the key and ivdrem's
    version, like the models' generated source)."""
    from .. import __version__
    from ..compile_cache import cache_dir
    return cache_dir() / "models" / f"{key[:32]}-{__version__}-engine.so"


def out_shapes(model) -> dict:
    """The shape of each function's output (the C functions write exactly that many)."""
    n, nb = model.n, model.ntheta
    shapes = {"M": (n, n), "C": (n, n), "G": (n,), "F": (n,), "forward_dynamics": (n,)}
    for name, args in ENGINE_FUNCTIONS.items():
        if name.startswith("Phi"):
            k = len(args) - 1
            shapes[name] = (n, nb, k * n) if name.endswith("_jac") else (n, nb)
    return shapes


def load(model, cc=None):
    """The model's C library (built into the compile cache if it is not there), loaded for
    ctypes and registered with LLVM for numba; None when there is no C compiler, or when
    the compiler fails to build it (a RuntimeWarning with its first error, once): the
    model then keeps its numba path."""
    from .._cc import CompilerError, CompilerNotFound, compiler
    path = library_path(model.key)
    lib = _LOADED.get(str(path))
    if lib is not None:
        return lib
    if str(path) in _FAILED:
        return None
    if not path.is_file():
        try:
            cc = compiler(cc)
        except CompilerNotFound:
            return None
        try:
            _build(model, path, cc)
        except CompilerError as exc:
            _FAILED[str(path)] = exc
            warnings.warn(f"{exc}; the functions of model {model.name} run from the numba "
                          "kernels instead (the first run compiles them: minutes on a real "
                          "arm)", RuntimeWarning, stacklevel=2)
            return None
    return _register(path)


def _build(model, path, cc):
    """Compile the model's C library into `path` (atomically: two processes may build it
    at once); a failed build raises :class:`ivdrem._cc.CompilerError`."""
    from .._cc import compile_shared
    from .._progress import preparing
    path.parent.mkdir(parents=True, exist_ok=True)
    with preparing(f"compiling the C functions of model {model.name} (n = {model.n}, "
                   f"{model.ntheta} parameters)", cached_in=path.parent):
        with tempfile.TemporaryDirectory(dir=path.parent) as tmp:
            src = os.path.join(tmp, "model.c")
            with open(src, "w", encoding="utf-8") as f:
                f.write(model.engine_c_source(symbol_prefix(model.key)))
            built = os.path.join(tmp, path.name)
            compile_shared([src], built, what=f"the C functions of model {model.name}", cc=cc)
            os.replace(built, path)


def _register(path):
    import llvmlite.binding as llvm
    lib = ctypes.CDLL(str(path))
    llvm.load_library_permanently(str(path))
    _LOADED[str(path)] = lib
    return lib


def require(key: str):
    """Load the library of the model of key `key` (the compiled engine's model module does
    this when it is imported: :func:`load` built it before)."""
    path = library_path(key)
    if str(path) not in _LOADED:
        if not path.is_file():
            raise ImportError(f"the C library of model {key[:16]} is not in the compile cache "
                              f"({path}): build it with ivdrem.models._c_engine.load(model)")
        _register(path)


def python_functions(model, lib):
    """The model's functions (the names and signatures of ``model.functions``) calling the
    library `lib` through ctypes; arguments are checked for size (the C functions read and
    write exactly the model's sizes) and copied when not contiguous float64."""
    import types
    pre = symbol_prefix(model.key)
    shapes = out_shapes(model)
    ns = {}
    for name, args in ENGINE_FUNCTIONS.items():
        fn = getattr(lib, pre + name)
        fn.argtypes = [ctypes.c_void_p] * len(args)
        fn.restype = ctypes.c_int if name == "forward_dynamics" else None
        ns[name] = _ctypes_function(model, name, args, fn, shapes[name])
    return types.SimpleNamespace(**ns)


def _ctypes_function(model, name, args, fn, out_shape):
    n, nb = model.n, model.ntheta
    sizes = [nb if a == "theta" else n for a in args[:-1]]

    def call(*values):
        if len(values) != len(args):
            raise TypeError(f"{name}() takes {len(args)} arguments ({', '.join(args)}), "
                            f"got {len(values)}")
        ins = []
        for a, v, size in zip(args, values, sizes):
            v = np.ascontiguousarray(v, dtype=np.float64)
            if v.size != size:
                raise ValueError(f"{name}: {a} must have {size} entries, got shape {v.shape}")
            ins.append(v)
        out = values[-1]
        if not isinstance(out, np.ndarray) or out.shape != out_shape:
            raise ValueError(f"{name}: out must be an array of shape {out_shape}, got "
                             f"{getattr(out, 'shape', type(out).__name__)}")
        direct = out.dtype == np.float64 and out.flags.c_contiguous and out.flags.writeable
        o = out if direct else np.empty(out_shape)
        status = fn(*[v.ctypes.data for v in ins], o.ctypes.data)
        if not direct:
            out[...] = o
        if name == "forward_dynamics" and status != 0:
            raise ValueError(SINGULAR_INERTIA_MESSAGE)
        return None
    call.__name__ = call.__qualname__ = name
    call.__doc__ = f"{name}({', '.join(args)}): the model's C function (ivdrem.models._c_engine)"
    return call


def _copy_back(out, nd):
    """Lines copying the contiguous result o into `out` (nd dimensions) entry by entry:
    numba compiles ``out[:, :] = o`` with its shape-mismatch error, whose message
    formatting cost about 2 s of compile per dimension count in every process that
    compiled a model module (docs/performance.md); the loops copy the same values."""
    idx = ", ".join(f"i{k}" for k in range(nd))
    lines = [f"{'    ' * (k + 2)}for i{k} in range(o.shape[{k}]):" for k in range(nd)]
    return lines + [f"{'    ' * (nd + 2)}{out}[{idx}] = o[{idx}]"]


def numba_source(model) -> str:
    """Python source of the compiled engine's model module for `model` (its library built
    by :func:`load`): every function of ``model.functions`` as a function calling the C
    function of the same name (arguments copied when not contiguous); the module compiles
    every function with ``njit(cache=True)`` (ivdrem.sim.compiled)."""
    pre = symbol_prefix(model.key)
    shapes = out_shapes(model)
    lines = [f"# the C library of model {model.name} (ivdrem.models._c_engine), key {model.key}",
             "import numpy as np",
             "from numba import types as _nt",
             "from ivdrem.models import _c_engine as _ce",
             "from ivdrem._native_call import float_pointer as _fp",
             f"_ce.require({model.key!r})",
             "_P = _nt.CPointer(_nt.float64)", ""]
    for name, args in ENGINE_FUNCTIONS.items():
        ret = "_nt.int32" if name == "forward_dynamics" else "_nt.void"
        sig = ", ".join(["_P"] * len(args))
        lines.append(f"_c_{name} = _nt.ExternalFunction({pre + name!r}, {ret}({sig}))")
    lines.append("")
    for name, args in ENGINE_FUNCTIONS.items():
        vals = ", ".join(args)
        ptrs = ", ".join(f"_fp({a}.ctypes.data)" for a in args)
        nd = len(shapes[name])
        contiguous = " and ".join(f"{a}.flags.c_contiguous" for a in args)
        copies = ", ".join(f"np.ascontiguousarray({a})" for a in args[:-1])
        status = "s = " if name == "forward_dynamics" else ""
        lines += [
            f"def _call_{name}({vals}):",
            "    # every array C-contiguous float64 of the model's sizes, alive for the call",
            f"    {'return ' if status else ''}_c_{name}({ptrs})",
            "",
            "",
            f"def {name}({vals}):",
            f"    if {contiguous}:",
            f"        {status}_call_{name}({vals})",
            "    else:",
            f"        o = np.empty({args[-1]}.shape)",
            f"        {status}_call_{name}({copies}, o)",
            *_copy_back(args[-1], nd),
        ]
        if status:
            lines += ["    if s != 0:", f"        raise ValueError({SINGULAR_INERTIA_MESSAGE!r})"]
        lines += ["    return None", "", ""]
    return "\n".join(lines)


def _check_names():
    # the library's functions are the model functions of every engine (ivdrem.models.base)
    from .base import FUNCTION_NAMES
    assert set(ENGINE_FUNCTIONS) == set(FUNCTION_NAMES), set(FUNCTION_NAMES) ^ set(ENGINE_FUNCTIONS)


_check_names()
del _check_names
