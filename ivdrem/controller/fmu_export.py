"""Export the sampled controller as an FMI 2.0 co-simulation FMU (generated C).

The FMU is the C library of :mod:`ivdrem.controller.codegen` (regressors printed from the
sympy model, hand-written core ``ivdrem_controller.c``) behind the hand-written FMI 2.0
wrapper ``fmi2_controller.c`` (Reference-FMU style, as the plant FMU's ``fmi2_plant.c``).

Variables (value reference = position; n = DoF, nθ = parameters)::

    q[i], dq[i]        input, continuous: the measured joint positions and velocities
    tau[i]             output, discrete: the torque for the next sample (delay 1)
    theta_hat[j]       output, discrete: the estimate theta_hat at the current time
    tau_d_hat[i]       output, discrete: the disturbance estimate of the last step
    Delta              output, discrete: Delta of (17) of the last step (IV-DREM, DREM)
    <parameters>       the parameter vector of ivdrem_controller.h (delay excluded: 1):
                       gains "tunable" (may change between steps), h, T, block, law,
                       corrected, theta_hat0 and the reference "fixed"

``fmi2DoStep(t_k, h)`` must use the controller's sample period h; see fmi2_controller.c.
"""
from __future__ import annotations

import hashlib
import math
import html
import re
import sys
import tempfile
import uuid
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from .._atomic import zip_tree_atomic
from .._cc import compile_shared, compiler
from .._paths import check_replaceable
from ..fmu.export import _platform, fmi2_header_dir, is_ivdrem_fmu
from ..laws import base_unit, get_law, sampled_gains, sampled_laws
from .codegen import _version, generate_controller_sources
from .loop import default_period
from .parameters import PARAMETERS, param_layout, param_vector
from .sampled import SampledController

__all__ = ["export_controller_fmu", "generate_controller_fmu_sources"]

_HERE = Path(__file__).resolve().parent
_FMI2_HEADERS = ("fmi2Functions.h", "fmi2FunctionTypes.h", "fmi2TypesPlatform.h")
SOURCE_FILES = ("fmi2_controller.c", "fmi_controller_common.c", "ivdrem_controller.c",
                "controller_model.c")
#: the hand-written files both wrappers share (the instance, state machine, value access,
#: step, FMU state): shipped in sources/ and compiled with either wrapper
_COMMON_FILES = ("fmi_controller_common.c", "fmi_controller_common.h")
_FMI3_HEADERS = ("fmi3Functions.h", "fmi3FunctionTypes.h", "fmi3PlatformTypes.h")
#: the sources per FMI version: the wrapper differs, the library and controller_fmu.h
#: (value references, one table for both) are the same
_SOURCES = {2: SOURCE_FILES, 3: ("fmi3_controller.c",) + SOURCE_FILES[1:]}



def _fmt(x):
    return repr(float(x)) if np.isfinite(x) else ("INF" if x > 0 else "-INF")


def _variables(model, par):
    n, nth = model.n, model.ntheta
    V = []
    for i in range(n):
        V.append(dict(name=f"q[{i}]", causality="input", variability="continuous", start=0.0,
                      unit="rad", description=f"measured joint position {i}"))
    for i in range(n):
        V.append(dict(name=f"dq[{i}]", causality="input", variability="continuous", start=0.0,
                      unit="rad/s", description=f"measured joint velocity {i}"))
    for i in range(n):
        V.append(dict(name=f"tau[{i}]", causality="output", variability="discrete",
                      initial="calculated", unit="N.m",
                      description=f"control torque {i} for the next sample (delay 1), eq. (9)"))
    for j in range(nth):
        V.append(dict(name=f"theta_hat[{j}]", causality="output", variability="discrete",
                      initial="calculated", description=f"parameter estimate {j}, eq. (11)"))
    for i in range(n):
        V.append(dict(name=f"tau_d_hat[{i}]", causality="output", variability="discrete",
                      initial="calculated", unit="N.m",
                      description=f"external torque estimate {i} of the last step"))
    V.append(dict(name="Delta", causality="output", variability="discrete",
                  initial="calculated", description="Delta of the mixing step (17), last step"))
    V += _parameters(model, par)
    for i in range(n):      # after the parameters: the value references above stay as they were
        V.append(dict(name=f"q_d[{i}]", causality="output", variability="discrete",
                      initial="calculated", unit="rad",
                      description=f"reference q_d,{i} of the last step (before the first: "
                                  "at t = 0)"))
    for i in range(n):
        V.append(dict(name=f"dq_d[{i}]", causality="output", variability="discrete",
                      initial="calculated", unit="rad/s",
                      description=f"reference dq_d,{i} of the last step (before the first: "
                                  "at t = 0)"))
    return V


def _parameters(model, par):
    """The FMU's parameters: one variable per entry of the parameter table
    (:data:`ivdrem.controller.parameters.PARAMETERS`), its start value from ``par``."""
    V = []
    off = 0
    for p, (name, size, descr) in zip(PARAMETERS, param_layout(model)):
        unit = p.declared()[0]
        for i in range(size):
            nm = name if size == 1 else f"{name}[{i}]"
            v = dict(name=nm, causality="parameter", initial="exact", start=par[off + i],
                     variability="tunable" if p.tunable else "fixed",
                     description=descr, hidden=p.hidden)
            if unit:
                v["unit"] = unit
            V.append(v)
        off += size
    return V


def _head_sections(V):
    """The UnitDefinitions, LogCategories and DefaultExperiment of both FMI versions'
    modelDescription (the same in FMI 2.0 and 3.0)."""
    units = sorted({v["unit"] for v in V if v.get("unit")})
    h = next(v["start"] for v in V if v["name"] == "h")
    out = ['  <UnitDefinitions>']
    out += [f'    <Unit name="{u}"><BaseUnit {base_unit(u)}/></Unit>' for u in units]
    out += ['  </UnitDefinitions>', '  <LogCategories>',
            '    <Category name="logEvents" description="Initialization (debug logging)"/>',
            '    <Category name="logStatusError" description="Errors: illegal calls, bad values (always logged)"/>',
            '  </LogCategories>',
            f'  <DefaultExperiment startTime="0" stopTime="10" stepSize="{_fmt(h)}"/>']
    return out


def _variable_attributes(vr, v):
    """(the attributes every FMI version gives variable vr, its unit and start)."""
    attrs = [f'name={quoteattr(v["name"])}', f'valueReference="{vr}"',
             f'description={quoteattr(v["description"])}', f'causality="{v["causality"]}"',
             f'variability="{v["variability"]}"']
    if "initial" in v:
        attrs.append(f'initial="{v["initial"]}"')
    real = [f'unit="{v["unit"]}"'] if v.get("unit") else []
    if "start" in v:
        real.append(f'start="{_fmt(v["start"])}"')
    return attrs, real


def _model_description(model, V, guid, ident, law):
    src = "\n".join(f'      <File name="{f}"/>' for f in SOURCE_FILES)
    out = ['<?xml version="1.0" encoding="UTF-8"?>', '<fmiModelDescription', '  fmiVersion="2.0"',
           f'  modelName={quoteattr(f"ivdrem controller {law} {model.name}")}',
           f'  guid="{guid}"',
           f'  description={quoteattr(f"Sampled IV-DREM family controller (law {law}) for the robot {model.name} (n = {model.n}): observer (7), control law (9), adaptation (11); fixed step h, delay 1. Generated C.")}',
           f'  generationTool="ivdrem {_version()}"', '  variableNamingConvention="structured"',
           '  numberOfEventIndicators="0">',
           f'  <CoSimulation modelIdentifier="{ident}" canHandleVariableCommunicationStepSize="false"'
           ' canInterpolateInputs="false" maxOutputDerivativeOrder="0" canRunAsynchronuously="false"'
           ' canGetAndSetFMUstate="true" canSerializeFMUstate="true"'
           ' canNotUseMemoryManagementFunctions="true" providesDirectionalDerivative="false">',
           '    <SourceFiles>', src, '    </SourceFiles>', '  </CoSimulation>']
    out += _head_sections(V) + ['  <ModelVariables>']
    exposed = [(vr, v) for vr, v in enumerate(V) if not v.get("hidden")]
    index = {}
    for vr, v in exposed:
        index[vr] = len(index) + 1
        attrs, real = _variable_attributes(vr, v)
        out += [f'    <ScalarVariable {" ".join(attrs)}>', f'      <Real {" ".join(real)}/>',
                '    </ScalarVariable>']
    out += ['  </ModelVariables>', '  <ModelStructure>', '    <Outputs>']
    outs = [vr for vr, v in exposed if v["causality"] == "output"]
    out += [f'      <Unknown index="{index[vr]}" dependencies=""/>' for vr in outs]
    out += ['    </Outputs>', '    <InitialUnknowns>']
    out += [f'      <Unknown index="{index[vr]}"/>' for vr in outs]
    out += ['    </InitialUnknowns>', '  </ModelStructure>', '</fmiModelDescription>', '']
    return "\n".join(out)


def _model_description3(model, V, guid, ident, law):
    """FMI 3.0 modelDescription.xml of the same variables (value references as in FMI 2)."""
    h = next(v["start"] for v in V if v["name"] == "h")
    out = ['<?xml version="1.0" encoding="UTF-8"?>', '<fmiModelDescription', '  fmiVersion="3.0"',
           f'  modelName={quoteattr(f"ivdrem controller {law} {model.name}")}',
           f'  instantiationToken="{guid}"',
           f'  description={quoteattr(f"Sampled IV-DREM family controller (law {law}) for the robot {model.name} (n = {model.n}): observer (7), control law (9), adaptation (11); fixed step h, delay 1. Generated C.")}',
           f'  generationTool="ivdrem {_version()}"', '  variableNamingConvention="structured">',
           f'  <CoSimulation modelIdentifier="{ident}" canHandleVariableCommunicationStepSize="false"'
           f' fixedInternalStepSize="{_fmt(h)}" canGetAndSetFMUState="true"'
           ' canSerializeFMUState="true" providesDirectionalDerivatives="false"'
           ' providesIntermediateUpdate="false" hasEventMode="false"/>']
    out += _head_sections(V) + [
            '  <ModelVariables>',
            f'    <Float64 name="time" valueReference="{len(V)}" causality="independent"'
            ' variability="continuous" unit="s" description="simulation time (VR_TIME)"/>']
    exposed = [(vr, v) for vr, v in enumerate(V) if not v.get("hidden")]
    for vr, v in exposed:
        attrs, value = _variable_attributes(vr, v)      # FMI 3: one element, no <Real>
        out.append(f'    <Float64 {" ".join(attrs + value)}/>')
    out += ['  </ModelVariables>', '  <ModelStructure>']
    outs = [vr for vr, v in exposed if v["causality"] == "output"]
    out += [f'    <Output valueReference="{vr}" dependencies=""/>' for vr in outs]
    out += [f'    <InitialUnknown valueReference="{vr}" dependencies=""/>' for vr in outs]
    out += ['  </ModelStructure>', '</fmiModelDescription>', '']
    return "\n".join(out)


def _build_description3(ident):
    """sources/buildDescription.xml: FMI 3.0 lists the sources to compile there (FMI 2.0 in
    the modelDescription's SourceFiles), so a host can build the FMU from sources/ alone."""
    src = "\n".join(f'      <SourceFile name="{f}"/>' for f in _SOURCES[3])
    return "\n".join(['<?xml version="1.0" encoding="UTF-8"?>',
                      '<fmiBuildDescription fmiVersion="3.0">',
                      f'  <BuildConfiguration modelIdentifier="{ident}">',
                      '    <SourceFileSet language="C99">', src, '    </SourceFileSet>',
                      '    <Library name="m" external="true" description="libm"/>',
                      '  </BuildConfiguration>', '</fmiBuildDescription>', ''])


def _fmu_header(model, V, guid):
    n, nth = model.n, model.ntheta
    npar = sum(s for _, s, _ in param_layout(model))
    pars = V[4 * n + nth + 1:4 * n + nth + 1 + npar]
    assert len(pars) == npar and V[4 * n + nth + 1 + npar]["name"] == "q_d[0]"
    names = ", ".join('"' + v["name"] + '"' for v in pars)
    tun = ", ".join("1" if v["variability"] == "tunable" else "0" for v in pars)
    exp = ", ".join("0" if v.get("hidden") else "1" for v in pars)
    return f"""/* controller_fmu.h: generated by ivdrem {_version()} for the controller FMU of
 * "{model.name}". Value references, as in modelDescription.xml. Do not edit. */
#ifndef CONTROLLER_FMU_H
#define CONTROLLER_FMU_H
#define MODEL_GUID "{guid}"
#define VR_Q 0
#define VR_DQ {n}
#define VR_TAU {2 * n}
#define VR_THETA_HAT {3 * n}
#define VR_TAU_D_HAT {3 * n + nth}
#define VR_DELTA {4 * n + nth}
#define VR_PAR {4 * n + nth + 1}
#define VR_Q_D {4 * n + nth + 1 + npar}
#define VR_DQ_D {4 * n + nth + 1 + npar + n}
#define VR_TIME {len(V)}
static const char *const PARAMETER_NAMES[IVC_NPAR] = {{{names}}};
static const int PARAMETER_TUNABLE[IVC_NPAR] = {{{tun}}};
static const int PARAMETER_EXPOSED[IVC_NPAR] = {{{exp}}};
#endif
"""


def _identifier(model, law):
    return "ivdrem_controller_" + re.sub(r"[^0-9A-Za-z_]", "_", f"{law}_{model.name}")


#: the arm a controller FMU was made for, where a name does not find it (a URDF file's arm):
#: the model's own description (ivdrem.models.urdf.RigidBodyModel's chain), read back by
#: ivdrem.controller.fmu_loop (``ivdrem cosim --controller-fmu``)
MODEL_RESOURCE = "resources/ivdrem_model.json"


def model_description_json(model):
    """The JSON text of MODEL_RESOURCE for a URDF arm (its name and chain, everything its
    code is generated from), None for the symbolic models (found by name)."""
    import json
    from ..models.urdf import RigidBodyModel
    if not isinstance(model, RigidBodyModel):
        return None
    return json.dumps({"name": model.name, "chain": model._chain})


def generate_controller_fmu_sources(model, law="iv-drem", *, fmi_version=2, **gains) -> dict:
    """{relative path: text} of the controller FMU but its binary.  ``gains`` are the
    arguments of :class:`~ivdrem.controller.sampled.SampledController` (start values);
    ``fmi_version`` 2 or 3 selects the wrapper and the modelDescription.xml."""
    from ..models import get_model
    if fmi_version not in (2, 3):
        raise ValueError(f"fmi_version must be 2 or 3, got {fmi_version!r}")
    model = get_model(model)
    gains = dict(gains)
    if gains.pop("delay", 1) != 1:
        raise ValueError("the controller FMU has delay 1 (no direct feedthrough); "
                         "see docs/controller.md")
    ref = SampledController(model, law, delay=1, **gains)     # validates everything
    par = param_vector(ref)
    lib = generate_controller_sources(model, par)
    V = _variables(model, par)
    ident = _identifier(model, law)
    mark = "@GUID@"
    xml = (_model_description if fmi_version == 2 else _model_description3)(model, V, mark,
                                                                             ident, law)
    head = _fmu_header(model, V, mark)
    wname = _SOURCES[fmi_version][0]
    wrapper = (_HERE / wname).read_text()
    common = {f: (_HERE / f).read_text() for f in _COMMON_FILES}
    digest = hashlib.sha256("\0".join([wrapper, *common.values(), xml, head,
                                       *lib.values()]).encode()).hexdigest()
    guid = "{" + str(uuid.uuid5(uuid.NAMESPACE_URL, "ivdrem-controller-fmu:" + digest)) + "}"
    files = {"modelDescription.xml": xml.replace(mark, guid),
             "sources/controller_fmu.h": head.replace(mark, guid),
             f"sources/{wname}": wrapper,
             **{f"sources/{f}": text for f, text in common.items()},
             "documentation/index.html": _documentation(model, V, law)}
    files.update({f"sources/{k}": v for k, v in lib.items()})
    if fmi_version == 3:
        files["sources/buildDescription.xml"] = _build_description3(ident)
    description = model_description_json(model)
    if description is not None:
        files[MODEL_RESOURCE] = description
    for h in (_FMI2_HEADERS if fmi_version == 2 else _FMI3_HEADERS):
        files[f"sources/{h}"] = (fmi2_header_dir() / h).read_text()   # fmpy's c-code folder
    return files


def _documentation(model, V, law):
    rows = "\n".join(f"<tr><td>{vr}</td><td>{html.escape(v['name'])}</td><td>{v['causality']}"
                     f"</td><td>{v['variability']}</td><td>{html.escape(v['description'])}</td></tr>"
                     for vr, v in enumerate(V) if not v.get("hidden"))
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>ivdrem controller</title>"
            f"</head><body><h1>Sampled controller, law {html.escape(law)}, robot "
            f"{html.escape(model.name)}</h1><p>Co-simulation FMU generated by ivdrem: "
            "fmi2DoStep(t_k, h) reads q(t_k), dq(t_k) and outputs the torque for the next "
            "sample (delay 1). The communication step must equal the parameter h.</p>"
            "<table><tr><th>vr</th><th>name</th><th>causality</th><th>variability</th>"
            f"<th>description</th></tr>{rows}</table></body></html>\n")


def export_controller_fmu(model, path, *, law="iv-drem", cc=None, overwrite=False, fmi_version=2,
                          **gains):
    """Write the sampled controller of ``law`` for ``model`` as an FMI 2.0 CS FMU.

    Same rules as the plant FMU (:func:`ivdrem.fmu.export_fmu`): an existing file that
    ivdrem did not write is refused before any work unless ``overwrite``; the FMU is
    written to a temporary next to ``path`` and moved into place.  Returns the path.
    """
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"the FMU path {path} is a directory; give a file name, e.g. "
                         f"{path / 'Controller.fmu'}")
    if law not in sampled_laws():
        raise ValueError(f"law {law!r} has no sampled controller; choose one of "
                         f"{', '.join(sampled_laws())}")
    if fmi_version not in (2, 3):
        raise ValueError(f"fmi_version must be 2 or 3, got {fmi_version!r}")
    check_replaceable(path, "FMU file", overwrite=overwrite, ours=is_ivdrem_fmu)
    files = generate_controller_fmu_sources(model, law, fmi_version=fmi_version, **gains)
    ident = re.search(r'modelIdentifier="([^"]+)"', files["modelDescription.xml"]).group(1)
    cc = compiler(cc)                  # refused here, before any work, if not found
    with tempfile.TemporaryDirectory(prefix="ivdrem_cfmu_") as tmp:
        root = Path(tmp)
        for rel, text in files.items():
            p = root / rel
            p.parent.mkdir(parents=True, exist_ok=True)
            p.write_text(text)
        plat, ext = _platform()
        if fmi_version == 3:        # FMI 3.0 platform tuple <arch>-<os>
            plat = {"linux64": "x86_64-linux", "linux32": "x86-linux",
                    "darwin64": "x86_64-darwin"}[plat]
        bdir = root / "binaries" / plat
        bdir.mkdir(parents=True)
        src = root / "sources"
        compile_shared([src / f for f in _SOURCES[fmi_version]], bdir / (ident + ext),
                       what=f"the controller FMU {path.name}", cc=cc, include_dirs=[src],
                       hidden=True)
        zip_tree_atomic(root, path)
    return path


#: closed_loop's arguments that belong to the plant or the host, not to the controller: the
#: arm's start, its true parameters and the disturbance (a host sets them, fmu_loop.py)
HOST_KEYS = ("q0", "dq0", "theta", "disturbance")


#: the multi-rate default of the scale-free mixings (the URDF arms' "eigen"): the mixing of
#: (Y, Psi)(t_k) every 20 samples, held from t_k+20 (measured on the Panda over 300 s: a
#: step of 90 µs median at load 22-27, the worst step of a mixing period 360 µs alone;
#: 575 µs median with the mixing at every sample; docs/controller.md)
MIX_EVERY = 20


def controller_design(experiment, law, *, h=None, mu_max=None):
    """The arguments of :class:`~ivdrem.controller.sampled.SampledController` for
    ``experiment`` (an :class:`~ivdrem.experiments.experiment.Experiment`, or a
    configuration: its Experiment is made) and ``law``: the gains, the reference, the
    window T, the mixing, γ as configured ("auto" left for :func:`resolve_gamma`), ``h``
    and ``mu_max`` when given; the scale-free mixings (the URDF arms' default) every
    :data:`MIX_EVERY` samples.  The law's arguments are the experiment's, resolved once
    (``LawSetup.configured``); the model is the experiment's.  An option of the
    experiment the sampled controller does not have is refused in one line (ValueError)."""
    import inspect
    from ..experiments.experiment import Experiment
    experiment = Experiment.of(experiment)
    config, model = experiment.config, experiment.model
    kw = dict(experiment.law(law).configured)
    kw.update(kw.pop("gains"))     # the sampled controller takes the law's gains by name
    # its own options and every gain a law with a sampled form declares (the registry's,
    # which SampledController takes as keywords)
    accepted = ((set(inspect.signature(SampledController.__init__).parameters)
                 - {"self", "model", "law", "gains"}) | set(sampled_gains()))
    out = {}
    for k, v in kw.items():
        if k in HOST_KEYS:
            continue
        if k == "mixing" and k not in accepted and v in (None, "paper"):
            continue        # the paper's mixing (17) is the sampled controller's own
        if k not in accepted:
            raise ValueError(f"the sampled controller has no option {k} = {v!r} (from the "
                             f"configuration, law {law}); docs/controller.md lists its options")
        out[k] = v
    table = config["trajectory"]
    if table.get("kind", "sinusoid") == "fourier":     # as the table, not closed_loop's block
        out["trajectory"] = {"kind": "fourier", "omega_f": float(table["omega_f"]),
                             **{k: np.asarray(table[k], dtype=float)
                                for k in ("a", "b", "offset")}}
    if h is not None:
        out["h"] = float(h)
    if mu_max is not None:
        out["mu_max"] = float(mu_max)
    from .sampled import GRADIENT_GAIN, default_design, default_mixing, inertia_scaled_gains
    if (out.get("mixing", default_mixing(model)) != "paper"
            and get_law(law).windowed):
        # the scale-free mixing of a real arm's tens of parameters is a Jacobi SVD, composite
        # learning's max-hold a lambda_min of Psi_b: each spread over MIX_EVERY samples
        # (docs/controller.md, "Real arms: reference, mixing, multi-rate"), the step stays
        # within the robot's deadline
        out.setdefault("mix_every", MIX_EVERY)
    if out.get("design", default_design(model)) == "inertia-scaled" and "K" in out:
        # the configuration's K is the continuous loop's joint gain (N m s); the sampled
        # inertia-scaled feedback M̂(q)(K + δ_μ μ) r takes K in 1/s (docs/controller.md,
        # "Sampled designs"): K_i / M_ii(q0), capped for the step h (from the configured
        # K: closed_loop_kwargs has already divided it for a configured design)
        K = np.asarray(config["controller"]["K"], dtype=float)
        sig = inspect.signature(SampledController.__init__).parameters
        out["K"] = np.diag(inertia_scaled_gains(
            model, K, np.asarray(config["initial"]["q0"], dtype=float),
            out.get("h", default_period()),
            delta_mu=out.get("delta_mu", sig["delta_mu"].default),
            mu_max=out.get("mu_max", sig["mu_max"].default),
            theta=np.asarray(config["model"]["theta"], dtype=float)))
        if "Gamma" in out:
            # the sampled design's Γ of (11): the gradient term alone moves θ̂ until the
            # window is full, and where it moves M(q, θ̂) the observer's injection of (8)
            # outgrows the per-step budget with the host's one-sample delay ("Sampled
            # designs"); γ = "auto" follows it (resolve_gamma: the composite rate Γ γ Δ² kept)
            out["Gamma"] = GRADIENT_GAIN * np.eye(model.ntheta)
    return out


def check_window(design, law):
    """h must divide the window T of (15a) into whole blocks: one line naming both if not."""
    if not get_law(law).windowed:       # the law's name is checked by the caller
        return
    h = float(design.get("h", default_period()))
    T = design.get("T")
    T = 20.0 if T is None else float(T)
    block = int(design.get("block", 10))
    if not (np.isfinite(h) and h > 0):
        raise ValueError(f"--h must be a number > 0, got {h!r}")
    N = round(T / h)
    if abs(N * h - T) > 1e-9 * T or N % block or N == 0:
        def fits(x):
            m = round(T / x)
            return abs(m * x - T) <= 1e-9 * T and m % block == 0 and m > 0
        nice = [x for x in (2e-3, 1e-3, 5e-4, 2.5e-4, 2e-4, 1e-4, 5e-5) if x <= h and fits(x)]
        good = nice[0] if nice else T / (block * max(1, round(T / (block * h))))
        raise ValueError(f"--h {h:g} does not divide the window T = {T:g} s of (15a) into "
                         f"whole blocks of {block} samples (T / h = {T / h:.6g}); give an h "
                         f"with T / h a multiple of {block}, e.g. --h {good:g}")


def check_mix_every(value, design, law):
    """``--mix-every M``: a whole number from 1 to the window's samples T / h, for a law
    with a window (its mixing (17) or max-hold every M samples); returns M, or refuses in one
    line naming the value and the bound."""
    if not get_law(law).windowed:
        windowed = ", ".join(n for n in sampled_laws() if get_law(n).windowed)
        raise ValueError(f"--mix-every {value} applies to the laws with a window ({windowed}), "
                         f"not to {law}")
    try:
        m = float(value)
    except (TypeError, ValueError):
        m = math.nan
    h = float(design.get("h", default_period()))
    T = design.get("T")
    T = 20.0 if T is None else float(T)
    N = int(round(T / h))
    if not (math.isfinite(m) and m == int(m) and 1 <= m <= N):
        raise ValueError(f"--mix-every {value} must be a whole number from 1 to the window's "
                         f"{N} samples (T = {T:g} s, h = {h:g} s)")
    return int(m)


def check_generated(model):
    """The controller's C code for ``model`` can be generated: one line naming the model and
    the reason if not (before any long work)."""
    try:
        generate_controller_sources(model)
    except Exception as exc:    # the generator's own failure, whatever it raised
        raise ValueError(f"the controller's C code cannot be generated for model "
                         f"{model.name!r} ({type(model).__name__}): {type(exc).__name__}: "
                         f"{str(exc).splitlines()[0] if str(exc) else ''}".rstrip(": ")) \
            from None


def resolve_gamma(model, law, design, experiment):
    """γ = "auto" resolved to a number by the continuous loop's rule
    (:func:`ivdrem.diagrams.gamma_auto.calibrate_gamma` on the closed loop of
    ``experiment``, an Experiment or a configuration, with the design's Γ, the same γ
    `ivdrem paper` takes when Γ is the configuration's, cached with it): returns (design
    with γ a number, the calibration's record or None)."""
    if design.get("gamma") != "auto":
        return design, None
    from ..diagrams.gamma_auto import calibrate_gamma
    from ..experiments.experiment import Experiment
    configured = Experiment.of(experiment).law(law).configured
    args = {k: v for k, v in configured.items() if k != "gamma"}
    if "Gamma" in design:           # the sampled design's own Γ (controller_design)
        args["Gamma"] = np.asarray(design["Gamma"], dtype=float)
    choice = calibrate_gamma(law, model, args)
    return {**design, "gamma": float(choice["gamma"])}, choice


def predict(model, law, design, experiment=None, progress=None):
    """The sampled loop's stability (ivdrem.controller.stability) for ``experiment`` (an
    Experiment or a configuration: its θ, disturbance and horizon; None: the model's θ, the
    paper's disturbance on the 2-link arm, 300 s) over the horizon, and until μ saturates.
    ``progress``: a bar of the simulated prefix on stderr (None: on a terminal)."""
    from .loop import PAPER_DISTURBANCE, disturbance_at
    from .stability import sampled_stability
    if experiment is None:
        theta, t_end = model.theta_values, 300.0
        dist = PAPER_DISTURBANCE if model.n == 2 and model.name == "two-link" else None
    else:
        from ..experiments.experiment import Experiment
        experiment = Experiment.of(experiment)
        kw = experiment.law(law).configured
        theta, t_end, dist = kw["theta"], experiment.t_end, kw.get("disturbance")
    mu0 = float(design.get("mu0", 1.0))
    mu1, mu_max = float(design.get("mu1", 15.0)), float(design.get("mu_max", 135.0))
    if mu0 > 0 and np.isfinite(mu_max):
        t_end = max(t_end, (mu_max - mu1) / mu0)      # the largest gain is reached too
    return sampled_stability(model, law, theta=theta, t_end=t_end,
                             disturbance=None if dist is None else
                             (lambda t: disturbance_at(t, dist)), progress=progress,
                             **{**design, "delay": 1})     # the FMU's torque: one sample late


def _model_override(name):
    """The configuration's overrides for ``--model``: a URDF file or a model name."""
    from pathlib import Path as _P
    from .._paths import user_path
    if name is None:
        return {}
    if str(name).lower().endswith(".urdf") or _P(user_path(name)).is_file():
        return {"model.urdf": str(user_path(name))}
    return {"model.name": str(name)}


def main_export_controller(args) -> int:
    """``ivdrem fmu export --controller``: the parsed arguments of ivdrem.cli.fmu.

    Without ``--config`` and for the paper's arms (two-link, planar-N) the controller has
    SampledController's defaults (the paper's experiment); with ``--config``, or a URDF arm
    by ``--model``, the configuration's experiment (an
    :class:`~ivdrem.experiments.experiment.Experiment`: its model, built once, its law's
    gains and its h, the configuration's ``[solver] h``, unless ``--h``) becomes the FMU's
    defaults.  Before
    anything is built: the options, h against the window T, the C code's generation, γ
    "auto" resolved, and the sampled loop's stability (refused if predicted unstable unless
    ``--despite-prediction``).  Exit 0 written, 2 refused (one line on stderr)."""
    import sys
    from .._paths import user_path
    from ..models import get_model
    prog = "ivdrem fmu export"
    mu_max = 135.0 if args.mu_max is None else args.mu_max
    h = args.h          # None: the experiment's (with a configuration) or default_period()
    extra = ""
    try:
        if args.no_compile or args.q0 is not None or args.dq0 is not None:
            raise ValueError("--no-compile, --q0 and --dq0 are options of the plant FMU, not "
                             "of --controller")
        if args.law not in sampled_laws():
            raise ValueError(f"law {args.law!r} has no sampled controller; choose one of "
                             f"{', '.join(sampled_laws())}")
        path = user_path(args.output)
        check_replaceable(path, "FMU file", overwrite=args.overwrite, ours=is_ivdrem_fmu)
        paper_arm = args.config is None and (args.model is None or re.fullmatch(
            r"two[-_]link|2-link|planar[-_]\d+", str(args.model).strip().lower()))
        mix_every = getattr(args, "mix_every", None)
        if paper_arm:
            model = get_model(args.model or "two-link")
            design = dict(mu_max=mu_max, h=default_period() if h is None else h)
            check_window(dict(design, **_law_window(args.law)), args.law)
            if mix_every is not None:
                design["mix_every"] = check_mix_every(
                    mix_every, dict(design, **_law_window(args.law)), args.law)
            check_generated(model)
            experiment = None
        else:
            from ..experiments.config import read_config
            from ..experiments.experiment import Experiment
            data = read_config(None if args.config is None else user_path(args.config),
                               _model_override(args.model))
            # the model built once, the reference designed once, the law resolved once
            experiment = Experiment.from_config(data, laws=[args.law])
            model = experiment.model
            design = controller_design(experiment, args.law,
                                       h=experiment.h if h is None else h, mu_max=mu_max)
            check_window(design, args.law)
            if mix_every is not None:
                design["mix_every"] = check_mix_every(mix_every, design, args.law)
            check_generated(model)
            design, choice = resolve_gamma(model, args.law, design, experiment)
            if choice is not None:
                extra += f", gamma = {design['gamma']:.4g} (auto)"
        SampledController(model, args.law, **design)           # every other check
        if not args.despite_prediction:
            st = predict(model, args.law, design, experiment)
            if not st.stable:
                raise ValueError(st.reason() + "; or --despite-prediction")
            extra += f", predicted growth {st.growth:.4g} per step"
        path = export_controller_fmu(model, path, law=args.law, cc=args.cc,
                                     overwrite=args.overwrite,
                                     fmi_version=getattr(args, "fmi_version", 2), **design)
    except (ValueError, RuntimeError, NotImplementedError, OSError) as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {path} (controller, law {args.law}, model {model.name}, n = {model.n}, "
          f"ntheta = {model.ntheta}, h = {design['h'] * 1e3:g} ms, "
          f"mu_max = {design.get('mu_max', mu_max):g}, mix_every = "
          f"{design.get('mix_every', 1)}{extra})")
    return 0


def _law_window(law):
    """The law's default window T (its registry entry), for the h check of the paper path."""
    T = get_law(law).defaults.get("T")
    return {} if T is None else {"T": T}
