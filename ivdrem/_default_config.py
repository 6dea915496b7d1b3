"""The default configuration's tables as written (ivdrem/experiments/default.toml): the
paper's experiment, its values written there once and read from there by every layer.

Below everything else: it reads the package's data file by its path, imports nothing of
ivdrem, and validates nothing (``ivdrem.experiments.config`` does).
"""
from __future__ import annotations

import copy
import functools
from pathlib import Path

try:  # Python >= 3.11
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    import tomli as tomllib

__all__ = ["DEFAULT_TOML", "default_tables", "paper_experiment"]

#: the embedded default configuration (package data)
DEFAULT_TOML = Path(__file__).resolve().parent / "experiments" / "default.toml"


@functools.lru_cache(maxsize=1)
def _tables() -> dict:
    return tomllib.loads(DEFAULT_TOML.read_text(encoding="utf-8"))


def default_tables() -> dict:
    """A fresh copy of default.toml's tables, as written (not validated)."""
    return copy.deepcopy(_tables())


def paper_experiment() -> dict:
    """The paper's experiment on its 2-link arm as the default configuration writes it:
    ``q0``, ``dq0``, ``theta_hat0`` ([initial]), ``trajectory`` and ``disturbance`` (the
    sinusoids' amplitude, omega, phase, offset), ``h`` ([solver]: the fixed or first step,
    also the sampled controller's period by default) and ``t_end``; fresh lists each call."""
    t = default_tables()
    return {"q0": t["initial"]["q0"], "dq0": t["initial"]["dq0"],
            "theta_hat0": t["initial"]["theta_hat0"], "trajectory": t["trajectory"],
            "disturbance": t["disturbance"], "h": float(t["solver"]["h"]),
            "t_end": float(t["experiment"]["t_end"])}
