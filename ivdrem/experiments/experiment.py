"""An experiment resolved once: the model, every law's gains and loop, the solver settings.

A configuration (:func:`ivdrem.experiments.config.read_config`) is data.  An
:class:`Experiment` is that data turned, once, into what the runs need, in the manner of
Drake's systems framework (a system declares its parameters; the simulator and the hosts
ask it, and nothing resolves the same value twice):

* the robot model, built once (``Experiment.model``), and the configuration resolved
  against it (``Experiment.config``: the keys that follow the model filled, the real-arm
  reference designed once, the whole checked);
* per law (:meth:`Experiment.law`, a :class:`LawSetup`): the configuration turned into
  ``closed_loop``'s arguments once (``configured``, as the configuration sets them: what
  the sampled controller and the MuJoCo loop take, with their own defaults for the rest):
  the loop's keywords and the law's ``gains`` (one channel, by the names its registry
  entry declares), the arm's rule for γ and the mixing applied
  (:func:`ivdrem.diagrams.closed_loop.resolve_loop`), and the solver settings;
* the sampled controller's period ``h`` (the configuration's ``[solver] h``);
* γ "auto" chosen once by its calibration (:meth:`Experiment.choose_gamma`,
  :func:`ivdrem.diagrams.gamma_auto.calibrate_gamma`, kept on disk as before) and kept;
* each law's loop built once (:meth:`Experiment.loop`): the preflight prices the loop the
  run then simulates.  A γ "auto" is a parameter of that loop, set for the run
  (``simulate(..., params={"gamma": γ})``), so pricing it needs no calibration.

``ivdrem paper`` and ``ivdrem report`` (their preflight, runs, report and FMU check),
``cosim`` (with the plant FMU or in MuJoCo), a study's runs (and a robustness study's),
``report --plant mujoco`` and ``fmu export --controller --config`` take one
(:meth:`Experiment.of` makes one of a configuration handed to a library function).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

from ..sim import simulate

__all__ = ["Experiment", "LawSetup", "LawRun"]


@dataclass
class LawRun:
    """One law's run: the python-control response (named outputs) and solver statistics."""
    law: str
    response: object
    stats: dict
    gamma: object = None  # γ of the composite term used (the number chosen for "auto")


@dataclass
class LawSetup:
    """One law of an :class:`Experiment`, resolved: ``gains`` (the law's, by name; γ may be
    "auto" until :meth:`Experiment.choose_gamma`), ``loop`` (closed_loop's own keywords,
    the real-arm experiment designed), ``solver`` (the simulator's settings, h_max held to
    half the window T), ``configured`` (closed_loop's arguments as the configuration sets
    them, before the loop's defaults and the arm's rules: what the sampled controller
    takes, :func:`ivdrem.controller.fmu_export.controller_design`), and γ's calibration
    once chosen (``gamma_choice``, ``gamma``)."""
    law: str
    gains: dict
    loop: dict
    solver: dict
    configured: dict = field(default_factory=dict, repr=False)
    gamma_choice: dict | None = None
    diagram: object = field(default=None, repr=False)

    @property
    def auto(self) -> bool:
        """Whether γ is "auto" (a calibration chooses it)."""
        return self.gains.get("gamma") == "auto"

    @property
    def gamma(self):
        """γ of the composite term: the calibration's choice for "auto", else the gain
        (None for a law without γ)."""
        if self.gamma_choice is not None:
            return self.gamma_choice["gamma"]
        return None if self.auto else self.gains.get("gamma")

    def arguments(self) -> dict:
        """closed_loop's arguments (``gains`` and the loop's keywords it was given, those
        left at their default None or False out, so that a caller may add its own, e.g.
        ``external_plant``) with γ a number once chosen (a fresh dict; γ stays "auto" before
        :meth:`Experiment.choose_gamma`)."""
        gains = dict(self.gains)
        if self.gamma_choice is not None:
            gains["gamma"] = self.gamma_choice["gamma"]
        loop = {k: v for k, v in self.loop.items() if v is not None and v is not False}
        return {**loop, "gains": gains}


class Experiment:
    """A validated configuration resolved once (module docstring).  Make one with
    :meth:`from_config`; ``config``, ``model``, ``engine``, ``laws`` (the configured laws,
    in order), ``t_end`` and ``dt_out`` are its data, :meth:`law` a law's resolved setup."""

    def __init__(self, config: Mapping, model, *, engine: str = "compiled", laws=None):
        self.config = config
        self.model = model
        self.engine = engine
        self.laws = list(config["experiment"]["laws"] if laws is None else laws)
        self.t_end = float(config["experiment"]["t_end"])
        self.dt_out = float(config["experiment"]["dt_out"])
        self.theta = np.asarray(config["model"]["theta"], float)
        #: the sampled controller's period h, s: the configuration's ``[solver] h`` (the
        #: default configuration's 1 ms, experiments/default.toml)
        self.h = float(config["solver"]["h"])
        self._setups: dict[str, LawSetup] = {}

    @classmethod
    def of(cls, experiment, *, engine: str | None = None) -> "Experiment":
        """`experiment` itself if it is an Experiment, else the Experiment of that
        configuration (data or resolved; :meth:`from_config`): for the library functions
        that take either."""
        if isinstance(experiment, cls):
            return experiment
        return cls.from_config(experiment, engine=engine or "compiled")

    @classmethod
    def from_config(cls, config: Mapping | None = None, *, engine: str = "compiled",
                    model=None, laws=None) -> "Experiment":
        """The experiment of `config`, configuration data
        (:func:`~ivdrem.experiments.config.read_config`; default: the embedded paper
        experiment) or a configuration already resolved: its model built once (or `model`,
        already built for it), the keys that follow the model filled and the real-arm
        reference designed once (:func:`~ivdrem.experiments.config.resolve_config`, which
        checks the whole against the model before any run), the configured laws (or
        `laws`) resolved."""
        from .config import read_config, resolve_config
        config, model = resolve_config(read_config() if config is None else config, model)
        experiment = cls(config, model, engine=engine, laws=laws)
        for law in experiment.laws:
            experiment.law(law)
        return experiment

    def __reduce__(self):
        # to another process (a study's Dask worker) as its resolved configuration: the
        # model is built there, once per process (config.model_from_config keeps it)
        return (_experiment_of, (self.config, self.engine, self.laws))

    def law(self, law: str) -> LawSetup:
        """`law`'s setup, resolved the first time it is asked for (a law outside
        ``laws``, e.g. the FMU check's iv-drem, is resolved on demand)."""
        setup = self._setups.get(law)
        if setup is None:
            from ..diagrams.closed_loop import resolve_loop
            from .config import closed_loop_kwargs, solver_kwargs
            kw = closed_loop_kwargs(self.config, law, self.model)     # once per law
            configured = {**kw, "gains": dict(kw["gains"])}
            _, _, gains, loop = resolve_loop(law, self.model, **kw)
            setup = LawSetup(law, gains, loop, solver_kwargs(self.config, law), configured)
            self._setups[law] = setup
        return setup

    # ------------------------------------------------------------------------- γ "auto"
    def choose_gamma(self, law: str):
        """γ "auto" of `law` chosen by its calibration (with the run's own solver
        settings and engine; kept on disk by ``ivdrem.diagrams.gamma_auto``) and kept here;
        returns the choice, or None for a law whose γ is a number (or that has none)."""
        setup = self.law(law)
        if not setup.auto:
            return None
        if setup.gamma_choice is None:
            from ..diagrams.gamma_auto import calibrate_gamma
            setup.gamma_choice = calibrate_gamma(
                law, self.model, {**setup.loop, **setup.gains}, engine=self.engine,
                dt_out=self.dt_out, **setup.solver)
        return setup.gamma_choice

    def check_gamma_auto(self, law: str):
        """Refuse `law`'s γ "auto" without simulating when the reference estimate of mean
        Δ² is far below the doubles (ivdrem.diagrams.gamma_auto.check_reference_delta);
        returns the estimate, or None for a law whose γ is not "auto"."""
        setup = self.law(law)
        if not setup.auto:
            return None
        from ..diagrams.gamma_auto import check_reference_delta
        return check_reference_delta(law, self.model, {**setup.loop, **setup.gains},
                                     variant=setup.gains.get("mixing") or "paper")

    # ------------------------------------------------------------------------- the loop
    def loop(self, law: str):
        """`law`'s closed loop, built the first time and kept until :meth:`release`: the
        loop the preflight prices and the run simulates.  A γ "auto" is built at a
        placeholder (the loop's cost and structure do not depend on it) and set for the
        run by :meth:`run_params`."""
        setup = self.law(law)
        if setup.diagram is None:
            from ..diagrams.closed_loop import build_resolved
            from ..laws import get_law
            gains = dict(setup.gains)
            if setup.auto:
                gains["gamma"] = 1.0
            setup.diagram = build_resolved(get_law(law), self.model, gains, **setup.loop)
        return setup.diagram

    def check_cost(self, law: str, diagram=None, *, allow_long=False, what=None):
        """Refuse `law`'s run on `diagram` (default its :meth:`loop`) if its output memory or
        step bound is above the limits of :mod:`ivdrem.sim.guards` (ValueError /
        CostLimitError naming `what`, default "the <law> run")."""
        from ..sim.guards import check_diagram_cost
        solver = self.law(law).solver
        return check_diagram_cost(self.loop(law) if diagram is None else diagram, self.t_end,
                                  engine=self.engine, dt_out=self.dt_out,
                                  method=solver["method"], h=solver["h"],
                                  h_max=solver["h_max"], allow_long=allow_long,
                                  what=what or f"the {law} run")

    def run_params(self, law: str) -> dict | None:
        """The parameters a run of :meth:`loop` is simulated with: γ of a γ "auto" (chosen
        first, :meth:`choose_gamma`), else None."""
        choice = self.choose_gamma(law)
        return None if choice is None else {"gamma": choice["gamma"]}

    def release(self, law: str) -> None:
        """Drop `law`'s loop (a run holds one law's loop at a time)."""
        self.law(law).diagram = None

    # ------------------------------------------------------------------------- a run
    def run(self, law: str, *, progress=True, log=None, allow_long=False,
            return_states=True):
        """Simulate `law`'s loop over the experiment (an
        :class:`LawRun`); a γ chosen by "auto" is printed to
        ``log`` (a callable, default none) and stored in ``stats["gamma_choice"]``."""
        setup = self.law(law)
        params = self.run_params(law)
        choice = setup.gamma_choice
        if choice is not None and log is not None:
            log(f"{law}: gamma = \"auto\" -> {_number_text(choice['gamma'])} "
                f"(mean Delta^2 = {_number_text(choice['mean_Delta2'], '.3g')} over t in "
                f"[{choice['window'][0]:g}, {choice['window'][1]:g}] s; {choice['rule']})")
        resp = simulate(self.loop(law), self.t_end, dt_out=self.dt_out, engine=self.engine,
                        progress=progress, desc=law, allow_long=allow_long,
                        return_states=return_states, params=params, **setup.solver)
        stats = dict(resp.stats)
        if choice is not None:
            stats["gamma_choice"] = choice
        return LawRun(law, resp, stats, gamma=setup.gamma)


def _experiment_of(config, engine, laws):
    """The Experiment of a resolved configuration (unpickling, :meth:`Experiment.__reduce__`)."""
    return Experiment.from_config(config, engine=engine, laws=laws)


def _number_text(value, fmt=".4g"):
    """A number, or a list of them (one per channel of the "channel" mixing), as text."""
    if isinstance(value, (list, tuple, np.ndarray)):
        return "[" + ", ".join(format(float(v), fmt) for v in value) + "]"
    return format(float(value), fmt)
