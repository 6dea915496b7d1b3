"""Export the robot plant of any robot model of ivdrem as an FMI 2.0 FMU.

The FMU is generated C, not a Python wrapper: ``plant_model.c`` is the model's C face
(``model.c_source("plant_")``, docs/models.md): for a symbolic model sympy's C99 printing
of M, C, G, F after common-subexpression elimination, for an arm from a URDF the recursive
Newton-Euler kernels of :mod:`ivdrem.models.rigid_body` printed to C; in both the same
numbers as the Python plant (``model.functions.forward_dynamics``).  Its
``forward_dynamics_k`` gives ``q'' = M^-1 (tau + tau_d - b)`` by the package's one Cholesky,
with the model's constants (``g``, link lengths) from the FMU's parameters.  A fixed,
hand-written C file (``fmi2_plant.c``, style of the FMI Reference FMUs) implements the FMI
2.0 API on top of it: a state machine, error checks, FMU state get/set/serialize.  One
binary provides model exchange and co-simulation.

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
import platform
import re
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
from . import DEFAULT_SUBSTEP             # one definition, in the package (no SymPy there)

__all__ = ["export_fmu", "generate_sources", "fmi2_header_dir", "FMU_SOURCE_FILES",
           "DEFAULT_SUBSTEP"]


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
    if not isinstance(getattr(model, "M", None), sp.MatrixBase):
        # no symbolic structure (a URDF arm): every joint of a serial arm couples with
        # every other (M^-1 is full): dense
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
def _c_double(x: float) -> str:
    s = repr(float(x))
    return s if ("e" in s or "." in s or "inf" in s or "nan" in s) else s + ".0"


def _c_string(s: str) -> str:
    return '"' + s.replace("\\", "\\\\").replace('"', '\\"') + '"'


def _plant_code(model, lay: _Layout, guid: str, deps_comment: str) -> tuple[str, str]:
    """plant_model.h and plant_model.c: the model's C face (``model.c_source("plant_")``,
    docs/models.md), whatever its kind, and the FMU's constant data."""
    header = _header(model, lay, guid)
    pnames = ", ".join(_c_string(nm) for nm in lay.param_names)
    pvals = ", ".join(_c_double(v) for v in lay.param_values)
    pmap = "\n".join(f" *   p[{k}] = {nm}" for k, nm in enumerate(lay.param_names))
    source = f"""/* plant_model.c: generated by ivdrem {_version()} from the model "{model.name}"
 * (model key {model.key}): its C face and the FMU's start values.  Do not edit.
 *
 *   M(q) q'' + C(q, q') q' + F(q') + G(q) = tau + tau_d
 *
 * q[i], dq[i]: joint positions and velocities; parameter vector p (theta, then the model
 * constants k):
{pmap}
 *
{deps_comment}
 */
#include "plant_model.h"
#define PLANT_FN PLANT_INTERNAL
{model.c_source("plant_")}
const double Q_START[NQ] = {{{", ".join(_c_double(v) for v in lay.q0)}}};
const double DQ_START[NQ] = {{{", ".join(_c_double(v) for v in lay.dq0)}}};
const double P_START[NP] = {{{pvals}}};
const char *const PARAMETER_NAMES[NP] = {{{pnames}}};

int plant_accelerations(const double *q, const double *dq, const double *tau,
                        const double *p, double *ddq) {{
    return plant_forward_dynamics_k(q, dq, tau, p, p + NTHETA, ddq);
}}
"""
    return header, source


def _header(model, lay: _Layout, guid: str) -> str:
    """plant_model.h: the layout used by fmi2_plant.c."""
    n = model.n
    return f"""/* plant_model.h: generated by ivdrem {_version()} from the model "{model.name}"
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

/* q'' solving M(q) q'' = tau - C(q, q') q' - F(q') - G(q) with the parameters p (theta,
 * then the model constants): the model's forward_dynamics_k.  0, or 1 when M(q) is not
 * positive definite (the package's one rule, docs/models.md). */
PLANT_INTERNAL int plant_accelerations(const double *q, const double *dq, const double *tau,
                                       const double *p, double *ddq);

#endif
"""


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
M(q) q'' + C(q, q') q' + F(q') + G(q) = tau + tau_d, generated C code (the model's C face) for FMI 2.0
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
    header, source = _plant_code(model, lay, mark, dcomment)
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
    """Compile the C sources in ``src_dir`` into the shared library ``out_file`` by
    :mod:`ivdrem._cc` (its one rule: ``cc``, ``$CC`` or ``cc``; -O2, C99, position
    independent, -Wall -Wextra, linked against libm, no undefined symbols on Linux), with
    only the fmi2 functions exported (-fvisibility=hidden): the binary needs nothing but
    libc and libm.  Returns the compiler's warnings (empty if none)."""
    from .._cc import compile_shared
    src_dir = Path(src_dir)
    return compile_shared([src_dir / f for f in FMU_SOURCE_FILES], out_file,
                          what=f"the FMU binary from {src_dir}", cc=cc,
                          include_dirs=[src_dir], hidden=True, extra_flags=extra_flags)


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
