"""The sampled loop: a fixed-step controller closed around ivdrem's plant FMU in FMPy.

At t_k = k h the plant's outputs q(t_k), q'(t_k) go to the controller, whose torque (and
the disturbance tau_d(t_k) of the paper's experiment) is held over [t_k, t_k + h] while the
plant FMU integrates (``fmi2DoStep``, RK4 sub-steps of at most ``cs_substep``).  With a
controller of ``delay = 0`` this is the Gauss-Seidel order (plant first, then the
controller, whose tau_k is applied at once); with ``delay = 1`` the controller's tau_k is
applied over the next sample, as a Jacobi host does (docs/controller.md).

``controller`` is anything with ``step(t, q, dq) -> tau``, ``h`` and ``n``: the Python
:class:`~ivdrem.controller.sampled.SampledController`, the C library
(:class:`~ivdrem.controller.clib.CController`) or a controller FMU
(:func:`fmu_controller_loop`).
"""
from __future__ import annotations

import shutil
import tempfile

import numpy as np

from .._default_config import paper_experiment

__all__ = ["FmuPlant", "ModelPlant", "sampled_loop", "as_response", "PAPER_DISTURBANCE",
           "PAPER_Q0", "paper_q0", "default_period"]

#: The paper's external torque τ_d,i = A_i sin(ω_i t) (Section 4), as keywords of
#: :func:`ivdrem.blocks.disturbance`.
PAPER_DISTURBANCE = dict(amplitude=[7.5, 1.5], omega=[0.5 * np.pi, 0.05 * np.pi],
                         phase=[0.0, 0.0], offset=[0.0, 0.0])


def paper_q0() -> tuple:
    """The paper's initial joint positions q(0) = (0, 0.3π) rad (Section 4), as the default
    configuration writes them (``[initial] q0`` of experiments/default.toml)."""
    return tuple(paper_experiment()["q0"])


def default_period() -> float:
    """The sampled controller's period h when none is given: the default configuration's
    ``[solver] h`` (experiments/default.toml), the paper's 1 ms."""
    return paper_experiment()["h"]


#: The paper's q(0) = (0, 0.3π) rad, read from the default configuration where it is written.
PAPER_Q0 = paper_q0()


class FmuPlant:
    """An ivdrem plant FMU (co-simulation) in FMPy's FMU2Slave, initialised at q0, dq0."""

    def __init__(self, path, q0, dq0, *, substep=None, name="plant"):
        from fmpy import extract, read_model_description
        from fmpy.fmi2 import FMU2Slave
        md = read_model_description(str(path))
        self.vr = {v.name: v.valueReference for v in md.modelVariables}
        n = sum(1 for v in md.modelVariables if v.name.startswith("q["))
        self.n = n
        self._dir = extract(str(path), unzipdir=tempfile.mkdtemp(prefix="ivdrem_plant_"))
        self.fmu = FMU2Slave(guid=md.guid, unzipDirectory=self._dir,
                             modelIdentifier=md.coSimulation.modelIdentifier,
                             instanceName=name)
        self.fmu.instantiate()
        start = {f"q[{i}]": float(q0[i]) for i in range(n)}
        start.update({f"dq[{i}]": float(dq0[i]) for i in range(n)})
        if substep is not None:
            start["cs_substep"] = float(substep)
        self.fmu.setReal([self.vr[k] for k in start], list(start.values()))
        self.fmu.setupExperiment(startTime=0.0)
        self.fmu.enterInitializationMode()
        self.fmu.exitInitializationMode()
        self.out_vr = [self.vr[f"q[{i}]"] for i in range(n)] + \
            [self.vr[f"dq[{i}]"] for i in range(n)]
        self.in_vr = [self.vr[f"tau[{i}]"] for i in range(n)] + \
            [self.vr[f"tau_d[{i}]"] for i in range(n)]

    def outputs(self):
        y = np.array(self.fmu.getReal(self.out_vr))
        return y[:self.n], y[self.n:]

    def step(self, t, h, tau, tau_d):
        self.fmu.setReal(self.in_vr, [*map(float, tau), *map(float, tau_d)])
        self.fmu.doStep(currentCommunicationPoint=t, communicationStepSize=h)

    def close(self):
        """Terminate and free the FMU, remove its unzipped files.  An FMU in its error state
        (after a failed step) may refuse fmi2Terminate (FMI 2.0: not allowed there); it is
        freed all the same, and the step's own error is the one that is reported."""
        from fmpy.fmi1 import FMICallException
        try:
            try:
                self.fmu.terminate()
            except FMICallException:
                pass
            self.fmu.freeInstance()
        finally:
            shutil.rmtree(self._dir, ignore_errors=True)


def disturbance_at(t, d=PAPER_DISTURBANCE):
    return (np.asarray(d["amplitude"]) * np.sin(np.asarray(d["omega"]) * t
                                                 + np.asarray(d["phase"]))
            + np.asarray(d["offset"]))


def sampled_loop(controller, plant, t_end, *, disturbance=PAPER_DISTURBANCE, every=100,
                 outputs=("theta_hat", "tau_d_hat")):
    """Run ``controller`` around ``plant`` (an :class:`FmuPlant`) for t_end seconds.

    Returns a dict of arrays sampled at t_k, every ``every`` samples and at t_end: t, q,
    dq, tau_d, the torque tau applied over [t_k, t_k+1], theta_hat(t_k) and the
    controller's other ``outputs`` of step k (tau_d_hat(t_k), Delta(t_k)); at t_end the
    controller takes one more step for them.  A controller with ``delay = 1`` outputs tau_k
    for the next sample: the torque applied is then its previous output.
    """
    h = controller.h
    N = int(round(t_end / h))
    if N < 1 or abs(N * h - t_end) > 1e-9 * max(1.0, t_end):
        raise ValueError(f"t_end = {t_end} must be a whole number of samples h = {h}")
    delay = getattr(controller, "delay", 0)
    rec = {k: [] for k in ("t", "q", "dq", "tau", "tau_d", "theta_hat", *outputs)}
    applied = np.zeros(controller.n)
    for k in range(N + 1):
        t = k * h
        q, dq = plant.outputs()
        keep = k == N or k % every == 0
        if keep:
            rec["theta_hat"].append(np.copy(controller.theta_hat))
        tau = controller.step(t, q, dq)
        if delay == 0:
            applied = tau
        tau_d = disturbance_at(t, disturbance)
        if keep:
            rec["t"].append(t)
            rec["q"].append(q)
            rec["dq"].append(dq)
            rec["tau"].append(np.copy(applied))
            rec["tau_d"].append(tau_d)
            for o in outputs:
                if o != "theta_hat":
                    rec[o].append(np.copy(getattr(controller, o)))
        if k == N:
            break
        plant.step(t, h, applied, tau_d)
        if delay == 1:
            applied = tau
    return {k: np.array(v) for k, v in rec.items()}


def as_response(rec):
    """The record of :func:`sampled_loop` as a response that ivdrem.experiments.metrics
    reads (time, outputs, output_labels)."""
    from types import SimpleNamespace
    rows, labels = [], []
    for name, v in rec.items():
        if name == "t":
            continue
        v = np.asarray(v, dtype=float)
        if v.ndim == 1:
            rows.append(v)
            labels.append(name)
        else:
            for i in range(v.shape[1]):
                rows.append(v[:, i])
                labels.append(f"{name}[{i}]")
    return SimpleNamespace(time=np.asarray(rec["t"]), outputs=np.array(rows),
                           output_labels=labels)


# ----------------------------------------------------------------------- a model's own plant
_RK4_STEPPERS: dict = {}
_CLOSED_LOOPS: dict = {}

#: RK4 over a model's forward dynamics with the torque held, compiled in a module of the
#: compile cache beside the model's own (``fd``, ``G``): numba keeps its machine code, so a
#: process loads it where it compiled it (12-16 s a model) in every process before
_RK4_SOURCE = """
@njit(cache=True)
def step(q, dq, tau, tau_d, theta, h, nsub, gravity):
    # states   q[n], dq[n] (advanced in place)
    # inputs   tau[n] (held), tau_d[n] (held), gravity: add G(q, theta) at every stage
    n = q.shape[0]
    dt = h / nsub
    u = np.empty(n)
    g = np.zeros(n)
    k1q, k2q, k3q, k4q = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    k1v, k2v, k3v, k4v = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    qs, vs = np.empty(n), np.empty(n)
    for _ in range(nsub):
        for stage in range(4):
            if stage == 0:
                qs[:] = q
                vs[:] = dq
            elif stage == 1:
                qs[:] = q + 0.5 * dt * k1q
                vs[:] = dq + 0.5 * dt * k1v
            elif stage == 2:
                qs[:] = q + 0.5 * dt * k2q
                vs[:] = dq + 0.5 * dt * k2v
            else:
                qs[:] = q + dt * k3q
                vs[:] = dq + dt * k3v
            if gravity:
                G(qs, theta, g)
            for i in range(n):
                u[i] = tau[i] + tau_d[i] + g[i]
            kq = (k1q, k2q, k3q, k4q)[stage]
            kv = (k1v, k2v, k3v, k4v)[stage]
            kq[:] = vs
            fd(qs, vs, u, theta, kv)
        for i in range(n):
            q[i] += dt / 6.0 * (k1q[i] + 2.0 * k2q[i] + 2.0 * k3q[i] + k4q[i])
            dq[i] += dt / 6.0 * (k1v[i] + 2.0 * k2v[i] + 2.0 * k3v[i] + k4v[i])
"""

#: The sampled loop of stability.closed_loop_prefix around step() above, in a module of its
#: own (importing step), so that the plant's module and its machine code stay as they were
_CLOSED_LOOP_SOURCE = """
@njit(cache=True)
def closed_loop(ctl_step, ctl_outputs, handle, q, dq, u, theta, tau_d, h, nsub, gravity,
                delay, keep, rec_q, rec_dq, rec_u, rec_theta_hat, progress, k_stop):
    # The sampled loop of stability.closed_loop_prefix, steps progress[0] .. k_stop - 1 of
    # it: the C library's controller (ivc_step, ivc_outputs at the address handle;
    # pointers as integers) around the plant's RK4 step(), the same calls in the same order
    # as the Python loop, so the same numbers.  Called again with the same arrays it goes
    # on where it stopped, so a loop run in pieces (between which Python sees a Ctrl-C) is
    # the loop run in one call, bit for bit.
    # states   q[n], dq[n] (advanced in place), u[n] the torque held (delay 1),
    #          progress = [k, j]: the next step k, the next record row j
    # inputs   tau_d[N, n] the disturbance held over step k
    # records  at k with keep[k] (k = 0..N): q, dq, u, theta_hat -> rec_*[j], j-th kept k
    # returns  0: ran to N; 1: the controller refused step progress[0]; 2: the plant's
    #          state not finite after it (a ValueError of the plant leaves progress[0]
    #          set); 3: stopped at k_stop < N + 1 (call again to go on)
    n = q.shape[0]
    N = tau_d.shape[0]
    tau = np.zeros(n)
    qk, dqk = np.empty(n), np.empty(n)
    tdh, Delta, tau_o = np.empty(n), np.empty(1), np.empty(n)
    j = progress[1]
    for k in range(progress[0], k_stop):
        t = k * h
        progress[0] = k
        qk[:] = q
        dqk[:] = dq
        if keep[k]:
            ctl_outputs(handle, rec_theta_hat[j].ctypes.data, tdh.ctypes.data,
                        Delta.ctypes.data, tau_o.ctypes.data)
            rec_q[j] = qk
            rec_dq[j] = dqk
            rec_u[j] = u
            j += 1
            progress[1] = j
        if k == N:
            return 0
        if ctl_step(handle, t, qk.ctypes.data, dqk.ctypes.data, tau.ctypes.data) != 0:
            return 1
        if delay == 0:
            step(q, dq, tau, tau_d[k], theta, h, nsub, gravity)
        else:
            step(q, dq, u, tau_d[k], theta, h, nsub, gravity)
        for i in range(n):
            if not (math.isfinite(q[i]) and math.isfinite(dq[i])):
                return 2
        u[:] = tau
    progress[0] = k_stop
    return 3
"""


def _rk4_stepper(model):
    """A compiled RK4 over the model's forward dynamics with the torque held (one per model
    key): step(q, dq, tau, tau_d, theta, h, nsub, gravity) advances (q, dq) in place by
    nsub steps of h / nsub; ``gravity``: the plant adds G(q, theta) to the torque itself (a
    robot that compensates its own gravity)."""
    key = model.key
    if key in _RK4_STEPPERS:
        return _RK4_STEPPERS[key]
    from ..models._jit_module import model_module
    functions = model_module(model)      # imported first: the module below imports it
    step = _generated_module("rk4", f"RK4 of model {model.name}, torque held",
                             f"from {functions.__name__} import forward_dynamics as fd, G",
                             _RK4_SOURCE).step
    _RK4_STEPPERS[key] = step
    return step


def _generated_module(kind, title, imports, body):
    """The module ``ivdrem_<kind>_<hash of its source>`` of the compile cache (written and
    imported once per process; numba keeps its machine code beside it)."""
    from ..compile_cache import GENERATED_HEADER, cache_dir, import_generated, source_hash
    src = "\n".join([f"# Generated by ivdrem: {title}. Do not edit.", *GENERATED_HEADER,
                     imports, "", body])
    return import_generated(cache_dir(), f"ivdrem_{kind}_{source_hash(src)}", src)


def compiled_closed_loop(model):
    """The compiled sampled loop of the model's RK4 plant around the C library's controller
    (``closed_loop`` of the generated module above, one per model key): the steps of
    stability.closed_loop_prefix, in pieces of any length (:func:`run_in_pieces`)."""
    key = model.key
    if key in _CLOSED_LOOPS:
        return _CLOSED_LOOPS[key]
    step = _rk4_stepper(model)          # imported first: the module below imports it
    loop = _generated_module("loop", f"the sampled loop of model {model.name}",
                             f"from {step.__module__} import step",
                             _CLOSED_LOOP_SOURCE).closed_loop
    _CLOSED_LOOPS[key] = loop
    return loop


class ModelPlant:
    """The arm's own dynamics M q'' + C q' + F + G = tau + tau_d (the model's forward
    dynamics at ``theta``, default its theta_values) integrated by RK4 with ``substeps``
    steps per sample and the inputs held: a plant for :func:`sampled_loop` without an FMU.
    ``gravity=True``: the plant adds G(q, theta) to the torque (a robot that compensates
    its own gravity, as Franka's and UR's torque interfaces do)."""

    def __init__(self, model, q0, dq0, *, theta=None, substeps=4, gravity=False):
        self.model, self.n = model, model.n
        self.theta = np.asarray(model.theta_values if theta is None else theta, dtype=float)
        self.q = np.array(q0, dtype=float)
        self.dq = np.array(dq0, dtype=float)
        self.substeps, self.gravity = int(substeps), bool(gravity)
        self._step = _rk4_stepper(model)

    def outputs(self):
        return self.q.copy(), self.dq.copy()

    def step(self, t, h, tau, tau_d):
        try:
            self._step(self.q, self.dq, np.asarray(tau, dtype=float),
                       np.asarray(tau_d, dtype=float), self.theta, float(h), self.substeps,
                       self.gravity)
        except ValueError as exc:        # M(q) singular along a diverged motion
            raise FloatingPointError(f"the plant diverged in [{t:.6g}, {t + h:.6g}] s: "
                                     f"{exc}") from None
        if not (np.all(np.isfinite(self.q)) and np.all(np.isfinite(self.dq))):
            raise FloatingPointError(f"the plant diverged at t = {t + h:.6g} s "
                                     f"(q = {self.q}, dq = {self.dq})")

    def close(self):
        pass
