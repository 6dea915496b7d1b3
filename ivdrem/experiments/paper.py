"""The paper experiment: run the closed loop for each law of a configuration."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .._preflight import gain_rule
from .._progress import want_progress
from ..diagrams import closed_loop
from ..sim import simulate
from .config import closed_loop_kwargs, load_config, model_from_config, solver_kwargs

__all__ = ["LawRun", "PaperRun", "run_paper", "run_law"]


@dataclass
class LawRun:
    """One law's run: the python-control response (named outputs) and solver statistics."""
    law: str
    response: object
    stats: dict
    gamma: object = None  # γ of the composite term used (the number chosen for "auto")


@dataclass
class PaperRun:
    """The runs of one experiment: its configuration, the true θ, the model, and a
    :class:`LawRun` per law (``runs``, by law name, in the order they ran)."""
    config: dict
    theta: np.ndarray
    model: object
    runs: dict = field(default_factory=dict)


def law_diagram(config, law, *, model=None, engine="compiled"):
    """The closed loop of `law` from `config`, as its run simulates it.

    With ``iv_drem.gamma = "auto"`` the γ of (21) is chosen here by a calibration run with
    the run's own solver settings (``ivdrem.diagrams.gamma_auto``, kept on disk, so a
    repeat reads it); the choice is in ``diagram.gamma_choice``.  The commands' preflight
    only prices the runs and refuses, without simulating, a γ "auto" whose Δ underflows
    (``ivdrem._preflight.check_runs``).
    """
    model = model_from_config(config) if model is None else model
    kw = closed_loop_kwargs(config, law)
    # used by closed_loop only when it chooses γ "auto" (also by its rule for other arms)
    kw["calibration"] = dict(engine=engine, dt_out=float(config["experiment"]["dt_out"]),
                             **solver_kwargs(config, law))
    return closed_loop(law, model, **kw)


def _choose_gamma(config, law, model, engine):
    """γ "auto" of `law` chosen (and kept on disk) as :func:`law_diagram`'s closed_loop
    chooses it, without building the run's loop; nothing for a law with another γ."""
    kw, mixing, auto = gain_rule(config, law, model)
    if not auto:
        return
    from ..diagrams.gamma_auto import calibrate_gamma
    args = {k: v for k, v in kw.items() if k != "gamma"}
    args["mixing"] = mixing
    calibrate_gamma(law, model, args, engine=engine,
                    dt_out=float(config["experiment"]["dt_out"]), **solver_kwargs(config, law))


def run_law(config, law, *, model=None, progress=True, engine="compiled", log=None,
            allow_long=False, diagram=None, return_states=True):
    """Simulate the closed loop of `law` from `config` (built by :func:`law_diagram`
    unless `diagram` is given; `allow_long`: beyond the cost limits of ivdrem.sim.guards;
    `return_states=False`: the response records the outputs only, as ``ivdrem paper``
    runs it: the Panda's 5,360 states are 1.3 GB over 300 s at the default dt_out).

    A γ chosen by ``gamma = "auto"`` is printed to ``log`` (a callable, default none) and
    stored in ``stats["gamma_choice"]`` and ``LawRun.gamma``.
    """
    if diagram is None:
        diagram = law_diagram(config, law, model=model, engine=engine)
    solver = solver_kwargs(config, law)
    choice = getattr(diagram, "gamma_choice", None)
    if choice is not None and log is not None:
        log(f"{law}: gamma = \"auto\" -> {choice['gamma']:.4g} "
            f"(mean Delta^2 = {choice['mean_Delta2']:.3g} over t in "
            f"[{choice['window'][0]:g}, {choice['window'][1]:g}] s; {choice['rule']})")
    resp = simulate(diagram, float(config["experiment"]["t_end"]),
                    dt_out=float(config["experiment"]["dt_out"]), engine=engine,
                    progress=progress, desc=law, allow_long=allow_long,
                    return_states=return_states, **solver)
    stats = dict(resp.stats)
    if choice is not None:
        stats["gamma_choice"] = choice
    gamma = choice["gamma"] if choice is not None else closed_loop_kwargs(config, law).get("gamma")
    return LawRun(law, resp, stats, gamma=gamma)


def run_paper(config=None, *, laws=None, progress=True, engine="compiled", log=None,
              allow_long=False, return_states=True):
    """Run every law of the configuration (default: the embedded paper experiment).

    `progress` shows a bar per law when stderr is a terminal and CI is not set.  Each run
    builds its loop (:func:`law_diagram`, γ "auto" calibrated there, once) and drops it
    when it ends, so one law's loop is held at a time; the γ "auto" of every law after the
    first is chosen before the first run starts.
    """
    config = load_config() if config is None else config
    laws = list(config["experiment"]["laws"] if laws is None else laws)
    model = model_from_config(config)
    run = PaperRun(config=config, theta=np.asarray(config["model"]["theta"], float),
                   model=model)
    show = want_progress(progress)   # one rule for every bar (ivdrem._progress)
    # a γ "auto" that its calibration refuses must stop the command before any law has
    # run (nothing computed is lost): the later laws' choices are made first and kept on
    # disk (ivdrem.diagrams.gamma_auto), so each run's own loop reads its choice
    for law in laws[1:]:
        _choose_gamma(config, law, model, engine)
    for law in laws:
        run.runs[law] = run_law(config, law, model=model, progress=show, engine=engine,
                                allow_long=allow_long, log=log, return_states=return_states)
    return run
