"""Writing files so that a reader never sees half of one: a temporary file next to the
target, then ``os.replace``.  Used by the report, ``ivdrem paper --json`` and the
compiled-code cache."""
from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager
from pathlib import Path

__all__ = ["new_tempfile", "remove_stale_tempfiles", "fsync_file", "write_text_atomic",
           "written_together", "zip_tree_atomic", "os_error_behind"]


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True    # exists (another user's), or cannot tell: keep its file
    return True


def remove_stale_tempfiles(directory, name: str) -> None:
    """Remove the temporaries of `name` left in `directory` by a process that was killed
    before it could (``.NAME.PID.*.tmp`` whose PID is no longer running)."""
    try:
        entries = list(Path(directory).glob(f".{name}.*.tmp"))
    except OSError:
        return
    for p in entries:
        pid = p.name[len(name) + 2:].split(".", 1)[0]
        if pid.isdigit() and int(pid) != os.getpid() and not _pid_alive(int(pid)):
            try:
                p.unlink()
            except OSError:
                pass


def new_tempfile(directory, name: str) -> Path:
    """A new hidden file ``.NAME.PID.*.tmp`` in `directory`, with the mode a plain open()
    would give (mkstemp alone would leave it 0600).  The PID in its name lets a later
    write remove what a killed process left behind."""
    remove_stale_tempfiles(directory, name)
    fd, tmp = tempfile.mkstemp(prefix=f".{name}.{os.getpid()}.", suffix=".tmp", dir=directory)
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


def write_file_atomic(path, write) -> Path:
    """Write `path` atomically by `write(binary file)`; on any error the old file stays."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = new_tempfile(path.parent, path.name)
    try:
        with open(tmp, "wb") as fh:
            write(fh)
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


def zip_tree_atomic(root, path) -> Path:
    """Zip every file under `root` (paths relative to it, sorted) into `path`: a hidden
    temporary next to the target, then os.replace, so a reader never sees half an archive
    (an FMU) and a failure leaves neither a partial archive nor the temporary behind."""
    import zipfile
    root, path = Path(root), Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = new_tempfile(path.parent, path.name)
    try:
        with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as zf:
            for p in sorted(root.rglob("*")):
                if p.is_file():
                    zf.write(p, p.relative_to(root).as_posix())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def os_error_behind(exc):
    """The OSError that caused `exc` (itself, or one in its chain), or None: matplotlib's
    PDF writer, closing a file on a full disk, raises zlib.error on top of the OSError
    (ENOSPC) that stopped it."""
    while exc is not None:
        if isinstance(exc, OSError):
            return exc
        exc = exc.__cause__ or exc.__context__
    return None
