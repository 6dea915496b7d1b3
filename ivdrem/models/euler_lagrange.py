"""Symbolic Euler-Lagrange robot models and their generated regressor code.

A robot is described once, symbolically (sympy), by

    M(q) q'' + C(q, q') q' + F(q') + G(q) = tau + tau_d,

with the inertia matrix ``M(q)``, a potential ``P(q)`` (``G = dP/dq``) or ``G(q)``
directly, and an optional friction ``F(q')``, all *linear* in the parameter vector
``theta``.  This is Property 1 of the paper: for any auxiliary vectors ``v``, ``dv``

    M(q) dv + C(q, q') v + F(q') + G(q) = Phi^T(q, q', v, dv) theta,
    Phi^T = Phi_M^T(q, dv) + Phi_C^T(q, q', v) + Phi_F^T(q') + Phi_G^T(q),
    Phi_dM^T(q, q', a) theta = Mdot(q, q') a.

``C`` is not given by the user: it is derived from ``M`` with the Christoffel symbols of
the first kind, which makes ``Mdot - 2 C`` skew-symmetric (Property 3 of the paper:
``x^T (Mdot/2 - C) x = 0``).  Every regressor is the Jacobian with respect to ``theta``
of the corresponding (linear in ``theta``) term, so no regressor is written by hand.

Model / data separation (as in Pinocchio's ``Model`` and ``Data``): an
:class:`EulerLagrangeModel` is immutable structure -- symbols, symbolic matrices, known
constants (``g``, link lengths) and the generated source.  Everything that changes during a
simulation is *data* owned by the caller: the state, the parameter vector (``theta`` is an
argument of ``M``, ``C``, ``G``, ``F`` and ``forward_dynamics``, so the same code serves the
true plant and the estimate ``theta_hat``), and the output buffers.  Every generated
function writes into a preallocated ``out`` array and returns ``None``; it allocates
nothing visible and keeps no state, so it can be called from numba-compiled simulators.
``theta_values`` is only the nominal (true) parameter vector of the model, kept as a
convenience.

Generated functions (``model.source(prefix)``, ``model.functions``,
``model.jit_functions``), ``n`` = DoF, ``nθ`` = number of parameters; regressors are
stored in the ``n x nθ`` orientation (they multiply ``theta``)::

    Phi_M(q, a, out)              out (n, nθ) = d(M(q) a)/dθ
    Phi_C(q, dq, v, out)          out (n, nθ) = d(C(q,dq) v)/dθ
    Phi_dM(q, dq, a, out)         out (n, nθ) = d(Mdot(q,dq) a)/dθ
    Phi_G(q, out)                 out (n, nθ) = dG/dθ
    Phi_F(dq, out)                out (n, nθ) = dF/dθ
    Phi(q, dq, v, dv, out)        out (n, nθ) = Phi_M(q,dv)+Phi_C(q,dq,v)+Phi_F(dq)+Phi_G(q)
    M(q, theta, out)              out (n, n)
    C(q, dq, theta, out)          out (n, n)
    G(q, theta, out)              out (n,)
    F(dq, theta, out)             out (n,)
    forward_dynamics(q, dq, tau, theta, out)
                                  out (n,) = qdd solving M qdd = tau - C dq - F - G

and the derivatives of the regressors with respect to their vector arguments (exact, from
sympy ``diff``), for the blocks' analytic Jacobians: for a regressor ``R(w_0, ..., w_{k-1})``
of ``k`` vector arguments of length ``n`` each, ``R_jac(w_0, ..., w_{k-1}, out)`` writes

    out[i, j, a*n + m] = d R[i, j] / d w_a[m]        out (n, nθ, k n)

with the arguments in the order of ``R``'s signature, e.g. ``Phi_C_jac(q, dq, v, out)``:
``out[:, :, 0:n]`` is d/dq, ``out[:, :, n:2n]`` d/ddq, ``out[:, :, 2n:3n]`` d/dv.
Generated: ``Phi_M_jac``, ``Phi_C_jac``, ``Phi_dM_jac``, ``Phi_G_jac``, ``Phi_F_jac``,
``Phi_jac``.  A derivative of ``Phi^T theta`` is the contraction ``out @ theta`` over ``j``.
"""
from __future__ import annotations

import hashlib
import re
import math
import types
from functools import cached_property

import numpy as np
import sympy as sp
from sympy.printing.pycode import PythonCodePrinter

from .base import (FUNCTION_NAMES as _FUNCTION_NAMES, REGRESSOR_ARGS, RobotModel,
                   linalg_import)

__all__ = ["EulerLagrangeModel", "CODEGEN_VERSION", "REGRESSOR_ARGS"]

#: Bumped whenever the generated source changes shape; part of :attr:`EulerLagrangeModel.key`.
CODEGEN_VERSION = "3"

# ----------------------------------------------------------------------------- helpers
def _is_zero(expr) -> bool:
    """True if ``expr`` is zero: structurally first, then after expand/simplify."""
    expr = sp.sympify(expr)
    if expr == 0:
        return True
    if expr.is_number:
        return bool(sp.simplify(expr) == 0)
    e = sp.expand(expr)
    if e == 0:
        return True
    return bool(sp.simplify(e) == 0)


def _as_symbol_list(seq, what):
    if isinstance(seq, sp.Symbol):
        seq = [seq]
    try:
        out = list(seq)
    except TypeError:
        raise ValueError(f"{what} must be a list of sympy Symbols, got {seq!r}") from None
    for s in out:
        if not isinstance(s, sp.Symbol):
            raise ValueError(f"{what} must contain sympy Symbols only, got {s!r} ({type(s).__name__})")
    return out


def _as_column(expr, n, what):
    try:
        m = sp.Matrix(expr)
    except Exception as exc:  # pragma: no cover - sympy raises many types
        raise ValueError(f"{what} must be an n x 1 sympy Matrix: {exc}") from None
    if m.shape == (1, n) and n != 1:
        m = m.T
    if m.shape != (n, 1):
        raise ValueError(f"{what} must be an n x 1 sympy Matrix with n = {n}, got shape {m.shape}")
    return m


class _Printer(PythonCodePrinter):
    """Python printer with ``math.`` functions and exact (round-trip) float literals."""

    def __init__(self, settings=None):
        s = {"fully_qualified_modules": True}
        s.update(settings or {})
        super().__init__(s)

    def _print_Float(self, expr):
        return repr(float(expr))

    def _print_Integer(self, expr):
        # integer literals stay integers (exact, and numba casts them on assignment)
        return str(int(expr))


# ----------------------------------------------------------------------------- model
class EulerLagrangeModel(RobotModel):
    """An n-DoF Euler-Lagrange robot ``M q'' + C q' + F + G = tau`` linear in ``theta``.

    Parameters
    ----------
    name : str
        Model name (e.g. ``"two-link"``).
    q : list of sympy.Symbol
        The n generalized coordinates.
    theta : list of sympy.Symbol
        The nθ parameters; ``M``, ``G`` (or the potential) and ``F`` must be linear in them.
    M : sympy.Matrix (n x n)
        Inertia matrix in ``q``, ``theta`` (and ``constants``); must be symmetric.
    potential : sympy expression, optional
        Potential energy ``P(q)``; then ``G = dP/dq``.  Exactly one of ``potential``/``G``.
    G : sympy.Matrix (n x 1), optional
        Gravity vector ``G(q)``.
    F : sympy.Matrix (n x 1), optional
        Friction ``F(dq)``; must not depend on ``q``.  Zero if omitted.
    dq : list of sympy.Symbol, optional
        Generalized velocities (``dq0 .. dq{n-1}`` if omitted).
    constants : dict {Symbol: float}, optional
        Known constants (``g``, lengths) kept symbolic in the sympy attributes and
        substituted by their values in the generated code.
    theta_values : array_like, optional
        Nominal (true) parameter vector, length nθ, finite.  ``None`` if not given.
    theta_names : list of str, optional
        Display names of the parameters (default: the symbol names).
    parameter_units : dict {name: unit}, optional
        Units of parameters and constants by name (FMI unit strings such as ``"kg.m2"``);
        names left out have no unit.
    """

    def __init__(self, name, q, theta, M, *, potential=None, G=None, F=None, dq=None,
                 constants=None, theta_values=None, theta_names=None, parameter_units=None):
        self.name = str(name)
        q = _as_symbol_list(q, "q")
        theta = _as_symbol_list(theta, "theta")
        n = len(q)
        if n < 1:
            raise ValueError("q must contain at least one generalized coordinate")
        if len(theta) < 1:
            raise ValueError("theta must contain at least one parameter")
        if dq is None:
            dq = [sp.Symbol(f"dq{i}") for i in range(n)]
        dq = _as_symbol_list(dq, "dq")
        if len(dq) != n:
            raise ValueError(f"dq must have the same length as q ({n}), got {len(dq)}")

        constants = dict(constants or {})
        const_syms = []
        const_vals = {}
        for k, val in constants.items():
            if isinstance(k, str):
                k = sp.Symbol(k)
            if not isinstance(k, sp.Symbol):
                raise ValueError(f"constants keys must be sympy Symbols, got {k!r}")
            try:
                fv = float(val)
            except (TypeError, ValueError):
                raise ValueError(f"constant {k} must be a real number, got {val!r}") from None
            if not math.isfinite(fv):
                raise ValueError(f"constant {k} must be finite, got {fv}")
            const_syms.append(k)
            const_vals[k] = fv

        all_syms = q + dq + theta + const_syms
        if len(set(all_syms)) != len(all_syms):
            seen, dup = set(), []
            for s in all_syms:
                if s in seen and s not in dup:
                    dup.append(s)
                seen.add(s)
            raise ValueError("duplicate symbols among q, dq, theta and constants: "
                             + ", ".join(map(str, dup)))

        self.n = n
        self.ntheta = len(theta)
        self.q = q
        self.dq = dq
        self.theta = theta
        self.constants = const_vals
        qs, dqs, ths, cs = set(q), set(dq), set(theta), set(const_syms)

        # --- M
        try:
            Mm = sp.Matrix(M)
        except Exception as exc:  # pragma: no cover
            raise ValueError(f"M must be an n x n sympy Matrix: {exc}") from None
        if Mm.shape != (n, n):
            raise ValueError(f"M must be square n x n with n = len(q) = {n}, got shape {Mm.shape}")
        self._check_symbols(Mm, "M", qs | ths | cs, {"dq": dqs})
        for i in range(n):
            for j in range(i + 1, n):
                if not _is_zero(Mm[i, j] - Mm[j, i]):
                    raise ValueError(f"M is not symmetric: M[{i},{j}] = {Mm[i, j]} differs from "
                                     f"M[{j},{i}] = {Mm[j, i]}")
        self._check_linear(Mm, "M", theta)

        # --- G / potential
        if (potential is None) == (G is None):
            raise ValueError("give exactly one of potential (scalar P(q), G = dP/dq) or G (n x 1)")
        if potential is not None:
            P = sp.sympify(potential)
            if isinstance(P, sp.MatrixBase):
                if P.shape != (1, 1):
                    raise ValueError(f"potential must be a scalar expression, got shape {P.shape}")
                P = P[0, 0]
            self._check_symbols(sp.Matrix([P]), "potential", qs | ths | cs, {"dq": dqs})
            Gm = sp.Matrix([sp.diff(P, qi) for qi in q])
            self._check_linear(Gm, "potential P (its gradient G = dP/dq)", theta)
            self.potential = P
        else:
            Gm = _as_column(G, n, "G")
            self._check_symbols(Gm, "G", qs | ths | cs, {"dq": dqs})
            self._check_linear(Gm, "G", theta)
            self.potential = None

        # --- F
        if F is None:
            Fm = sp.zeros(n, 1)
        else:
            Fm = _as_column(F, n, "F")
            self._check_symbols(Fm, "F", dqs | ths | cs, {"q": qs})
            self._check_linear(Fm, "F", theta)

        # --- theta values / names
        if theta_values is None:
            self.theta_values = None
        else:
            tv = np.asarray(theta_values, dtype=float).reshape(-1)
            if tv.shape != (self.ntheta,):
                raise ValueError(f"theta_values must have length ntheta = {self.ntheta}, "
                                 f"got {tv.size}")
            if not np.all(np.isfinite(tv)):
                raise ValueError(f"theta_values must be finite, got {tv}")
            tv.setflags(write=False)
            self.theta_values = tv
        if theta_names is None:
            theta_names = [str(s) for s in theta]
        theta_names = [str(s) for s in theta_names]
        if len(theta_names) != self.ntheta:
            raise ValueError(f"theta_names must have length ntheta = {self.ntheta}, "
                             f"got {len(theta_names)}")
        if len(set(theta_names)) != len(theta_names):
            raise ValueError(f"theta_names must be unique, got {theta_names}")
        self.theta_names = theta_names
        known = set(theta_names) | {str(k) for k in const_vals}
        units = {str(k): str(u) for k, u in (parameter_units or {}).items()}
        extra = sorted(set(units) - known)
        if extra:
            raise ValueError("parameter_units names neither a parameter nor a constant: "
                             + ", ".join(extra))
        self.parameter_units = units

        self.M = sp.ImmutableMatrix(Mm)
        self.G = sp.ImmutableMatrix(Gm)
        self.F = sp.ImmutableMatrix(Fm)
        self.C = sp.ImmutableMatrix(self._christoffel_C())

        # auxiliary vectors of the regressors (Phi_M(q, a), Phi_C(q, dq, v), Phi(q,dq,v,dv))
        taken = {str(s) for s in all_syms}
        self.a = self._fresh("a", n, taken)
        self.v = self._fresh("v", n, taken)
        self.dv = self._fresh("dv", n, taken)

        self._source_cache = {}
        self._rjac_cache = {}

    # ------------------------------------------------------------------ validation
    @staticmethod
    def _check_symbols(mat, what, allowed, forbidden_named):
        free = set()
        for e in mat:
            free |= sp.sympify(e).free_symbols
        for label, syms in forbidden_named.items():
            bad = free & syms
            if bad:
                raise ValueError(f"{what} must not depend on {label}, but contains "
                                 + ", ".join(sorted(map(str, bad))))
        bad = free - allowed
        if bad:
            raise ValueError(f"{what} contains unknown symbols (not in q, dq, theta or constants): "
                             + ", ".join(sorted(map(str, bad))))

    @staticmethod
    def _check_linear(mat, what, theta):
        ths = set(theta)
        zero_theta = {t: 0 for t in theta}
        for idx in range(len(mat)):
            e = sp.sympify(mat[idx])
            i, j = divmod(idx, mat.shape[1])
            where = f"{what}[{i},{j}]" if mat.shape[1] > 1 else f"{what}[{i}]"
            for t in theta:
                d = sp.diff(e, t)
                for t2 in sorted(d.free_symbols & ths, key=str):
                    if not _is_zero(sp.diff(d, t2)):
                        raise ValueError(f"{what} is not linear in theta: {where} = {e} has a "
                                         f"nonzero second derivative w.r.t. ({t}, {t2})")
            rest = e.subs(zero_theta)
            if not _is_zero(rest):
                raise ValueError(f"{what} is not linear in theta: {where} = {e} has a "
                                 f"theta-free nonzero term {rest}")

    @staticmethod
    def _fresh(base, n, taken):
        stem = base
        while any(f"{stem}{i}" in taken for i in range(n)):
            stem = "_" + stem
        return [sp.Symbol(f"{stem}{i}") for i in range(n)]

    def _christoffel(self, M):
        """C_kj = sum_i (dM_kj/dq_i + dM_ki/dq_j - dM_ij/dq_k)/2 dq_i (linear in M)."""
        n, q, dq = self.n, self.q, self.dq
        dM = [M.diff(qi) for qi in q]  # dM[i][k, j] = dM_kj / dq_i
        C = sp.zeros(n, n)
        for k in range(n):
            for j in range(n):
                s = sp.Integer(0)
                for i in range(n):
                    c = (dM[i][k, j] + dM[j][k, i] - dM[k][i, j]) / 2
                    if c != 0:
                        s += c * dq[i]
                C[k, j] = s
        return C

    def _christoffel_C(self):
        return self._christoffel(self.M)

    def _mdot(self, M):
        return sum((M.diff(qi) * dqi for qi, dqi in zip(self.q, self.dq)),
                   sp.zeros(self.n, self.n))

    # ------------------------------------------------------------------ symbolic
    # Everything is linear in theta, so the Jacobian w.r.t. theta of (M a), (C v), (Mdot a)
    # has column k equal to M_k a, C_k v, Mdot_k a with M_k = dM/dtheta_k (theta-free) and
    # C_k, Mdot_k the Christoffel matrix / time derivative of M_k (both linear in M).  This is
    # the same Jacobian, computed without differentiating large expressions.
    @cached_property
    def _M_parts(self):
        return [sp.Matrix(self.M).diff(t).applyfunc(sp.expand) for t in self.theta]

    @cached_property
    def Mdot(self):
        """dM/dt = sum_i dM/dq_i dq_i (sympy n x n)."""
        return sp.ImmutableMatrix(self._mdot(sp.Matrix(self.M)))

    def _columns(self, cols):
        return sp.ImmutableMatrix(sp.Matrix.hstack(*cols).applyfunc(sp.expand))

    @cached_property
    def Phi_M(self):
        """Phi_M^T(q, a) = d(M(q) a)/dtheta, sympy n x ntheta in (q, self.a)."""
        a = sp.Matrix(self.a)
        return self._columns([Mk * a for Mk in self._M_parts])

    @cached_property
    def Phi_C(self):
        """Phi_C^T(q, dq, v) = d(C(q, dq) v)/dtheta, in (q, dq, self.v)."""
        v = sp.Matrix(self.v)
        return self._columns([self._christoffel(Mk) * v for Mk in self._M_parts])

    @cached_property
    def Phi_dM(self):
        """Phi_dM^T(q, dq, a) = d(Mdot(q, dq) a)/dtheta, in (q, dq, self.a)."""
        a = sp.Matrix(self.a)
        return self._columns([self._mdot(Mk) * a for Mk in self._M_parts])

    @cached_property
    def Phi_G(self):
        """Phi_G^T(q) = dG/dtheta."""
        return sp.ImmutableMatrix(sp.Matrix(self.G).jacobian(sp.Matrix(self.theta)))

    @cached_property
    def Phi_F(self):
        """Phi_F^T(dq) = dF/dtheta."""
        return sp.ImmutableMatrix(sp.Matrix(self.F).jacobian(sp.Matrix(self.theta)))

    @cached_property
    def Phi(self):
        """Phi^T(q, dq, v, dv) = Phi_M^T(q, dv) + Phi_C^T(q, dq, v) + Phi_F^T + Phi_G^T."""
        PM = self.Phi_M.xreplace(dict(zip(self.a, self.dv)))
        return sp.ImmutableMatrix(PM + self.Phi_C + self.Phi_F + self.Phi_G)

    def regressor_jacobian(self, name):
        """d R[i, j] / d w_a[m] of regressor `name` (e.g. ``"Phi_C"``) as a sympy
        (n * nθ) x (k n) matrix, row ``i * nθ + j``, column ``a * n + m`` over its vector
        arguments ``REGRESSOR_ARGS[name]`` (symbols ``self.q``, ``self.dq``, ``self.a``,
        ``self.v``, ``self.dv``; ``Phi``'s fourth argument is ``self.dv``)."""
        if name not in REGRESSOR_ARGS:
            raise ValueError(f"unknown regressor {name!r}; valid: {', '.join(REGRESSOR_ARGS)}")
        if name not in self._rjac_cache:
            R = sp.Matrix(getattr(self, name))
            wrt = [s for arg in REGRESSOR_ARGS[name] for s in getattr(self, arg)]
            flat = sp.Matrix([R[i, j] for i in range(self.n) for j in range(self.ntheta)])
            self._rjac_cache[name] = sp.ImmutableMatrix(flat.jacobian(wrt))
        return self._rjac_cache[name]

    # ------------------------------------------------------------------ identity
    @cached_property
    def key(self) -> str:
        """Stable sha256 hex digest of the symbolic content, constants and code generator."""
        parts = [
            "ivdrem.models.EulerLagrangeModel", CODEGEN_VERSION, sp.__version__,
            repr([sp.srepr(s) for s in self.q]),
            repr([sp.srepr(s) for s in self.dq]),
            repr([sp.srepr(s) for s in self.theta]),
            sp.srepr(self.M), sp.srepr(self.G), sp.srepr(self.F),
            repr(sorted((sp.srepr(k), repr(v)) for k, v in self.constants.items())),
        ]
        return hashlib.sha256("\n".join(parts).encode("utf-8")).hexdigest()

    def __repr__(self):
        return f"EulerLagrangeModel({self.name!r}, n={self.n}, ntheta={self.ntheta})"

    # ------------------------------------------------------------------ code generation
    def source(self, prefix: str = "") -> str:
        """Python source defining the generated functions, names prefixed with ``prefix``.

        The fragment needs ``import math`` and ``import numpy as np`` at the top of the
        module it is placed in, and is numba-nopython compilable.
        """
        # sympy's printing takes minutes for a large arm: kept on disk
        return self._memo_source(prefix, lambda p: linalg_import(p) + self._disk_cached_source(
            p, self._generate_body))

    def generate_source(self, prefix: str = "") -> str:
        """:meth:`source` made from the symbolic model, without any cache."""
        prefix = self._check_prefix(prefix)
        return linalg_import(prefix) + self._generate_body(prefix)

    def _generate_body(self, prefix):
        # the functions (what the disk cache keeps: the import line names the kernels'
        # current version, which the cached text must not fix)
        prefix = self._check_prefix(prefix)
        return "\n\n".join(self._gen(name, prefix) for name in _FUNCTION_NAMES) + "\n"

    @cached_property
    def _numeric(self):
        """Symbolic expressions with constants substituted, and variable naming."""
        csub = {k: sp.Float(v, 17) for k, v in self.constants.items()}
        # map every model symbol to a code-safe symbol and its array access
        names = {}
        groups = {"q": self.q, "dq": self.dq, "theta": self.theta,
                  "a": self.a, "v": self.v, "dv": self.dv}
        code_name = {"q": "q", "dq": "dq", "theta": "th", "a": "a", "v": "v", "dv": "dv"}
        ren = {}
        for g, syms in groups.items():
            for i, s in enumerate(syms):
                cs = sp.Symbol(f"{code_name[g]}_{i}")
                ren[s] = cs
                names[cs] = f"{g}[{i}]"
        sub = dict(csub)
        sub.update(ren)

        def num(m):
            return sp.Matrix(m).xreplace(sub)

        return types.SimpleNamespace(num=num, access=names)

    def _gen(self, fname, prefix):
        N = self._numeric
        n = self.n
        full = prefix + fname
        if fname in ("Phi_M", "Phi_C", "Phi_dM", "Phi_G", "Phi_F", "Phi"):
            expr = N.num(getattr(self, fname))
            args = {"Phi_M": "q, a", "Phi_C": "q, dq, v", "Phi_dM": "q, dq, a", "Phi_G": "q",
                    "Phi_F": "dq", "Phi": "q, dq, v, dv"}[fname]
            doc = {"Phi_M": "Phi_M^T(q, a) = d(M a)/dtheta",
                   "Phi_C": "Phi_C^T(q, dq, v) = d(C v)/dtheta",
                   "Phi_dM": "Phi_dM^T(q, dq, a) = d(Mdot a)/dtheta",
                   "Phi_G": "Phi_G^T(q) = dG/dtheta", "Phi_F": "Phi_F^T(dq) = dF/dtheta",
                   "Phi": "Phi^T(q, dq, v, dv) = Phi_M^T(q,dv)+Phi_C^T(q,dq,v)+Phi_F^T+Phi_G^T",
                   }[fname]
            return self._emit(full, f"{args}, out", f"{doc}; out ({n}, {self.ntheta})",
                              [((i, j), expr[i, j]) for i in range(n) for j in range(self.ntheta)],
                              two_d=True)
        if fname.endswith("_jac") and fname[:-4] in REGRESSOR_ARGS:
            base = fname[:-4]
            args = REGRESSOR_ARGS[base]
            k, nt = len(args), self.ntheta
            expr = N.num(self.regressor_jacobian(base))
            doc = (f"d{base}[i, j]/d(" + ", ".join(args) + f")[c], c = arg * {n} + entry; "
                   f"out ({n}, {nt}, {k * n})")
            return self._emit(full, ", ".join(args) + ", out", doc,
                              [((i, j, c), expr[i * nt + j, c]) for i in range(n)
                               for j in range(nt) for c in range(k * n)], two_d=True)
        if fname == "M":
            expr = N.num(self.M)
            return self._emit(full, "q, theta, out", f"inertia matrix M(q); out ({n}, {n})",
                              [((i, j), expr[i, j]) for i in range(n) for j in range(n)], two_d=True)
        if fname == "C":
            expr = N.num(self.C)
            return self._emit(full, "q, dq, theta, out",
                              f"Coriolis matrix C(q, dq) (Christoffel); out ({n}, {n})",
                              [((i, j), expr[i, j]) for i in range(n) for j in range(n)], two_d=True)
        if fname == "G":
            expr = N.num(self.G)
            return self._emit(full, "q, theta, out", f"gravity G(q); out ({n},)",
                              [((i,), expr[i]) for i in range(n)], two_d=False)
        if fname == "F":
            expr = N.num(self.F)
            return self._emit(full, "dq, theta, out", f"friction F(dq); out ({n},)",
                              [((i,), expr[i]) for i in range(n)], two_d=False)
        if fname == "forward_dynamics":
            return self._emit_forward_dynamics(full, prefix)
        raise KeyError(fname)  # pragma: no cover

    def _cse(self, exprs):
        syms = sp.numbered_symbols("_t")
        repl, red = sp.cse(exprs, symbols=syms, order="none")
        return repl, red

    def _unpack_lines(self, exprs, repl, indent="    "):
        N = self._numeric
        used = set()
        for e in list(exprs) + [r for _, r in repl]:
            used |= sp.sympify(e).free_symbols
        lines = []
        for s in sorted((s for s in used if s in N.access), key=lambda s: (str(s).split("_")[0],
                                                                           int(str(s).split("_")[1]))):
            lines.append(f"{indent}{s} = {N.access[s]}")
        return lines

    def _emit(self, full, args, doc, entries, two_d):
        P = _Printer()
        nonzero = [(idx, e) for idx, e in entries if e != 0]
        lines = [f"def {full}({args}):", f'    """{doc}"""']
        if len(nonzero) < len(entries):
            lines.append("    out[:] = 0.0")
        if nonzero:
            repl, red = self._cse([e for _, e in nonzero])
            lines += self._unpack_lines(red, repl)
            for s, e in repl:
                lines.append(f"    {s} = {P.doprint(e)}")
            for (idx, _), e in zip(nonzero, red):
                lines.append(f"    out[{', '.join(map(str, idx))}] = {P.doprint(e)}")
        lines.append("    return None")
        return "\n".join(lines)

    def _emit_forward_dynamics(self, full, prefix):
        P = _Printer()
        N = self._numeric
        n = self.n
        Mn = N.num(self.M)
        rhs = N.num(sp.Matrix(self.C) * sp.Matrix(self.dq) + sp.Matrix(self.F) + sp.Matrix(self.G))
        tau = [sp.Symbol(f"tau_{i}") for i in range(n)]
        exprs = [Mn[i, j] for i in range(n) for j in range(i + 1)]  # lower triangle
        exprs += [tau[i] - rhs[i] for i in range(n)]
        repl, red = self._cse(exprs)
        lines = [f"def {full}(q, dq, tau, theta, out):",
                 '    """qdd solving M(q) qdd = tau - C(q,dq) dq - F(dq) - G(q) (Cholesky);'
                 ' out (%d,)"""' % n]
        used = set()
        for e in list(red) + [r for _, r in repl]:
            used |= e.free_symbols
        lines += self._unpack_lines(red, repl)
        for i in range(n):
            if tau[i] in used:
                lines.append(f"    tau_{i} = tau[{i}]")
        for s, e in repl:
            lines.append(f"    {s} = {P.doprint(e)}")
        lines.append(f"    _L = np.empty(({n}, {n}))")
        k = 0
        for i in range(n):
            for j in range(i + 1):
                lines.append(f"    _L[{i}, {j}] = {P.doprint(red[k])}")
                k += 1
        for i in range(n):
            lines.append(f"    out[{i}] = {P.doprint(red[k])}")
            k += 1
        # the package's one Cholesky (ivdrem.models.rigid_body, one rule for "singular")
        lines += [f"    {prefix}_linalg._rb_spd_solve(_L, out)", "    return None"]
        return "\n".join(lines)

    # ------------------------------------------------------------------ the C face
    def _c_symbols(self, with_k):
        """{model symbol: C access symbol} (``q[i]``, ``theta[j]``, ...); the constants as
        ``k[i]`` if `with_k`, else their values (17 digits: every double round-trips)."""
        ren = {}
        for g, syms in (("q", self.q), ("dq", self.dq), ("a", self.a), ("v", self.v),
                        ("dv", self.dv), ("theta", self.theta)):
            for i, s in enumerate(syms):
                ren[s] = sp.Symbol(f"{g}[{i}]")
        for i, (k, v) in enumerate(self.constants.items()):
            ren[k] = sp.Symbol(f"k[{i}]") if with_k else sp.Float(v, 17)
        return ren

    @staticmethod
    def _c_function(head, args, exprs, targets, tail=()):
        """A C function `head` whose body assigns sympy `exprs` (after CSE) to `targets`;
        the pointer arguments it does not read are cast to void."""
        body = []
        if exprs:
            repl, red = sp.cse(list(exprs), symbols=sp.numbered_symbols("w"), order="none")
            body = [f"    const double {s} = {sp.ccode(e, standard='C99')};" for s, e in repl]
            body += [f"    {t} = {sp.ccode(e, standard='C99')};" for t, e in zip(targets, red)]
        text = "\n".join(body)
        unused = [f"    (void){a};" for a in args
                  if not re.search(rf"(?<![A-Za-z_]){a}\[", text)]
        return f"{head} {{\n" + "\n".join(unused + body + list(tail)) + "\n}\n"

    def _make_c_source(self, prefix):
        # sympy's printing takes minutes for a large arm: kept on disk, as source()
        return self._disk_cached_source(prefix, super()._make_c_source, kind="c")

    def _c_body(self, prefix):
        from .base import C_FUNCTION_ARGS, _c_prototype
        P = prefix.upper()
        n, nth = self.n, self.ntheta
        lit = self._c_symbols(False)
        out = []
        for name in ("Phi_M", "Phi_C", "Phi_dM", "Phi_G", "Phi_F", "Phi"):
            # the same printing as the controller's C had (bit-for-bit the same library)
            E = sp.Matrix(getattr(self, name)).xreplace(lit)
            out.append(self._c_function(f"{P}FN {_c_prototype(prefix, name)}",
                                        C_FUNCTION_ARGS[name][:-1],
                                        [E[i, j] for i in range(n) for j in range(nth)],
                                        [f"out[{k}]" for k in range(n * nth)]))
        for name, mat in (("M", self.M), ("C", self.C), ("G", self.G), ("F", self.F)):
            E = sp.Matrix(mat).xreplace(lit)
            out.append(self._c_function(f"{P}FN {_c_prototype(prefix, name)}",
                                        C_FUNCTION_ARGS[name][:-1], list(E),
                                        [f"out[{k}]" for k in range(len(E))]))
        # forward dynamics: M(q) (lower triangle) and tau - C dq - F - G, as the Python
        # forward_dynamics; the constants from k
        ren = self._c_symbols(True)
        Mk = sp.Matrix(self.M).xreplace(ren)
        rhs = (sp.Matrix(self.C) * sp.Matrix(self.dq) + sp.Matrix(self.F)
               + sp.Matrix(self.G)).xreplace(ren)
        lower = [(i, j) for i in range(n) for j in range(i + 1)]
        exprs = [Mk[i, j] for i, j in lower] + [sp.Symbol(f"tau[{i}]") - rhs[i]
                                                for i in range(n)]
        targets = [f"A[{i * n + j}]" for i, j in lower] + [f"ddq[{i}]" for i in range(n)]
        out.append(self._c_function(
            f"{P}FN {_c_prototype(prefix, 'forward_dynamics_k')}",
            C_FUNCTION_ARGS["forward_dynamics_k"][:-1], exprs, targets,
            [f"    if ({prefix}rb_cholesky(A) != 0) return 1;",
             f"    {prefix}rb_cholesky_solve(A, ddq);", "    return 0;"]).replace(
                " {\n", f" {{\n    double A[{n * n}];\n", 1))
        kvals = ", ".join(repr(float(v)) for v in self.constants.values()) or "0.0"
        out.append(f"static const double {prefix}constants[{max(1, len(self.constants))}] = "
                   f"{{{kvals}}};\n\n"
                   f"{P}FN {_c_prototype(prefix, 'forward_dynamics')} {{\n"
                   f"    return {prefix}forward_dynamics_k(q, dq, tau, theta, "
                   f"{prefix}constants, ddq);\n}}\n")
        return "\n" + "\n".join(out)
