"""python-control's ``input_output_response`` on ivdrem's simulator (docs/simulation.md,
"A drop-in for python-control").

:func:`input_output_response` takes the arguments of ``ct.input_output_response`` of the
supported python-control release (0.10.2) with their meaning and defaults, turns the system
into the one-level diagram :func:`ivdrem.sim.simulate` runs, and returns python-control's
``TimeResponseData`` (``TimeResponseList`` for a list of systems).  :func:`installed`
makes every binding of python-control's function inside the ``control`` package (and
modules imported while it is installed) call it instead, so that ``control.optimal``,
``forced_response`` on a nonlinear system and ``phase_plane_plot`` run on ivdrem too.

This module only translates arguments and results; the simulation is ``simulate``'s.
It reads python-control's private argument helpers (``_process_kwargs``,
``_process_param``, ``_timeresp_aliases``), so that the aliases and their error messages are
python-control's own; tests/test_pycontrol.py pins the release.
"""
from __future__ import annotations

import contextlib
import copy
import functools
import importlib
import sys as _sys
import warnings

import numpy as np
import control as ct
from control.timeresp import TimeResponseData, TimeResponseList

from .sim.errors import StiffnessWarning
from .sim.foreign import PythonBlockNotice
from .sim._control import (PrivateDiagram, evaluate_output, flatten,
                           process_kwargs as _process_kwargs,
                           process_param as _process_param, timeresp_aliases as _timeresp_aliases)
from .sim.simulator import simulate, interpolate_inputs, _input_table

__all__ = ["input_output_response", "drop_in", "installed", "replaced", "flatten",
           "PYTHON_CONTROL_SIMULATOR", "SOLVE_IVP_METHODS", "SUPPORTED_RELEASE"]

#: the python-control release whose conventions are followed (and whose tests are run)
SUPPORTED_RELEASE = "0.10.2"

_NLSYS = importlib.import_module("control.nlsys")   # ``control.nlsys`` is also a function
#: python-control's own simulator, as imported (what :func:`replaced` restores)
PYTHON_CONTROL_SIMULATOR = _NLSYS.input_output_response

#: scipy.integrate.solve_ivp's methods and ivdrem's counterpart: the explicit
#: error-controlled ones run Dormand-Prince 5(4), the implicit / stiffness-switching ones
#: the L-stable Rosenbrock method
SOLVE_IVP_METHODS = {"RK45": "dp45", "RK23": "dp45", "DOP853": "dp45",
                     "Radau": "rodas5p", "BDF": "rodas5p", "LSODA": "rodas5p"}

#: solve_ivp's default tolerances, python-control's defaults too
_SCIPY_RTOL, _SCIPY_ATOL = 1e-3, 1e-6

#: the simulator's loosest relative tolerance (it refuses rtol >= 1)
_LOOSEST_RTOL = 0.999

#: solve_ivp keywords with a counterpart among simulate's settings
_SOLVE_IVP_SETTINGS = {"rtol": "rtol", "atol": "atol", "max_step": "h_max",
                       "first_step": "h"}


def _solver_settings(options):
    """simulate's (method, settings) from solve_ivp's keywords (method included); a keyword
    without a counterpart is a ValueError naming it and what to use instead."""
    options = dict(options)
    name = options.pop("method")
    if not isinstance(name, str) or name not in SOLVE_IVP_METHODS:
        raise ValueError(
            f"solve_ivp_method {name!r} has no counterpart in ivdrem's simulator: give one of "
            f"{', '.join(SOLVE_IVP_METHODS)} (a solver class or another name runs only on "
            "python-control's own simulator, ivdrem.pycontrol.PYTHON_CONTROL_SIMULATOR)")
    settings = {"rtol": _SCIPY_RTOL, "atol": _SCIPY_ATOL}
    for key, value in options.items():
        if key not in _SOLVE_IVP_SETTINGS:
            raise ValueError(
                f"solve_ivp_kwargs[{key!r}] has no counterpart in ivdrem's simulator, which "
                f"takes {', '.join(sorted(_SOLVE_IVP_SETTINGS))} (and method); leave it out, "
                "or run python-control's own simulator "
                "(ivdrem.pycontrol.PYTHON_CONTROL_SIMULATOR)")
        if key == "atol" and np.ndim(value) > 0:
            raise ValueError("solve_ivp_kwargs['atol'] must be a number: ivdrem's simulator "
                             "has one absolute tolerance for every state")
        settings[_SOLVE_IVP_SETTINGS[key]] = value
    if isinstance(settings["rtol"], (int, float)) and not isinstance(settings["rtol"], bool) \
            and settings["rtol"] >= 1:
        # solve_ivp accepts rtol >= 1, which controls nothing (max_step bounds the steps);
        # the simulator's largest relative tolerance means the same
        settings["rtol"] = _LOOSEST_RTOL
    return SOLVE_IVP_METHODS[name], settings


# --------------------------------------------------------------------------- the call
def input_output_response(
        sys, timepts=None, inputs=0., initial_state=0., params=None,
        ignore_errors=False, transpose=False, return_states=False,
        squeeze=None, solve_ivp_kwargs=None, evaluation_times='T', *,
        engine="compiled", **kwargs):
    """``ct.input_output_response`` on ivdrem's simulator: the same arguments (aliases
    ``T``, ``U``, ``X0``, ``return_x``, ``t_eval``, ``solve_ivp_method``, ``method``), the
    same defaults (RK45's counterpart dp45 at solve_ivp's rtol 1e-3, atol 1e-6) and the same
    ``TimeResponseData``; ``engine`` chooses ivdrem's engine.

    Stricter than python-control (docs/simulation.md): an initial state of the wrong size
    and a parameter no block has are errors; a solve_ivp keyword or method without a
    counterpart is refused naming it.
    """
    _process_kwargs(kwargs, _timeresp_aliases)
    T = _process_param('timepts', timepts, kwargs, _timeresp_aliases)
    U = _process_param('inputs', inputs, kwargs, _timeresp_aliases, sigval=0.)
    X0 = _process_param('initial_state', initial_state, kwargs, _timeresp_aliases,
                        sigval=0.)
    return_x = _process_param('return_states', return_states, kwargs, _timeresp_aliases,
                              sigval=False)
    t_eval = _process_param('evaluation_times', evaluation_times, kwargs,
                            _timeresp_aliases, sigval='T')
    options = dict(solve_ivp_kwargs) if solve_ivp_kwargs else {}
    if kwargs.get('solve_ivp_method', None):
        if kwargs.get('method', None):
            raise ValueError("ivp_method specified more than once")
        options['method'] = kwargs.pop('solve_ivp_method')
    elif kwargs.get('method', None):
        options['method'] = kwargs.pop('method')
    if options.get('method', None) is None:
        options['method'] = 'RK45'
    if kwargs:
        raise TypeError("unrecognized keyword(s): ", str(kwargs))

    if isinstance(sys, (list, tuple)):
        return TimeResponseList([input_output_response(
            s, timepts=T, inputs=U, initial_state=X0, params=params,
            ignore_errors=ignore_errors, transpose=transpose, return_states=return_x,
            squeeze=squeeze, evaluation_times=t_eval, solve_ivp_kwargs=options,
            engine=engine) for s in sys])
    if not isinstance(sys, (ct.NonlinearIOSystem, ct.TransferFunction)):
        raise TypeError("System of type ", type(sys), " not valid")
    if options.get('t_eval') is not None:
        if isinstance(t_eval, str) and t_eval == 'T':
            t_eval = options.pop('t_eval')
        else:
            raise ValueError("t_eval specified more than once")
    options.pop('t_eval', None)
    method, settings = _solver_settings(options)
    if isinstance(t_eval, str) and t_eval == 'T':
        t_eval = None                     # simulate's default: the output times are T
    sys = _sized(sys, T, U, X0, params)
    diagram = flatten(sys)
    if ct.isdtime(sys, strict=True):
        T, t_eval, diagram = _discrete_times(sys, T, t_eval, diagram)
    labels = dict(output_labels=sys.output_labels, input_labels=sys.input_labels,
                  sysname=sys.name, title="Input/output response for " + sys.name,
                  transpose=transpose, return_x=return_x, squeeze=squeeze,
                  issiso=sys.issiso())
    if diagram.nstates == 0:
        return _static_response(diagram, T, U, t_eval, params, labels)
    success, message = True, None
    with warnings.catch_warnings():
        # which blocks run as Python callbacks is the compiled engine's business; a caller
        # who reads failures from the response hears of stiffness there too
        warnings.simplefilter("ignore", PythonBlockNotice)
        if ignore_errors:
            warnings.simplefilter("ignore", StiffnessWarning)
        resp = simulate(diagram, T, inputs=U, initial_state=X0, params=params,
                        t_eval=t_eval, method=method, engine=engine, progress=False,
                        partial=ignore_errors, **settings)
    if not getattr(resp, "success", True):
        # python-control's words first: callers match them (phase_plane_plot's warning)
        success, message = False, "solve_ivp failed: ivdrem's simulator: " + resp.message
    out = TimeResponseData(resp.t, resp.y, resp.x, resp.u, params=params,
                           state_labels=sys.state_labels, success=success,
                           message=message, **labels)
    out.stats = resp.stats
    return out


def _sized(sys, T, U, X0, params):
    """`sys`, or a copy with the sizes it leaves open (None) found as python-control finds
    them: inputs from U, states from X0, outputs from the output function at T[0]."""
    if isinstance(sys, ct.InterconnectedSystem) or not isinstance(sys, ct.NonlinearIOSystem) \
            or None not in (sys.ninputs, sys.nstates, sys.noutputs):
        return sys
    out = copy.copy(sys)
    T = np.atleast_1d(np.asarray(T, dtype=float))
    if out.ninputs is None:
        if isinstance(U, (list, tuple)) and len(U) != T.size:
            n = sum(1 if np.ndim(u) == 0 else
                    (np.shape(u)[0] if np.ndim(u) == 2 or np.size(u) != T.size else 1)
                    for u in U)
        else:
            a = np.asarray(U, dtype=float)
            n = a.shape[0] if a.ndim == 2 else (1 if a.ndim == 0 or a.size == T.size
                                                 else a.size)
        out.set_inputs(n)
    if out.nstates is None:
        parts = X0 if isinstance(X0, (list, tuple)) else [X0]
        out.set_states(int(sum(np.size(x) for x in parts)))
    if out.noutputs is None:
        if out.outfcn is None:
            out.set_outputs(out.nstates)
        else:
            x0 = np.zeros(out.nstates)
            out.set_outputs(int(np.size(evaluate_output(out, T[0], x0, np.zeros(out.ninputs),
                                                        params))))
    return out


def _discrete_times(sys, T, t_eval, diagram):
    """(timepts, t_eval, diagram) of a discrete-time system, with python-control's rules:
    the output times (t_eval, default T) equally spaced by the sample period dt (for
    dt = True, the spacing is the period); the run starts at the first of them."""
    times = np.asarray(T if t_eval is None else t_eval, dtype=float)
    if times.ndim != 1 or times.size < 2:
        raise ValueError("parameter `t_eval`: a discrete-time response needs at least two "
                         "equally spaced times")
    dt = times[1] - times[0]
    if not np.allclose(times[1:] - times[:-1], dt):
        raise ValueError("parameter `t_eval`: time values must be equally spaced")
    if sys.dt is not True and not np.isclose(dt, sys.dt):
        raise ValueError("Time steps `T` must be equal to sampling time")
    if any(leaf.dt is True for leaf in diagram.syslist):
        # an unspecified timebase: one update per output time, as python-control steps
        diagram = copy.copy(diagram)
        diagram.syslist = [_with_period(leaf, dt) if leaf.dt is True else leaf
                           for leaf in diagram.syslist]
        diagram.dt = dt
    return times, None, diagram


def _with_period(leaf, dt):
    out = copy.copy(leaf)
    out.dt = float(dt)
    return out


def _static_response(diagram, T, U, t_eval, params, labels):
    """A system without states has nothing to integrate: its outputs at the output times
    (python-control evaluates them the same way), with the inputs interpolated as
    ``simulate`` interpolates them."""
    resp_t = np.asarray(T if t_eval is None else t_eval, dtype=float)
    # simulate's input conventions, checked and interpolated at the output times
    private = PrivateDiagram(diagram, params)
    values, times = _input_table(private.diagram, U, np.asarray(T, float))
    if times is None:
        u = np.repeat(values.reshape(-1, 1), resp_t.size, axis=1)
    else:
        u = interpolate_inputs(times, values, resp_t)
    y = np.column_stack([private.out(t, np.zeros(0), u[:, i])
                         for i, t in enumerate(resp_t)]) if resp_t.size else \
        np.zeros((diagram.noutputs, 0))
    return TimeResponseData(resp_t, y, None, u, params=params, **labels)


def drop_in(**options):
    """:func:`input_output_response` with simulate's options fixed (e.g. ``engine``)."""
    return functools.wraps(input_output_response)(
        functools.partial(input_output_response, **options))


# --------------------------------------------------------------------------- installing
def _bindings(value):
    """[(module, attribute)] of every binding of `value` in the control package's modules
    (and the test modules under it) loaded now."""
    found = []
    for name, module in list(_sys.modules.items()):
        if module is None or not (name == "control" or name.startswith("control.")):
            continue
        for attr, v in list(vars(module).items()):
            if v is value:
                found.append((module, attr))
    return found


@contextlib.contextmanager
def replaced(function):
    """Within the block, every binding of python-control's ``input_output_response`` in
    the modules of the ``control`` package loaded so far is `function`; restored on exit
    (those modules only: a module that copies the binding after entry keeps its copy)."""
    patched = _bindings(PYTHON_CONTROL_SIMULATOR)
    for module, attr in patched:
        setattr(module, attr, function)
    try:
        yield function
    finally:
        for module, attr in patched:
            if getattr(module, attr, None) is function:
                setattr(module, attr, PYTHON_CONTROL_SIMULATOR)


def installed(**options):
    """Context manager: python-control's ``input_output_response`` (``ct.`` and every
    binding inside the package: ``control.optimal``, ``forced_response`` on a nonlinear
    system, ``phase_plane_plot``, ``stochsys``) is ivdrem's :func:`input_output_response`
    with `options` (e.g. ``engine="reference"``) within the block::

        with ivdrem.pycontrol.installed():
            resp = ct.input_output_response(sys, T, U, X0)

    Limits: a module outside ``control`` that did ``from control import
    input_output_response`` before the block keeps python-control's; calls running in
    other threads meanwhile see ivdrem's."""
    return replaced(drop_in(**options))
