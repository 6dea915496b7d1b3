"""The compile cache: where generated modules (robot models, block kernels, their
C-callable wrappers) and the C stepper's shared library live, and how a
generated module is written and imported.  A leaf below the models and the simulator: the
models' generated code, the compiled engine, the foreign-block adapter and the compile
child all use it without importing each other (docs/developers.md, "Layout").

A generated module is named by the hash of its source, written atomically (a concurrent
process never reads half a file) and imported from the cache directory; numba keeps its
machine code beside it (``cache=True``), so a second process loads instead of compiling.
"""
from __future__ import annotations

import hashlib
import importlib.util
import math
import os
import sys
from contextlib import contextmanager
from functools import lru_cache
from pathlib import Path

import numpy as np

from . import __version__
from ._atomic import write_text_atomic
from ._cache_home import cache_dir   # noqa: F401 - one definition, read before numba loads
from ._prebuilt import BUILD_ENV, guard_numba_index, prebuilt_module, sources_digest

__all__ = ["cache_dir", "package_digest", "source_hash", "write_generated",
           "import_generated", "import_path", "compile_lock", "GENERATED_HEADER",
           "helpers_digest", "CacheFault", "CompileLockTimeout", "guard_numba_index",
           "lock_wait_limit", "lock_holder", "LOCK_WAIT_S", "LOCK_NOTICE_S", "LOCK_WAIT_ENV",
           "prebuilt_module"]

#: the package files every generated module imports its helpers from
HELPER_FILES = ("blocks/_kernels.py", "_native_call.py")


def helpers_digest(root=Path(__file__).resolve().parent, files=HELPER_FILES):
    """Digest of the helpers' sources.  numba's cache notices a change in the file of a
    cached function only, not in a function of another file it calls and compiles in: the
    digest in every generated module's text (hence its name) makes such a change a new
    module, compiled afresh, where it would otherwise load machine code built from the old
    helpers."""
    h = hashlib.sha256()
    for rel in files:
        h.update(rel.encode() + b"\0" + (Path(root) / rel).read_bytes() + b"\0")
    return h.hexdigest()[:20]


#: the first lines of every generated kernel module: what a kernel may call
GENERATED_HEADER = [f"# helpers {helpers_digest()}", "import math", "import numpy as np",
                    "from numba import njit", "from ivdrem.blocks._kernels import *",
                    "from ivdrem._native_call import call_c"]




def source_hash(text):
    """The 20 hex digits that name a generated module after its source."""
    return hashlib.sha256(text.encode()).hexdigest()[:20]


def write_generated(cdir, name, src):
    """Path of module `name` in `cdir`, (re)written when its text differs from `src`."""
    path = Path(cdir) / f"{name}.py"
    if not path.exists() or path.read_text() != src:
        write_text_atomic(path, src)   # a concurrent process never sees half a file
    return path


def import_generated(cdir, name, src):
    """The module `name` of source `src`, written to `cdir` and imported (once per
    process); a module whose import failed is not left in sys.modules.  Imported under the
    module's lock (:func:`compile_lock`): another process importing it at the same time
    waits, then loads the machine code this one compiled.

    A module the prebuilt directory holds with the same text (``ivdrem._prebuilt``) is
    imported from there, with its machine code, and nothing is written; while the prebuild
    runs, modules are written into its staging directory instead of `cdir`."""
    if name in sys.modules:
        return sys.modules[name]
    prebuilt = prebuilt_module(name, src)
    if prebuilt is not None:
        return import_path(name, prebuilt)
    building = os.environ.get(BUILD_ENV)
    if building:
        cdir = Path(building) / "generated"
        cdir.mkdir(parents=True, exist_ok=True)
    path = write_generated(cdir, name, src)
    with compile_lock(path):
        return import_path(name, path)


class CacheFault(OSError):
    """A compile cache that cannot serve (full, damaged, no compiler): the message names the
    cache and the remedy, in one line."""


def import_path(name, path):
    """The module `name` of the Python file at `path`, imported once per process; a module
    whose import failed is not left in sys.modules.  (No lock: `path` may be a user's
    file, beside which nothing is written.)"""
    if name in sys.modules:
        return sys.modules[name]
    guard_numba_index()       # the module's numba kernels load their cached machine code
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    try:
        spec.loader.exec_module(mod)
    except BaseException:
        sys.modules.pop(name, None)
        raise
    return mod


#: Seconds a wait on a module's compile lock lasts before it says so (one line on stderr).
LOCK_NOTICE_S = 30.0

#: Seconds a wait on a module's compile lock lasts before it gives up
#: (:class:`CompileLockTimeout`); the environment variable :data:`LOCK_WAIT_ENV` sets
#: another.  As long as the compile child's own wait (``ivdrem/sim/_compile_child.py``): a
#: module numba takes longer than that to compile is not to be expected.
LOCK_WAIT_S = 900.0

#: The environment variable that sets the limit of a wait on a compile lock, in seconds.
LOCK_WAIT_ENV = "IVDREM_LOCK_WAIT_S"


class CompileLockTimeout(CacheFault):
    """A wait on a generated module's compile lock that lasted past its limit (a process
    holding it forever: a stuck compile, a hung network file system); the message names the
    lock file, its holder when known, and what to do."""


def lock_wait_limit() -> float:
    """The limit of a wait on a compile lock: ``$IVDREM_LOCK_WAIT_S`` if set, else
    :data:`LOCK_WAIT_S`; a value that is not a number of seconds > 0 is refused, naming
    the variable."""
    raw = os.environ.get(LOCK_WAIT_ENV, "").strip()
    if not raw:
        return LOCK_WAIT_S
    try:
        value = float(raw)
    except ValueError:
        value = math.nan
    if not value > 0:                  # NaN too
        raise CacheFault(f"{LOCK_WAIT_ENV} = {raw!r}: must be a number of seconds > 0 (how "
                         f"long to wait for another process compiling the same module; "
                         f"default {LOCK_WAIT_S:g})")
    return value


def _process(pid) -> str:
    """``process PID (its command line, shortened)``; only the number where /proc does not
    say (another system, another machine's process)."""
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            argv = [a.decode(errors="replace") for a in f.read().split(b"\0") if a]
        with open(f"/proc/{pid}/stat") as f:
            ppid = int(f.read().rsplit(")", 1)[1].split()[1])
    except (OSError, ValueError, IndexError):
        return f"process {pid}"
    if "-c" in argv:                   # a program given inline: its name, not its text
        i = argv.index("-c")
        argv = argv[:i + 1] + ["..."] + argv[i + 2:]
    text = " ".join(argv)
    text = text if len(text) <= 120 else text[:117] + "..."
    mine = "" if ppid != os.getpid() else (
        ", this process's compile child" if "--modules" in argv else ", a child of this process")
    return f"process {pid} ({text}{mine})"


def lock_holder(fd):
    """Who holds the flock on the open file ``fd``: "process PID (command)" from the
    kernel's table of locks (/proc/locks, Linux), else from the line the holder wrote into
    the lock file (``PID HOST``), else None."""
    try:
        st = os.fstat(fd)
        dev = f"{os.major(st.st_dev):02x}:{os.minor(st.st_dev):02x}:{st.st_ino}"
        with open("/proc/locks") as f:
            for line in f:
                words = line.split()
                # "1: FLOCK  ADVISORY  WRITE 1234 fe:00:5678 0 EOF"; "1: -> FLOCK ..." waits
                if len(words) > 5 and words[1] == "FLOCK" and words[5] == dev:
                    return _process(int(words[4]))
    except (OSError, ValueError):
        pass
    try:
        pid, host = os.pread(fd, 200, 0).decode(errors="replace").split()[:2]
        int(pid)
    except (OSError, ValueError):
        return None
    import socket
    here = host == socket.gethostname()
    return _process(pid) if here else f"process {pid} on {host}"


def _take_lock(lock, limit, notice):
    """The descriptor of the lock file ``lock`` with its flock taken, polling (a blocking
    flock cannot be given a limit): one line on stderr once the wait lasts ``notice`` s,
    naming the file and its holder; :class:`CompileLockTimeout` after ``limit`` s.  A lock
    file deleted while waited for (as the message after the limit suggests) is created
    again and taken.  Ctrl-C stops the wait.  OSError: the file cannot be opened."""
    import fcntl
    import time
    fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        t0 = time.monotonic()
        pause, said = 0.001, False
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                return fd
            except BlockingIOError:
                pass
            waited = time.monotonic() - t0
            if waited >= limit:
                holder = lock_holder(fd)
                raise CompileLockTimeout(
                    f"gave up after {waited:.0f} s waiting for the compile lock {lock} of "
                    f"{lock.name[1:-5]}.py, held by {holder or 'another process'}: if that "
                    f"process is stuck, end it"
                    f"{f' (kill {holder.split()[1]})' if holder else ''}; if none is running "
                    f"(a hung network file system, a process on another machine), delete "
                    f"{lock}; {LOCK_WAIT_ENV} sets how long to wait (now {limit:g} s)")
            if not said and waited >= notice:
                said = True
                holder = lock_holder(fd)
                print(f"ivdrem: waiting {waited:.0f} s so far for the compile lock {lock} of "
                      f"{lock.name[1:-5]}.py, held by {holder or 'another process'}; giving "
                      f"up after {limit:g} s ({LOCK_WAIT_ENV})", file=sys.stderr, flush=True)
            time.sleep(min(pause, max(0.0, limit - waited)))
            pause = min(2 * pause, 0.02)      # a released lock is taken within 20 ms
            if not _same_file(fd, lock):      # deleted (or replaced) while waited for
                os.close(fd)
                fd = -1
                fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
    except BaseException:
        if fd >= 0:
            os.close(fd)
        raise


def _same_file(fd, path) -> bool:
    try:
        a, b = os.fstat(fd), os.stat(path)
    except OSError:
        return False
    return (a.st_dev, a.st_ino) == (b.st_dev, b.st_ino)


@contextmanager
def compile_lock(path, *, limit=None, notice=LOCK_NOTICE_S):
    """An exclusive lock on the generated module at `path` in the cache directory, held
    while it is imported (numba compiles its kernels then, or loads them from its cache).

    The laws' loops share most kernels (plant, observer, filters): two study workers
    starting one law each on an empty cache compiled the shared ones twice, at once (28 s
    of compilation in all against 9 s for both laws in one process, measured).  With the
    lock the second worker waits for each shared module, then loads it.  An advisory
    ``flock`` on ``.NAME.lock`` beside the module, released when the process ends, however
    it ends; no lock where the cache cannot hold the lock file or flock does not exist.
    The holder writes ``PID HOST`` into the file (read where /proc/locks does not say).

    A wait that lasts ``notice`` seconds says so in one line on stderr (the lock file and
    the process holding it); one that lasts ``limit`` seconds (default
    :func:`lock_wait_limit`: ``$IVDREM_LOCK_WAIT_S`` or :data:`LOCK_WAIT_S`) raises
    :class:`CompileLockTimeout`, naming the lock file and what to do: a process holding a
    lock forever blocked every later run silently."""
    try:
        import fcntl  # noqa: F401 - the lock exists here
    except ImportError:           # not a POSIX system: compiled twice at worst
        yield
        return
    limit = lock_wait_limit() if limit is None else float(limit)
    path = Path(path)
    try:
        fd = _take_lock(path.with_name(f".{path.stem}.lock"), limit, notice)
    except CompileLockTimeout:
        raise
    except OSError:               # the cache cannot hold the lock file
        yield
        return
    try:
        _say_holder(fd)
        yield
    finally:
        os.close(fd)              # closing the descriptor releases the lock


def _say_holder(fd):
    """Write ``PID HOST`` into the lock file just taken (who holds it, where /proc/locks
    does not say: another system, a network file system); a file that cannot be written
    (a read-only cache) only loses the name."""
    import socket
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()} {socket.gethostname()}\n".encode(), 0)
    except OSError:
        pass


#: the installed ivdrem package, whose sources key everything kept across processes
PACKAGE_ROOT = Path(__file__).resolve().parent


@lru_cache(maxsize=1)
def package_digest():
    """sha256 of every Python and C source of the installed ivdrem package (read once per
    process): a result on disk is reused only by the exact code that computed it; None
    where the sources cannot be read (nothing is then kept)."""
    return sources_digest(f"{__version__} {sys.version} {np.__version__}")
