"""What every robot model of ivdrem presents to the blocks, the engines and the FMU export.

Two kinds of model satisfy it: :class:`~ivdrem.models.EulerLagrangeModel` (written in sympy,
its code generated from the symbolic M, G, F) and
:class:`~ivdrem.models.RigidBodyModel` (a URDF arm, its code the recursive kernels of
:mod:`ivdrem.models.rigid_body` over constant arrays of its chain).  Both generate Python
source (``source(prefix)``) defining the same functions with the same signatures (listed in
:mod:`ivdrem.models.euler_lagrange`), from which the plain-Python reference path
(``functions``), numba (``jit_functions``) and the compiled engine's model module are made,
and one C99 translation unit (``c_source(prefix)``, the *C face*: the same functions in C,
for the plant FMU and the controller's library; docs/models.md).
"""
from __future__ import annotations

import math
import re
import types
from functools import cached_property

import numpy as np

# the one Cholesky's rule and message, defined with it (re-exported: every model's face)
from .rigid_body import PIVOT_RTOL, SINGULAR_INERTIA_MESSAGE

__all__ = ["RobotModel", "REGRESSOR_ARGS", "FUNCTION_NAMES", "SINGULAR_INERTIA_MESSAGE",
           "C_FUNCTION_ARGS", "PIVOT_RTOL"]


#: The regressors and their vector arguments, in signature order.
REGRESSOR_ARGS = {"Phi_M": ("q", "a"), "Phi_C": ("q", "dq", "v"), "Phi_dM": ("q", "dq", "a"),
                  "Phi_G": ("q",), "Phi_F": ("dq",), "Phi": ("q", "dq", "v", "dv")}


#: The functions of every model's C face (``c_source``) and their pointer arguments, in
#: signature order (the last one is written); ``forward_dynamics`` returns an int.
C_FUNCTION_ARGS = {
    "Phi_M": ("q", "a", "out"), "Phi_C": ("q", "dq", "v", "out"),
    "Phi_dM": ("q", "dq", "a", "out"), "Phi_G": ("q", "out"), "Phi_F": ("dq", "out"),
    "Phi": ("q", "dq", "v", "dv", "out"),
    "M": ("q", "theta", "out"), "C": ("q", "dq", "theta", "out"), "G": ("q", "theta", "out"),
    "F": ("dq", "theta", "out"), "forward_dynamics": ("q", "dq", "tau", "theta", "ddq"),
    "forward_dynamics_k": ("q", "dq", "tau", "theta", "k", "ddq"),
}

#: The functions every model's source defines (signatures in ivdrem.models.euler_lagrange).
FUNCTION_NAMES = ("Phi_M", "Phi_C", "Phi_dM", "Phi_G", "Phi_F", "Phi",
                  "M", "C", "G", "F", "forward_dynamics",
                  *(f"{r}_jac" for r in REGRESSOR_ARGS))


def kernels_digest():
    """16 hex digits naming the source of :mod:`ivdrem.models.rigid_body` (the kernels every
    model's generated source calls): part of that source, so numba's cache of a model
    module is never the code of older kernels."""
    import hashlib
    import inspect
    from . import rigid_body
    return hashlib.sha256(inspect.getsource(rigid_body).encode()).hexdigest()[:16]


def linalg_import(prefix):
    """The line of a symbolic model's source that imports the package's one Cholesky
    (``_rb_spd_solve`` of :mod:`ivdrem.models.rigid_body`, compiled), named by the kernels'
    hash so that numba's cache of a model module never keeps an older kernel's code."""
    return (f"# kernels: ivdrem.models.rigid_body {kernels_digest()}\n"
            f"import ivdrem.models._rigid_body_jit as {prefix}_linalg\n\n\n")


def _c_prototype(prefix, name):
    args = C_FUNCTION_ARGS[name]
    ret = "int" if name.startswith("forward_dynamics") else "void"
    sig = ", ".join([f"const double *{a}" for a in args[:-1]] + [f"double *{args[-1]}"])
    return f"{ret} {prefix}{name}({sig})"


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

    def _disk_cached_source(self, prefix, generate, kind="py"):
        """The source of `prefix` from the compile cache's ``models`` directory, else made by
        `generate(prefix)` (with a note: a large model's symbolic code generation takes
        minutes) and written there for every later model object and process; `kind` is
        ``"py"`` (:meth:`source`) or ``"c"`` (:meth:`c_source`).

        The file is named by :attr:`key` (the model's content and code generator) and
        ivdrem's version and starts with a line repeating both, checked on reading: a
        changed model or a new ivdrem never reads a stale file.  Written atomically (two
        processes filling it at once both succeed); an unwritable cache only costs the
        regeneration next time."""
        from .. import __version__
        from .._atomic import write_text_atomic
        from .._progress import preparing
        from ..compile_cache import cache_dir
        header = f"ivdrem model source: key {self.key} ivdrem {__version__} prefix {prefix!r}"
        header = f"# {header}\n" if kind == "py" else f"/* {header} */\n"
        path = cache_dir() / "models" / f"{self.key[:32]}-{__version__}-{prefix or '_'}.{kind}"
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

    # ------------------------------------------------------------------ the C face
    def c_source(self, prefix: str = "") -> str:
        """One C99 translation unit (``<math.h>`` only, no allocation, workspace on the
        stack with sizes fixed here) defining the model's functions with names prefixed by
        `prefix`: the regressors ``Phi_M, Phi_C, Phi_dM, Phi_G, Phi_F, Phi`` (n x nθ, in
        the model's own parameters), ``M, C`` (n x n), ``G, F`` (n), all row major, and
        ``int forward_dynamics(q, dq, tau, theta, ddq)`` (0, or 1 when M(q) fails the one
        positive-definiteness rule, :data:`PIVOT_RTOL`); the same numbers as
        :attr:`functions`.  Also ``forward_dynamics_k``, whose argument ``k`` holds the
        model's constants (``<P>NCONST`` of them, in the order of ``model.constants``;
        the plant FMU's parameters), and the macros ``<P>N``, ``<P>NTHETA``,
        ``<P>NCONST`` (``<P>`` the prefix upper-cased).  Every function is declared
        ``<P>FN`` (empty unless the includer defines it, e.g. ``static``).  docs/models.md,
        "The C face"."""
        prefix = self._check_c_prefix(prefix)
        cache = self.__dict__.setdefault("_c_source_cache", {})
        if prefix not in cache:
            cache[prefix] = self._make_c_source(prefix)
        return cache[prefix]

    def _make_c_source(self, prefix):
        """:meth:`c_source` made from the model (a symbolic model keeps it on disk)."""
        return self._c_frame(prefix) + self._c_body(prefix)

    def c_declarations(self, prefix: str = "", linkage: str = "") -> str:
        """The prototypes of :meth:`c_source`'s functions (for a header), each preceded by
        `linkage` (e.g. a visibility macro)."""
        prefix = self._check_c_prefix(prefix)
        lead = f"{linkage} " if linkage else ""
        return "\n".join(f"{lead}{_c_prototype(prefix, name)};" for name in C_FUNCTION_ARGS) + "\n"

    def _c_body(self, prefix: str) -> str:  # pragma: no cover - abstract
        raise NotImplementedError

    @staticmethod
    def _check_c_prefix(prefix):
        prefix = str(prefix)
        if prefix and not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", prefix):
            raise ValueError(f"prefix must be the start of a C identifier, got {prefix!r}")
        return prefix

    def _c_frame(self, prefix):
        P = prefix.upper()
        from .. import __version__
        from ._c_printer import print_kernels
        from .rigid_body import C_CHOLESKY
        table = "\n".join(f" *   {_c_prototype(prefix, name)}" for name in C_FUNCTION_ARGS)
        guards = "".join(f"#ifndef {P}{m}\n#define {P}{m} {v}\n#endif\n" for m, v in (
            ("N", self.n), ("NTHETA", self.ntheta), ("NCONST", len(self.constants)),
            ("FN", "")))
        return f"""/* The C face of the ivdrem model "{self.name}" (n = {self.n}, ntheta = {self.ntheta}),
 * model key {self.key}; generated by ivdrem {__version__}.  Do not edit.
 * docs/models.md, "The C face": the same functions and numbers as the model's Python code,
 * matrices row major, regressors n x ntheta in the model's parameters:
{table}
 * forward_dynamics returns 0, or 1 when M(q) is not positive definite: a Cholesky pivot
 * d_j not finite or d_j <= {PIVOT_RTOL!r} max_i M_ii (the one rule of every language).
 */
#include <math.h>
{guards}
/* The package's one Cholesky, printed from its Python (ivdrem.models.rigid_body,
 * _rb_cholesky and _rb_cholesky_solve) by ivdrem.models._c_printer. */
{print_kernels(C_CHOLESKY, prefix)}"""

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
