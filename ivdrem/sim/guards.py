"""Cost guards: what a run will cost, estimated before it starts, and refused beyond limits.

Two numbers are known before the first step:

* the memory of the output grid: ``ceil(t_end / dt_out) + 1`` samples of every output (and
  of every state when ``return_states``), 8 bytes each;
* the number of steps: exactly ``ceil(t_end / h)`` for a fixed-step method (RK4), a lower
  bound ``t_end / h_max`` for an adaptive one (its steps never exceed ``h_max``; for
  Dormand-Prince the loop's stiffness makes the real count larger: ~140 000 steps against
  the bound 30 000 for the paper's 300 s run, docs/performance.md).  Which of the two a
  method is, the method registry says (:mod:`ivdrem.sim.methods`, ``adaptive``).

For the paper's 2-link loop the commands also know what a run really costs: its step
counts and times per step measured per law and engine (:data:`PAPER_LOOP_STEPS_300S`,
:data:`SECONDS_PER_STEP`); :func:`check_run_time` refuses a run (or the set of runs of a
command) estimated beyond :data:`MAX_RUN_SECONDS`, with the estimate (the reference
engine's default ``paper``: about 40 minutes).

A run beyond :data:`MAX_OUTPUT_BYTES` or :data:`MAX_STEPS` (per engine) is refused with
:class:`CostLimitError` giving the numbers; ``allow_long=True`` (``--allow-long`` on the
command line) lifts both limits.  An adaptive run whose lower bound already exceeds its
``max_steps`` cannot finish and is refused regardless.  ``h_max`` and ``dt_out`` have
fixed lower bounds (:data:`H_MAX_MIN`, :data:`DT_OUT_MIN`) that no flag lifts: below them
the step or the sample spacing is a typo, not a plan.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from .methods import DEFAULT_METHOD, method_info
from .sampled import sample_period

__all__ = ["CostLimitError", "CostEstimate", "estimate_cost", "check_cost",
           "check_bounds", "MAX_OUTPUT_BYTES", "MAX_STEPS", "H_MAX_MIN", "DT_OUT_MIN",
           "DEFAULT_H_MAX", "check_diagram_cost", "paper_loop_steps", "check_run_time",
           "run_seconds", "SECONDS_PER_STEP", "MAX_RUN_SECONDS", "PAPER_LOOP_STEPS_300S",
           "oscillation_steps", "STEPS_PER_PERIOD_MIN", "check_interconnect_size",
           "interconnect_bytes", "MAX_INTERCONNECT_BYTES", "tolerance_factor",
           "PAPER_LOOP_STEPS_BY_RTOL"]

#: Largest output grid (returned samples of outputs and states), bytes: 2 GiB.
MAX_OUTPUT_BYTES = 2 * 2**30
#: Largest lower bound on the step count, per engine.  Compiled: ~45 µs per
#: Dormand-Prince step of the paper's loop (docs/performance.md: 12.5 s for 2 x 140 000
#: steps), so 1e7 steps is about 8 minutes; reference (python-control evaluation, ~300x
#: slower per step): 1e5 steps is about 25 minutes.
MAX_STEPS = {"compiled": 10_000_000, "reference": 100_000}
#: Smallest accepted h_max (s) and output spacing dt_out (s).
H_MAX_MIN = 1e-6
#: Smallest accepted output spacing dt_out (s).
DT_OUT_MIN = 1e-6
#: The simulator's largest default h_max (it takes min(0.05, T/4) for the shortest delay T).
DEFAULT_H_MAX = 0.05


#: Measured on the paper's closed loop (2-link arm, default configuration; ivdrem 300 s
#: runs, Rodas5P, default tolerances): accepted (implicit Rodas5P, explicit BS23) steps
#: over 300 s.  Rodas5P is accuracy-bound there (steps grow like t_end,
#: docs/simulation.md); composite learning's steps are pinned to its max-hold's grid, most
#: of them explicit (stats "explicit_steps").
PAPER_LOOP_STEPS_300S = {("iv-drem", "rodas5p"): (5863, 0),
                         ("composite-learning", "rodas5p"): (6032, 19992)}
#: Dormand-Prince on the same loop is stability-bound (steps grow like t_end**2):
#: ~140 000 steps for 300 s (docs/performance.md).
PAPER_LOOP_DP45_STEPS_300S = 140_000
#: Measured seconds per accepted step on the paper's loop, per engine: (a step with a
#: Jacobian and an LU: Rodas5P, or any step of an explicit method; an explicit BS23 step
#: of a pinned Rodas5P run).  Compiled: 200 µs (IV-DREM, 1.18 s for 5 863 steps), 23 µs
#: (composite learning, 0.59 s for 26 024 steps); reference (python-control evaluation,
#: forward-difference Jacobian of 60 states): 0.19 s (IV-DREM, 3 s), 7.5 ms (composite
#: learning, 8 s: 7 989 of 7 994 steps explicit).
SECONDS_PER_STEP = {"compiled": (2.0e-4, 2.3e-5), "reference": (0.19, 7.5e-3)}
#: Longest estimated wall time (s) accepted without allow_long: 30 minutes.
MAX_RUN_SECONDS = 1800.0


#: Rodas5P's accepted steps on the paper's IV-DREM loop against its rtol (atol = rtol/100),
#: over 10 s and 30 s: {rtol: (steps over 10 s, steps over 30 s)}, measured (2 cores).
#: Down to rtol 1e-8 the steps grow like rtol^-0.23 (a 4th-order error estimate: about
#: rtol^-1/5) and like t_end; tighter, rounding limits the step and the count grows faster
#: than t_end (t_end^1.2 at 1e-10, t_end^1.7 at 1e-12: 16 k, 104 k steps for 10, 30 s, and
#: 399 k for 60 s, so a 300 s run at 1e-12 is millions of steps).
PAPER_LOOP_STEPS_BY_RTOL = {2e-4: (140, 437), 1e-6: (480, 1498), 1e-8: (1328, 4138),
                            1e-10: (3713, 14_000), 1e-12: (16_186, 103_658)}


def _steps_at(row, t_end):
    """Steps of a (10 s, 30 s) row at t_end: the power law through its two points."""
    s10, s30 = row
    b = math.log(s30 / s10) / math.log(3.0)
    return s30 * (t_end / 30.0) ** b


def tolerance_factor(rtol, t_end, default_rtol=2e-4):
    """(steps at `rtol` / steps at the default rtol over t_end, source) for Rodas5P on the
    paper's loop, from :data:`PAPER_LOOP_STEPS_BY_RTOL`: interpolated in log rtol, each row
    extrapolated in t_end by its own growth; beyond the tightest row, extended by the last
    two rows' slope.  1 for an rtol at or above the default."""
    if rtol is None or not rtol < default_rtol:
        return 1.0, None
    t_end = max(float(t_end), 1e-9)
    rows = sorted(PAPER_LOOP_STEPS_BY_RTOL.items(), reverse=True)    # loosest first
    logs = [(math.log10(r), math.log(_steps_at(row, t_end))) for r, row in rows]
    x = math.log10(rtol)
    (x0, y0), (x1, y1) = next(((a, b) for a, b in zip(logs, logs[1:]) if b[0] <= x),
                              (logs[-2], logs[-1]))
    y = y0 + (y1 - y0) * (x - x0) / (x1 - x0)
    base = math.log(_steps_at(PAPER_LOOP_STEPS_BY_RTOL[default_rtol], t_end)) \
        if default_rtol in PAPER_LOOP_STEPS_BY_RTOL else logs[0][1]
    factor = max(1.0, math.exp(y - base))
    return factor, (f"rtol = {rtol:g}: {factor:.3g}x the steps of rtol {default_rtol:g} "
                    f"over {t_end:g} s (measured at rtol 2e-4 ... 1e-12, 10 and 30 s)")


def paper_loop_steps(law, method, t_end, rtol=None):
    """((steps, explicit steps), source) the paper's loop takes for `law` over t_end with
    an adaptive `method`, from the measured table above (a law not measured takes the
    largest count measured); None for a method without a measurement.  A Rodas5P `rtol`
    below the default multiplies the implicit steps (:func:`tolerance_factor`; the
    explicit ones follow composite learning's sample grid)."""
    found = _measured_steps(law, method, t_end)
    if found is None or method != "rodas5p":
        return found
    factor, why = tolerance_factor(rtol, t_end, method_info(method).rtol)
    if why is None:
        return found
    (imp, exp), src = found
    return (imp * factor, exp), f"{src}; {why}"


def _measured_steps(law, method, t_end):
    t_end = float(t_end)
    scale = t_end / 300.0
    if method == "dp45":
        return ((PAPER_LOOP_DP45_STEPS_300S * scale ** 2, 0.0),
                f"{PAPER_LOOP_DP45_STEPS_300S:g} steps per 300 s measured, growing like "
                "t_end**2 (stiffness)")
    table = {lw: v for (lw, m), v in PAPER_LOOP_STEPS_300S.items() if m == method}
    if not table:
        return None
    src = f"measured for {law}" if law in table else "the largest count measured"
    imp, exp = table[law] if law in table else max(table.values(), key=sum)
    return (imp * scale, exp * scale), f"{(imp + exp) / 300:.3g} steps/s, {src}"


#: Accepted steps per period of the fastest sinusoid in the loop (disturbance or
#: reference), at least: measured on the paper's loop over 2 s with ω from 1e3 to 1e4
#: rad/s (the configuration's limit), both default laws, Rodas5P and DP45 at their default
#: tolerances: 1.57 to 6.37 steps per period, fewest at the highest ω.
STEPS_PER_PERIOD_MIN = 1.0


def oscillation_steps(omega_max, t_end):
    """((steps, 0), source): a lower bound on the steps of an adaptive method that must
    follow a sinusoid of ω_max rad/s for t_end seconds (:data:`STEPS_PER_PERIOD_MIN`)."""
    periods = float(omega_max) * float(t_end) / (2 * math.pi)
    return ((STEPS_PER_PERIOD_MIN * periods, 0.0),
            f"at least {STEPS_PER_PERIOD_MIN:g} step per period of the fastest sinusoid, "
            f"ω = {float(omega_max):g} rad/s: {periods:.3g} periods")


def run_seconds(steps, engine="compiled"):
    """Estimated wall time (s) of (steps, explicit steps) on `engine`."""
    per, per_explicit = SECONDS_PER_STEP.get(engine, SECONDS_PER_STEP["compiled"])
    return steps[0] * per + steps[1] * per_explicit


def check_run_time(wall, source, *, engine="compiled", allow_long=False, what="the run",
                   limit_s=None):
    """Refuse a run (or runs) whose estimated wall time `wall` (s; :func:`run_seconds`)
    exceeds :data:`MAX_RUN_SECONDS`, giving the estimate and its `source`."""
    limit = MAX_RUN_SECONDS if limit_s is None else limit_s
    if wall > limit and not allow_long:
        remedies = ["shorten t_end"]
        if engine != "compiled":
            remedies.append("use engine='compiled' (command line: --engine compiled)")
        if "rtol =" in source:
            remedies.append("raise solver.rtol (the default of the method is priced "
                            "from its own step counts)")
        raise CostLimitError(
            f"{what} would take about {_duration(wall)} on the {engine} engine ({source}; "
            f"measured time per step, ivdrem.sim.guards), above the limit of "
            f"{_duration(limit)}: {', '.join(remedies)}, or allow it with allow_long=True "
            "(command line: --allow-long)")
    return wall


def _duration(s):
    return f"{s / 3600:.1f} h" if s >= 3600 else f"{s / 60:.0f} min" if s >= 60 else \
        f"{s:.0f} s"


class CostLimitError(ValueError):
    """A run refused before it starts because of its estimated memory or step count."""


def _gib(nbytes: float) -> str:
    if nbytes >= 2**40:
        return f"{nbytes / 2**40:.3g} TiB"
    if nbytes >= 2**30:
        return f"{nbytes / 2**30:.3g} GiB"
    return f"{nbytes / 2**20:.3g} MiB"


@dataclass(frozen=True)
class CostEstimate:
    """What a run costs at least: output samples x columns, bytes, steps."""
    t_end: float
    samples: float
    columns: int
    bytes: float
    steps_min: float
    step_source: str      # "t_end / h" or "t_end / h_max", with the numbers
    step_knob: str = "h_max"   # what sets steps_min: "h", "h_max" or "the sample period"

    def memory_text(self) -> str:
        return (f"{self.samples:.3g} samples x {self.columns} signals x 8 bytes = "
                f"{_gib(self.bytes)}")


def _positive(x) -> float | None:
    """x as a float if it is a finite number > 0, else None (the simulator's own checks
    report those values; the guard only prices valid ones)."""
    try:
        f = float(x)
    except (TypeError, ValueError):
        return None
    return f if f > 0 and math.isfinite(f) else None


def check_bounds(*, h_max=None, dt_out=None) -> None:
    """Raise ValueError for an ``h_max`` or ``dt_out`` below its documented lower bound."""
    for name, value, low in (("h_max", h_max, H_MAX_MIN), ("dt_out", dt_out, DT_OUT_MIN)):
        value = _positive(value)
        if value is not None and value < low:
            raise ValueError(f"{name} = {float(value):g} s is below its lower bound "
                             f"{low:g} s (ivdrem.sim.guards)")


def estimate_cost(t_end, *, noutputs, nstates=0, method=DEFAULT_METHOD, h=1e-3, h_max=None,
                  dt_out=0.01, return_states=True, samples=None,
                  sample_period=None) -> CostEstimate:
    """What simulating ``t_end`` seconds costs at least (see the module docstring);
    ``samples``: the number of output times when they are given as an array;
    ``sample_period``: the shortest period of the diagram's sampled blocks, each of whose
    sample times ends a step (:mod:`ivdrem.sim.sampled`), so at least ``t_end / period``
    steps whatever the method.  An unknown method is a ValueError naming the valid ones."""
    info = method_info(method)
    t_end = float(t_end)
    dt_out = min(_positive(dt_out) or t_end, t_end)
    if samples is None:
        samples = math.ceil(t_end / dt_out * (1 - 1e-12)) + 1
    columns = int(noutputs) + (int(nstates) if return_states else 0)
    name = _step_name(info)
    step = _positive(h) if info.fixed_step else \
        (DEFAULT_H_MAX if h_max is None else _positive(h_max))
    if step is None:
        steps, src = 0.0, f"{name} invalid"
    elif info.fixed_step:
        # the loop's own count: steps at t0 + k h until t_end - 1e-9 h (_stepper_codes.step_loop)
        steps = float(max(math.ceil(t_end / step - 1e-9), 1))
        src = f"t_end / h = {t_end:g} / {step:g} rounded up: fixed-step {info.name}"
    else:
        steps, src = t_end / step, f"t_end / {name} = {t_end:g} / {step:g}"
    knob = name
    period = _positive(sample_period)
    forced = 0 if period is None else math.ceil(t_end / period - 1e-9)
    if forced > steps:
        steps, knob = float(forced), "the sample period"
        src = (f"t_end / sample period = {t_end:g} / {period:g}: a sampled block forces a "
               "step at every sample time")
    return CostEstimate(t_end, float(samples), columns, float(samples) * columns * 8.0,
                        steps, src, knob)


def _step_name(info) -> str:
    """The argument that sets a method's step count: h (fixed step) or h_max."""
    return "h" if info.fixed_step else "h_max"


def check_cost(t_end, *, noutputs, nstates=0, method=DEFAULT_METHOD, engine="compiled", h=1e-3,
               h_max=None, dt_out=0.01, return_states=True, max_steps=None,
               allow_long=False, max_bytes=None, max_steps_estimate=None,
               what="the run", samples=None, sample_period=None) -> CostEstimate:
    """Refuse a run that is certain to be too big or too long, before it starts.

    Raises ValueError (bounds of ``h_max``/``dt_out``) or :class:`CostLimitError`; returns
    the :class:`CostEstimate` otherwise.  ``max_bytes`` and ``max_steps_estimate`` override
    :data:`MAX_OUTPUT_BYTES` and :data:`MAX_STEPS` (tests use small ones).
    """
    check_bounds(h_max=h_max, dt_out=dt_out)
    est = estimate_cost(t_end, noutputs=noutputs, nstates=nstates, method=method, h=h,
                        h_max=h_max, dt_out=dt_out, return_states=return_states,
                        samples=samples, sample_period=sample_period)
    info = method_info(method)
    knob = est.step_knob
    if info.adaptive and max_steps is not None and est.steps_min > max_steps:
        raise CostLimitError(
            f"{what} cannot finish: it needs at least {est.steps_min:.3g} steps "
            f"({est.step_source}), more than max_steps = {int(max_steps)}; raise {knob} "
            f"or shorten t_end")
    if allow_long:
        return est
    limit_b = MAX_OUTPUT_BYTES if max_bytes is None else max_bytes
    if est.bytes > limit_b:
        raise CostLimitError(
            f"{what} would record {est.memory_text()} of output (t_end = {est.t_end:g} s, "
            f"dt_out = {est.t_end / max(est.samples - 1, 1):g} s), above the limit of "
            f"{_gib(limit_b)}: raise dt_out, shorten t_end, or allow it with "
            f"allow_long=True (command line: --allow-long)")
    limit_s = MAX_STEPS.get(engine, MAX_STEPS["compiled"]) if max_steps_estimate is None \
        else max_steps_estimate
    if est.steps_min > limit_s:
        raise CostLimitError(
            f"{what} needs at least {est.steps_min:.3g} steps ({est.step_source}), above "
            f"the limit of {limit_s:.3g} steps for the {engine} engine: raise "
            f"{knob}, shorten t_end, or allow it with "
            f"allow_long=True (command line: --allow-long)")
    return est


def check_diagram_cost(diagram, t_end, **kwargs) -> CostEstimate:
    """:func:`check_cost` with the output and state counts of a closed diagram and the
    shortest period of its sampled blocks (discrete-time blocks or their stand-ins)."""
    periods = [p for p in map(sample_period, getattr(diagram, "syslist", ())) if p > 0]
    return check_cost(t_end, noutputs=diagram.noutputs, nstates=diagram.nstates,
                      sample_period=min(periods, default=None), **kwargs)


#: Largest memory (bytes) the dense maps of one ``ct.interconnect`` may take: the limit of
#: the output grid, and never more than half of this machine's memory.  python-control
#: keeps a dense connection map of every block input against every block output (plus the
#: input and output maps): at nθ = 134 (a 20-link chain) that was 105 GiB, requested after
#: 185 s of work.
MAX_INTERCONNECT_BYTES = MAX_OUTPUT_BYTES


def _physical_memory() -> float | None:
    try:
        import os
        return float(os.sysconf("SC_PAGE_SIZE")) * float(os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return None


def interconnect_bytes(ninputs, noutputs, n_ext_inputs=0, n_ext_outputs=0) -> float:
    """Bytes of the dense maps python-control's InterconnectedSystem holds for blocks with
    `ninputs` inputs and `noutputs` outputs in all: connect_map (inputs x outputs),
    input_map (inputs x external inputs), output_map (external outputs x (outputs +
    inputs)), float64 each."""
    return 8.0 * (ninputs * noutputs + ninputs * n_ext_inputs
                  + n_ext_outputs * (noutputs + ninputs))


def check_interconnect_size(blocks, *, n_ext_inputs=0, n_ext_outputs=0, what="the diagram",
                            max_bytes=None):
    """Refuse, before ``ct.interconnect`` allocates them, dense maps beyond
    :data:`MAX_INTERCONNECT_BYTES` (or half the machine's memory), with the numbers.
    Returns the estimate (bytes) otherwise."""
    nin = sum(int(b.ninputs) for b in blocks)
    nout = sum(int(b.noutputs) for b in blocks)
    nx = sum(int(b.nstates) for b in blocks)
    need = interconnect_bytes(nin, nout, n_ext_inputs, n_ext_outputs)
    limit = MAX_INTERCONNECT_BYTES if max_bytes is None else float(max_bytes)
    ram = _physical_memory()
    if ram is not None and max_bytes is None:
        limit = min(limit, 0.5 * ram)
    if need > limit:
        raise CostLimitError(
            f"{what} is too large to assemble: {len(blocks)} blocks with {nx:,} states, "
            f"{nin:,} block inputs and {nout:,} block outputs; python-control's dense "
            f"connection maps alone take {nin:,} x {nout:,} x 8 bytes = {_gib(need)}, above "
            f"the limit of {_gib(limit)} (ivdrem.sim.guards): use a model with fewer "
            "parameters (URDF joints=[...] to lock joints, no friction terms)")
    return need


def loop_states(n, ntheta) -> int:
    """States of the IV-DREM closed loop (paper mixing) of an arm with `n` joints and
    `ntheta` parameters, 2nθ² + 5n·nθ + 3nθ + 4n, known before any block is built; equal
    to the built loop's count on the 2-link and planar-3 arms (tests/test_user_round_two.py)."""
    n, nt = int(n), int(ntheta)
    return 2 * nt * nt + 5 * n * nt + 3 * nt + 4 * n
