"""The robot plant from an FMU (model exchange) as a block of the closed loop.

:func:`fmu_plant` wraps a plant FMU exported by :func:`ivdrem.fmu.export_fmu` (or any FMI 2.0
model-exchange FMU with the same variable names) as a ``ct.nlsys`` with exactly the signal
names of the Python plant block (:func:`ivdrem.blocks.plant`), so one can replace the other
in a diagram (``closed_loop(..., replace={"plant": fmu_plant(path)})``) and the two can be
checked against each other.

The FMU is instantiated once (:class:`~ivdrem.fmu.instance.FmuInstance`), initialized and
kept in continuous-time mode.  The states belong to the simulator: every evaluation sets
time, continuous states and inputs on the FMU, then reads ``fmi2GetDerivatives`` (state
derivatives) or ``fmi2GetReal`` (outputs ``q``, ``dq``).  Two ways run the same calls:

* python-control and the reference engine call the nlsys's functions, which go through
  fmpy's Python wrappers;
* the compiled engine runs the block's kernels (:func:`fmu_plant_update`,
  :func:`fmu_plant_output`), which call the fmi2 C functions directly by address
  (:func:`ivdrem._native_call.call_c`, through the kernel helper
  :func:`ivdrem.blocks._kernels.fmi2_evaluate`), so no Python runs per right-hand side.

The block declares itself (``sys.ivdrem``, a :class:`~ivdrem.blocks.BlockSpec`): its ports,
its states, its initial state (the FMU's own after initialization: its start values unless
``q0``/``dq0`` are given) and its direct feedthrough, read from the modelDescription's
``ModelStructure`` (:func:`ivdrem.fmu.describe.output_dependencies`).

FMU parameters are fixed at construction (``params``); build a new block for other values.
If the FMU reports an error (e.g. ``M(q)`` not positive definite), the error carries the
FMU's log message and the FMU is reset and re-initialized, so the next call works again.
"""
from __future__ import annotations

import math
from ctypes import CFUNCTYPE, c_double, c_int32, c_int64, c_uint, c_void_p, cast, memmove
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import control as ct

from ..blocks._core import BlockSpec
from ..blocks._kernels import FMI2_TABLE, fmi2_evaluate
from .describe import direct_ports, output_dependencies, read_description
from .instance import FmuError, FmuInstance

__all__ = ["fmu_plant", "FmuPlantInfo", "FmuEvaluationError", "check_plant_fits", "size_mismatch",
           "fmu_plant_update", "fmu_plant_output"]

# what the kernels' address table holds, in order (fmi[k]): the helper's one declaration
_TABLE = FMI2_TABLE
# a float64 holds every integer below 2^53 exactly (52-bit mantissa + hidden bit)
_EXACT_INT = 2 ** 53


@dataclass
class FmuPlantInfo:
    """What :func:`fmu_plant` attaches to the returned system as ``sys.fmu``."""
    path: Path
    model_description: object   # fmpy ModelDescription
    n: int
    x0: np.ndarray              # [q0, dq0]: the FMU's continuous states after initialization
    parameters: dict            # FMU parameter name -> value used
    messages: list              # FMU log messages (last 100)
    unzipdir: str | None        # temporary extraction, removed with the system
    direct: tuple = ()          # input ports the outputs depend on (ModelStructure)
    instance: FmuInstance = None


# ----------------------------------------------------------------------------- kernels
# Module-level functions in the numba subset: the compiled engine copies their source into
# a cached module.  Both run the same fmi2 call sequence, written once as the kernel helper
# ivdrem.blocks._kernels.fmi2_evaluate; all C addresses arrive at run time in the float64
# vector `fmi`, never as literals, so the generated code is the same in every process (see
# _address_table).

def fmu_plant_update(t, x, u, dx, fmi, vr_in, vr_out, perm):
    """The FMU plant block's update kernel: dx = the FMU's state derivatives at (t, x, u)."""
    # states   x = [q (n), dq (n)] (the FMU's state k' = perm[k] is the block's state k)
    # inputs   u = [tau (n), tau_d (n)]
    # params   fmi: C addresses, FMI2_TABLE's order (component, fmi2SetTime,
    #               fmi2SetContinuousStates, fmi2SetReal, fmi2GetDerivatives, fmi2GetReal,
    #               error report)
    #          vr_in (2n), vr_out (2n): value references of the inputs and outputs
    #          perm (2n): FMU state index of each block state
    # writes   dx = fmi2GetDerivatives, in the block's state order (NaN for a NaN x, u)
    fmi2_evaluate(fmi, True, t, x, u, perm, vr_in, vr_out, dx)


def fmu_plant_output(t, x, u, y, fmi, vr_in, vr_out, perm):
    """The FMU plant block's output kernel: y = the FMU's outputs [q, dq] at (t, x, u)."""
    # states   x = [q (n), dq (n)];  inputs u = [tau (n), tau_d (n)] (as in the update)
    # outputs  y = [q (n), dq (n)] = fmi2GetReal of the FMU's outputs vr_out
    fmi2_evaluate(fmi, False, t, x, u, perm, vr_in, vr_out, y)


# ----------------------------------------------------------------------------- the block
def _vector(name, value, n):
    a = np.asarray(value, dtype=float).reshape(-1)
    if a.size != n:
        raise ValueError(f"{name} must have length {n}, got {a.size}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite, got {a}")
    return a


def _address_table(inst: FmuInstance, report) -> np.ndarray:
    """The C addresses the kernels call, as float64 (the kernels' parameters are float64).

    A float64 represents every integer below 2^53 exactly, and user-space addresses are
    far below that (x86-64 and AArch64 Linux: < 2^48), so int(fmi[k]) in the kernel is the
    address again.  Checked here rather than assumed.
    """
    addrs = [inst.component_address] + [inst.address(f) for f in _TABLE[1:-1]]
    addrs.append(int(cast(report, c_void_p).value))
    for what, a in zip(_TABLE, addrs):
        if not 0 < a < _EXACT_INT:
            raise ValueError(f"{inst.path}: the address of {what} ({a:#x}) does not fit a "
                             "float64 exactly; the compiled engine cannot call this FMU "
                             "(use engine='reference')")
    table = np.array(addrs, dtype=np.float64)
    assert all(int(v) == a for v, a in zip(table, addrs))
    return table


def fmu_plant(path, name="plant", q0=None, dq0=None, params=None, n=None):
    """The plant FMU at ``path`` (model exchange) as a block.

    ======  =================================================================
    states  q[n], dq[n]   (set on the FMU by every call: the simulator owns them)
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
        Start values set on the FMU before initialization (default: the FMU's own).  The
        block's initial state (``sys.ivdrem.x0``, also ``sys.fmu.x0``) is the FMU's
        continuous state after initialization.
    params : dict, optional
        FMU parameter values by name, e.g. ``{"theta1": 1.2, "g": 9.7}``; the key
        ``"theta"`` sets all model parameters theta (in order) of an ivdrem-exported FMU.
    n : int, optional
        Degrees of freedom the loop expects (e.g. ``model.n``): an FMU of another size is
        refused here, naming both sizes, instead of leaving loop signals unconnected.

    Returns a ``ct.nlsys`` with ``sys.ivdrem`` (its :class:`~ivdrem.blocks.BlockSpec`, so
    both engines can simulate it) and ``sys.fmu`` (:class:`FmuPlantInfo`).

    Raises FileNotFoundError if ``path`` does not exist, ValueError if it is not a suitable
    FMU, has another size than ``n``, or a parameter is unknown; FmuError (a RuntimeError)
    if the FMU fails to initialize, with its message.
    """
    path = Path(path)
    # everything the model description can refuse is refused before extracting and
    # loading the binary
    md = read_description(path, "model exchange")
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
    tau = [f"tau[{i}]" for i in range(n)]
    tau_d = [f"tau_d[{i}]" for i in range(n)]
    inputs = tau + tau_d
    for s in inputs:
        v = variables.get(s)
        if v is None or v.causality != "input" or v.type != "Real":
            raise ValueError(f"{path}: missing Real input {s}")
    for s in want:
        if variables[s].causality != "output":
            raise ValueError(f"{path}: {s} must be an output")
    in_vr = [variables[s].valueReference for s in inputs]
    out_vr = [variables[s].valueReference for s in want]
    # direct feedthrough: which input ports the outputs q, dq depend on
    direct = direct_ports(output_dependencies(path), want, {"tau": tau, "tau_d": tau_d})

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
    start = dict(values)
    if q0 is not None:
        start.update({f"q[{i}]": x for i, x in enumerate(_vector(f"{name}: q0", q0, n))})
    if dq0 is not None:
        start.update({f"dq[{i}]": x for i, x in enumerate(_vector(f"{name}: dq0", dq0, n))})
    layout = dict(nx=nx, n=n, perm=perm, inputs=inputs, want=want, in_vr=in_vr,
                  out_vr=out_vr, direct=direct, fmu_params=fmu_params, values=values)
    inst = FmuInstance(path, "model exchange", instance_name=name, label=name, md=md)
    try:
        return _build(inst, path, name, start, **layout)
    except BaseException:
        inst.close()        # terminate, free, remove the extracted files now
        raise


def _build(inst, path, name, start, *, nx, n, perm, inputs, want, in_vr, out_vr, direct,
           fmu_params, values):
    md = inst.md
    inst.initialize(start)
    fmu = inst.fmu
    xs = (c_double * nx)()
    inst.call("fmi2GetContinuousStates", fmu.getContinuousStates, xs, nx)
    x0 = np.array(xs[:])[perm]       # the block's initial state: the FMU's own

    # ---- the Python path (python-control, reference engine): fmpy's wrappers
    x_c = (c_double * nx)()
    dx_c = (c_double * nx)()
    u_c = (c_double * (2 * n))()
    y_c = (c_double * nx)()
    in_c = (c_uint * (2 * n))(*in_vr)
    out_c = (c_uint * nx)(*out_vr)
    def set_all(t, x, u):
        inst.recover()      # after an earlier error that could not be reset at once
        xf = np.empty(nx)
        xf[perm] = x
        x_c[:] = xf.tolist()
        u_c[:] = np.asarray(u, dtype=float).tolist()
        fmu.fmi2SetTime(fmu.component, float(t))
        fmu.fmi2SetContinuousStates(fmu.component, x_c, nx)
        fmu.fmi2SetReal(fmu.component, in_c, 2 * n, u_c)

    def finite(t, x, u):
        return math.isfinite(t) and np.all(np.isfinite(x)) and np.all(np.isfinite(u))

    def evaluate(what, t, x, u, get, buf):
        # NaN in, NaN out (as the compiled kernels and the Python plant): the step
        # control rejects a diverging trial step instead of the FMU stopping the run
        x = np.asarray(x, dtype=float)
        u = np.asarray(u, dtype=float)
        if not finite(t, x, u):
            return np.full(nx, np.nan)
        mark = inst.log_count
        try:
            set_all(t, x, u)
            get(fmu.component, buf, nx) if what == "fmi2GetDerivatives" else \
                get(fmu.component, out_c, nx, buf)
        except FmuError as exc:
            raise FmuEvaluationError(str(exc)) from None
        except Exception as exc:
            err = inst.fail_and_reset(f"{what} at t = {float(t):.6g} s", exc, mark)
            raise FmuEvaluationError(str(err)) from None
        return np.array(buf[:])

    def updfcn(t, x, u, params=None):
        return evaluate("fmi2GetDerivatives", t, x, u, fmu.fmi2GetDerivatives, dx_c)[perm]

    def outfcn(t, x, u, params=None):
        return evaluate("fmi2GetReal", t, x, u, fmu.fmi2GetReal, y_c)

    # ---- the compiled path: the kernels call the C functions; errors come back here
    def report(which, status, t, buf, size):
        # called by a kernel whose fmi2 call failed: the error text (with the FMU's
        # message) into buf, then reset the FMU so that the next run starts clean
        what = _TABLE[which] if 0 < which < len(_TABLE) - 1 else "fmi2 call"
        try:
            text = str(inst.fail_and_reset(f"{what} at t = {t:.6g} s (status {status})"))
        except Exception as exc:        # never let an exception escape into C
            text = f"{name}: FMU {path.name}: {what} failed ({exc})"
        data = text.encode("ascii", "replace")[:size]
        memmove(buf, data, len(data))
        return len(data)

    report_c = _REPORT_TYPE(report)
    table = _address_table(inst, report_c)

    sys = ct.nlsys(updfcn, outfcn, inputs=inputs, outputs=want, states=want, name=name)
    sys.ivdrem = BlockSpec(
        name=name, inputs=[("tau", n), ("tau_d", n)], outputs=[("q", n), ("dq", n)],
        states=[("q", n), ("dq", n)], x0=x0.copy(),
        param_names=("fmi", "vr_in", "vr_out", "perm"),
        update=fmu_plant_update, output=fmu_plant_output, direct=direct, kind="ode",
        # runtime values fixed for the block's life: not python-control parameters (they
        # would share the diagram's namespace); arrays, so they travel in the compiled
        # engine's parameter vector, not as literals in the generated source
        constants={"fmi": table, "vr_in": np.array(in_vr, dtype=np.float64),
                   "vr_out": np.array(out_vr, dtype=np.float64),
                   "perm": perm.astype(np.float64)},
        # the report callback must live as long as its address in the table
        info={"fmu": str(path), "report": report_c})
    used = {v.name: float(values.get(v.name, v.start)) for v in fmu_params}
    sys.fmu = FmuPlantInfo(path=path, model_description=md, n=n, x0=x0, parameters=used,
                           messages=inst.messages, unzipdir=inst.unzipdir, direct=direct,
                           instance=inst)
    inst.bind_owner(sys)      # release the FMU with the system
    return sys


_REPORT_TYPE = CFUNCTYPE(c_int32, c_int64, c_int64, c_double, c_void_p, c_int64)


class FmuEvaluationError(FmuError, ValueError):
    """An FMU evaluation failed (derivatives or outputs), with the FMU's message.  Also a
    ValueError, like the compiled kernels' error, so that the simulator stops the run on
    either engine with a SimulationError naming the time."""


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
