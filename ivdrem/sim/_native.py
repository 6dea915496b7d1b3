"""Calls to C functions by address from compiled code (FMU functions, Python callbacks).

A C function's address is a runtime value (it changes from process to process), so it is
passed in as an integer rather than baked into the machine code: the generated diagram
modules stay cacheable on disk.  ``call_c(address, args)`` calls ``int f(args...)`` with
the C calling convention; each argument is an integer (pointers and sizes: pass
``array.ctypes.data`` for an array) or a float64 (a C ``double``).
"""
from llvmlite import ir
from numba import types
from numba.extending import intrinsic

__all__ = ["call_c"]


@intrinsic
def call_c(typingctx, address, args):
    """int32 f(*args) for the C function at `address` (int64); `args` a tuple of
    int64 / uint64 / float64 values."""
    if not isinstance(address, types.Integer):
        return None
    if not isinstance(args, types.BaseTuple):
        return None
    for a in args.types:
        if not isinstance(a, (types.Integer, types.Float)):
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
