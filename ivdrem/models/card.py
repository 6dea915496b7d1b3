"""A symbolic model read from its card: what a run needs of it, without sympy.

Building ``planar-6`` in sympy takes about a second (its inertia matrix, Christoffel
symbols and linearity checks), and importing sympy alone 0.25 s; a run needs none of it
once the model's code is in the cache.  The first :func:`ivdrem.models.get_model` of a
symbolic model (``two-link``, ``planar-N``) writes a *card*: the model's name, sizes,
parameter values, names and units, and its content key (:attr:`EulerLagrangeModel.key`,
which names its generated source in the cache).  Every later ``get_model`` of the same
name and options, in any process, returns a :class:`CardModel` made from the card.

A :class:`CardModel` is a :class:`~ivdrem.models.RobotModel`: its ``source``, ``functions``
and ``jit_functions`` come from the cached source under its key.  Anything symbolic
(``M``, ``C``, ``Phi_M``, ``constants``, ``generate_source``, ...) builds the sympy model
on first use, checks that its key is the card's, and is read from it.

A card is named by the recipe (the name and options given to ``get_model``) and the digest
of ivdrem's source (``ivdrem.compile_cache.package_digest``), so a changed model definition or a
new ivdrem never reads an old card; the card also repeats its recipe, checked on reading.
It is written atomically (two processes writing it at once both succeed); a damaged or
unreadable card is built again.
"""
from __future__ import annotations

import hashlib
import json

import numpy as np

from .base import RobotModel, linalg_import

__all__ = ["CardModel", "cached_symbolic_model", "CARD_FORMAT"]

#: the cards' own format, in their key and content
CARD_FORMAT = 1
#: the attributes a card holds (the others are the symbolic model's)
_CARD_FIELDS = ("name", "n", "ntheta", "theta_values", "theta_names", "parameter_units", "key")


def _recipe_text(name, options) -> str:
    return json.dumps({"format": CARD_FORMAT, "name": name,
                       "options": {k: options[k] for k in sorted(options)}},
                      sort_keys=True, allow_nan=False)


def _card_path(recipe: str):
    from ..compile_cache import cache_dir, package_digest
    digest = hashlib.sha256(f"{recipe}\n{package_digest()}".encode()).hexdigest()
    return cache_dir() / "models" / "cards" / f"{digest[:32]}.json"


def cached_symbolic_model(name: str, options: dict, build):
    """The model `build()` makes (an :class:`EulerLagrangeModel` named `name`, made with
    `options`), as a :class:`CardModel` read from its card when one is kept; else
    `build()` itself, whose card is then written.  Options that are not JSON numbers,
    strings or lists of them are never carded: `build()` is returned."""
    try:
        recipe = _recipe_text(name, options)
    except (TypeError, ValueError):     # e.g. numpy arrays of masses: built every time
        return build()
    path = _card_path(recipe)
    try:
        card = json.loads(path.read_text(encoding="utf-8"))
        if card.get("recipe") == recipe:
            return CardModel(card, build)
    except (OSError, ValueError, KeyError, TypeError):
        pass
    model = build()
    card = {"recipe": recipe,
            "name": model.name, "n": int(model.n), "ntheta": int(model.ntheta),
            "theta_values": None if model.theta_values is None
            else [float(v) for v in model.theta_values],
            "theta_names": list(model.theta_names),
            "parameter_units": dict(model.parameter_units), "key": model.key}
    try:
        from .._atomic import write_text_atomic
        path.parent.mkdir(parents=True, exist_ok=True)
        write_text_atomic(path, json.dumps(card, indent=1) + "\n")
    except OSError:
        pass    # an unwritable cache only costs the symbolic build next time
    return model


class CardModel(RobotModel):
    """A symbolic model known by its card (module docstring); the sympy model is built on
    the first access to anything the card does not hold (``model.symbolic``)."""

    def __init__(self, card: dict, build):
        missing = [f for f in _CARD_FIELDS if f not in card]
        if missing:
            raise KeyError(f"model card without {', '.join(missing)}")
        self.name = str(card["name"])
        self.n = int(card["n"])
        self.ntheta = int(card["ntheta"])
        tv = card["theta_values"]
        if tv is None:
            self.theta_values = None
        else:
            tv = np.asarray(tv, dtype=float)
            if tv.shape != (self.ntheta,):
                raise ValueError("model card: theta_values of the wrong length")
            tv.setflags(write=False)
            self.theta_values = tv
        self.theta_names = [str(s) for s in card["theta_names"]]
        self.parameter_units = {str(k): str(v) for k, v in card["parameter_units"].items()}
        self.key = str(card["key"])
        self._build = build
        self._symbolic = None
        self._source_cache = {}

    @property
    def symbolic(self):
        """The sympy model this card describes (built once, on first use)."""
        if self._symbolic is None:
            model = self._build()
            if model.key != self.key:     # a card must never stand for another model
                raise RuntimeError(f"model card of {self.name!r} does not match the model "
                                   f"built from its recipe (key {self.key[:12]} against "
                                   f"{model.key[:12]}); delete the card to rebuild it")
            self._symbolic = model
        return self._symbolic

    def __getattr__(self, attr):
        # only reached for what the card does not hold: the symbolic model's attributes
        if attr.startswith("__") or attr in ("_build", "_symbolic", "_source_cache",
                                             "_c_source_cache"):
            raise AttributeError(attr)
        return getattr(self.symbolic, attr)

    @property
    def constants(self):
        """{symbol: value} of the model's known constants (symbolic: from the sympy model)."""
        return self.symbolic.constants

    def source(self, prefix: str = "") -> str:
        """The generated source (:meth:`EulerLagrangeModel.source`), from the cache by key;
        generated by the symbolic model only when the cache does not hold it."""
        return self._memo_source(prefix, lambda p: linalg_import(p) + self._disk_cached_source(
            p, lambda q: self.symbolic._generate_body(q)))

    def _make_c_source(self, prefix):
        """The C face (:meth:`RobotModel.c_source`), from the cache by key; printed by the
        symbolic model only when the cache does not hold it."""
        return self._disk_cached_source(prefix, lambda p: self.symbolic.c_source(p), kind="c")

    def __repr__(self):
        return f"EulerLagrangeModel({self.name!r}, n={self.n}, ntheta={self.ntheta}) [card]"
