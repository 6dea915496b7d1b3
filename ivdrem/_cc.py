"""The one way ivdrem invokes the C compiler: which compiler, which flags, what an error says.

* The compiler is the ``cc`` argument, else ``$CC``, else ``cc``; one that cannot be found
  is refused before any work with :class:`CompilerNotFound`, a one-line message naming it.
* Flags: C99, position independent, ``-Wall -Wextra``, optimisation ``-O2`` unless the caller
  gives its own, linked against libm; a shared library on Linux is also linked with
  ``-Wl,--no-undefined`` (it needs nothing but libc and libm) and, when ``hidden``, exports
  only what its sources mark visible (``-fvisibility=hidden``).
* A failed build raises :class:`CompilerError`: one line naming the compiler, what was being
  built and the compiler's first error; the whole command and output are in
  ``exc.command`` and ``exc.output`` (and a note on the exception, shown in a traceback).

Used by the plant FMU (:func:`ivdrem.fmu.export.compile_binary`), a URDF arm's C library
(:mod:`ivdrem.models._c_engine`: the functions the engines call), the controller's library
(:func:`ivdrem.controller.codegen.build_library`) and FMU
(:func:`ivdrem.controller.fmu_export.export_controller_fmu`) and the tests of the models' C
face; the C stepper still calls the compiler its own way (to be moved here).
"""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

__all__ = ["CompilerError", "CompilerNotFound", "compiler", "compile_shared", "BASE_FLAGS"]

#: flags of every build
BASE_FLAGS = ("-std=c99", "-fPIC", "-Wall", "-Wextra")


class CompilerError(RuntimeError):
    """A C build failed; the message is one line, ``command`` and ``output`` the details."""

    def __init__(self, message, command=(), output=""):
        super().__init__(message)
        self.command = list(command)
        self.output = output


class CompilerNotFound(CompilerError):
    """The C compiler named by ``cc``, ``$CC`` or ``cc`` is not on this machine."""


def compiler(cc=None) -> str:
    """The C compiler to call: `cc`, else ``$CC``, else ``cc``; refused (one line naming
    it and where the name came from) if it is not found."""
    source = "cc=" if cc else ("$CC" if os.environ.get("CC") else "the default")
    cc = cc or os.environ.get("CC") or "cc"
    if shutil.which(cc) is None:
        raise CompilerNotFound(f"C compiler {cc!r} ({source}) not found: install a C compiler "
                               "(e.g. gcc) or name one with CC=... or cc=...")
    return cc


def _first_error(output: str) -> str:
    lines = [ln.strip() for ln in output.splitlines() if ln.strip()]
    for ln in lines:            # gcc and clang: "file:line:col: error: ..."
        if re.search(r":\s*(fatal )?error:", ln):
            return ln
    return lines[0] if lines else "no message"


def compile_shared(sources, out, *, what, cc=None, include_dirs=(), opt=("-O2",),
                   hidden=False, extra_flags=()) -> str:
    """Compile the C `sources` into the shared library `out`; returns the compiler's
    warnings (empty if none).  `what` names the build in an error ("the FMU plant_model.c")."""
    cc = compiler(cc)
    cmd = [cc, "-shared", *BASE_FLAGS, *opt]
    if hidden:
        cmd.append("-fvisibility=hidden")
    for d in include_dirs:
        cmd += ["-I", str(d)]
    if sys.platform.startswith("linux"):
        cmd.append("-Wl,--no-undefined")
    cmd += [str(Path(s)) for s in sources]
    cmd += ["-o", str(out), "-lm", *extra_flags]
    try:
        res = subprocess.run(cmd, capture_output=True, text=True)
    except OSError as exc:
        raise CompilerError(f"C compiler {cc!r} could not be run for {what}: {exc}",
                            cmd) from None
    if res.returncode != 0:
        output = res.stderr + res.stdout
        err = CompilerError(f"C compiler {cc!r} failed to build {what} (exit "
                            f"{res.returncode}): {_first_error(output)}", cmd, output)
        err.add_note("command: " + " ".join(cmd) + "\n" + output)
        raise err
    return res.stderr
