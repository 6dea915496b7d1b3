"""Closed-loop diagrams assembled from the block library with ct.interconnect."""
from .closed_loop import closed_loop, assemble, check_connected


def __getattr__(name):            # LAWS: the law registry's names, read on each access
    if name == "LAWS":
        from ..laws import law_names
        return law_names()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

__all__ = ["closed_loop", "assemble", "check_connected", "LAWS"]
