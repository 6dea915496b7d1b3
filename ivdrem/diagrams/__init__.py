"""Closed-loop diagrams assembled from the block library with ct.interconnect."""
from .closed_loop import closed_loop, assemble, check_connected, LAWS

__all__ = ["closed_loop", "assemble", "check_connected", "LAWS"]
