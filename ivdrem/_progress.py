"""When to show a progress bar: one rule for every bar ivdrem draws.

A bar is drawn only when stderr is a terminal, the environment variable ``CI`` is not set
and the caller did not ask for quiet (``--quiet``, ``progress=False``).  A bar in a
redirected stderr is noise in a log file; CI systems often give a pseudo-terminal.
"""
from __future__ import annotations

import os
import sys

__all__ = ["want_progress"]


def want_progress(requested=None, stream=None) -> bool:
    """True if a progress bar should be drawn on `stream` (default ``sys.stderr``).

    `requested` False (quiet) always wins; None and True both mean "if the rule allows".
    """
    if requested is not None and not requested:
        return False
    stream = sys.stderr if stream is None else stream
    try:
        tty = bool(stream.isatty())
    except (AttributeError, ValueError):   # closed or replaced stream
        tty = False
    return tty and not os.environ.get("CI")
