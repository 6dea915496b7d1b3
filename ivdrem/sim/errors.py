"""The simulator's errors and warnings, in one leaf module (it imports nothing of ivdrem):
every module of ``sim`` raises these without importing the engine that reports them."""
from __future__ import annotations

__all__ = ["SimulationError", "StiffnessWarning", "BlockError", "CompileError",
           "BLOCK_RAISED_MESSAGE"]

#: what the compiled stepper raises when a block's kernel raised (the simulator turns it
#: into a BlockError naming the block and the time)
BLOCK_RAISED_MESSAGE = "ivdrem: a block kernel raised inside the compiled stepper"


class StiffnessWarning(RuntimeWarning):
    """An explicit method's steps are limited by stability, not accuracy: use a stiff one."""


class SimulationError(RuntimeError):
    """A run that diverged, hit a singular model, or could not continue."""


class BlockError(SimulationError):
    """A block's own function raised during a run; the message names the block and the
    simulated time, the block's exception is chained (``__cause__``)."""


class CompileError(ValueError):
    """A diagram that the compiled path cannot turn into numba code."""
