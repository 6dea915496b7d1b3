"""``python -m ivdrem.cli.prebuild``: compile ivdrem's arm-independent machine code once, into
the installation's prebuilt directory (``ivdrem._prebuilt``; docs/developers.md, "The
prebuilt machine code").

numba types do not carry array sizes, so what a run compiles of ivdrem's own functions
(the rigid-body kernels, the mixing, the blocks' helpers) is the same machine code on a
two-joint arm as on the Panda.  The prebuild runs what a first run runs, on a small arm: the
paper command with every law over a few steps on the Panda's first two joints (γ "auto"'s
estimate, the loop, the diagnostics), and every variant of the mixing functions for the
argument types every caller passes.  numba writes the package functions' machine code, and
the generated modules with theirs, into a staging directory (``$IVDREM_PREBUILD_INTO``),
renamed into place whole when everything succeeded: a crash or Ctrl-C never leaves a
prebuilt that is used.  Other keys' directories (an older source) are removed then.

``./run`` runs it after installing when the prebuilt for the current source is missing.
Exit status 0 when the prebuilt exists (made or already there), 1 when it could not be made
(the message says why; runs then compile as before).
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from .._prebuilt import BUILD_ENV, PREBUILT_ENV, prebuilt_key, prebuilt_root

#: the small arm the prebuild runs: the Panda's first two joints (a URDF arm: the
#: rigid-body kernels a URDF arm's run uses), every law
_CONFIG = """\
[experiment]
t_end = 0.05
laws = ["none", "sigma-modification", "drem", "composite-learning", "iv-drem"]

[model]
name = "panda"
joints = ["panda_joint1", "panda_joint2"]
"""

#: the same on a planar arm, where the named arms' URDF files are not installed (the
#: ``arms`` extra): the package functions a sympy-generated model's run uses
_CONFIG_PLANAR = """\
[experiment]
t_end = 0.05
laws = ["none", "sigma-modification", "drem", "composite-learning", "iv-drem"]

[model]
name = "planar-2"
"""

#: the program of the prebuild's child: the run, then every mixing variant
_CHILD = """\
import sys
from ivdrem.cli import main
code = main(sys.argv[1:])
if code:
    sys.exit(code)
from ivdrem.blocks._kernels import MIXING_VARIANTS, compile_variant
for name in ("mixing_values", "mixing_derivatives"):
    for code in range(len(MIXING_VARIANTS)):
        compile_variant(name, code)
"""


def _say(quiet, text):
    if not quiet:
        print(f"ivdrem prebuild: {text}", file=sys.stderr, flush=True)


def _has_urdf_arms() -> bool:
    try:
        from ..models.urdf import arm_urdf
        arm_urdf("panda")
        return True
    except Exception:
        return False


def prebuild(root=None, *, quiet=False, force=False, program=None) -> Path:
    """Make the prebuilt directory of this installation under `root` (default
    :func:`ivdrem._prebuilt.prebuilt_root`) unless it exists (`force`: make it again);
    its path.  RuntimeError (the message says why) when it cannot be made.

    `program`: Python source the child runs instead of the small arm's run (tests: a
    prebuilt of a few functions, made in seconds)."""
    root = Path(root) if root is not None else prebuilt_root()
    key = prebuilt_key()
    if root is None or key is None:
        raise RuntimeError(f"no prebuilt directory here ({PREBUILT_ENV} is empty, or the "
                           "sources or numba's version cannot be read)")
    final = root / key
    if final.is_dir() and not force:
        _say(quiet, f"{final} exists (the prebuilt for this source)")
        return final
    try:
        root.mkdir(parents=True, exist_ok=True)
        work = Path(tempfile.mkdtemp(prefix=f".{key}.", dir=root))
    except OSError as exc:
        raise RuntimeError(f"cannot write in {root} ({exc.strerror or exc}); set "
                           f"{PREBUILT_ENV} to a folder you can write") from None
    staging, scratch = work / "prebuilt", work / "cache"
    try:
        staging.mkdir()
        config = work / "small-arm.toml"
        config.write_text(_CONFIG if _has_urdf_arms() else _CONFIG_PLANAR)
        env = dict(os.environ, **{BUILD_ENV: str(staging), "IVDREM_CACHE_DIR": str(scratch),
                                  "IVDREM_COMPILE_CHILD": "0", "OPENBLAS_NUM_THREADS": "1"})
        env.pop("NUMBA_CACHE_DIR", None)       # the scratch cache's, for anything else
        _say(quiet, f"compiling ivdrem's arm-independent functions into {final} "
                    "(a run of every law on a two-joint arm; 1-3 minutes)")
        t0 = time.perf_counter()
        # the package's parent first on the path: this installation, whatever the cwd
        env["PYTHONPATH"] = os.pathsep.join(
            [str(Path(__file__).resolve().parents[2])] + env.get("PYTHONPATH", "").split(
                os.pathsep)).rstrip(os.pathsep)
        child = ([sys.executable, "-c", program] if program is not None else
                 [sys.executable, "-c", _CHILD, "paper", "--config", str(config), "--quiet"])
        out = subprocess.run(child, env=env,
                             cwd=work, stdin=subprocess.DEVNULL, capture_output=True, text=True)
        if out.returncode != 0:
            tail = (out.stderr or out.stdout).strip().splitlines()[-8:]
            raise RuntimeError("the prebuild's run failed (exit "
                               f"{out.returncode}):\n    " + "\n    ".join(tail))
        for lock in staging.glob("generated/.*.lock"):
            lock.unlink()
        try:
            staging.rename(final)                  # whole, or not at all
        except OSError:
            if not final.is_dir():
                raise
            if force:                              # --force: the old one goes
                shutil.rmtree(final)
                staging.rename(final)
            # else another prebuild made it meanwhile: that one stays (a run may read it)
        _say(quiet, f"done in {time.perf_counter() - t0:.0f} s ({_size(final)})")
    finally:
        shutil.rmtree(work, ignore_errors=True)
    _remove_others(root, key, quiet)
    return final


def _size(path) -> str:
    n = sum(f.stat().st_size for f in Path(path).rglob("*") if f.is_file())
    return f"{n / 2**20:.0f} MB"


def _remove_others(root, key, quiet):
    """Remove the prebuilt directories of other keys (older sources) and staging folders
    left by an interrupted prebuild (``.KEY.*``, older than a day: not one running now)."""
    for d in root.iterdir():
        if d.name == key or not d.is_dir():
            continue
        stale = not d.name.startswith(".")
        if not stale:
            try:
                stale = time.time() - d.stat().st_mtime > 86400
            except OSError:
                continue
        if stale:
            shutil.rmtree(d, ignore_errors=True)
            _say(quiet, f"removed {d} (another source's)")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m ivdrem.cli.prebuild",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("--dir", type=Path, default=None,
                    help=f"the folder of prebuilt directories (default ${PREBUILT_ENV} or "
                         "<sys.prefix>/share/ivdrem/prebuilt)")
    ap.add_argument("--force", action="store_true", help="make it again even if it exists")
    ap.add_argument("--quiet", action="store_true", help="print nothing but errors")
    ap.add_argument("--print-dir", action="store_true",
                    help="print the prebuilt directory this installation loads, and exit "
                         "(0 if it exists, 1 if not)")
    a = ap.parse_args(argv)
    if a.print_dir:
        root = a.dir or prebuilt_root()
        key = prebuilt_key()
        if root is None or key is None:
            return 1
        print(root / key)
        return 0 if (root / key).is_dir() else 1
    quiet = a.quiet or not sys.stderr.isatty()     # progress on a terminal only
    try:
        prebuild(a.dir, quiet=quiet, force=a.force)
    except RuntimeError as exc:
        print(f"ivdrem prebuild: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
