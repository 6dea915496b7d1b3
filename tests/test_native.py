"""call_c: a C function called by address from compiled code (a ctypes callback here)."""
import ctypes

import numpy as np
from numba import njit

from ivdrem._native_call import call_c

_CB = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_double, ctypes.c_void_p, ctypes.c_int64)


def _scale(t, p, n):
    a = np.ctypeslib.as_array(ctypes.cast(p, ctypes.POINTER(ctypes.c_double)), (n,))
    a *= t
    return 7 if n == 3 else -1


@njit
def _call(address, t, x):
    return call_c(address, (t, x.ctypes.data, x.size))


def test_call_c_passes_double_pointer_and_size_and_returns_int():
    cb = _CB(_scale)
    address = ctypes.cast(cb, ctypes.c_void_p).value
    x = np.arange(3.0)
    assert _call(address, 2.5, x) == 7
    np.testing.assert_array_equal(x, [0.0, 2.5, 5.0])
    y = np.ones(2)
    assert _call(address, -1.0, y) == -1
    np.testing.assert_array_equal(y, [-1.0, -1.0])


def test_call_c_from_plain_python_is_the_same_call():
    cb = _CB(_scale)
    address = ctypes.cast(cb, ctypes.c_void_p).value
    x = np.arange(3.0)
    assert _call.py_func(address, 2.5, x) == 7
    np.testing.assert_array_equal(x, [0.0, 2.5, 5.0])
