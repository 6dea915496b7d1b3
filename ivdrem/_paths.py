"""Paths the user gives on the command line, and checking output locations up front.

``./run`` changes into the clone before it starts ivdrem, so it exports the caller's
working directory as ``IVDREM_CALLER_CWD``; relative paths are the user's, resolved
against that directory (or the current one when it is not set), and printed absolute.

:func:`check_writable` probes an output location by creating and removing a file in it
(``os.access`` misses read-only mounts and immutable directories for root), so an unusable
location is refused before minutes of simulation.  :func:`write_text_or_keep` writes a
result and, if that still fails at the end, keeps it in a fallback file and says where.
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

from ._atomic import write_text_atomic

__all__ = ["caller_cwd", "user_path", "OutputLocationError", "check_writable",
           "check_writable_file", "check_writable_dir", "write_text_or_keep"]

CALLER_CWD_ENV = "IVDREM_CALLER_CWD"


class OutputLocationError(OSError):
    """An output location that cannot be written; the message names it."""


def caller_cwd() -> Path:
    """The directory the command was started from."""
    d = os.environ.get(CALLER_CWD_ENV)
    if d and os.path.isdir(d):
        return Path(d)
    return Path(os.getcwd())


def user_path(p) -> Path:
    """A command-line path as an absolute path, relative ones taken from :func:`caller_cwd`."""
    p = Path(os.path.expanduser(os.fspath(p)))
    if not p.is_absolute():
        p = caller_cwd() / p
    return Path(os.path.abspath(p))


def _nearest_existing(path: Path) -> Path:
    p = path
    while not os.path.lexists(p):
        if p.parent == p:
            break
        p = p.parent
    return p


def check_writable(directory, what: str, target=None) -> Path:
    """Raise :class:`OutputLocationError` unless files can be created in `directory` (or,
    if it does not exist yet, in its nearest existing ancestor, where it would be made).
    The message names `target` (default: `directory`) as the `what`."""
    directory = Path(directory)
    target = directory if target is None else Path(target)
    base = _nearest_existing(directory)
    if not base.is_dir():
        raise OutputLocationError(f"{what} {target} cannot be written: {base} is not a directory")
    try:
        fd, probe = tempfile.mkstemp(prefix=".ivdrem-write-probe.", dir=base)
    except OSError as exc:
        where = "" if base == target else f" (cannot create files in {base})"
        raise OutputLocationError(f"{what} {target} cannot be written{where}: "
                                  f"{exc.strerror or exc}") from None
    os.close(fd)
    os.unlink(probe)
    return directory


def check_writable_dir(directory, what: str) -> Path:
    """`directory` must be a directory (or not exist yet) that files can be created in."""
    directory = Path(directory)
    if os.path.lexists(directory) and not directory.is_dir():
        raise OutputLocationError(f"{what} {directory} is not a directory")
    return check_writable(directory, what)


def check_writable_file(path, what: str) -> Path:
    """`path` can be (re)placed atomically: its directory is writable, and it is not a
    directory nor an existing file that refuses writing (read-only, immutable)."""
    path = Path(path)
    if path.is_dir():
        raise OutputLocationError(f"{what} {path} is a directory; give a file name")
    if os.path.lexists(path) and not os.access(path, os.W_OK):
        raise OutputLocationError(f"{what} {path} exists and is not writable")
    check_writable(path.parent, what, target=path)
    return path


def fallback_path(path: Path) -> Path:
    """A new file for results that could not be written to `path`: next to it if that
    directory takes it, else in the temporary directory."""
    name = path.name or "ivdrem-output"
    for d in (path.parent, Path(tempfile.gettempdir())):
        try:
            fd, tmp = tempfile.mkstemp(prefix=f"{name}.unsaved-", suffix=path.suffix, dir=d)
        except OSError:
            continue
        os.close(fd)
        return Path(tmp)
    raise OSError(f"no writable place for the results of {path}")


def write_text_or_keep(path, text: str) -> tuple[Path, Exception | None]:
    """Write `text` to `path` atomically; if that fails, write it to a fallback file.

    Returns (where the text is, the error writing `path` or None).
    """
    path = Path(path)
    try:
        return write_text_atomic(path, text), None
    except OSError as exc:
        keep = fallback_path(path)
        keep.write_text(text, encoding="utf-8")
        return keep, exc
