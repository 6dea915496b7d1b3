"""The robot plant from an FMU (model exchange) as a python-control block.

:func:`fmu_plant` wraps a plant FMU exported by :func:`ivdrem.fmu.export_fmu` (or any FMI 2.0
model-exchange FMU with the same variable names) as a ``ct.nlsys`` with exactly the signal
names of the Python plant block (:func:`ivdrem.blocks.plant.plant`), so one can replace the
other in a diagram and the two can be checked against each other.

The FMU is instantiated once (fmpy ``FMU2Model``), initialized, and kept in continuous-time
mode.  The states belong to the caller: the update function sets time, continuous states
and inputs on the FMU and returns ``fmi2GetDerivatives``; the output function returns the
FMU's outputs ``q``, ``dq``.  FMU parameters are fixed at construction (``params``); build a
new block for other values.  If the FMU reports an error (e.g. ``M(q)`` not positive
definite), a ``RuntimeError`` carries the FMU's log message, and the next call resets and
re-initializes the FMU.
"""
from __future__ import annotations

import ctypes
import shutil
import weakref
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import control as ct
from ..fmu.describe import extract_fmu, read_description

__all__ = ["fmu_plant", "FmuPlantInfo", "check_plant_fits"]


@dataclass
class FmuPlantInfo:
    """What :func:`fmu_plant` attaches to the returned system as ``sys.fmu``."""
    path: Path
    model_description: object   # fmpy ModelDescription
    n: int
    x0: np.ndarray              # [q0, dq0] as set on the FMU
    parameters: dict            # FMU parameter name -> value used
    messages: list              # FMU log messages (last 100)
    unzipdir: str | None        # temporary extraction, removed with the system


def _read(path: Path):
    """Model description of the FMU at ``path`` (model exchange); clear errors otherwise."""
    return read_description(path, "model exchange")


def _vector(name, value, n):
    a = np.asarray(value, dtype=float).reshape(-1)
    if a.size != n:
        raise ValueError(f"{name} must have length {n}, got {a.size}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite, got {a}")
    return a


def fmu_plant(path, name="plant", q0=None, dq0=None, params=None, n=None):
    """The plant FMU at ``path`` (model exchange) as a ``ct.nlsys``.

    ======  =================================================================
    states  q[n], dq[n]   (set on the FMU by every call: the caller owns them)
    inputs  tau[n] (control torque), tau_d[n] (external torque)
    output  q[n], dq[n]
    ======  =================================================================

    Parameters
    ----------
    path : path-like
        The ``.fmu`` file (or a directory with an extracted FMU).
    name : str
        System name.
    q0, dq0 : array_like, optional
        Start values set on the FMU before initialization (default: the FMU's).  Also
        available as ``sys.fmu.x0`` for the simulation's initial state.
    params : dict, optional
        FMU parameter values by name, e.g. ``{"theta1": 1.2, "g": 9.7}``; the key
        ``"theta"`` sets all model parameters theta (in order) of an ivdrem-exported FMU.
    n : int, optional
        Degrees of freedom the loop expects (e.g. ``model.n``): an FMU of another size is
        refused here, naming both sizes, instead of leaving loop signals unconnected.

    Raises FileNotFoundError if ``path`` does not exist, ValueError if it is not a suitable
    FMU, has another size than ``n``, or a parameter is unknown.
    """
    from fmpy.fmi2 import FMU2Model, fmi2CallbackFunctions, fmi2CallbackLoggerTYPE, \
        fmi2CallbackAllocateMemoryTYPE, fmi2CallbackFreeMemoryTYPE
    from fmpy import calloc, free

    path = Path(path)
    md = _read(path)
    variables = {v.name: v for v in md.modelVariables}

    # states x = [q, dq] in the FMU's order (ModelStructure/Derivatives)
    fmu_states = [d.variable.derivative.name for d in md.derivatives]
    nx = len(fmu_states)
    n_expected, n = n, nx // 2
    want = [f"q[{i}]" for i in range(n)] + [f"dq[{i}]" for i in range(n)]
    if nx == 0 or nx % 2 or sorted(fmu_states) != sorted(want):
        raise ValueError(f"{path}: the continuous states must be q[0..n-1], dq[0..n-1]; "
                         f"found {', '.join(fmu_states) or 'none'}")
    if n_expected is not None and n != int(n_expected):
        raise ValueError(size_mismatch(path, n, int(n_expected)))
    # block state k is FMU state perm[k]
    perm = np.array([fmu_states.index(s) for s in want])
    inputs = [f"tau[{i}]" for i in range(n)] + [f"tau_d[{i}]" for i in range(n)]
    for s in inputs:
        v = variables.get(s)
        if v is None or v.causality != "input" or v.type != "Real":
            raise ValueError(f"{path}: missing Real input {s}")
    for s in want:
        if variables[s].causality != "output":
            raise ValueError(f"{path}: {s} must be an output")
    in_vr = [variables[s].valueReference for s in inputs]
    out_vr = [variables[s].valueReference for s in want]

    # parameters
    fmu_params = [v for v in md.modelVariables if v.causality == "parameter"]
    theta_vars = [v for v in fmu_params if (v.description or "").startswith("model parameter theta[")]
    values = {}
    for key, val in dict(params or {}).items():
        if key == "theta" and theta_vars:
            th = _vector(f"{name}: params['theta']", val, len(theta_vars))
            values.update({v.name: float(x) for v, x in zip(theta_vars, th)})
        elif key in variables and variables[key].causality == "parameter":
            x = float(np.asarray(val, dtype=float).reshape(()))
            if not np.isfinite(x):
                raise ValueError(f"{name}: parameter {key} must be finite, got {x}")
            values[key] = x
        else:
            raise ValueError(f"{name}: unknown FMU parameter {key!r}; parameters of {path.name}: "
                             + ", ".join(v.name for v in fmu_params)
                             + (", theta" if theta_vars else ""))
    start = {}
    if q0 is not None:
        start.update({f"q[{i}]": x for i, x in enumerate(_vector(f"{name}: q0", q0, n))})
    if dq0 is not None:
        start.update({f"dq[{i}]": x for i, x in enumerate(_vector(f"{name}: dq0", dq0, n))})
    x0 = np.array([float(start.get(s, variables[s].start or 0.0)) for s in want])

    # the FMU: extracted to a temporary directory, removed with the system
    unzipdir = extract_fmu(path) if path.is_file() else str(path)
    messages = []

    def log(env, instance, status, category, message):
        # ivdrem's FMUs pass complete text with '%' doubled (printf-safe): undo that
        messages.append(message.decode("utf-8", "replace").replace("%%", "%"))
        del messages[:-100]

    # No fmpy.logging.addLoggerProxy here: its native proxy keeps the last registered
    # Python logger in one global, which dangles once these callbacks are freed and then
    # crashes every FMU in the process that logs through the proxy.
    callbacks = fmi2CallbackFunctions()
    callbacks.logger = fmi2CallbackLoggerTYPE(log)
    callbacks.allocateMemory = fmi2CallbackAllocateMemoryTYPE(calloc)
    callbacks.freeMemory = fmi2CallbackFreeMemoryTYPE(free)

    try:
        fmu = FMU2Model(guid=md.guid, unzipDirectory=unzipdir,
                        modelIdentifier=md.modelExchange.modelIdentifier, instanceName=name)
    except Exception as exc:
        if path.is_file():
            shutil.rmtree(unzipdir, ignore_errors=True)
        raise ValueError(f"{path}: cannot load the FMU binary: {exc}") from None
    try:
        fmu.instantiate(callbacks=callbacks)
    except Exception as exc:
        fmu.freeLibrary()
        if path.is_file():
            shutil.rmtree(unzipdir, ignore_errors=True)
        raise ValueError(f"{path}: fmi2Instantiate failed: {' '.join(messages) or exc}") from None

    set_vrs = [variables[k].valueReference for k in values] + [variables[k].valueReference for k in start]
    set_vals = list(values.values()) + list(start.values())
    state = {"broken": False, "mark": 0}

    def initialize():
        fmu.setupExperiment(startTime=0.0)
        if set_vrs:
            fmu.setReal(set_vrs, set_vals)
        fmu.enterInitializationMode()
        fmu.exitInitializationMode()
        while True:  # event iteration (the ivdrem plant has no events)
            new_discrete_states_needed, terminate = fmu.newDiscreteStates()[:2]
            if terminate:
                raise RuntimeError("the FMU requested termination during initialization")
            if not new_discrete_states_needed:
                break
        fmu.enterContinuousTimeMode()

    def failed(what, exc):
        state["broken"] = True
        new = messages[state["mark"]:] if state["mark"] <= len(messages) else messages[-1:]
        text = " ".join(new) if new else "no message from the FMU"
        return RuntimeError(f"{name}: FMU {path.name}: {what} failed: {text} ({exc})")

    try:
        initialize()
    except Exception as exc:
        err = failed("initialization", exc)
        _release(fmu, unzipdir if path.is_file() else None)
        raise err from None

    x_c = (ctypes.c_double * nx)()
    dx_c = (ctypes.c_double * nx)()
    u_c = (ctypes.c_double * (2 * n))()
    y_c = (ctypes.c_double * nx)()
    in_c = (ctypes.c_uint * (2 * n))(*in_vr)
    out_c = (ctypes.c_uint * nx)(*out_vr)

    def set_all(t, x, u):
        state["mark"] = len(messages)
        if state["broken"]:  # recover from an earlier fmi2Error
            fmu.reset()
            initialize()
            state["broken"] = False
        x = np.asarray(x, dtype=float)
        xf = np.empty(nx)
        xf[perm] = x
        x_c[:] = xf.tolist()
        u_c[:] = np.asarray(u, dtype=float).tolist()
        fmu.fmi2SetTime(fmu.component, float(t))
        fmu.fmi2SetContinuousStates(fmu.component, x_c, nx)
        fmu.fmi2SetReal(fmu.component, in_c, 2 * n, u_c)

    def updfcn(t, x, u, params=None):
        try:
            set_all(t, x, u)
            fmu.fmi2GetDerivatives(fmu.component, dx_c, nx)
        except Exception as exc:
            raise failed("derivatives", exc) from None
        return np.array(dx_c[:])[perm]

    def outfcn(t, x, u, params=None):
        try:
            set_all(t, x, u)
            fmu.fmi2GetReal(fmu.component, out_c, nx, y_c)
        except Exception as exc:
            raise failed("outputs", exc) from None
        return np.array(y_c[:])

    sys = ct.nlsys(updfcn, outfcn, inputs=inputs, outputs=want, states=want, name=name)
    used = {v.name: float(values.get(v.name, v.start)) for v in fmu_params}
    sys.fmu = FmuPlantInfo(path=path, model_description=md, n=n, x0=x0, parameters=used,
                           messages=messages, unzipdir=unzipdir if path.is_file() else None)
    # free the instance and the extracted files with the system
    weakref.finalize(sys, _release, fmu, unzipdir if path.is_file() else None, callbacks)
    return sys


def size_mismatch(path, n_fmu: int, n_loop: int) -> str:
    """The message for a plant FMU whose size differs from the loop's."""
    return (f"{path}: the FMU's plant has n = {n_fmu} degrees of freedom (signals "
            f"q[0..{n_fmu - 1}], dq, tau, tau_d), the loop's model has n = {n_loop}: export "
            f"the FMU of the loop's model (ivdrem fmu export --model ...)")


def check_plant_fits(block, n: int) -> None:
    """Raise ValueError if `block` is a :func:`fmu_plant` of another size than `n` (for
    code that puts a given plant block into an n-DoF loop)."""
    info = getattr(block, "fmu", None)
    if isinstance(info, FmuPlantInfo) and info.n != int(n):
        raise ValueError(size_mismatch(info.path, info.n, int(n)))


def _release(fmu, unzipdir, callbacks=None):
    try:
        fmu.terminate()
    except Exception:
        pass
    try:
        fmu.freeInstance()
    except Exception:
        pass
    if unzipdir:
        shutil.rmtree(unzipdir, ignore_errors=True)
    del callbacks
