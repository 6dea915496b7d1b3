"""Writing files so that a reader never sees half of one: a temporary file next to the
target, then ``os.replace``.  Used by the report, ``ivdrem paper --json`` and the
compiled-code cache."""
from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager
from pathlib import Path

__all__ = ["new_tempfile", "fsync_file", "write_text_atomic", "written_together"]


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def new_tempfile(directory, name: str) -> Path:
    """A new hidden file in `directory`, with the mode a plain open() would give
    (mkstemp alone would leave it 0600)."""
    fd, tmp = tempfile.mkstemp(prefix=f".{name}.", suffix=".tmp", dir=directory)
    try:
        os.fchmod(fd, 0o666 & ~_umask())
    except (AttributeError, OSError):  # pragma: no cover - platforms without fchmod
        pass
    os.close(fd)
    return Path(tmp)


def fsync_file(path) -> None:
    """Flush a written file to disk before it replaces the old one (best effort)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def write_text_atomic(path, text: str) -> Path:
    """Write `text` to `path` atomically; on any error the old file stays as it was."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = new_tempfile(path.parent, path.name)
    try:
        tmp.write_text(text, encoding="utf-8")
        fsync_file(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


@contextmanager
def written_together(*targets):
    """Temporaries next to each target, yielded as a tuple; on normal exit each is flushed
    and replaces its target (in order); on any error no target is touched, and no
    temporary is left behind either way."""
    temps = []
    try:
        for target in targets:
            target = Path(target)
            temps.append(new_tempfile(target.parent, target.name))
        yield tuple(temps)
        for tmp in temps:
            fsync_file(tmp)
        for tmp, target in zip(temps, targets):
            os.replace(tmp, target)
    finally:
        for tmp in temps:
            try:
                tmp.unlink(missing_ok=True)
            except OSError:
                pass
