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
import os
import sys
from contextlib import contextmanager
from functools import lru_cache
from pathlib import Path

import numpy as np

from . import __version__
from ._atomic import write_text_atomic
from ._cache_home import cache_dir   # noqa: F401 - one definition, read before numba loads

__all__ = ["cache_dir", "package_digest", "source_hash", "write_generated",
           "import_generated", "import_path", "compile_lock", "GENERATED_HEADER",
           "helpers_digest", "CacheFault", "guard_numba_index"]

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
    waits, then loads the machine code this one compiled."""
    if name in sys.modules:
        return sys.modules[name]
    path = write_generated(cdir, name, src)
    with compile_lock(path):
        return import_path(name, path)


class CacheFault(OSError):
    """A compile cache that cannot serve (full, damaged, no compiler): the message names the
    cache and the remedy, in one line."""


def guard_numba_index() -> None:
    """Make a damaged numba cache index (a truncated or garbled ``.nbi``: a disk that filled
    up, a copy cut short) a cache miss instead of a raw ``UnpicklingError`` deep inside a
    run: the file is removed, one line on stderr names it, and numba compiles that function
    again and writes a new index.  numba's own contract for a missing or stale index is the
    same empty answer.  Wraps ``numba.core.caching.IndexDataCacheFile._load_index`` (a
    private method, numba 0.59-0.61; tests/test_user_round_two.py garbles an index), once
    per process."""
    import pickle

    from numba.core import caching
    load = caching.IndexDataCacheFile._load_index
    if getattr(load, "_ivdrem", False):
        return

    def _load_index(self):
        try:
            return load(self)
        except (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError,
                ImportError, IndexError) as exc:
            path = getattr(self, "_index_path", "?")
            print(f"ivdrem: numba's cache index {path} was unreadable "
                  f"({type(exc).__name__}); removed it, compiling that function again",
                  file=sys.stderr, flush=True)
            try:
                os.unlink(path)
            except OSError:
                pass
            return {}
    _load_index._ivdrem = True
    caching.IndexDataCacheFile._load_index = _load_index


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


@contextmanager
def compile_lock(path):
    """An exclusive lock on the generated module at `path` in the cache directory, held
    while it is imported (numba compiles its kernels then, or loads them from its cache).

    The laws' loops share most kernels (plant, observer, filters): two study workers
    starting one law each on an empty cache compiled the shared ones twice, at once (28 s
    of compilation in all against 9 s for both laws in one process, measured).  With the
    lock the second worker waits for each shared module, then loads it.  An advisory
    ``flock`` on ``.NAME.lock`` beside the module, released when the process ends, however
    it ends; no lock where the cache cannot hold the lock file or flock does not exist."""
    try:
        import fcntl
    except ImportError:           # not a POSIX system: compiled twice at worst
        yield
        return
    path = Path(path)
    try:
        fd = os.open(path.with_name(f".{path.stem}.lock"), os.O_RDWR | os.O_CREAT, 0o644)
    except OSError:
        yield
        return
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)              # closing the descriptor releases the lock


#: the installed ivdrem package, whose sources key everything kept across processes
PACKAGE_ROOT = Path(__file__).resolve().parent


@lru_cache(maxsize=1)
def package_digest():
    """sha256 of every Python and C source of the installed ivdrem package (read once per
    process): a result on disk is reused only by the exact code that computed it; None
    where the sources cannot be read (nothing is then kept)."""
    h = hashlib.sha256(f"{__version__} {sys.version} {np.__version__}".encode())
    try:
        for f in sorted(PACKAGE_ROOT.rglob("*")):
            if f.suffix in (".py", ".c", ".h") and "__pycache__" not in f.parts:
                h.update(f.relative_to(PACKAGE_ROOT).as_posix().encode())
                h.update(f.read_bytes())
    except OSError:
        return None
    return h.hexdigest()
