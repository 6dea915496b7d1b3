"""Compile the shared stepper in a second process while this one compiles the kernels.

The first compiled run on a machine (empty numba cache) compiles two independent things:
the shared stepper (:mod:`ivdrem.sim.stepper`, the same for every diagram, about 60 % of
the time) and the diagram's own kernels and their wrappers.  numba compiles under one
process-wide lock, so a thread cannot overlap them; a child process can.  When the
stepper is not in numba's on-disk cache yet, :func:`start` launches
``python -m ivdrem.sim._warm_stepper``, which runs a one-state linear system for one step
on the compiled engine (that compiles the stepper with the same argument types as every
diagram and writes it to the cache) while the parent compiles its kernels; the parent then
:meth:`Warmup.wait` s for it before its first call into the stepper, and loads the machine
code from the cache instead of compiling it.

Any failure of the child (no numba cache, another interpreter layout, a crash) only costs
the overlap: the parent then compiles the stepper itself, as without this module.
``IVDREM_STEPPER_PREFETCH=0`` turns it off.
"""
from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

_CHILD_ENV = "IVDREM_STEPPER_CHILD"
_SWITCH_ENV = "IVDREM_STEPPER_PREFETCH"
#: how long the parent waits for the child before compiling the stepper itself
WAIT_LIMIT_S = 900.0


def stepper_cached(module) -> bool:
    """Whether numba's on-disk cache already holds the stepper's loop (its index file for
    ``step_loop`` exists).  Unknown (numba internals moved) counts as cached: no child."""
    try:
        cache = module.step_loop._cache
        path = Path(cache._cache_path) / cache._cache_file._index_name
        return path.exists()
    except Exception:        # pragma: no cover - numba internals changed
        return True


class Warmup:
    """A running child compiling the stepper (or nothing to wait for)."""

    def __init__(self, proc=None):
        self.proc = proc
        self.waited_s = 0.0

    def wait(self, limit=WAIT_LIMIT_S):
        """Wait for the child (at most `limit` seconds); True if it finished cleanly."""
        if self.proc is None:
            return False
        t0 = time.perf_counter()
        try:
            rc = self.proc.wait(timeout=limit)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            rc = None
        except BaseException:
            self.proc.kill()            # interrupted: do not leave the child running
            raise
        finally:
            self.waited_s = time.perf_counter() - t0
            self.proc = None
        return rc == 0


# what ``python -m ivdrem.sim._warm_stepper`` runs, but with this process's ivdrem first on
# the path (-m would put the working directory first, and with it any other ivdrem there)
_BOOT = ("import sys; sys.path.insert(0, sys.argv.pop(1)); "
         "from ivdrem.sim._warm_stepper import main; sys.exit(main())")


def start(module) -> Warmup:
    """Launch the child when the stepper `module` is not cached yet (and this process is
    not itself that child, and the switch is not off); else a Warmup with nothing to wait
    for."""
    if (os.environ.get(_CHILD_ENV) or os.environ.get(_SWITCH_ENV, "1") == "0"
            or os.environ.get("NUMBA_DISABLE_JIT", "0") not in ("", "0")
            or stepper_cached(module)):
        return Warmup()
    import ivdrem
    from .compiled import cache_dir
    env = dict(os.environ)
    env[_CHILD_ENV] = "1"
    env["IVDREM_CACHE_DIR"] = str(cache_dir())
    root = str(Path(ivdrem.__file__).resolve().parents[1])   # the same ivdrem in the child
    try:
        proc = subprocess.Popen([sys.executable, "-c", _BOOT, root], env=env,
                                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)
    except OSError:                # pragma: no cover - cannot start a process here
        return Warmup()
    return Warmup(proc)


def main():
    """The child: one step of a one-state linear system on the compiled engine."""
    import control as ct
    from ivdrem.sim import simulate
    lag = ct.ss([[-1.0]], [[1.0]], [[1.0]], [[0.0]], inputs="u", outputs="y", name="lag")
    loop = ct.interconnect([lag], inputs="u", outputs="y", name="stepper_warmup")
    simulate(loop, [0.0, 1e-3], inputs=1.0, method="rodas5p", progress=False)
    return 0


if __name__ == "__main__":
    sys.exit(main())
