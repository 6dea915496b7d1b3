"""What a first run compiles (docs/performance.md, "The first run on a real arm"): the mixing
functions one variant at a time (ivdrem.blocks._kernels: written once, compiled per variant,
a kernel's literal variant calling that one alone), a helper child compiling the mixing's
derivatives while γ "auto"'s estimate runs (ivdrem.sim._compile_child.start_helpers), and the
model module's strided fallback without a slice assignment."""
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from ivdrem.blocks import _kernels
from ivdrem.blocks._kernels import MIXING_VARIANTS, mixing_derivatives, mixing_values


def _fresh_env(tmp_path):
    """An environment whose numba cache and ivdrem cache are empty directories, and no
    prebuilt machine code (these tests count what a process compiles)."""
    env = dict(os.environ, IVDREM_CACHE_DIR=str(tmp_path / "cache"),
               NUMBA_CACHE_DIR=str(tmp_path / "numba"), IVDREM_PREBUILT_DIR="")
    for k in ("IVDREM_STEPPER_CHILD", "IVDREM_COMPILE_CHILD", "IVDREM_STEPPER_PREFETCH"):
        env.pop(k, None)
    return env


def _psi(n, seed, rank=None):
    rng = np.random.default_rng(seed)
    r = n if rank is None else rank
    return (rng.standard_normal((n, r)) @ rng.standard_normal((r, n))).ravel(), \
        rng.standard_normal(n)


@pytest.mark.parametrize("variant", MIXING_VARIANTS)
def test_each_variant_is_its_python_source_compiled(variant):
    # the compiled variant against the plain Python evaluation of the same source (the one
    # function the variants were), on the regular and the rank-deficient route: same bits
    code = MIXING_VARIANTS.index(variant)
    for n in (3, 6):
        for seed, rank in ((1, None), (2, n - 1), (3, n - 2)):
            Psi, Y = _psi(n, seed, rank)
            k = n if variant == "channel" else 1
            got = [np.empty(k), np.empty(n), np.empty(k)]
            want = [np.empty(k), np.empty(n), np.empty(k)]
            mixing_values(code, Y, Psi, 1e-6, 1e-3, *got)
            mixing_values.variants[code].py_func(Y, Psi, 1e-6, 1e-3, *want)
            for a, b in zip(got, want):
                assert np.array_equal(a, b, equal_nan=True), (variant, n, rank, a, b)
            J = np.zeros((2 * k + n, n + n * n))
            Jp = np.zeros_like(J)
            mixing_derivatives(code, Y, Psi, 1e-6, 1e-3, J)
            mixing_derivatives.variants[code].py_func(Y, Psi, 1e-6, 1e-3, Jp)
            assert np.array_equal(J, Jp), (variant, n, rank)


def test_any_code_besides_paper_and_eigen_is_channel():
    # the else branch of the function the variants were written as
    assert [_kernels._variant_index(c) for c in (0, 1, 2, 3, -1)] == [0, 1, 2, 2, 2]


_LITERAL = r"""
import json, sys
import numpy as np
from numba import njit
from ivdrem.blocks._kernels import mixing_values, mixing_derivatives

code = int(sys.argv[1])

@njit
def kernel(Y, Psi, D, cY, lD, J):      # the variant a structural constant, as in a wrapper
    mixing_values(2, Y, Psi, 1e-6, 1e-3, D, cY, lD)
    mixing_derivatives(2, Y, Psi, 1e-6, 1e-3, J)

@njit
def runtime(c, Y, Psi, D, cY, lD):     # the variant a value: chosen at run time
    mixing_values(c, Y, Psi, 1e-6, 1e-3, D, cY, lD)

rng = np.random.default_rng(5)
n = 4
Psi, Y = rng.standard_normal(n * n), rng.standard_normal(n)
D, cY, lD, J = np.empty(n), np.empty(n), np.empty(n), np.zeros((3 * n, n + n * n))
kernel(Y, Psi, D, cY, lD, J)
after_literal = [[len(f.signatures) for f in fn.variants] for fn in (mixing_values, mixing_derivatives)]
D2, cY2, lD2, J2 = np.empty(n), np.empty(n), np.empty(n), np.zeros_like(J)
mixing_values.variants[2].py_func(Y, Psi, 1e-6, 1e-3, D2, cY2, lD2)
mixing_derivatives.variants[2].py_func(Y, Psi, 1e-6, 1e-3, J2)
same = all(np.array_equal(a, b) for a, b in ((D, D2), (cY, cY2), (lD, lD2), (J, J2)))
D3, cY3, lD3 = np.empty(n), np.empty(n), np.empty(n)
runtime(2, Y, Psi, D3, cY3, lD3)
same_runtime = all(np.array_equal(a, b) for a, b in ((D, D3), (cY, cY3), (lD, lD3)))
print(json.dumps(dict(after_literal=after_literal, same=same, same_runtime=same_runtime)))
"""


def test_a_kernel_with_a_literal_variant_compiles_that_variant_alone(tmp_path):
    out = subprocess.run([sys.executable, "-c", _LITERAL, "2"], env=_fresh_env(tmp_path),
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    got = json.loads(out.stdout.strip().splitlines()[-1])
    # "channel" compiled, neither "paper" nor "eigen" (each its own pruned function)
    assert got["after_literal"] == [[0, 0, 1], [0, 0, 1]], got
    assert got["same"] and got["same_runtime"], got


_HELPER = r"""
import json
from ivdrem.blocks._kernels import mixing_derivatives
from ivdrem.sim import _compile_child
from ivdrem.sim._compile_child import index_exists, join_helpers, start_helpers
before = [index_exists(f._cache) for f in mixing_derivatives.variants]
w = start_helpers([("mixing_derivatives", 2)])
started = w.proc is not None
join_helpers()
after = [index_exists(f._cache) for f in mixing_derivatives.variants]
again = start_helpers([("mixing_derivatives", 2)]).proc is not None   # cached now: no child
print(json.dumps(dict(before=before, started=started, after=after, again=again,
                      left=len(_compile_child._HELPERS))))
"""


def test_a_helper_child_compiles_the_mixing_derivatives_into_numbas_cache(tmp_path):
    out = subprocess.run([sys.executable, "-c", _HELPER], env=_fresh_env(tmp_path),
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got == dict(before=[False, False, False], started=True,
                       after=[False, False, True], again=False, left=0), got


def test_no_helper_child_from_a_child_or_when_switched_off(monkeypatch):
    from ivdrem.sim import _compile_child
    monkeypatch.setattr(_compile_child, "index_exists", lambda cache: False)
    for var, value in (("IVDREM_COMPILE_CHILD", "0"), ("IVDREM_STEPPER_CHILD", "1")):
        with monkeypatch.context() as m:
            m.setenv(var, value)
            assert _compile_child.start_helpers([("mixing_derivatives", 1)]).proc is None
    assert not _compile_child._HELPERS


def test_the_helper_job_compiles_what_it_is_given(monkeypatch):
    from ivdrem.sim import _compile_child
    done = []
    monkeypatch.setattr(_kernels, "compile_variant", lambda name, code: done.append((name, code)))
    assert _compile_child._job(["--helpers", "mixing_derivatives:1", "mixing_values:0"]) == 0
    assert done == [("mixing_derivatives", 1), ("mixing_values", 0)]


def test_the_model_modules_strided_fallback_has_no_slice_assignment():
    # the copy back is entry by entry (a slice assignment compiles numba's shape-mismatch
    # message, about 2 s per dimension count in every process); tests/test_c_engine.py
    # checks the strided call's numbers
    from ivdrem.models._c_engine import _copy_back
    assert _copy_back("out", 2) == ["        for i0 in range(o.shape[0]):",
                                    "            for i1 in range(o.shape[1]):",
                                    "                out[i0, i1] = o[i0, i1]"]
    ns = {}
    src = "def copy(out, o):\n    if True:\n" + "\n".join(_copy_back("out", 3)) + "\n"
    exec(src, ns)
    o = np.arange(24.0).reshape(2, 3, 4)
    big = np.zeros((2, 3, 8))
    ns["copy"](big[:, :, ::2], o)
    assert np.array_equal(big[:, :, ::2], o) and not big[:, :, 1::2].any()


def test_a_mixing_function_counts_as_ready_for_the_probe_when_one_variant_is(monkeypatch):
    # the probe reads a block from its Jacobian kernel only where the helpers it calls are
    # compiled or cached; a mixing function is its variants (a run uses one of them)
    from ivdrem.blocks.jacobians import mixing_jacobian
    from ivdrem.sim import jacobian as jac
    assert jac._compiled_functions(mixing_derivatives) == mixing_derivatives.variants
    assert jac._compiled_functions(np.sum) == ()
    cached = set()
    monkeypatch.setattr(jac, "index_exists", lambda cache: cache in cached)
    fresh = [type("Variant", (), {"signatures": [], "_cache": object(), "py_func": None})()
             for _ in MIXING_VARIANTS]
    monkeypatch.setattr(mixing_derivatives, "variants", tuple(fresh))
    assert jac._compiles_first(mixing_jacobian)
    cached.add(fresh[2]._cache)                # one variant in numba's cache
    assert not jac._compiles_first(mixing_jacobian)
