"""The robot-model blocks' sparsity probe through their compiled wrappers
(ivdrem.sim.jacobian.wrapper_probe_applies, _wrapper_kernels): where a block's model
is its C library in both paths (a URDF arm), the wrappers compute what the Python kernels
compute bit for bit, so the probe's patterns, the Jacobian program and the kept tables are
the same whichever way the blocks are probed; a sympy model keeps the Python probe."""
from __future__ import annotations

from collections import OrderedDict

import numpy as np
import pytest

from ivdrem.blocks._core import bind_model, kernel_args
from ivdrem.sim import jacobian as jac

ROBOT_BLOCKS = {"plant", "torque_observer", "regression_filter", "instrument"}

_LINK = ('<link name="{n}"><inertial><origin xyz="0.05 0.01 0.1"/><mass value="{m}"/>'
         '<inertia ixx="0.03" ixy="0.001" ixz="0.002" iyy="0.025" iyz="0.003" izz="0.02"/>'
         '</inertial></link>')
_JOINT = ('<joint name="{n}" type="revolute"><parent link="{p}"/><child link="{c}"/>'
          '<origin xyz="0.3 0 0" rpy="0 0 0"/><axis xyz="0 0 1"/>'
          '<limit lower="-2" upper="2" effort="10" velocity="2"/></joint>')


@pytest.fixture(scope="module")
def planar_urdf(tmp_path_factory):
    """A 3-joint planar arm read from a URDF file (a C-library model, like the real arms)."""
    from ivdrem.models import from_urdf
    body = _LINK.format(n="base", m=1.0)
    for k in range(3):
        body += _LINK.format(n=f"l{k + 1}", m=1.0 + 0.5 * k)
        body += _JOINT.format(n=f"j{k + 1}", p="base" if k == 0 else f"l{k}", c=f"l{k + 1}")
    path = tmp_path_factory.mktemp("planar") / "planar.urdf"
    path.write_text(f'<?xml version="1.0"?><robot name="planar">{body}</robot>')
    model = from_urdf(path, cache=False, gravity=(0.0, -9.81, 0.0))
    from ivdrem.models import _c_engine
    if _c_engine.load(model) is None:
        pytest.skip("no C compiler: a URDF arm's model is not a C library here")
    return model


def _planar_loop(model, law="iv-drem", **kw):
    from ivdrem.diagrams import closed_loop
    ones = np.ones(3)
    traj = dict(amplitude=0.5 * ones, omega=[1.0, 0.7, 0.4], phase=0 * ones, offset=0.2 * ones)
    dist = dict(amplitude=[2.0, 1.0, 0.5], omega=[0.5, 0.3, 0.2], phase=0 * ones,
                offset=0 * ones)
    gains = dict(mixing="eigen", gamma=1.0) if law == "iv-drem" else {}
    return closed_loop(law, model=model, trajectory=traj, disturbance=dist, gains=gains, **kw)


def _arm_plan(arm, law):
    """The plan of the `law` loop of examples/<arm>.toml."""
    from pathlib import Path
    from ivdrem.experiments.config import read_config, resolve_config
    from ivdrem.experiments.experiment import Experiment
    from ivdrem.sim.plan import DiagramPlan
    root = Path(__file__).resolve().parents[1]
    try:
        c = resolve_config(read_config(root / "examples" / f"{arm}.toml",
                                       overrides={"experiment.t_end": 1.0,
                                                  "experiment.laws": [law]}))[0]
    except ImportError as exc:          # the arms' data packages (ivdrem[arms])
        pytest.skip(str(exc))
    return DiagramPlan.from_diagram(Experiment.from_config(c).loop(law))


def _plan_modules(plan):
    from ivdrem.sim.compiled import kernel_modules
    return plan, kernel_modules(plan)


def _model_blocks(plan):
    return [b for b in plan.blocks if b.spec.kind == "ode" and b.spec.model is not None
            and b.sys.nstates + b.sys.ninputs]


def _sizes(b):
    return b.sys.nstates, b.sys.ninputs, b.sys.noutputs


def _bits(a):
    return np.ascontiguousarray(a, dtype=np.float64).view(np.uint64)


def _case_plan(case, planar_urdf):
    from ivdrem.sim.plan import DiagramPlan
    where, law, *rest = case.split(":")
    if where == "planar":
        kw = dict(design="inertia-scaled", K=3.0) if rest == ["inertia-scaled"] else {}
        return DiagramPlan.from_diagram(_planar_loop(planar_urdf, law, **kw))
    return _arm_plan(where, law)


@pytest.mark.parametrize("case", ["planar:iv-drem", "planar:sigma-modification",
                                  "planar:iv-drem:inertia-scaled", "ur5:iv-drem",
                                  "ur5:sigma-modification"])
def test_wrappers_compute_the_python_kernels_values_and_patterns_bit_for_bit(case,
                                                                             planar_urdf):
    """At the probe's own random points (parameters moved, states and inputs of both
    signs) every robot-model block's compiled update and output wrappers write exactly the
    Python kernels' values (or both raise), and the difference probe through them finds
    the Python probe's pattern entry by entry."""
    plan, modules = _plan_modules(_case_plan(case, planar_urdf))
    seen = set()
    for b in _model_blocks(plan):
        spec = b.spec
        assert jac.wrapper_probe_applies(spec), b.sys.name
        nx, nu, ny = _sizes(b)
        args = kernel_args(spec, plan.block_params(b))
        wout, wupd = jac._wrapper_kernels(b, modules)
        pout = bind_model(spec.output, spec.model)
        pupd = bind_model(spec.update, spec.model) if nx else None
        rng = np.random.default_rng(7 + b.index)
        compared = 0
        for a, v in jac._probe_points(spec, args, rng, nx + nu, 3):
            for py, wr, n in ((pout, wout, ny), (pupd, wupd, nx)):
                if py is None:
                    continue
                got, want = np.full(n, np.pi), np.full(n, np.pi)
                raised = []
                for f, o in ((py, want), (wr, got)):
                    try:
                        with np.errstate(all="ignore"):
                            f(jac._PROBE_TIME, v[:nx].copy(), v[nx:].copy(), o, *a)
                        raised.append(False)
                    except (ValueError, ArithmeticError):
                        raised.append(True)
                assert raised[0] == raised[1], (b.sys.name, raised)
                if not raised[0]:
                    assert np.array_equal(_bits(got), _bits(want)), (
                        f"{b.sys.name}: {int((got != want).sum())} of {n} values differ")
                    compared += 1
        assert compared >= 3, b.sys.name
        python = jac._difference_pattern(spec, args, nx, nu, ny, seed=b.index, n_points=3)
        compiled = jac._difference_pattern(spec, args, nx, nu, ny, seed=b.index, n_points=3,
                                           kernels=(wout, wupd))
        assert python is not None and python.any()
        assert np.array_equal(compiled, python), (
            f"{b.sys.name}: {int((python & ~compiled).sum())} entries missing, "
            f"{int((compiled & ~python).sum())} more")
        seen.add(b.sys.name)
    want = {"plant"} if "sigma" in case else set(ROBOT_BLOCKS)
    if "inertia-scaled" in case:
        want.add("control_law")
    assert want <= seen, sorted(want - seen)


def _fresh_probe(monkeypatch):
    """Every pattern probed again in this process (none read from memory or disk)."""
    monkeypatch.setattr(jac, "_PATTERNS", OrderedDict())
    monkeypatch.setattr(jac, "_read_pattern", lambda path, shape: (False, None))
    monkeypatch.setattr(jac, "_write_pattern", lambda path, pat: None)


def test_the_probe_runs_the_wrappers_of_a_urdf_arms_robot_model_blocks(monkeypatch,
                                                                        planar_urdf):
    """With the diagram's modules the probe of every robot-model block calls its compiled
    wrappers (2 (nx + nu) + 1 output calls per point) and never the block's Python
    kernels; the other blocks keep their way; the patterns are the Python probe's."""
    from ivdrem.sim.plan import DiagramPlan
    plan, modules = _plan_modules(DiagramPlan.from_diagram(_planar_loop(planar_urdf)))
    _fresh_probe(monkeypatch)
    python = jac._local_patterns(plan, 0)
    calls, python_kernels = {}, []
    real_wrappers, real_probe = jac._wrapper_kernels, jac._probe_kernels

    def counted(b, mods):
        out, upd = real_wrappers(b, mods)

        def out_counted(*a):
            calls[b.sys.name] = calls.get(b.sys.name, 0) + 1
            return out(*a)
        return out_counted, upd

    def probe_kernels(spec, *a):
        python_kernels.append(spec.name)
        return real_probe(spec, *a)

    monkeypatch.setattr(jac, "_wrapper_kernels", counted)
    monkeypatch.setattr(jac, "_probe_kernels", probe_kernels)
    _fresh_probe(monkeypatch)
    compiled = jac._local_patterns(plan, 0, modules)
    robot = {b.sys.name: b for b in _model_blocks(plan)}
    assert set(robot) == ROBOT_BLOCKS
    assert set(calls) == ROBOT_BLOCKS
    for name, b in robot.items():
        nx, nu, _ = _sizes(b)
        assert calls[name] == 3 * (2 * (nx + nu) + 1), name
    assert not set(python_kernels) & ROBOT_BLOCKS
    assert python_kernels         # the blocks without a model still go their own way
    assert python.keys() == compiled.keys()
    for k in python:
        assert np.array_equal(python[k], compiled[k]), plan.blocks[k].sys.name


def test_a_sympy_model_and_a_urdf_arm_without_c_library_keep_the_python_probe(
        monkeypatch, planar_urdf):
    """The paper's 2-link arm (a sympy model: its Python functions are not the compiled
    ones, and its θ̂(300 s) must stay bit for bit) is probed in Python, modules or not; so
    is a URDF arm whose C library is not there (its compiled path is numba's)."""
    from ivdrem.diagrams import closed_loop
    from ivdrem.models import _c_engine
    from ivdrem.sim.plan import DiagramPlan
    plan, modules = _plan_modules(DiagramPlan.from_diagram(closed_loop("iv-drem")))
    blocks = _model_blocks(plan)
    assert {b.sys.name for b in blocks} == ROBOT_BLOCKS
    assert not any(jac.wrapper_probe_applies(b.spec) for b in blocks)
    assert jac.probe_wrappers(plan, modules) == []

    def refuse(*a):
        raise AssertionError("a sympy model's block probed through its wrappers")

    monkeypatch.setattr(jac, "_wrapper_kernels", refuse)
    _fresh_probe(monkeypatch)
    with_modules = jac._local_patterns(plan, 0, modules)
    _fresh_probe(monkeypatch)
    without = jac._local_patterns(plan, 0)
    assert all(np.array_equal(with_modules[k], without[k]) for k in without)

    urdf_plan = DiagramPlan.from_diagram(_planar_loop(planar_urdf))
    urdf_blocks = _model_blocks(urdf_plan)
    assert all(jac.wrapper_probe_applies(b.spec) for b in urdf_blocks)
    monkeypatch.setattr(_c_engine, "load", lambda model, cc=None: None)
    assert not any(jac.wrapper_probe_applies(b.spec) for b in urdf_blocks)


def test_a_kernel_raising_at_a_point_is_skipped_the_same_way(monkeypatch, planar_urdf):
    """A point where the kernel raises (the plant at negated masses: M(q) indefinite, the
    model's forward dynamics refuses it) is skipped: the wrapper's non-zero return counts
    as the Python kernel's ValueError, and the next points give the same pattern as a
    probe without that point."""
    from ivdrem.sim.plan import DiagramPlan
    plan, modules = _plan_modules(DiagramPlan.from_diagram(_planar_loop(planar_urdf)))
    b = next(b for b in plan.blocks if b.sys.name == "plant")
    args = kernel_args(b.spec, plan.block_params(b))
    kernels = jac._wrapper_kernels(b, modules)
    reference = jac._difference_pattern(b.spec, args, *_sizes(b), seed=3, n_points=3,
                                        kernels=kernels)
    real_points = jac._probe_points
    bad = [-np.asarray(args[0], dtype=float)] + list(args[1:])     # theta negated

    def with_a_bad_point(spec, a, rng, size, n_points):
        yield bad, np.full(size, 0.7)
        yield from real_points(spec, a, rng, size, n_points)

    raised = []
    real_raised = jac._WrapperRaised

    class Counted(real_raised):
        def __init__(self, *a):
            raised.append(a)
            super().__init__(*a)

    nx, nu, _ = _sizes(b)
    upd = kernels[1]
    x, u, out = np.full(nx, 0.7), np.full(nu, 0.7), np.zeros(nx)
    with pytest.raises(ValueError):             # the Python kernel refuses the point
        bind_model(b.spec.update, b.spec.model)(0.1, x, u, out, *bad)
    with pytest.raises(jac._WrapperRaised):     # and so does the wrapper
        upd(0.1, x, u, out, *bad)
    monkeypatch.setattr(jac, "_probe_points", with_a_bad_point)
    monkeypatch.setattr(jac, "_WrapperRaised", Counted)
    compiled = jac._difference_pattern(b.spec, args, *_sizes(b), seed=3, n_points=3,
                                       kernels=jac._wrapper_kernels(b, modules))
    python = jac._difference_pattern(b.spec, args, *_sizes(b), seed=3, n_points=3)
    assert len(raised) == 1
    assert reference.any()
    assert np.array_equal(compiled, reference) and np.array_equal(python, reference)


def test_the_tables_of_the_compiled_probe_are_the_python_probes(monkeypatch, planar_urdf):
    """The tables a first run keeps (the Jacobian program, the LU, every array) are the
    same bit for bit whether the robot-model blocks were probed through their wrappers or
    in Python."""
    from ivdrem.sim import compiled
    from ivdrem.sim.plan import DiagramPlan
    plan, modules = _plan_modules(DiagramPlan.from_diagram(_planar_loop(planar_urdf)))
    monkeypatch.setattr(compiled, "tables_key", lambda plan, modules: None)
    monkeypatch.setattr(jac, "_program_path", lambda key: None)

    def build():
        _fresh_probe(monkeypatch)
        monkeypatch.setattr(jac, "_PROGRAMS", OrderedDict())
        return compiled.diagram_tables(plan, modules)

    used = []
    real = jac._wrapper_kernels
    monkeypatch.setattr(jac, "_wrapper_kernels", lambda b, m: used.append(b) or real(b, m))
    through_wrappers = build()
    assert {b.sys.name for b in used} == ROBOT_BLOCKS
    monkeypatch.setattr(jac, "wrapper_probe_applies", lambda spec: False)
    used.clear()
    in_python = build()
    assert not used
    assert through_wrappers._fields == in_python._fields
    for name, a, c in zip(in_python._fields, in_python, through_wrappers):
        assert np.asarray(a).dtype == np.asarray(c).dtype, name
        assert np.array_equal(a, c), name


def test_the_compile_child_gets_the_probes_wrappers_first(monkeypatch, planar_urdf):
    """The engine gives its compile child the robot-model blocks' update and output
    wrappers at the head of its list, in the order the probe takes them (after the other
    blocks: the child compiles them meanwhile), every other uncached wrapper after them,
    dearest first as before."""
    import math
    import sys
    from ivdrem.sim import _compile_child, compiled
    from ivdrem.sim.plan import DiagramPlan
    plan, modules = _plan_modules(DiagramPlan.from_diagram(_planar_loop(planar_urdf)))
    probe = jac.probe_wrappers(plan, modules)
    assert len(probe) == 2 * len(ROBOT_BLOCKS)
    assert len(set(probe)) == len(probe)
    monkeypatch.setattr(_compile_child, "function_cached", lambda path, qualname: False)
    monkeypatch.setattr(_compile_child, "enabled", lambda: True)
    for name in [m for m in sys.modules if m.startswith("ivdrem_")]:
        monkeypatch.delitem(sys.modules, name)
    given = []

    def no_child(names):
        given.append(names)
        return _compile_child.Warmup()

    monkeypatch.setattr(_compile_child, "start_modules", no_child)
    plain = compiled.start_kernels(modules.deps, parent_busy=math.inf).later
    ordered = compiled.start_kernels(modules.deps, parent_busy=math.inf, first=probe).later
    assert set(probe) <= set(plain) and sorted(ordered) == sorted(plain)
    assert ordered[:len(probe)] == probe
    assert ordered[len(probe):] == [n for n in plain if n not in set(probe)]
    wrappers = [n for n in given[-1] if n.startswith("ivdrem_wrapper_")]
    assert wrappers == ordered          # the child's own list: its imports, then these

    # and the probe takes them after every other block
    order = []
    real = jac.cached_block_pattern

    def record(spec, *a, **k):
        order.append(k.get("compiled") is not None)
        return real(spec, *a, **k)

    monkeypatch.setattr(jac, "cached_block_pattern", record)
    jac._local_patterns(plan, 0, modules)
    assert order == sorted(order) and sum(order) == len(ROBOT_BLOCKS)
