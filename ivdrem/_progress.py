"""When to show a progress bar or a note on long preparation: one rule for every bar and
note ivdrem draws.

A bar is drawn only when stderr is a terminal, the environment variable ``CI`` is not set
and the caller did not ask for quiet (``--quiet``, ``progress=False``).  A bar in a
redirected stderr is noise in a log file; CI systems often give a pseudo-terminal.

A *note* (:func:`note`, :func:`preparing`) is one line on stderr saying what a long
preparation step is doing (generating a model's code, compiling it) and that its result is
cached; it follows the same rule, and a command's ``--quiet`` silences it for the whole
process (:func:`set_quiet`).

Off a terminal (a log file, a pipe; not in CI, not with ``--quiet``) a step that is still
running after :data:`SLOW_STEP_S` seconds says so in one line, and again when it is done:
a log shows what a minute of compiling was, and a quick step adds nothing to it.
"""
from __future__ import annotations

import os
import sys
import time
from contextlib import contextmanager

__all__ = ["want_progress", "set_quiet", "note", "preparing"]

#: set by a command's --quiet: no notes for the rest of the process
_quiet = False


def want_progress(requested=None, stream=None) -> bool:
    """True if a progress bar should be drawn on `stream` (default ``sys.stderr``).

    `requested` False (quiet) always wins, and so does a command's ``--quiet``
    (:func:`set_quiet`) for every bar of the command; None and True both mean "if the rule
    allows".
    """
    if _quiet or (requested is not None and not requested):
        return False
    stream = sys.stderr if stream is None else stream
    try:
        tty = bool(stream.isatty())
    except (AttributeError, ValueError):   # closed or replaced stream
        tty = False
    return tty and not os.environ.get("CI")


def set_quiet(quiet: bool = True) -> None:
    """Silence (or allow again) every note of this process (a command's ``--quiet``)."""
    global _quiet
    _quiet = bool(quiet)


def note(message: str, stream=None) -> bool:
    """Print ``ivdrem: message`` on `stream` (default stderr) if the rule allows a bar
    there and no ``--quiet`` was given; returns whether it was printed."""
    stream = sys.stderr if stream is None else stream
    if _quiet or not want_progress(stream=stream):
        return False
    print(f"ivdrem: {message}", file=stream, flush=True)
    return True


#: Seconds after which a preparation step still running says so off a terminal.
SLOW_STEP_S = 5.0


@contextmanager
def preparing(what: str, cached_in=None, stream=None, *, only_if_slow=False):
    """A long preparation step: a note before it (what, and where its result is cached)
    and one after it with its wall time; off a terminal (or with `only_if_slow`, for a
    step that is often quick: loading compiled code from the cache) the same two lines
    only if the step lasts longer than :data:`SLOW_STEP_S`."""
    import threading
    stream = sys.stderr if stream is None else stream
    where = f"; cached in {cached_in} for later runs" if cached_in is not None else ""
    shown = False if only_if_slow else note(f"{what}{where} ...", stream=stream)
    t0 = time.perf_counter()
    late = []
    timer = None
    if not shown and not _quiet and not os.environ.get("CI"):
        def say_late():
            late.append(True)
            print(f"ivdrem: {what}{where} (running for {SLOW_STEP_S:g} s) ...", file=stream,
                  flush=True)
        timer = threading.Timer(SLOW_STEP_S, say_late)
        timer.daemon = True
        timer.start()
    try:
        yield
    finally:
        if timer is not None:
            timer.cancel()
    if shown:
        note(f"{what}: done in {time.perf_counter() - t0:.1f} s", stream=stream)
    elif late:
        print(f"ivdrem: {what}: done in {time.perf_counter() - t0:.1f} s", file=stream,
              flush=True)
