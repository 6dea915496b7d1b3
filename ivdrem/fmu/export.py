"""Export the robot plant of an :class:`~ivdrem.models.EulerLagrangeModel` as an FMI 2.0 FMU.

The FMU is generated C, not a Python wrapper: the plant's ``M(q)`` and bias
``b(q, q') = C(q, q') q' + F(q') + G(q)`` are printed from the same sympy model that the
Python plant (``model.functions.forward_dynamics``) comes from, with sympy's C99 printer
after common-subexpression elimination (``sympy.cse``); for an arm from a URDF
(:class:`~ivdrem.models.RigidBodyModel`) they are the same recursive Newton-Euler algorithm
as its Python kernels (:mod:`ivdrem.models.rigid_body`), written in C over the chain's
constant arrays (``M`` column by column, ``b`` in one pass), its parameters the base
parameters.  A fixed, hand-written C file
(``fmi2_plant.c``, style of the FMI Reference FMUs) implements the FMI 2.0 API on top of
it: ``q'' = M^-1 (tau + tau_d - b)`` by Cholesky, a state machine, error checks, FMU state
get/set/serialize.  One binary provides model exchange and co-simulation.

FMU contents::

    modelDescription.xml
    binaries/<platform>/<modelIdentifier>.so   compiled with the system C compiler
    sources/fmi2_plant.c  sources/plant_model.c  sources/plant_model.h
    sources/fmi2Functions.h  fmi2FunctionTypes.h  fmi2TypesPlatform.h  (copied from fmpy)
    documentation/index.html

``fmpy compile FILE.fmu`` rebuilds the binary from ``sources/`` on another platform.

Variables (value reference = position in this list, 0-based; n = DoF)::

    q[i]          output, continuous, initial="exact" (start = q0)    state   rad
    dq[i]         output, continuous, initial="exact" (start = dq0)   state   rad/s
    der(q[i])     local, derivative of q[i] (= dq[i])                         rad/s
    der(dq[i])    local, derivative of dq[i] (= q''[i])                       rad/s2
    tau[i]        input, continuous, start 0 (control torque)                 N.m
    tau_d[i]      input, continuous, start 0 (disturbance torque)             N.m
    <theta names> parameter, fixed: the model parameters theta, start = theta_values
    <constants>   parameter, fixed: the model constants (g, link lengths ...)
    cs_substep    parameter, fixed: bound h of the co-simulation RK4 sub-step  s

Parameters are ``variability="fixed"``: they may be changed after instantiation and in
initialization mode, not afterwards.  The continuous state vector (order of
``ModelStructure/Derivatives``) is ``x = [q, dq]``.

Co-simulation: ``fmi2DoStep(t, H)`` integrates with ``k = ceil(H / cs_substep)`` classical
Runge-Kutta (RK4) steps of equal size ``H / k <= cs_substep``, inputs held constant over
the step.  The global error is O(cs_substep^4): over 2 s with piecewise-constant torques
(tests/test_fmu.py) the default 1e-3 s gives max errors of about 2e-9 (2-link arm) and 3e-7
(planar-3) against a DOP853 reference, 1e-4 s gives 4e-12 and 3e-11.  Model exchange
ignores ``cs_substep``.

Errors (non-finite inputs or parameters, ``M(q)`` not positive definite, calls in the wrong
state) return ``fmi2Error`` after a message to the logger (category ``logStatusError``).
"""
from __future__ import annotations

import hashlib
import html
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import uuid
import warnings
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np
import sympy as sp

from .._atomic import zip_tree_atomic
from .._paths import check_replaceable

__all__ = ["export_fmu", "generate_sources", "fmi2_header_dir", "FMU_SOURCE_FILES",
           "DEFAULT_SUBSTEP"]

#: Default bound of the co-simulation RK4 sub-step (parameter ``cs_substep``), seconds.
DEFAULT_SUBSTEP = 1e-3

#: C files compiled into the binary (listed in modelDescription.xml SourceFiles).
FMU_SOURCE_FILES = ("fmi2_plant.c", "plant_model.c")

_FMI2_HEADERS = ("fmi2Functions.h", "fmi2FunctionTypes.h", "fmi2TypesPlatform.h")

_HERE = Path(__file__).resolve().parent

# Units: name -> (FMI 2.0 BaseUnit exponents of kg, m, s, rad)
_UNITS = {
    "rad": dict(rad=1),
    "rad/s": dict(s=-1, rad=1),
    "rad/s2": dict(s=-2, rad=1),
    "N.m": dict(kg=1, m=2, s=-2),
    "N.m.s/rad": dict(kg=1, m=2, s=-1, rad=-1),
    "N.s/m": dict(kg=1, s=-1),
    "N": dict(kg=1, m=1, s=-2),
    "m/s2": dict(m=1, s=-2),
    "m": dict(m=1),
    "kg": dict(kg=1),
    "kg.m": dict(kg=1, m=1),
    "kg.m2": dict(kg=1, m=2),
    "s": dict(s=1),
}


def _default_parameter_units(model) -> dict:
    """Units of the model's parameters and constants: its ``parameter_units`` {name: unit}
    (every model of :mod:`ivdrem.models` declares them), and ``m/s2`` for a constant named
    ``g`` it leaves out.  Names not covered get no unit (rather than a wrong one)."""
    units = {str(s): "m/s2" for s in model.constants if str(s) == "g"}
    units.update(getattr(model, "parameter_units", None) or {})
    return units


def fmi2_header_dir() -> Path:
    """Directory of the FMI 2.0 headers shipped with fmpy (maintained copies of the standard's)."""
    import fmpy
    d = Path(fmpy.__file__).resolve().parent / "c-code"
    if not all((d / h).is_file() for h in _FMI2_HEADERS):
        raise FileNotFoundError(f"the FMI 2.0 headers {', '.join(_FMI2_HEADERS)} were not found "
                                f"in {d} (fmpy {getattr(fmpy, '__version__', '?')})")
    return d


# ----------------------------------------------------------------------------- layout
@dataclass
class _Layout:
    """Variables of the FMU in value-reference order (see the module docstring)."""
    n: int
    param_names: list
    param_values: list
    param_units: list
    param_descriptions: list
    q0: np.ndarray
    dq0: np.ndarray
    substep: float
    variables: list = field(default_factory=list)  # dicts, index = vr + 1

    @property
    def n_params(self):
        return len(self.param_names)

    # value references (0-based), mirrored by plant_model.h
    def vr_q(self, i): return i
    def vr_dq(self, i): return self.n + i
    def vr_der_q(self, i): return 2 * self.n + i
    def vr_der_dq(self, i): return 3 * self.n + i
    def vr_tau(self, i): return 4 * self.n + i
    def vr_tau_d(self, i): return 5 * self.n + i
    def vr_p(self, k): return 6 * self.n + k
    @property
    def vr_substep(self): return 6 * self.n + self.n_params


def _check_vector(name, value, n):
    a = np.zeros(n) if value is None else np.asarray(value, dtype=float).reshape(-1)
    if a.shape != (n,):
        raise ValueError(f"{name} must have length {n}, got {a.size}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite, got {a}")
    return a


def _layout(model, q0, dq0, substep) -> _Layout:
    n = model.n
    if model.theta_values is None:
        raise ValueError(f"model {model.name!r} has no theta_values: the FMU needs start values "
                         "for the parameters")
    units = _default_parameter_units(model)
    names = list(model.theta_names) + [str(s) for s in model.constants]
    values = [float(v) for v in model.theta_values] + [float(v) for v in model.constants.values()]
    descr = ([f"model parameter theta[{k}]" for k in range(model.ntheta)]
             + [f"model constant {s}" for s in model.constants])
    substep = float(substep)
    if not (np.isfinite(substep) and substep > 0):
        raise ValueError(f"substep must be a positive finite number, got {substep}")
    lay = _Layout(n, names, values, [units.get(nm) for nm in names], descr,
                  _check_vector("q0", q0, n), _check_vector("dq0", dq0, n), substep)
    V = lay.variables
    for i in range(n):
        V.append(dict(name=f"q[{i}]", causality="output", variability="continuous",
                      initial="exact", start=lay.q0[i], unit="rad",
                      description=f"joint position {i} (continuous state)"))
    for i in range(n):
        V.append(dict(name=f"dq[{i}]", causality="output", variability="continuous",
                      initial="exact", start=lay.dq0[i], unit="rad/s",
                      description=f"joint velocity {i} (continuous state)"))
    for i in range(n):
        V.append(dict(name=f"der(q[{i}])", causality="local", variability="continuous",
                      initial="calculated", derivative=lay.vr_q(i) + 1, unit="rad/s",
                      description=f"derivative of q[{i}] (= dq[{i}])"))
    for i in range(n):
        V.append(dict(name=f"der(dq[{i}])", causality="local", variability="continuous",
                      initial="calculated", derivative=lay.vr_dq(i) + 1, unit="rad/s2",
                      description=f"joint acceleration {i}: derivative of dq[{i}]"))
    for i in range(n):
        V.append(dict(name=f"tau[{i}]", causality="input", variability="continuous",
                      start=0.0, unit="N.m", description=f"control torque {i}"))
    for i in range(n):
        V.append(dict(name=f"tau_d[{i}]", causality="input", variability="continuous",
                      start=0.0, unit="N.m", description=f"disturbance torque {i}"))
    for k in range(lay.n_params):
        V.append(dict(name=names[k], causality="parameter", variability="fixed",
                      initial="exact", start=values[k], unit=lay.param_units[k],
                      description=descr[k]))
    V.append(dict(name="cs_substep", causality="parameter", variability="fixed",
                  initial="exact", start=substep, unit="s",
                  description="co-simulation: bound of the fixed RK4 sub-step "
                              "(fmi2DoStep uses ceil(H/cs_substep) equal sub-steps)"))
    all_names = [v["name"] for v in V]
    dup = sorted({nm for nm in all_names if all_names.count(nm) > 1})
    if dup:
        raise ValueError(f"parameter names of model {model.name!r} clash with FMU variable "
                         f"names: {', '.join(dup)}")
    return lay


# ----------------------------------------------------------------------------- dependencies
def _free(expr):
    return sp.sympify(expr).free_symbols


def _dependencies(model):
    """Structural dependencies of q''[i] on q, dq, tau/tau_d (joint indices) and parameters.

    q'' = M^-1 (tau + tau_d - b): q''[i] depends on everything that enters the rows and
    columns of the connected component of joint i in the sparsity graph of M (M^-1 is
    block diagonal over these components, and generically full inside each).
    """
    n = model.n
    if _is_rigid_body(model):
        # every joint of a serial arm couples with every other (M^-1 is full): dense
        return [dict(q=list(range(n)), dq=list(range(n)), tau=list(range(n)),
                     theta=list(range(model.ntheta)), const=[]) for _ in range(n)]
    M = sp.Matrix(model.M)
    b = sp.Matrix(model.C) * sp.Matrix(model.dq) + sp.Matrix(model.F) + sp.Matrix(model.G)
    # connected components of the sparsity graph of M
    comp = list(range(n))

    def root(i):
        while comp[i] != i:
            i = comp[i]
        return i

    for i in range(n):
        for j in range(n):
            if M[i, j] != 0:
                comp[root(i)] = root(j)
    deps = []
    for i in range(n):
        K = [k for k in range(n) if root(k) == root(i)]
        syms = set()
        for r in K:
            syms |= _free(b[r])
            for c in K:
                syms |= _free(M[r, c])
        deps.append(dict(
            q=[j for j in range(n) if model.q[j] in syms],
            dq=[j for j in range(n) if model.dq[j] in syms],
            tau=K,
            theta=[k for k in range(model.ntheta) if model.theta[k] in syms],
            const=[k for k, s in enumerate(model.constants) if s in syms]))
    return deps


# ----------------------------------------------------------------------------- C code
_MATH_CONSTANTS = {
    "M_E": "2.718281828459045235360287471352662498", "M_LOG2E": "1.442695040888963407359924681001892137",
    "M_LOG10E": "0.434294481903251827651128918916605082", "M_LN2": "0.693147180559945309417232121458176568",
    "M_LN10": "2.302585092994045684017991454684364208", "M_PI": "3.141592653589793238462643383279502884",
    "M_PI_2": "1.570796326794896619231321691639751442", "M_PI_4": "0.785398163397448309615660845819875721",
    "M_1_PI": "0.318309886183790671537767526745028724", "M_2_PI": "0.636619772367581343075535053490057448",
    "M_2_SQRTPI": "1.128379167095512573896158903121545172", "M_SQRT2": "1.414213562373095048801688724209698079",
    "M_SQRT1_2": "0.707106781186547524400844362104849039",
}


def _c_double(x: float) -> str:
    s = repr(float(x))
    return s if ("e" in s or "." in s or "inf" in s or "nan" in s) else s + ".0"


def _c_string(s: str) -> str:
    return '"' + s.replace("\\", "\\\\").replace('"', '\\"') + '"'


def _model_code(model, lay: _Layout, guid: str, deps_comment: str) -> tuple[str, str]:
    """plant_model.h and plant_model.c for ``model``."""
    n = model.n
    ren = {}
    for i in range(n):
        ren[model.q[i]] = sp.Symbol(f"q[{i}]")
        ren[model.dq[i]] = sp.Symbol(f"dq[{i}]")
    for k, s in enumerate(list(model.theta) + list(model.constants)):
        ren[s] = sp.Symbol(f"p[{k}]")
    M = sp.Matrix(model.M).xreplace(ren)
    b = (sp.Matrix(model.C) * sp.Matrix(model.dq) + sp.Matrix(model.F)
         + sp.Matrix(model.G)).xreplace(ren)
    allowed = set(ren.values())
    for e in list(M) + list(b):
        extra = _free(e) - allowed
        if extra:
            raise ValueError(f"model {model.name!r}: M, C, F, G contain symbols that are not q, dq, "
                             f"theta or constants: {', '.join(sorted(map(str, extra)))}")

    def emit(exprs, targets):
        repl, red = sp.cse(exprs, symbols=sp.numbered_symbols("w"), order="none")
        lines = [f"    const double {s} = {sp.ccode(e, standard='C99')};" for s, e in repl]
        lines += [f"    {t} = {sp.ccode(e, standard='C99')};" for t, e in zip(targets, red)]
        return lines

    lower = [(i, j) for i in range(n) for j in range(i + 1)]
    mass_lines = emit([M[i, j] for i, j in lower], [f"M[{i * n + j}]" for i, j in lower])
    mass_lines += [f"    M[{j * n + i}] = M[{i * n + j}];" for i, j in lower if i != j]
    bias_lines = emit(list(b), [f"b[{i}]" for i in range(n)])

    def uses(lines, arg):  # "q[" must not match "dq["
        return any(re.search(rf"(?<![A-Za-z_]){re.escape(arg)}\[", ln) for ln in lines)

    used = {"mass_q": uses(mass_lines, "q"), "mass_p": uses(mass_lines, "p"),
            "bias_q": uses(bias_lines, "q"), "bias_dq": uses(bias_lines, "dq"),
            "bias_p": uses(bias_lines, "p")}

    def unused(flag, arg):
        return [] if used[flag] else [f"    (void){arg};"]

    header = _header(model, lay, guid, "the sympy model")
    consts = "\n".join(f"#ifndef {k}\n#define {k} {v}\n#endif" for k, v in _MATH_CONSTANTS.items()
                       if any(re.search(rf"\b{k}\b", ln) for ln in mass_lines + bias_lines))
    pnames = ", ".join(_c_string(nm) for nm in lay.param_names)
    pvals = ", ".join(_c_double(v) for v in lay.param_values)
    pmap = "\n".join(f" *   p[{k}] = {nm}" for k, nm in enumerate(lay.param_names))
    source = f"""/* plant_model.c: generated by ivdrem {_version()} from the sympy model "{model.name}"
 * (model key {model.key}) with sympy {sp.__version__}: sympy.cse + sympy.ccode (C99).
 * Do not edit.
 *
 *   M(q) q'' + C(q, q') q' + F(q') + G(q) = tau + tau_d
 *
 * q[i], dq[i]: joint positions and velocities; parameter vector p:
{pmap}
 *
{deps_comment}
 */
#include <math.h>
#include "plant_model.h"
{consts}

const double Q_START[NQ] = {{{", ".join(_c_double(v) for v in lay.q0)}}};
const double DQ_START[NQ] = {{{", ".join(_c_double(v) for v in lay.dq0)}}};
const double P_START[NP] = {{{pvals}}};
const char *const PARAMETER_NAMES[NP] = {{{pnames}}};

void plant_mass(const double *q, const double *p, double *M) {{
{chr(10).join(unused("mass_q", "q") + unused("mass_p", "p") + mass_lines)}
}}

void plant_bias(const double *q, const double *dq, const double *p, double *b) {{
{chr(10).join(unused("bias_q", "q") + unused("bias_dq", "dq") + unused("bias_p", "p") + bias_lines)}
}}
"""
    return header, source


def _header(model, lay: _Layout, guid: str, origin: str) -> str:
    """plant_model.h: the layout used by fmi2_plant.c."""
    n = model.n
    return f"""/* plant_model.h: generated by ivdrem {_version()} from {origin} "{model.name}"
 * (model key {model.key}). Do not edit. Layout used by fmi2_plant.c. */
#ifndef PLANT_MODEL_H
#define PLANT_MODEL_H

#define MODEL_GUID {_c_string(guid)}

#define NQ {n}     /* degrees of freedom */
#define NTHETA {model.ntheta} /* parameters theta: p[0 .. NTHETA-1] */
#define NCONST {len(model.constants)} /* model constants: p[NTHETA ...] */
#define NP (NTHETA + NCONST)

/* value references, as in modelDescription.xml */
#define VR_Q      0                 /* q[i]        */
#define VR_DQ     (NQ)              /* dq[i]       */
#define VR_DER_Q  (2 * NQ)          /* der(q[i])   */
#define VR_DER_DQ (3 * NQ)          /* der(dq[i])  */
#define VR_TAU    (4 * NQ)          /* tau[i]      */
#define VR_TAU_D  (5 * NQ)          /* tau_d[i]    */
#define VR_P      (6 * NQ)          /* parameters  */
#define VR_SUBSTEP (6 * NQ + NP)    /* cs_substep  */

#define SUBSTEP_START {_c_double(lay.substep)}

#if defined(__GNUC__) && !defined(_WIN32)
#define PLANT_INTERNAL __attribute__((visibility("hidden")))
#else
#define PLANT_INTERNAL
#endif

PLANT_INTERNAL extern const double Q_START[NQ];
PLANT_INTERNAL extern const double DQ_START[NQ];
PLANT_INTERNAL extern const double P_START[NP];
PLANT_INTERNAL extern const char *const PARAMETER_NAMES[NP];

/* M(q) (row major, NQ x NQ) */
PLANT_INTERNAL void plant_mass(const double *q, const double *p, double *M);
/* b(q, dq) = C(q, dq) dq + F(dq) + G(q) */
PLANT_INTERNAL void plant_bias(const double *q, const double *dq, const double *p, double *b);

#endif
"""

def _is_rigid_body(model) -> bool:
    from ivdrem.models import RigidBodyModel
    return isinstance(model, RigidBodyModel)


def _c_array(values) -> str:
    return "{" + ", ".join(_c_double(v) for v in np.asarray(values, float).reshape(-1)) + "}"


# The recursive Newton-Euler algorithm of ivdrem.models.rigid_body in C (docs/models.md):
# body frames, spatial vectors (linear, angular), the base accelerating at -g.
_RNEA_C = r"""
static void body_pose(int j, double qj, double R[3][3], double p[3]) {
    const double *u = AXIS[j];
    if (JTYPE[j] == 0) {
        const double c = cos(qj), s = sin(qj), t = 1.0 - c;
        const double E[3][3] = {
            {c + t * u[0] * u[0], t * u[0] * u[1] - s * u[2], t * u[0] * u[2] + s * u[1]},
            {t * u[0] * u[1] + s * u[2], c + t * u[1] * u[1], t * u[1] * u[2] - s * u[0]},
            {t * u[0] * u[2] - s * u[1], t * u[1] * u[2] + s * u[0], c + t * u[2] * u[2]}};
        for (int r = 0; r < 3; r++) {
            for (int k = 0; k < 3; k++)
                R[r][k] = RP[j][r][0] * E[0][k] + RP[j][r][1] * E[1][k] + RP[j][r][2] * E[2][k];
            p[r] = PP[j][r];
        }
    } else {
        for (int r = 0; r < 3; r++) {
            for (int k = 0; k < 3; k++) R[r][k] = RP[j][r][k];
            p[r] = PP[j][r] + (RP[j][r][0] * u[0] + RP[j][r][1] * u[1] + RP[j][r][2] * u[2]) * qj;
        }
    }
}

static void cross3(const double *a, const double *b, double *out) {
    out[0] = a[1] * b[2] - a[2] * b[1];
    out[1] = a[2] * b[0] - a[0] * b[2];
    out[2] = a[0] * b[1] - a[1] * b[0];
}

/* motion m (parent frame) in the frame (R, p): (R^T (m_l - p x m_a), R^T m_a) */
static void xmotion(double R[3][3], const double *p, const double *m, double *out) {
    double px[3], t[3];
    cross3(p, m + 3, px);
    for (int r = 0; r < 3; r++) t[r] = m[r] - px[r];
    for (int r = 0; r < 3; r++) {
        out[r] = R[0][r] * t[0] + R[1][r] * t[1] + R[2][r] * t[2];
        out[3 + r] = R[0][r] * m[3] + R[1][r] * m[4] + R[2][r] * m[5];
    }
}

/* tau = C(q, w) w + M(q) acc + grav G(q) for standard link parameters pi */
static void rnea(const double *q, const double *w, const double *acc, double grav,
                 const double *pi, double *tau) {
    double R[NQ][3][3], p[NQ][3], V[NQ][6], A[NQ][6], f[NQ][6];
    for (int j = 0; j < NQ; j++) {
        double vp[6] = {0, 0, 0, 0, 0, 0}, ap[6], t[6], sw[6] = {0, 0, 0, 0, 0, 0};
        body_pose(j, q[j], R[j], p[j]);
        if (PARENT[j] < 0) {
            for (int r = 0; r < 3; r++) { ap[r] = -grav * GRAV[r]; ap[3 + r] = 0.0; }
        } else {
            for (int r = 0; r < 6; r++) { vp[r] = V[PARENT[j]][r]; ap[r] = A[PARENT[j]][r]; }
        }
        const int off = JTYPE[j] == 0 ? 3 : 0;
        for (int r = 0; r < 3; r++) sw[off + r] = AXIS[j][r] * w[j];
        xmotion(R[j], p[j], vp, t);
        for (int r = 0; r < 6; r++) V[j][r] = t[r] + sw[r];
        xmotion(R[j], p[j], ap, t);
        for (int r = 0; r < 3; r++) t[off + r] += AXIS[j][r] * acc[j];
        /* + V x (S w): (w x sw_l + v x sw_a, w x sw_a) */
        double c1[3], c2[3], c3[3];
        cross3(V[j] + 3, sw, c1);
        cross3(V[j], sw + 3, c2);
        cross3(V[j] + 3, sw + 3, c3);
        for (int r = 0; r < 3; r++) { A[j][r] = t[r] + c1[r] + c2[r]; A[j][3 + r] = t[3 + r] + c3[r]; }
        /* body force f = I A + V x* (I V) about the joint frame's origin */
        const double *P = pi + 10 * j;
        const double m = P[0], h[3] = {P[1], P[2], P[3]};
        const double I[3][3] = {{P[4], P[5], P[7]}, {P[5], P[6], P[8]}, {P[7], P[8], P[9]}};
        const double *v = V[j], *om = V[j] + 3, *a = A[j], *al = A[j] + 3;
        double hw[3], hv[3], ha[3], hal[3], L[3], H[3], wL[3], wH[3], vL[3];
        cross3(h, om, hw);
        cross3(h, v, hv);
        cross3(h, a, ha);
        cross3(h, al, hal);
        for (int r = 0; r < 3; r++) {
            L[r] = m * v[r] - hw[r];
            H[r] = I[r][0] * om[0] + I[r][1] * om[1] + I[r][2] * om[2] + hv[r];
        }
        cross3(om, L, wL);
        cross3(om, H, wH);
        cross3(v, L, vL);
        for (int r = 0; r < 3; r++) {
            f[j][r] = m * a[r] - hal[r] + wL[r];
            f[j][3 + r] = I[r][0] * al[0] + I[r][1] * al[1] + I[r][2] * al[2] + ha[r] + wH[r] + vL[r];
        }
    }
    for (int j = NQ - 1; j >= 0; j--) {
        const int off = JTYPE[j] == 0 ? 3 : 0;
        tau[j] = AXIS[j][0] * f[j][off] + AXIS[j][1] * f[j][off + 1] + AXIS[j][2] * f[j][off + 2];
        const int pa = PARENT[j];
        if (pa >= 0) {
            double fl[3], nl[3], pf[3];
            for (int r = 0; r < 3; r++) {
                fl[r] = R[j][r][0] * f[j][0] + R[j][r][1] * f[j][1] + R[j][r][2] * f[j][2];
                nl[r] = R[j][r][0] * f[j][3] + R[j][r][1] * f[j][4] + R[j][r][2] * f[j][5];
            }
            cross3(p[j], fl, pf);
            for (int r = 0; r < 3; r++) { f[pa][r] += fl[r]; f[pa][3 + r] += nl[r] + pf[r]; }
        }
    }
}

/* standard parameters with K pi = theta: the base ones in their columns, the others 0 */
static void standard_parameters(const double *p, double *pi) {
    for (int k = 0; k < NSTD; k++) pi[k] = 0.0;
    for (int b = 0; b < NTHETA; b++) pi[BASE[b]] = p[b];
}

void plant_mass(const double *q, const double *p, double *M) {
    double pi[NSTD], z[NQ], e[NQ], tau[NQ];
    standard_parameters(p, pi);
    for (int i = 0; i < NQ; i++) z[i] = 0.0;
    for (int k = 0; k < NQ; k++) {
        for (int i = 0; i < NQ; i++) e[i] = (i == k) ? 1.0 : 0.0;
        rnea(q, z, e, 0.0, pi, tau);
        for (int i = 0; i < NQ; i++) M[i * NQ + k] = tau[i];
        if (IA >= 0) M[k * NQ + k] += pi[IA + k];
    }
}

void plant_bias(const double *q, const double *dq, const double *p, double *b) {
    double pi[NSTD], z[NQ];
    standard_parameters(p, pi);
    for (int i = 0; i < NQ; i++) z[i] = 0.0;
    rnea(q, dq, z, 1.0, pi, b);
    for (int i = 0; i < NQ; i++) {
        if (FV >= 0) b[i] += pi[FV + i] * dq[i];
        if (FC >= 0) b[i] += pi[FC + i] * tanh(dq[i] / FRICTION_WIDTH);
    }
}
"""


def _rigid_body_code(model, lay: _Layout, guid: str, deps_comment: str) -> tuple[str, str]:
    """plant_model.h and plant_model.c of a URDF arm: the recursive Newton-Euler algorithm
    of ivdrem.models.rigid_body in C, over the chain as constant arrays."""
    n = model.n
    ch = model._chain
    nl = 10 * n
    fv = nl if ch["viscous"] else -1
    fc = nl + (n if ch["viscous"] else 0) if ch["coulomb"] else -1
    ia = (nl + (n if ch["viscous"] else 0) + (n if ch["coulomb"] else 0)) if ch["armature"] else -1
    header = _header(model, lay, guid, "the URDF model")
    pmap = "\n".join(f" *   p[{k}] = {nm}" for k, nm in enumerate(lay.param_names))
    groups = "\n".join(f" *   {nm} = " + " + ".join(f"{c:.17g} {s}" for c, s in terms)
                       for nm, _, _, terms in model.parameter_table())
    pnames = ", ".join(_c_string(nm) for nm in lay.param_names)
    pvals = ", ".join(_c_double(v) for v in lay.param_values)

    def mat(rows):
        return "{" + ", ".join(_c_array(r) for r in rows) + "}"

    source = f"""/* plant_model.c: generated by ivdrem {_version()} from the URDF model "{model.name}"
 * ({model.urdf}; model key {model.key}): the recursive Newton-Euler algorithm over the
 * chain's constant data.  Do not edit.
 *
 *   M(q) q'' + C(q, q') q' + F(q') + G(q) = tau + tau_d
 *
 * joints: {", ".join(model.joint_names)}
 * q[i], dq[i]: joint positions and velocities; parameter vector p (base parameters):
{pmap}
 * each the combination of standard parameters (10 per link about its joint frame:
 * m, mx, my, mz, Ixx, Ixy, Iyy, Ixz, Iyz, Izz; friction fv, fc; armature Ia):
{groups}
 *
{deps_comment}
 */
#include <math.h>
#include "plant_model.h"

#define NSTD {model.nstandard}
#define FV {fv}
#define FC {fc}
#define IA {ia}
#define FRICTION_WIDTH {_c_double(model.friction_width)}

static const int PARENT[NQ] = {{{", ".join(str(int(x)) for x in ch["parent"])}}};
static const int JTYPE[NQ] = {{{", ".join(str(int(x)) for x in ch["jtype"])}}};
static const double AXIS[NQ][3] = {mat(ch["axis"])};
static const double RP[NQ][3][3] = {{{", ".join(mat(r) for r in ch["Rp"])}}};
static const double PP[NQ][3] = {mat(ch["pp"])};
static const double GRAV[3] = {_c_array(ch["gravity"])};
static const int BASE[NTHETA] = {{{", ".join(str(int(x)) for x in model.base_columns)}}};

const double Q_START[NQ] = {{{", ".join(_c_double(v) for v in lay.q0)}}};
const double DQ_START[NQ] = {{{", ".join(_c_double(v) for v in lay.dq0)}}};
const double P_START[NP] = {{{pvals}}};
const char *const PARAMETER_NAMES[NP] = {{{pnames}}};
{_RNEA_C}"""
    return header, source


def _version():
    try:
        from ivdrem import __version__
        return __version__
    except Exception:  # pragma: no cover
        return "?"


# ----------------------------------------------------------------------------- XML
def _fmt(x: float) -> str:
    return repr(float(x))


def _model_description(model, lay: _Layout, guid: str, model_identifier: str, deps) -> str:
    n = model.n
    idx = lambda vr: vr + 1  # noqa: E731  (ScalarVariable index is 1-based)
    units_used = sorted({v["unit"] for v in lay.variables if v.get("unit")})
    for u in units_used:
        if u not in _UNITS:
            raise ValueError(f"unknown unit {u!r}; known: {', '.join(_UNITS)}")
    src = "\n".join(f'      <File name="{f}"/>' for f in FMU_SOURCE_FILES)
    out = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        '<fmiModelDescription',
        '  fmiVersion="2.0"',
        f'  modelName={quoteattr("ivdrem plant " + model.name)}',
        f'  guid="{guid}"',
        f'  description={quoteattr(f"Euler-Lagrange robot {model.name} (n = {n}): M(q) ddq + C(q,dq) dq + F(dq) + G(q) = tau + tau_d. Generated C; co-simulation uses fixed RK4 sub-steps of at most cs_substep.")}',
        f'  generationTool="ivdrem {_version()}"',
        '  variableNamingConvention="structured"',
        '  numberOfEventIndicators="0">',
        f'  <ModelExchange modelIdentifier="{model_identifier}" canGetAndSetFMUstate="true"'
        ' canSerializeFMUstate="true" canNotUseMemoryManagementFunctions="true"'
        ' completedIntegratorStepNotNeeded="true" providesDirectionalDerivative="false">',
        '    <SourceFiles>', src, '    </SourceFiles>',
        '  </ModelExchange>',
        f'  <CoSimulation modelIdentifier="{model_identifier}" canHandleVariableCommunicationStepSize="true"'
        ' canInterpolateInputs="false" maxOutputDerivativeOrder="0" canRunAsynchronuously="false"'
        ' canGetAndSetFMUstate="true" canSerializeFMUstate="true" canNotUseMemoryManagementFunctions="true"'
        ' providesDirectionalDerivative="false">',
        '    <SourceFiles>', src, '    </SourceFiles>',
        '  </CoSimulation>',
        '  <UnitDefinitions>',
    ]
    for u in units_used:
        attrs = " ".join(f'{k}="{v}"' for k, v in _UNITS[u].items())
        out.append(f'    <Unit name="{u}"><BaseUnit {attrs}/></Unit>')
    out += [
        '  </UnitDefinitions>',
        '  <LogCategories>',
        '    <Category name="logEvents" description="Mode changes (debug logging)"/>',
        '    <Category name="logStatusError" description="Errors: illegal calls, bad values (always logged)"/>',
        '  </LogCategories>',
        f'  <DefaultExperiment startTime="0" stopTime="10" stepSize="{_fmt(lay.substep)}"/>',
        '  <ModelVariables>',
    ]
    for vr, v in enumerate(lay.variables):
        attrs = [f'name={quoteattr(v["name"])}', f'valueReference="{vr}"',
                 f'description={quoteattr(v["description"])}',
                 f'causality="{v["causality"]}"', f'variability="{v["variability"]}"']
        if "initial" in v and v["causality"] != "input":
            attrs.append(f'initial="{v["initial"]}"')
        real = []
        if "derivative" in v:
            real.append(f'derivative="{v["derivative"]}"')
        if v.get("unit"):
            real.append(f'unit="{v["unit"]}"')
        if "start" in v:
            real.append(f'start="{_fmt(v["start"])}"')
        out.append(f'    <!-- index {vr + 1} -->')
        out.append(f'    <ScalarVariable {" ".join(attrs)}>')
        out.append(f'      <Real {" ".join(real)}/>')
        out.append('    </ScalarVariable>')
    out.append('  </ModelVariables>')

    def unknown(vr, dep_vrs):
        d = " ".join(str(idx(x)) for x in sorted(dep_vrs))
        return f'      <Unknown index="{idx(vr)}" dependencies="{d}"/>'

    out += ['  <ModelStructure>', '    <Outputs>']
    # outputs are the states themselves
    out += [unknown(lay.vr_q(i), [lay.vr_q(i)]) for i in range(n)]
    out += [unknown(lay.vr_dq(i), [lay.vr_dq(i)]) for i in range(n)]
    out += ['    </Outputs>', '    <Derivatives>']

    def ddq_deps(i, with_params):
        d = deps[i]
        vrs = ([lay.vr_q(j) for j in d["q"]] + [lay.vr_dq(j) for j in d["dq"]]
               + [lay.vr_tau(j) for j in d["tau"]] + [lay.vr_tau_d(j) for j in d["tau"]])
        if with_params:
            vrs += [lay.vr_p(k) for k in d["theta"]]
            vrs += [lay.vr_p(model.ntheta + k) for k in d["const"]]
        return vrs

    out += [unknown(lay.vr_der_q(i), [lay.vr_dq(i)]) for i in range(n)]
    out += [unknown(lay.vr_der_dq(i), ddq_deps(i, False)) for i in range(n)]
    out += ['    </Derivatives>', '    <InitialUnknowns>']
    out += [unknown(lay.vr_der_q(i), [lay.vr_dq(i)]) for i in range(n)]
    out += [unknown(lay.vr_der_dq(i), ddq_deps(i, True)) for i in range(n)]
    out += ['    </InitialUnknowns>', '  </ModelStructure>', '</fmiModelDescription>', '']
    return "\n".join(out)


def _deps_comment(model, lay, deps) -> str:
    lines = [" * Structural dependencies of q'' (ModelStructure):"]
    for i, d in enumerate(deps):
        parts = ([f"q[{j}]" for j in d["q"]] + [f"dq[{j}]" for j in d["dq"]]
                 + [f"tau[{j}], tau_d[{j}]" for j in d["tau"]]
                 + [lay.param_names[k] for k in d["theta"]]
                 + [lay.param_names[model.ntheta + k] for k in d["const"]])
        lines.append(f" *   q''[{i}]: " + ", ".join(parts))
    return "\n".join(lines)


def _documentation(model, lay, model_identifier) -> str:
    rows = "\n".join(
        f"<tr><td>{vr}</td><td>{html.escape(v['name'])}</td><td>{v['causality']}</td>"
        f"<td>{v['variability']}</td><td>{html.escape(v.get('unit') or '')}</td>"
        f"<td>{html.escape(v['description'])}</td></tr>"
        for vr, v in enumerate(lay.variables))
    return f"""<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>{html.escape(model_identifier)}</title></head><body>
<h1>ivdrem plant FMU: {html.escape(model.name)}</h1>
<p>Euler-Lagrange robot with n = {model.n} joints,
M(q) q'' + C(q, q') q' + F(q') + G(q) = tau + tau_d, generated C code (sympy) for FMI 2.0
model exchange and co-simulation in one binary. States x = [q, dq]; outputs q, dq.</p>
<p><b>Co-simulation:</b> fmi2DoStep(t, H) integrates with k = ceil(H / cs_substep) fixed
classical Runge-Kutta (RK4) sub-steps of size H / k &lt;= cs_substep (default {lay.substep:g} s);
the inputs tau, tau_d are held constant over the communication step. The global error is
O(cs_substep<sup>4</sup>).</p>
<p><b>Parameters</b> (theta and the model constants such as g) have variability "fixed": set them
before fmi2ExitInitializationMode. Values that make M(q) not positive definite, non-finite values
and calls in the wrong state return fmi2Error with a message (category logStatusError).</p>
<p>Rebuild from sources/: <code>fmpy compile FILE.fmu</code> (link with the math library).</p>
<table border="1"><tr><th>vr</th><th>name</th><th>causality</th><th>variability</th><th>unit</th>
<th>description</th></tr>
{rows}
</table></body></html>
"""


# ----------------------------------------------------------------------------- build
def _identifier(model) -> str:
    ident = "ivdrem_" + re.sub(r"[^0-9A-Za-z_]", "_", model.name)
    return ident


def generate_sources(model, *, q0=None, dq0=None, substep=DEFAULT_SUBSTEP,
                     model_identifier=None) -> dict:
    """The files of the FMU except the binary: {relative path: text}.

    ``model`` is an :class:`~ivdrem.models.EulerLagrangeModel` or a model name.
    """
    from ivdrem.models import get_model
    model = get_model(model)
    ident = model_identifier or _identifier(model)
    if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", ident):
        raise ValueError(f"model_identifier must be a C identifier, got {ident!r}")
    lay = _layout(model, q0, dq0, substep)
    deps = _dependencies(model)
    dcomment = _deps_comment(model, lay, deps)
    framework = (_HERE / "fmi2_plant.c").read_text()
    # the GUID identifies the generated code and interface: hash of everything but itself
    mark = "@GUID@"
    header, source = (_rigid_body_code if _is_rigid_body(model) else _model_code)(
        model, lay, mark, dcomment)
    xml = _model_description(model, lay, mark, ident, deps)
    digest = hashlib.sha256("\0".join([framework, header, source, xml]).encode()).hexdigest()
    guid = "{" + str(uuid.uuid5(uuid.NAMESPACE_URL, "ivdrem-fmu:" + digest)) + "}"
    header, xml = header.replace(mark, guid), xml.replace(mark, guid)
    files = {
        "modelDescription.xml": xml,
        "sources/fmi2_plant.c": framework,
        "sources/plant_model.h": header,
        "sources/plant_model.c": source,
        "documentation/index.html": _documentation(model, lay, ident),
    }
    hdir = fmi2_header_dir()
    for h in _FMI2_HEADERS:
        files[f"sources/{h}"] = (hdir / h).read_text()
    return files


def _platform():
    """FMI 2.0 binaries folder and shared library suffix of this machine."""
    mach = platform.machine().lower()
    bits64 = sys.maxsize > 2 ** 32
    if sys.platform.startswith("linux"):
        return ("linux64" if bits64 else "linux32"), ".so"
    if sys.platform == "darwin":
        return "darwin64", ".dylib"
    raise NotImplementedError(
        f"compiling the FMU binary on {sys.platform} ({mach}) is not supported by ivdrem; "
        "export with compile=False and run `fmpy compile FILE.fmu` (CMake)")


def compile_binary(src_dir, out_file, *, cc=None, extra_flags=()):
    """Compile the C sources in ``src_dir`` into the shared library ``out_file``.

    Flags: -O2, C99, position independent, only the fmi2 functions exported
    (-fvisibility=hidden), linked against libm, and (Linux) no undefined symbols left
    (-Wl,--no-undefined): the binary needs nothing but libc and libm.
    """
    src_dir = Path(src_dir)
    cc = cc or os.environ.get("CC") or "cc"
    if shutil.which(cc) is None:
        raise RuntimeError(f"C compiler {cc!r} not found (set CC or pass cc=...)")
    cmd = [cc, "-shared", "-fPIC", "-O2", "-std=c99", "-fvisibility=hidden",
           "-Wall", "-Wextra", "-I", str(src_dir)]
    if sys.platform.startswith("linux"):
        cmd += ["-Wl,--no-undefined"]
    cmd += [str(src_dir / f) for f in FMU_SOURCE_FILES]
    cmd += ["-o", str(out_file), "-lm", *extra_flags]
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        raise RuntimeError(f"compiling the FMU failed ({' '.join(cmd)}):\n{res.stderr}")
    return res.stderr  # warnings, if any


def is_ivdrem_fmu(path) -> bool:
    """Whether `path` is an FMU that ivdrem exported (its modelDescription.xml names
    ivdrem as the generation tool), so that a new export may replace it."""
    try:
        with zipfile.ZipFile(path) as zf:
            head = zf.read("modelDescription.xml")[:4096]
    except (OSError, KeyError, zipfile.BadZipFile):
        return False
    return b'generationTool="ivdrem ' in head


def export_fmu(model, path, *, q0=None, dq0=None, substep=DEFAULT_SUBSTEP, cc=None,
               compile=True, model_identifier=None, overwrite=False):
    """Write the plant of ``model`` as an FMI 2.0 FMU (model exchange + co-simulation).

    Parameters
    ----------
    model : EulerLagrangeModel or str
        Any model of :mod:`ivdrem.models` (or a name for :func:`ivdrem.models.get_model`,
        e.g. ``"two-link"``, ``"planar-3"``).
    path : path-like
        Output file, conventionally ``*.fmu``.
    q0, dq0 : array_like, optional
        Start values of q and dq (default zeros).  Can be changed before initialization.
    substep : float
        Start value of ``cs_substep``: bound of the co-simulation RK4 sub-step (s).
    cc : str, optional
        C compiler (default ``$CC`` or ``cc``).
    compile : bool
        If False, ship sources only (build later with ``fmpy compile``).
    model_identifier : str, optional
        Name of the binary (default ``ivdrem_<model name>``).
    overwrite : bool
        Replace an existing `path` that is not an FMU ivdrem exported (an earlier export is
        replaced without it; anything else is refused before any work).

    Returns the path of the FMU.  Build files live in a temporary directory.
    """
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"the FMU path {path} is a directory; give a file name, e.g. "
                         f"{path / 'Plant.fmu'}")
    check_replaceable(path, "FMU file", overwrite=overwrite,   # before generating
                      ours=is_ivdrem_fmu)                       # and compiling
    files = generate_sources(model, q0=q0, dq0=dq0, substep=substep,
                             model_identifier=model_identifier)
    ident = re.search(r'modelIdentifier="([^"]+)"', files["modelDescription.xml"]).group(1)
    with tempfile.TemporaryDirectory(prefix="ivdrem_fmu_") as tmp:
        root = Path(tmp)
        for rel, text in files.items():
            p = root / rel
            p.parent.mkdir(parents=True, exist_ok=True)
            p.write_text(text)
        if compile:
            plat, ext = _platform()
            bdir = root / "binaries" / plat
            bdir.mkdir(parents=True)
            msgs = compile_binary(root / "sources", bdir / (ident + ext), cc=cc)
            if msgs.strip():
                warnings.warn(f"C compiler messages while building {path.name}:\n{msgs}",
                              stacklevel=2)
        zip_tree_atomic(root, path)   # a reader never sees half an FMU
    return path
