"""The paper experiment (SPEC section 8): run the closed loop for each law of a config."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .._progress import want_progress
from ..diagrams import closed_loop
from ..models import get_model
from ..sim import simulate
from .config import closed_loop_kwargs, load_config, solver_kwargs

__all__ = ["LawRun", "PaperRun", "run_paper", "run_law"]


@dataclass
class LawRun:
    """One law's run: the python-control response (named outputs) and solver statistics."""
    law: str
    response: object
    stats: dict


@dataclass
class PaperRun:
    config: dict
    theta: np.ndarray
    model: object
    runs: dict = field(default_factory=dict)


def _model(config):
    m = config["model"]
    kwargs = {"g": float(m["g"])} if "g" in m else {}
    return get_model(m["name"], **kwargs)


def run_law(config, law, *, model=None, progress=True, engine="compiled", allow_long=False):
    """Build the closed loop of `law` from `config` and simulate it (`allow_long`: beyond
    the cost limits of ivdrem.sim.guards)."""
    model = _model(config) if model is None else model
    diagram = closed_loop(law, model, **closed_loop_kwargs(config, law))
    resp = simulate(diagram, float(config["experiment"]["t_end"]),
                    dt_out=float(config["experiment"]["dt_out"]), engine=engine,
                    progress=progress, desc=law, allow_long=allow_long,
                    **solver_kwargs(config))
    return LawRun(law, resp, resp.stats)


def run_paper(config=None, *, laws=None, progress=True, engine="compiled", allow_long=False):
    """Run every law of the configuration (default: the embedded paper experiment).

    `progress` shows a bar per law when stderr is a terminal and CI is not set.
    """
    config = load_config() if config is None else config
    laws = list(config["experiment"]["laws"] if laws is None else laws)
    model = _model(config)
    run = PaperRun(config=config, theta=np.asarray(config["model"]["theta"], float),
                   model=model)
    show = want_progress(progress)   # one rule for every bar (ivdrem._progress)
    for law in laws:
        run.runs[law] = run_law(config, law, model=model, progress=show, engine=engine,
                                allow_long=allow_long)
    return run
