"""One FMI 2.0 FMU instance (fmpy), shared by the FMU plant block and the co-simulation.

:class:`FmuInstance` does what both need: read the model description (clear errors for
missing or unsuitable files, :mod:`ivdrem.fmu.describe`), extract the archive to a
temporary directory, load the binary and instantiate it with a logger that keeps the FMU's
messages, initialize it with start values, turn a failing call into :class:`FmuError`
carrying the FMU's own message, reset and re-initialize after such an error, and release
everything (``fmi2Terminate``, ``fmi2FreeInstance``, the extracted files) when its owner
is garbage-collected (``weakref.finalize``) or on :meth:`close`.

It also gives the C addresses of the fmi2 functions and of the component
(:meth:`address`, :attr:`component_address`), so compiled code can call the FMU directly
(:func:`ivdrem._native_call.call_c`).
"""
from __future__ import annotations

import ctypes
import shutil
import weakref
from pathlib import Path

from .describe import extract_fmu, read_description

__all__ = ["FmuInstance", "FmuError"]

#: Messages kept per instance (the most recent ones).
MAX_MESSAGES = 100


class FmuError(RuntimeError):
    """An FMU call failed; the message carries the FMU's own log text."""


class _Resources:
    """What must be released, held apart from the owner so that weakref.finalize does not
    keep the owner alive."""

    def __init__(self):
        self.fmu = None
        self.instantiated = False
        self.unzipdir = None        # temporary extraction (None: an extracted directory)
        self.callbacks = None       # ctypes callbacks: alive as long as the instance

    def release(self):
        fmu, self.fmu = self.fmu, None
        if fmu is not None:
            if self.instantiated:
                for step in (fmu.terminate, fmu.freeInstance):   # freeInstance unloads too
                    try:
                        step()
                    except Exception:
                        pass
            else:
                try:
                    fmu.freeLibrary()
                except Exception:
                    pass
        if self.unzipdir:
            shutil.rmtree(self.unzipdir, ignore_errors=True)
            self.unzipdir = None
        self.callbacks = None


class FmuInstance:
    """An instantiated FMI 2.0 FMU.

    Parameters
    ----------
    path : path-like
        The ``.fmu`` archive or a directory holding an extracted FMU.
    interface : "model exchange" or "co-simulation"
    instance_name : str
        ``instanceName`` passed to ``fmi2Instantiate`` (appears in the FMU's messages).
    owner : object, optional
        Release the FMU when this object is garbage-collected (default: when this
        instance is); see also :meth:`bind_owner`.
    label : str, optional
        Prefix of error messages (e.g. the block name).
    md : fmpy ModelDescription, optional
        The FMU's model description, if the caller has read it already.

    Raises FileNotFoundError / ValueError (from :func:`~ivdrem.fmu.describe.read_description`)
    for a missing or unsuitable file, ValueError if the binary cannot be loaded or
    ``fmi2Instantiate`` fails (with the FMU's message, e.g. a wrong GUID).
    """

    def __init__(self, path, interface, *, instance_name="plant", owner=None, label=None,
                 md=None):
        from fmpy import calloc, free
        from fmpy.fmi2 import (FMU2Model, FMU2Slave, fmi2CallbackFunctions,
                               fmi2CallbackLoggerTYPE, fmi2CallbackAllocateMemoryTYPE,
                               fmi2CallbackFreeMemoryTYPE)
        if interface not in ("model exchange", "co-simulation"):
            raise ValueError(f"interface must be 'model exchange' or 'co-simulation', "
                             f"got {interface!r}")
        self.path = Path(path)
        self.interface = interface
        self.label = label
        self.md = read_description(self.path, interface) if md is None else md
        self.variables = {v.name: v for v in self.md.modelVariables}
        self.messages = []
        self.broken = False
        self._start = ([], [])
        self._start_time = 0.0
        self._count = [0]           # messages logged so far (a mark for failure())
        self._initialized_at = 0    # the count when the FMU was last (re)initialized
        self._res = res = _Resources()
        self._finalizer = weakref.finalize(self if owner is None else owner, res.release)
        messages, count = self.messages, self._count

        def log(env, instance, status, category, message):
            # ivdrem's FMUs pass complete text with '%' doubled (printf-safe): undo that
            messages.append(message.decode("utf-8", "replace").replace("%%", "%"))
            del messages[:-MAX_MESSAGES]
            count[0] += 1

        try:
            if self.path.is_file():
                res.unzipdir = extract_fmu(self.path)
            # No fmpy.logging.addLoggerProxy: its native proxy keeps the last registered
            # Python logger in one global, which dangles once these callbacks are freed and
            # then crashes every FMU in the process that logs through the proxy.
            cb = fmi2CallbackFunctions()
            cb.logger = fmi2CallbackLoggerTYPE(log)
            cb.allocateMemory = fmi2CallbackAllocateMemoryTYPE(calloc)
            cb.freeMemory = fmi2CallbackFreeMemoryTYPE(free)
            res.callbacks = (cb, log)
            me = interface == "model exchange"
            kind = FMU2Model if me else FMU2Slave
            ident = (self.md.modelExchange if me else self.md.coSimulation).modelIdentifier
            try:
                res.fmu = kind(guid=self.md.guid, unzipDirectory=res.unzipdir or str(self.path),
                               modelIdentifier=ident, instanceName=instance_name)
            except Exception as exc:
                raise ValueError(f"{self.path}: cannot load the FMU binary: {exc}") from None
            try:
                res.fmu.instantiate(callbacks=cb)
            except Exception as exc:
                raise ValueError(f"{self.path}: fmi2Instantiate failed: "
                                 f"{' '.join(messages) or exc}") from None
            res.instantiated = True
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ the FMU
    @property
    def fmu(self):
        """The fmpy ``FMU2Model`` / ``FMU2Slave`` (None once released)."""
        return self._res.fmu

    @property
    def component_address(self) -> int:
        """The ``fmi2Component`` pointer, as an integer."""
        return int(self._res.fmu.component)

    def address(self, function: str) -> int:
        """C address of the FMU library's function `function` (e.g. ``"fmi2SetReal"``)."""
        fn = getattr(self._res.fmu.dll, function)
        return int(ctypes.cast(fn, ctypes.c_void_p).value)

    def value_reference(self, name: str) -> int:
        return int(self.variables[name].valueReference)

    @property
    def unzipdir(self):
        """The temporary extraction directory (None for an FMU given as a directory)."""
        return self._res.unzipdir

    @property
    def log_count(self) -> int:
        """How many messages the FMU has logged so far (a mark for :meth:`failure`)."""
        return self._count[0]

    def bind_owner(self, owner):
        """Release the FMU when `owner` is garbage-collected (instead of the previous owner)."""
        if self._finalizer.detach() is not None:
            self._finalizer = weakref.finalize(owner, self._res.release)

    # ------------------------------------------------------------------ calls and errors
    def failure(self, what, exc=None, mark=None) -> FmuError:
        """An FmuError for a failed call `what`, with the FMU's messages logged since `mark`
        (a :attr:`log_count`; default: since the last (re)initialization); marks the
        instance broken."""
        self.broken = True
        mark = self._initialized_at if mark is None else mark
        k = min(self._count[0] - mark, len(self.messages))
        new = self.messages[len(self.messages) - k:] if k > 0 else []
        text = " ".join(new) if new else "no message from the FMU"
        prefix = f"{self.label}: " if self.label else ""
        tail = f" ({exc})" if exc is not None else ""
        return FmuError(f"{prefix}FMU {self.path.name}: {what} failed: {text}{tail}")

    def fail_and_reset(self, what, exc=None, mark=None) -> FmuError:
        """:meth:`failure`, then reset and re-initialize the FMU at once (so the next call
        works); a failing reset is added to the message and retried by :meth:`recover`."""
        err = self.failure(what, exc, mark)
        try:
            self.reset()
        except FmuError as again:
            return FmuError(f"{err}; resetting the FMU failed too: {again}")
        return err

    def call(self, what, fn, *args):
        """``fn(*args)``; an exception becomes :class:`FmuError` with the FMU's messages."""
        mark = self._count[0]
        try:
            return fn(*args)
        except Exception as exc:
            raise self.failure(what, exc, mark) from None

    def initialize(self, start=None, start_time=0.0):
        """Set start values ({variable name: value}) and initialize; a model-exchange FMU is
        left in continuous-time mode.  The start values are kept for :meth:`reset`."""
        start = dict(start or {})
        self._start = ([self.value_reference(k) for k in start], [float(v) for v in start.values()])
        self._start_time = float(start_time)
        self.call("initialization", self._initialize)

    def _initialize(self):
        fmu = self._res.fmu
        fmu.setupExperiment(startTime=self._start_time)
        if self._start[0]:
            fmu.setReal(*self._start)
        fmu.enterInitializationMode()
        fmu.exitInitializationMode()
        if self.interface == "model exchange":
            while True:  # event iteration (ivdrem's plant has no events)
                new_discrete_states_needed, terminate = fmu.newDiscreteStates()[:2]
                if terminate:
                    raise RuntimeError("the FMU requested termination during initialization")
                if not new_discrete_states_needed:
                    break
            fmu.enterContinuousTimeMode()
        self.broken = False
        self._initialized_at = self._count[0]

    def reset(self):
        """fmi2Reset and initialize again with the same start values (after an error)."""
        self.call("reset", self._res.fmu.reset)
        self.call("initialization", self._initialize)

    def recover(self):
        """Reset if an earlier call failed (FMI 2.0: after fmi2Error only reset or free)."""
        if self.broken:
            self.reset()

    def close(self):
        """Terminate and free the instance and remove its extracted files (idempotent)."""
        self._finalizer()

    @property
    def closed(self) -> bool:
        return not self._finalizer.alive
