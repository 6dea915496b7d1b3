"""The compiled path: one numba module generated from a diagram, cached on disk.

The generator reads the diagram's subsystem list and connection map (through
:class:`~ivdrem.sim.plan.DiagramPlan`) and emits:

* the robot models' functions (``model.source(prefix)``, generated from sympy),
* every block's own kernels (their source, renamed, with ``model.f`` -> ``m<k>_f``),
* the stepping template ``_template.py`` verbatim (the same code the reference path runs),
* ``diagram_eval``: block outputs in topological order of direct feedthrough, inputs
  gathered from the connection map, delay outputs from the history, max-hold outputs from
  the held values; then, by mode, the state derivatives, the after-step update of the
  history and holds, or the diagram outputs.

Nothing is fused by hand: a rewired diagram, another law or another robot model compiles
the same way.  A block without kernels (a plain nlsys) cannot be compiled; the error says
so and points to ``engine="reference"``.

The module is written to ``$IVDREM_CACHE_DIR`` (default ``~/.cache/ivdrem``) under the hash
of its source, and numba caches its machine code beside it, so a second process loads it
without compiling.
"""
from __future__ import annotations

import hashlib
import importlib.util
import inspect
import os
import re
import sys
import tempfile
import textwrap
from pathlib import Path

import numpy as np

from .. import __version__
from ..blocks import _kernels
from ..blocks._core import kernel_args
from . import _template

__all__ = ["CompiledEngine", "generate_source", "cache_dir", "CompileError"]

_ALLOWED_GLOBALS = {"np", "math", "model"} | {k for k in dir(_kernels) if not k.startswith("_")}
_modules = {}


class CompileError(ValueError):
    """A diagram that the compiled path cannot turn into numba code."""


def cache_dir() -> Path:
    d = os.environ.get("IVDREM_CACHE_DIR")
    if d:
        return Path(d)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "ivdrem"


def _kernel_source(fn, new_name, model_prefix, block_name):
    cv = inspect.getclosurevars(fn)
    if cv.nonlocals:
        raise CompileError(f"kernel {fn.__name__} of block '{block_name}' is a closure "
                           f"(uses {sorted(cv.nonlocals)}); kernels must be module-level functions")
    for g, val in cv.globals.items():
        if g not in _ALLOWED_GLOBALS:
            raise CompileError(
                f"kernel {fn.__name__} of block '{block_name}' uses the global {g!r}, which the "
                f"compiled path cannot see (allowed: np, math, model and ivdrem.blocks._kernels "
                f"helpers). Pass it as a parameter, or simulate with engine='reference'.")
        if g not in ("np", "math", "model") and val is not getattr(_kernels, g, None):
            raise CompileError(f"kernel {fn.__name__} of block '{block_name}': global {g!r} "
                               "shadows an ivdrem.blocks._kernels helper")
    src = textwrap.dedent(inspect.getsource(fn))
    src, k = re.subn(r"^def\s+" + re.escape(fn.__name__) + r"\s*\(", f"def {new_name}(", src,
                     count=1, flags=re.M)
    if k != 1:
        raise CompileError(f"cannot read the source of kernel {fn.__name__} of block '{block_name}'")
    if model_prefix is not None:
        src = re.sub(r"\bmodel\.(\w+)", model_prefix + r"\1", src)
    elif re.search(r"\bmodel\.", src):
        raise CompileError(f"kernel {fn.__name__} of block '{block_name}' calls model "
                           "functions but the block has no model")
    return src


def _runs(pairs):
    """Group [(dst, src)] with unit gain into contiguous runs (dst0, src0, length)."""
    runs = []
    for d, s in pairs:
        if runs and runs[-1][0] + runs[-1][2] == d and runs[-1][1] + runs[-1][2] == s:
            runs[-1][2] += 1
        else:
            runs.append([d, s, 1])
    return runs


def _fill_inputs(plan, indices, ny, lines, ind="    "):
    """Emit us[k] = sum_j C[k, j] ys[j] (+ input_map u_ext) for the given input indices."""
    Cin = np.asarray(plan.diagram.input_map)
    simple, other = [], []
    for k in indices:
        srcs = plan.conn[k]
        ext = np.flatnonzero(Cin[k]) if Cin.size else []
        if len(srcs) == 1 and srcs[0][1] == 1.0 and len(ext) == 0:
            simple.append((k, srcs[0][0]))
        else:
            terms = [f"{g!r} * ys[{j}]" for j, g in srcs]
            terms += [f"{float(Cin[k, j])!r} * ue[{j}]" for j in ext]
            other.append(f"{ind}us[{k}] = " + (" + ".join(terms) if terms else "0.0"))
    for d, s, n in _runs(simple):
        if n == 1:
            lines.append(f"{ind}us[{d}] = ys[{s}]")
        else:
            lines.append(f"{ind}copy_into(us, {d}, ys, {s}, {n})")
    lines += other


def generate_source(plan):
    """Python/numba source of the whole diagram (see module docstring)."""
    d = plan.diagram
    ny = sum(b.sys.noutputs for b in plan.blocks)
    out = [f"# Generated by ivdrem {__version__} from diagram {d.name!r}. Do not edit.",
           "import math", "import numpy as np", "from numba import njit",
           "from ivdrem.blocks._kernels import *", ""]
    jit_names = []
    models, kernels = {}, {}
    for b in plan.blocks:
        spec = b.spec
        if spec is None:
            raise CompileError(f"block '{b.sys.name}' is a plain nlsys without ivdrem kernels; "
                               "the compiled path cannot run it. Use engine='reference' (slow "
                               "but general), or declare the block with ivdrem.blocks.BlockSpec.")
        if spec.kind != "ode":
            continue
        prefix = None
        if spec.model is not None:
            key = spec.model.key
            if key not in models:
                prefix = f"m{len(models)}_"
                models[key] = (prefix, spec.model)
            prefix = models[key][0]
        for role in ("update", "output"):
            fn = getattr(spec, role)
            if fn is None:
                continue
            kk = (fn.__module__, fn.__qualname__, prefix)
            if kk not in kernels:
                name = f"k{len(kernels)}_{fn.__name__}"
                kernels[kk] = (name, _kernel_source(fn, name, prefix, b.sys.name))
    for key, (prefix, model) in models.items():
        out.append(f"# ---- model {model.name} ({key[:12]})")
        out.append(model.source(prefix))
        jit_names += re.findall(r"^def\s+(\w+)\s*\(", model.source(prefix), flags=re.M)
    out.append("# ---- block kernels")
    for name, src in kernels.values():
        out.append(src)
        jit_names.append(name)
    out.append("# ---- stepping template (ivdrem/sim/_template.py, verbatim)")
    tsrc = Path(_template.__file__).read_text()
    out.append(tsrc)
    jit_names += [n for n in re.findall(r"^def\s+(\w+)\s*\(", tsrc, flags=re.M)]

    def kname(b, role):
        fn = getattr(b.spec, role)
        prefix = models[b.spec.model.key][0] if b.spec.model is not None else None
        return kernels[(fn.__module__, fn.__qualname__, prefix)][0]

    def pargs(b):
        return "".join(f", P[{b.index}][{i}]" for i in range(len(b.spec.param_names)))

    def sl(s):
        return f"{s.start}:{s.stop}"

    # one function for the three modes (see _template): signals first, in topological order
    # of direct feedthrough, then the mode's work
    lines = ["def diagram_eval(mode, t, x, P, W, out):", "    ys = W[6]", "    us = W[7]",
             "    ue = W[8]"]
    filled = set()
    for k in plan.order:
        b = plan.blocks[k]
        spec = b.spec
        direct = [int(i) for i in b.direct_inputs] if spec.kind == "ode" else []
        _fill_inputs(plan, direct, ny, lines)
        filled |= set(direct)
        if spec.kind == "ode":
            lines.append(f"    {kname(b, 'output')}(t, x[{sl(b.x)}], us[{sl(b.u)}], "
                         f"ys[{sl(b.y)}]{pargs(b)})")
        elif spec.kind == "delay":
            dl = next(x for x in plan.delays if x["block"] == k)
            lines.append(f"    hist_lookup(W, t - P[{k}][0], {dl['off']}, {dl['size']}, "
                         f"ys[{sl(b.y)}])")
        else:
            hd = next(x for x in plan.holds if x["block"] == k)
            y0 = b.y.start
            lines.append(f"    copy_into(ys, {y0}, W[4], {hd['off']}, {hd['size']})")
            lines.append(f"    ys[{y0 + hd['size']}] = W[5][{hd['k']}]")
    rest = [i for b in plan.blocks for i in range(b.u.start, b.u.stop) if i not in filled]
    _fill_inputs(plan, rest, ny, lines)

    # mode RHS: state derivatives into out
    lines.append("    if mode == RHS:")
    n_upd = 0
    for b in plan.blocks:
        if b.spec.kind == "ode" and b.spec.update is not None and b.sys.nstates:
            lines.append(f"        {kname(b, 'update')}(t, x[{sl(b.x)}], us[{sl(b.u)}], "
                         f"out[{sl(b.x)}]{pargs(b)})")
            n_upd += 1
    lines.append("        return OK")

    # mode AFTER_STEP: push the delay history, update the max-holds
    lines.append("    if mode == AFTER_STEP:")
    if plan.delays:
        lines += [f"        v = np.empty({plan.nd})", f"        dv = np.zeros({plan.nd})",
                  f"        est = np.zeros({plan.nd}, dtype=np.int64)"]
        tmax = []
        for dl in plan.delays:
            a, s = dl["off"], dl["size"]
            lines.append(f"        copy_into(v, {a}, us, {dl['u']}, {s})")
            if dl["hermite"]:
                lines.append(f"        copy_into(dv, {a}, us, {dl['du']}, {s})")
            else:
                lines.append(f"        for _i in range({a}, {a + s}):\n            est[_i] = 1")
            tmax.append(f"P[{dl['block']}][0]")
        lines += ["        st = hist_push(W, t, v, dv, est)", "        if st != OK:",
                  "            return st",
                  f"        hist_trim(W, t - max({', '.join(tmax + ['0.0'])}))"]
    lines.append("        upd = 0")
    for hd in plan.holds:
        lines.append(f"        upd |= hold_update(W, {hd['k']}, {hd['off']}, {hd['size']}, "
                     f"{hd['nvec']}, {hd['nmat']}, us[{hd['u']}:{hd['u'] + hd['size']}], "
                     f"P[{hd['block']}][0])")
    lines.append("        return HOLD_UPDATED if upd else OK")

    # mode RECORD: diagram outputs (output_map over [block outputs, block inputs])
    Om = np.asarray(d.output_map)
    for r in range(Om.shape[0]):
        terms = []
        for j in np.flatnonzero(Om[r]):
            src = f"ys[{j}]" if j < ny else f"us[{j - ny}]"
            g = float(Om[r, j])
            terms.append(src if g == 1.0 else f"{g!r} * {src}")
        lines.append(f"    out[{r}] = " + (" + ".join(terms) if terms else "0.0"))
    lines.append("    return OK")
    out.append("\n".join(lines) + "\n")
    jit_names += ["diagram_eval"]

    out.append("# ---- compile everything with numba, machine code cached beside this file")
    out.append(f"_JIT = {sorted(set(jit_names))!r}")
    out.append("for _n in _JIT:\n    globals()[_n] = njit(cache=True)(globals()[_n])\n")
    return "\n".join(out)


def _load(src):
    h = hashlib.sha256(src.encode()).hexdigest()[:24]
    if h in _modules:
        return _modules[h]
    cdir = cache_dir()
    cdir.mkdir(parents=True, exist_ok=True)
    path = cdir / f"ivdrem_diagram_{h}.py"
    if not path.exists() or path.read_text() != src:
        fd, tmp = tempfile.mkstemp(dir=cdir, suffix=".py.tmp")
        with os.fdopen(fd, "w") as f:
            f.write(src)
        os.replace(tmp, path)
    name = f"ivdrem_diagram_{h}"
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    _modules[h] = mod
    return mod


class CompiledEngine:
    """Runs the generated module; same interface as the reference engine."""

    name = "compiled"

    def __init__(self, plan, params=None):
        self.plan = plan
        self.source = generate_source(plan)
        self.module = _load(self.source)
        P = []
        for b in plan.blocks:
            if b.spec.kind == "ode":
                P.append(kernel_args(b.spec, plan.block_params(b)))
            elif b.spec.kind == "delay":
                P.append((float(next(x["T"] for x in plan.delays if x["block"] == b.index)),))
            else:
                P.append((float(next(x["eps"] for x in plan.holds if x["block"] == b.index)),))
        self.P = tuple(P)

    def chunk(self, method, *args):
        fn = self.module.rk4_chunk if method == "rk4" else self.module.dp45_chunk
        return fn(*args)

    def after_step(self, t, x, W):
        return self.module.diagram_eval(_template.AFTER_STEP, t, x, self.P, W, x)

    def record(self, t, x, W, row):
        self.module.diagram_eval(_template.RECORD, t, x, self.P, W, row)

    def rhs(self, t, x, W):
        dx = np.zeros_like(x)
        self.module.diagram_eval(_template.RHS, t, x, self.P, W, dx)
        return dx
