"""Compile in a second process while this one compiles: half the kernel wrappers.

The first compiled run on a machine (empty numba cache) compiles the diagram's own kernels
and their C-callable wrappers.  numba compiles under one process-wide lock, so a thread
cannot overlap them; a child process can.  The child (``python -m
ivdrem.sim._warm_stepper --modules name ...``) imports, and so compiles into numba's
cache, those generated modules, in that order, from the cache directory the parent has
written them to (:func:`start_modules`): the parent gives it about half of the kernel
wrappers that are not cached yet and compiles the other half itself.  (The stepper is C,
built by the C compiler in ~2 s on a thread of the parent: no child.)

The parent :meth:`Warmup.wait` s for the child before it needs the child's work, and then
loads the machine code from the cache instead of compiling it.  Any failure of the child
(no numba cache, another interpreter layout, a crash, a module it cannot import) only
costs the overlap: the parent then compiles that work itself, as without this module.
``IVDREM_COMPILE_CHILD=0`` (or the older ``IVDREM_STEPPER_PREFETCH=0``) turns it off.
"""
from __future__ import annotations

import os
import subprocess
import sys
import time
import types
from pathlib import Path

from .cache import cache_dir

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
    ``cfunc``'s ``_cache``, a :class:`numba.core.caching.FunctionCache`) exists."""
    return (Path(cache._cache_path) / cache._cache_file._index_name).exists()


def function_cached(path, qualname) -> bool:
    """Whether numba's on-disk cache holds the top-level function `qualname` of the source
    file `path`, decided without importing the file (importing a ``cfunc`` compiles it):
    numba's cache for a stand-in function with the same code location.  Unknown (numba
    internals moved, no cache possible) counts as cached."""
    try:
        from numba.core.caching import FunctionCache
        code = compile(Path(path).read_text(), str(path), "exec")
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
        self.waited_s = 0.0

    def wait(self, limit=WAIT_LIMIT_S):
        """Wait for the child (at most `limit` seconds); True if it finished cleanly."""
        if self.proc is None:
            return False
        t0 = time.perf_counter()
        try:
            rc = self.proc.wait(timeout=limit)
        except subprocess.TimeoutExpired:
            self.cancel()
            rc = None
        except BaseException:
            self.cancel()               # interrupted: do not leave the child running
            raise
        finally:
            self.waited_s = time.perf_counter() - t0
            self.proc = None
        return rc == 0

    def cancel(self):
        """Kill the child (the parent failed or was interrupted) and reap it."""
        proc, self.proc = self.proc, None
        if proc is not None:
            proc.kill()
            proc.wait()


# what ``python -m ivdrem.sim._warm_stepper ARGS`` runs, but with this process's ivdrem first
# on the path (-m would put the working directory first, and with it any other ivdrem
# there); for ``--modules``, ivdrem.sim and ivdrem.blocks are bare packages: the generated
# modules import only ivdrem.blocks._kernels and ivdrem.sim._native, and the packages' own
# imports (python-control, SciPy, matplotlib) would cost the child ~2 s
_BOOT = """\
import os, sys, types
root = sys.argv.pop(1)
sys.path.insert(0, root)
if sys.argv[1:2] == ["--modules"]:
    for pkg in ("ivdrem.sim", "ivdrem.blocks"):
        sys.modules[pkg] = types.ModuleType(pkg)
        sys.modules[pkg].__path__ = [os.path.join(root, *pkg.split("."))]
from ivdrem.sim._warm_stepper import _job
sys.exit(_job(sys.argv[1:]))
"""


def _launch(args, modules=()) -> Warmup:
    """The child running `args` (see :func:`_job`) on this ivdrem and cache directory."""
    env = dict(os.environ)
    env[_CHILD_ENV] = "1"
    env["IVDREM_CACHE_DIR"] = str(cache_dir())
    root = str(Path(__file__).resolve().parents[2])   # the same ivdrem in the child
    try:
        proc = subprocess.Popen([sys.executable, "-c", _BOOT, root, *args], env=env,
                                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)
    except OSError:                # pragma: no cover - cannot start a process here
        return Warmup()
    return Warmup(proc, modules)


def start_modules(names) -> Warmup:
    """Launch the child importing the generated modules `names` (in that order; their
    sources already written to the cache directory), unless :func:`enabled` says no."""
    if not names or not enabled():
        return Warmup()
    return _launch(["--modules", *names], names)


def compile_modules(names):
    """The child's ``--modules`` job: import the modules `names`, in order, from the cache
    directory the parent has written them to (what compiled._import does, without
    importing the compiled engine)."""
    import importlib.util
    cdir = cache_dir()       # the parent's, passed as IVDREM_CACHE_DIR
    for name in names:
        spec = importlib.util.spec_from_file_location(name, Path(cdir) / f"{name}.py")
        mod = sys.modules[name] = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
    return 0


def _job(argv):
    """The child's job from its command line: ``--modules name ...``."""
    if argv[:1] != ["--modules"]:
        raise SystemExit("usage: python -m ivdrem.sim._warm_stepper --modules NAME ...")
    return compile_modules(argv[1:])


if __name__ == "__main__":
    sys.exit(_job(sys.argv[1:]))
