"""The prebuilt machine code (ivdrem._prebuilt, ``python -m ivdrem.cli.prebuild``): a fresh
process with an empty user cache loads ivdrem's package functions and the prebuilt's generated
modules instead of compiling them, with the same results bit for bit; a stale, damaged or
read-only prebuilt is never used wrongly nor written; ``./run``'s stamp.

Each check is a fresh process (numba's caches are per process); numba's ``numba:compile``
events say what was compiled.  The prebuilt here holds a few functions (made in seconds by
the prebuild's own code, :func:`ivdrem.cli.prebuild.prebuild` with a small program); the
installation's whole prebuilt is checked against a URDF arm's run by
``test_a_small_urdf_arms_run_compiles_no_package_function``.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from ivdrem._prebuilt import BUILD_ENV, PREBUILT_ENV, prebuilt_key
from ivdrem.cli.prebuild import prebuild

ROOT = Path(__file__).resolve().parents[1]

#: a generated module (named by its text's hash, as import_generated names them)
GEN_SRC = textwrap.dedent("""\
    from numba import njit
    from ivdrem.blocks._kernels import matT_vec

    @njit(cache=True)
    def twice_at(A, x, out):
        matT_vec(A, x, out)
        for i in range(out.shape[0]):
            out[i] *= 2.0
    """)

#: what the small prebuilt compiles, and what each check's process then calls (the same
#: argument types: C-contiguous float64 arrays); prints the results' bytes and the compile
#: events of ivdrem's functions (package files and generated modules)
WORK = textwrap.dedent("""\
    import json, os, sys
    import numpy as np
    from numba.core import event
    compiled = []
    class Listen(event.Listener):
        def on_start(self, ev):
            f = getattr(ev.data.get("dispatcher"), "py_func", None)
            if f is not None and f.__module__.startswith("ivdrem"):
                compiled.append(f"{f.__module__}.{f.__qualname__}")
        def on_end(self, ev):
            pass
    event.register("numba:compile", Listen())
    from ivdrem.blocks import _kernels
    from ivdrem.compile_cache import cache_dir, import_generated, source_hash
    src = os.environ["GEN_SRC"]
    gen = import_generated(cache_dir(), "ivdrem_test_" + source_hash(src), src)
    rng = np.random.default_rng(3)
    R = rng.standard_normal((4, 4))
    A, B = R @ R.T + 4 * np.eye(4), rng.standard_normal((4, 2))
    _kernels.spd_solve(A, B)
    out = np.empty(4)
    gen.twice_at(R, B[:, 0].copy(), out)
    w = _kernels.start_weight(1.3, 1.0, 0.5)
    if len(sys.argv) > 1:                       # a signature the prebuilt does not hold
        _kernels.spd_solve(A.astype(np.float32), B.astype(np.float32))
    print(json.dumps(dict(bytes=(B.tobytes() + out.tobytes() + np.float64(w).tobytes()).hex(),
                          compiled=compiled, gen_file=gen.__file__)))
    """)

FUNCS = {"ivdrem.blocks._kernels.spd_solve", "ivdrem.blocks._kernels.start_weight",
         "ivdrem.blocks._kernels.matT_vec"}


def _env(prebuilt_root, cache):
    env = dict(os.environ, IVDREM_CACHE_DIR=str(cache), GEN_SRC=GEN_SRC,
               IVDREM_COMPILE_CHILD="0", PYTHONPATH=str(ROOT))
    env[PREBUILT_ENV] = str(prebuilt_root) if prebuilt_root is not None else ""
    for k in ("NUMBA_CACHE_DIR", BUILD_ENV):
        env.pop(k, None)
    return env


def _work(prebuilt_root, cache, *args):
    res = subprocess.run([sys.executable, "-c", WORK, *args], capture_output=True, text=True,
                         env=_env(prebuilt_root, cache), timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    return json.loads(res.stdout.strip().splitlines()[-1]), res.stderr


def _snapshot(d):
    """{relative path: (size, mtime_ns)} of every file under `d`."""
    return {p.relative_to(d).as_posix(): (p.stat().st_size, p.stat().st_mtime_ns)
            for p in Path(d).rglob("*") if p.is_file()}


@pytest.fixture(scope="module")
def small_prebuilt(tmp_path_factory):
    """A prebuilt of the few functions WORK calls, made by the prebuild; and the results of
    WORK without any prebuilt (everything compiled into an empty user cache)."""
    root = tmp_path_factory.mktemp("prebuilt")
    old = os.environ.get("GEN_SRC")
    os.environ["GEN_SRC"] = GEN_SRC
    try:
        made = prebuild(root, quiet=True, program=WORK)
    finally:
        os.environ.pop("GEN_SRC") if old is None else os.environ.update(GEN_SRC=old)
    plain, _ = _work(None, tmp_path_factory.mktemp("plain-cache"))
    return root, made, plain


def test_the_prebuild_makes_its_directory_whole_under_its_key(small_prebuilt):
    root, made, plain = small_prebuilt
    assert made == root / prebuilt_key() and made.is_dir()
    # nothing else left in the folder: the staging directory was renamed, the work removed
    assert [p.name for p in root.iterdir()] == [made.name]
    files = _snapshot(made)
    assert any(f.startswith("numba/ivdrem/blocks/_kernels.spd_solve-") and f.endswith(".nbi")
               for f in files), sorted(files)
    gen = [f for f in files if f.startswith("generated/")]
    assert gen == [f"generated/ivdrem_test_{__import__('ivdrem.compile_cache').compile_cache.source_hash(GEN_SRC)}.py"]
    assert any(f.startswith("numba/generated/") and "twice_at" in f for f in files)
    # without a prebuilt, the functions compile (what the checks below count)
    assert FUNCS | {f"{Path(gen[0]).stem}.twice_at"} <= set(plain["compiled"])
    # a second prebuild finds it and does nothing
    before = _snapshot(made)
    assert prebuild(root, quiet=True, program="raise SystemExit(3)") == made
    assert _snapshot(made) == before


def test_a_fresh_process_loads_the_prebuilt_and_gives_the_same_bits(small_prebuilt, tmp_path):
    root, made, plain = small_prebuilt
    got, _ = _work(root, tmp_path / "cache")
    assert got["compiled"] == [], got["compiled"]
    assert got["bytes"] == plain["bytes"]
    # the generated module came from the prebuilt (nothing written for it in the user cache)
    assert Path(got["gen_file"]).parent == made / "generated"
    assert not list((tmp_path / "cache").glob("ivdrem_test_*.py"))


def test_a_stale_prebuilt_is_ignored_and_removed_by_the_next_prebuild(small_prebuilt,
                                                                       tmp_path):
    root, made, plain = small_prebuilt
    other = tmp_path / "root"
    shutil.copytree(made, other / ("0" * 24))           # another source's key
    got, _ = _work(other, tmp_path / "cache")
    assert FUNCS <= set(got["compiled"]) and got["bytes"] == plain["bytes"]
    assert Path(got["gen_file"]).parent == tmp_path / "cache"
    prebuild(other, quiet=True, program="pass")
    assert [p.name for p in other.iterdir()] == [prebuilt_key()]


def test_a_read_only_prebuilt_is_never_written(small_prebuilt, tmp_path):
    """A signature the prebuilt does not hold compiles into the user cache."""
    root, made, plain = small_prebuilt
    ro = tmp_path / "root"
    shutil.copytree(made, ro / made.name)
    for p in [ro, *ro.rglob("*")]:
        p.chmod(0o555 if p.is_dir() else 0o444)
    before = _snapshot(ro)
    try:
        got, _ = _work(ro, tmp_path / "cache", "float32")
        # the float32 spd_solve, and the float32 Cholesky it calls
        assert "ivdrem.blocks._kernels.spd_solve" in got["compiled"]
        assert set(got["compiled"]) <= {"ivdrem.blocks._kernels.spd_solve",
                                        "ivdrem.models._rigid_body_jit._rb_cholesky",
                                        "ivdrem.models._rigid_body_jit._rb_cholesky_solve"}
        assert got["bytes"] == plain["bytes"]
        assert _snapshot(ro) == before
        # the new signature is in the user cache: a second process compiles nothing
        again, _ = _work(ro, tmp_path / "cache", "float32")
        assert again["compiled"] == []
        assert _snapshot(ro) == before
    finally:
        for p in [ro, *ro.rglob("*")]:
            p.chmod(0o755 if p.is_dir() else 0o644)


def test_a_damaged_prebuilt_index_is_a_miss_not_a_crash(small_prebuilt, tmp_path):
    root, made, plain = small_prebuilt
    bad = tmp_path / "root"
    shutil.copytree(made, bad / made.name)
    index = next((bad / made.name / "numba" / "ivdrem" / "blocks").glob("_kernels.spd_solve-*.nbi"))
    index.write_bytes(index.read_bytes()[:40] + b"garbled")
    before = _snapshot(bad)
    got, err = _work(bad, tmp_path / "cache")
    assert got["compiled"] == ["ivdrem.blocks._kernels.spd_solve"], got["compiled"]
    assert got["bytes"] == plain["bytes"]
    lines = [l for l in err.splitlines() if "prebuilt index" in l]
    assert len(lines) == 1 and str(index) in lines[0] and "unreadable" in lines[0], err
    assert "Traceback" not in err
    assert _snapshot(bad) == before                     # left where it is, unchanged


def test_a_generated_module_of_another_text_is_not_taken_from_the_prebuilt(small_prebuilt,
                                                                             tmp_path):
    """Same name, other text (a hand-edited prebuilt, a hash collision): written to the user
    cache and compiled, never the prebuilt's."""
    root, made, plain = small_prebuilt
    edited = tmp_path / "root"
    shutil.copytree(made, edited / made.name)
    gen = next((edited / made.name / "generated").glob("ivdrem_test_*.py"))
    gen.write_text(gen.read_text().replace("*= 2.0", "*= 3.0"))
    got, _ = _work(edited, tmp_path / "cache")
    assert Path(got["gen_file"]).parent == tmp_path / "cache"
    assert got["bytes"] == plain["bytes"]
    assert got["compiled"] == [f"{Path(got['gen_file']).stem}.twice_at"]


# ------------------------------------------------------------------------------ ./run's step
def _run(tmp_path, root, *, stamp_name="stamp"):
    env = dict(os.environ, IVDREM_PREBUILT_STAMP=str(tmp_path / stamp_name))
    env[PREBUILT_ENV] = str(root)
    for k in ("IVDREM_RUN_QUIET", "IVDREM_PREBUILD"):
        env.pop(k, None)
    return subprocess.run([str(ROOT / "run"), "python", "-c", "print('ran')"], cwd=tmp_path,
                          capture_output=True, text=True, env=env, timeout=600)


def test_the_set_up_stamps_the_prebuilt_and_does_not_redo_it(small_prebuilt, tmp_path):
    root, made, plain = small_prebuilt
    stamp = tmp_path / "stamp"
    res = _run(tmp_path, root)                         # the prebuilt exists: only stamped
    assert res.returncode == 0 and res.stdout.strip() == "ran", res.stderr
    assert "prebuild" not in res.stderr and stamp.read_text().strip() == str(made)
    mtime = stamp.stat().st_mtime_ns
    res = _run(tmp_path, root)
    assert res.returncode == 0 and stamp.stat().st_mtime_ns == mtime   # not looked at again
    # the stamped directory removed: made again (here: into a place it cannot be written,
    # so the prebuild fails: one warning, the command runs, and the next ./run stays quiet)
    blocked = tmp_path / "file"
    blocked.write_text("")
    stamp.write_text(str(tmp_path / "gone") + "\n")
    res = _run(tmp_path, blocked / "sub")
    assert res.returncode == 0 and res.stdout.strip() == "ran", res.stderr
    assert res.stderr.count("warning: the prebuild failed") == 1, res.stderr
    assert "cannot write in" in res.stderr and stamp.read_text().strip() == "failed"
    res = _run(tmp_path, blocked / "sub")
    assert res.returncode == 0 and "prebuild" not in res.stderr, res.stderr
    # a source newer than the stamp: tried again
    os.utime(stamp, (0, 0))
    res = _run(tmp_path, blocked / "sub")
    assert res.stderr.count("warning: the prebuild failed") == 1, res.stderr
    # IVDREM_PREBUILT_DIR set empty (no prebuilt wanted): nothing tried, nothing stamped
    stamp.unlink()
    res = _run(tmp_path, "")
    assert res.returncode == 0 and res.stdout.strip() == "ran", res.stderr
    assert "prebuil" not in res.stderr and not stamp.exists(), res.stderr


# ------------------------------------------------------------------- the whole prebuilt
@pytest.mark.slow
def test_a_small_urdf_arms_run_compiles_no_package_function(tmp_path):
    """The installation's prebuilt (made by ./run's set-up; made here if missing, 1-2
    minutes) holds every package function a URDF arm's run asks for: IV-DREM on the
    Panda's joints 2-3 (another arm than the prebuild's), from an empty user cache,
    compiles only its model's generated code and the small functions numba inlines into
    it (an overload's ``impl``), none of the package's own functions."""
    pytest.importorskip("pinocchio")
    try:
        from ivdrem.models.urdf import arm_urdf
        arm_urdf("panda")
    except Exception:
        pytest.skip("the arms extra is missing")
    made = prebuild(quiet=True)
    config = tmp_path / "arm.toml"
    config.write_text('[model]\nname = "panda"\njoints = ["panda_joint2", "panda_joint3"]\n')
    program = textwrap.dedent("""\
        import json, sys
        from numba.core import event
        compiled = []
        class Listen(event.Listener):
            def on_start(self, ev):
                f = getattr(ev.data.get("dispatcher"), "py_func", None)
                if f is not None:
                    compiled.append(f"{f.__module__}.{f.__qualname__}")
            def on_end(self, ev):
                pass
        event.register("numba:compile", Listen())
        from ivdrem.cli import main
        code = main(sys.argv[1:])
        print(json.dumps(dict(code=code, compiled=compiled)))
        """)
    env = _env(made.parent, tmp_path / "cache")
    res = subprocess.run([sys.executable, "-c", program, "paper", "--config", str(config),
                          "--t-end", "0.05", "--laws", "iv-drem", "--quiet"],
                         capture_output=True, text=True, env=env, timeout=900, cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    got = json.loads(res.stdout.strip().splitlines()[-1])
    assert got["code"] == 0
    package = [f for f in got["compiled"] if f.startswith("ivdrem.")
               and "<locals>" not in f and "__ports_" not in f]
    assert package == [], package
    # the run did compile its own model (the events are seen at all)
    assert any(f.startswith("ivdrem_model_") for f in got["compiled"]), got["compiled"]
