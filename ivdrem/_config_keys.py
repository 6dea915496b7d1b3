"""The declaration of one configuration key: its type, the check of its values and the text
of that check for the error message.

A leaf module: the configuration (:mod:`ivdrem.experiments.config`) declares the sections
every run reads with it, and the law registry (:mod:`ivdrem.laws`) each law's own section,
so a built-in law's gains are checked like a user's law's.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

__all__ = ["Key", "in_range", "magnitude", "POSITIVE", "base_unit"]


@dataclass(frozen=True)
class Key:
    """One configuration key.

    kind: "float", "str", "strlist", "names", "vec", "mat", "float_or_vec", "float_or_auto";
    length: "n" or "ntheta" for a vector; check: applied to every number, with
    requirement its text for the message; choices: the strings a "str" key accepts.
    A law's key may also give default: the configuration's default on the paper's arm where
    it differs from the law's ``defaults`` (closed_loop's), and follow(model): its default
    on any other model; unit and doc: the gain's unit and what it is (the sampled
    controller's parameter table and its FMU's variables read them); structural: the gain
    fixes the memory of the law's state (a window's length), so a sampled controller takes
    it before its first step and never between steps.
    """
    kind: str
    length: str | None = None
    check: Callable[[float], bool] | None = None
    requirement: str = ""
    choices: tuple[str, ...] | None = None
    default: Any = None
    follow: Callable[[Any], Any] | None = None
    unit: str = ""
    doc: str = ""
    structural: bool = False

    def __post_init__(self):
        if self.unit:
            base_unit(self.unit)     # refused here, at the declaration, not at an FMU export


#: SI base-unit exponents of the unit symbols a variable may carry (FMI's BaseUnit
#: attributes: kg, m, s, A, K, mol, cd, rad)
_UNIT_SYMBOLS = {"1": {}, "rad": {"rad": 1}, "s": {"s": 1}, "m": {"m": 1}, "kg": {"kg": 1},
                 "N": {"kg": 1, "m": 1, "s": -2}, "Hz": {"s": -1}}


def base_unit(unit):
    """The BaseUnit attributes of `unit` ("rad/s", "N.m", "1/s", "kg.m^2", ...): symbols
    joined by "." (product) and "/" (the rest divides), each with an optional integer
    power "^k"; a symbol FMI's base units cannot express is refused naming it."""
    exps = {}
    for i, part in enumerate(unit.split("/")):
        for factor in part.split("."):
            symbol, _, power = factor.partition("^")
            try:
                k = int(power) if power else 1
            except ValueError:
                k = None
            if symbol not in _UNIT_SYMBOLS or k is None:
                raise ValueError(f"unit {unit!r}: {factor!r} is not one of the units an FMU's "
                                 f"BaseUnit can express ({', '.join(_UNIT_SYMBOLS)}, "
                                 "joined by '.' and '/', powers as '^k')")
            for b, e in _UNIT_SYMBOLS[symbol].items():
                exps[b] = exps.get(b, 0) + (k * e if i == 0 else -k * e)
    order = ("kg", "m", "s", "A", "K", "mol", "cd", "rad")
    return " ".join(f'{b}="{exps[b]}"' for b in order if exps.get(b))


POSITIVE = dict(check=lambda x: x > 0, requirement="> 0")


def in_range(lo: float, hi: float, why: str = "", *, open_lo: bool = False) -> dict:
    """A check `lo <= x <= hi` (`lo < x` with open_lo) and its text for the message: a value
    outside it overflows the loop's products (a huge gain) or divides by almost zero (a tiny
    observer weight) within the first steps, where the run would report a block instead of
    the key."""
    # a positive lower bound reads "> 0 (at least lo)", like h_max and dt_out
    low = f"> {lo:g}" if open_lo else ">= 0" if lo == 0 else \
        f"> 0 (at least {lo:g})" if lo > 0 else f">= {lo:g}"
    check = (lambda x: lo < x <= hi) if open_lo else (lambda x: lo <= x <= hi)
    return dict(check=check, requirement=f"{low} and <= {hi:g}" + (f" ({why})" if why else ""))


def magnitude(hi: float, why: str = "") -> dict:
    """A check `|x| <= hi` and its text for the message."""
    return dict(check=lambda x: abs(x) <= hi,
                requirement=f"at most {hi:g} in magnitude" + (f" ({why})" if why else ""))
