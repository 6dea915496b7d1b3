"""The generated C controller library through ctypes, with the Python reference's interface.

``CController(model, law, **gains)`` validates the gains as
:class:`~ivdrem.controller.sampled.SampledController` does, builds the library of
:mod:`ivdrem.controller.codegen` for the model (cached by the hash of its sources under
``$IVDREM_CACHE_DIR/controller``, default ``~/.cache/ivdrem/controller``) and drives it: ``step(t, q, dq) ->
tau``, ``theta_hat``, ``tau_d_hat``, ``Delta``, ``state()`` / ``set_state()``.
"""
from __future__ import annotations

import ctypes
from pathlib import Path

import numpy as np

from .codegen import build_library
from .parameters import controller_arguments, param_layout, param_vector
from .sampled import SampledController

__all__ = ["CController", "load_library", "cache_dir"]

_c_double_p = ctypes.POINTER(ctypes.c_double)


def cache_dir() -> Path:
    """``controller/`` in ivdrem's compile cache (``$IVDREM_CACHE_DIR``, default
    ``~/.cache/ivdrem``, :mod:`ivdrem.compile_cache`)."""
    from ..compile_cache import cache_dir as ivdrem_cache
    return ivdrem_cache() / "controller"


def load_library(model, *, flags=("-O2",)):
    """The controller's C library for `model`, built (or read from the compile cache) and
    loaded with ctypes, its functions' argument and result types declared.

    `flags` are the C compiler's flags; the library is built in the compile cache under
    the model's key, so a later call loads the built library.
    """
    lib = ctypes.CDLL(str(build_library(model, cache_dir() / model.key[:16], flags=flags)))
    lib.ivc_init.restype = ctypes.c_void_p
    lib.ivc_init.argtypes = [_c_double_p, ctypes.c_char_p, ctypes.c_size_t]
    lib.ivc_step.restype = ctypes.c_int
    lib.ivc_step.argtypes = [ctypes.c_void_p, ctypes.c_double, _c_double_p, _c_double_p,
                             _c_double_p]
    lib.ivc_outputs.argtypes = [ctypes.c_void_p] + [_c_double_p] * 4
    lib.ivc_state_size.restype = ctypes.c_size_t
    lib.ivc_state_size.argtypes = [ctypes.c_void_p]
    lib.ivc_get_state.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_size_t]
    lib.ivc_set_state.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_size_t]
    lib.ivc_set_param.argtypes = [ctypes.c_void_p, ctypes.c_int, ctypes.c_double]
    lib.ivc_message.restype = ctypes.c_char_p
    lib.ivc_message.argtypes = [ctypes.c_void_p]
    lib.ivc_window_bytes.restype = ctypes.c_size_t
    lib.ivc_window_bytes.argtypes = [ctypes.c_void_p]
    lib.ivc_free.argtypes = [ctypes.c_void_p]
    lib.ivc_reset.argtypes = [ctypes.c_void_p]
    lib.ivc_reference.argtypes = [ctypes.c_void_p, _c_double_p, _c_double_p]
    return lib


class CControllerError(RuntimeError):
    """The C controller refused a call (its message says why)."""


class CController:
    """The C library of the sampled controller (same arguments as SampledController)."""

    def __init__(self, model=None, law="iv-drem", *, flags=("-O2",), **kwargs):
        ref = SampledController(model, law, **kwargs)       # validation, defaults
        self.model, self.law, self.n, self.ntheta = ref.model, law, ref.n, ref.ntheta
        self.h, self.delay, self.injection = ref.h, ref.delay, ref.injection
        self.lib = load_library(self.model, flags=tuple(flags))   # the C compiler's flags
        self.par = param_vector(ref)
        self.index = {}
        off = 0
        for name, size, _ in param_layout(self.model):
            self.index[name] = off
            off += size
        msg = ctypes.create_string_buffer(256)
        self._c = self.lib.ivc_init(self.par.ctypes.data_as(_c_double_p), msg, 256)
        if not self._c:
            raise ValueError(f"C controller: {msg.value.decode()}")
        n, nth = self.n, self.ntheta
        self._q, self._dq, self._tau = np.zeros(n), np.zeros(n), np.zeros(n)
        self._th, self._tdh, self._D, self._tau_o = np.zeros(nth), np.zeros(n), np.zeros(1), \
            np.zeros(n)
        self._p = [a.ctypes.data_as(_c_double_p) for a in
                   (self._q, self._dq, self._tau, self._th, self._tdh, self._D, self._tau_o)]

    @classmethod
    def from_params(cls, model, law, par):
        """The controller of a flat parameter vector (ivdrem_controller.h's layout), e.g.
        the start values of a controller FMU (:mod:`ivdrem.controller.parameters`)."""
        return cls(model, law, **controller_arguments(model, law, par))

    def __del__(self):
        c = getattr(self, "_c", None)
        if c:
            self.lib.ivc_free(c)
            self._c = None

    @property
    def window_bytes(self):
        return int(self.lib.ivc_window_bytes(self._c))

    def step(self, t, q, dq):
        self._q[:] = q
        self._dq[:] = dq
        st = self.lib.ivc_step(self._c, float(t), self._p[0], self._p[1], self._p[2])
        if st != 0:
            raise CControllerError(f"ivc_step: {self.lib.ivc_message(self._c).decode()} "
                                   f"(status {st})")
        return self._tau.copy()

    def entry_points(self):
        """(step, outputs, handle): ``ivc_step`` and ``ivc_outputs`` as ctypes function
        pointers whose pointer arguments (the controller, the arrays) are integers
        (``handle``; ``a.ctypes.data``), so a numba function can call them
        (:func:`ivdrem.controller.loop.compiled_closed_loop`): step(handle, t, q, dq,
        tau) -> status, outputs(handle, theta_hat, tau_d_hat, Delta, tau) -> status.
        Valid while this controller lives."""
        P = ctypes.c_size_t             # a pointer, as an integer (same size and passing)
        step = ctypes.CFUNCTYPE(ctypes.c_int, P, ctypes.c_double, P, P, P)(
            ctypes.cast(self.lib.ivc_step, ctypes.c_void_p).value)
        outputs = ctypes.CFUNCTYPE(ctypes.c_int, P, P, P, P, P)(
            ctypes.cast(self.lib.ivc_outputs, ctypes.c_void_p).value)
        return step, outputs, int(self._c)

    def _outputs(self):
        self.lib.ivc_outputs(self._c, *self._p[3:])

    @property
    def theta_hat(self):
        self._outputs()
        return self._th.copy()

    @property
    def tau_d_hat(self):
        self._outputs()
        return self._tdh.copy()

    def last_reference(self):
        """(q_d, dq_d) of the last step (ivc_reference)."""
        qd, dqd = np.zeros(self.n), np.zeros(self.n)
        self.lib.ivc_reference(self._c, qd.ctypes.data_as(_c_double_p),
                               dqd.ctypes.data_as(_c_double_p))
        return qd, dqd

    @property
    def Delta(self):
        self._outputs()
        return float(self._D[0])

    def set_param(self, name, value, i=0):
        st = self.lib.ivc_set_param(self._c, self.index[name] + i, float(value))
        if st != 0:
            raise CControllerError(self.lib.ivc_message(self._c).decode())

    def state(self):
        size = self.lib.ivc_state_size(self._c)
        buf = ctypes.create_string_buffer(size)
        if self.lib.ivc_get_state(self._c, buf, size) != 0:
            raise CControllerError("ivc_get_state failed")
        return buf.raw

    def set_state(self, raw):
        buf = ctypes.create_string_buffer(raw, len(raw))
        if self.lib.ivc_set_state(self._c, buf, len(raw)) != 0:
            raise CControllerError(self.lib.ivc_message(self._c).decode())

    def reset(self):
        self.lib.ivc_reset(self._c)
