"""The closed loop's Jacobian df/dx from block Jacobians chained through the connection map.

Each block ``b`` with kernels is differentiated alone: its local Jacobian

    [ dy_b/dx_b  dy_b/du_b ]        (outputs)
    [ df_b/dx_b  df_b/du_b ]        (state derivatives)

comes from the block's own ``jacobian`` kernel when it has one (closed forms in
:mod:`ivdrem.blocks.jacobians`; the library's robot-model blocks build theirs from the
regressors' derivatives generated with the model), otherwise from differences of *its own*
kernels only
(columns perturbed in groups whose rows do not overlap, Curtis-Powell-Reid):

* forward differences, step sqrt(eps) max(|v|, 1), for blocks without a robot model (linear
  or bilinear in their arguments, so the truncation error is nil or small).  The base point
  costs nothing: it is the block's outputs and state derivatives at (t, x), which the
  right-hand-side evaluation that gathers the signals has just computed, so a group costs
  one kernel call;
* central differences, step eps^(1/3) max(|v|, 1) (accurate to about eps^(2/3) relative),
  for blocks that call the robot model without a kernel of their own (a user's block): their trigonometric terms, multiplied by gains such
  as mu(t), make forward differences' rounding error eps |f| / h reach 1e-6 of an entry
  (measured on planar_arm(3)); two kernel calls per group.

The chain rule then follows the same topological order as the right-hand side: for the blocks in order of direct feedthrough

    du_b/dx = sum_j C[b, j] dy_j/dx         (connection map; diagram inputs are constants)
    dy_b/dx = dy_b/dx_b E_b + dy_b/du_b du_b/dx

and finally df_b/dx = df_b/dx_b E_b + df_b/du_b du_b/dx (E_b selects the block's states).
Transport-delay outputs come from the history at t - T and max-hold outputs are held
values, so both are constants here (their rows of dy/dx are empty).

Sparsity is fixed when the diagram's tables are built: each block's kernels are probed
(in Python; compiled by numba for a large block without a robot model; through the
compiled C-callable wrappers the run uses for a robot-model block whose model is its C
library in both paths, a URDF arm: the same values bit for bit, checked, and so the same
pattern, :func:`wrapper_probe_applies`) at a few random
points (random states, inputs and parameter values, so that a gain that is 0
today, or a diagonal matrix parameter, does not hide an entry once it changes; parameter
values are not part of the compiled code).  An entry is structural when a difference of
the kernel's output is not exactly zero at any probe.  A block with a Jacobian kernel of its
own and no robot model gives its pattern from that kernel at the same points instead (one
call per point, :func:`_jacobian_pattern`; the difference probe's entries on every library
block).  The Jacobian then only
touches structural nonzeros: the chain is a list of multiply-adds over slots of a flat
array, each row's slots consecutive in column order so that the multiply-adds merge into
runs over consecutive slots (a vectorised loop each; the UR5 loop's 2.08 million in 128,721
runs), run by ``jac_chain`` in ``stepper.c``, which stores df/dx at its positions in the
Newton matrix's filled LU pattern (``tables.jacobian_positions``).  A block's own Jacobian
kernel is read row by row into consecutive factors, so that a row read through rows of a
single entry (the mixing's derivatives with respect to the averaged Psi) is one run of
factors and sources taken one each; and the factors this run's parameter values make
exactly zero (an off-diagonal entry of a diagonal Gamma or K, :func:`_parameter_zeros`)
are left out of the chain, while the pattern keeps their entries.  Neither changes a sum
or its order: df/dx is the same bit for bit.
"""
from __future__ import annotations

import hashlib
import itertools
import re
import sys
from collections import OrderedDict
from contextlib import contextmanager
from functools import lru_cache, partial
from pathlib import Path

import numpy as np

from .._atomic import write_file_atomic
from ..blocks._core import bind_model, kernel_args
from ..compile_cache import PACKAGE_ROOT as _PACKAGE_ROOT, cache_dir
from ..compile_cache import package_digest as _package_digest
from ._compile_child import index_exists
from .foreign import ForeignSpec

__all__ = ["block_pattern", "JacobianProgram", "DeclarationError", "probe_wrappers",
           "wrapper_probe_applies"]

# central-difference step factor eps^(1/3): truncation h^2 and rounding eps/h balance
FD_STEP = float(np.finfo(float).eps ** (1.0 / 3.0))


class DeclarationError(ValueError):
    """A block whose declared structure contradicts what its kernels compute."""


def _random_args(spec, args, rng):
    """Kernel arguments with every non-constant parameter moved randomly (up to 20 %), and
    its exact zeros made small nonzeros, so no structural entry hides behind a value."""
    out = []
    for name, v in zip(spec.param_names, args):
        if name in spec.constants:
            out.append(v)
            continue
        a = np.asarray(v, dtype=float)
        scale = max(float(np.max(np.abs(a), initial=0.0)), 1e-6)
        r = a * rng.uniform(0.8, 1.2, size=a.shape)
        r = np.where(a == 0.0, 1e-3 * scale * rng.uniform(0.5, 1.5, size=a.shape), r)
        out.append(float(r) if np.ndim(v) == 0 else r)
    return out


#: block patterns probed in this process, by what the probe depends on: the probe calls the
#: Python kernels thousands of times (2 s for planar-4, minutes for a real arm), and every
#: simulate() of a diagram needs it again (the calibration of gamma = "auto", then the run)
_PATTERNS: OrderedDict = OrderedDict()
_PATTERNS_MAX = 512


def _value_key(v):
    a = np.asarray(v)
    if a.dtype == object:
        return ("repr", repr(v))
    return (a.dtype.str, a.shape, a.tobytes())


def cached_block_pattern(spec, args, nx, nu, ny, *, seed=0, compiled=None):
    """:func:`block_pattern`, probed once per process for the same kernels, model, sizes,
    seed and parameter values (the probe's inputs, so the pattern is the same bit for bit),
    and kept on disk for the next process when the kernels are ivdrem's own
    (:func:`_pattern_path`).  A block ivdrem did not write (a user's nlsys) is probed every
    time: its functions may read state of their own that a key cannot see.  `compiled`
    (optional): called only if the block is probed, it gives the block's kernels as its
    compiled wrappers (:func:`_wrapper_kernels`; the same pattern bit for bit, so the key
    does not say which way it was probed)."""
    if isinstance(spec, ForeignSpec):
        return block_pattern(spec, args, nx, nu, ny, seed=seed)
    fkey = (_kernel_names((spec.update, spec.output)),
            tuple(None if f is None else id(f.__code__) for f in (spec.update, spec.output)))
    rest = _probe_inputs(spec, args, nx, nu, ny, seed)
    key = (fkey,) + rest
    if key in _PATTERNS:
        _PATTERNS.move_to_end(key)
    else:
        path = _pattern_path(spec, rest)
        found, pat = _read_pattern(path, (ny + nx, nx + nu))
        if not found:
            pat = block_pattern(spec, args, nx, nu, ny, seed=seed,
                                kernels=None if compiled is None else compiled())
            _write_pattern(path, pat)
        _PATTERNS[key] = pat
        while len(_PATTERNS) > _PATTERNS_MAX:
            _PATTERNS.popitem(last=False)
    pat = _PATTERNS[key]
    return None if pat is None else pat.copy()


def _probe_inputs(spec, args, nx, nu, ny, seed):
    """What a probe of `spec`'s kernels reads besides their code: the robot model's key,
    the sizes, the seed, the parameters' names and values."""
    return (spec.model.key if spec.model is not None else None, nx, nu, ny, seed,
            tuple(spec.param_names), tuple(_value_key(a) for a in args))


def _kernel_names(funcs):
    """(module, qualified name) of each kernel (None for a missing one)."""
    return tuple(None if f is None else (f.__module__, f.__qualname__) for f in funcs)


def _own_kernel(f):
    """Whether `f` is a plain module-level function of ivdrem's package (its behaviour then
    follows from the package's source alone; a closure, or a user's function, may not)."""
    if f is None:
        return True
    module = sys.modules.get(getattr(f, "__module__", None) or "")
    file = getattr(module, "__file__", None)
    return (file is not None and _in_package(file)
            and "<locals>" not in f.__qualname__ and getattr(f, "__closure__", None) is None)


@lru_cache(maxsize=256)
def _in_package(file):
    """Whether the module file `file` lies in ivdrem's package (resolved once per file: every
    simulate keys its tables by its blocks' kernels)."""
    return Path(file).resolve().is_relative_to(_PACKAGE_ROOT)


def _pattern_path(spec, rest):
    """Where the probed pattern of `spec` for `rest` (model key, sizes, seed, parameter
    names and values) is kept across processes, or None: only for kernels of ivdrem's
    own package, keyed by the digest of its whole source (so a changed kernel, helper or
    ivdrem version never reads a stale pattern), the kernels' names and `rest`."""
    funcs = (spec.update, spec.output)
    digest = _package_digest()
    if digest is None or not all(_own_kernel(f) for f in funcs):
        return None
    h = hashlib.sha256(digest.encode())
    h.update(repr(_kernel_names(funcs)).encode())
    h.update(repr(rest).encode())
    return cache_dir() / "patterns" / f"{h.hexdigest()[:40]}.npy"


#: what a pattern file holds where the probe found no finite value (block_pattern's None)
_NO_PATTERN = np.zeros(0, dtype=np.int8)


def _read_pattern(path, shape):
    """(True, pattern or None) from the file at `path`, or (False, None) where there is none
    or it is not a pattern of `shape` (a damaged file is probed again and rewritten)."""
    if path is None:
        return False, None
    try:
        a = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError):
        return False, None
    if a.dtype == np.uint8 and a.ndim == 1 and a.size == (shape[0] * shape[1] + 7) // 8:
        pat = np.unpackbits(a, count=shape[0] * shape[1]).reshape(shape).astype(bool)
        pat.setflags(write=False)
        return True, pat
    if a.dtype == _NO_PATTERN.dtype and a.size == 0:
        return True, None
    return False, None


def _write_pattern(path, pat):
    """Keep `pat` at `path` for later processes: written to a temporary and renamed (two
    processes filling the cache at once both succeed); an unwritable cache only costs the
    probe next time."""
    if path is None:
        return
    # packed: a real arm's window integrator alone is 4,000 x 4,000 entries
    data = _NO_PATTERN if pat is None else np.packbits(np.asarray(pat, bool))
    try:
        write_file_atomic(path, lambda fh: np.save(fh, data))
    except OSError:
        pass


#: probe work, in (kernel calls per probe point) x (values each call writes), above which
#: a block's kernels are compiled by numba for the probe: the probe calls them 2 (nx + nu)
#: times per point, so its Python cost grows as the square of a block that writes what it
#: reads (the UR5 loop's window integrator, nx + nu = 3996: 72-130 s in Python, 2-10 s
#: compiled and run).  A compile costs 1 s or more: the UR5's eigen mixing (38 outputs of
#: 1332 inputs, below the bound) probes in 6-8 s in Python and took 15 s compiled
PROBE_COMPILE_WORK = 1_000_000


def _probe_kernels(spec, args, nx, nu, ny):
    """(output, update) kernels for the probe: numba-compiled for a large library block
    without a robot model (the same kernel: its differences are exactly zero where the
    Python kernel's are, entry by entry on the UR5's and the planar loops' blocks), the
    Python kernels otherwise or if numba refuses them."""
    upd = bind_model(spec.update, spec.model) if nx else None
    out = bind_model(spec.output, spec.model)
    if (spec.model is not None or isinstance(spec, ForeignSpec)
            or (nx + nu) * (nx + ny) < PROBE_COMPILE_WORK):
        return out, upd
    try:
        from numba import njit
        jout = njit(out)
        jupd = njit(upd) if upd is not None else None
        x, u, yf = np.full(nx, 0.5), np.full(nu, 0.5), np.zeros(ny + nx)
        with np.errstate(all="ignore"):
            jout(_PROBE_TIME, x, u, yf[:ny], *args)      # compiles for these argument types
            if jupd is not None:
                jupd(_PROBE_TIME, x, u, yf[ny:], *args)
    except Exception:           # numba cannot compile it (or it raised here): Python probe
        return out, upd
    return jout, jupd


def _kernel_probe_applies(spec):
    """Whether `spec`'s pattern comes from its own Jacobian kernel (:func:`_jacobian_pattern`):
    an ivdrem block with a Jacobian kernel and without the robot model.  A block that calls
    the model keeps the difference probe: there the two patterns differ by entries at
    rounding level (cancellations that one sees and the other does not: on the Panda's
    torque observer 329 and 400 of 14,047 entries), and the run's df/dx, which reads the
    kernel at the pattern's entries, would change in its last bits."""
    return (getattr(spec, "jacobian", None) is not None and spec.model is None
            and not isinstance(spec, ForeignSpec) and not _compiles_first(spec.jacobian))


def wrapper_probe_applies(spec):
    """Whether the difference probe of `spec`'s block runs its compiled update and output
    wrappers (:func:`_wrapper_kernels`) instead of its Python kernels: a block of ivdrem's
    own kernels (module-level functions of the package) with a robot model whose functions
    are its C library in both paths (a URDF arm with a C compiler: ctypes from Python, the
    same symbols from numba, ivdrem.models._c_engine).  The rule is written once, here,
    and depends on nothing a compile child changes.  There, the two paths compute the same
    values bit for bit: the model's functions are one machine code, and the kernels' own
    arithmetic (loops of sums, differences, products and quotients) is IEEE float64 in
    both (numba without fastmath contracts nothing): checked at the probe's random points on every robot-model block
    of the UR5's and a planar URDF arm's loops, both laws (tests/test_probe_compiled.py),
    and of the Panda's (docs/performance.md).
    A model whose Python functions are not the compiled ones (a sympy model, the paper's
    2-link arm; a URDF arm without a C compiler, whose numba path compiles the rigid-body
    kernels) keeps the Python probe."""
    model = spec.model
    from numba.core import config as numba_config
    if (model is None or isinstance(spec, ForeignSpec) or numba_config.DISABLE_JIT
            or not (_own_kernel(spec.update) and _own_kernel(spec.output))
            or not callable(getattr(model, "engine_source", None))):
        return False
    from ..models import _c_engine
    return _c_engine.load(model) is not None


def probe_wrappers(plan, modules):
    """The wrapper modules (of `modules`, ivdrem.sim.compiled.KernelModules) the probe of
    `plan`'s blocks imports (:func:`wrapper_probe_applies`), in the blocks' order: the
    compiled engine gives them to its compile child first, in this order (the order the
    probe takes them in, after the other blocks, :func:`_local_patterns`), so that the
    child compiles them while this process probes the other blocks, and the two processes
    never compile the model's functions at the same time."""
    names = []
    for b in plan.blocks:
        if b.spec is None or b.spec.kind != "ode" or not wrapper_probe_applies(b.spec):
            continue
        for role in ("output", "update") if b.sys.nstates else ("output",):
            k = modules.windex.get((b.index, role))
            if k is not None:
                names.append(modules.wrappers[k][2])
    return names


class _WrapperRaised(ArithmeticError):
    """A compiled wrapper returned non-zero: its kernel raised (an exception cannot cross
    C).  The probe takes it as the Python kernel's exception: it tries another point."""


def _wrapper_kernels(b, modules):
    """(output, update) of block `b` as its compiled C-callable wrappers (numba ``cfunc``
    ``int32(float64 t, int64 x, int64 u, int64 out, int64 p)``) called through ctypes,
    with the Python kernels' signature ``(t, x, u, out, *args)``: `args` (the probe's
    random parameter values) are written into the block's parameter slice p at the slots
    of the layout `modules` hold (``modules.playout``, ``modules.pbase``; a constant is a
    literal in the wrapper and is not written, nor varied by the probe).  The wrapper
    modules are imported here, each under its compile lock
    (``compile_cache.import_generated``): one a compile child has compiled is loaded, one
    it is compiling is waited for, one it has not reached is compiled here (the child then
    loads it).  A kernel that raised (non-zero return) raises :class:`_WrapperRaised`."""
    from ..compile_cache import import_generated
    sources = dict(modules.deps)
    cdir = cache_dir()
    nx = b.sys.nstates
    slots = modules.playout[b.index]
    base = modules.pbase[b.index]
    spans = [(a.offset - base, a.size) for a in slots if hasattr(a, "offset")]
    npar = max((lo + n for lo, n in spans), default=0)

    def load(role):
        wmod = modules.wrappers[modules.windex[(b.index, role)]][2]
        for name in _generated_imports(wmod, sources):
            import_generated(cdir, name, sources[name])
        return import_generated(cdir, wmod, sources[wmod]).wrapper.ctypes

    def kernel(wrapper):
        held = [None, np.zeros(max(npar, 1))]       # the args last written, p

        def call(t, x, u, out, *args):
            kept = held[0]
            if kept is None or any(v is not w for v, w in zip(kept, args)):
                p = held[1]
                for a, v in zip(slots, args):
                    if hasattr(a, "offset"):
                        lo = a.offset - base
                        p[lo:lo + a.size] = np.asarray(v, dtype=float).reshape(-1)
                held[0] = args
            x = np.ascontiguousarray(x, dtype=float)
            u = np.ascontiguousarray(u, dtype=float)
            if out.dtype != np.float64 or not out.flags.c_contiguous:
                raise TypeError("a wrapper writes a contiguous float64 buffer")
            if wrapper(t, x.ctypes.data, u.ctypes.data, out.ctypes.data, held[1].ctypes.data):
                raise _WrapperRaised(f"the compiled kernel of block '{b.sys.name}' raised")
        return call

    out = kernel(load("output"))
    upd = kernel(load("update")) if nx else None
    return out, upd


def _generated_imports(name, sources):
    """The generated modules (robot models, kernels) the generated module `name` imports,
    recursively, in the order of `sources` (a dict in import order)."""
    need, todo = set(), [name]
    while todo:
        for m in _GENERATED_IMPORT.findall(sources[todo.pop()]):
            if m not in need:
                need.add(m)
                todo.append(m)
    return [n for n in sources if n in need]


_GENERATED_IMPORT = re.compile(r"^(?:from|import) (ivdrem_\w+)", flags=re.M)


#: {helper: in numba's cache} read when :func:`helpers_cache_as_now` was entered, or None
_HELPERS_SEEN = None


@contextmanager
def helpers_cache_as_now():
    """Within the block, :func:`_compiles_first` answers from numba's on-disk cache of the
    ivdrem.blocks._kernels helpers as it stood on entry (and from what this process has
    compiled, as outside the block): a compile child started inside
    writes that cache meanwhile, and the probe's way for a block (its Jacobian kernel or
    differences) must not depend on how far the child has come."""
    global _HELPERS_SEEN
    from ..blocks import _kernels
    helpers = (f for name in dir(_kernels) for f in _compiled_functions(getattr(_kernels, name)))
    seen = {h: _in_numba_cache(h) for h in helpers}
    outer, _HELPERS_SEEN = _HELPERS_SEEN, seen
    try:
        yield
    finally:
        _HELPERS_SEEN = outer


def _compiles_first(fn):
    """Whether calling the kernel `fn` would first make numba compile a helper it calls
    (one neither compiled in this process nor in numba's cache).  The probe runs only when
    the patterns are not kept yet, i.e. on a first run, and then such a compile costs more
    than the difference probe it replaces (the mixing's derivatives: 10 s of CPU against
    2.6 s of differences through the mixing step, already compiled for γ "auto"); the
    compile is left to the kernels' wrappers, which share the work between two processes."""
    for name in fn.__code__.co_names:
        compiled = _compiled_functions(fn.__globals__.get(name))
        if compiled and not any(_compiled_or_cached(f) for f in compiled):
            return True
    return False


def _compiled_functions(helper):
    """The njit functions behind `helper`: itself, a mixing function's variants (one
    compiled function per variant, ivdrem.blocks._kernels), or none."""
    if hasattr(helper, "py_func"):
        return (helper,)
    return tuple(getattr(helper, "variants", ()))


def _compiled_or_cached(helper):
    """Whether the njit function `helper` is compiled in this process or in numba's cache
    (as it stood when :func:`helpers_cache_as_now` was entered, within it).  A mixing
    function counts as ready when one of its variants is: a run uses one variant, and the
    kernel probe of another (a user who changed the variant) compiles that one alone."""
    if helper.signatures:
        return True
    if _HELPERS_SEEN is not None and helper in _HELPERS_SEEN:
        return _HELPERS_SEEN[helper]
    return _in_numba_cache(helper)


def _in_numba_cache(helper):
    """Whether numba's on-disk cache holds machine code of the njit function `helper`."""
    try:
        return bool(index_exists(helper._cache))
    except Exception:     # pragma: no cover - numba internals changed: assume not
        return False


#: the time at which a probe evaluates a block's kernels (no particular instant)
_PROBE_TIME = 0.7315


def _probe_points(spec, args, rng, size, n_points):
    """The random points of a probe, (parameter arguments, [x, u]) for each of at most
    4 n_points attempts (the caller stops once n_points gave finite values): entries of
    magnitude 0.5-1.5, every third point with random signs, the others positive."""
    for attempt in range(4 * n_points):
        a = _random_args(spec, args, rng)
        sign = 1.0 if attempt % 3 != 2 else rng.choice([-1.0, 1.0], size=size)
        yield a, sign * rng.uniform(0.5, 1.5, size=size)


def _stacked_evaluation(out, upd, nx, ny):
    """ev(v, a): the block's outputs then its state derivatives at [x, u] = v (copies:
    a kernel may not keep or change its arguments)."""
    def ev(v, a):
        yf = np.zeros(ny + nx)
        out(_PROBE_TIME, v[:nx].copy(), v[nx:].copy(), yf[:ny], *a)
        if upd is not None:
            upd(_PROBE_TIME, v[:nx].copy(), v[nx:].copy(), yf[ny:], *a)
        return yf
    return ev


def _jacobian_pattern(spec, args, nx, nu, ny, *, seed, n_points):
    """The local pattern of a block from its own Jacobian kernel: the entries it makes
    nonzero at `n_points` random points (the difference probe's points, parameters moved
    the same way), one kernel call per point where the difference probe makes 2 (nx + nu).
    An entry the kernel computes as a structural zero is exactly zero; a nonzero one is
    nonzero at a random point with probability one.  On the blocks of the paper's loops,
    planar-3, the UR5 and the Panda this is the difference probe's pattern entry by entry
    (tests/test_jacobian.py), at 0.2-2 % of its time.

    Checked at each point against one central difference of the block's own kernels along
    a random direction w: an output that moves while the kernel's row has no entry (a
    Jacobian kernel that forgets a dependence) sends the block back to the difference probe
    (None is returned), so a kernel cannot make the pattern smaller than what its kernels
    compute.  None also where no point gives finite values."""
    jac = bind_model(spec.jacobian, spec.model)
    out = bind_model(spec.output, spec.model)
    upd = bind_model(spec.update, spec.model) if nx else None
    rng = np.random.default_rng(seed)
    pat = np.zeros((ny + nx, nx + nu), dtype=bool)
    ev = _stacked_evaluation(out, upd, nx, ny)
    good = 0
    for a, v in _probe_points(spec, args, rng, nx + nu, n_points):
        if good >= n_points:
            break
        w = rng.uniform(-1.0, 1.0, size=nx + nu)
        J = np.zeros((ny + nx, nx + nu))
        try:
            with np.errstate(all="ignore"):
                jac(_PROBE_TIME, v[:nx].copy(), v[nx:].copy(), J, *a)
                h = 1e-3 * max(float(np.max(np.abs(v))), 1.0)
                d = ev(v + h * w, a) - ev(v - h * w, a)
        except (ValueError, ArithmeticError):
            continue            # e.g. a model refusing a random state: try another point
        if not (np.all(np.isfinite(J)) and np.all(np.isfinite(d))):
            continue
        nonzero = J != 0.0
        if np.any((d != 0.0) & ~nonzero.any(axis=1)):
            return None         # a row moves that the kernel says depends on nothing
        pat |= nonzero
        good += 1
    return pat if good else None


def block_pattern(spec, args, nx, nu, ny, *, seed=0, n_points=3, kernels=None):
    """Structural nonzeros of a block's local Jacobian, probed from its kernels.

    Returns a boolean array (ny + nx, nx + nu): rows are outputs then state derivatives,
    columns are states then inputs.  A block whose kernels give no finite value at any probe
    point (e.g. a plant whose parameters make M(q) indefinite) returns None: the caller takes
    it as dense within its declaration (correct, only slower), and the run itself reports
    the model's error.  A block with a Jacobian kernel of its own and no robot model gives
    its pattern from that kernel (:func:`_jacobian_pattern`); the others by differences of
    their kernels, column by column (`kernels`, optional: the (output, update) kernels
    to difference instead of the block's Python kernels, :func:`_wrapper_kernels`).
    """
    if _kernel_probe_applies(spec):
        pat = _jacobian_pattern(spec, args, nx, nu, ny, seed=seed, n_points=n_points)
        if pat is not None:
            return pat
    return _difference_pattern(spec, args, nx, nu, ny, seed=seed, n_points=n_points,
                               kernels=kernels)


def _difference_pattern(spec, args, nx, nu, ny, *, seed, n_points, kernels=None):
    """:func:`block_pattern` by central differences of the block's kernels (or of
    `kernels`, (output, update) with the kernels' signature), one column at a time, at
    `n_points` random points: an entry is structural where a difference is not exactly
    zero at any of them."""
    out, upd = _probe_kernels(spec, args, nx, nu, ny) if kernels is None else kernels
    rng = np.random.default_rng(seed)
    pat = np.zeros((ny + nx, nx + nu), dtype=bool)
    ev = _stacked_evaluation(out, upd, nx, ny)
    good = 0
    for a, v in _probe_points(spec, args, rng, nx + nu, n_points):
        if good >= n_points:
            break
        ok = True
        cols = np.zeros_like(pat)
        try:
            with np.errstate(all="ignore"):
                base = ev(v, a)
                ok = bool(np.all(np.isfinite(base)))
                for c in range(nx + nu):
                    if not ok:
                        break
                    h = 1e-3 * max(abs(v[c]), 1.0)
                    vp = v.copy()
                    vp[c] += h
                    vm = v.copy()
                    vm[c] -= h
                    d = ev(vp, a) - ev(vm, a)
                    ok = bool(np.all(np.isfinite(d)))
                    cols[:, c] = d != 0.0
        except (ValueError, ArithmeticError):
            ok = False          # e.g. a model refusing a random state: try another point
        if ok:
            pat |= cols
            good += 1
    if good == 0:
        return None
    return pat


def _rows_of_columns(sub, lo):
    """{column: set of rows + lo} of the nonzeros of the boolean matrix `sub`, its columns
    with any in increasing order (one pass over the nonzeros, not one per column)."""
    cols, rows = np.nonzero(sub.T)                  # by column, then row
    if cols.size == 0:
        return {}
    cut = np.flatnonzero(cols[1:] != cols[:-1]) + 1
    starts = np.concatenate(([0], cut)).tolist()
    ends = np.concatenate((cut, [cols.size])).tolist()
    rows = (rows + lo).tolist()
    return {c: set(rows[a:b]) for c, a, b in zip(cols[starts].tolist(), starts, ends)}


def _color(rows_of_col):
    """Greedy grouping of columns whose row sets are disjoint (Curtis-Powell-Reid): the
    columns by decreasing row count, each into the first group none of its rows is in.
    A group is taken by each row it holds (`taken[row, group]`), so the first free group of
    a column is the first False of the OR of its rows' lines: one vectorised pass per column
    where comparing it with every group in turn was quadratic in Python (the Panda's mixing:
    1,892 columns reading the same 45 rows, 1,892 groups)."""
    cols = sorted(rows_of_col, key=lambda c: -len(rows_of_col[c]))
    if not cols:
        return []
    index = {r: k for k, r in enumerate(sorted(set().union(*rows_of_col.values())))}
    taken = np.zeros((len(index), 16), dtype=bool)
    groups = []
    for c in cols:
        rows = [index[r] for r in rows_of_col[c]]
        busy = taken[rows].any(axis=0) if rows else np.zeros(taken.shape[1], dtype=bool)
        g = int(np.argmin(busy[:len(groups)])) if len(groups) else 0
        if not len(groups) or busy[g]:
            g = len(groups)
            groups.append([])
            if g == taken.shape[1]:
                taken = np.concatenate([taken, np.zeros_like(taken)], axis=1)
        taken[rows, g] = True
        groups[g].append(c)
    return [sorted(g) for g in groups]


def _local_patterns(plan, seed, modules=None):
    """{block index: local pattern (ny + nx, nx + nu)} of the ode blocks with states or
    inputs (probed once per process, cached_block_pattern), each checked against the
    block's declared direct feedthrough.  With the diagram's generated `modules`
    (ivdrem.sim.compiled.KernelModules), a block :func:`wrapper_probe_applies` to is
    probed through its compiled wrappers (:func:`_wrapper_kernels`), after the other blocks
    (a compile child started with them first has compiled them meanwhile); the patterns do
    not depend on the order the blocks are probed in (each block's points are drawn from
    its own seed)."""
    patterns = {}
    through_wrappers = {b.index: modules is not None and b.spec.kind == "ode"
                        and wrapper_probe_applies(b.spec) for b in plan.blocks}
    for b in sorted(plan.blocks, key=lambda b: through_wrappers[b.index]):
        spec = b.spec
        if spec.kind != "ode":
            continue
        nx, nu, ny = b.sys.nstates, b.sys.ninputs, b.sys.noutputs
        if nx + nu == 0:
            continue
        args = kernel_args(spec, plan.block_params(b))
        compiled = partial(_wrapper_kernels, b, modules) if through_wrappers[b.index] else None
        pat = cached_block_pattern(spec, args, nx, nu, ny, seed=seed + b.index,
                                   compiled=compiled)
        direct_local = set(int(i) - b.u.start for i in b.direct_inputs)
        if pat is None:   # not probeable: dense, outputs only on states and direct inputs
            pat = np.ones((ny + nx, nx + nu), dtype=bool)
            for i in range(nu):
                if i not in direct_local:
                    pat[:ny, nx + i] = False
        bad = [c - nx for c in range(nx, nx + nu)
               if pat[:ny, c].any() and (c - nx) not in direct_local]
        if bad:
            labels = [b.sys.input_labels[i] for i in bad]
            raise DeclarationError(
                f"block '{b.sys.name}': its outputs depend on the inputs {labels}, which "
                "the block does not declare as direct feedthrough (BlockSpec.direct); the "
                "right-hand side would read them before they are computed")
        patterns[b.index] = pat
    return {b.index: patterns[b.index] for b in plan.blocks if b.index in patterns}


def _parameter_zeros(plan, patterns, *, seed=0, n_points=3):
    """{block index: boolean mask (ny + nx, nx + nu)} of the structural entries (of the
    local pattern, probed with random parameter values) that this run's own parameter
    values make exactly zero at every state: an off-diagonal entry of a diagonal Gamma in
    the adaptation law (on the Panda's loop 61,166 of the chain's 211,246 runs, 3.56 million
    multiply-adds by an exact zero).  Only blocks with a Jacobian kernel of their own and a
    parameter array holding an exact zero are looked at (an entry can be zero for the run's
    values only through a parameter; nothing is left out of a block that has none), at
    `n_points` random states and inputs, as the pattern's probe; the kernel is called once
    per point.  The chain leaves their multiply-adds out (JacobianProgram); the pattern of
    df/dx, and so the LU's, keeps them, so the run's values are the same bit for bit (the
    chain skipped a zero factor before as well)."""
    zeros = {}
    for b in plan.blocks:
        pat = patterns.get(b.index)
        spec = b.spec
        if pat is None or getattr(spec, "jacobian", None) is None or not pat.any():
            continue
        args = kernel_args(spec, plan.block_params(b))
        if not any(np.ndim(a) > 0 and np.asarray(a).dtype.kind == "f"
                   and (np.asarray(a) == 0.0).any() for a in args):
            continue
        nx, nu, ny = b.sys.nstates, b.sys.ninputs, b.sys.noutputs
        jac = bind_model(spec.jacobian, spec.model)
        rng = np.random.default_rng(seed + b.index)
        zero = pat.copy()
        try:
            with np.errstate(all="ignore"):
                for k in range(n_points):
                    sign = 1.0 if k % 3 != 2 else rng.choice([-1.0, 1.0], size=nx + nu)
                    v = sign * rng.uniform(0.5, 1.5, size=nx + nu)
                    J = np.zeros((ny + nx, nx + nu))
                    jac(_PROBE_TIME, v[:nx].copy(), v[nx:].copy(), J, *args)
                    if not np.all(np.isfinite(J)):
                        raise ArithmeticError("not finite")
                    zero &= J == 0.0
        except (ValueError, ArithmeticError):
            continue                # a kernel refusing a random point: nothing left out
        if zero.any():
            zeros[b.index] = zero
    return zeros


#: Jacobian programs of this process by the structure they are built from: every simulate()
#: of a diagram (the calibration of gamma = "auto", then the run, then the report's) needs
#: the same one, and building it took 3-5 s on the real arms (millions of multiply-adds
#: scheduled in Python)
_PROGRAMS: OrderedDict = OrderedDict()
_PROGRAMS_MAX = 8


def _program_key(plan, patterns, zeros=None):
    """A digest of everything a JacobianProgram reads of `plan`: the blocks' kinds, places
    and sizes, direct inputs, whether they call the robot model or have a Jacobian kernel,
    their local patterns and the entries the run's parameters make zero
    (:func:`_parameter_zeros`), the connection map with its gains and the evaluation
    order."""
    h = hashlib.sha256()
    for i, z in sorted((zeros or {}).items()):
        h.update(repr(("zeros", i, z.shape)).encode())
        h.update(np.packbits(z).tobytes())
    for b in plan.blocks:
        direct = (tuple(int(i) for i in b.direct_inputs) if b.spec.kind == "ode" else ())
        h.update(repr((b.index, b.spec.kind, b.x.start, b.sys.nstates, b.u.start,
                       b.sys.ninputs, b.y.start, b.sys.noutputs, direct,
                       b.spec.model is not None,
                       getattr(b.spec, "jacobian", None) is not None)).encode())
        pat = patterns.get(b.index)
        if pat is not None:
            h.update(repr(pat.shape).encode())
            h.update(np.packbits(pat).tobytes())
    h.update(repr((plan.x0.size, plan.conn, list(plan.order))).encode())
    return h.hexdigest()


def structure_digest(plan, *, seed=0):
    """A digest of everything the compiled engine's tables of `plan` are built from, read
    off the plan without probing: ivdrem's source (the probe, the program's builder, the
    LU's search), and per block its kind, information, kernels (by name), robot model,
    place in the state, input and output vectors, direct inputs, state labels (the LU's
    groups), parameter names (which of them are constants: the probe keeps those) and
    kernel arguments (the parameter values the probe moves and
    :func:`_parameter_zeros` reads); the delays and max-holds, the connection, input and
    output maps, the evaluation order and the probe's `seed`.  The block patterns, the
    Jacobian program and the symbolic LU are functions of these (each kept on disk under
    a key made of some of them).  None where a block's kernels are not ivdrem's own (a
    user's nlsys, an FMU): what they compute cannot be keyed."""
    digest = _package_digest()
    if digest is None:
        return None
    h = hashlib.sha256(digest.encode())
    for b in plan.blocks:
        spec = b.spec
        if spec is None or isinstance(spec, ForeignSpec):
            return None
        funcs = (spec.update, spec.output, spec.jacobian)
        if not all(_own_kernel(f) for f in funcs):
            return None
        h.update(repr((b.index, spec.name, spec.kind, repr(spec.info), _kernel_names(funcs),
                       spec.model.key if spec.model is not None else None,
                       tuple(getattr(spec, "param_names", ())),
                       sorted(getattr(spec, "constants", None) or ()),
                       repr(getattr(spec, "kernel_names", None)),
                       (b.x.start, b.x.stop), (b.u.start, b.u.stop), (b.y.start, b.y.stop),
                       [int(i) for i in b.direct_inputs], list(b.sys.state_labels))).encode())
        if spec.kind == "ode":
            for a in kernel_args(spec, plan.block_params(b)):
                *kind, data = _value_key(a)     # an array's bytes hashed as they are
                data = data if isinstance(data, bytes) else data.encode()
                h.update(repr((kind, len(data))).encode())
                h.update(data)
    h.update(repr((plan.delays, plan.holds, plan.nd, plan.nh, list(plan.order),
                   plan.x0.size, seed)).encode())
    for m in plan.maps:                 # CSR, each row's entries in column order
        h.update(repr(m.shape).encode())
        for a in (m.indptr, m.indices, m.data):
            h.update(repr(a.dtype.str).encode())
            h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def kernel_code_ids(plan):
    """The identities of the blocks' kernels' code objects: what, besides
    :func:`structure_digest`, keys a result kept in this process (a kernel replaced by
    another function of the same name, as a test does, is a new key)."""
    return tuple(None if f is None else id(getattr(f, "__code__", f))
                 for b in plan.blocks if b.spec is not None
                 for f in (b.spec.update, b.spec.output, getattr(b.spec, "jacobian", None)))


def run_digest(plan, *, seed=0):
    """A digest of everything a run of `plan` computes from, for results kept across
    processes (``gamma = "auto"``'s calibration): the diagram's structure, kernels and
    parameter values (:func:`structure_digest`) and the initial state.  None where a
    block's kernels are not ivdrem's own (a user's nlsys, an FMU): what they compute
    cannot be keyed."""
    digest = structure_digest(plan, seed=seed)
    if digest is None:
        return None
    h = hashlib.sha256(digest.encode())
    h.update(np.ascontiguousarray(plan.x0, dtype=float).tobytes())
    return h.hexdigest()


#: what a JacobianProgram keeps on disk besides the differentiated blocks' indices
_PROGRAM_ARRAYS = ("fd_x0", "fd_nx", "fd_u0", "fd_nu", "fd_ny", "fd_y0", "fd_central",
                   "g_ptr", "gc_ptr", "col", "g_kind", "e_ptr", "e_row", "e_slot", "run_dst",
                   "run_f", "run_src", "run_len", "gains", "j_row", "j_col", "j_slot", "pattern")
_PROGRAM_COUNTS = ("n", "n_jb", "n_slots", "n_ins")


def _program_path(key):
    """Where the program of structure `key` is kept across processes: named by `key` and
    the digest of ivdrem's whole source (a changed builder never reads a stale program)."""
    digest = _package_digest()
    if digest is None:
        return None
    h = hashlib.sha256(f"{digest} {key}".encode()).hexdigest()[:40]
    return cache_dir() / "jacobian-programs" / f"{h}.npz"


def _slots_by_row(rows, n_slots):
    """old slot -> new slot, each row's slots made consecutive in the order of its columns:
    a source row read in column order (the chain reads each in one loop) then meets a
    destination row in consecutive slots wherever the two share consecutive columns."""
    renumber = np.full(n_slots, -1, dtype=np.int64)
    k = 0
    for row in rows:
        for _, s in sorted(row.items()):
            renumber[s] = k
            k += 1
    if k != n_slots or (renumber < 0).any():
        raise AssertionError("the Jacobian chain has a slot of no row")
    return renumber


def _runs(dst, f, src, first=None):
    """The multiply-adds S[dst] += F[f] * S[src] (F[f] alone where src < 0), in program
    order, merged into runs of consecutive destinations of three kinds: consecutive sources
    under one factor (run_src >= 0, their first), consecutive factors added alone (run_src =
    -1), or consecutive factors times consecutive sources, one each (run_src = -2 - their
    first source: a block's row read through single-entry rows, such as the mixing's
    derivatives with respect to the averaged Psi, one run instead of one per entry).
    `first` (optional, boolean): the multiply-adds that are the first term of their
    destination; a run holds only first terms or none, and a run of first terms has the
    negative of its length (``jac_chain`` stores 0.0 + term there, so that S is never
    cleared).  Merging keeps the order in which every slot receives its terms, so the
    chain's sums are the same bit for bit."""
    if dst.size == 0:
        z = np.zeros(0, dtype=np.int64)
        return z, z, z, z
    first = np.zeros(dst.size, dtype=bool) if first is None else np.asarray(first, bool)
    alone = src < 0
    cont = np.zeros(dst.size, dtype=bool)
    step = ((dst[1:] == dst[:-1] + 1) & (alone[1:] == alone[:-1])
            & (first[1:] == first[:-1]))
    cont[1:] = step & np.where(alone[1:], f[1:] == f[:-1] + 1,
                               (f[1:] == f[:-1]) & (src[1:] == src[:-1] + 1))
    start = np.flatnonzero(~cont)
    length = np.diff(np.append(start, dst.size))
    d, g, s, fs = dst[start], f[start], src[start], first[start]
    # single multiply-adds next to each other in all three indices: elementwise runs
    single = (length == 1) & (s >= 0)
    each = np.zeros(d.size, dtype=bool)
    each[1:] = (single[1:] & single[:-1] & (d[1:] == d[:-1] + 1) & (g[1:] == g[:-1] + 1)
                & (s[1:] == s[:-1] + 1) & (fs[1:] == fs[:-1]))
    first_run = np.flatnonzero(~each)
    merged = np.diff(np.append(first_run, d.size))
    s = np.where(merged > 1, -2 - s[first_run], s[first_run])
    length = np.add.reduceat(length, first_run) if first_run.size else length
    length = np.where(fs[first_run], -length, length)
    return d[first_run], g[first_run], s, length.astype(np.int64)


def _first_terms(dst, n_slots):
    """(first, unreached): whether each multiply-add S[dst] += ... is the first its
    destination receives, and the slots none reaches (all their terms left out by
    _parameter_zeros), sorted."""
    at = np.full(n_slots, dst.size, dtype=np.int64)      # each slot's first multiply-add
    np.minimum.at(at, dst, np.arange(dst.size, dtype=np.int64))
    reached = at < dst.size
    first = np.zeros(dst.size, dtype=bool)
    first[at[reached]] = True
    return first, np.flatnonzero(~reached).astype(np.int64)


def _entries_by_row(entries):
    """{local row: [(row, col, slot), ...]} in the entries' order: one pass, where selecting
    each row's entries from the whole list cost rows x entries (minutes on the real arms)."""
    by_row = {}
    for e in entries:
        by_row.setdefault(e[0], []).append(e)
    return by_row


class JacobianProgram:
    """Index arrays of the block finite differences and of the chain rule for one plan.

    Attributes used by the code generator (all int64 arrays unless said)::

      fd_blocks: [BlockEntry] of the differentiated blocks, in FD order
      fd_x0, fd_nx, fd_u0, fd_nu, fd_ny: per differentiated block
      g_ptr (per block -> groups), gc_ptr (per group -> columns), col (local column),
      e_ptr (per column -> entries), e_row (local row of yf), e_slot (index into JB)
      n_jb: number of local-Jacobian values
      run_dst, run_f, run_src, run_len: the chain's multiply-adds as runs, F = [JB, gains]:
          S[dst + k] += F[f] * S[src + k] for k < len (src >= 0), S[dst + k] += F[f + k]
          (src = -1), S[dst + k] += F[f + k] * S[-2 - src + k] (src <= -2) for k < len,
          a run of first terms (len < 0) storing S[dst + k] = 0.0 + term for k < -len
          (:func:`_runs`), the slots no term reaches first stored 0 by a zero factor (the
          last gain); n_ins the multiply-adds they hold (those of the factors
          _parameter_zeros finds left out); gains (float64)
      n_slots, j_row, j_col, j_slot: the entry (j_row, j_col) of df/dx is slot j_slot of
          the chain (tables.jacobian_positions places it in the LU pattern's order)
      pattern: boolean n x n structural pattern of df/dx
      patterns: {block index: boolean (ny + nx, nx + nu) local pattern} of the ode blocks
          with states or inputs (also used for the max-hold probe's dependencies)
    """

    def __init__(self, plan, *, seed=0, modules=None):
        # modules (ivdrem.sim.compiled.KernelModules, optional): the robot-model blocks'
        # compiled wrappers then probe their patterns (the same, bit for bit)
        patterns = _local_patterns(plan, seed, modules)
        zeros = _parameter_zeros(plan, patterns, seed=seed)
        key = _program_key(plan, patterns, zeros)
        hit = _PROGRAMS.get(key)
        if hit is not None:             # the same structure: the same program, bit for bit
            _PROGRAMS.move_to_end(key)
            self.__dict__.update({k: v for k, v in hit.items() if k != "fd_block_index"})
            self.plan = plan
            self.fd_blocks = [plan.blocks[i] for i in hit["fd_block_index"]]
            return
        path = _program_path(key)
        if not self._read(path, plan, patterns):
            self._build(plan, patterns, zeros)
            self._write(path)
        for v in self.__dict__.values():
            if isinstance(v, np.ndarray):
                v.flags.writeable = False      # shared by every plan of this structure
        _PROGRAMS[key] = self._shared()
        while len(_PROGRAMS) > _PROGRAMS_MAX:
            _PROGRAMS.popitem(last=False)

    def _shared(self):
        """What every plan of this structure shares, kept in this process: the program
        without its plan and blocks (a plan holds its diagram: on the Panda's loop 1.65 GiB
        of python-control's connection maps, which the cache must not keep alive)."""
        d = {k: v for k, v in self.__dict__.items() if k not in ("plan", "fd_blocks")}
        d["fd_block_index"] = [b.index for b in self.fd_blocks]
        return d

    # ---- kept on disk: the arrays and counts, the differentiated blocks by index
    def _stored(self):
        d = {k: getattr(self, k) for k in _PROGRAM_ARRAYS + _PROGRAM_COUNTS}
        d["fd_block_index"] = np.array([b.index for b in self.fd_blocks], dtype=np.int64)
        d["pattern"] = np.packbits(self.pattern)          # n x n booleans, 8 to a byte
        return d

    def _read(self, path, plan, patterns):
        """Fill this program from the file at `path` (False where there is none, or it does
        not hold a whole program of this size: then it is built again)."""
        if path is None:
            return False
        try:
            with np.load(path, allow_pickle=False) as f:
                d = {k: f[k] for k in f.files}
        except (OSError, ValueError, EOFError, KeyError):
            return False
        names = set(_PROGRAM_ARRAYS) | set(_PROGRAM_COUNTS) | {"fd_block_index"}
        n = plan.x0.size
        if (set(d) != names or int(d["n"]) != n or d["pattern"].dtype != np.uint8
                or d["pattern"].size != (n * n + 7) // 8):
            return False
        d["pattern"] = np.unpackbits(d["pattern"], count=n * n).reshape(n, n).astype(bool)
        for k in _PROGRAM_COUNTS:
            d[k] = int(d[k])
        self.fd_blocks = [plan.blocks[int(i)] for i in d.pop("fd_block_index")]
        self.__dict__.update(d)
        self.plan, self.patterns = plan, patterns
        return True

    def _write(self, path):
        """Keep this program at `path` for later processes (atomically: two processes
        filling the cache at once both succeed; an unwritable cache costs a build)."""
        if path is None:
            return
        try:
            write_file_atomic(path, lambda fh: np.savez(fh, **self._stored()))
        except OSError:
            pass

    def _build(self, plan, patterns, zeros=None):
        self.plan = plan
        n = plan.x0.size
        self.n = n
        ny_total = sum(b.sys.noutputs for b in plan.blocks)
        # ---- local patterns and FD program
        local = {}          # block index -> list of (row, col, jb slot)
        jb = 0
        fd = dict(blk=[], x0=[], nx=[], u0=[], nu=[], ny=[], y0=[], central=[])
        g_ptr, gc_ptr, cols, e_ptr, e_row, e_slot = [0], [0], [], [0], [], []
        g_kind = []         # per group: 0 output kernel, 1 update kernel
        dropped = []        # the slots of entries the run's parameters make exactly zero
        self.fd_blocks = []
        self.patterns = patterns  # block index -> its local pattern (ny + nx, nx + nu)
        for b in plan.blocks:
            if b.index not in patterns:
                continue
            spec = b.spec
            nx, nu, ny = b.sys.nstates, b.sys.ninputs, b.sys.noutputs
            pat = patterns[b.index]
            if not pat.any():
                local[b.index] = []
                continue
            # the output kernel and the update kernel are differenced apart, each with its
            # own column groups (a column that only moves outputs costs no update call)
            groups = []             # (kernel, [(column, [rows])]) in the order differenced
            for kind, lo, hi in ((0, 0, ny), (1, ny, ny + nx)):
                rows_of_col = _rows_of_columns(pat[lo:hi], lo)
                for grp in _color(rows_of_col):
                    groups.append((kind, [(c, sorted(rows_of_col[c])) for c in grp]))
            if getattr(spec, "jacobian", None) is None:
                entries = []
                for kind, grp in groups:
                    for c, rows in grp:
                        cols.append(c)
                        for r in rows:
                            e_row.append(r)
                            e_slot.append(jb)
                            entries.append((r, c, jb))
                            jb += 1
                        e_ptr.append(len(e_row))
                    gc_ptr.append(len(cols))
                    g_kind.append(kind)
            else:
                # a block with its own Jacobian kernel is not differenced: its entries are
                # read from the kernel's buffer row by row (the buffer's order) into slots
                # numbered in that order, so that the factors of one row are consecutive
                # in F (the chain's elementwise runs, _runs); the chain still takes them
                # in the order above, so every sum keeps its order
                order = [(r, c) for _, grp in groups for c, rows in grp for r in rows]
                by_row = sorted(order)
                slot = {rc: jb + k for k, rc in enumerate(by_row)}
                entries = [(r, c, slot[(r, c)]) for r, c in order]
                zero = (zeros or {}).get(b.index)
                if zero is not None:
                    dropped.extend(slot[(r, c)] for r, c in order if zero[r, c])
                for r, c in by_row:
                    cols.append(c)
                    e_row.append(r)
                    e_slot.append(slot[(r, c)])
                    e_ptr.append(len(e_row))
                jb += len(order)
                gc_ptr.append(len(cols))
                g_kind.append(0)
            g_ptr.append(len(gc_ptr) - 1)
            local[b.index] = entries
            self.fd_blocks.append(b)
            for k, v in (("x0", b.x.start), ("nx", nx), ("u0", b.u.start), ("nu", nu),
                         ("ny", ny), ("y0", b.y.start),
                         ("central", int(spec.model is not None))):
                fd[k].append(v)
        self.n_jb = jb
        i64 = lambda v: np.asarray(v, dtype=np.int64)
        self.fd_x0, self.fd_nx, self.fd_u0 = i64(fd["x0"]), i64(fd["nx"]), i64(fd["u0"])
        self.fd_nu, self.fd_ny, self.fd_y0 = i64(fd["nu"]), i64(fd["ny"]), i64(fd["y0"])
        self.fd_central = i64(fd["central"])
        self.g_ptr, self.gc_ptr, self.col = i64(g_ptr), i64(gc_ptr), i64(cols)
        self.g_kind = i64(g_kind)
        self.e_ptr, self.e_row, self.e_slot = i64(e_ptr), i64(e_row), i64(e_slot)

        # ---- chain rule, symbolically: rows are {state column: slot}; each multiply-add
        # S[dst] += F[f] * S[src] appended to three int lists (src -1: F[f] alone), which
        # numpy reads as they are (a list of tuples took seconds to convert on the Panda)
        n_slot = [0]        # the next slot
        gains = {}
        ins_dst, ins_f, ins_src = [], [], []
        add_dst, add_f, add_src = ins_dst.append, ins_f.append, ins_src.append

        def gain_index(g):
            if g not in gains:
                gains[g] = jb + len(gains)
            return gains[g]

        yrow = [dict() for _ in range(ny_total)]
        urow = {}
        sorted_rows = {}

        def by_column(row):
            # a row read as a source is complete (blocks in topological order): its columns
            # and slots sorted by column once, so that a source's run lands on a
            # destination run
            got = sorted_rows.get(id(row))
            if got is None:
                items = sorted(row.items())
                got = sorted_rows[id(row)] = (row, [c for c, _ in items], [s for _, s in items])
            return got[1], got[2]

        def add_row(row, src_row, f):
            # row[col] += F[f] * src_row[col] over src_row's entries in column order; the
            # columns new to row get the next slots in that order
            cols, srcs = by_column(src_row)
            new = [c for c in cols if c not in row] if row else cols
            if new:
                k = n_slot[0]
                n_slot[0] = k + len(new)
                row.update(zip(new, range(k, k + len(new))))
            ins_dst.extend([row[c] for c in cols])
            ins_f.extend(itertools.repeat(f, len(cols)))
            ins_src.extend(srcs)

        def make_u(k):
            srcs = plan.conn[k]
            if len(srcs) == 1 and srcs[0][1] == 1.0:
                urow[k] = yrow[srcs[0][0]]        # a plain copy: share the row
                return
            row = {}
            for j, g in srcs:
                add_row(row, yrow[j], gain_index(g))
            urow[k] = row

        def accumulate(row, entries, nx, u0, x0):
            for r, c, slot in entries:
                if c < nx:
                    col = x0 + c
                    d = row.get(col)
                    if d is None:
                        d = row[col] = n_slot[0]
                        n_slot[0] += 1
                    add_dst(d)
                    add_f(slot)
                    add_src(-1)
                else:
                    add_row(row, urow[u0 + c - nx], slot)

        for k in plan.order:
            b = plan.blocks[k]
            if b.spec.kind != "ode":
                continue          # delay / max-hold outputs: constants
            for i in b.direct_inputs:
                make_u(int(i))
            by_row = _entries_by_row(local.get(b.index, []))
            nx, ny = b.sys.nstates, b.sys.noutputs
            for r in range(ny):
                accumulate(yrow[b.y.start + r], by_row.get(r, ()), nx, b.u.start, b.x.start)
        for b in plan.blocks:
            for k in range(b.u.start, b.u.stop):
                if k not in urow:
                    make_u(k)
        jrows = {}
        for b in plan.blocks:
            if b.spec.kind != "ode" or not b.sys.nstates:
                continue
            by_row = _entries_by_row(local.get(b.index, []))
            nx, ny = b.sys.nstates, b.sys.noutputs
            for r in range(nx):
                row = {}
                accumulate(row, by_row.get(ny + r, ()), nx, b.u.start, b.x.start)
                jrows[b.x.start + r] = row
        self.n_slots = n_slot[0]
        rows = {id(r): r for r in (*yrow, *urow.values(), *jrows.values())}
        renumber = _slots_by_row(rows.values(), self.n_slots)
        ins_dst = np.array(ins_dst, dtype=np.int64)
        ins_f = np.array(ins_f, dtype=np.int64)
        ins_src = np.array(ins_src, dtype=np.int64)
        # a factor that is exactly zero for this run's parameters adds nothing: its
        # multiply-adds are left out (the entries of df/dx they reach stay in the pattern)
        left_out = np.zeros(jb + len(gains), dtype=bool)
        left_out[np.asarray(dropped, dtype=np.int64)] = True
        keep = ~left_out[ins_f]
        ins_dst, fac, ins_src = ins_dst[keep], ins_f[keep], ins_src[keep]
        self.n_ins = int(fac.size)
        dst = renumber[ins_dst]
        src = np.where(ins_src >= 0, renumber[np.maximum(ins_src, 0)], -1)
        # each slot's first term is stored, not added (S is not cleared before the chain);
        # a slot no term reaches is stored +0 first, by a factor 0 appended to the gains
        first, unreached = _first_terms(dst, self.n_slots)
        g = np.zeros(len(gains) + (1 if unreached.size else 0))
        if unreached.size:
            zero = jb + len(gains)
            dst = np.concatenate([unreached, dst])
            fac = np.concatenate([np.full(unreached.size, zero, dtype=np.int64), fac])
            src = np.concatenate([unreached, src])
            first = np.concatenate([np.ones(unreached.size, dtype=bool), first])
        self.run_dst, self.run_f, self.run_src, self.run_len = _runs(dst, fac, src, first)
        jrows = {i: {col: int(renumber[s]) for col, s in r.items()} for i, r in jrows.items()}
        for val, idx in gains.items():
            g[idx - jb] = val
        self.gains = g
        jr, jc, js = [], [], []
        pattern = np.zeros((n, n), dtype=bool)
        for i in sorted(jrows):
            for col in sorted(jrows[i]):
                jr.append(i)
                jc.append(col)
                js.append(jrows[i][col])
                pattern[i, col] = True
        self.j_row, self.j_col, self.j_slot = i64(jr), i64(jc), i64(js)
        self.pattern = pattern

    @property
    def nnz(self):
        return int(self.pattern.sum())
