"""The prebuilt machine code: ivdrem's own numba functions compiled once at set-up, into a
directory of the installation, and loaded from there by every run whose user cache does not
hold them yet (docs/developers.md, "The prebuilt machine code"; made by
``python -m ivdrem.cli.prebuild``).

numba types do not carry array sizes, so the machine code of ivdrem's package functions
(``blocks/_kernels.py``, ``models/_rigid_body_jit.py``, ...) does not depend on the arm: a
run on a small arm compiles exactly what the Panda's first run asks for.  Where it lives::

    <sys.prefix>/share/ivdrem/prebuilt/<key>/    ($IVDREM_PREBUILT_DIR/<key> if set)
        numba/ivdrem/<package folder>/           numba's index (.nbi) and code (.nbc) files
        generated/<module>.py                    generated modules (named by their text's hash)
        numba/generated/                         their machine code

``<key>`` digests ivdrem's whole source, Python's, NumPy's and numba's versions
(:func:`prebuilt_key`): an edited checkout never loads stale code, and another key's
directory is ignored.  The directory is made complete elsewhere and renamed into place, so a
directory that exists is whole.

How numba is told (written and tested against numba 0.68.1's ``numba/core/caching.py``): one
place, :func:`numba_loaded`, run once when ``numba.core.caching`` is imported (the import hook
of :func:`install_numba_hook`, set by ``ivdrem/__init__.py`` before anything imports numba):

- a cache locator (:class:`PrebuiltLocator` from :func:`_locator_class`), first in
  ``CacheImpl._locator_classes``, for functions of ivdrem's package files and of the
  prebuilt's generated modules: it keeps numba's own choice of a cache directory (the user's
  cache, ``$IVDREM_CACHE_DIR/numba``) and adds the prebuilt one, read only.  While the
  prebuild runs (``$IVDREM_PREBUILD_INTO`` names its staging directory) it writes there;
- ``Cache._load_overload`` (private) reads the user's cache first, then the prebuilt's; a
  function the prebuilt does not hold (another signature) compiles and is saved into the
  user's cache as before: nothing is ever written into the prebuilt directory at run time;
- a damaged index (``IndexDataCacheFile._load_index``) is a cache miss, not a crash
  (:func:`guard_numba_index`).
Another numba that moved these internals only loses the prebuilt: runs compile as before.
"""
from __future__ import annotations

import hashlib
import os
import sys
from functools import lru_cache
from pathlib import Path

__all__ = ["PACKAGE_ROOT", "PREBUILT_ENV", "BUILD_ENV", "sources_digest", "prebuilt_key",
           "prebuilt_root", "prebuilt_dir", "install_numba_hook", "numba_loaded",
           "guard_numba_index", "prebuilt_module"]

#: the installed ivdrem package
PACKAGE_ROOT = Path(__file__).resolve().parent

#: The environment variable naming the folder that holds the prebuilt directories (default
#: ``<sys.prefix>/share/ivdrem/prebuilt``); empty: no prebuilt is used.
PREBUILT_ENV = "IVDREM_PREBUILT_DIR"

#: Set by the prebuild for its run: the staging directory numba writes ivdrem's functions to.
BUILD_ENV = "IVDREM_PREBUILD_INTO"


def sources_digest(prefix: str):
    """sha256 of `prefix` and every Python and C source of the installed ivdrem package
    (paths and bytes); None where a source cannot be read."""
    h = hashlib.sha256(prefix.encode())
    try:
        for f in sorted(PACKAGE_ROOT.rglob("*")):
            if f.suffix in (".py", ".c", ".h") and "__pycache__" not in f.parts:
                h.update(f.relative_to(PACKAGE_ROOT).as_posix().encode())
                h.update(f.read_bytes())
    except OSError:
        return None
    return h.hexdigest()


@lru_cache(maxsize=1)
def prebuilt_key():
    """The name of the prebuilt directory this installation loads: 24 hex digits of its
    sources and of the Python, NumPy and numba it runs on (numba's own index keys the
    machine code by numba's version and the CPU, not NumPy's); None where the sources
    cannot be read or numba is missing."""
    try:
        from importlib.metadata import version
        versions = f"python {sys.version} numpy {version('numpy')} numba {version('numba')}"
    except Exception:                 # not installed as distributions: no prebuilt
        return None
    digest = sources_digest(f"ivdrem prebuilt {versions}")
    return None if digest is None else digest[:24]


def prebuilt_root() -> Path | None:
    """The folder of the prebuilt directories: ``$IVDREM_PREBUILT_DIR`` if set (empty:
    None, no prebuilt), else ``<sys.prefix>/share/ivdrem/prebuilt``."""
    d = os.environ.get(PREBUILT_ENV)
    if d is not None:
        return Path(d) if d else None
    return Path(sys.prefix) / "share" / "ivdrem" / "prebuilt"


def prebuilt_dir() -> Path | None:
    """This installation's prebuilt directory if it exists (complete: it was renamed into
    place whole), else None.  Not while a prebuild runs (it makes it)."""
    root, key = prebuilt_root(), prebuilt_key()
    if root is None or key is None or os.environ.get(BUILD_ENV):
        return None
    d = root / key
    return d if d.is_dir() else None


def prebuilt_module(name: str, src: str) -> Path | None:
    """The prebuilt copy of the generated module `name` when the prebuilt holds it with the
    text `src` (its machine code then loads from there), else None."""
    d = prebuilt_dir()
    if d is None:
        return None
    path = d / "generated" / f"{name}.py"
    try:
        return path if path.read_text() == src else None
    except OSError:
        return None


# ------------------------------------------------------------------------ numba's side
class _AfterImport:
    """A finder on ``sys.meta_path`` that runs `then(module)` once the module `name` has
    been executed (the first import of numba's cache machinery), then leaves the path."""

    def __init__(self, name, then):
        self.name, self.then = name, then

    def find_spec(self, fullname, path, target=None):
        if fullname != self.name:
            return None
        if self in sys.meta_path:
            sys.meta_path.remove(self)
        from importlib.machinery import PathFinder
        spec = PathFinder.find_spec(fullname, path, target)
        if spec is None or not hasattr(spec.loader, "exec_module"):
            return spec
        run, then = spec.loader.exec_module, self.then

        def exec_module(module):
            run(module)
            then(module)
        spec.loader.exec_module = exec_module
        return spec


def install_numba_hook() -> None:
    """Have :func:`numba_loaded` run when numba's cache machinery is imported (now, if it
    already is).  Imports nothing heavy: ``import ivdrem`` stays light."""
    name = "numba.core.caching"
    if name in sys.modules:
        numba_loaded(sys.modules[name])
    elif not any(isinstance(f, _AfterImport) for f in sys.meta_path):
        sys.meta_path.insert(0, _AfterImport(name, numba_loaded))


def numba_loaded(caching) -> None:
    """Teach numba's cache (the module ``numba.core.caching``) the prebuilt directory and
    the guard of damaged indexes (the module docstring); once per process.  numba internals
    that moved leave numba as it is (runs compile as before)."""
    if getattr(caching, "_ivdrem_prebuilt", False):
        return
    caching._ivdrem_prebuilt = True
    try:
        impl = getattr(caching, "CacheImpl", None) or caching._CacheImpl
        impl._locator_classes.insert(0, _locator_class(caching, impl))
        _read_prebuilt_after_user_cache(caching)
    except Exception:                 # pragma: no cover - numba internals moved
        pass
    guard_numba_index(caching)


def _subpath(py_file):
    """Where the machine code of a function of the file `py_file` goes inside a prebuilt
    directory: ``numba/ivdrem/<folder>`` for ivdrem's package files, ``numba/generated``
    for a generated module in the prebuilt's (or, in a prebuild, the staging directory's)
    ``generated``; None for any other file."""
    try:
        path = Path(os.path.realpath(py_file))
    except (OSError, ValueError, TypeError):
        return None
    if path.is_relative_to(PACKAGE_ROOT):
        return Path("numba", "ivdrem", *path.parent.relative_to(PACKAGE_ROOT).parts)
    building = os.environ.get(BUILD_ENV)
    home = Path(os.path.realpath(building)) if building else prebuilt_dir()
    if home is not None and path.parent == Path(os.path.realpath(home)) / "generated":
        return Path("numba", "generated")
    return None


def _locator_class(caching, impl):
    """numba's cache locator for ivdrem's functions (see the module docstring)."""

    class PrebuiltLocator(caching._CacheLocator):
        """ivdrem's function: numba's own cache directory (the user's), plus
        ``prebuilt_path`` read after it; in a prebuild, the staging directory alone."""

        def __init__(self, inner, cache_path, prebuilt_path):
            self._inner = inner                   # numba's own locator, or None (prebuild)
            self._cache_path = cache_path
            self.prebuilt_path = prebuilt_path
            self._py_file = inner._py_file if inner is not None else None
            self._lineno = inner._lineno if inner is not None else None

        @classmethod
        def from_function(cls, py_func, py_file):
            sub = _subpath(py_file)
            if sub is None:
                return None
            building = os.environ.get(BUILD_ENV)
            if building:
                self = cls(None, str(Path(building) / sub), None)
                self._py_file, self._lineno = py_file, py_func.__code__.co_firstlineno
                try:
                    self.ensure_cache_path()
                except OSError:
                    return None
                return self
            pre = prebuilt_dir()
            if pre is None:
                return None                       # numba's own choice, unchanged
            for other in impl._locator_classes:
                if other is not cls:
                    inner = other.from_function(py_func, py_file)
                    if inner is not None:
                        return cls(inner, inner.get_cache_path(), str(pre / sub))
            return None

        def ensure_cache_path(self):
            if self._inner is not None:
                return self._inner.ensure_cache_path()
            return super().ensure_cache_path()

        def get_cache_path(self):
            return self._cache_path

        def get_source_stamp(self):             # the file's content hash (numba >= 0.62)
            if self._inner is not None:
                return self._inner.get_source_stamp()
            return caching._SourceFileBackedLocatorMixin.get_source_stamp(self)

        def get_disambiguator(self):
            return str(self._lineno)

    return PrebuiltLocator


def _read_prebuilt_after_user_cache(caching):
    """``Cache._load_overload``: the user's cache, then the prebuilt's (read only)."""
    load = caching.Cache._load_overload
    index_file = _read_only_index_class(caching)

    def _load_overload(self, sig, target_context):
        data = load(self, sig, target_context)
        pre = getattr(self._impl.locator, "prebuilt_path", None)
        if data is not None or pre is None or not self._enabled:
            return data
        files = self.__dict__.get("_ivdrem_prebuilt")
        if files is None:
            files = self._ivdrem_prebuilt = index_file(
                cache_path=pre, filename_base=self._impl.filename_base,
                source_stamp=self._cache_file._source_stamp)
        data = files.load(self._index_key(sig, target_context.codegen()))
        return None if data is None else self._impl.rebuild(target_context, data)

    caching.Cache._load_overload = _load_overload


def _read_only_index_class(caching):
    """numba's index and data files of the prebuilt directory: read, never written; an index
    that cannot be read is a miss (one line on stderr), and is left where it is."""

    class PrebuiltIndex(caching.IndexDataCacheFile):
        def _load_index(self):
            load = caching.IndexDataCacheFile._load_index
            try:
                return getattr(load, "__wrapped__", load)(self)
            except _UNREADABLE as exc:
                print(f"ivdrem: the prebuilt index {self._index_path} is unreadable "
                      f"({type(exc).__name__}); compiling that function into the user cache "
                      f"(python -m ivdrem.cli.prebuild makes the prebuilt again)",
                      file=sys.stderr, flush=True)
                return {}

        def save(self, key, data):      # pragma: no cover - never called (read only)
            raise PermissionError(f"the prebuilt directory {self._cache_path} is read only")

    return PrebuiltIndex


_UNREADABLE = (__import__("pickle").UnpicklingError, EOFError, ValueError, TypeError,
               AttributeError, ImportError, IndexError)


def guard_numba_index(caching=None) -> None:
    """Make a damaged numba cache index (a truncated or garbled ``.nbi``: a disk that filled
    up, a copy cut short) a cache miss instead of a raw ``UnpicklingError`` deep inside a
    run: the file is removed, one line on stderr names it, and numba compiles that function
    again and writes a new index.  numba's own contract for a missing or stale index is the
    same empty answer.  Wraps ``numba.core.caching.IndexDataCacheFile._load_index`` (a
    private method, numba 0.59-0.68; tests/test_user_round_two.py garbles an index), once
    per process."""
    if caching is None:
        from numba.core import caching
    load = caching.IndexDataCacheFile._load_index
    if getattr(load, "_ivdrem", False):
        return

    def _load_index(self):
        try:
            return load(self)
        except _UNREADABLE as exc:
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
    _load_index.__wrapped__ = load
    caching.IndexDataCacheFile._load_index = _load_index
