"""The closed loop of two FMUs, controller and plant, in FMPy (own FMU2Slave loop) and in
libcosim (``libcosimpy``), both Jacobi: at t_k every FMU's outputs are read, then passed
on, then every FMU steps over [t_k, t_k + h].  The controller FMU has delay 1 (its torque
output after the step at t_k is meant for [t_k+1, t_k+2]), so both hosts compute the loop
of the Python reference with ``delay=1`` (docs/controller.md).

The disturbance tau_d(t) of the paper's experiment is an input of the plant FMU, set at
each t_k by the master: FMPy's loop here, libcosim's override manipulator.
"""
from __future__ import annotations

import re
import shutil
import tempfile

import numpy as np

from .loop import PAPER_DISTURBANCE, disturbance_at, paper_q0

__all__ = ["fmpy_closed_loop", "libcosim_closed_loop", "controller_period"]


class _Slave:
    def __init__(self, path, name, start):
        from fmpy import extract, read_model_description
        from fmpy.fmi2 import FMU2Slave
        md = read_model_description(str(path))
        self.vr = {v.name: v.valueReference for v in md.modelVariables}
        self.dir = extract(str(path), unzipdir=tempfile.mkdtemp(prefix="ivdrem_loop_"))
        self.messages = []

        def logger(env, inst, status, cat, msg):
            self.messages.append(msg.decode() if isinstance(msg, bytes) else str(msg))
        ident = md.coSimulation.modelIdentifier
        m = re.fullmatch(r"ivdrem controller (\S+) (\S+)", md.modelName or "")
        self.model_name = m.group(2) if m else None
        if md.fmiVersion.startswith("3"):       # FMI 3.0: Float64 access, no setupExperiment
            from fmpy.fmi3 import FMU3Slave
            self.fmu = FMU3Slave(guid=md.guid, unzipDirectory=self.dir, modelIdentifier=ident,
                                 instanceName=name)
            self.fmu.instantiate(logMessage=lambda env, status, cat, msg: logger(env, None, status,
                                                                                cat, msg))
            self.get, self.set = self.fmu.getFloat64, self.fmu.setFloat64
            if start:
                self.set([self.vr[k] for k in start], [float(v) for v in start.values()])
            self.fmu.enterInitializationMode(startTime=0.0)
        else:
            self.fmu = FMU2Slave(guid=md.guid, unzipDirectory=self.dir, modelIdentifier=ident,
                                 instanceName=name)
            self.fmu.instantiate(callbacks=None)
            self.get, self.set = self.fmu.getReal, self.fmu.setReal
            if start:
                self.set([self.vr[k] for k in start], [float(v) for v in start.values()])
            self.fmu.setupExperiment(startTime=0.0)
            self.fmu.enterInitializationMode()
        self.fmu.exitInitializationMode()

    def step(self, t, h):
        self.fmu.doStep(t, h)

    def refs(self, names):
        return [self.vr[n] for n in names]

    def close(self):
        try:
            self.fmu.terminate()
            self.fmu.freeInstance()
        finally:
            shutil.rmtree(self.dir, ignore_errors=True)


def controller_period(controller_fmu, controller_start=None):
    """The sample period h of an ivdrem controller FMU: its parameter ``h`` (the start value
    in its modelDescription.xml, or ``controller_start["h"]`` when the host sets it).  The
    hosts ask the FMU for it, as Drake's simulator asks a system for its period."""
    from fmpy import read_model_description
    if controller_start and "h" in controller_start:
        h = float(controller_start["h"])
    else:
        md = read_model_description(str(controller_fmu))
        v = next((v for v in md.modelVariables if v.name == "h"), None)
        if v is None or v.causality != "parameter":
            raise ValueError(f"{controller_fmu} has no parameter h: not a controller FMU "
                             "exported by ivdrem (ivdrem fmu export --controller)")
        h = float(v.start)
    if not (np.isfinite(h) and h > 0):
        raise ValueError(f"{controller_fmu}: the sample period h must be > 0, got {h!r}")
    return h


def _steps(t_end, h):
    N = int(round(t_end / h))
    if not (t_end > 0 and N >= 1 and abs(N * h - t_end) <= 1e-9 * max(1.0, t_end)):
        raise ValueError(f"t_end = {t_end:g} s must be a whole number of the controller's "
                         f"samples h = {h:g} s")
    return N


def fmpy_closed_loop(controller_fmu, plant_fmu, t_end, *, q0=None, dq0=None,
                     disturbance=PAPER_DISTURBANCE, every=100, controller_start=None,
                     outputs=()):
    """Controller FMU + plant FMU in FMPy, Jacobi, communication step h = the controller
    FMU's parameter h (:func:`controller_period`); the record of
    :func:`ivdrem.controller.loop.sampled_loop` (t, q, dq, tau, tau_d, theta_hat, and the
    controller's other ``outputs`` of its step at t_k, e.g. "q_d": the reference at t_k; at
    t_end the controller takes one more step for them).

    ``q0``, ``dq0``: the plant's start; default the controller's reference q_d(0), q̇_d(0)
    (its outputs q_d, dq_d: the arm starts on the reference), for the paper's 2-link arm
    (and an FMU without those outputs) the paper's q(0) = (0, 0.3 pi) at rest.  A non-finite plant state stops the run with
    a ValueError naming the time (the loop diverged)."""
    h = controller_period(controller_fmu, controller_start)
    N = _steps(t_end, h)
    ctrl = _Slave(controller_fmu, "controller", dict(controller_start or {}))
    plant = None
    try:
        if q0 is None:
            q0, dq0_ref = _reference_start(ctrl)
            dq0 = dq0_ref if dq0 is None else dq0
        n = len(q0)
        dq0 = np.zeros(n) if dq0 is None else dq0
        start = {f"q[{i}]": q0[i] for i in range(n)}
        start.update({f"dq[{i}]": dq0[i] for i in range(n)})
        plant = _Slave(plant_fmu, "plant", start)
        nth = sum(1 for k in ctrl.vr if k.startswith("theta_hat["))
        p_out = plant.refs([f"q[{i}]" for i in range(n)] + [f"dq[{i}]" for i in range(n)])
        p_in = plant.refs([f"tau[{i}]" for i in range(n)] + [f"tau_d[{i}]" for i in range(n)])
        c_in = ctrl.refs([f"q[{i}]" for i in range(n)] + [f"dq[{i}]" for i in range(n)])
        c_out = ctrl.refs([f"tau[{i}]" for i in range(n)] + [f"theta_hat[{j}]" for j in range(nth)])
        extra = {o: ctrl.refs(sorted((k for k in ctrl.vr if k.split("[")[0] == o),
                                     key=lambda k: int(k[len(o) + 1:-1]) if "[" in k else 0))
                 for o in outputs}
        rec = {k: [] for k in ("t", "q", "dq", "tau", "tau_d", "theta_hat", *outputs)}
        for k in range(N + 1):
            t = k * h
            y = np.array(plant.get(p_out))
            if not np.all(np.isfinite(y)):
                raise ValueError(f"the loop diverged: the plant's state is not finite at "
                                 f"t = {t:g} s (step {k} of h = {h:g} s)")
            c = np.array(ctrl.get(c_out))
            tau, th = c[:n], c[n:n + nth]
            tau_d = disturbance_at(t, disturbance)
            keep = k == N or k % every == 0
            if keep:
                rec["t"].append(t)
                rec["q"].append(y[:n])
                rec["dq"].append(y[n:])
                rec["tau"].append(tau)
                rec["tau_d"].append(tau_d)
                rec["theta_hat"].append(th)
            ctrl.set(c_in, list(y))
            ctrl.step(t, h)
            if keep:        # the outputs of step k (q_d: the reference at t_k), as sampled_loop
                for o, vrs in extra.items():
                    rec[o].append(np.array(ctrl.get(vrs)))
            if k == N:
                break
            plant.set(p_in, [*tau, *tau_d])
            plant.step(t, h)
        return {k: np.array(v) for k, v in rec.items()}
    finally:
        ctrl.close()
        if plant is not None:
            plant.close()


def _reference_start(ctrl):
    """(q_d(0), q̇_d(0)) from the controller FMU's outputs after initialisation; the paper's
    start (0, 0.3 pi) at rest for the paper's arm (its experiment starts off the reference,
    Section 4) and for an FMU without the reference outputs."""
    if "q_d[0]" not in ctrl.vr or ctrl.model_name == "two-link":
        return np.array(paper_q0()), None
    n = sum(1 for k in ctrl.vr if k.startswith("q_d["))
    q = np.array(ctrl.get(ctrl.refs([f"q_d[{i}]" for i in range(n)])))
    dq = np.array(ctrl.get(ctrl.refs([f"dq_d[{i}]" for i in range(n)])))
    return q, dq


def libcosim_closed_loop(controller_fmu, plant_fmu, t_end, *, q0=None,
                         dq0=None, disturbance=PAPER_DISTURBANCE, every=100):
    """Controller FMU + plant FMU in libcosim (``libcosimpy``, its fixed-step algorithm,
    step = the controller FMU's h, :func:`controller_period`): q, dq and tau connected FMU
    to FMU by libcosim; the disturbance tau_d(t_k) set on the plant before each step by an
    override manipulator.  Same record as :func:`fmpy_closed_loop` (t, q, dq, tau, tau_d,
    theta_hat).  ``q0``: default the paper's q(0) (:func:`~ivdrem.controller.loop.paper_q0`)."""
    from fmpy import read_model_description
    from libcosimpy.CosimExecution import CosimExecution
    from libcosimpy.CosimLogging import CosimLogLevel, log_output_level
    from libcosimpy.CosimSlave import CosimLocalSlave
    q0 = paper_q0() if q0 is None else q0
    n = len(q0)
    dq0 = np.zeros(n) if dq0 is None else dq0
    vr_p = {v.name: v.valueReference for v in read_model_description(str(plant_fmu)).modelVariables}
    vr_c = {v.name: v.valueReference for v in
            read_model_description(str(controller_fmu)).modelVariables}
    nth = sum(1 for k in vr_c if k.startswith("theta_hat["))
    h = controller_period(controller_fmu)
    steps = _steps(t_end, h)
    step_ns = int(round(h * 1e9))
    if abs(step_ns * 1e-9 - h) > 1e-15:
        raise ValueError(f"libcosim steps in whole nanoseconds; h = {h} is not")
    log_output_level(CosimLogLevel.ERROR)        # libcosim logs every FMU load at debug
    ex = CosimExecution.from_step_size(step_ns)
    ip = ex.add_local_slave(_local_slave(CosimLocalSlave, plant_fmu, "plant"))
    ic = ex.add_local_slave(_local_slave(CosimLocalSlave, controller_fmu, "controller"))
    for i in range(n):
        ex.real_initial_value(ip, vr_p[f"q[{i}]"], float(q0[i]))
        ex.real_initial_value(ip, vr_p[f"dq[{i}]"], float(dq0[i]))
        for name in (f"q[{i}]", f"dq[{i}]"):
            ex.connect_real_variables(ip, vr_p[name], ic, vr_c[name])
        ex.connect_real_variables(ic, vr_c[f"tau[{i}]"], ip, vr_p[f"tau[{i}]"])
    start = np.concatenate([np.asarray(q0, float), np.asarray(dq0, float)])
    return run_libcosim(ex, ip, ic, vr_p, vr_c, n, nth, steps, h, every, disturbance,
                        start=start)


def _local_slave(CosimLocalSlave, path, name):
    """libcosim's slave of the FMU at `path`, or a RuntimeError with libcosim's reason: for
    an FMU it cannot load (an FMI 3.0 one with libcosim 0.11, docs/controller.md) it returns
    a null slave, which libcosimpy passes on and add_local_slave crashes the process on."""
    from libcosimpy._internal import get_last_error_message
    slave = CosimLocalSlave(fmu_path=str(path), instance_name=name)
    if not slave.ptr():
        raise RuntimeError(f"libcosim cannot load the FMU {path}: {get_last_error_message()}")
    return slave


def run_libcosim(ex, ip, ic, vr_p, vr_c, n, nth, steps, h, every, disturbance, *,
                 start=None):
    """Step a libcosim execution of the controller (slave `ic`) and the plant (`ip`)
    `steps` times, tau_d(t_k) set on the plant's input before each step by an override
    manipulator, and record t, q, dq, tau, tau_d, theta_hat every `every` steps and at the
    end.  `start` ([q0, dq0]) records t = 0 too, with the controller's outputs at 0; without
    it the record starts at t = every h."""
    from libcosimpy.CosimManipulator import CosimManipulator
    from libcosimpy.CosimObserver import CosimObserver
    manip = CosimManipulator.create_override()
    ex.add_manipulator(manipulator=manip)
    obs = CosimObserver.create_last_value()
    ex.add_observer(observer=obs)
    p_out = [vr_p[f"q[{i}]"] for i in range(n)] + [vr_p[f"dq[{i}]"] for i in range(n)]
    c_out = [vr_c[f"tau[{i}]"] for i in range(n)] + [vr_c[f"theta_hat[{j}]"] for j in range(nth)]
    tau_d_vr = [vr_p[f"tau_d[{i}]"] for i in range(n)]
    rec = {k: [] for k in ("t", "q", "dq", "tau", "tau_d", "theta_hat")}
    for k in range(steps + 1):
        t = k * h
        tau_d = disturbance_at(t, disturbance)
        if k == steps or (k % every == 0 and (k > 0 or start is not None)):
            if k == 0:
                y, c = np.asarray(start, float), np.zeros(n + nth)
            else:
                y = np.array(obs.last_real_values(ip, p_out))
                c = np.array(obs.last_real_values(ic, c_out))
            rec["t"].append(t)
            rec["q"].append(y[:n])
            rec["dq"].append(y[n:])
            rec["tau"].append(c[:n])
            rec["tau_d"].append(tau_d)
            rec["theta_hat"].append(c[n:])
        if k == steps:
            break
        manip.slave_real_values(ip, tau_d_vr, list(tau_d))
        if not ex.step():
            raise RuntimeError(f"libcosim: step {k} (t = {t}) failed")
    return {k: np.array(v) for k, v in rec.items()}


def _fmu_model(path, name, get_model):
    """The arm of a controller FMU: the description it carries (a URDF arm,
    fmu_export.MODEL_RESOURCE), else the model of that name."""
    import json
    import zipfile
    from .fmu_export import MODEL_RESOURCE
    with zipfile.ZipFile(path) as zf:
        text = (zf.read(MODEL_RESOURCE).decode() if MODEL_RESOURCE in zf.namelist()
                else None)
    if text is None:
        return get_model(name)
    from ..models.urdf import RigidBodyModel
    d = json.loads(text)
    return RigidBodyModel(d["name"], d["chain"])


def _fmu_parameters(path):
    """(model name, law, flat parameter vector) of an ivdrem controller FMU."""
    from fmpy import read_model_description
    from ..models import get_model
    from ..laws import sampled_laws
    from .parameters import param_layout
    md = read_model_description(str(path))
    m = re.fullmatch(r"ivdrem controller (\S+) (\S+)", md.modelName or "")
    if not m or not (md.generationTool or "").startswith("ivdrem "):
        raise ValueError(f"{path} is not a controller FMU exported by ivdrem "
                         "(ivdrem fmu export --controller)")
    law, name = m.groups()
    if law not in sampled_laws():
        raise ValueError(f"{path}: unknown law {law!r}")
    model = _fmu_model(path, name, get_model)
    start = {v.name: v.start for v in md.modelVariables if v.causality == "parameter"}
    par = []
    for pname, size, _ in param_layout(model):
        for i in range(size):
            key = pname if size == 1 else f"{pname}[{i}]"
            par.append(1.0 if pname == "delay" else float(start[key]))
    return model, law, np.array(par)


def main_cosim_controller(args) -> int:
    """``ivdrem cosim --controller-fmu FILE [--fmu PLANT] [--t-end T]``: the controller FMU
    closed around the plant FMU in FMPy against the C reference (same parameters, delay 1);
    exit 0 if q and theta_hat agree to 1e-6, 1 if not or a run failed, 2 bad input."""
    import sys
    import time
    from pathlib import Path
    from .._paths import user_path
    from .clib import CController
    from .loop import FmuPlant, sampled_loop
    prog = "ivdrem cosim"
    try:
        cpath = user_path(args.controller_fmu)
        if not Path(cpath).is_file():
            raise ValueError(f"controller FMU {cpath} does not exist")
        model, law, par = _fmu_parameters(cpath)
        h = par[0]
        N = round(args.t_end / h)
        if not (args.t_end > 0 and abs(N * h - args.t_end) <= 1e-9 * args.t_end):
            raise ValueError(f"--t-end {args.t_end:g} must be a whole number of samples "
                             f"h = {h:g} s")
    except (ValueError, OSError, KeyError) as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    q0 = paper_q0() if model.name == "two-link" else tuple([0.0] * model.n)
    with tempfile.TemporaryDirectory(prefix="ivdrem_cosim_ctl_") as tmp:
        try:
            if args.fmu is None:
                from ..fmu.export import export_fmu
                plant = export_fmu(model, Path(tmp) / "Plant.fmu")
            else:
                plant = user_path(args.fmu)
            t0 = time.perf_counter()
            rec = fmpy_closed_loop(cpath, plant, args.t_end, q0=q0)
            wall = time.perf_counter() - t0
            ref_ctl = CController.from_params(model, law, par)
            p = FmuPlant(plant, q0, np.zeros(model.n))
            try:
                ref = sampled_loop(ref_ctl, p, args.t_end, outputs=("theta_hat",))
            finally:
                p.close()
        except (ValueError, OSError, RuntimeError) as exc:
            print(f"{prog}: run failed: {exc}", file=sys.stderr)
            return 1
    dq = float(np.abs(rec["q"] - ref["q"]).max())
    dth = float(np.abs(rec["theta_hat"] - ref["theta_hat"]).max())
    ok = dq <= 1e-6 and dth <= 1e-6
    print(f"Closed loop of FMUs in FMPy (Jacobi, h = {h:g} s): controller {Path(cpath).name} "
          f"(law {law}, model {model.name}) + plant FMU, t_end = {args.t_end:g} s, {wall:.1f} s")
    print(f"theta_hat(t_end) = {np.array2string(rec['theta_hat'][-1], precision=6)}")
    print(f"against the C reference controller (delay 1): max |q - q_ref| = {dq:.3g}, "
          f"max |theta_hat - theta_hat_ref| = {dth:.3g} (<= 1e-6: {'yes' if ok else 'NO'})")
    return 0 if ok else 1
