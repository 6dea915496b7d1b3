"""The C face of every robot model (``model.c_source(prefix)``, docs/models.md): compiled into
a small shared library and compared, function by function, with the model's Python functions
at 200 random states (relative 1e-12); forward dynamics of the URDF arms also against
Pinocchio's ``aba``; the one positive-definiteness rule in both languages; the package holds
one Newton-Euler recursion and one Cholesky per language."""
from __future__ import annotations

import ctypes
import re
from pathlib import Path

import numpy as np
import pytest

from ivdrem import _cc
from ivdrem.models import get_model
from ivdrem.models.base import C_FUNCTION_ARGS, PIVOT_RTOL, SINGULAR_INERTIA_MESSAGE

REL = 1e-12
NSTATES = 200
PREFIX = "tcf_"
#: against Pinocchio: a second algorithm (ABA), so its round-off, amplified by cond M(q)
ABA_REL = 1e-9


def c_library(model, directory, prefix=PREFIX):
    """The model's C face compiled (through ivdrem._cc) and loaded by ctypes; its
    functions with argument types set."""
    directory = Path(directory)
    src = directory / f"{prefix}face.c"
    src.write_text(model.c_source(prefix))
    lib_path = directory / f"lib{prefix}face.so"
    warnings = _cc.compile_shared([src], lib_path, what=f"the C face of {model.name}")
    assert warnings.strip() == "", warnings       # -Wall -Wextra: the generated C is clean
    lib = ctypes.CDLL(str(lib_path))
    ptr = ctypes.POINTER(ctypes.c_double)
    for name, args in C_FUNCTION_ARGS.items():
        f = getattr(lib, prefix + name)
        f.argtypes = [ptr] * len(args)
        f.restype = ctypes.c_int if name.startswith("forward_dynamics") else None
    return lib


def _p(a):
    return np.ascontiguousarray(a, dtype=float).ctypes.data_as(ctypes.POINTER(ctypes.c_double))


def _rel(got, ref):
    scale = max(1.0, float(np.max(np.abs(ref))))
    return float(np.max(np.abs(got - ref))) / scale


def _states(model, rng):
    n = model.n
    lo, hi = model.position_limits[:, 0], model.position_limits[:, 1]
    lo = np.where(np.isfinite(lo), lo, -np.pi)
    hi = np.where(np.isfinite(hi), hi, np.pi)
    for _ in range(NSTATES):
        yield (rng.uniform(lo, hi), rng.standard_normal(n), rng.standard_normal(n),
               rng.standard_normal(n), rng.standard_normal(n))


def compare_all(model, lib, prefix=PREFIX, seed=1):
    """Largest relative difference of every C-face function against the model's Python
    functions (a URDF arm's numba path: its ``functions`` are the C library itself)."""
    fn = getattr(model, "numba_functions", model.functions)
    n, nt = model.n, model.ntheta
    theta = np.asarray(model.theta_values, float)
    worst = {}

    def check(name, got, ref):
        worst[name] = max(worst.get(name, 0.0), _rel(got, ref))

    C = {name: getattr(lib, prefix + name) for name in C_FUNCTION_ARGS}
    for q, dq, v, dv, a in _states(model, np.random.default_rng(seed)):
        tau = 5.0 * a
        calls = {"Phi_M": (q, a), "Phi_C": (q, dq, v), "Phi_dM": (q, dq, a), "Phi_G": (q,),
                 "Phi_F": (dq,), "Phi": (q, dq, v, dv)}
        for name, args in calls.items():
            ref, got = np.empty((n, nt)), np.empty((n, nt))
            getattr(fn, name)(*args, ref)
            C[name](*map(_p, args), _p(got) if False else got.ctypes.data_as(
                ctypes.POINTER(ctypes.c_double)))
            check(name, got, ref)
        for name, args, shape in (("M", (q, theta), (n, n)), ("C", (q, dq, theta), (n, n)),
                                  ("G", (q, theta), (n,)), ("F", (dq, theta), (n,))):
            ref, got = np.empty(shape), np.empty(shape)
            getattr(fn, name)(*args, ref)
            C[name](*map(_p, args), got.ctypes.data_as(ctypes.POINTER(ctypes.c_double)))
            check(name, got, ref)
        ref, got = np.empty(n), np.empty(n)
        fn.forward_dynamics(q, dq, tau, theta, ref)
        assert C["forward_dynamics"](_p(q), _p(dq), _p(tau), _p(theta),
                                     got.ctypes.data_as(ctypes.POINTER(ctypes.c_double))) == 0
        check("forward_dynamics", got, ref)
    return worst


SYMBOLIC = {
    "two-link": lambda: get_model("two-link"),
    "planar-3": lambda: get_model("planar-3"),
    "planar-2+friction": lambda: __import__("ivdrem.models", fromlist=["planar_arm"])
    .planar_arm(2, friction=True),
}


@pytest.mark.parametrize("name", list(SYMBOLIC))
def test_symbolic_model_c_face_equals_python(name, tmp_path):
    model = SYMBOLIC[name]()
    lib = c_library(model, tmp_path)
    worst = compare_all(model, lib)
    print(f"\n{name}: " + ", ".join(f"{k} {v:.1e}" for k, v in worst.items()))
    assert set(worst) == set(C_FUNCTION_ARGS) - {"forward_dynamics_k"}
    assert max(worst.values()) <= REL, worst


def test_sizes_and_prototypes():
    model = get_model("planar-3")
    src = model.c_source("abc_")
    assert "#define ABC_N 3\n" in src and f"#define ABC_NTHETA {model.ntheta}\n" in src
    assert "#include <math.h>" in src and "malloc" not in src
    assert re.findall(r"#include <(\w+)\.h>", src) == ["math"]
    decl = model.c_declarations("abc_", "EXTERN")
    for name in C_FUNCTION_ARGS:
        assert f"EXTERN {'int' if name.startswith('forward') else 'void'} abc_{name}(" in decl
    with pytest.raises(ValueError, match="C identifier"):
        model.c_source("9x")


def test_linkage_macro_makes_the_functions_static(tmp_path):
    """An includer that defines <P>FN static gets file-local functions: two C faces of two
    models (two prefixes) in one translation unit, none exported."""
    a, b = get_model("two-link"), get_model("planar-3")
    src = tmp_path / "both.c"
    src.write_text("#define A_FN static\n#define B_FN static\n" + a.c_source("a_")
                   + b.c_source("b_") + "\nint both_n(void) { double q[3] = {0}, th[6] = {0}, "
                   "o[9]; a_M(q, th, o); b_M(q, th, o); return A_N + B_N; }\n")
    lib = tmp_path / "libboth.so"
    _cc.compile_shared([src], lib, what="two C faces", extra_flags=("-Wno-unused-function",))
    dll = ctypes.CDLL(str(lib))
    assert dll.both_n() == 5
    with pytest.raises(AttributeError):
        dll.a_M


def test_constants_come_from_k(tmp_path):
    """forward_dynamics_k reads the model's constants from k (the plant FMU's parameters):
    the two-link arm with k = (g = 3.7) equals the sympy model built with g = 3.7."""
    from ivdrem.models import two_link
    base, other = two_link(), two_link(g=3.7)
    lib = c_library(base, tmp_path)
    rng = np.random.default_rng(3)
    th = np.asarray(base.theta_values, float)
    k = np.array([3.7])
    for _ in range(20):
        q, dq, tau = rng.standard_normal(2), rng.standard_normal(2), rng.standard_normal(2)
        got, ref = np.empty(2), np.empty(2)
        assert lib.tcf_forward_dynamics_k(_p(q), _p(dq), _p(tau), _p(th), _p(k),
                                          got.ctypes.data_as(
                                              ctypes.POINTER(ctypes.c_double))) == 0
        other.functions.forward_dynamics(q, dq, tau, th, ref)
        assert _rel(got, ref) <= REL


def test_one_rule_for_a_matrix_that_is_not_positive_definite(tmp_path):
    """theta that make M(q) singular or indefinite: the C face returns 1, the Python
    functions raise the one message; a nearly singular M (pivot 1e-14 of the diagonal)
    too, while 1e-12 passes in both."""
    model = get_model("two-link")
    lib = c_library(model, tmp_path)
    q, dq, tau = np.array([0.3, -0.7]), np.array([0.1, 0.2]), np.array([1.0, 2.0])
    out = np.empty(2)
    outp = out.ctypes.data_as(ctypes.POINTER(ctypes.c_double))
    M = np.empty((2, 2))
    for theta in ([0.0, 0.0, 0.0, 1.0, 1.0], [-1.0, 0.2, 0.3, 1.0, 1.0],
                  [np.nan, 0.2, 0.3, 1.0, 1.0]):
        theta = np.array(theta)
        assert lib.tcf_forward_dynamics(_p(q), _p(dq), _p(tau), _p(theta), outp) == 1
        with pytest.raises(ValueError, match=re.escape(SINGULAR_INERTIA_MESSAGE)):
            model.functions.forward_dynamics(q, dq, tau, theta, out)
    # two-link at q2 = pi/2: M = [[t1, t3], [t3, t3]]; with t1 = t3 (1 + x) the second
    # pivot is t3 x / (1 + x), a fraction x / (1 + x) of the largest diagonal entry
    q = np.array([0.0, np.pi / 2])
    for frac, ok in ((1e-14, False), (1e-12, True)):
        theta = np.array([1.0 + frac, 0.0, 1.0, 1.0, 1.0])
        model.functions.M(q, theta, M)
        pivot = M[1, 1] - M[1, 0] ** 2 / M[0, 0]
        assert abs(pivot / M.max() / frac - 1.0) < 1e-2       # the case is what it says
        rc = lib.tcf_forward_dynamics(_p(q), _p(dq), _p(tau), _p(theta), outp)
        assert rc == (0 if ok else 1), (frac, rc)
        if ok:
            model.functions.forward_dynamics(q, dq, tau, theta, out)
        else:
            with pytest.raises(ValueError, match=re.escape(SINGULAR_INERTIA_MESSAGE)):
                model.functions.forward_dynamics(q, dq, tau, theta, out)
    assert PIVOT_RTOL == 1e-13


def test_compiler_errors_are_one_line_naming_the_compiler(tmp_path, monkeypatch):
    monkeypatch.setenv("CC", "no-such-cc-ivdrem")
    with pytest.raises(_cc.CompilerNotFound, match="'no-such-cc-ivdrem' \\(\\$CC\\) not found"):
        _cc.compiler()
    monkeypatch.delenv("CC")
    bad = tmp_path / "bad.c"
    bad.write_text("int f(void) { return undeclared_name; }\n")
    with pytest.raises(_cc.CompilerError) as exc:
        _cc.compile_shared([bad], tmp_path / "libbad.so", what="a broken file")
    msg = str(exc.value)
    assert "\n" not in msg and "failed to build a broken file" in msg
    assert "undeclared_name" in msg and "undeclared_name" in exc.value.output


#: every named arm, and the UR5 with friction and armature (their columns, offsets and
#: the smooth Coulomb sign in C)
ARMS = {"panda": {}, "ur5": {}, "iiwa": {}, "xarm7": {},
        "ur5+friction+armature": dict(friction={"viscous": 0.8, "coulomb": 1.5},
                                      armature=[0.1, 0.2, 0.1, 0.05, 0.05, 0.02])}


@pytest.fixture(scope="module", params=list(ARMS))
def arm_and_lib(request, tmp_path_factory):
    from ivdrem.models import arm
    try:
        model = arm(request.param.split("+")[0], **ARMS[request.param])
    except ImportError as exc:      # the arms' data packages (ivdrem[arms])
        pytest.skip(str(exc))
    return model, c_library(model, tmp_path_factory.mktemp(request.param))


def test_urdf_arm_c_face_equals_python(arm_and_lib):
    model, lib = arm_and_lib
    worst = compare_all(model, lib)
    print(f"\n{model.name}: " + ", ".join(f"{k} {v:.1e}" for k, v in worst.items()))
    assert max(worst.values()) <= REL, worst


def test_urdf_arm_forward_dynamics_equals_pinocchio_aba(arm_and_lib):
    import pinocchio as pin
    model, lib = arm_and_lib
    if any(model._chain[k] for k in ("viscous", "coulomb", "armature")):
        pytest.skip("Pinocchio's aba has no friction nor armature")
    pm = model.pinocchio_model()
    data = pm.createData()
    theta = np.asarray(model.theta_values, float)
    worst = 0.0
    for q, dq, _, _, a in _states(model, np.random.default_rng(7)):
        tau = 5.0 * a
        got = np.empty(model.n)
        assert lib.tcf_forward_dynamics(_p(q), _p(dq), _p(tau), _p(theta), got.ctypes.data_as(
            ctypes.POINTER(ctypes.c_double))) == 0
        ref = pin.aba(pm, data, model.pinocchio_configuration(q), dq, tau)
        worst = max(worst, _rel(got, ref))
    print(f"\n{model.name}: forward dynamics against Pinocchio aba, {NSTATES} states: "
          f"{worst:.1e}")
    assert worst <= ABA_REL


# ------------------------------------------------------------------ one source of each
PACKAGE = Path(__file__).resolve().parents[1] / "ivdrem"


def _cholesky_like(fn_node):
    """A function that factors a matrix: a square root and an inner-product update
    ``x -= a[.., k] * b[.., k]`` inside nested loops (what every Cholesky does)."""
    import ast
    has_sqrt = any(isinstance(n, ast.Call) and getattr(n.func, "attr", getattr(n.func, "id", ""))
                   == "sqrt" for n in ast.walk(fn_node))
    update = any(isinstance(n, ast.AugAssign) and isinstance(n.op, ast.Sub)
                 and isinstance(n.value, ast.BinOp) and isinstance(n.value.op, ast.Mult)
                 and isinstance(n.value.left, ast.Subscript)
                 and isinstance(n.value.right, ast.Subscript) for n in ast.walk(fn_node))
    return has_sqrt and update


def test_the_package_has_one_cholesky_per_language():
    """Python: one factorisation (rigid_body._rb_cholesky), every solve with M(q) calls it;
    C: none written by hand (fmi2_plant.c and every generated C face use the one printed
    from it)."""
    import ast
    found = []
    for path in PACKAGE.rglob("*.py"):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.FunctionDef) and _cholesky_like(node):
                found.append(f"{path.relative_to(PACKAGE)}:{node.name}")
    assert found == ["models/rigid_body.py:_rb_cholesky"], found
    # the symbolic models' generated forward dynamics and the blocks' solve call it
    assert "_linalg._rb_spd_solve(" in get_model("two-link").source("")
    kernels = (PACKAGE / "blocks" / "_kernels.py").read_text()
    assert "_rb_cholesky(L)" in kernels
    # C: the hand-written sources factor nothing
    assert "sqrt(" not in (PACKAGE / "fmu" / "fmi2_plant.c").read_text()
    for path in PACKAGE.rglob("*.c"):       # the stepper's LU, the controller's SVD: no
        if path.name != "fmi2_plant.c":     # Cholesky in any other hand-written C
            assert "cholesky" not in path.read_text().lower(), path
    # and every C face holds the printed one, once
    from ivdrem.models._c_printer import print_kernels
    from ivdrem.models.rigid_body import C_CHOLESKY
    printed = print_kernels(C_CHOLESKY, "x_")
    body = printed.split("\n\n", 1)[1]
    for model in (get_model("two-link"), SYMBOLIC["planar-2+friction"]()):
        src = model.c_source("x_")
        assert src.count(body) == 1 and src.count("sqrt(") == 1


def test_the_package_has_one_newton_euler():
    """The recursion is rigid_body's Python kernels; a URDF model's C face is their print;
    the plant FMU's C is the C face (no recursion written in ivdrem/fmu)."""
    from ivdrem.models import arm
    from ivdrem.models._c_printer import print_kernels
    from ivdrem.models.rigid_body import C_CHOLESKY, C_KERNELS
    export = (PACKAGE / "fmu" / "export.py").read_text()
    plant_c = (PACKAGE / "fmu" / "fmi2_plant.c").read_text()
    for text in (export, plant_c):
        for word in ("rnea", "xmotion", "body_pose", "cross3", "for (int"):
            assert word not in text, word
    assert 'model.c_source("plant_")' in export
    try:
        model = arm("ur5")
    except ImportError as exc:
        pytest.skip(str(exc))
    printed = print_kernels([f for f in C_KERNELS if f not in C_CHOLESKY], "x_",
                            printed=C_CHOLESKY)
    assert printed in model.c_source("x_")
    # the Python side of the model calls the same kernels (rigid_body's, compiled)
    assert "_rbk._rb_Phi(" in model.source("")


def _kernel_with_a_slice(x: "real[N]", out: "real[N]"):
    out[0:2] = x[0:2]


def _kernel_without_types(x, out):
    out[0] = x[0]


def test_the_printer_refuses_what_it_does_not_translate():
    from ivdrem.models._c_printer import CPrintError, print_kernels
    with pytest.raises(CPrintError, match=r"_kernel_with_a_slice \(line \d+\): slices"):
        print_kernels([_kernel_with_a_slice], "x_")
    with pytest.raises(CPrintError, match="_kernel_without_types.*'x' has no type annotation"):
        print_kernels([_kernel_without_types], "x_")
