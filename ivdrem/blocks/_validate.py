"""Parameter checks shared by the block factories; every message names the parameter."""
from __future__ import annotations

import numpy as np

from ._core import ParameterError


def _arr(block, name, value):
    try:
        a = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise ParameterError(f"block '{block}': parameter '{name}' must be numeric, got {value!r}")
    if not np.all(np.isfinite(a)):
        raise ParameterError(f"block '{block}': parameter '{name}' has non-finite entries")
    return a


def scalar(block, name, value, *, positive=False, nonneg=False, lo=None, hi=None, open_=True):
    a = _arr(block, name, value)
    if a.ndim != 0:
        if a.size == 1:
            a = a.reshape(())
        else:
            raise ParameterError(f"block '{block}': parameter '{name}' must be a scalar, "
                                 f"got shape {a.shape}")
    v = float(a)
    if positive and not v > 0:
        raise ParameterError(f"block '{block}': parameter '{name}' must be > 0, got {v}")
    if nonneg and not v >= 0:
        raise ParameterError(f"block '{block}': parameter '{name}' must be >= 0, got {v}")
    if lo is not None and hi is not None:
        ok = (lo < v < hi) if open_ else (lo <= v <= hi)
        if not ok:
            br = "()" if open_ else "[]"
            raise ParameterError(f"block '{block}': parameter '{name}' must be in "
                                 f"{br[0]}{lo}, {hi}{br[1]}, got {v}")
    return v


def vector(block, name, value, size):
    a = _arr(block, name, value).reshape(-1) if np.ndim(value) <= 1 else None
    if a is None:
        raise ParameterError(f"block '{block}': parameter '{name}' must be a vector of "
                             f"length {size}, got shape {np.shape(value)}")
    if a.size != size:
        raise ParameterError(f"block '{block}': parameter '{name}' must have length {size}, "
                             f"got {a.size}")
    return a


def square(block, name, value, size, *, pd=False, diag_ok=True, symmetric=False):
    """A size x size matrix; a scalar c means c*I and a vector d means diag(d)."""
    a = _arr(block, name, value)
    if a.ndim == 0 and diag_ok:
        a = float(a) * np.eye(size)
    elif a.ndim == 1 and diag_ok and a.size == size:
        a = np.diag(a)
    if a.shape != (size, size):
        raise ParameterError(f"block '{block}': parameter '{name}' must be {size}x{size} "
                             f"(or a scalar / diagonal), got shape {np.shape(value)}")
    if (pd or symmetric) and not np.allclose(a, a.T, rtol=1e-12, atol=1e-14):
        raise ParameterError(f"block '{block}': parameter '{name}' must be symmetric")
    if pd:
        ev = np.linalg.eigvalsh(0.5 * (a + a.T))
        if not ev.min() > 0:
            raise ParameterError(f"block '{block}': parameter '{name}' must be positive "
                                 f"definite (smallest eigenvalue {ev.min():.3g})")
    return np.ascontiguousarray(a)
