"""The kernels' temporaries on the stack (ivdrem.blocks._kernels.stack_empty).

Oracles: np.empty's own semantics (shape, dtype, writable, independent arrays), the plain
Python path of the same function (the reference engine's), numba's allocation counter
(NUMBA_NRT_STATS, in a child process: the counter is fixed when numba starts), and the
paper's loop's theta_hat against the same loop on the reference engine.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
from numba import njit

from ivdrem.blocks._kernels import as_matrix, mixing_values, stack_empty


@njit(cache=False)
def _fill(n, m):
    A = stack_empty((n, m))
    v = stack_empty(n)
    p = stack_empty(m, np.int64)
    for i in range(n):
        acc = 0.0
        for j in range(m):
            A[i, j] = 1.5 * i - j
            acc += A[i, j]
        v[i] = acc
    for j in range(m):
        p[j] = 3 * j
    return A.copy(), v.copy(), p.copy(), A.shape, v.shape, p.itemsize


def _calls(k):
    # the temporaries of one call do not alias another's: a deeper call fills its own
    out = []
    for n in range(1, k + 1):
        out.append(_fill(n, n + 2))
    return out


def test_compiled_equals_plain_python():
    for n, m in ((1, 1), (2, 5), (7, 70), (0, 3), (3, 0)):
        got = _fill(n, m)
        ref = _fill.py_func(n, m)
        assert got[3] == (n, m) and got[4] == (n,)
        assert got[5] == 8
        np.testing.assert_array_equal(got[0], ref[0])
        np.testing.assert_array_equal(got[1], ref[1])
        np.testing.assert_array_equal(got[2], ref[2])
        assert got[2].dtype == np.int64


def test_repeated_calls_independent():
    a = _calls(6)
    for n, (A, v, p, *_rest) in enumerate(a, start=1):
        np.testing.assert_array_equal(A, (1.5 * np.arange(n)[:, None] - np.arange(n + 2)))
        np.testing.assert_array_equal(v, A.sum(axis=1))
        np.testing.assert_array_equal(p, 3 * np.arange(n + 2))


def test_plain_python_is_np_empty():
    a = stack_empty((2, 3))
    b = stack_empty(4, np.int64)
    assert a.shape == (2, 3) and a.dtype == np.float64 and a.flags.writeable
    assert b.shape == (4,) and b.dtype == np.int64


def test_mixing_values_same_as_python_path():
    # the paper's mixing's LU scratch (P, P^-1, one vector, pivots) on the stack: the same
    # bits as the plain Python evaluation of the same kernel, on the LU and the SVD route
    rng = np.random.default_rng(7)
    for n in (3, 5, 8):
        for k in range(20):
            Psi = rng.standard_normal((n, n))
            if k % 4 == 0:               # rank n - 1: the SVD route
                Psi = rng.standard_normal((n, n - 1)) @ rng.standard_normal((n - 1, n))
            Y = rng.standard_normal(n)
            outs = []
            # the compiled step against its plain Python source (the paper's variant)
            python = lambda code, *a: mixing_values.variants[code].py_func(*a)  # noqa: E731
            for fn in (mixing_values, python):
                D, cY, lD = np.empty(1), np.empty(n), np.empty(1)
                fn(0, Y, Psi.ravel().copy(), 1e-6, 1e-3, D, cY, lD)
                outs.append((D, cY, lD))
            for a, b in zip(*outs):
                np.testing.assert_allclose(a, b, rtol=1e-13, atol=0.0)


_CHILD = r"""
import json, warnings
import numba
from numba.core.runtime import rtsys
from ivdrem.diagrams import closed_loop
from ivdrem.sim import simulate
warnings.simplefilter("ignore")
d = closed_loop("iv-drem")
simulate(d, 0.5, progress=False)
a = rtsys.get_allocation_stats()
r = simulate(d, 5.0, progress=False, return_states=False)
b = rtsys.get_allocation_stats()
print(json.dumps({"allocs": b.alloc - a.alloc, "frees": b.free - a.free,
                  "rhs": r.stats["rhs_calls"], "jac": r.stats["jacobians"]}))
"""


def test_paper_loop_kernels_do_not_allocate_per_call():
    # numba heap arrays over the first 5 s of the paper's loop (674 right-hand sides, 74
    # Jacobians): 16,512 before the stack scratch (24.5 per right-hand side), 3,389 with it:
    # the right-hand side's block kernels take none; what is left is the model's Cholesky
    # factor in the plant (one per right-hand side) and the closed-form Jacobian kernels'
    # temporaries (per Jacobian)
    env = dict(os.environ, NUMBA_NRT_STATS="1")
    p = subprocess.run([sys.executable, "-c", _CHILD], capture_output=True, text=True,
                       env=env, timeout=1800)
    assert p.returncode == 0, p.stderr[-2000:]
    s = json.loads(p.stdout.strip().splitlines()[-1])
    assert s["rhs"] > 100
    assert s["allocs"] == s["frees"]
    per_rhs = s["allocs"] / s["rhs"]
    assert per_rhs < 6.0, s


# ------------------------------------------------------------------ as_matrix
@njit(cache=False)
def _views(v, n, m):
    u = v[2:2 + n * m]                  # a slice of a contiguous vector, as a kernel's port
    A = as_matrix(u, n, m)
    B = u.reshape((n, m))
    A[1, 1] += 100.0                    # a view: writes reach the vector
    return A.copy(), B.copy(), A.shape, A.strides, B.strides


@njit(cache=False)
def _wrong_size(v, n, m):
    return as_matrix(v, n, m).sum()


def test_as_matrix_is_numpy_s_reshape_without_a_copy():
    """Compiled, as_matrix of a contiguous vector is reshape's view (shape, strides, values)
    sharing the vector's memory; a shape that does not match the size is an error, as
    reshape's; in plain Python it is reshape."""
    import pytest
    from ivdrem.blocks._kernels import as_matrix as plain
    v = np.arange(20.0)
    A, B, shape, sa, sb = _views(v, 3, 4)
    assert shape == (3, 4) and sa == sb == (32, 8)
    assert v[2 + 4 + 1] == 107.0 and A[1, 1] == 107.0 and B[1, 1] == 107.0
    assert np.array_equal(A, v[2:14].reshape(3, 4)) and np.array_equal(A, B)
    with pytest.raises(ValueError, match="size"):
        _wrong_size(np.arange(20.0), 3, 4)
    w = np.arange(6.0)
    P = plain(w, 2, 3)
    assert P.base is w and np.array_equal(P, w.reshape(2, 3))
