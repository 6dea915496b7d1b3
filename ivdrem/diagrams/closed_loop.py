"""Closed loops of the paper assembled with ct.interconnect, signals connected by name."""
from __future__ import annotations

import numpy as np
import control as ct

from .. import blocks as block_library
from .. import laws as law_registry
from .._default_config import paper_experiment
from ..sim._control import sparse_maps
from ..sim.guards import check_interconnect_size
from ..sim.plan import check_signal_sizes, rows_with_entries, signal_sizes
from .wiring import NOT_PLAIN, wire_by_name

__all__ = ["closed_loop", "resolve_loop", "build_resolved", "check_gains", "LOOP_ARGUMENTS",
           "LAWS", "assemble", "check_connected"]

#: ``LAWS``: names of the registered composite terms vartheta_c (``ivdrem.laws``), read
#: from the registry on every access: "iv-drem" (proposed, eq. 21), "composite-learning"
#: (eq. 35, Pan & Yu), "drem" (DREM with phi in place of the instrument),
#: "sigma-modification" (erratum E5), "none" (plain disturbance-rejection adaptive
#: control); plus any law added by ``register_law``.
#: ``PAPER_TRAJECTORY``, ``PAPER_DISTURBANCE``: the paper's reference and disturbance
#: (sinusoids' amplitude, omega, phase, offset) as the default configuration writes them
#: (:func:`ivdrem._default_config.paper_experiment`).
def __getattr__(name):
    if name == "LAWS":
        return law_registry.law_names()
    if name in ("PAPER_TRAJECTORY", "PAPER_DISTURBANCE"):
        return paper_experiment()[name.split("_", 1)[1].lower()]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def check_connected(diagram, maps=None):
    """Raise if any subsystem input is left unconnected (python-control would feed 0).
    `maps`: the diagram's sparse maps (ivdrem.sim._control.sparse_maps) if at hand."""
    C, M, _ = sparse_maps(diagram) if maps is None else maps
    rows = np.flatnonzero(~(rows_with_entries(C) | rows_with_entries(M)))
    if rows.size:
        labels = []
        for sys in diagram.syslist:
            labels += [f"{sys.name}.{lab}" for lab in sys.input_labels]
        missing = sorted({labels[i].split("[")[0] for i in rows})
        raise ValueError("unconnected block inputs: " + ", ".join(missing) +
                         ". Give each an output of the same name, or connect it explicitly.")


def assemble(blocks, outputs, name="closed_loop", connections=None, inputs=()):
    """ct.interconnect of `blocks` (connected by signal name) with a connectivity check.

    Without `connections` the blocks are wired by name here (ivdrem.diagrams.wiring: the
    same diagram, its maps kept sparse); explicit `connections` go to ct.interconnect."""
    names = [b.name for b in blocks]
    dup = {n for n in names if names.count(n) > 1}
    if dup:
        raise ValueError(f"duplicate block names in diagram: {sorted(dup)}")
    inputs = list(inputs)
    # python-control's constructor still asks for its dense maps (as zeros: nothing
    # writes them on the sparse route), priced before it does (ivdrem.sim.guards)
    check_interconnect_size(blocks, n_ext_inputs=len(inputs), what=f"diagram {name!r}")
    diagram = wire_by_name(blocks, inputs, outputs, name=name) if connections is None \
        else NOT_PLAIN
    if diagram is NOT_PLAIN:
        kw = {} if connections is None else {"connections": connections}
        diagram = ct.interconnect(blocks, inputs=inputs, outputs=outputs, name=name,
                                  check_unused=False, **kw)
    maps = sparse_maps(diagram)
    check_connected(diagram, maps)
    check_signal_sizes(diagram, maps)  # a 3-vector tau_d into a 2-joint plant: an error
    return diagram


def check_gains(spec, gains) -> dict:
    """A copy of `gains` (None: none) checked against the gains `spec` declares (its
    registry entry's ``defaults``): an unknown name is refused naming the law's gains."""
    gains = {} if gains is None else dict(gains)
    unknown = sorted(set(gains) - set(spec.defaults))
    if unknown:
        known = ", ".join(spec.defaults) or "none"
        raise ValueError(f"law {spec.name!r} has no gain(s) {', '.join(map(repr, unknown))}; "
                         f"its gains (ivdrem.laws, its entry's defaults): {known}")
    return gains


def resolve_loop(law="iv-drem", model=None, *, gains=None, **loop):
    """(law's Law, model, gains, loop) as :func:`closed_loop` builds them: the model (default
    the paper's 2-link arm), the law's `gains` checked (:func:`check_gains`), and on any arm but
    the paper's the real-arm experiment designed for what `loop` and `gains` leave at None
    (docs/experiment.md) and the arm's rule for γ and the mixing
    (:func:`ivdrem.laws.arm_gain_rule`).  γ may come out "auto": a number is chosen from it
    by :func:`ivdrem.diagrams.gamma_auto.calibrate_gamma` (an ``Experiment`` or
    :func:`~ivdrem.diagrams.gamma_auto.calibrated_loop` do)."""
    spec = law_registry.get_law(law)
    unknown = sorted(set(loop) - set(LOOP_ARGUMENTS))
    if unknown:
        hint = [k for k in unknown if k in spec.defaults]
        raise TypeError(f"closed_loop() got unexpected keyword argument(s) "
                        f"{', '.join(map(repr, unknown))}"
                        + (f"; a law's gains go in gains={{...}} ({', '.join(hint)})"
                           if hint else ""))
    gains = check_gains(spec, gains)
    if model is None:
        from ..models import two_link
        model = two_link()
    loop = {k: loop.get(k, v) for k, v in LOOP_ARGUMENTS.items()}
    design = "paper" if loop["design"] is None else loop["design"]
    if design not in block_library.DESIGNS:
        raise ValueError(f"design = {design!r} is not a design of (9); choose one of "
                         + ", ".join(map(repr, block_library.DESIGNS)))
    from ..blocks.control_law import default_injection
    loop["design"] = design
    if loop["injection"] is None:
        loop["injection"] = default_injection(design)
    if not law_registry.is_paper_arm(model):
        # the real-arm experiment, as a configuration naming this model gets it
        joint_gains = loop["K"] is None            # the experiment's, in N m s
        (loop["trajectory"], loop["disturbance"], loop["q0"], loop["dq0"], loop["K"],
         T) = _arm_experiment(model, spec, loop["theta"], loop["trajectory"],
                              loop["disturbance"], loop["q0"], loop["dq0"], loop["K"],
                              gains.get("T"))
        if T is not None and "T" in spec.defaults:
            gains["T"] = T
        if design == "inertia-scaled" and joint_gains:
            loop["K"] = np.diag(block_library.inertia_scaled_gain(
                model, np.diag(loop["K"]), loop["q0"], loop["theta_nominal"]))
    # every arm but the paper's: the mixing and gain rule that work at its size
    gamma, mixing = law_registry.arm_gain_rule(spec, model, gains.get("gamma"),
                                               gains.get("mixing"))
    for name, value in (("gamma", gamma), ("mixing", mixing)):
        if value is not None:
            gains[name] = value
    if mixing is not None and mixing not in law_registry.MIXING_VARIANTS:
        raise ValueError(f"unknown mixing {mixing!r}; choose one of "
                         + ", ".join(repr(v) for v in law_registry.MIXING_VARIANTS)
                         + " (docs/mixing.md)")
    if isinstance(gamma, str):
        if gamma != "auto":
            raise ValueError(f"gamma must be a positive number or 'auto', got {gamma!r}")
        if not spec.uses_delta:
            raise ValueError(f"gamma='auto' needs the mixed regression (17); law {law!r} has none")
    return spec, model, gains, loop


#: closed_loop's own parameters (the loop's, not a law's) and their defaults: the paper's
#: experiment on its 2-link arm (docs/experiment.md)
LOOP_ARGUMENTS = dict(alpha=1.0, K=None, delta_mu=0.8, Gamma=0.01, mu0=1.0, mu1=15.0,
                      observer_variant="corrected", l=50.0, theta_hat0=None, q0=None,
                      dq0=None, theta=None, trajectory=None, disturbance=None, replace=None,
                      external_plant=False, design=None, theta_nominal=None, injection=None)


def closed_loop(law="iv-drem", model=None, *, gains=None, **loop):
    """The paper's closed loop with composite term `law`, as one InterconnectedSystem.

    ``gains``: the law's gains by name (those its registry entry ``ivdrem.laws`` declares:
    T, p, F0, gamma, mixing for "iv-drem" and "drem"; T, gamma, epsilon for
    "composite-learning"; sigma, theta_star for "sigma-modification"; a user law's own),
    each left out taking the entry's default; a name the law does not declare is refused.
    γ must be a number here: ``gamma = "auto"`` is chosen by a calibration
    (:func:`ivdrem.diagrams.gamma_auto.calibrated_loop`, or an
    :class:`ivdrem.experiments.Experiment`, which keeps the choice).

    The loop's own parameters are keywords (:data:`LOOP_ARGUMENTS`): alpha, K, delta_mu,
    Gamma, mu0, mu1, observer_variant, l, theta_hat0, q0, dq0, theta, trajectory,
    disturbance, replace, external_plant, design, theta_nominal, injection.  They are the
    paper's experiment by default (K = 2, the reference, disturbance and q(0) of the
    default configuration, ``ivdrem/experiments/default.toml``).  `trajectory` and
    `disturbance` are either dicts of sinusoid parameters (amplitude, omega, phase, offset)
    or ready nlsys blocks with outputs (q_d, dq_d, ddq_d) and (tau_d).

    Any other model (a URDF arm, a planar arm) gets the real-arm experiment of
    docs/experiment.md, as a configuration naming that model does
    (:mod:`ivdrem.diagrams.arm_reference`): what is left at None of `trajectory` (the Fourier
    reference inside the joint limits), `disturbance` (scaled to the torque that reference
    needs), `q0`, `dq0` (on the reference), `K` (per joint) and the window T of the gains
    (a common period of reference and disturbance) is designed for the model; the mixing
    and γ left out default to :func:`ivdrem.laws.default_mixing` and "auto".  `replace`
    maps block names to user blocks with the same signal names, e.g.
    ``replace={"disturbance": my_block}``.

    Outputs: q, dq, q_d, e, r, tau, tau_d, tau_d_hat, theta_hat, mu, Pi, v, dv; plus those of the
    law (``ivdrem.laws``): Delta, calY, z, phi (and zeta) for "iv-drem"/"drem",
    lambda_min_held for "composite-learning".

    ``mixing`` (laws with the mixed regression (17)) is "paper" (eq. 17), "eigen" or
    "channel" (docs/mixing.md).

    With ``external_plant=True`` the plant block is left out: the diagram has inputs q, dq
    (measured by an external plant, e.g. an FMU) and the same outputs less q, dq (tau and
    tau_d are what the plant receives).

    ``design`` is the feedback of (9): "paper" (the default, (K + δ_μ μ) r) or
    "inertia-scaled" (M̂(q)(K + δ_μ μ) r, M̂ the model's inertia at ``theta_nominal``,
    default its theta_values; K in 1/s): the sampled controller's design
    (:class:`~ivdrem.controller.sampled.SampledController`) in continuous time
    (docs/controller.md, "The inertia-scaled design in continuous time").  With K left at
    None on a real arm, the experiment's joint gains become K_i / M̂_ii(q0).  ``injection``:
    the observer's injection of (8) at θ̂ ("estimate", the paper's design's) or at
    ``theta_nominal`` ("nominal", the inertia-scaled design's default; docs/controller.md,
    "The observer on the nominal inertia").
    """
    spec, model, gains, loop = resolve_loop(law, model, gains=gains, **loop)
    if gains.get("gamma") == "auto":
        raise ValueError(
            f"gamma = 'auto' of law {law!r} is chosen by a calibration run, not by "
            "closed_loop: build the loop with ivdrem.diagrams.gamma_auto.calibrated_loop"
            "(law, model, gains=..., ...) or an ivdrem.experiments.Experiment, or give "
            "gains={'gamma': <a number>}")
    return build_resolved(spec, model, gains, **loop)


def build_resolved(spec, model, gains, *, alpha, K, delta_mu, Gamma, mu0, mu1, observer_variant, l,
           theta_hat0, q0, dq0, theta, trajectory, disturbance, replace, external_plant,
           design, theta_nominal, injection):
    """The loop of :func:`closed_loop` from arguments :func:`resolve_loop` resolved
    (`spec` the law's registry entry, γ a number), built without resolving them again."""
    law = spec.name
    n, nth = model.n, model.ntheta
    if law_registry.is_paper_arm(model):
        paper = paper_experiment()
        trajectory = paper["trajectory"] if trajectory is None else trajectory
        disturbance = paper["disturbance"] if disturbance is None else disturbance
        q0 = paper["q0"] if q0 is None else q0
    K = 2.0 if K is None else K

    def source(spec, factory):
        if isinstance(spec, ct.NonlinearIOSystem):
            return spec
        if not isinstance(spec, dict):
            raise TypeError(f"expected a dict of sinusoid parameters or an nlsys, got {spec!r}")
        unknown = set(spec) - {"amplitude", "omega", "phase", "offset"}
        if unknown:
            raise ValueError(f"unknown sinusoid parameter(s) {sorted(unknown)}")
        return factory(n, **spec)

    blocks = [] if external_plant else [block_library.plant(model, theta=theta, q0=q0, dq0=dq0)]
    blocks += [
        source(trajectory, block_library.trajectory),
        source(disturbance, block_library.disturbance),
        block_library.mu_schedule(mu0, mu1),
        block_library.tracking_error(n, alpha),
        block_library.torque_observer(model, variant=observer_variant, injection=injection,
                                      theta_nominal=theta_nominal),
        block_library.control_law(n, nth, K=K, delta_mu=delta_mu, design=design, model=model,
                                  theta_nominal=theta_nominal, injection=injection),
        block_library.adaptation_law(n, nth, Gamma=Gamma, theta_hat0=theta_hat0),
    ]
    outputs = ["q", "dq", "q_d", "e", "r", "tau", "tau_d", "tau_d_hat", "theta_hat", "mu",
               "Pi", "v", "dv"]  # Pi, v, dv: the observer (7) with the true θ, offline
    # the law's own gains over its registry entry's defaults, and the loop's filter gain l
    params = law_registry.resolve_params(spec, gains)
    params.setdefault("l", l)
    law_blocks, law_outputs = spec.build(law_registry.LawContext(model, n, nth, params))
    blocks += list(law_blocks)
    outputs += [o for o in law_outputs if o not in outputs]

    start = {}
    if replace and "plant" in replace and not external_plant:
        start = _replaced_plant_start(replace["plant"], n, q0, dq0)
    if replace:
        names = {b.name: i for i, b in enumerate(blocks)}
        for key, blk in replace.items():
            if key not in names:
                raise ValueError(f"replace: no block named {key!r}; blocks are {sorted(names)}")
            if not isinstance(blk, ct.InputOutputSystem):
                raise TypeError(f"replace[{key!r}] must be a python-control system")
            _check_signal_sizes(key, blocks[names[key]], blk)
            blocks[names[key]] = blk
    if external_plant:
        outputs = [o for o in outputs if o not in ("q", "dq")]
        return assemble(blocks, outputs, name=f"controller[{law}]", inputs=["q", "dq"])
    diagram = assemble(blocks, outputs, name=f"closed_loop[{law}]")
    if start:
        # read by ivdrem.sim.plan: the replaced plant's start, by state name
        diagram.ivdrem_start = {replace["plant"].name: start}
    return diagram


def _arm_experiment(model, spec, theta, trajectory, disturbance, q0, dq0, K, T):
    """(trajectory, disturbance, q0, dq0, K, T) of the real-arm experiment for `model`
    (docs/experiment.md), each one the caller left at None designed by the functions the
    configuration uses for that model (``ivdrem.experiments.config``, ARM_FOLLOWING): the
    Fourier reference, q(0) = q_d(0), q̇(0) = 0, the disturbance scaled to the arm, the gains
    per joint and the window T of (15a) for a law that has one."""
    from . import arm_reference as arm_experiment
    from ..blocks.sources import fourier_trajectory
    table = trajectory
    if trajectory is None:
        table = arm_experiment.design_trajectory(model)
    elif isinstance(trajectory, dict):
        table = {"kind": "sinusoid", **trajectory}
    elif disturbance is None or q0 is None or (T is None and "T" in spec.defaults):
        raise ValueError(f"model {model.name!r}: with a trajectory block of your own, give "
                         "`disturbance`, `q0` and the window `T` too (the real-arm "
                         "experiment designs them from a reference it can evaluate)")
    if disturbance is None:
        disturbance = arm_experiment.design_disturbance(model, table, theta)
    if q0 is None or dq0 is None:
        # a block of the caller's: q0 was required above, and q̇(0) = 0 as in the design
        q_start, dq_start = (arm_experiment.initial_state(table) if isinstance(table, dict)
                             else (None, np.zeros(model.n)))
        q0 = np.asarray(q_start, float) if q0 is None else q0
        dq0 = np.asarray(dq_start, float) if dq0 is None else dq0
    if K is None:
        K = np.diag(arm_experiment.design_gains(model, q0, theta))
    if T is None and "T" in spec.defaults and isinstance(disturbance, dict):
        T = arm_experiment.design_window(table, disturbance)   # None: the law's own T
    if trajectory is None:
        trajectory = fourier_trajectory(model.n, float(table["omega_f"]),
                                        np.asarray(table["a"], float),
                                        np.asarray(table["b"], float),
                                        np.asarray(table["offset"], float))
    if isinstance(disturbance, dict):
        disturbance = {k: np.asarray(disturbance[k], float)
                       for k in ("amplitude", "omega", "phase", "offset")}
    return trajectory, disturbance, q0, dq0, K, T


def _replaced_plant_start(plant, n, q0, dq0):
    """The experiment's q(0), q̇(0) reach a plant that replaces ivdrem's, or the call refuses.

    An ivdrem block with its own initial state (``fmu_plant(..., q0=...)``: the FMU's start
    values) must already start there; a plain python-control system gets them by its state
    names ``q[i]``, ``dq[i]`` (returned as {state name: value}, applied by the simulator's
    plan where no ``x0`` is given).  Anything else would silently drop q0/dq0."""
    want = np.concatenate([np.zeros(n) if q0 is None else np.asarray(q0, float).reshape(-1),
                           np.zeros(n) if dq0 is None else np.asarray(dq0, float).reshape(-1)])
    spec = getattr(plant, "ivdrem", None)
    if spec is not None and np.size(getattr(spec, "x0", None)) == 2 * n:
        have = np.asarray(spec.x0, float).reshape(-1)
        if have.shape != want.shape or not np.array_equal(have, want):
            raise ValueError(
                f"replace['plant'] starts from its own initial state "
                f"{np.round(have, 6).tolist()}, but the loop's [q(0), dq(0)] is "
                f"{np.round(want, 6).tolist()} (q0, dq0; the paper's q(0) for the 2-link arm): "
                "build the replacement with that state (e.g. ivdrem.fmu.fmu_plant(path, "
                "q0=..., dq0=...)), or pass q0/dq0 equal to the plant's")
        return {}
    names = [f"q[{i}]" for i in range(n)] + [f"dq[{i}]" for i in range(n)]
    labels = list(getattr(plant, "state_labels", []))
    if set(names) <= set(labels):
        return dict(zip(names, want.tolist()))
    if np.any(want != 0):
        raise ValueError(
            f"replace['plant'] has no states named q[0..{n - 1}], dq[0..{n - 1}] (its states: "
            f"{labels[:8]}{' ...' if len(labels) > 8 else ''}), so the loop's "
            f"[q(0), dq(0)] = {np.round(want, 6).tolist()} cannot reach it: name its states so, "
            "or pass simulate(..., x0=...) with q0 = dq0 = 0 here")
    return {}


def _check_signal_sizes(key, old, new):
    """A replacement block must carry each signal it shares with the block it replaces at
    the same size: a 3-vector tau_d in a 2-joint loop is an error, not a silent truncation."""
    for kind in ("input", "output"):
        was = signal_sizes(getattr(old, f"{kind}_labels"))
        now = signal_sizes(getattr(new, f"{kind}_labels"))
        for name in sorted(set(was) & set(now)):
            if was[name] != now[name]:
                raise ValueError(
                    f"replace[{key!r}]: {kind} signal {name!r} has {now[name]} entries, but the "
                    f"loop's {key!r} block has {was[name]}")
