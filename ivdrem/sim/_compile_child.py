"""The compile child: a second process that compiles kernel wrappers while this one builds
the diagram's tables and compiles the others.

numba compiles under one process-wide lock, so a thread cannot overlap the first compiled
run's kernels and wrappers; a child process can.  The child imports, and so compiles into
numba's cache, the generated modules the parent has written to the cache directory and
given it (:func:`start_modules`: the compiled engine gives it every wrapper not cached yet,
before its sparsity probe); the parent, its tables built, takes the child's list back from
the end (each module under its lock: loaded from the cache if the child has compiled it),
then :meth:`Warmup.wait` s for the child.  Any failure of the child only costs the
overlap: the parent then compiles that work itself.  ``IVDREM_COMPILE_CHILD=0`` (or the older ``IVDREM_STEPPER_PREFETCH=0``) turns
it off.
"""
from __future__ import annotations

import atexit
import os
import subprocess
import sys
import types
from pathlib import Path

from ..compile_cache import cache_dir, compile_lock, import_path, prebuilt_module

_CHILD_ENV = "IVDREM_STEPPER_CHILD"
_SWITCH_ENVS = ("IVDREM_COMPILE_CHILD", "IVDREM_STEPPER_PREFETCH")
#: how long the parent waits for the child before compiling the child's work itself
WAIT_LIMIT_S = 900.0


def enabled() -> bool:
    """Whether this process may start a child: it is not one itself, the switch is not
    off, and numba compiles (and so caches) at all."""
    return not (os.environ.get(_CHILD_ENV)
                or any(os.environ.get(k, "1") == "0" for k in _SWITCH_ENVS)
                or os.environ.get("NUMBA_DISABLE_JIT", "0") not in ("", "0"))


def index_exists(cache) -> bool:
    """Whether numba's index file of a function's on-disk cache (a dispatcher's or a
    ``cfunc``'s ``_cache``, a :class:`numba.core.caching.FunctionCache`) exists, in the
    user's cache or in the prebuilt directory (``ivdrem._prebuilt``)."""
    name = cache._cache_file._index_name
    prebuilt = getattr(cache._impl.locator, "prebuilt_path", None)
    return any((Path(d) / name).exists() for d in (cache._cache_path, prebuilt) if d)


def function_cached(path, qualname) -> bool:
    """Whether numba's on-disk cache holds the top-level function `qualname` of the source
    file `path`, decided without importing the file (importing a ``cfunc`` compiles it):
    numba's cache for a stand-in function with the same code location.  Unknown (numba
    internals moved, no cache possible) counts as cached."""
    try:
        from numba.core.caching import FunctionCache
        text = Path(path).read_text()
        if prebuilt_module(Path(path).stem, text) is not None:
            return True            # imported from the prebuilt, with its machine code
        code = compile(text, str(path), "exec")
        fcode = next(c for c in code.co_consts
                     if isinstance(c, types.CodeType) and c.co_name == qualname)
        return index_exists(FunctionCache(types.FunctionType(fcode, {})))
    except Exception:        # pragma: no cover - numba internals changed
        return True


class Warmup:
    """A running child (or nothing to wait for); `modules` names what it compiles."""

    def __init__(self, proc=None, modules=()):
        self.proc = proc
        self.modules = list(modules)

    def wait(self, limit=WAIT_LIMIT_S):
        """Wait for the child (at most `limit` seconds); True if it finished cleanly."""
        if self.proc is None:
            return False
        try:
            rc = self.proc.wait(timeout=limit)
        except subprocess.TimeoutExpired:
            self.cancel()
            rc = None
        except BaseException:
            self.cancel()               # interrupted: do not leave the child running
            raise
        finally:
            self.proc = None
        return rc == 0

    def cancel(self):
        """Kill the child (the parent failed or was interrupted) and reap it."""
        proc, self.proc = self.proc, None
        if proc is not None:
            proc.kill()
            proc.wait()


# the child's program: its job (:func:`_job`) with this process's ivdrem first on the path,
# and ivdrem.sim and ivdrem.blocks bare packages: the generated modules import only
# ivdrem.blocks._kernels and ivdrem._native_call, and the packages' own imports
# (python-control, SciPy, matplotlib) would cost the child ~2 s
_BOOT = """\
import os, sys, types
root = sys.argv.pop(1)
sys.path.insert(0, root)
for pkg in ("ivdrem.sim", "ivdrem.blocks"):
    sys.modules[pkg] = types.ModuleType(pkg)
    sys.modules[pkg].__path__ = [os.path.join(root, *pkg.split("."))]
from ivdrem.sim._compile_child import _job
sys.exit(_job(sys.argv[1:]))
"""


def start_modules(names) -> Warmup:
    """Launch the child importing the generated modules `names` (in that order; their
    sources already written to the cache directory), unless :func:`enabled` says no."""
    if not names or not enabled():
        return Warmup()
    env = dict(os.environ)
    env[_CHILD_ENV] = "1"
    env["IVDREM_CACHE_DIR"] = str(cache_dir())
    root = str(Path(__file__).resolve().parents[2])   # the same ivdrem in the child
    try:
        proc = subprocess.Popen([sys.executable, "-c", _BOOT, root, "--modules", *names],
                                env=env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)
    except OSError:                # pragma: no cover - cannot start a process here
        return Warmup()
    return Warmup(proc, names)


#: helper children running (:func:`start_helpers`), joined by :func:`join_helpers`
_HELPERS: list = []


def start_helpers(entries) -> Warmup:
    """Launch a child compiling mixing functions into numba's cache, `entries` [(name, variant
    code)] of :func:`ivdrem.blocks._kernels.compile_variant` not cached yet, while this process
    does other work (γ "auto"'s estimate, then the loop's set-up): the compiled engine
    :func:`join_helpers` before its probe and wrappers, which then load them."""
    from ..blocks import _kernels
    todo = [(name, int(code)) for name, code in entries
            if not index_exists(getattr(_kernels, name).variants[int(code)]._cache)]
    if not todo or not enabled():
        return Warmup()
    env = dict(os.environ)
    env[_CHILD_ENV] = "1"
    env["IVDREM_CACHE_DIR"] = str(cache_dir())
    root = str(Path(__file__).resolve().parents[2])
    try:
        proc = subprocess.Popen([sys.executable, "-c", _BOOT, root, "--helpers",
                                 *(f"{name}:{code}" for name, code in todo)],
                                env=env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)
    except OSError:                # pragma: no cover - cannot start a process here
        return Warmup()
    if not _HELPERS:
        atexit.register(_cancel_helpers)     # a process that ends first does not leave it
    warmup = Warmup(proc, [f"{name}:{code}" for name, code in todo])
    _HELPERS.append(warmup)
    return warmup


def join_helpers(limit=WAIT_LIMIT_S):
    """Wait for the helper children (:func:`start_helpers`): what they compiled is then in
    numba's cache, whatever else this process does meanwhile (the probe's way for a block
    reads that cache, and must not depend on how far a child has come)."""
    while _HELPERS:
        _HELPERS.pop().wait(limit)


def _cancel_helpers():
    while _HELPERS:
        _HELPERS.pop().cancel()


def _job(argv):
    """The child's job: ``--modules name ...``, import the modules, in order, from the cache
    directory the parent has written them to (what compiled._import does, without
    importing the compiled engine); ``--helpers name:code ...``, compile those variants of
    the mixing functions (:func:`ivdrem.blocks._kernels.compile_variant`)."""
    if argv[:1] == ["--helpers"]:
        from ..blocks._kernels import compile_variant
        for entry in argv[1:]:
            name, code = entry.split(":")
            compile_variant(name, int(code))
        return 0
    if argv[:1] != ["--modules"]:
        raise SystemExit("usage: the child's job is --modules NAME ... or --helpers NAME:CODE ...")
    cdir = cache_dir()       # the parent's, passed as IVDREM_CACHE_DIR
    for name in argv[1:]:
        path = Path(cdir) / f"{name}.py"
        if prebuilt_module(name, path.read_text()) is not None:
            continue               # the parent imports it from the prebuilt
        with compile_lock(path):   # a module the parent compiles too is compiled once
            import_path(name, path)
    return 0
