"""The C stepper (ivdrem/sim/stepper.c), the one stepper of both engines: the enumerations
from one place, its errors, the build cache, and a clear error where no C compiler is.
(Its numbers: tests/test_methods.py, tests/test_independent.py, and
benchmarks/record_theta.py against the numba build it replaced.)"""
import os
import re

import numpy as np
import pytest

from ivdrem.diagrams import closed_loop
from ivdrem.sim import _cstepper, _diagram, _stepper_codes, compiled
from ivdrem.sim.simulator import WORKSPACE_LAYOUT, Simulator
from ivdrem.sim.tables import INT_FIELDS

from conftest import build_lab


def test_every_enumeration_of_stepper_c_comes_from_the_generated_header():
    """stepper.c defines no constant of its own that Python has (one source of truth),
    and every upper-case name it uses is in the header or a C-local macro."""
    src = _cstepper.SOURCE.read_text()
    header = _cstepper.header_source()
    defined = set(re.findall(r"#define (\w+)", header))
    defined |= set(re.findall(r"static const double (\w+)", header))
    local = set(re.findall(r"#define (\w+)", src))
    assert local <= {"EXPORT", "F_PTR", "ROW"}, local
    code = re.sub(r"/\*.*?\*/", "", src, flags=re.S)
    used = set(re.findall(r"\b([A-Z][A-Z0-9_]{2,})\b", code))
    c_names = {"INFINITY", "NULL", "EXPORT", "F_PTR", "ROW"}
    assert used - c_names <= defined, sorted(used - c_names - defined)
    # values: the header's are the Python modules' (spot checks of each source)
    vals = dict(re.findall(r"#define (\w+) (-?\d+)", header))
    assert int(vals["RODAS5P"]) == _stepper_codes.RODAS5P and int(vals["S_FRESH"]) == _stepper_codes.S_FRESH
    fields = [f for f, _, _ in WORKSPACE_LAYOUT]
    assert int(vals["FIELD_LAPACK_INTS"]) == fields.index("lapack_ints")
    assert int(vals["T_SLOPE_FLAGS"]) == INT_FIELDS.index("slope_flags")
    for name, (code_, _) in _cstepper.FAILURES.items():
        assert int(vals[name]) == code_
    # coefficients exactly (repr round-trips)
    m = re.search(r"RODAS5P_C\[64\] = \{([^}]*)\}", header)
    assert np.array_equal(np.array([float(v) for v in m.group(1).split(",")]),
                          _stepper_codes.RODAS5P_C.reshape(-1))


def test_a_failure_raised_in_c_is_a_clear_error():
    sim = Simulator(closed_loop("composite-learning"))
    assert sim.engine.stepper == "c"
    sim.advance(0.01)
    W = sim.W
    small = W._replace(scratch=np.zeros(3))         # smaller than the tables say
    out = np.zeros(sim.x.size)
    with pytest.raises(RuntimeError, match="scratch is smaller than its tables"):
        sim.engine.module.diagram_jacobian(small, sim.engine.P, sim.t, sim.x,
                                           np.zeros(int(sim.engine.tables.lu_rowptr[-1])))
    # arrays C would read raw are checked: dtype, contiguity, writeability
    bad = W._replace(ys=W.ys.astype(np.float32))
    with pytest.raises(TypeError, match="workspace field ys"):
        sim.engine.module.diagram_eval(bad, sim.engine.P, _stepper_codes.RHS, sim.t, sim.x, out)
    with pytest.raises(TypeError, match="out"):
        sim.engine.module.diagram_eval(W, sim.engine.P, _stepper_codes.RHS, sim.t, sim.x, out[::2])
    # and the state is untouched by those refusals: the run goes on as before
    before = sim.x.copy()
    sim.advance(0.02)
    assert np.all(np.isfinite(sim.x)) and not np.array_equal(before, sim.x)


def test_the_library_is_built_once_into_the_cache(tmp_path):
    p1 = _cstepper.build(tmp_path)
    m1 = p1.stat().st_mtime_ns
    p2 = _cstepper.build(tmp_path)
    assert p1 == p2 and p2.stat().st_mtime_ns == m1
    assert [q.name for q in tmp_path.iterdir()] == [p1.name]     # no temporary left behind


@pytest.mark.parametrize("engine", ["compiled", "reference"])
def test_without_a_c_compiler_simulating_is_an_error_naming_what_to_install(engine,
                                                                           monkeypatch):
    monkeypatch.setenv("CC", os.path.join(os.sep, "nonexistent", "cc"))
    with pytest.raises(compiled.CCompilerMissing, match=r"needs a C compiler.*apt-get "
                       r"install gcc.*\$CC.*not found"):
        Simulator(build_lab(), engine=engine)


def test_a_compiler_that_fails_to_build_is_not_reported_as_a_missing_one(tmp_path,
                                                                        monkeypatch):
    cc = tmp_path / "cc"
    cc.write_text('#!/bin/sh\nif [ "$1" = "--version" ]; then echo "fake cc 1.0"; exit 0; fi\n'
                  'echo "stepper.c:1: error: not today" >&2\nexit 1\n')
    cc.chmod(0o755)
    monkeypatch.setenv("CC", str(cc))
    monkeypatch.setenv("IVDREM_CACHE_DIR", str(tmp_path / "cache"))
    with pytest.raises(RuntimeError, match=r"(?s)did not build ivdrem's stepper.*not today") as e:
        compiled.load_c_stepper()
    assert not isinstance(e.value, compiled.CCompilerMissing)
    assert "install" not in str(e.value).split("(")[0]


def test_a_damaged_library_in_the_cache_is_built_again(tmp_path):
    lib = _cstepper.build(tmp_path)
    lib.write_bytes(b"not an ELF file")            # e.g. a disk that filled up mid-copy
    st = _cstepper.load(tmp_path)
    assert st.path == lib and lib.stat().st_size > 1000
    # and it runs: the sparse LU of a 2 x 2 system against numpy (a full pattern, its rows
    # swapped by perm: J's values in the pattern's order are those of J[perm][:, perm])
    J = np.array([[1.0, 2.0], [0.5, -3.0]])
    LU, piv = np.zeros(4 + _diagram.LU_WORK_ROWS * 2), np.zeros(2, dtype=np.int64)
    perm, rowptr = np.array([1, 0]), np.array([0, 2, 4])
    colidx, diagp = np.array([0, 1, 0, 1], dtype=np.int32), np.array([0, 3])
    values = J[perm][:, perm].ravel()
    no_panels = (np.zeros(0, dtype=np.int64), np.zeros(1, dtype=np.int64),
                 np.zeros(0, dtype=np.int64))
    assert st.slu_factor(values, 2, 10.0, LU, piv, perm, rowptr, colidx, diagp,
                         *no_panels) == _stepper_codes.OK
    b = np.array([1.0, -2.0])
    x = b.copy()
    st.slu_solve(LU, 2, perm, rowptr, colidx, diagp, x)
    np.testing.assert_allclose(x, np.linalg.solve(10.0 * np.eye(2) - J, b), rtol=1e-14)


def test_dsyevd_work_lengths_in_c_are_the_python_functions():
    header = _cstepper.header_source()
    from ivdrem.sim import _diagram
    for fn in (_diagram.dsyevd_lwork, _diagram.dsyevd_liwork):
        m = re.search(rf"{fn.__name__}\(int64_t n\) {{ return (-?\d+) \+ (-?\d+) \* n \+ "
                      r"(-?\d+) \* n \* n; }", header)
        c0, c1, c2 = (int(v) for v in m.groups())
        assert all(c0 + c1 * n + c2 * n * n == fn(n) for n in range(1, 50))


def test_the_entry_point_table_matches_the_c_prototypes():
    """Every row of _ENTRY_POINTS (and the loop's signature) against its prototype in
    stepper.c, read from the source: the argument types and the result, in order."""
    import ctypes
    import re
    src = _cstepper.SOURCE.read_text()
    c_type = {"double": ctypes.c_double, "i64": ctypes.c_int64}
    sigs = {**_cstepper._SIGNATURES, **_cstepper._ctypes_signatures()}
    assert set(sigs) == {f"ivdrem_{n}" for n in _cstepper._ENTRY_POINTS} | {"ivdrem_step_loop"}
    for name, (res, argtypes) in sigs.items():
        m = re.search(rf"EXPORT (int|void) {name}\(([^)]*)\)", src)
        assert m, name
        want = [ctypes.c_void_p if "*" in a else c_type[a.split()[-2]]
                for a in m.group(2).replace("\n", " ").split(",")]
        assert argtypes == want, name
        assert res == (ctypes.c_int if m.group(1) == "int" else None), name


def test_an_int32_table_is_packed_as_its_count_and_values_two_to_an_int64():
    """The index tables the Jacobian and the LU read as int32 (tables._i32): pack() stores
    the count, then the values (odd counts padded), which i32_table in stepper.c reads back;
    a value beyond int32 is refused when the tables are built."""
    import pytest
    from ivdrem.sim import tables
    for values in ([], [7], [-1, 2, 2 ** 31 - 1], list(range(10))):
        packed = tables._packed_i32(tables._i32(values))
        assert packed.dtype == np.int64 and packed[0] == len(values)
        assert packed.size == 1 + (len(values) + 1) // 2
        assert packed[1:].view(np.int32)[:len(values)].tolist() == values
    with pytest.raises(OverflowError, match="beyond int32"):
        tables._i32([0, 2 ** 31])
    int32 = [f for f, dt, _ in tables.TABLES_LAYOUT if dt == "int32"]
    assert {"lu_colidx", "jac_run_dst", "jac_j_pos", "fd_e_slot"} <= set(int32)
    ints, _ = tables.pack(tables.empty_tables())
    for f in int32:                      # every int32 table of no diagram: a count of 0
        k = tables.INT_FIELDS.index(f)
        assert ints[ints[k]] == 0 and ints[k + 1] - ints[k] == 1
