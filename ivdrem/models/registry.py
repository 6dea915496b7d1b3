"""Robot models by name: :func:`get_model` and the names it accepts.

Importing this module loads neither sympy nor a URDF parser: a symbolic model whose card is
kept (:mod:`ivdrem.models.card`) is returned without building it in sympy.
"""
from __future__ import annotations

import functools
import re

from .base import RobotModel
from .urdf import ARM_NAMES

__all__ = ["get_model", "model_names", "MODEL_NAMES"]

#: Names accepted by :func:`get_model` (the URDF arms need the ``arms`` extra).
MODEL_NAMES = ("two-link", "planar-N (N >= 1, e.g. planar-3)", *ARM_NAMES)


def model_names():
    """The names :func:`get_model` accepts: ``"two-link"``, the pattern ``"planar-N"``
    (N >= 1) and the named URDF arms (:func:`ivdrem.models.arm`)."""
    return MODEL_NAMES


def _build_symbolic(name, n, kwargs):
    """The sympy model of :func:`get_model`'s symbolic names (kept a module function, so
    that a card's recipe pickles)."""
    from . import robots
    if n is None:
        return robots.two_link(**kwargs)
    return robots.planar_arm(n, **kwargs)


def get_model(name, **kwargs):
    """Model by name: ``"two-link"``, ``"planar-N"`` or a named arm (``"panda"``, ``"ur5"``,
    ``"iiwa"``, ``"xarm7"``); keyword arguments are passed on.  A model is returned as is.

    ``two-link`` and ``planar-N`` are built in sympy the first time (in any process) and
    read from their card afterwards (:class:`ivdrem.models.card.CardModel`: the same
    numbers and code, its symbolic content built only if asked for)."""
    if isinstance(name, RobotModel):
        return name
    from .card import cached_symbolic_model
    key = str(name).strip().lower()
    if key in ("two-link", "two_link", "2-link"):
        return cached_symbolic_model("two-link", kwargs,
                                     functools.partial(_build_symbolic, "two-link", None, kwargs))
    mt = re.fullmatch(r"planar[-_](\d+)", key)
    if mt and int(mt.group(1)) >= 1:
        n = int(mt.group(1))
        return cached_symbolic_model(f"planar-{n}", kwargs,
                                     functools.partial(_build_symbolic, f"planar-{n}", n, kwargs))
    if key in ARM_NAMES:
        from .urdf import arm
        if "g" in kwargs:
            kwargs["gravity"] = kwargs.pop("g")
        return arm(key, **kwargs)
    raise ValueError(f"unknown model {name!r}; valid names: " + ", ".join(MODEL_NAMES))
