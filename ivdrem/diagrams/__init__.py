"""Closed-loop diagrams assembled from the block library with ct.interconnect."""
from .closed_loop import closed_loop, assemble, check_connected
from .gamma_auto import calibrated_loop


#: ``LAWS``: names of the registered laws (:func:`ivdrem.laws.law_names`), read from the
#: registry on each access, so a law registered later is in it.
def __getattr__(name):
    if name == "LAWS":
        from ..laws import law_names
        return law_names()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

__all__ = ["closed_loop", "calibrated_loop", "assemble", "check_connected", "LAWS"]
