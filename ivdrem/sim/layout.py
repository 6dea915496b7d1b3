"""The workspace of a run, declared once: its fields (name, dtype, ndim) in the order the
stepper indexes them, and the integer positions it is built with (``FIELD_*``, the
diagram tables' ``DIM_*``, ``T_*``, ``TF_*``): the C stepper's generated header reads
:func:`layout_constants`.

The fields: the delay history (hist_t[cap], hist_v and hist_d[cap, nd], hist_meta [start,
count, cap, 0]); the max-holds' records (held, score; per hold its sampling period
hold_dt, its mode at the next after-step evaluation hold_mode, the time of its last update
hold_time, and hold_vec the eigenvector of lambda_min of its held matrix, the last row the
latest candidate); probing (1 while the loop probes a hold at an interpolated point: no
history push) and clock (the time of the current after-step evaluation); the signals (ys
the block outputs, us the block inputs, u_ext the diagram inputs); the diagram inputs'
table (u_times, u_values: empty while the inputs are held at u_ext); compiled engine only,
``kernels`` the addresses of the blocks' kernel wrappers, ``failure`` [wrapper index, t,
states] of a kernel that raised, ``table_ints`` / ``table_floats`` the diagram as tables
(:mod:`ivdrem.sim.tables`, packed) and the work arrays of the diagram functions and
LAPACK; ``callbacks`` the addresses of the reference engine's diagram function (0: the
diagram is the tables), of the report function (``stepper.c``'s ``report_fn``) and of the
sampled blocks' sample function (0: none); ``sample_dt`` their periods and
``sample_due`` which of them fall on the current sample time (set by the stepper);
``record_row`` one sample of the diagram's outputs, recorded there first where the output
array is not row-major (a response's (outputs x samples) array, written in place);
``jac_dirty`` 1 while a Jacobian kernel's buffer may hold values at entries that are read
(a kernel that raised part-way): the next Jacobian clears the whole buffer first.
"""
from __future__ import annotations

from collections import namedtuple

from .tables import DIMS, FLOAT_FIELDS, INT_FIELDS

__all__ = ["WORKSPACE_LAYOUT", "Workspace", "layout_constants"]

#: The workspace of a run: (field, dtype, ndim), in order (the compiled code indexes the
#: fields by position).
WORKSPACE_LAYOUT = (
    ("hist_t", "float64", 1), ("hist_v", "float64", 2), ("hist_d", "float64", 2),
    ("hist_meta", "int64", 1), ("held", "float64", 1), ("score", "float64", 1),
    ("ys", "float64", 1), ("us", "float64", 1), ("u_ext", "float64", 1),
    ("hold_dt", "float64", 1), ("hold_mode", "int64", 1), ("hold_time", "float64", 1),
    ("hold_vec", "float64", 2), ("probing", "int64", 1), ("clock", "float64", 1),
    ("u_times", "float64", 1), ("u_values", "float64", 2), ("kernels", "int64", 1),
    ("failure", "float64", 1), ("table_ints", "int64", 1),
    ("table_floats", "float64", 1), ("scratch", "float64", 1), ("lapack", "int64", 1),
    ("lapack_chars", "uint8", 1), ("lapack_ints", "int32", 1), ("callbacks", "int64", 1),
    ("sample_dt", "float64", 1), ("sample_due", "int64", 1), ("record_row", "float64", 1),
    ("jac_dirty", "int64", 1))
Workspace = namedtuple("Workspace", [f for f, _, _ in WORKSPACE_LAYOUT])
Workspace.__doc__ = """The work arrays of a run, one field per row of :data:`WORKSPACE_LAYOUT`
(history of the delays, max-hold state, Jacobian scratch, LAPACK work, ...): allocated once,
so a step allocates nothing."""


def layout_constants():
    """[(name, value)] of the positions the stepper indexes by: workspace fields
    (FIELD_*), table dimensions (DIM_*), int and float tables (T_*, TF_*)."""
    out = [(f"FIELD_{name.upper()}", i) for i, (name, _, _) in enumerate(WORKSPACE_LAYOUT)]
    out += [(f"DIM_{d}", i) for i, d in enumerate(DIMS)]
    out += [(f"T_{f.upper()}", i) for i, f in enumerate(INT_FIELDS)]
    out += [(f"TF_{f.upper()}", i) for i, f in enumerate(FLOAT_FIELDS)]
    out.append(("N_INT_TABLES", len(INT_FIELDS)))
    return out
