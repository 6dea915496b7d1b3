"""The compile cache's lock (``ivdrem.compile_cache.compile_lock``): a generated module imported
by two processes at once is compiled by one of them and loaded by the other."""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

from ivdrem.compile_cache import compile_lock, import_generated

pytest.importorskip("fcntl")

#: a generated module whose cfunc takes numba a noticeable time to compile (so that two
#: processes started together overlap), with an argument naming the run in its source
_SOURCE = textwrap.dedent('''
    import numpy as np
    from numba import cfunc, types
    @cfunc(types.float64(types.float64), cache=True)
    def kernel(x):
        s = 0.0
        for k in range(20):
            s += np.sin(x * k) * np.cos(x + k) / (1.0 + k) ** 0.5 + np.arctan2(x, k + 1.0)
        return s
''')

_CHILD = textwrap.dedent('''
    import sys, time
    from pathlib import Path
    from ivdrem.compile_cache import import_generated
    while time.time() < float(sys.argv[2]):   # both children start importing together
        time.sleep(0.001)
    mod = import_generated(Path(sys.argv[1]), "ivdrem_locktest_" + sys.argv[3],
                           Path(sys.argv[4]).read_text())
    print(mod.kernel.cache_hits, mod.kernel.ctypes(0.5))
''')


def _import_twice_at_once(tmp_path, tag):
    import time
    src = tmp_path / "src.py"
    src.write_text(_SOURCE + f"# {tag}\n")
    start = time.time() + 3.0
    procs = [subprocess.Popen([sys.executable, "-c", _CHILD, str(tmp_path), str(start), tag,
                               str(src)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True, env={**os.environ, "NUMBA_CACHE_DIR": ""})
             for _ in range(2)]
    outs = [p.communicate(timeout=300) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], [e[-2000:] for _, e in outs]
    return [o.split() for o, _ in outs]


def test_two_processes_importing_one_module_at_once_compile_it_once(tmp_path):
    got = _import_twice_at_once(tmp_path, "a")
    hits = sorted(int(g[0]) for g in got)
    assert hits == [0, 1]                 # one compiled it, the other loaded its machine code
    assert got[0][1] == got[1][1]         # the same kernel, the same value


def test_the_lock_is_exclusive_between_processes_and_released_on_exit(tmp_path):
    path = tmp_path / "ivdrem_kernel_x.py"
    code = ("import sys, fcntl, os; from pathlib import Path; from ivdrem.compile_cache import "
            "compile_lock\nfd = os.open(Path(sys.argv[1]).with_name('.ivdrem_kernel_x.lock'), "
            "os.O_RDWR)\ntry:\n    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)\n    print('free')\n"
            "except BlockingIOError:\n    print('held')\n")
    with compile_lock(path):
        held = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True,
                              text=True, timeout=120)
    free = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True,
                          text=True, timeout=120)
    assert held.stdout.strip() == "held", held.stderr
    assert free.stdout.strip() == "free", free.stderr


def test_a_cache_that_cannot_hold_the_lock_file_imports_without_a_lock(tmp_path, monkeypatch):
    import ivdrem.compile_cache as cache
    real_open = os.open

    def refuse_lock_files(path, *a, **k):
        if str(path).endswith(".lock"):
            raise PermissionError(13, "Permission denied", str(path))
        return real_open(path, *a, **k)
    monkeypatch.setattr(cache.os, "open", refuse_lock_files)
    mod = import_generated(tmp_path, "ivdrem_locktest_ro", "VALUE = 3\n")
    assert mod.VALUE == 3
    assert not list(tmp_path.glob(".*.lock"))


def test_a_users_module_imported_by_path_gets_no_lock_file_beside_it(tmp_path):
    """import_path also imports a configuration's plugin files (experiment.plugins): a
    user's directory must not receive a lock file."""
    from ivdrem.compile_cache import import_path
    user = tmp_path / "my_laws.py"
    user.write_text("VALUE = 7\n")
    assert import_path("ivdrem_locktest_user", user).VALUE == 7
    assert not [p for p in tmp_path.rglob("*") if p.name.endswith(".lock")]
