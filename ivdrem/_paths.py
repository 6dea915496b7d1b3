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
import stat
import tempfile
from pathlib import Path

from ._atomic import write_text_atomic

__all__ = ["caller_cwd", "user_path", "OutputLocationError", "check_writable",
           "check_writable_file", "check_writable_dir", "check_replaceable", "write_text_or_keep",
           "InputFileError", "read_input_bytes", "not_a_regular_file", "STDOUT",
           "MAX_INPUT_BYTES"]

#: the path that means standard output, where a command can write a stream there
STDOUT = "-"
#: the most ivdrem reads of a file given to it (a configuration, a study, a JSON file it
#: may replace): no text it reads comes near this, and a device such as /dev/zero or a
#: runaway file is refused instead of read into memory
MAX_INPUT_BYTES = 16 * 2**20

CALLER_CWD_ENV = "IVDREM_CALLER_CWD"


class OutputLocationError(OSError):
    """An output location that cannot be written; the message names it."""


class InputFileError(OSError):
    """A file given to ivdrem that it will not read (not a regular file, too large); the
    message names it."""


_KINDS = ((stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
          (stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISSOCK, "a socket"),
          (stat.S_ISDIR, "a directory"))


def _kind(mode: int) -> str:
    for test, name in _KINDS:
        if test(mode):
            return name
    return "not a regular file"


def not_a_regular_file(path) -> str | None:
    """What `path` is when it exists and is not a regular file ("a character device", "a
    FIFO (named pipe)", ...), following symbolic links; None for a regular file or no file.
    Asked of the status only: such a file is never opened (a FIFO would block, /dev/zero
    never ends)."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return None
    return None if stat.S_ISREG(mode) else _kind(mode)


def read_input_bytes(path, what: str, limit: int = MAX_INPUT_BYTES) -> bytes:
    """The bytes of the regular file `path`, at most `limit` of them.

    Raises FileNotFoundError for no file, :class:`InputFileError` (naming `what` and the
    path) for a device, FIFO, socket or directory, or a file above `limit`, and OSError
    for one that cannot be read.  Opened without blocking (a FIFO with no writer would
    wait forever in a plain open()) and checked on the open descriptor, so what is read is
    what was checked."""
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0)
    fd = os.open(path, flags)
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise InputFileError(f"{what} {path} is {_kind(st.st_mode)}, not a regular file; "
                                 "ivdrem reads only regular files")
        if st.st_size > limit:
            raise InputFileError(f"{what} {path} has {st.st_size:,} bytes, more than the "
                                 f"{limit // 2**20} MiB ivdrem reads of such a file")
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)
        chunks, size = [], 0
        while size <= limit:
            chunk = os.read(fd, min(1 << 20, limit + 1 - size))
            if not chunk:
                break
            chunks.append(chunk)
            size += len(chunk)
        if size > limit:      # grew while read
            raise InputFileError(f"{what} {path} has more than the {limit // 2**20} MiB "
                                 "ivdrem reads of such a file")
        return b"".join(chunks)
    finally:
        os.close(fd)


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
    kind = not_a_regular_file(path)
    if kind is not None:   # os.replace would put a file in the device's place; never read
        raise OutputLocationError(
            f"{what} {path} is {kind}, not a regular file: ivdrem writes a new file and "
            "renames it over the old one, so it writes only to regular files; give a file "
            "name" + (f" (or {STDOUT} for standard output)" if what == "JSON file" else ""))
    if os.path.lexists(path) and not os.access(path, os.W_OK):
        raise OutputLocationError(f"{what} {path} exists and is not writable")
    check_writable(path.parent, what, target=path)
    return path


def _keep_text(path: Path, text: str) -> Path:
    """Write `text` to a new file next to `path` or, if that directory does not take it
    (full, read-only), in the temporary directory; a place that fails keeps no empty file."""
    name = path.name or "ivdrem-output"
    errors = []
    for d in (path.parent, Path(tempfile.gettempdir())):
        try:
            fd, tmp = tempfile.mkstemp(prefix=f"{name}.unsaved-", suffix=path.suffix, dir=d)
        except OSError as exc:
            errors.append(f"{d}: {exc.strerror or exc}")
            continue
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as f:
                f.write(text)
                f.flush()
                os.fsync(f.fileno())
        except OSError as exc:
            errors.append(f"{d}: {exc.strerror or exc}")
            Path(tmp).unlink(missing_ok=True)
            continue
        return Path(tmp)
    raise OSError(f"no writable place for the results of {path} ({'; '.join(errors)})")


def write_text_or_keep(path, text: str) -> tuple[Path, Exception | None]:
    """Write `text` to `path` atomically; if that fails, keep it in a new file next to
    `path` or in the temporary directory (``$TMPDIR``).

    Returns (where the text is, the error writing `path` or None).  Raises OSError only
    when no place takes it; no empty file is left anywhere.
    """
    path = Path(path)
    try:
        return write_text_atomic(path, text), None
    except OSError as exc:
        return _keep_text(path, text), exc


def check_replaceable(path, what: str, *, overwrite: bool, ours=None) -> Path:
    """The one rule for every output file: an existing file is replaced only if ivdrem
    wrote it (``ours(path)`` is true) or the user passed ``--overwrite``; otherwise
    :class:`OutputLocationError` before any work.  Also checks :func:`check_writable_file`."""
    path = check_writable_file(path, what)
    if os.path.lexists(path) and not overwrite and not (ours is not None and ours(path)):
        raise OutputLocationError(
            f"refusing to overwrite {path}: it exists and was not written by ivdrem; move it, "
            f"choose another name, or pass --overwrite")
    return path
