"""Ctrl-C and SIGTERM stop the sampled loop's stability prediction (ivdrem.controller.stability)
promptly: its prefix, the C library's loop compiled around the RK4 plant, runs in pieces of
about PIECE_S s of wall time (``run_in_pieces``), between which Python handles the signal.
In one call (6-12 s on the Panda) a signal waited until the call returned."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


#: another process that sends SIGINT to argv[1] after argv[2] seconds and prints when (a
#: thread of this process would wait for the GIL, which the compiled loop holds)
_KILLER = ("import os, signal, sys, time; time.sleep(float(sys.argv[2])); "
           "print(repr(time.time()), flush=True); os.kill(int(sys.argv[1]), signal.SIGINT)")


def test_ctrl_c_stops_the_compiled_prefix_within_a_piece(ctrl_c_delivered):
    """SIGINT from another process 1 s into a 2000 s prefix of the 2-link arm's IV-DREM
    (2e6 steps, tens of seconds in one call): KeyboardInterrupt within a second of the
    signal (PIECE_S = 0.1 s), raised between two pieces, before the loop's end."""
    from ivdrem.controller import stability
    from ivdrem.models import two_link
    m = two_link()
    stability.closed_loop_prefix(m, "iv-drem", m.theta_values, 0.2, h=1e-3, delay=1)  # warm
    calls = []
    real = stability.run_in_pieces
    killer = []

    def signalled(piece, progress, stop, *a, **k):
        def counted(k_stop):
            calls.append(k_stop)
            return piece(k_stop)
        killer.append(subprocess.Popen([sys.executable, "-c", _KILLER, str(os.getpid()),
                                        "1.0"], stdout=subprocess.PIPE, text=True))
        return real(counted, progress, stop, *a, **k)
    stability.run_in_pieces = signalled
    try:
        with pytest.raises(KeyboardInterrupt):
            stability.closed_loop_prefix(m, "iv-drem", m.theta_values, 2000.0, h=1e-3,
                                         delay=1)
        stopped = time.time()
    finally:
        stability.run_in_pieces = real
        for p in killer:
            out, _ = p.communicate(timeout=60)
    sent = float(out)
    assert stopped - sent < 1.0, stopped - sent
    assert calls[-1] < 2_000_001 and len(calls) > 2     # stopped before the loop's end


#: the export's prediction in a process of its own, which says when its prefix starts and
#: where the interrupt stopped it (in one call: at its end, the loop done)
_DRIVER = textwrap.dedent(r"""
    import sys
    import ivdrem.cli
    from ivdrem.controller import stability
    real = stability.run_in_pieces
    mark, config, out = sys.argv[1:4]
    def marked(piece, progress, stop, *a, **k):
        with open(mark, "a") as f:
            f.write("started\n")
        try:
            return real(piece, progress, stop, *a, **k)
        except KeyboardInterrupt:
            with open(mark, "a") as f:
                f.write(f"interrupted {progress[0]} {stop}\n")
            raise
    stability.run_in_pieces = marked
    sys.exit(ivdrem.cli.main(["fmu", "export", "--controller", "--config", config,
                              "-o", out]))
""")


def _earlier_export(path):
    """A file that an earlier export of ivdrem wrote (its modelDescription.xml names ivdrem
    as the generation tool), which the export replaces without --overwrite."""
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("modelDescription.xml",
                    '<?xml version="1.0"?>\n<fmiModelDescription fmiVersion="2.0" '
                    'generationTool="ivdrem 0.0 (an earlier export)"/>\n')
    return path.read_bytes()


@pytest.mark.parametrize("signum, code, label", [(signal.SIGINT, 130, "Ctrl-C"),
                                                 (signal.SIGTERM, 143, "SIGTERM")])
def test_a_signal_during_the_exports_prediction_stops_it_and_writes_nothing(
        signum, code, label, tmp_path):
    """`ivdrem fmu export --controller` on the Panda's configuration (a prefix of 50 s, 1.25
    windows, 6-12 s), Ctrl-C or SIGTERM 1 s into the prefix: the command's usual exit (130,
    143) with its one line, no traceback, the prefix stopped before its end, within a few
    seconds of the signal, and the FMU an earlier export wrote there the same bytes, nothing
    else left in the folder."""
    out = tmp_path / "panda_controller.fmu"
    before = _earlier_export(out)
    mark = tmp_path / "prefix"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen(
        [sys.executable, "-c", _DRIVER, str(mark), str(ROOT / "examples" / "panda.toml"),
         str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
        cwd=tmp_path, preexec_fn=lambda: (signal.signal(signal.SIGINT, signal.SIG_DFL),
                                          signal.signal(signal.SIGTERM, signal.SIG_DFL)))
    try:
        deadline = time.time() + 300
        while not mark.exists() and proc.poll() is None and time.time() < deadline:
            time.sleep(0.05)
        time.sleep(1.0)
        sent = time.perf_counter()
        proc.send_signal(signum)
        _, err = proc.communicate(timeout=120)
        ended = time.perf_counter()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == code, err[-2000:]
    assert err.strip().splitlines()[-1] == f"ivdrem: interrupted ({label})"
    assert "Traceback" not in err
    started, interrupted, k, stop = mark.read_text().split()
    assert (started, interrupted) == ("started", "interrupted")
    assert int(k) < int(stop) - 1                   # stopped before the prefix's end
    assert ended - sent < 5.0, ended - sent         # the process's exit included
    print(f"exited {ended - sent:.2f} s after the signal, at step {k} of {stop}")
    assert out.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([out.name, mark.name])
