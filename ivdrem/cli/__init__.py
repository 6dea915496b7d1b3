"""Command line: ``ivdrem paper | study | report | examples | fmu export | cosim``.

Every command-line face of ivdrem is in this package, above the library it drives:
``paper`` and ``examples`` here, :mod:`.report` (``ivdrem report``), :mod:`.study`
(``ivdrem study``), :mod:`.fmu` (``ivdrem fmu export``, ``ivdrem cosim``), :mod:`.plants`
(the MuJoCo plant: ``cosim --plant mujoco``, ``report --plant mujoco``, the robustness
study) and :mod:`.preflight` (what the commands check before the first simulation step).
"""
from __future__ import annotations

import argparse
import functools
import json
import math
import sys
from pathlib import Path

__all__ = ["main"]


def _cmd_paper(args):
    from .._config_file import ConfigError, read_toml
    from .._paths import STDOUT, OutputLocationError, check_replaceable, user_path
    from .preflight import (PreflightError, check_cache_dir, check_runs, method_overrides,
                             horizon_note, long_run_note, timing_text)
    from .._progress import want_progress
    prog = "ivdrem paper"
    overrides = {}
    if args.t_end is not None:
        overrides["experiment.t_end"] = args.t_end
    if args.law:
        overrides["experiment.laws"] = list(args.law)
    json_path = None
    try:   # every option and output location before the first step
        overrides.update(method_overrides(
            args.method, None if args.config is None else user_path(args.config)))
        if args.t_end is not None and not (math.isfinite(args.t_end) and args.t_end > 0):
            raise PreflightError(f"--t-end must be a finite number of seconds > 0, "
                                 f"got {args.t_end:g}")
        try:
            # the file, the output and the compiler first, before python-control and
            # SciPy are imported: a typo costs a tenth of a second, not three
            if args.config is not None:
                read_toml(user_path(args.config))
            if args.json == STDOUT:      # the JSON alone on stdout; the lines go to stderr
                json_path = STDOUT
            elif args.json:
                json_path = check_replaceable(user_path(args.json), "JSON file",
                                              overwrite=args.overwrite, ours=_is_paper_json)
            check_cache_dir(args.engine)
            import_library()
            from ..experiments.config import read_config
            from ..experiments.experiment import Experiment
            # the data, then the experiment: the model built once, the keys that follow it
            # filled and checked against it (Experiment.from_config)
            data = read_config(None if args.config is None else user_path(args.config),
                               overrides or None)
            experiment = Experiment.from_config(data, engine=args.engine)   # resolved once
        except ConfigError as e:     # the value came from --t-end: name the option
            if args.t_end is not None and "experiment.t_end" in str(e):
                raise PreflightError(f"--t-end {args.t_end:g} s: {e}") from None
            raise
        config = experiment.config
        walls = check_runs(experiment, allow_long=args.allow_long)
    except (ConfigError, PreflightError, OutputLocationError, ValueError, ImportError) as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 2
    note = horizon_note(config)
    if note and set(config["experiment"]["laws"]) >= {"iv-drem", "composite-learning"}:
        print(f"{prog}: {note}", file=sys.stderr)
    long_note = long_run_note(walls)
    if long_note and not args.quiet:      # minutes ahead: said before they start
        print(f"{prog}: {long_note}", file=sys.stderr)
    # with --json - standard output carries the JSON alone: every line goes to stderr
    say = print if json_path != STDOUT else functools.partial(print, file=sys.stderr)

    from ..experiments.metrics import conclusions, format_conclusions, summary
    from ..experiments.paper import run_paper
    from ..sim import SimulationError
    from ..diagrams.gamma_auto import GainRuleError
    try:
        run = run_paper(experiment, progress=want_progress(not args.quiet),
                        allow_long=args.allow_long, log=say,
                        return_states=False)     # nothing below reads the states
    except GainRuleError as e:       # refused by the calibration, before that law's run
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 2
    except SimulationError as e:
        print(f"{prog}: simulation failed: {e}", file=sys.stderr)
        return 1
    out = {law: summary(lr, run.theta) for law, lr in run.runs.items()}
    for law, s in out.items():
        st = run.runs[law].stats
        say(f"{law:>20s}: |theta_err|(t_end) = {s['theta_err_norm']:.4g}, "
            f"max|e| last 20% = {s['e_max_last20']:.3g} rad, "
            f"RMS tau_d err last 20% = {s['tau_d_err_rms_last20']:.4g} N m  "
            f"({st['steps']} steps, {timing_text(st)})")
    # the conclusions the laws run allow (C4 needs iv-drem and drem, C1-C3 composite learning)
    evaluated = [c for c in conclusions(run) if c["verdict"] is not None]
    if evaluated:
        say(format_conclusions(evaluated))
    from ..experiments.diagnostics import diagnose_run, format_diagnostics, to_json
    for law, d in diagnose_run(run).items():   # the assumptions of Theorem 2 on this run
        from ..experiments.diagnostics import learning_warnings
        say(format_diagnostics(d))
        out[law]["diagnostics"] = to_json(d)
        out[law]["warnings"] = learning_warnings(d)
        gamma = getattr(run.runs[law], "gamma", None)
        if isinstance(gamma, (int, float)):
            out[law]["gamma"] = float(gamma)
        elif isinstance(gamma, (list, tuple)):          # one γ_i per channel ("channel")
            out[law]["gamma"] = [float(g) for g in gamma]
    # a run that does not learn says so last, under its numbers (docs/diagnostics.md, LEARN)
    for law in out:
        for w in out[law]["warnings"]:
            say(f"{law}: WARNING: {w}")
    if json_path == STDOUT:
        sys.stdout.write(json.dumps(out, indent=2) + "\n")
        sys.stdout.flush()
    elif json_path is not None:
        from .._paths import write_text_or_keep
        where, failed = write_text_or_keep(json_path, json.dumps(out, indent=2) + "\n")
        if failed is not None:
            print(f"{prog}: error: cannot write {json_path}: {failed}; "
                  f"the results were kept in {where}", file=sys.stderr)
            return 1
        print(f"wrote {where}")
    return 0


def _is_paper_json(path) -> bool:
    """Whether `path` holds what ``ivdrem paper --json`` writes (per law: its summary)."""
    from .._paths import read_input_bytes
    try:     # bounded, and never a device or a FIFO (ivdrem._paths)
        data = json.loads(read_input_bytes(path, "JSON file").decode("utf-8"))
    except (OSError, ValueError):
        return False
    return (isinstance(data, dict) and bool(data)
            and all(isinstance(v, dict) and {"theta_err_norm", "theta_hat"} <= set(v)
                    for v in data.values()))


def _cmd_examples(args):
    """``ivdrem examples [DIR]``: list the examples, or write them into DIR."""
    from .._bundled import ExamplesError, describe_examples, write_examples
    from .._paths import user_path
    try:
        if args.dir is None:
            print(describe_examples())
            print("write them with: ivdrem examples DIR")
            return 0
        dest = user_path(args.dir)
        written = write_examples(dest, overwrite=args.overwrite)
    except ExamplesError as e:
        print(f"ivdrem examples: error: {e}", file=sys.stderr)
        return 2
    if written:
        print(f"wrote {len(written)} file(s) to {dest}: " + ", ".join(p.name for p in written))
    else:
        print(f"{dest} already holds every example, unchanged")
    print(f"e.g.  ivdrem paper --config {dest / 'paper.toml'}")
    return 0


def _cmd_study(args):
    from .._paths import user_path
    from ..plants.study import is_robustness_file
    if is_robustness_file(user_path(args.study)):       # the MuJoCo robustness study
        import_library()
        from .plants import run_robustness_command
        return run_robustness_command(args)
    from .study import run_study_command
    return run_study_command(args)


def _cmd_report(args):
    from .report import run_report_command
    return run_report_command(args)


class LawNames:
    """The laws' names, read from the registry only when used: joined by commas when a help
    text is printed (``%(law_names)s`` in an option's help), or as an option's ``choices``
    (a name checked, or listed in argparse's error): the registry (:mod:`ivdrem.laws`)
    imports python-control, which parsing the arguments does not need."""

    @staticmethod
    def _names():
        from ..laws import law_names
        return law_names()

    def __str__(self):
        return ", ".join(self._names())

    def __contains__(self, name):
        return name in self._names()

    def __iter__(self):
        return iter(self._names())


def build_parser():
    from .. import __version__
    from .preflight import add_run_options
    from .report import add_report_arguments
    p = argparse.ArgumentParser(prog="ivdrem", description=(
        "Composite adaptive disturbance rejection via IV-based DREM "
        "(Glushchenko & Lastochkin): paper experiment, report, plant FMU."))
    p.add_argument("--version", action="version", version=f"ivdrem {__version__}")
    sub = p.add_subparsers(dest="command", required=True)

    pp = sub.add_parser("paper", help="run the paper experiment and print/write its numbers")
    pp.add_argument("--t-end", type=float, default=None, metavar="SECONDS",
                    help="horizon (default from the config: 300 s, the horizon "
                         "conclusions C1-C3 need)")
    laws = pp.add_argument(
        "--laws", "--law", dest="law", nargs="+", default=None, metavar="NAME",
        help="laws to run, overrides experiment.laws; 'all' or any of: %(law_names)s "
             "(default: iv-drem composite-learning)")
    laws.law_names = LawNames()
    pp.add_argument("--json", default=None, metavar="FILE",
                    help="write per-law numbers as JSON (an existing file only if ivdrem "
                         "wrote it, or with --overwrite; - for standard output, the other "
                         "lines then go to stderr)")
    pp.add_argument("--overwrite", action="store_true",
                    help="replace an existing --json file that ivdrem did not write")
    pp.add_argument("--config", default=None, metavar="FILE.toml",
                    help="experiment configuration (see examples/paper.toml)")
    pp.add_argument("--engine", choices=("compiled", "reference"), default="compiled")
    pp.add_argument("--quiet", action="store_true", help="no progress bars, no notes on long preparation")
    add_run_options(pp)
    pp.set_defaults(func=_cmd_paper)

    sp = sub.add_parser("study", help="run a parameter study (grid / Monte Carlo, or a MuJoCo robustness study) on a Dask cluster")
    from .study import add_study_arguments
    add_study_arguments(sp)
    sp.set_defaults(func=_cmd_study)

    ep = sub.add_parser("examples", help="list the example configurations, studies and "
                                         "custom law, or write them into DIR")
    ep.add_argument("dir", nargs="?", default=None, metavar="DIR",
                    help="directory to write them into (made if missing)")
    ep.add_argument("--overwrite", action="store_true",
                    help="replace files in DIR that have other text")
    ep.set_defaults(func=_cmd_examples)

    rp = sub.add_parser("report", help="run the paper experiment and write the PDF/HTML report")
    add_report_arguments(rp)
    rp.set_defaults(func=_cmd_report)

    fp = sub.add_parser("fmu", help="plant FMU tools (ivdrem fmu export -o FILE.fmu)",
                        add_help=False)
    fp.set_defaults(func=None, passthrough="fmu")
    cp = sub.add_parser("cosim", help="co-simulate the controller with the plant FMU",
                        add_help=False)
    cp.set_defaults(func=None, passthrough="cosim")
    return p


#: the exit status of a command stopped by Ctrl-C (128 + SIGINT, as a shell reports it)
EXIT_INTERRUPTED = 130


class Terminated(KeyboardInterrupt):
    """SIGTERM (systemd, Kubernetes, a batch scheduler stopping a job), raised where Python
    raises Ctrl-C's KeyboardInterrupt, so that every command stops the same way: the same
    clean-up (a study's saved runs, the temporaries, the cluster's processes), the same one
    line."""

    signum = 15
    label = "SIGTERM"


def interrupted(prog, exc=None):
    """The one line a command prints when Ctrl-C or SIGTERM stops it (no traceback), and
    its exit status, 128 + the signal's number as a shell reports it.  Called in the
    ``except KeyboardInterrupt`` clause: `exc` defaults to the exception being handled."""
    exc = sys.exc_info()[1] if exc is None else exc
    if isinstance(exc, Terminated):
        print(f"{prog}: interrupted ({exc.label})", file=sys.stderr)
        return 128 + exc.signum
    print(f"{prog}: interrupted (Ctrl-C)", file=sys.stderr)
    return EXIT_INTERRUPTED


def _swallowing(frame) -> bool:
    """Whether an exception raised in `frame` would be reported as "Exception ignored" and
    dropped: inside a garbage-collector callback (``gc.callbacks``) or a ``__del__``."""
    import gc
    codes = {getattr(getattr(cb, "__func__", cb), "__code__", None) for cb in gc.callbacks}
    while frame is not None:
        if frame.f_code in codes or frame.f_code.co_name == "__del__":
            return True
        frame = frame.f_back
    return False


class _sigterm_as_interrupt:
    """While a command runs in the main thread of a process that left SIGTERM at its
    default (killing the process on the spot, no clean-up), SIGTERM raises
    :class:`Terminated`; the handler found is restored after."""

    def __enter__(self):
        import os
        import signal
        import threading
        self.previous = None
        if threading.current_thread() is not threading.main_thread():
            return self
        if signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL:
            return self     # the embedding program's own handler (or SIGTERM ignored)

        def on_sigterm(signum, frame):
            if _swallowing(frame):
                # Python would print "Exception ignored" and go on (a gc callback such as
                # Dask's GC diagnosis, a __del__): deliver it again once that returned
                threading.Timer(0.05, os.kill, (os.getpid(), signum)).start()
                return
            exc = Terminated()
            exc.signum = signum
            raise exc
        self.previous = signal.signal(signal.SIGTERM, on_sigterm)
        return self

    def __exit__(self, *exc):
        if self.previous is not None:
            import signal
            signal.signal(signal.SIGTERM, self.previous)
        return False


def main(argv=None):
    """Run the ``ivdrem`` command line with `argv` (default: ``sys.argv[1:]``).

    Returns the exit status: 0 on success, 1 when the results could not be written where
    asked (they are kept elsewhere and the path is printed), 2 for refused options or
    input, 130 after Ctrl-C.  The console script ``ivdrem`` is :func:`run`, which calls
    this and exits without the interpreter's teardown.
    """
    from .._threads import one_blas_thread
    try:
        with _sigterm_as_interrupt(), one_blas_thread():
            # ivdrem's own process: small LAPACK calls, one thread each
            return _main(argv)
    except KeyboardInterrupt as exc:
        return interrupted("ivdrem", exc)
    except OSError as exc:
        line = _cache_fault_line(exc)
        if line is None:
            raise
        print(f"ivdrem: error: {line}", file=sys.stderr)
        return 1


def _cache_fault_line(exc) -> str | None:
    """One line for a cache fault that reached the top (ivdrem.compile_cache.CacheFault, or a
    disk that filled up while writing anything), naming the file and the remedy; None for
    any other error."""
    import errno
    from ..compile_cache import CacheFault, cache_dir
    if isinstance(exc, CacheFault):
        return str(exc)
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        where = exc.filename or "a file"
        return (f"no space left on the device while writing {where} ({exc.strerror}): free "
                f"some space there; ivdrem's compile cache is {cache_dir()} "
                "(IVDREM_CACHE_DIR moves it)")
    return None


def _main(argv=None):
    from .. import _progress
    was_quiet = _progress._quiet
    try:
        return _run_command(argv)
    finally:
        _progress.set_quiet(was_quiet)     # a command's --quiet ends with the command


def _run_command(argv):
    argv = sys.argv[1:] if argv is None else list(argv)
    from .._progress import set_quiet
    # sub-commands owned by ivdrem.fmu parse their own arguments
    if argv and argv[0] in ("fmu", "cosim"):
        set_quiet("--quiet" in argv)   # no notes on long preparation either
        from . import fmu as fcli
        fn = fcli.main_fmu if argv[0] == "fmu" else getattr(fcli, "main_cosim", None)
        if fn is None:
            print("ivdrem cosim: not available in this version", file=sys.stderr)
            return 2
        return fn(argv[1:])
    args = build_parser().parse_args(argv)
    set_quiet(getattr(args, "quiet", False))   # --quiet: no bars, no notes on preparation
    return args.func(args)


def run():
    """The ``ivdrem`` console script and ``python -m ivdrem``: :func:`main` in a process of
    its own, which it starts and ends faster than a plain ``sys.exit(main())`` (a caller
    in Python uses :func:`main`, which changes neither).

    Start: nothing heavy before the arguments are checked; then the cyclic garbage
    collector is paused while python-control, scipy and numpy are imported, and what they
    allocated is frozen out of later collections (:func:`import_library`).

    End: once the command has returned, its output is flushed and the exit handlers
    (``atexit``) have run, the process exits without the interpreter's teardown.  Freeing
    every module's objects one by one took 0.5 s at the end of ``ivdrem paper``; nothing
    of a command's work is lost by skipping it, since every file is written and closed
    before the command returns.  An exception that escapes the command (argparse's exit
    included) keeps the ordinary exit.
    """
    global _freeze_imports
    _freeze_imports = True
    code = main()
    _exit_now(code)


#: whether :func:`import_library` pauses and freezes the garbage collector (the console
#: script's own process, :func:`run`; never a caller's of :func:`main`)
_freeze_imports = False


def import_library():
    """Import python-control and its SciPy (:mod:`ivdrem.laws`, 2-3 s of CPU), which every
    command's work needs and none of its checks: a command calls this once its arguments,
    files and output locations are checked, so that a refusal comes in a tenth of a second.

    In the console script (:func:`run`) the cyclic garbage collector is paused meanwhile
    and what the imports allocated is frozen out of later collections, which find nothing
    to free there (0.11 s of ``ivdrem paper --t-end 1``, measured)."""
    if not _freeze_imports:
        from .. import laws  # noqa: F401
        return
    import gc
    gc.disable()
    try:
        from .. import laws  # noqa: F401, F811
    finally:
        gc.freeze()
        gc.enable()


def _exit_now(code):
    """Exit with `code` (main's return value) after flushing and the exit handlers, but
    without the interpreter's teardown; the ordinary exit if the output cannot be flushed
    (a closed pipe: Python's own report of it is kept)."""
    import atexit
    import os
    code = 0 if code is None else code
    if not isinstance(code, int):
        sys.exit(code)
    try:
        sys.stdout.flush()
        sys.stderr.flush()
    except (OSError, ValueError):
        sys.exit(code)
    run_handlers = getattr(atexit, "_run_exitfuncs", None)   # CPython's own, kept private
    if run_handlers is None:
        sys.exit(code)
    run_handlers()
    try:
        sys.stdout.flush()
        sys.stderr.flush()
    except (OSError, ValueError):
        pass
    try:     # C code's own buffered output (an FMU that prints), which os._exit would drop
        import ctypes
        ctypes.CDLL(None).fflush(None)
    except (OSError, AttributeError):
        pass
    os._exit(code)


if __name__ == "__main__":
    run()
