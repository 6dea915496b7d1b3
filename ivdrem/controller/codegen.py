"""The sampled controller as a self-contained C library, generated for any model.

``generate_controller_sources(model)`` returns the files of the library:

* ``ivdrem_controller.h``: the one header: sizes, the parameter vector's layout (index
  macros ``IVC_P_<NAME>`` and defaults ``IVC_PAR_DEFAULTS``: the paper's experiment), law
  codes and the documented API (``ivc_init / ivc_step / ivc_get_state / ivc_set_state /
  ivc_free`` ...);
* ``controller_model.c``: the regressors Phi_M, Phi_C, Phi_dM, Phi_G, Phi_F, Phi of
  Property 1, printed from the sympy model by ``sympy.cse`` + ``sympy.ccode`` (C99), as
  ivdrem.fmu.export prints the plant;
* ``ivdrem_controller.c``: the hand-written core (this folder), the algorithm of
  :mod:`ivdrem.controller.sampled`.

``build_library(model, directory)`` compiles them into a shared library (plain C99, libm
only) for :class:`ivdrem.controller.clib.CController` (ctypes).
"""
from __future__ import annotations

import hashlib
import os
import sys
from pathlib import Path

import numpy as np
import sympy as sp

from .._cc import compile_shared
from ..blocks.control_law import INJECTIONS
from ..blocks.mixing import START_RAMP_REL
from ..models._c_printer import c_double as _c_double
from .sampled import REFERENCE_HARMONICS

__all__ = ["param_layout", "generate_controller_sources", "build_library", "LAW_CODES",
           "CORE_SOURCE", "DESIGN_CODES", "GRAVITY_CODES", "MIXING_CODES", "STRUCTURAL"]

_HERE = Path(__file__).resolve().parent
#: The hand-written C core of the controller library, shared by every model and law.
CORE_SOURCE = _HERE / "ivdrem_controller.c"

#: law name -> code of the parameter ``law``
LAW_CODES = {"iv-drem": 0, "composite-learning": 1, "drem": 2, "sigma-modification": 3,
             "none": 4}

#: parameters that fix the memory or the meaning of the state (set before ivc_init)
STRUCTURAL = ("h", "T", "block", "law", "delay", "corrected", "design", "mixing", "mix_every",
              "gravity", "ref_kind")

#: design name -> code of the parameter ``design`` (docs/controller.md, "Sampled designs")
DESIGN_CODES = {"paper": 0, "inertia-scaled": 1}
#: gravity option -> code of the parameter ``gravity`` ("robot": the robot adds ĝ(q) itself)
GRAVITY_CODES = {"controller": 0, "robot": 1}
#: mixing variant -> code of the parameter ``mixing`` (ivdrem.blocks._kernels.MIXING_VARIANTS)
MIXING_CODES = {"paper": 0, "eigen": 1, "channel": 2}


def param_layout(model):
    """[(name, size, description)] of the flat parameter vector, in order."""
    n, nth = model.n, model.ntheta
    return [
        ("h", 1, "sample period (s)"),
        ("alpha", 1, "tracking error filter alpha: r = de + alpha e"),
        ("K", n * n, "feedback gain K (n x n, row major), control law (9)"),
        ("delta_mu", 1, "delta_mu in (0, 1), control law (9)"),
        ("Gamma_diag", nth, "adaptation gain Gamma (diagonal), (11)"),
        ("mu0", 1, "mu(t) = min(mu0 t + mu1, mu_max)"),
        ("mu1", 1, "mu(0) > 0"),
        ("mu_max", 1, "saturation of mu (docs/controller.md)"),
        ("l", 1, "filter gain l of (13), (14)"),
        ("T", 1, "window length T of (15a) (s)"),
        ("p", 1, "averaging F(t) = t^p + F0 (15b)"),
        ("F0", 1, "averaging F0 > 0 (erratum E3)"),
        ("gamma", 1, "gain gamma of the composite term (21) or (35)"),
        ("sigma", 1, "sigma-modification gain (erratum E5)"),
        ("epsilon", 1, "composite learning: threshold of lambda_min"),
        ("theta_star", nth, "sigma-modification prior theta*"),
        ("theta_hat0", nth, "initial estimate theta_hat(0)"),
        ("tau_max", n, "torque limit |tau_i| <= tau_max_i of the command (N m; inf: none)"),
        ("delay", 1, "0: tau_k applied over [t_k, t_k+1]; 1: over [t_k+1, t_k+2]"),
        ("block", 1, "samples per block sum of the window"),
        ("law", 1, "0 iv-drem, 1 composite-learning, 2 drem, 3 sigma-modification, 4 none"),
        ("corrected", 1, "1: observer gain mu + dmu/mu for Phi_Mf (erratum E1); 0: mu"),
        ("tr_amplitude", n, "reference q_d = A sin(w t + phi) + c: A"),
        ("tr_omega", n, "reference: w (rad/s)"),
        ("tr_phase", n, "reference: phi"),
        ("tr_offset", n, "reference: c (also the Fourier reference's offset)"),
        ("design", 1, "0 paper: feedback (K + delta_mu mu) r of (9); 1 inertia-scaled: "
                      "M(q, theta_nominal)(K + delta_mu mu) r, K in 1/s"),
        ("mixing", 1, "mixing (17): 0 paper, 1 eigen, 2 channel (docs/mixing.md)"),
        ("mix_every", 1, "the mixing (17), or composite learning's max-hold of (35), every m "
                          "samples (multi-rate, m > 1: held or decided one period later, its "
                          "work spread over the period)"),
        ("f_rel", 1, "eigen mixing: f0 = f_rel ||Psi||_F"),
        ("guard", 1, "channel mixing: guard of the (i, i) cofactor"),
        ("gravity", 1, "0: the law's tau is commanded; 1 robot: tau - G(q, theta_nominal) "
                       "(the robot adds its own gravity)"),
        ("theta_nominal", nth, "nominal parameters (the URDF's): inertia-scaled design, "
                               "gravity robot"),
        ("tau_rate_max", n, "rate limit |tau_k,i - tau_k-1,i| <= h tau_rate_max_i (N m/s; "
                            "inf: none)"),
        ("first_zero", 1, "1: the first command tau_0 is 0"),
        ("ref_kind", 1, "reference: 0 the sinusoid tr_*, 1 the Fourier series fr_*"),
        ("fr_omega_f", 1, "Fourier reference: base frequency omega_f (rad/s)"),
        ("fr_a", n * REFERENCE_HARMONICS,
         "Fourier reference: a (n x H, row major): q_d,i = c_i + sum_l (a_il sin(l w t) - "
         "b_il cos(l w t))/(l w)"),
        ("fr_b", n * REFERENCE_HARMONICS, "Fourier reference: b (n x H, row major)"),
        ("injection", 1, "the observer's injection mu (Phi_M^T(q, r) - Phi_Mf^T) theta of (8) "
                         "at 0 theta_hat (the paper's), 1 theta_nominal (adaptation (11) "
                         "with Phi^T - Phi_f^T)"),
    ]


def param_vector(ctrl):
    """The flat parameter vector of a :class:`~ivdrem.controller.sampled.SampledController`."""
    vals = {"h": ctrl.h, "alpha": ctrl.alpha, "K": ctrl.K.reshape(-1),
            "delta_mu": ctrl.delta_mu, "Gamma_diag": ctrl.Gamma, "mu0": ctrl.mu0,
            "mu1": ctrl.mu1, "mu_max": ctrl.mu_max, "l": ctrl.l, "T": ctrl.T, "p": ctrl.p,
            "F0": ctrl.F0, "gamma": ctrl.gamma, "sigma": ctrl.sigma,
            "epsilon": ctrl.epsilon, "theta_star": ctrl.theta_star,
            "theta_hat0": ctrl.theta_hat0, "tau_max": ctrl.tau_max, "delay": ctrl.delay,
            "block": ctrl.block, "law": LAW_CODES[ctrl.law],
            "corrected": 1.0 if ctrl.corrected else 0.0, "tr_amplitude": ctrl.tr_A,
            "tr_omega": ctrl.tr_w, "tr_phase": ctrl.tr_phi, "tr_offset": ctrl.tr_c,
            "design": DESIGN_CODES[ctrl.design], "mixing": MIXING_CODES[ctrl.mixing],
            "mix_every": ctrl.mix_every, "f_rel": ctrl.f_rel, "guard": ctrl.guard,
            "gravity": GRAVITY_CODES[ctrl.gravity], "theta_nominal": ctrl.theta_nominal,
            "tau_rate_max": ctrl.tau_rate_max, "first_zero": 1.0 if ctrl.first_zero else 0.0,
            "ref_kind": 1.0 if ctrl.fourier else 0.0, "fr_omega_f": ctrl.fr_wf,
            "fr_a": ctrl.fr_a.reshape(-1), "fr_b": ctrl.fr_b.reshape(-1),
            "injection": INJECTIONS.index(ctrl.injection)}
    out = []
    for name, size, _ in param_layout(ctrl.model):
        v = np.atleast_1d(np.asarray(vals[name], dtype=float)).reshape(-1)
        assert v.size == size, name
        out.extend(v.tolist())
    return np.array(out)


def _regressor_code(model):
    """The model's C face (``model.c_source("ivc_")``, docs/models.md): ivc_<R>(args...,
    out) of the regressors, out row major n x ntheta, for any robot model; and the
    regressors' (name, None, arguments)."""
    from ..models.base import REGRESSOR_ARGS
    specs = [(name, None, args) for name, args in REGRESSOR_ARGS.items()]
    return [model.c_source("ivc_")], specs


def _version():
    try:
        from importlib.metadata import version
        return version("ivdrem")
    except Exception:  # pragma: no cover
        return "0"


def generate_controller_sources(model, defaults=None) -> dict:
    """{file name: text} of the C library for ``model``; ``defaults`` is a flat parameter
    vector (default: the paper's experiment for the 2-link arm, see ``param_vector``)."""
    from ..models import get_model
    from .sampled import SampledController
    model = get_model(model)
    n, nth = model.n, model.ntheta
    if defaults is None:
        defaults = param_vector(SampledController(model, law="iv-drem"))
    layout = param_layout(model)
    npar = sum(s for _, s, _ in layout)
    defaults = np.asarray(defaults, dtype=float).reshape(-1)
    if defaults.size != npar:
        raise ValueError(f"defaults must have {npar} entries, got {defaults.size}")
    funcs, specs = _regressor_code(model)
    idx, off = [], 0
    for name, size, descr in layout:
        idx.append(f"#define IVC_P_{name.upper():<14} {off:4d}  /* [{size}] {descr} */")
        off += size
    protos = "\n".join(
        f"IVC_INTERNAL void ivc_{name}(" + ", ".join(f"const double *{a}" for a in args)
        + ", double *out);" for name, _, args in specs)
    laws = "\n".join(f"#define IVC_LAW_{k}  {v}" for k, v in
                     (("IV_DREM", 0), ("COMPOSITE", 1), ("DREM", 2), ("SIGMA", 3), ("NONE", 4)))
    codes = "\n".join(
        [f"#define IVC_DESIGN_{k.upper().replace('-', '_')}  {v}" for k, v in DESIGN_CODES.items()]
        + [f"#define IVC_GRAVITY_{k.upper()}  {v}" for k, v in GRAVITY_CODES.items()]
        + [f"#define IVC_MIXING_{k.upper()}  {v}" for k, v in MIXING_CODES.items()])
    header = f"""/* ivdrem_controller.h: the sampled IV-DREM controller (Glushchenko & Lastochkin,
 * eqs. 7-21) for the robot model "{model.name}" (n = {n} joints, ntheta = {nth} parameters).
 * Generated by ivdrem {_version()} (model key {model.key}). Do not edit.
 *
 * Usage (plain C99, no dependency but libm, no allocation after ivc_init):
 *
 *     double par[IVC_NPAR];
 *     ivc_default_params(par);             the paper's experiment; edit par[IVC_P_...]
 *     char msg[256];
 *     ivc_controller *c = ivc_init(par, msg, sizeof msg);     NULL: msg says why
 *     for (k = 0; ; k++) {{                 t_k = k h, every h seconds:
 *         if (ivc_step(c, k * h, q, dq, tau) != IVC_OK) ... ivc_message(c)
 *         apply tau (delay 0) ...
 *     }}
 *     ivc_free(c);
 *
 * ivc_step(c, t_k, q, dq, tau): one sample.  q, dq: measured joint positions and velocities
 *   at t_k = k h (k counts the calls: any other t is refused); tau: the torque tau_k
 *   (with delay 1 it is meant for [t_k+1, t_k+2]).  Returns IVC_OK, or an error with the
 *   state unchanged: IVC_ERR_ARG (wrong t), IVC_ERR_NONFINITE (NaN/Inf in q, dq),
 *   IVC_ERR_DIVERGED (non-finite torque).
 * ivc_outputs(c, theta_hat, tau_d_hat, Delta, tau): the estimate theta_hat(t_k+1), the
 *   disturbance estimate tau_d_hat(t_k), Delta(t_k) of (17) (the smallest channel's for the
 *   "channel" mixing), tau_k (any may be NULL).
 * ivc_reference(c, q_d, dq_d): the reference q_d(t_k), dq_d(t_k) of the last step (either
 *   may be NULL), e.g. to start the arm on it and log the tracking.
 * ivc_state_size / ivc_get_state / ivc_set_state: the whole state (window included) as
 *   bytes, for save and restore; a restored controller continues bit for bit.
 * ivc_set_param(c, IVC_P_x, value): change a gain between steps (not the structural h, T,
 *   block, law, delay, corrected, design, mixing, mix_every, gravity, ref_kind: give those
 *   to ivc_init).
 * The command tau_k: the law's (9) (design 1: its feedback scaled by M(q, theta_nominal);
 *   injection 1: the observer's injection of (8) at theta_nominal), minus
 *   G(q, theta_nominal) with gravity 1 (the robot adds its own), clipped at +-tau_max,
 *   within h tau_rate_max of tau_k-1, 0 at k = 0 with first_zero (docs/controller.md).
 * ivc_reset(c): back to t = 0.  ivc_window_bytes(c): memory of the window.
 */
#ifndef IVDREM_CONTROLLER_H
#define IVDREM_CONTROLLER_H

#include <stddef.h>

#define IVC_NQ {n}
#define IVC_NTHETA {nth}
#define IVC_NPAR {npar}
#define IVC_NH {REFERENCE_HARMONICS}          /* harmonics per joint of the Fourier reference */
#define IVC_START_RAMP_REL {_c_double(START_RAMP_REL)}  /* scale-free mixings: term on at T, ramp 0.1 T */

/* parameter vector layout: par[IVC_P_NAME + i] */
{chr(10).join(idx)}

/* law codes (par[IVC_P_LAW]) */
{laws}

/* design, gravity and mixing codes (par[IVC_P_DESIGN], par[IVC_P_GRAVITY], par[IVC_P_MIXING]) */
{codes}

/* return codes */
#define IVC_OK 0
#define IVC_ERR_ARG 1
#define IVC_ERR_NONFINITE 2
#define IVC_ERR_DIVERGED 3
#define IVC_ERR_STATE 4

#if defined(__GNUC__) && !defined(_WIN32)
#define IVC_INTERNAL __attribute__((visibility("hidden")))
#else
#define IVC_INTERNAL
#endif
#ifndef IVC_API
#define IVC_API
#endif

typedef struct ivc_controller ivc_controller;

IVC_API void ivc_default_params(double *par);
IVC_API int ivc_check_params(const double *par, char *msg, size_t len);
IVC_API ivc_controller *ivc_init(const double *par, char *msg, size_t len);
IVC_API int ivc_step(ivc_controller *c, double t, const double *q, const double *dq, double *tau);
IVC_API int ivc_outputs(const ivc_controller *c, double *theta_hat, double *tau_d_hat,
                        double *Delta, double *tau);
IVC_API size_t ivc_state_size(const ivc_controller *c);
IVC_API int ivc_get_state(const ivc_controller *c, void *buf, size_t size);
IVC_API int ivc_set_state(ivc_controller *c, const void *buf, size_t size);
IVC_API int ivc_set_param(ivc_controller *c, int index, double value);
IVC_API double ivc_get_param(const ivc_controller *c, int index);
IVC_API int ivc_reset(ivc_controller *c);
IVC_API double ivc_time(const ivc_controller *c);
IVC_API int ivc_reference(const ivc_controller *c, double *q_d, double *dq_d);
IVC_API size_t ivc_window_bytes(const ivc_controller *c);
IVC_API const char *ivc_message(const ivc_controller *c);
IVC_API void ivc_free(ivc_controller *c);

/* generated: regressors of Property 1, out row major n x ntheta (controller_model.c) */
{protos}
IVC_INTERNAL extern const double IVC_PAR_DEFAULTS[IVC_NPAR];

#endif
"""
    source = (f"/* controller_model.c: generated by ivdrem {_version()} from the sympy model "
              f"\"{model.name}\"\n * (model key {model.key}) with sympy {sp.__version__}: "
              "sympy.cse + sympy.ccode (C99). Do not edit. */\n"
              "#include <math.h>\n#include \"ivdrem_controller.h\"\n\n"
              "const double IVC_PAR_DEFAULTS[IVC_NPAR] = {"
              + ", ".join(_c_double(v) for v in defaults) + "};\n\n" + "\n".join(funcs))
    return {"ivdrem_controller.h": header, "controller_model.c": source,
            "ivdrem_controller.c": CORE_SOURCE.read_text()}


def build_library(model, directory, *, defaults=None, cc=None, flags=("-O2",)):
    """Compile the sources into a shared library in ``directory``; returns its path
    (cached by the hash of the sources and flags).  The compiler, its checks and its errors
    are ivdrem's one rule (:mod:`ivdrem._cc`: CompilerNotFound, CompilerError)."""
    files = generate_controller_sources(model, defaults)
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    digest = hashlib.sha256("\0".join(files[k] for k in sorted(files)).encode()
                            + " ".join(flags).encode()).hexdigest()[:16]
    ext = ".dylib" if sys.platform == "darwin" else ".so"
    lib = directory / f"libivdrem_controller_{digest}{ext}"
    if lib.exists():
        return lib
    import tempfile
    # sources and binary in a private folder, then one rename: concurrent builds of the
    # same library (pytest workers) never see half-written files
    with tempfile.TemporaryDirectory(prefix="build_", dir=directory) as tmp:
        tmp = Path(tmp)
        for name, text in files.items():
            (tmp / name).write_text(text)
        out = tmp / lib.name
        compile_shared([tmp / "ivdrem_controller.c", tmp / "controller_model.c"], out,
                       what=f"the controller library of model {model.name!r}", cc=cc,
                       include_dirs=[tmp], opt=tuple(flags))
        os.replace(out, lib)
    return lib
