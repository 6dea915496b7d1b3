"""Calls to C functions by address from compiled code (FMU functions, Python callbacks).

A leaf of the package's base layer (docs/developers.md, "Layout"): the block kernels'
helpers (:mod:`ivdrem.blocks._kernels`), the simulator's generated wrappers and the models'
generated C faces all call through it, so it imports nothing of ivdrem.

A C function's address is a runtime value (it changes from process to process), so it is
passed in as an integer rather than baked into the machine code: the generated diagram
modules stay cacheable on disk.  ``call_c(address, args)`` calls ``int f(args...)`` with
the C calling convention; each argument is an integer (pointers and sizes: pass
``array.ctypes.data`` for an array) or a float64 (a C ``double``).  The same call works
from plain Python (through ctypes), so a kernel that uses it runs in both worlds.
"""
from ctypes import CFUNCTYPE, c_double, c_int32, c_int64

from llvmlite import ir
from numba import types
from numba.extending import intrinsic, overload

__all__ = ["call_c", "float_pointer"]

_CTYPES_FUNCTIONS = {}


def call_c(address, args):
    """int32 f(*args) for the C function at `address`; `args` a tuple of ints and floats
    (from Python: through ctypes; from numba code: a direct call, see _call_c)."""
    sig = tuple(c_double if isinstance(a, float) else c_int64 for a in args)
    fn_type = _CTYPES_FUNCTIONS.get(sig)
    if fn_type is None:
        fn_type = _CTYPES_FUNCTIONS[sig] = CFUNCTYPE(c_int32, *sig)
    return int(fn_type(int(address))(*[float(a) if isinstance(a, float) else int(a)
                                        for a in args]))


@overload(call_c)
def _call_c_overload(address, args):
    def impl(address, args):
        return _call_c(address, args)
    return impl


@intrinsic
def _call_c(typingctx, address, args):
    """int32 f(*args) for the C function at `address` (int64); `args` a tuple of
    int64 / uint64 / float64 values."""
    if not (isinstance(address, types.Integer) and isinstance(args, types.BaseTuple)
            and all(isinstance(a, (types.Integer, types.Float)) for a in args.types)):
        return None
    sig = types.int32(address, args)

    def codegen(context, builder, signature, llargs):
        addr, tup = llargs
        argtys = []
        vals = []
        for i, a in enumerate(args.types):
            v = builder.extract_value(tup, i)
            if isinstance(a, types.Integer):
                v = context.cast(builder, v, a, types.int64)
                argtys.append(ir.IntType(64))
            else:
                v = context.cast(builder, v, a, types.float64)
                argtys.append(ir.DoubleType())
            vals.append(v)
        fnty = ir.FunctionType(ir.IntType(32), argtys)
        addr64 = context.cast(builder, addr, address, types.int64)
        fn = builder.inttoptr(addr64, fnty.as_pointer())
        return builder.call(fn, vals)
    return sig, codegen


@intrinsic
def float_pointer(typingctx, address):
    """A float64 pointer from an address (for numba.carray in C-callable wrappers)."""
    if not isinstance(address, types.Integer):
        return None
    sig = types.CPointer(types.float64)(address)

    def codegen(context, builder, signature, llargs):
        addr64 = context.cast(builder, llargs[0], address, types.int64)
        return builder.inttoptr(addr64, context.get_value_type(types.CPointer(types.float64)))
    return sig, codegen
