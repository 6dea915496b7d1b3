"""What every robot model of ivdrem presents to the blocks, the engines and the FMU export.

Two kinds of model satisfy it: :class:`~ivdrem.models.EulerLagrangeModel` (written in sympy,
its code generated from the symbolic M, G, F) and
:class:`~ivdrem.models.RigidBodyModel` (a URDF arm, its code the recursive kernels of
:mod:`ivdrem.models.rigid_body` over constant arrays of its chain).  Both generate Python
source (``source(prefix)``) defining the same functions with the same signatures (listed in
:mod:`ivdrem.models.euler_lagrange`), from which the plain-Python reference path
(``functions``), numba (``jit_functions``) and the compiled engine's model module are made.
"""
from __future__ import annotations

import math
import re
import types
from functools import cached_property

import numpy as np

__all__ = ["RobotModel", "REGRESSOR_ARGS", "FUNCTION_NAMES", "SINGULAR_INERTIA_MESSAGE"]

#: The message of the error raised where M(q) is not positive definite.
SINGULAR_INERTIA_MESSAGE = "inertia matrix M(q) is not positive definite (singular inertia)"

#: The regressors and their vector arguments, in signature order.
REGRESSOR_ARGS = {"Phi_M": ("q", "a"), "Phi_C": ("q", "dq", "v"), "Phi_dM": ("q", "dq", "a"),
                  "Phi_G": ("q",), "Phi_F": ("dq",), "Phi": ("q", "dq", "v", "dv")}

#: The functions every model's source defines (signatures in ivdrem.models.euler_lagrange).
FUNCTION_NAMES = ("Phi_M", "Phi_C", "Phi_dM", "Phi_G", "Phi_F", "Phi",
                  "M", "C", "G", "F", "forward_dynamics",
                  *(f"{r}_jac" for r in REGRESSOR_ARGS))


class RobotModel:
    """Common numeric interface; subclasses set ``name``, ``n``, ``ntheta``,
    ``theta_values``, ``theta_names`` and define ``key`` and ``source(prefix)``."""

    #: known constants substituted in the generated code (name -> value); none by default
    constants: dict = {}

    # joints and their limits (a URDF arm has its own; a symbolic model has none: +-inf)
    @cached_property
    def joint_names(self):
        """Names of the joints, in the order of q."""
        return [f"joint{i + 1}" for i in range(self.n)]

    @cached_property
    def position_limits(self):
        """(n, 2) lower and upper limits of q; +-inf where none."""
        a = np.column_stack([np.full(self.n, -np.inf), np.full(self.n, np.inf)])
        a.setflags(write=False)
        return a

    @cached_property
    def velocity_limits(self):
        """(n,) limits of |dq|; inf where none."""
        a = np.full(self.n, np.inf)
        a.setflags(write=False)
        return a

    @cached_property
    def effort_limits(self):
        """(n,) limits of |tau|; inf where none."""
        a = np.full(self.n, np.inf)
        a.setflags(write=False)
        return a

    def source(self, prefix: str = "") -> str:  # pragma: no cover - abstract
        raise NotImplementedError

    def _disk_cached_source(self, prefix, generate):
        """The source of `prefix` from the compile cache's ``models`` directory, else made by
        `generate(prefix)` (with a note: a large model's symbolic code generation takes
        minutes) and written there for every later model object and process.

        The file is named by :attr:`key` (the model's content and code generator) and
        ivdrem's version and starts with a line repeating both, checked on reading: a
        changed model or a new ivdrem never reads a stale file.  Written atomically (two
        processes filling it at once both succeed); an unwritable cache only costs the
        regeneration next time."""
        from .. import __version__
        from .._atomic import write_text_atomic
        from .._progress import preparing
        from ..sim.cache import cache_dir
        header = f"# ivdrem model source: key {self.key} ivdrem {__version__} prefix {prefix!r}\n"
        path = cache_dir() / "models" / f"{self.key[:32]}-{__version__}-{prefix or '_'}.py"
        try:
            text = path.read_text(encoding="utf-8")
            if text.startswith(header):
                return text[len(header):]
        except (OSError, UnicodeDecodeError):
            pass
        with preparing(f"generating the code of model {self.name} (n = {self.n}, "
                       f"{self.ntheta} parameters)", cached_in=path.parent):
            src = generate(prefix)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            write_text_atomic(path, header + src)
        except OSError:
            pass
        return src

    def _memo_source(self, prefix, make):
        """``source(prefix)``'s memory: `make(prefix)` once per prefix and model object
        (in ``self._source_cache``), the prefix checked first."""
        prefix = self._check_prefix(prefix)
        if prefix not in self._source_cache:
            self._source_cache[prefix] = make(prefix)
        return self._source_cache[prefix]

    @staticmethod
    def _check_prefix(prefix):
        prefix = str(prefix)
        if prefix and not prefix.isidentifier():
            raise ValueError(f"prefix must be a valid Python identifier prefix, got {prefix!r}")
        return prefix

    # ------------------------------------------------------------------ numeric
    def _namespace(self, jit):
        src = self.source("")
        glb = {"math": math, "np": np, "__name__": f"ivdrem_generated_{self.key[:12]}"}
        exec(compile(src, f"<ivdrem model {self.name} {self.key[:12]}>", "exec"), glb)
        if jit:
            import numba
            # every function of the source (helpers too: a compiled function calls only
            # compiled ones), replaced in the namespace before the first call compiles it
            for name in re.findall(r"^def\s+(\w+)\s*\(", src, flags=re.M):
                glb[name] = numba.njit(glb[name])
        return types.SimpleNamespace(**{name: glb[name] for name in FUNCTION_NAMES})

    @cached_property
    def functions(self):
        """Namespace of the generated functions as plain Python (reference path)."""
        return self._namespace(jit=False)

    @cached_property
    def jit_functions(self):
        """Namespace of ``numba.njit`` versions of the generated functions (compiled lazily)."""
        return self._namespace(jit=True)

    # convenience helpers: allocate and return arrays (not for inner loops)
    def _theta(self, theta):
        if theta is None:
            if self.theta_values is None:
                raise ValueError(f"model {self.name!r} has no theta_values; pass theta")
            return np.asarray(self.theta_values, dtype=float)
        th = np.asarray(theta, dtype=float)
        if th.shape != (self.ntheta,):
            raise ValueError(f"theta must have shape ({self.ntheta},), got {th.shape}")
        return th

    def regressor(self, q, dq, v, dv):
        """Phi^T(q, dq, v, dv) as a new (n, ntheta) array."""
        out = np.empty((self.n, self.ntheta))
        self.functions.Phi(np.asarray(q, float), np.asarray(dq, float), np.asarray(v, float),
                           np.asarray(dv, float), out)
        return out

    def inverse_dynamics(self, q, dq, ddq, theta=None):
        """tau = M ddq + C dq + F + G (= Phi^T(q, dq, dq, ddq) theta) as a new array."""
        return self.regressor(q, dq, dq, ddq) @ self._theta(theta)

    def acceleration(self, q, dq, tau, theta=None):
        """qdd from forward dynamics as a new array."""
        out = np.empty(self.n)
        self.functions.forward_dynamics(np.asarray(q, float), np.asarray(dq, float),
                                        np.asarray(tau, float), self._theta(theta), out)
        return out
