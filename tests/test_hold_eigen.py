"""The max-hold's eigensolver (LAPACK dsyevd by address on preallocated work arrays, the
C stepper's lowest_eigenpair, both engines') against numpy's eigh, on composite learning's
own workspace."""
import numpy as np
import pytest

from ivdrem.diagrams import closed_loop
from ivdrem.sim.simulator import Simulator


@pytest.fixture(scope="module")
def sim():
    s = Simulator(closed_loop("composite-learning"))
    s.advance(0.01)
    return s


def test_lowest_eigenpair_equals_eigh(sim):
    mod, W = sim.engine.module, sim.W
    nmat = W.hold_vec.shape[1]
    nvec = 3                                   # the matrix after a few vector entries
    rng = np.random.default_rng(5)
    for trial in range(20):
        M = rng.normal(size=(nmat, nmat))
        A = M @ M.T + (1e-6 if trial % 2 else 1.0) * np.eye(nmat)
        A += 1e-3 * rng.normal(size=A.shape)   # not symmetric: its symmetric part counts
        u = np.r_[rng.normal(size=nvec), A.reshape(-1)]
        lam = mod.lowest_eigenpair(W, u, nvec, nmat)
        v = W.hold_vec[-1].copy()
        S = 0.5 * (A + A.T)
        w, V = np.linalg.eigh(S)
        assert abs(lam - w[0]) <= 1e-12 * abs(w).max()
        assert abs(np.linalg.norm(v) - 1.0) < 1e-12
        np.testing.assert_allclose(S @ v, lam * v, atol=1e-11 * abs(w).max())


def test_a_matrix_that_is_not_finite_is_an_error(sim):
    mod, W = sim.engine.module, sim.W
    nmat = W.hold_vec.shape[1]
    u = np.zeros(1 + nmat * nmat)
    u[1 + nmat + 1] = np.nan
    with pytest.raises(RuntimeError, match="not finite"):
        mod.lowest_eigenpair(W, u, 1, nmat)
