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


# ------------------------------------------------------------- a wait with a limit
#: a process that takes the lock file argv[1] (as compile_lock does, without writing its
#: PID into it unless argv[3] says so), says "held", and holds it for argv[2] seconds
_HOLDER = textwrap.dedent('''
    import fcntl, os, sys, time
    fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT, 0o644)
    fcntl.flock(fd, fcntl.LOCK_EX)
    if sys.argv[3] == "write":
        os.write(fd, f"{os.getpid()} {__import__('socket').gethostname()}\\n".encode())
    print("held", flush=True)
    time.sleep(float(sys.argv[2]))
''')


def _hold(lock, seconds, write="no"):
    proc = subprocess.Popen([sys.executable, "-c", _HOLDER, str(lock), str(seconds), write],
                            stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "held"
    return proc


def test_a_lock_held_too_long_gives_up_naming_the_file_and_its_holder(tmp_path, capfd):
    """A process holding a module's lock forever (a stuck compile, a hung NFS) blocked every
    later run silently.  Now the wait says so after `notice` s, in one line naming the lock
    file and the process holding it, and gives up after `limit` s with a CacheFault naming
    the lock file, the holder and what to do; the lock is not taken."""
    import time

    from ivdrem.compile_cache import CacheFault, CompileLockTimeout
    path = tmp_path / "ivdrem_kernel_x.py"
    lock = tmp_path / ".ivdrem_kernel_x.lock"
    holder = _hold(lock, 60)
    try:
        t0 = time.monotonic()
        with pytest.raises(CompileLockTimeout) as info:
            with compile_lock(path, limit=1.5, notice=0.5):
                pytest.fail("the lock was taken while another process held it")
        waited = time.monotonic() - t0
        still = holder.poll() is None
    finally:
        holder.kill()
        holder.wait()
    assert still and 1.5 <= waited < 5.0
    assert isinstance(info.value, CacheFault)       # the commands: one line, exit 1
    msg = str(info.value)
    assert str(lock) in msg and f"process {holder.pid}" in msg and f"kill {holder.pid}" in msg
    assert "delete" in msg and "IVDREM_LOCK_WAIT_S" in msg and "\n" not in msg
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("ivdrem: waiting ")
    assert str(lock) in err[0] and f"process {holder.pid}" in err[0]


def test_a_wait_shorter_than_the_notice_is_silent_and_takes_the_lock(tmp_path, capfd):
    """A lock released within the limit is taken (within the 20 ms poll), silently when the
    wait was shorter than the notice; the holder's PID is written into the lock file."""
    import time
    path = tmp_path / "ivdrem_kernel_y.py"
    lock = tmp_path / ".ivdrem_kernel_y.lock"
    holder = _hold(lock, 0.5)
    t0 = time.monotonic()
    with compile_lock(path, limit=30, notice=20):
        waited = time.monotonic() - t0
        assert lock.read_text().split()[0] == str(os.getpid())
    holder.wait()
    assert 0.2 < waited < 10.0
    assert capfd.readouterr().err == ""


def test_the_limit_is_read_from_the_environment_and_checked(tmp_path, monkeypatch):
    """IVDREM_LOCK_WAIT_S sets the limit (import_generated under a held lock gives up after
    it); a value that is not a number of seconds > 0 is refused naming the variable, before
    any wait."""
    import time

    from ivdrem.compile_cache import (LOCK_WAIT_S, CacheFault, CompileLockTimeout,
                                      lock_wait_limit)
    monkeypatch.delenv("IVDREM_LOCK_WAIT_S", raising=False)
    assert lock_wait_limit() == LOCK_WAIT_S
    for bad in ("abc", "0", "-3", "nan"):
        monkeypatch.setenv("IVDREM_LOCK_WAIT_S", bad)
        with pytest.raises(CacheFault, match="IVDREM_LOCK_WAIT_S = "):
            lock_wait_limit()
    monkeypatch.setenv("IVDREM_LOCK_WAIT_S", "0.8")
    holder = _hold(tmp_path / ".ivdrem_locktest_env.lock", 60)
    try:
        t0 = time.monotonic()
        with pytest.raises(CompileLockTimeout, match="now 0.8 s"):
            import_generated(tmp_path, "ivdrem_locktest_env", "VALUE = 1\n")
        assert 0.8 <= time.monotonic() - t0 < 5.0
    finally:
        holder.kill()
        holder.wait()


def test_the_holder_is_named_from_the_lock_file_where_proc_locks_does_not_say(
        tmp_path, monkeypatch):
    """Where the kernel's table of locks cannot be read (another system, a network file
    system), the holder is the PID it wrote into the lock file; a file with no PID: None."""
    import builtins

    from ivdrem.compile_cache import lock_holder
    real_open = builtins.open

    def no_proc_locks(file, *a, **k):
        if str(file) == "/proc/locks":
            raise FileNotFoundError(2, "No such file or directory", file)
        return real_open(file, *a, **k)
    lock = tmp_path / ".ivdrem_kernel_z.lock"
    for write in ("write", "no"):
        holder = _hold(lock, 60, write)
        try:
            fd = os.open(lock, os.O_RDWR)
            try:
                seen = lock_holder(fd)
                monkeypatch.setattr(builtins, "open", no_proc_locks)
                fallback = lock_holder(fd)
                monkeypatch.setattr(builtins, "open", real_open)
            finally:
                os.close(fd)
        finally:
            holder.kill()
            holder.wait()
        assert seen.startswith(f"process {holder.pid} (")        # /proc/locks
        if write == "write":
            assert fallback.startswith(f"process {holder.pid} (")  # the file's PID
        else:
            assert fallback is None
        lock.unlink()


def test_a_lock_file_deleted_while_waited_for_is_taken_again(tmp_path):
    """The message after the limit says: delete the lock file if no process is running.  A
    waiter then takes the new file at once, without waiting for its limit."""
    import threading
    import time
    path = tmp_path / "ivdrem_kernel_w.py"
    lock = tmp_path / ".ivdrem_kernel_w.lock"
    holder = _hold(lock, 60)
    try:
        threading.Timer(0.5, lock.unlink).start()
        t0 = time.monotonic()
        with compile_lock(path, limit=30, notice=20):
            waited = time.monotonic() - t0
        assert holder.poll() is None and 0.4 < waited < 10.0
    finally:
        holder.kill()
        holder.wait()


def test_a_lock_timeout_is_one_line_of_a_command(monkeypatch, capsys):
    """A command stopped by a lock that timed out prints one line (``ivdrem: error: ...``,
    the message naming the lock file) and exits 1, no traceback."""
    import ivdrem.cli as cli
    from ivdrem.compile_cache import CompileLockTimeout
    msg = "gave up after 900 s waiting for the compile lock /c/.m.lock, held by process 7"

    def stuck(argv):
        raise CompileLockTimeout(msg)
    monkeypatch.setattr(cli, "_run_command", stuck)
    assert cli.main(["paper"]) == 1
    assert capsys.readouterr().err.strip().splitlines() == [f"ivdrem: error: {msg}"]
