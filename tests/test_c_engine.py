"""A URDF arm's functions from its C library (ivdrem.models._c_engine): the same numbers as
the numba-compiled kernels (the path without a C compiler), through ctypes
(``model.functions``) and from the compiled engine's model module (numba calling the C
functions by symbol); the regressors' derivatives of the C library against finite
differences of its regressors; without a compiler the numba path, unchanged."""
from __future__ import annotations

import warnings

import numpy as np
import pytest

from ivdrem.models.base import SINGULAR_INERTIA_MESSAGE

NSTATES = 8


@pytest.fixture(scope="module")
def panda(tmp_path_factory):
    from ivdrem.models import arm
    try:
        return arm("panda")
    except ImportError as exc:      # the arms' data packages (ivdrem[arms])
        pytest.skip(str(exc))


@pytest.fixture(scope="module")
def ur5_friction():
    from ivdrem.models import arm
    try:
        return arm("ur5", friction={"viscous": 0.8, "coulomb": 1.5},
                   armature=[0.1, 0.2, 0.1, 0.05, 0.05, 0.02])
    except ImportError as exc:
        pytest.skip(str(exc))


def _values(model, rng):
    v = {a: rng.standard_normal(model.n) for a in ("q", "dq", "v", "dv", "a", "tau")}
    v["theta"] = np.asarray(model.theta_values, float)
    return v


def _differences(model, fns, ref, seed=3):
    from ivdrem.models._c_engine import ENGINE_FUNCTIONS, out_shapes
    shapes = out_shapes(model)
    rng = np.random.default_rng(seed)
    worst = {}
    for _ in range(NSTATES):
        vals = _values(model, rng)
        for name, args in ENGINE_FUNCTIONS.items():
            got, want = np.full(shapes[name], np.nan), np.full(shapes[name], np.nan)
            getattr(fns, name)(*[vals[a] for a in args[:-1]], got)
            getattr(ref, name)(*[vals[a] for a in args[:-1]], want)
            assert np.all(np.isfinite(want)), name
            worst[name] = max(worst.get(name, 0.0), float(np.max(np.abs(got - want))))
    return worst


@pytest.mark.parametrize("which", ["panda", "ur5_friction"])
def test_c_library_equals_numba_kernels(which, request):
    """Every function, the derivatives too: equal to 0.0."""
    model = request.getfixturevalue(which)
    from ivdrem.models import _c_engine
    assert _c_engine.load(model) is not None, "no C compiler on this machine"
    worst = _differences(model, model.functions, model.numba_functions)
    print(f"\n{model.name}: " + ", ".join(f"{k} {v:.1e}" for k, v in worst.items()))
    assert max(worst.values()) == 0.0, worst


def test_c_derivatives_against_finite_differences(ur5_friction):
    """The derivatives are derivatives: central differences of the C regressors (step 1e-6,
    truncation and round-off about 1e-8 relative)."""
    model, fn = ur5_friction, ur5_friction.functions
    from ivdrem.models.base import REGRESSOR_ARGS
    n, nb = model.n, model.ntheta
    vals = _values(model, np.random.default_rng(5))
    h = 1e-6
    for name, args in REGRESSOR_ARGS.items():
        jac = np.empty((n, nb, len(args) * n))
        getattr(fn, name + "_jac")(*[vals[a] for a in args], jac)
        for k, a in enumerate(args):
            for m in range(n):
                lo, hi = dict(vals), dict(vals)
                lo[a], hi[a] = vals[a].copy(), vals[a].copy()
                lo[a][m] -= h
                hi[a][m] += h
                rl, rh = np.empty((n, nb)), np.empty((n, nb))
                getattr(fn, name)(*[lo[b] for b in args], rl)
                getattr(fn, name)(*[hi[b] for b in args], rh)
                fd = (rh - rl) / (2 * h)
                scale = max(1.0, float(np.max(np.abs(fd))))
                err = float(np.max(np.abs(jac[:, :, k * n + m] - fd))) / scale
                assert err < 1e-7, (name, a, m, err)


def test_compiled_engine_module_calls_the_c_library(panda):
    """The compiled engine's model module: numba functions calling the C library (no
    rigid-body kernel compiled), the same numbers, for contiguous and strided arrays."""
    from ivdrem.sim.compiled import _model_module, model_module
    name, src = _model_module(panda)
    assert "_nt.ExternalFunction(" in src and "_rbk" not in src
    mod = model_module(panda)
    worst = _differences(panda, mod, panda.numba_functions)
    assert max(worst.values()) == 0.0, worst
    # strided input and output: copied, the same numbers
    n, nb = panda.n, panda.ntheta
    rng = np.random.default_rng(9)
    q2, dq2 = rng.standard_normal((n, 2)), rng.standard_normal((n, 2))
    out2 = np.zeros((n, nb, 2))
    mod.Phi_G(q2[:, 0], out2[:, :, 1])
    want = np.empty((n, nb))
    panda.numba_functions.Phi_G(np.ascontiguousarray(q2[:, 0]), want)
    assert np.array_equal(out2[:, :, 1], want) and not np.any(out2[:, :, 0])


def test_singular_inertia_raises_the_one_message(panda):
    theta = np.zeros(panda.ntheta)
    out = np.empty(panda.n)
    z = np.zeros(panda.n)
    with pytest.raises(ValueError, match=r"not positive definite"):
        panda.functions.forward_dynamics(z, z, z, theta, out)
    with pytest.raises(ValueError) as exc:
        panda.functions.forward_dynamics(z, z, z, theta, out)
    assert str(exc.value) == SINGULAR_INERTIA_MESSAGE


def test_wrong_sizes_are_refused_before_the_c_call(panda):
    with pytest.raises(ValueError, match=r"Phi_G: q must have 7 entries"):
        panda.functions.Phi_G(np.zeros(6), np.empty((7, panda.ntheta)))
    with pytest.raises(ValueError, match=r"Phi_G: out must be an array of shape \(7, 43\)"):
        panda.functions.Phi_G(np.zeros(7), np.empty((7, 42)))


def test_without_a_c_compiler_the_numba_path(monkeypatch, tmp_path):
    """No compiler: load() says None, the engine's module is the numba source, the
    functions the numba kernels' (the first run then compiles them)."""
    from ivdrem.models import arm, _c_engine
    monkeypatch.setenv("IVDREM_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv("CC", "no-such-compiler-ivdrem")
    try:
        model = arm("ur5")
    except ImportError as exc:
        pytest.skip(str(exc))
    assert _c_engine.load(model) is None
    assert model.engine_source() == model.source("")
    assert "_rbk._rb_Phi(" in model.engine_source()
    assert not _c_engine.library_path(model.key).exists()


def test_a_compiler_that_fails_falls_back_to_the_numba_path(monkeypatch, tmp_path):
    """A compiler that is there but fails (a broken installation): load() warns once,
    quoting its first error, and says None; the engine's module is the numba source."""
    import os
    from ivdrem.models import arm, _c_engine
    broken = tmp_path / "broken-cc"
    broken.write_text("#!/bin/sh\necho 'model.c:1:1: error: broken installation' >&2\nexit 1\n")
    os.chmod(broken, 0o755)
    monkeypatch.setenv("IVDREM_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setenv("CC", str(broken))
    monkeypatch.setattr(_c_engine, "_FAILED", {})
    try:
        model = arm("ur5")
    except ImportError as exc:
        pytest.skip(str(exc))
    with pytest.warns(RuntimeWarning, match="error: broken installation.*numba kernels"):
        assert _c_engine.load(model) is None
    with warnings.catch_warnings():
        warnings.simplefilter("error")                  # once: no second build, no warning
        assert _c_engine.load(model) is None
        assert model.engine_source() == model.source("")
    assert not _c_engine.library_path(model.key).exists()
