"""The paper experiment: run the closed loop for each law of a configuration."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .._progress import want_progress
from .config import model_from_config
from .experiment import LawRun  # noqa: F401  (defined beside the Experiment that runs it)

__all__ = ["PaperRun", "run_paper", "run_law"]


@dataclass
class PaperRun:
    """The runs of one experiment: its configuration, the true θ, the model, and a
    :class:`LawRun` per law (``runs``, by law name, in the order they ran)."""
    config: dict
    theta: np.ndarray
    model: object
    runs: dict = field(default_factory=dict)
    #: the :class:`~ivdrem.experiments.experiment.Experiment` the runs came from (each
    #: law's arguments resolved there once: the report reads them, it does not resolve again)
    experiment: object = field(default=None, repr=False, compare=False)


def run_law(config, law, *, model=None, progress=True, engine="compiled", log=None,
            allow_long=False, return_states=True, experiment=None):
    """Simulate the closed loop of `law` from `config` (or of `experiment`, an
    :class:`~ivdrem.experiments.experiment.Experiment` of it; `allow_long`: beyond the cost
    limits of ivdrem.sim.guards; `return_states=False`: the response records the outputs
    only, as ``ivdrem paper`` runs it: the Panda's 5,360 states are 1.3 GB over 300 s at the
    default dt_out).

    A γ chosen by ``gamma = "auto"`` is printed to ``log`` (a callable, default none) and
    stored in ``stats["gamma_choice"]`` and ``LawRun.gamma``.
    """
    from .experiment import Experiment
    if experiment is None:
        experiment = Experiment(config, model_from_config(config) if model is None else model,
                                engine=engine)
    try:
        return experiment.run(law, progress=progress, log=log, allow_long=allow_long,
                              return_states=return_states)
    finally:
        experiment.release(law)


def run_paper(config=None, *, laws=None, progress=True, engine="compiled", log=None,
              allow_long=False, return_states=True):
    """Run every law of the experiment: `config` is a configuration (default: the embedded
    paper experiment) or an :class:`~ivdrem.experiments.experiment.Experiment` of one (as
    the commands pass it after their preflight priced its loops).

    `progress` shows a bar per law when stderr is a terminal and CI is not set.  Each run
    simulates its law's loop (built once, :meth:`Experiment.loop`) and drops it when it
    ends; the γ "auto" of every law after the first is chosen before the first run starts.
    """
    from .experiment import Experiment
    if isinstance(config, Experiment):
        experiment = config
    else:
        experiment = Experiment.from_config(config, engine=engine)
    config = experiment.config
    laws = list(experiment.laws if laws is None else laws)
    run = PaperRun(config=config, theta=experiment.theta, model=experiment.model,
                   experiment=experiment)
    show = want_progress(progress)   # one rule for every bar (ivdrem._progress)
    # a γ "auto" that its calibration refuses must stop the command before any law has
    # run (nothing computed is lost): the later laws' choices are made first and kept
    for law in laws[1:]:
        experiment.choose_gamma(law)
    for law in laws:
        run.runs[law] = run_law(config, law, progress=show, log=log, allow_long=allow_long,
                                return_states=return_states, experiment=experiment)
    return run
