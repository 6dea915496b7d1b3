"""The compiled engine's diagram functions, driven by tables: the same code for every diagram.

Written in the numba-compatible subset of Python and compiled once with the stepping
template into the shared stepper module (:mod:`ivdrem.sim.stepper`).  A diagram is data
here (:class:`ivdrem.sim.tables.DiagramTables`, in the workspace field ``tables``): its
blocks with their offsets, the evaluation order of direct feedthrough, the connection map
as sparse rows, delays, max-holds, the diagram outputs, the Jacobian's finite-difference
program and the static LU pattern.  The blocks' kernels are separately compiled C-callable
wrappers (one per kernel and block shape, cached, ``ivdrem.sim.compiled``), called by the
addresses in the workspace field ``kernels``.  So a new diagram compiles no code at all
beyond the kernels it is the first to use.

Defines the four functions the template calls: ``diagram_eval``, ``diagram_jacobian``,
``newton_factor``, ``newton_solve``.  Names it uses from its surroundings in the stepper
module: the template's helpers and constants, ``call_c`` / ``element_address``
(:mod:`ivdrem.sim._native`), the shared sparse kernels (:mod:`ivdrem.sim._jit_sparse`),
``FIELD_*`` (workspace positions), ``DIM_*`` (entries of ``DiagramTables.dims``) and
``BLOCK_RAISED_MESSAGE``.
"""
import numpy as np
from numba import uint64        # an index type without wraparound code (see _jit_sparse)

# How the stepper compiles these (ivdrem.sim.stepper).  Functions that allocate nothing
# and return no array are compiled without reference counting: numba's atomic counts on
# every view and array argument were a quarter of a Rodas5P step (perf, IV-DREM).  The
# table views are inlined into their callers, so no count is taken for them either.
NO_REFCOUNT = ("kernel_call", "row_sum", "fill_input", "fill_runs", "diagram_eval",
               "diagram_jacobian_at", "push_history", "lowest_eigenpair", "newton_factor",
               "newton_solve")
INLINE = ("int_table", "float_table", "scratch_part", "dsyevd_lwork", "dsyevd_liwork")

# columns of DiagramTables.blocks
B_KIND = 0      # 0 ode, 1 delay, 2 max-hold
B_X0 = 1
B_NX = 2
B_U0 = 3
B_NU = 4
B_Y0 = 5
B_NY = 6
B_P0 = 7        # start of the block's parameters in P
B_OUT = 8       # wrapper index of the output kernel (-1: none)
B_UPD = 9       # wrapper index of the update kernel (-1: none)
B_SPECIAL = 10  # row in the delay / hold table
B_FILL0 = 11    # range of DiagramTables.fill_order filled before this block's output
B_FILL1 = 12
N_BLOCK_COLUMNS = 13

# columns of DiagramTables.fill_runs (ivdrem.sim.tables.with_fill_runs) and their kinds
RUN_KIND = 0
RUN_D0 = 1      # first block input filled
RUN_S0 = 2      # first source: a block output (RUN_SIGNALS) or a diagram input (RUN_INPUTS)
RUN_N = 3
N_RUN_COLUMNS = 4
RUN_SIGNALS = 0
RUN_INPUTS = 1
RUN_ROW = 2     # one input row summed over its connection row (RUN_D0 = the row)
# entries of DiagramTables.fill_run_ranges after the blocks' pairs
FR_REST = 0
FR_PROBE = 1
FR_RECORD = 2
FR_HISTORY = 3

# the work arrays in the workspace field scratch, in this order; DiagramTables.
# scratch_offsets holds where each starts (and the end), sized by ivdrem.sim.tables
SC_V = 0          # history push: the delays' inputs, their slopes (push_history)
SC_DV = 1
SC_HOLD_A = 2     # max-hold eigensolver: the matrix, its eigenvalues, dsyevd's work
SC_HOLD_W = 3
SC_HOLD_WORK = 4
SC_F = 5          # Jacobian (diagram_jacobian_at): block entries, base and shifted
SC_XB = 6         # block vectors, steps, the local Jacobian, the chain's slots
SC_XB0 = 7
SC_UB = 8
SC_UB0 = 9
SC_YP = 10
SC_Y0 = 11
SC_YM = 12
SC_HH = 13
SC_JL = 14
SC_S = 15
N_SCRATCH = 16

N_DELAY_COLUMNS = 6
N_HOLD_COLUMNS = 7
ZERO = 0        # an offset argument (a runtime int in the stepper module: no literal)
# columns of DiagramTables.fd (one row per differenced block)
FD_X0 = 0
FD_NX = 1
FD_U0 = 2
FD_NU = 3
FD_NY = 4
FD_WOUT = 5     # wrapper indices of the output / update / Jacobian kernels (-1: none)
FD_WUPD = 6
FD_WJAC = 7
FD_P0 = 8
FD_Y0 = 9       # the block's first output in the signal vector
FD_CENTRAL = 10  # 1: central differences (the block calls the robot model)
N_FD_COLUMNS = 11
# columns of DiagramTables.delays
D_OFF = 0
D_SIZE = 1
D_TP = 2        # index of T in P
D_HERMITE = 3
D_U = 4
D_DU = 5
# columns of DiagramTables.holds
H_K = 0
H_OFF = 1
H_SIZE = 2
H_NVEC = 3
H_NMAT = 4
H_U = 5
H_EP = 6        # index of epsilon in P


def int_table(ti, f):
    """The int64 table number f (T_*) as a view of the packed ints."""
    return ti[ti[f]:ti[f + 1]]


def float_table(ti, tf, f):
    """The float64 table number f (TF_*) as a view of the packed floats."""
    base = N_INT_TABLES + 1
    return tf[ti[base + f]:ti[base + f + 1]]


def scratch_part(W, part):
    """Work array `part` (SC_*) of the workspace's scratch, as a view (inlined: no
    allocation, no reference count)."""
    so = int_table(W[FIELD_TABLE_INTS], T_SCRATCH_OFFSETS)
    sc = W[FIELD_SCRATCH]
    if so[part + 1] > sc.shape[0]:
        raise RuntimeError("ivdrem: the workspace's scratch is smaller than its tables")
    return sc[so[part]:so[part + 1]]


def kernel_call(kernels, failure, wrapper_nx, j, t, x, x0, u, u0, out, o0, P, p0):
    """Call kernel wrapper j on x[x0:], u[u0:], out[o0:], P[p0:]; a kernel that raised is
    recorded in `failure` ([wrapper index, t, the block's states]) and stops the run.
    (Arrays, not the workspace: a namedtuple argument is copied and reference-counted
    field by field on every call.)"""
    st = call_c(kernels[j], (t, element_address(x, x0), element_address(u, u0),
                             element_address(out, o0), element_address(P, p0)))
    if st != 0:
        failure[0] = j
        failure[1] = t
        for i in range(min(wrapper_nx[j], failure.shape[0] - 2)):
            failure[2 + i] = x[x0 + i]
        raise RuntimeError(BLOCK_RAISED_MESSAGE)


def row_sum(ptr, src, gain, r, pos, neg):
    """Sum of gain * source over sparse row r: a source j >= 0 is pos[j], a negative one
    neg[-1 - j] (the connection map: block outputs / diagram inputs; the output map: block
    outputs / block inputs)."""
    s = 0.0
    for e in range(ptr[r], ptr[r + 1]):
        j = src[e]
        if j >= 0:
            s += gain[e] * pos[j]
        else:
            s += gain[e] * neg[-1 - j]
    return s


def fill_input(in_ptr, in_src, in_gain, k, ys, us, ue):
    """us[k] from the connection map's row k (block outputs ys, diagram inputs ue)."""
    us[k] = row_sum(in_ptr, in_src, in_gain, k, ys, ue)


def fill_runs(runs, gains, r0, r1, in_ptr, in_src, in_gain, ys, us, ue):
    """Fill block inputs by runs r0..r1-1 of the fill tables: a run copies consecutive
    sources times its gain (0.0 + g y, as the row sum gives it, so -0.0 reads as 0.0),
    without the dependent index loads per entry that bound the row-by-row fill."""
    for r in range(r0, r1):
        kind = runs[r * N_RUN_COLUMNS + RUN_KIND]
        d0 = runs[r * N_RUN_COLUMNS + RUN_D0]
        s0 = runs[r * N_RUN_COLUMNS + RUN_S0]
        n = runs[r * N_RUN_COLUMNS + RUN_N]
        g = gains[r]
        if kind == RUN_SIGNALS or kind == RUN_INPUTS:
            # through views indexed from 0: with us[d0 + i] numba must allow a negative
            # index, and LLVM turns the loop into gathers and scatters
            dst = us[d0:d0 + n]
            src = ys[s0:s0 + n] if kind == RUN_SIGNALS else ue[s0:s0 + n]
            for i in range(n):
                dst[i] = 0.0 + g * src[i]
        else:
            fill_input(in_ptr, in_src, in_gain, d0, ys, us, ue)


def diagram_eval(mode, t, x, P, W, out):
    ys = W[6]
    us = W[7]
    ue = external_inputs(W, t)     # the diagram inputs at t (held, or a table over time)
    ti = W[FIELD_TABLE_INTS]
    tf = W[FIELD_TABLE_FLOATS]
    B = int_table(ti, T_BLOCKS)
    nb = B.shape[0] // N_BLOCK_COLUMNS
    order = int_table(ti, T_ORDER)
    runs = int_table(ti, T_FILL_RUNS)
    run_gain = float_table(ti, tf, TF_FILL_RUN_GAIN)
    ranges = int_table(ti, T_FILL_RUN_RANGES)
    rest = 2 * nb + 2 * FR_REST        # the range of the inputs filled after the blocks
    delays = int_table(ti, T_DELAYS)
    holds = int_table(ti, T_HOLDS)
    kernels = W[FIELD_KERNELS]
    failure = W[FIELD_FAILURE]
    wnx = int_table(ti, T_WRAPPER_NX)
    in_ptr = int_table(ti, T_IN_PTR)
    in_src = int_table(ti, T_IN_SRC)
    in_gain = float_table(ti, tf, TF_IN_GAIN)
    if mode == AFTER_STEP_EVALUATED:
        mode = AFTER_STEP
    else:
        if mode == AFTER_STEP and W[13][0] != 0:
            # probing a max-hold at an interpolated point: only the signals its inputs
            # depend on (the loop sweeps everything again before it uses the others)
            order = int_table(ti, T_PROBE_ORDER)
            rest = 2 * nb + 2 * FR_PROBE
        elif mode == RECORD:
            # recording the diagram outputs: only the signals the output map reads (an
            # output inside a step is followed by a full sweep at the step's end)
            order = int_table(ti, T_RECORD_ORDER)
            rest = 2 * nb + 2 * FR_RECORD
        elif mode == HISTORY_POINT:
            # a point of the delays' history inside a step: only the delays' inputs (a
            # full sweep follows at the step's end)
            order = int_table(ti, T_HISTORY_ORDER)
            rest = 2 * nb + 2 * FR_HISTORY
        # signals, in topological order of direct feedthrough
        for i in range(order.shape[0]):
            k = order[i]
            fill_runs(runs, run_gain, ranges[2 * k], ranges[2 * k + 1], in_ptr, in_src, in_gain,
                      ys, us, ue)
            kind = B[k * N_BLOCK_COLUMNS + B_KIND]
            if kind == 0:
                if B[k * N_BLOCK_COLUMNS + B_OUT] >= 0:
                    kernel_call(kernels, failure, wnx, B[k * N_BLOCK_COLUMNS + B_OUT], t, x, B[k * N_BLOCK_COLUMNS + B_X0], us, B[k * N_BLOCK_COLUMNS + B_U0], ys,
                                B[k * N_BLOCK_COLUMNS + B_Y0], P, B[k * N_BLOCK_COLUMNS + B_P0])
            elif kind == 1:
                dl = delays[B[k * N_BLOCK_COLUMNS + B_SPECIAL] * N_DELAY_COLUMNS:]
                y0 = B[k * N_BLOCK_COLUMNS + B_Y0]
                hist_lookup(W, t - P[dl[D_TP]], dl[D_OFF], dl[D_SIZE],
                            ys[y0:y0 + dl[D_SIZE]])
            else:
                hd = holds[B[k * N_BLOCK_COLUMNS + B_SPECIAL] * N_HOLD_COLUMNS:]
                y0 = B[k * N_BLOCK_COLUMNS + B_Y0]
                copy_into(ys, y0, W[4], hd[H_OFF], hd[H_SIZE])
                ys[y0 + hd[H_SIZE]] = W[5][hd[H_K]]
        fill_runs(runs, run_gain, ranges[rest], ranges[rest + 1], in_ptr, in_src, in_gain,
                  ys, us, ue)
    if mode == RHS:
        for k in range(nb):
            if B[k * N_BLOCK_COLUMNS + B_UPD] >= 0:
                kernel_call(kernels, failure, wnx, B[k * N_BLOCK_COLUMNS + B_UPD], t, x, B[k * N_BLOCK_COLUMNS + B_X0], us, B[k * N_BLOCK_COLUMNS + B_U0], out,
                            B[k * N_BLOCK_COLUMNS + B_X0], P, B[k * N_BLOCK_COLUMNS + B_P0])
        return OK
    if mode == AFTER_STEP or mode == HISTORY_POINT:
        if delays.shape[0] > 0 and W[13][0] == 0:     # (a max-hold probe adds no history)
            st = push_history(t, P, W)
            if st != OK:
                return st
        if mode == HISTORY_POINT:      # (no max-hold samples inside a step here)
            return OK
        upd = 0
        for r in range(holds.shape[0] // N_HOLD_COLUMNS):
            hd = holds[r * N_HOLD_COLUMNS:]
            u0 = hd[H_U]
            upd |= hold_update(W, hd[H_K], hd[H_OFF], hd[H_SIZE], hd[H_NVEC], hd[H_NMAT],
                               us[u0:u0 + hd[H_SIZE]], P[hd[H_EP]])
        return HOLD_UPDATED if upd else OK
    # RECORD: the diagram outputs (output map over block outputs, then block inputs)
    rec_ptr = int_table(ti, T_REC_PTR)
    rec_src = int_table(ti, T_REC_SRC)
    rec_gain = float_table(ti, tf, TF_REC_GAIN)
    for r in range(rec_ptr.shape[0] - 1):
        out[r] = row_sum(rec_ptr, rec_src, rec_gain, r, ys, us)
    return OK


def push_history(t, P, W):
    """Append the delays' inputs at the accepted point t (the signals in W[7]) to the
    history and forget what no lookup can need any more (work vectors from the scratch;
    the slopes to estimate, where no derivative is wired, are a table)."""
    ti = W[FIELD_TABLE_INTS]
    us = W[7]
    delays = int_table(ti, T_DELAYS)
    v = scratch_part(W, SC_V)
    dv = scratch_part(W, SC_DV)
    for i in range(dv.shape[0]):
        dv[i] = 0.0
    t_max = 0.0
    for r in range(delays.shape[0] // N_DELAY_COLUMNS):
        dl = delays[r * N_DELAY_COLUMNS:]
        copy_into(v, dl[D_OFF], us, dl[D_U], dl[D_SIZE])
        if dl[D_HERMITE] != 0:
            copy_into(dv, dl[D_OFF], us, dl[D_DU], dl[D_SIZE])
        t_max = max(t_max, P[dl[D_TP]])
    st = hist_push(W, t, v, dv, int_table(ti, T_SLOPE_FLAGS))
    if st != OK:
        return st
    hist_trim(W, t - t_max)
    return OK


def dsyevd_lwork(n):
    """dsyevd's minimum double work length for eigenvectors (jobz 'V') of order n."""
    return 1 + 6 * n + 2 * n * n


def dsyevd_liwork(n):
    """dsyevd's minimum integer work length for jobz 'V' and order n."""
    return 3 + 5 * n


def lowest_eigenpair(W, u, nvec, nmat):
    """lambda_min of the symmetric part of the nmat x nmat matrix in u[nvec:] and its unit
    eigenvector (into the last row of W[12]), by LAPACK's dsyevd (jobz 'V', uplo 'L', as
    np.linalg.eigh calls it), at the address in the workspace field lapack, on the work
    arrays in the scratch and lapack_ints: np.linalg.eigh allocated seven arrays and asked
    for the workspace size on every call, a quarter of composite learning's time while its
    hold updates every sample (the template's version, for the reference engine)."""
    iw = W[FIELD_LAPACK_INTS]
    A = scratch_part(W, SC_HOLD_A)
    w = scratch_part(W, SC_HOLD_W)
    work = scratch_part(W, SC_HOLD_WORK)
    nn = nmat * nmat
    lwork = dsyevd_lwork(nmat)
    liwork = dsyevd_liwork(nmat)
    if (A.shape[0] < nn or w.shape[0] < nmat or work.shape[0] < lwork
            or 5 + liwork > iw.shape[0]):
        raise RuntimeError("ivdrem: the max-hold's LAPACK work arrays are too small")
    for i in range(nmat):
        for j in range(nmat):
            a = 0.5 * (u[nvec + i * nmat + j] + u[nvec + j * nmat + i])
            if not np.isfinite(a):
                raise RuntimeError("ivdrem: a max-hold's matrix is not finite")
            A[j * nmat + i] = a                # column-major, as LAPACK reads it
    iw[0] = nmat
    iw[1] = nmat
    iw[2] = lwork
    iw[3] = liwork
    iw[4] = 0
    ch = W[FIELD_LAPACK_CHARS]
    # dsyevd(jobz, uplo, n, a, lda, w, work, lwork, iwork, liwork, info): all by reference
    # (void: call_c's int result means nothing, info is the status)
    call_c(W[FIELD_LAPACK][0], (element_address(ch, 0), element_address(ch, 1),
                                element_address(iw, 0), element_address(A, 0),
                                element_address(iw, 1), element_address(w, 0),
                                element_address(work, 0), element_address(iw, 2),
                                element_address(iw, 5), element_address(iw, 3),
                                element_address(iw, 4)))
    if iw[4] != 0:
        raise RuntimeError("ivdrem: LAPACK dsyevd failed on a max-hold's matrix")
    cand = W[12][W[12].shape[0] - 1]
    for i in range(nmat):
        cand[i] = A[i]                         # column 0: the eigenvector of w[0]
    return w[0]


def diagram_jacobian(t, x, P, W, J):
    """df/dx at (t, x) (see diagram_jacobian_at), with f(t, x) evaluated first."""
    f0 = np.empty(x.shape[0])
    diagram_eval(RHS, t, x, P, W, f0)       # the signals at (t, x)
    return diagram_jacobian_at(t, x, P, W, J, f0)


def diagram_jacobian_at(t, x, P, W, J, f0):
    """df/dx at (t, x) when f0 = f(t, x) and the signals W[6], W[7] are those of the
    evaluation that gave f0: each block from its own Jacobian kernel, or differenced alone
    on its grouped columns (central for blocks calling the robot model, forward from the
    base values at hand for the others), chained through the connection map
    (ivdrem.sim.jacobian)."""
    ti = W[FIELD_TABLE_INTS]
    tf = W[FIELD_TABLE_FLOATS]
    dims = int_table(ti, T_DIMS)
    ys = W[6]
    us = W[7]
    kernels = W[FIELD_KERNELS]
    failure = W[FIELD_FAILURE]
    wnx = int_table(ti, T_WRAPPER_NX)
    jac_gains = float_table(ti, tf, TF_JAC_GAINS)
    njb = dims[DIM_NJB]
    ng = jac_gains.shape[0]
    fd_g_ptr = int_table(ti, T_FD_G_PTR)
    fd_g_kind = int_table(ti, T_FD_G_KIND)
    fd_gc_ptr = int_table(ti, T_FD_GC_PTR)
    fd_col = int_table(ti, T_FD_COL)
    fd_e_ptr = int_table(ti, T_FD_E_PTR)
    fd_e_row = int_table(ti, T_FD_E_ROW)
    fd_e_slot = int_table(ti, T_FD_E_SLOT)
    # work arrays from the workspace's scratch: no allocation per Jacobian
    F = scratch_part(W, SC_F)
    xb = scratch_part(W, SC_XB)
    xb0 = scratch_part(W, SC_XB0)
    ub = scratch_part(W, SC_UB)
    ub0 = scratch_part(W, SC_UB0)
    yp = scratch_part(W, SC_YP)
    y0 = scratch_part(W, SC_Y0)
    ym = scratch_part(W, SC_YM)
    hh = scratch_part(W, SC_HH)
    jl = scratch_part(W, SC_JL)   # a block's local Jacobian, row-major
    S = scratch_part(W, SC_S)
    for i in range(ng):
        F[njb + i] = jac_gains[i]
    fd = int_table(ti, T_FD)
    for kb in range(fd.shape[0] // N_FD_COLUMNS):
        r0 = kb * N_FD_COLUMNS
        nx = fd[r0 + FD_NX]
        nu = fd[r0 + FD_NU]
        ny = fd[r0 + FD_NY]
        copy_into(xb0, 0, x, fd[r0 + FD_X0], nx)
        copy_into(xb, 0, xb0, 0, nx)
        copy_into(ub0, 0, us, fd[r0 + FD_U0], nu)
        copy_into(ub, 0, ub0, 0, nu)
        p0 = fd[r0 + FD_P0]
        if fd[r0 + FD_WJAC] >= 0:     # the block's own Jacobian kernel
            for i in range((ny + nx) * (nx + nu)):
                jl[i] = 0.0
            kernel_call(kernels, failure, wnx, fd[r0 + FD_WJAC], t, xb, ZERO, ub, ZERO, jl, ZERO, P, p0)
            for g in range(fd_g_ptr[kb], fd_g_ptr[kb + 1]):
                for c in range(fd_gc_ptr[g], fd_gc_ptr[g + 1]):
                    col = fd_col[c]
                    for e in range(fd_e_ptr[c], fd_e_ptr[c + 1]):
                        # (uint64 indices: no wraparound code, see _jit_sparse)
                        q = uint64(e)
                        F[uint64(fd_e_slot[q])] = jl[uint64(fd_e_row[q] * (nx + nu) + col)]
            continue
        central = fd[r0 + FD_CENTRAL] != 0
        if not central:
            # the base values are the signals and derivatives just computed at (t, x)
            copy_into(y0, 0, ys, fd[r0 + FD_Y0], ny)
            copy_into(y0, ny, f0, fd[r0 + FD_X0], nx)
        for g in range(fd_g_ptr[kb], fd_g_ptr[kb + 1]):
            c0 = fd_gc_ptr[g]
            c1 = fd_gc_ptr[g + 1]
            # kind 0: the output kernel into y[0:ny]; 1: the update kernel into y[ny:]
            if fd_g_kind[g] == 0:
                w = fd[r0 + FD_WOUT]
                o0 = 0
            else:
                w = fd[r0 + FD_WUPD]
                o0 = ny
            if central:      # a block calling the robot model (see ivdrem.sim.jacobian)
                fd_shift(xb, ub, xb0, ub0, nx, fd_col, c0, c1, 1.0, hh)
                kernel_call(kernels, failure, wnx, w, t, xb, ZERO, ub, ZERO, yp, o0, P, p0)
                fd_shift(xb, ub, xb0, ub0, nx, fd_col, c0, c1, -1.0, hh)
                kernel_call(kernels, failure, wnx, w, t, xb, ZERO, ub, ZERO, ym, o0, P, p0)
                fd_shift(xb, ub, xb0, ub0, nx, fd_col, c0, c1, 0.0, hh)
                fd_scatter(yp, ym, hh, c0, c1, fd_e_ptr, fd_e_row, fd_e_slot, F)
            else:
                fd_forward(xb, ub, xb0, ub0, nx, fd_col, c0, c1, 1.0, hh)
                kernel_call(kernels, failure, wnx, w, t, xb, ZERO, ub, ZERO, yp, o0, P, p0)
                fd_forward(xb, ub, xb0, ub0, nx, fd_col, c0, c1, 0.0, hh)
                fd_forward_scatter(yp, y0, hh, c0, c1, fd_e_ptr, fd_e_row, fd_e_slot, F)
    jac_chain(F, S, int_table(ti, T_JAC_INS_DST), int_table(ti, T_JAC_INS_F),
              int_table(ti, T_JAC_INS_SRC), int_table(ti, T_JAC_J_ROW),
              int_table(ti, T_JAC_J_COL), int_table(ti, T_JAC_J_SLOT), J)
    return OK


def newton_factor(W, J, c, LU, piv):
    ti = W[FIELD_TABLE_INTS]
    return slu_factor(J, c, LU, piv, int_table(ti, T_LU_PERM), int_table(ti, T_LU_ROWPTR),
                      int_table(ti, T_LU_COLIDX), int_table(ti, T_LU_DIAGP))


def newton_solve(W, LU, piv, b):
    ti = W[FIELD_TABLE_INTS]
    slu_solve(LU, int_table(ti, T_LU_PERM), int_table(ti, T_LU_ROWPTR),
              int_table(ti, T_LU_COLIDX), int_table(ti, T_LU_DIAGP), b)
