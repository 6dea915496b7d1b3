/* The stepper: the stepping loop, the methods (Rodas5P, DP45, RK4, and BS23 for a Rodas5P
 * run's pinned steps), dense output, the transport-delay history and the max-holds, written
 * once for both engines (ivdrem/sim/_cstepper.py builds and caches it; docs/simulation.md
 * describes it).
 *
 * It sees a diagram through diagram_eval (modes RHS, AFTER_STEP, HISTORY_POINT, RECORD),
 * diagram_jacobian(_at), newton_factor and newton_solve.  The compiled engine's diagram is
 * its tables (the table-driven functions below) and its blocks' kernels, numba C-callable
 * wrappers called by address; the reference engine's is one Python function
 * (python-control's evaluation) called back through ctypes (Ctx.callback), whose
 * Jacobian is forward differences of the whole right-hand side and whose Newton matrix is
 * factored dense.  A method is a step function and its row in ivdrem/sim/methods.py;
 * method_step dispatches on the row's id, and an id it has no branch for stops the run
 * (UNKNOWN_METHOD), never another method.
 *
 * Every enumeration (modes, status codes, method ids, stats and tf entries, workspace
 * fields, table numbers and columns, Rodas5P's coefficients) comes from the Python
 * modules through the generated header stepper_consts.h: one source of truth.
 *
 * Conventions: max(a, b) / min(a, b) are Python's (b > a ? b : a), also for NaN; no fused
 * multiply-adds (built with -ffp-contract=off), no reassociation; a failure (a kernel or
 * the reference engine's callback that raised: BLOCK_RAISED; a work array too small, a
 * max-hold matrix that is not finite, dsyevd failing: ERR_*, from _cstepper.FAILURES) ends
 * the call with longjmp to the entry point, which returns its code; _cstepper.py raises a
 * RuntimeError for it.
 */
#include <math.h>
#include <setjmp.h>
#include <stddef.h>
#include <stdint.h>

#include "stepper_consts.h"

typedef int64_t i64;

#define EXPORT __attribute__((visibility("default")))

typedef struct { const i64 *p; i64 n; } ivec;
typedef struct { const int32_t *p; i64 n; } jvec;   /* an int32 index table (tables._i32) */
typedef struct { const double *p; i64 n; } fvec;

/* the reference engine's diagram: one Python function, called through a ctypes callback as
 * the compiled engine calls a Python block, evaluating the diagram with python-control:
 * mode RHS writes dx/dt into out, RECORD the diagram outputs, AFTER_STEP the block inputs
 * (the workspace's us, which the history push and the max-holds read); ue the external
 * inputs at t.  Nonzero: the Python side raised (it keeps the exception). */
typedef int32_t (*diagram_fn)(i64 mode, double t, i64 x, i64 ue, i64 out);

/* the report function (progress, and the moment Python handles a pending Ctrl-C): called
 * with the time of the first accepted step at or past tf[F_REPORT], which it moves on; it
 * reads nothing the step uses and changes nothing, so the steps are those of a run without
 * it.  Nonzero: stop the run (the Python side keeps its exception). */
typedef int32_t (*report_fn)(double t);

/* the sample function of the sampled (discrete-time) blocks: called at every accepted step
 * that ends on a sample time t_k = t0 + k dt of one of them (the steps land there); it
 * applies their updates x[k] = f(t_{k-1}, x[k-1], u[k-1]) in x, then holds their outputs
 * and inputs of t_k (ivdrem/sim/sampled.py).  Nonzero: stop the run (Python keeps the
 * exception). */
typedef int32_t (*sample_fn)(double t, i64 x);

/* the workspace: a pointer per field of WORKSPACE_LAYOUT (WORKSPACE_POINTERS, from the
 * generated header) and the sizes the code reads; callbacks[0..2] as functions (NULL: the
 * diagram is the tables, no progress report, no sampled block); the parameters; the exit */
typedef struct {
    WORKSPACE_POINTERS
    i64 nd, nmh, nue, hv_rows, hv_cols, nut, uv_cols, nfailure, nscratch, nlapack_ints, nsd;
    diagram_fn callback;
    report_fn report;
    sample_fn sample;
    double *P;
    jmp_buf exit;
} Ctx;

static void fail(Ctx *c, int code) { longjmp(c->exit, code); }

static inline double pmax(double a, double b) { return b > a ? b : a; }
static inline double pmin(double a, double b) { return b < a ? b : a; }
static inline i64 imax(i64 a, i64 b) { return b > a ? b : a; }
static inline i64 imin(i64 a, i64 b) { return b < a ? b : a; }

/* addresses and shapes ([field][2]) of the workspace arrays, from _cstepper.py */
static void bind_ctx(Ctx *c, const i64 *addr, const i64 *shape, double *P) {
    BIND_WORKSPACE(c, addr)
    c->nd = shape[2 * FIELD_HIST_V + 1];
    c->nmh = shape[2 * FIELD_SCORE];
    c->nue = shape[2 * FIELD_U_EXT];
    c->hv_rows = shape[2 * FIELD_HOLD_VEC];
    c->hv_cols = shape[2 * FIELD_HOLD_VEC + 1];
    c->nut = shape[2 * FIELD_U_TIMES];
    c->uv_cols = shape[2 * FIELD_U_VALUES + 1];
    c->nfailure = shape[2 * FIELD_FAILURE];
    c->nscratch = shape[2 * FIELD_SCRATCH];
    c->nlapack_ints = shape[2 * FIELD_LAPACK_INTS];
    c->callback = (diagram_fn)(intptr_t)c->callbacks[0];
    c->report = (report_fn)(intptr_t)c->callbacks[1];
    c->sample = (sample_fn)(intptr_t)c->callbacks[2];
    c->nsd = c->sample ? shape[2 * FIELD_SAMPLE_DT] : 0;
    c->P = P;
}

/* ---------------------------------------------------------------- tables (ivdrem/sim/tables.py) */
static inline ivec int_table(const Ctx *c, int f) {
    ivec v = {c->table_ints + c->table_ints[f], c->table_ints[f + 1] - c->table_ints[f]};
    return v;
}

/* an index table of int32 values: its count, then the values two to an int64 entry */
static inline jvec i32_table(const Ctx *c, int f) {
    const i64 *b = c->table_ints + c->table_ints[f];
    jvec v = {(const int32_t *)(b + 1), b[0]};
    return v;
}

static inline fvec float_table(const Ctx *c, int f) {
    const i64 base = N_INT_TABLES + 1;
    fvec v = {c->table_floats + c->table_ints[base + f], c->table_ints[base + f + 1] - c->table_ints[base + f]};
    return v;
}

static double *scratch_part(Ctx *c, int part, i64 *len) {
    ivec so = int_table(c, T_SCRATCH_OFFSETS);
    if (so.p[part + 1] > c->nscratch) fail(c, ERR_SCRATCH);
    if (len) *len = so.p[part + 1] - so.p[part];
    return c->scratch + so.p[part];
}

/* ------------------------------------------------------- history, inputs, max-holds */
static inline void copy_into(double *dst, i64 d0, const double *src, i64 s0, i64 n) {
    for (i64 i = 0; i < n; i++) dst[d0 + i] = src[s0 + i];
}

/* the ring position of the history's point i (0 <= i < count <= capacity, start <
 * capacity: one subtraction, not a division; the lookup's binary search takes a dozen) */
static inline i64 hist_index(const i64 *meta, i64 i) {
    i64 k = meta[0] + i;
    return k >= meta[2] ? k - meta[2] : k;
}

static double quad_slope(double ta, double va, double tb, double vb, double tc, double vc) {
    return (va * (2.0 * ta - tb - tc) / ((ta - tb) * (ta - tc))
            + vb * (ta - tc) / ((tb - ta) * (tb - tc))
            + vc * (ta - tb) / ((tc - ta) * (tc - tb)));
}

static int hist_push(Ctx *c, double t, const double *v, i64 nd, const double *d,
                     const i64 *estimate_slope) {
    if (c->probing[0] != 0) return OK;
    double *ht = c->hist_t, *hv = c->hist_v, *hd = c->hist_d;
    i64 *meta = c->hist_meta;
    const i64 w = c->nd;     /* row length of the history arrays */
    if (meta[1] > 0 && t <= ht[hist_index(meta, meta[1] - 1)]) {
        i64 k = hist_index(meta, meta[1] - 1);
        for (i64 j = 0; j < nd; j++) {
            hv[k * w + j] = v[j];
            if (estimate_slope[j] == 0) hd[k * w + j] = d[j];
        }
        return OK;
    }
    if (meta[1] >= meta[2]) return HISTORY_FULL;
    i64 k = hist_index(meta, meta[1]);
    ht[k] = t;
    for (i64 j = 0; j < nd; j++) {
        hv[k * w + j] = v[j];
        hd[k * w + j] = d[j];
    }
    i64 cnt = meta[1] + 1;
    int any_est = 0;
    for (i64 j = 0; j < nd; j++)
        if (estimate_slope[j] == 1) any_est = 1;
    if (!any_est) {
        meta[1] = cnt;
        return OK;
    }
    if (cnt >= 3) {
        i64 k1 = hist_index(meta, cnt - 2);
        i64 k2 = hist_index(meta, cnt - 3);
        for (i64 j = 0; j < nd; j++) {
            if (estimate_slope[j] == 1) {
                hd[k * w + j] = quad_slope(t, v[j], ht[k1], hv[k1 * w + j], ht[k2],
                                           hv[k2 * w + j]);
                if (cnt == 3) {
                    hd[k1 * w + j] = quad_slope(ht[k1], hv[k1 * w + j], t, v[j], ht[k2],
                                                hv[k2 * w + j]);
                    hd[k2 * w + j] = quad_slope(ht[k2], hv[k2 * w + j], t, v[j], ht[k1],
                                                hv[k1 * w + j]);
                }
            }
        }
    } else if (cnt == 2) {
        i64 k1 = hist_index(meta, 0);
        for (i64 j = 0; j < nd; j++)
            if (estimate_slope[j] == 1) hd[k * w + j] = (v[j] - hv[k1 * w + j]) / (t - ht[k1]);
    } else {
        for (i64 j = 0; j < nd; j++)
            if (estimate_slope[j] == 1) hd[k * w + j] = 0.0;
    }
    meta[1] = cnt;
    return OK;
}

static void hist_trim(Ctx *c, double t_keep) {
    if (c->probing[0] != 0) return;
    i64 *meta = c->hist_meta;
    while (meta[1] > 2 && c->hist_t[hist_index(meta, 1)] <= t_keep) {
        meta[0] = (meta[0] + 1) % meta[2];
        meta[1] -= 1;
    }
}

static void hist_lookup(Ctx *c, double tq, i64 off, i64 size, double *out) {
    const double *ht = c->hist_t, *hv = c->hist_v, *hd = c->hist_d;
    const i64 *meta = c->hist_meta;
    const i64 w = c->nd;
    i64 cnt = meta[1];
    if (cnt == 0) {
        for (i64 j = 0; j < size; j++) out[j] = 0.0;
        return;
    }
    i64 kf = hist_index(meta, 0);
    if (tq <= ht[kf] || cnt == 1) {
        copy_into(out, 0, hv + kf * w, off, size);
        return;
    }
    i64 kl = hist_index(meta, cnt - 1);
    if (tq >= ht[kl]) {
        copy_into(out, 0, hv + kl * w, off, size);
        return;
    }
    i64 lo = 0, hi = cnt - 1;
    while (hi - lo > 1) {
        i64 mid = (lo + hi) / 2;
        if (ht[hist_index(meta, mid)] <= tq) lo = mid;
        else hi = mid;
    }
    i64 a = hist_index(meta, lo), b = hist_index(meta, hi);
    double h = ht[b] - ht[a];
    double s = (tq - ht[a]) / h;
    double s2 = s * s, s3 = s2 * s;
    double h00 = 2.0 * s3 - 3.0 * s2 + 1.0;
    double h10 = s3 - 2.0 * s2 + s;
    double h01 = -2.0 * s3 + 3.0 * s2;
    double h11 = s3 - s2;
    const double *va = hv + a * w + off, *da = hd + a * w + off;
    const double *vb = hv + b * w + off, *db = hd + b * w + off;
    for (i64 j = 0; j < size; j++)
        out[j] = h00 * va[j] + h10 * h * da[j] + h01 * vb[j] + h11 * h * db[j];
}

static double *external_inputs(Ctx *c, double t) {
    double *ue = c->u_ext;
    const double *tt = c->u_times;
    i64 nt = c->nut;
    if (nt < 2) return ue;
    i64 lo = 0, hi = nt;
    while (lo < hi) {
        i64 mid = (lo + hi) / 2;
        if (tt[mid] < t) lo = mid + 1;
        else hi = mid;
    }
    i64 i = imin(imax(lo, 1), nt - 1);
    double s = (t - tt[i - 1]) / (tt[i] - tt[i - 1]);
    const double *uu = c->u_values;
    const i64 w = c->uv_cols;
    for (i64 j = 0; j < c->nue; j++)
        ue[j] = uu[(i - 1) * w + j] * (1.0 - s) + uu[i * w + j] * s;
    return ue;
}

/* dsyevd(jobz, uplo, n, a, lda, w, work, lwork, iwork, liwork, info), all by reference */
typedef void (*dsyevd_fn)(char *, char *, int32_t *, double *, int32_t *, double *, double *,
                          int32_t *, int32_t *, int32_t *, int32_t *);

static double lowest_eigenpair(Ctx *c, const double *u, i64 nvec, i64 nmat) {
    int32_t *iw = c->lapack_ints;
    i64 nA, nw, nwork;
    double *A = scratch_part(c, SC_HOLD_A, &nA);
    double *w = scratch_part(c, SC_HOLD_W, &nw);
    double *work = scratch_part(c, SC_HOLD_WORK, &nwork);
    i64 nn = nmat * nmat;
    i64 lwork = dsyevd_lwork(nmat);        /* from _diagram, through the header */
    i64 liwork = dsyevd_liwork(nmat);
    if (nA < nn || nw < nmat || nwork < lwork || 5 + liwork > c->nlapack_ints)
        fail(c, ERR_LAPACK_SIZE);
    for (i64 i = 0; i < nmat; i++) {
        for (i64 j = 0; j < nmat; j++) {
            double a = 0.5 * (u[nvec + i * nmat + j] + u[nvec + j * nmat + i]);
            if (!isfinite(a)) fail(c, ERR_HOLD_NAN);
            A[j * nmat + i] = a;
        }
    }
    iw[0] = (int32_t)nmat;
    iw[1] = (int32_t)nmat;
    iw[2] = (int32_t)lwork;
    iw[3] = (int32_t)liwork;
    iw[4] = 0;
    char *ch = (char *)c->lapack_chars;
    dsyevd_fn f = (dsyevd_fn)(intptr_t)c->lapack[0];
    f(ch, ch + 1, iw, A, iw + 1, w, work, iw + 2, iw + 5, iw + 3, iw + 4);
    if (iw[4] != 0) fail(c, ERR_DSYEVD);
    double *cand = c->hold_vec + (c->hv_rows - 1) * c->hv_cols;
    for (i64 i = 0; i < nmat; i++) cand[i] = A[i];
    return w[0];
}

static int hold_update(Ctx *c, i64 k, i64 off, i64 size, i64 nvec, i64 nmat, const double *u,
                       double epsilon) {
    i64 mode = c->hold_mode[k];
    if (mode == HOLD_SKIP) return 0;
    double *score = c->score;
    double bound = u[nvec];
    for (i64 i = 0; i < nmat; i++)
        if (u[nvec + i * nmat + i] < bound) bound = u[nvec + i * nmat + i];
    double *vec = c->hold_vec;
    const i64 vw = c->hv_cols;
    if (score[k] > 0.0 && bound > score[k]) {
        double r = 0.0;
        for (i64 i = 0; i < nmat; i++) {
            double ri = 0.0;
            for (i64 j = 0; j < nmat; j++) ri += u[nvec + i * nmat + j] * vec[k * vw + j];
            r += vec[k * vw + i] * ri;
        }
        if (r < bound) bound = r;
    }
    if (!(bound > epsilon && bound > score[k])) return 0;
    double lam = lowest_eigenpair(c, u, nvec, nmat);
    if (lam > epsilon && lam > score[k]) {
        if (mode == HOLD_PROBE) return 1;
        score[k] = lam;
        for (i64 j = 0; j < size; j++) c->held[off + j] = u[j];
        const double *cand = vec + (c->hv_rows - 1) * vw;
        for (i64 i = 0; i < nmat; i++) vec[k * vw + i] = cand[i];
        c->hold_time[k] = c->clock[0];
        return 1;
    }
    return 0;
}

/* ----------------------------------------------------------- diagram functions */
typedef int32_t (*kernel_fn)(double, i64, i64, i64, i64);

static void call_kernel(Ctx *c, ivec wnx, i64 j, double t, const double *x, i64 x0,
                        const double *u, i64 u0, double *out, i64 o0, i64 p0) {
    kernel_fn f = (kernel_fn)(intptr_t)c->kernels[j];
    int32_t st = f(t, (i64)(intptr_t)(x + x0), (i64)(intptr_t)(u + u0),
                   (i64)(intptr_t)(out + o0), (i64)(intptr_t)(c->P + p0));
    if (st != 0) {
        c->failure[0] = (double)j;
        c->failure[1] = t;
        i64 m = imin(wnx.p[j], c->nfailure - 2);
        for (i64 i = 0; i < m; i++) c->failure[2 + i] = x[x0 + i];
        fail(c, BLOCK_RAISED);
    }
}

static double row_sum(ivec ptr, ivec src, fvec gain, i64 r, const double *pos,
                      const double *neg) {
    double s = 0.0;
    for (i64 e = ptr.p[r]; e < ptr.p[r + 1]; e++) {
        i64 j = src.p[e];
        if (j >= 0) s += gain.p[e] * pos[j];
        else s += gain.p[e] * neg[-1 - j];
    }
    return s;
}

static void fill_runs(ivec runs, fvec gains, i64 r0, i64 r1, ivec in_ptr, ivec in_src,
                      fvec in_gain, const double *ys, double *us, const double *ue) {
    for (i64 r = r0; r < r1; r++) {
        i64 kind = runs.p[r * N_RUN_COLUMNS + RUN_KIND];
        i64 d0 = runs.p[r * N_RUN_COLUMNS + RUN_D0];
        i64 s0 = runs.p[r * N_RUN_COLUMNS + RUN_S0];
        i64 n = runs.p[r * N_RUN_COLUMNS + RUN_N];
        double g = gains.p[r];
        if (kind == RUN_SIGNALS || kind == RUN_INPUTS) {
            double *dst = us + d0;
            const double *src = (kind == RUN_SIGNALS ? ys : ue) + s0;
            for (i64 i = 0; i < n; i++) dst[i] = 0.0 + g * src[i];
        } else {
            us[d0] = row_sum(in_ptr, in_src, in_gain, d0, ys, ue);
        }
    }
}

static int push_history(Ctx *c, double t);

/* the after-step work on the block inputs us of (t, x): the delay history's point (not
 * while probing a max-hold), then (mode AFTER_STEP) the max-holds; HOLD_UPDATED if one
 * updated */
static int history_and_holds(Ctx *c, i64 mode, double t) {
    ivec delays = int_table(c, T_DELAYS);
    ivec holds = int_table(c, T_HOLDS);
    if (delays.n > 0 && c->probing[0] == 0) {
        int st = push_history(c, t);
        if (st != OK) return st;
    }
    if (mode == HISTORY_POINT) return OK;
    int upd = 0;
    for (i64 r = 0; r < holds.n / N_HOLD_COLUMNS; r++) {
        const i64 *hd = holds.p + r * N_HOLD_COLUMNS;
        upd |= hold_update(c, hd[H_K], hd[H_OFF], hd[H_SIZE], hd[H_NVEC], hd[H_NMAT],
                           c->us + hd[H_U], c->P[hd[H_EP]]);
    }
    return upd ? HOLD_UPDATED : OK;
}

/* the reference engine's diagram_eval: the Python callback, then the same after-step work */
static int callback_eval(Ctx *c, i64 mode, double t, const double *x, double *out) {
    const double *ue = external_inputs(c, t);
    int after = mode == AFTER_STEP || mode == AFTER_STEP_EVALUATED || mode == HISTORY_POINT;
    if (c->callback(after ? AFTER_STEP : mode, t, (i64)(intptr_t)x, (i64)(intptr_t)ue,
                    (i64)(intptr_t)(after ? c->us : out)) != 0)
        fail(c, BLOCK_RAISED);
    if (!after) return OK;
    return history_and_holds(c, mode == HISTORY_POINT ? HISTORY_POINT : AFTER_STEP, t);
}

static int diagram_eval(Ctx *c, i64 mode, double t, const double *x, double *out) {
    if (c->callback) return callback_eval(c, mode, t, x, out);
    double *ys = c->ys, *us = c->us;
    const double *ue = external_inputs(c, t);
    ivec B = int_table(c, T_BLOCKS);
    i64 nb = B.n / N_BLOCK_COLUMNS;
    ivec order = int_table(c, T_ORDER);
    ivec runs = int_table(c, T_FILL_RUNS);
    fvec run_gain = float_table(c, TF_FILL_RUN_GAIN);
    ivec ranges = int_table(c, T_FILL_RUN_RANGES);
    i64 rest = 2 * nb + 2 * FR_REST;
    ivec delays = int_table(c, T_DELAYS);
    ivec holds = int_table(c, T_HOLDS);
    ivec wnx = int_table(c, T_WRAPPER_NX);
    ivec in_ptr = int_table(c, T_IN_PTR);
    ivec in_src = int_table(c, T_IN_SRC);
    fvec in_gain = float_table(c, TF_IN_GAIN);
    if (mode == AFTER_STEP_EVALUATED) {
        mode = AFTER_STEP;
    } else {
        if (mode == AFTER_STEP && c->probing[0] != 0) {
            order = int_table(c, T_PROBE_ORDER);
            rest = 2 * nb + 2 * FR_PROBE;
        } else if (mode == RECORD) {
            order = int_table(c, T_RECORD_ORDER);
            rest = 2 * nb + 2 * FR_RECORD;
        } else if (mode == HISTORY_POINT) {
            order = int_table(c, T_HISTORY_ORDER);
            rest = 2 * nb + 2 * FR_HISTORY;
        }
        for (i64 i = 0; i < order.n; i++) {
            i64 k = order.p[i];
            const i64 *b = B.p + k * N_BLOCK_COLUMNS;
            fill_runs(runs, run_gain, ranges.p[2 * k], ranges.p[2 * k + 1], in_ptr, in_src,
                      in_gain, ys, us, ue);
            i64 kind = b[B_KIND];
            if (kind == 0) {
                if (b[B_OUT] >= 0)
                    call_kernel(c, wnx, b[B_OUT], t, x, b[B_X0], us, b[B_U0], ys, b[B_Y0],
                                b[B_P0]);
            } else if (kind == 1) {
                const i64 *dl = delays.p + b[B_SPECIAL] * N_DELAY_COLUMNS;
                i64 y0 = b[B_Y0];
                hist_lookup(c, t - c->P[dl[D_TP]], dl[D_OFF], dl[D_SIZE], ys + y0);
            } else {
                const i64 *hd = holds.p + b[B_SPECIAL] * N_HOLD_COLUMNS;
                i64 y0 = b[B_Y0];
                copy_into(ys, y0, c->held, hd[H_OFF], hd[H_SIZE]);
                ys[y0 + hd[H_SIZE]] = c->score[hd[H_K]];
            }
        }
        fill_runs(runs, run_gain, ranges.p[rest], ranges.p[rest + 1], in_ptr, in_src, in_gain,
                  ys, us, ue);
    }
    if (mode == RHS) {
        for (i64 k = 0; k < nb; k++) {
            const i64 *b = B.p + k * N_BLOCK_COLUMNS;
            if (b[B_UPD] >= 0)
                call_kernel(c, wnx, b[B_UPD], t, x, b[B_X0], us, b[B_U0], out, b[B_X0],
                            b[B_P0]);
        }
        return OK;
    }
    if (mode == AFTER_STEP || mode == HISTORY_POINT) return history_and_holds(c, mode, t);
    ivec rec_ptr = int_table(c, T_REC_PTR);
    ivec rec_src = int_table(c, T_REC_SRC);
    fvec rec_gain = float_table(c, TF_REC_GAIN);
    for (i64 r = 0; r < rec_ptr.n - 1; r++) out[r] = row_sum(rec_ptr, rec_src, rec_gain, r, ys, us);
    return OK;
}

static int push_history(Ctx *c, double t) {
    ivec delays = int_table(c, T_DELAYS);
    i64 nv, ndv;
    double *v = scratch_part(c, SC_V, &nv);
    double *dv = scratch_part(c, SC_DV, &ndv);
    for (i64 i = 0; i < ndv; i++) dv[i] = 0.0;
    double t_max = 0.0;
    for (i64 r = 0; r < delays.n / N_DELAY_COLUMNS; r++) {
        const i64 *dl = delays.p + r * N_DELAY_COLUMNS;
        copy_into(v, dl[D_OFF], c->us, dl[D_U], dl[D_SIZE]);
        if (dl[D_HERMITE] != 0) copy_into(dv, dl[D_OFF], c->us, dl[D_DU], dl[D_SIZE]);
        t_max = pmax(t_max, c->P[dl[D_TP]]);
    }
    int st = hist_push(c, t, v, nv, dv, int_table(c, T_SLOPE_FLAGS).p);
    if (st != OK) return st;
    hist_trim(c, t - t_max);
    return OK;
}

/* ------------------------------------------------------------ sparse kernels */
/* the chain rule's multiply-adds, run by run (ivdrem/sim/jacobian.py, _runs): a run of
 * consecutive destinations takes one factor times consecutive sources (src >= 0),
 * consecutive factors alone (src = -1), or consecutive factors times consecutive sources,
 * one each (src = -2 - the first source); the runs never overlap their sources.  A run of
 * negative length -m holds the first term of each of its m destinations: it stores
 * 0.0 + term, the sum as it starts from +0, so that S needs no clearing (467,638 slots, a
 * 3.7 MB memset per Jacobian on the Panda's loop); a slot no term reaches (every one left
 * out, _parameter_zeros) has such a run with a factor that is 0, and is stored +0 */
static void jac_chain(const double *F, double *S, jvec dst, jvec fidx, jvec src, jvec len,
                      jvec j_pos, jvec j_slot, double *J) {
    for (i64 r = 0; r < dst.n; r++) {
        double *restrict d = S + dst.p[r];
        i64 m = len.p[r];
        int first = m < 0;
        if (first) m = -m;
        if (src.p[r] < 0) {
            const double *restrict g = F + fidx.p[r];
            if (src.p[r] == -1) {
                if (first) for (i64 k = 0; k < m; k++) d[k] = 0.0 + g[k];
                else for (i64 k = 0; k < m; k++) d[k] += g[k];
            } else {
                /* a factor that is 0 adds +-0 to a sum that starts at +0 and so is never
                 * -0: the same values as skipping it, as the runs of one factor do */
                const double *restrict s = S + (-2 - (i64)src.p[r]);
                if (first) for (i64 k = 0; k < m; k++) d[k] = 0.0 + g[k] * s[k];
                else for (i64 k = 0; k < m; k++) d[k] += g[k] * s[k];
            }
        } else {
            /* a factor that is 0 now (an off-diagonal entry of a diagonal Gamma: 1.7 of the
             * UR5 loop's 2.08 million multiply-adds) adds nothing: skipped */
            const double a = F[fidx.p[r]];
            if (a == 0.0) {
                if (first) for (i64 k = 0; k < m; k++) d[k] = 0.0;
                continue;
            }
            const double *restrict s = S + src.p[r];
            if (first) for (i64 k = 0; k < m; k++) d[k] = 0.0 + a * s[k];
            else for (i64 k = 0; k < m; k++) d[k] += a * s[k];
        }
    }
    for (i64 e = 0; e < j_pos.n; e++) J[j_pos.p[e]] = S[j_slot.p[e]];
}

/* the columns c0..c1 of a block's states and inputs moved by sign * h (sign 0: restored);
 * h relative to max(|v|, 1), the step central (the cube root of eps) or forward (its square
 * root); the step taken, as rounded, into hh when moving forward */
static void fd_shift(double *xb, double *ub, const double *xb0, const double *ub0, i64 nx,
                     ivec col, i64 c0, i64 c1, double sign, int central, double *hh) {
    for (i64 c = c0; c < c1; c++) {
        i64 j = col.p[c];
        double v = j < nx ? xb0[j] : ub0[j - nx];
        double h = (central ? 6.055454452393343e-06 : 1.4901161193847656e-08)
                   * pmax(fabs(v), 1.0);
        double w = sign != 0.0 ? v + sign * h : v;
        if (sign > 0) hh[c] = central ? (v + h) - (v - h) : w - v;
        if (j < nx) xb[j] = w;
        else ub[j - nx] = w;
    }
}

static void fd_scatter(const double *yp, const double *ym, const double *hh, i64 c0, i64 c1,
                       ivec e_ptr, jvec e_row, jvec e_slot, double *JB) {
    for (i64 c = c0; c < c1; c++) {
        double inv = 1.0 / hh[c];
        for (i64 e = e_ptr.p[c]; e < e_ptr.p[c + 1]; e++) {
            i64 r = e_row.p[e];
            JB[e_slot.p[e]] = (yp[r] - ym[r]) * inv;
        }
    }
}

/* The static pattern's rows: perm, CSR (rowptr, colidx, diagp) and the panels
 * (sparse_lu.panels: first rows, and the columns each eliminates, kptr / k) */
typedef struct {
    const i64 *perm, *rowptr, *diagp, *panel_rows, *panel_kptr, *panel_k;
    const int32_t *colidx;              /* int32: read once per entry of L + U per solve */
    i64 npanels;
} SluPattern;

/* a pivot d of a row whose largest entry of c I - J was rmax: refused when tiny or not
 * finite (PIVOT_RTOL; the integrator then shrinks the step) */
static inline int pivot_ok(double d, double rmax) {
    return fabs(d) > PIVOT_RTOL * rmax && isfinite(d) && isfinite(rmax);
}

/* Rows s .. s + LU_PANEL - 1 eliminated together into the work block Wb (column j of the
 * panel at Wb[j LU_PANEL ..]): each row k of U is subtracted from every row with an L entry
 * at k, in increasing k, as the rows one by one would (the same operations, in the same
 * order, entry by entry; a zero multiplier is skipped as there).  Row s + g is finished
 * (pivot checked, values stored) once every column before s + g is eliminated. */
static int slu_panel(const double *J, double cc, double *vals, double *inv, double *Wb,
                     const SluPattern *pt, i64 s, const i64 *ks, i64 nk) {
    const i64 *rowptr = pt->rowptr, *diagp = pt->diagp;
    const int32_t *colidx = pt->colidx;
    double rmax[LU_PANEL];
    for (i64 g = 0; g < LU_PANEL; g++)
        for (i64 p = rowptr[s + g]; p < rowptr[s + g + 1]; p++) {
            double *wc = Wb + colidx[p] * LU_PANEL;
            for (i64 r = 0; r < LU_PANEL; r++) wc[r] = 0.0;
        }
    for (i64 g = 0; g < LU_PANEL; g++) {
        double m = 0.0;
        for (i64 p = rowptr[s + g]; p < rowptr[s + g + 1]; p++) {
            double a = -J[p];
            if (colidx[p] == s + g) a += cc;
            Wb[colidx[p] * LU_PANEL + g] = a;
            if (!(fabs(a) <= m)) m = fabs(a);
        }
        rmax[g] = m;
    }
    i64 done = 0;                   /* rows s .. s + done - 1 are finished */
    for (i64 e = 0; e <= nk; e++) {
        i64 k = e < nk ? ks[e] : s + LU_PANEL;
        while (done < LU_PANEL && s + done <= k) {
            i64 i = s + done;
            for (i64 p = rowptr[i]; p < rowptr[i + 1]; p++)
                vals[p] = Wb[colidx[p] * LU_PANEL + done];
            double d = vals[diagp[i]];
            if (!pivot_ok(d, rmax[done])) return SINGULAR;
            inv[i] = 1.0 / d;
            done++;
        }
        if (e == nk) break;
        i64 r0 = k < s ? 0 : k - s + 1;         /* the rows with column k in their L part */
        double *wk = Wb + k * LU_PANEL, l[LU_PANEL];
        int all = r0 == 0;
        for (i64 r = r0; r < LU_PANEL; r++) {
            l[r] = wk[r] * inv[k];
            wk[r] = l[r];
            if (l[r] == 0.0) all = 0;
        }
        i64 q0 = diagp[k] + 1, q1 = rowptr[k + 1];
        if (all) {                  /* one short dense update per entry of row k of U */
            for (i64 q = q0; q < q1; q++) {
                double v = vals[q], *wc = Wb + colidx[q] * LU_PANEL;
                for (i64 r = 0; r < LU_PANEL; r++) wc[r] -= l[r] * v;
            }
        } else {
            for (i64 r = r0; r < LU_PANEL; r++)
                if (l[r] != 0.0)
                    for (i64 q = q0; q < q1; q++) Wb[colidx[q] * LU_PANEL + r] -= l[r] * vals[q];
        }
    }
    return OK;
}

/* c I - J factored in the static pattern (ivdrem/sim/sparse_lu.py): J holds df/dx at the
 * pattern's positions (zero at the fill, tables.jacobian_positions); LU holds the factor's
 * values, then the inverse pivots and LU_PANEL work rows (ivdrem_work_sizes).  Row by row,
 * but the panels' rows together (slu_panel) */
static int slu_factor(const double *J, i64 n, double cc, double *LU, i64 *piv,
                      const SluPattern *pt) {
    const i64 *rowptr = pt->rowptr, *diagp = pt->diagp;
    const int32_t *colidx = pt->colidx;
    double *vals = LU;
    double *inv = LU + rowptr[n];
    double *w = inv + n;
    i64 next = 0;                  /* the next panel */
    for (i64 i = 0; i < n; i++) piv[i] = pt->perm[i];
    for (i64 i = 0; i < n; i++) {
        if (next < pt->npanels && pt->panel_rows[next] == i) {
            const i64 *kp = pt->panel_kptr + next;
            int st = slu_panel(J, cc, vals, inv, w, pt, i, pt->panel_k + kp[0], kp[1] - kp[0]);
            if (st != OK) return st;
            i += LU_PANEL - 1;
            next++;
            continue;
        }
        double rmax = 0.0;
        for (i64 p = rowptr[i]; p < rowptr[i + 1]; p++) {
            i64 j = colidx[p];
            double a = -J[p];
            if (j == i) a += cc;
            w[j] = a;
            if (!(fabs(a) <= rmax)) rmax = fabs(a);
        }
        for (i64 p = rowptr[i]; p < diagp[i]; p++) {
            i64 k = colidx[p];
            double l = w[k] * inv[k];
            w[k] = l;
            if (l != 0.0)
                for (i64 q = diagp[k] + 1; q < rowptr[k + 1]; q++) w[colidx[q]] -= l * vals[q];
        }
        for (i64 p = rowptr[i]; p < rowptr[i + 1]; p++) vals[p] = w[colidx[p]];
        double d = vals[diagp[i]];
        if (!pivot_ok(d, rmax)) return SINGULAR;
        inv[i] = 1.0 / d;
    }
    return OK;
}

/* the number of the first entries p0 .. p1 of a row's L part that lie in columns before c:
 * its columns increase, so only the last few can be c or more */
static inline i64 prefix_before(const int32_t *colidx, i64 p0, i64 p1, i64 c) {
    while (p1 > p0 && colidx[p1 - 1] >= c) p1--;
    return p1 - p0;
}

static void slu_solve(double *LU, i64 n, const SluPattern *pt, double *b) {
    const i64 *perm = pt->perm, *rowptr = pt->rowptr, *diagp = pt->diagp;
    const int32_t *colidx = pt->colidx;
    const double *vals = LU;
    const double *inv = LU + rowptr[n];
    double *y = LU + rowptr[n] + n;
    for (i64 i = 0; i < n; i++) y[i] = b[perm[i]];
    for (i64 i = 0; i < n; i++) {
        i64 a0 = rowptr[i], a1 = diagp[i];
        if (a1 - a0 >= SOLVE_GROUP_MIN && i + 3 < n
            && diagp[i + 1] - rowptr[i + 1] >= SOLVE_GROUP_MIN
            && diagp[i + 2] - rowptr[i + 2] >= SOLVE_GROUP_MIN
            && diagp[i + 3] - rowptr[i + 3] >= SOLVE_GROUP_MIN) {
            /* four rows summed side by side over their first entries in columns before i,
             * where none waits for another's y: four chains of dependent subtractions in
             * flight instead of one (each row's own order kept, so the same sums), then
             * each row's rest, in row order */
            i64 b0 = rowptr[i + 1], c0 = rowptr[i + 2], d0 = rowptr[i + 3];
            i64 b1 = diagp[i + 1], c1 = diagp[i + 2], d1 = diagp[i + 3];
            i64 m = imin(imin(a1 - a0, prefix_before(colidx, b0, b1, i)),
                         imin(prefix_before(colidx, c0, c1, i), prefix_before(colidx, d0, d1, i)));
            double s = y[i], u = y[i + 1], v = y[i + 2], w = y[i + 3];
            for (i64 k = 0; k < m; k++) {
                s -= vals[a0 + k] * y[colidx[a0 + k]];
                u -= vals[b0 + k] * y[colidx[b0 + k]];
                v -= vals[c0 + k] * y[colidx[c0 + k]];
                w -= vals[d0 + k] * y[colidx[d0 + k]];
            }
            for (i64 p = a0 + m; p < a1; p++) s -= vals[p] * y[colidx[p]];
            y[i] = s;
            for (i64 p = b0 + m; p < b1; p++) u -= vals[p] * y[colidx[p]];
            y[i + 1] = u;
            for (i64 p = c0 + m; p < c1; p++) v -= vals[p] * y[colidx[p]];
            y[i + 2] = v;
            for (i64 p = d0 + m; p < d1; p++) w -= vals[p] * y[colidx[p]];
            y[i + 3] = w;
            i += 3;
            continue;
        }
        if (a1 - a0 >= SOLVE_GROUP_MIN && i + 1 < n) {
            /* the same for two rows (the next is long too, or the one after is not) */
            i64 b0 = rowptr[i + 1], b1 = diagp[i + 1];
            i64 m = imin(a1 - a0, prefix_before(colidx, b0, b1, i));
            double s = y[i], u = y[i + 1];
            for (i64 k = 0; k < m; k++) {
                s -= vals[a0 + k] * y[colidx[a0 + k]];
                u -= vals[b0 + k] * y[colidx[b0 + k]];
            }
            for (i64 p = a0 + m; p < a1; p++) s -= vals[p] * y[colidx[p]];
            y[i] = s;
            for (i64 p = b0 + m; p < b1; p++) u -= vals[p] * y[colidx[p]];
            y[i + 1] = u;
            i++;
            continue;
        }
        double s = y[i];
        for (i64 p = a0; p < a1; p++) s -= vals[p] * y[colidx[p]];
        y[i] = s;
    }
    for (i64 i = n - 1; i >= 0; i--) {
        double s = y[i];
        for (i64 p = diagp[i] + 1; p < rowptr[i + 1]; p++) s -= vals[p] * y[colidx[p]];
        y[i] = s * inv[i];
    }
    for (i64 i = 0; i < n; i++) b[perm[i]] = y[i];
}

/* ------------------------------------------------------ the Jacobian */
static int fd_columns(Ctx *c, double t, const double *x, double *J, i64 n, const double *f0,
                      double *fp, double *xp);

static int diagram_jacobian_at(Ctx *c, double t, const double *x, double *J, i64 n,
                               const double *f0) {
    if (c->callback) {     /* the reference engine: forward differences of the whole f */
        i64 nfp, nxp;
        double *fp = scratch_part(c, SC_YP, &nfp), *xp = scratch_part(c, SC_YM, &nxp);
        if (nfp < n || nxp < n) fail(c, ERR_SCRATCH);
        return fd_columns(c, t, x, J, n, f0, fp, xp);
    }
    ivec dims = int_table(c, T_DIMS);
    const double *ys = c->ys, *us = c->us;
    ivec wnx = int_table(c, T_WRAPPER_NX);
    fvec jac_gains = float_table(c, TF_JAC_GAINS);
    i64 njb = dims.p[DIM_NJB];
    i64 ng = jac_gains.n;
    ivec fd_g_ptr = int_table(c, T_FD_G_PTR);
    ivec fd_g_kind = int_table(c, T_FD_G_KIND);
    ivec fd_gc_ptr = int_table(c, T_FD_GC_PTR);
    ivec fd_col = int_table(c, T_FD_COL);
    ivec fd_e_ptr = int_table(c, T_FD_E_PTR);
    jvec fd_e_row = i32_table(c, T_FD_E_ROW);
    jvec fd_e_slot = i32_table(c, T_FD_E_SLOT);
    double *F = scratch_part(c, SC_F, NULL);
    double *xb = scratch_part(c, SC_XB, NULL);
    double *xb0 = scratch_part(c, SC_XB0, NULL);
    double *ub = scratch_part(c, SC_UB, NULL);
    double *ub0 = scratch_part(c, SC_UB0, NULL);
    double *yp = scratch_part(c, SC_YP, NULL);
    double *y0 = scratch_part(c, SC_Y0, NULL);
    double *ym = scratch_part(c, SC_YM, NULL);
    double *hh = scratch_part(c, SC_HH, NULL);
    i64 njl;
    double *jl = scratch_part(c, SC_JL, &njl);
    if (c->jac_dirty[0] != 0) {      /* a kernel raised part-way through the last Jacobian */
        for (i64 i = 0; i < njl; i++) jl[i] = 0.0;
        c->jac_dirty[0] = 0;
    }
    double *S = scratch_part(c, SC_S, NULL);
    for (i64 i = 0; i < ng; i++) F[njb + i] = jac_gains.p[i];
    ivec fd = int_table(c, T_FD);
    i64 jl0 = 0;          /* where the next Jacobian kernel's own buffer starts in jl */
    for (i64 kb = 0; kb < fd.n / N_FD_COLUMNS; kb++) {
        const i64 *r = fd.p + kb * N_FD_COLUMNS;
        i64 nx = r[FD_NX], nu = r[FD_NU], ny = r[FD_NY];
        copy_into(xb0, 0, x, r[FD_X0], nx);
        copy_into(xb, 0, xb0, 0, nx);
        copy_into(ub0, 0, us, r[FD_U0], nu);
        copy_into(ub, 0, ub0, 0, nu);
        i64 p0 = r[FD_P0];
        if (r[FD_WJAC] >= 0) {
            /* the kernel's own (ny + nx) x (nx + nu) buffer, in which the entries read are 0
             * before it runs (it may add into them): each is cleared as it is read, in the
             * same pass (a pass of its own cost about 1 ms per Jacobian on the Panda, a cache
             * line per entry); the entries it writes and nothing reads are its own */
            double *jb = jl + jl0;
            jl0 += (ny + nx) * (nx + nu);
            c->jac_dirty[0] = 1;
            call_kernel(c, wnx, r[FD_WJAC], t, xb, 0, ub, 0, jb, 0, p0);
            for (i64 g = fd_g_ptr.p[kb]; g < fd_g_ptr.p[kb + 1]; g++)
                for (i64 cc = fd_gc_ptr.p[g]; cc < fd_gc_ptr.p[g + 1]; cc++) {
                    i64 col = fd_col.p[cc];
                    for (i64 e = fd_e_ptr.p[cc]; e < fd_e_ptr.p[cc + 1]; e++) {
                        double *v = jb + fd_e_row.p[e] * (nx + nu) + col;
                        F[fd_e_slot.p[e]] = *v;
                        *v = 0.0;
                    }
                }
            c->jac_dirty[0] = 0;
            continue;
        }
        int central = r[FD_CENTRAL] != 0;
        if (!central) {
            copy_into(y0, 0, ys, r[FD_Y0], ny);
            copy_into(y0, ny, f0, r[FD_X0], nx);
        }
        for (i64 g = fd_g_ptr.p[kb]; g < fd_g_ptr.p[kb + 1]; g++) {
            i64 c0 = fd_gc_ptr.p[g], c1 = fd_gc_ptr.p[g + 1];
            i64 w, o0;
            if (fd_g_kind.p[g] == 0) {
                w = r[FD_WOUT];
                o0 = 0;
            } else {
                w = r[FD_WUPD];
                o0 = ny;
            }
            fd_shift(xb, ub, xb0, ub0, nx, fd_col, c0, c1, 1.0, central, hh);
            call_kernel(c, wnx, w, t, xb, 0, ub, 0, yp, o0, p0);
            if (central) {
                fd_shift(xb, ub, xb0, ub0, nx, fd_col, c0, c1, -1.0, central, hh);
                call_kernel(c, wnx, w, t, xb, 0, ub, 0, ym, o0, p0);
            }
            fd_shift(xb, ub, xb0, ub0, nx, fd_col, c0, c1, 0.0, central, hh);
            fd_scatter(yp, central ? ym : y0, hh, c0, c1, fd_e_ptr, fd_e_row, fd_e_slot, F);
        }
    }
    jac_chain(F, S, i32_table(c, T_JAC_RUN_DST), i32_table(c, T_JAC_RUN_F),
              i32_table(c, T_JAC_RUN_SRC), i32_table(c, T_JAC_RUN_LEN), i32_table(c, T_JAC_J_POS),
              i32_table(c, T_JAC_J_SLOT), J);
    return OK;
}

/* df/dx with f(t, x) evaluated first, into tmp (n entries) */
static int diagram_jacobian(Ctx *c, double t, const double *x, double *J, i64 n, double *tmp) {
    diagram_eval(c, RHS, t, x, tmp);
    return diagram_jacobian_at(c, t, x, J, n, tmp);
}

static int dense_factor(const double *J, i64 n, double cc, double *LU, i64 *piv);
static void dense_solve(const double *LU, i64 n, const i64 *piv, double *b);

static SluPattern slu_pattern(Ctx *c) {
    ivec rows = int_table(c, T_LU_PANEL_ROWS);
    return (SluPattern){int_table(c, T_LU_PERM).p, int_table(c, T_LU_ROWPTR).p,
                        int_table(c, T_LU_DIAGP).p, rows.p, int_table(c, T_LU_PANEL_KPTR).p,
                        int_table(c, T_LU_PANEL_K).p, i32_table(c, T_LU_COLIDX).p, rows.n};
}

static int newton_factor(Ctx *c, const double *J, i64 n, double cc, double *LU, i64 *piv) {
    if (c->callback) return dense_factor(J, n, cc, LU, piv);
    SluPattern pt = slu_pattern(c);
    return slu_factor(J, n, cc, LU, piv, &pt);
}

static void newton_solve(Ctx *c, double *LU, const i64 *piv, i64 n, double *b) {
    if (c->callback) {
        dense_solve(LU, n, piv, b);
        return;
    }
    SluPattern pt = slu_pattern(c);
    slu_solve(LU, n, &pt, b);
}

/* ----------------------------------------------------------------- methods */
/* where the recorded samples go: sample k's output j at out_y[k ystep + j ynext] (ycols
 * outputs), its state i at out_x[k xstep + i xnext] (xcols = n, or 0: states not recorded);
 * a row-major (samples x outputs) array has ynext = 1, the transpose of one that is
 * (outputs x samples), as simulate() records into its response, ystep = 1 */
typedef struct {
    double *out_y, *out_x;
    i64 ycols, ystep, ynext, xcols, xstep, xnext;
} Rec;

static void emit(Ctx *c, double t, const double *x, i64 n, const Rec *r, i64 *io) {
    i64 k = io[0];
    if (r->ynext == 1) {
        diagram_eval(c, RECORD, t, x, r->out_y + k * r->ystep);
    } else {
        diagram_eval(c, RECORD, t, x, c->record_row);
        for (i64 j = 0; j < r->ycols; j++) r->out_y[k * r->ystep + j * r->ynext] = c->record_row[j];
    }
    if (r->xcols == n)
        for (i64 i = 0; i < n; i++) r->out_x[k * r->xstep + i * r->xnext] = x[i];
    io[0] = k + 1;
}

static i64 check_state(const double *x, i64 n, double x_limit) {
    for (i64 i = 0; i < n; i++) {
        double v = x[i];
        if (!(fabs(v) <= x_limit)) return i;
    }
    return -1;
}

static double err_norm(const double *x, const double *xn, const double *e, i64 n, double rtol,
                       double atol) {
    double s = 0.0;
    for (i64 i = 0; i < n; i++) {
        double sc = atol + rtol * pmax(fabs(x[i]), fabs(xn[i]));
        double r = e[i] / sc;
        s += r * r;
    }
    return sqrt(s / (double)n);
}

#define ROW(K, r) ((K) + (r) * n)

static double rk4_step(Ctx *c, double t, double h, const double *x, double *xn, double *K, i64 n,
                       i64 *stats) {
    double *k1 = ROW(K, 0), *k2 = ROW(K, 1), *k3 = ROW(K, 2), *k4 = ROW(K, 3), *xt = ROW(K, 4);
    for (i64 i = 0; i < n; i++) xt[i] = x[i] + 0.5 * h * k1[i];
    diagram_eval(c, RHS, t + 0.5 * h, xt, k2);
    for (i64 i = 0; i < n; i++) xt[i] = x[i] + 0.5 * h * k2[i];
    diagram_eval(c, RHS, t + 0.5 * h, xt, k3);
    for (i64 i = 0; i < n; i++) xt[i] = x[i] + h * k3[i];
    diagram_eval(c, RHS, t + h, xt, k4);
    for (i64 i = 0; i < n; i++)
        xn[i] = x[i] + h / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i]);
    stats[S_RHS] += 3;
    return 0.0;
}

static double dp45_step(Ctx *c, double t, double h, const double *x, double *xn, double *K,
                        i64 n, double rtol, double atol, i64 *stats) {
    double *k1 = ROW(K, 0), *k2 = ROW(K, 1), *k3 = ROW(K, 2), *k4 = ROW(K, 3);
    double *k5 = ROW(K, 4), *k6 = ROW(K, 5), *k7 = ROW(K, 6), *xt = ROW(K, 7);
    for (i64 i = 0; i < n; i++) xt[i] = x[i] + h * (0.2 * k1[i]);
    diagram_eval(c, RHS, t + 0.2 * h, xt, k2);
    for (i64 i = 0; i < n; i++) xt[i] = x[i] + h * (3.0 / 40.0 * k1[i] + 9.0 / 40.0 * k2[i]);
    diagram_eval(c, RHS, t + 0.3 * h, xt, k3);
    for (i64 i = 0; i < n; i++)
        xt[i] = x[i] + h * (44.0 / 45.0 * k1[i] - 56.0 / 15.0 * k2[i] + 32.0 / 9.0 * k3[i]);
    diagram_eval(c, RHS, t + 0.8 * h, xt, k4);
    for (i64 i = 0; i < n; i++)
        xt[i] = x[i] + h * (19372.0 / 6561.0 * k1[i] - 25360.0 / 2187.0 * k2[i]
                            + 64448.0 / 6561.0 * k3[i] - 212.0 / 729.0 * k4[i]);
    diagram_eval(c, RHS, t + 8.0 / 9.0 * h, xt, k5);
    for (i64 i = 0; i < n; i++)
        xt[i] = x[i] + h * (9017.0 / 3168.0 * k1[i] - 355.0 / 33.0 * k2[i]
                            + 46732.0 / 5247.0 * k3[i] + 49.0 / 176.0 * k4[i]
                            - 5103.0 / 18656.0 * k5[i]);
    diagram_eval(c, RHS, t + h, xt, k6);
    for (i64 i = 0; i < n; i++)
        xn[i] = x[i] + h * (35.0 / 384.0 * k1[i] + 500.0 / 1113.0 * k3[i]
                            + 125.0 / 192.0 * k4[i] - 2187.0 / 6784.0 * k5[i]
                            + 11.0 / 84.0 * k6[i]);
    diagram_eval(c, RHS, t + h, xn, k7);
    stats[S_RHS] += 6;
    double *e = ROW(K, 8);     /* not read after the step (the stiffness test reads 5-7) */
    for (i64 i = 0; i < n; i++)
        e[i] = h * (71.0 / 57600.0 * k1[i] - 71.0 / 16695.0 * k3[i] + 71.0 / 1920.0 * k4[i]
                    - 17253.0 / 339200.0 * k5[i] + 22.0 / 525.0 * k6[i]
                    - 1.0 / 40.0 * k7[i]);
    return err_norm(x, xn, e, n, rtol, atol);
}

static double bs23_step(Ctx *c, double t, double h, const double *x, double *xn, double *K,
                        i64 n, double rtol, double atol, i64 *stats) {
    double *k1 = ROW(K, 0), *k2 = ROW(K, 1), *k3 = ROW(K, 5), *k4 = ROW(K, 6), *xt = ROW(K, 7);
    for (i64 i = 0; i < n; i++) xt[i] = x[i] + h * (0.5 * k1[i]);
    diagram_eval(c, RHS, t + 0.5 * h, xt, k2);
    for (i64 i = 0; i < n; i++) xt[i] = x[i] + h * (0.75 * k2[i]);
    diagram_eval(c, RHS, t + 0.75 * h, xt, k3);
    for (i64 i = 0; i < n; i++)
        xn[i] = x[i] + h * (2.0 / 9.0 * k1[i] + 1.0 / 3.0 * k2[i] + 4.0 / 9.0 * k3[i]);
    diagram_eval(c, RHS, t + h, xn, k4);
    stats[S_RHS] += 3;
    double *e = ROW(K, 2);
    for (i64 i = 0; i < n; i++)
        e[i] = h * (-5.0 / 72.0 * k1[i] + 1.0 / 12.0 * k2[i] + 1.0 / 9.0 * k3[i]
                    - 1.0 / 8.0 * k4[i]);
    return err_norm(x, xn, e, n, rtol, atol);
}

static double rodas5p_step(Ctx *c, double t, double h, const double *x, double *xn, double *K,
                           i64 n, double *J, double *LU, i64 *piv, double rtol, double atol,
                           i64 *stats) {
    double *f0 = ROW(K, 0), *ft = ROW(K, 9), *fs = ROW(K, 10);
    /* J and df/dt depend on (t, x) only: a step retried after a rejection (same t and x,
     * smaller h) reuses them and refactors c I - J for its own h, bit for bit the values
     * a fresh evaluation gives */
    if (stats[S_JVALID] != 1) {
        if (stats[S_FRESH] == 1) diagram_jacobian_at(c, t, x, J, n, f0);
        else diagram_jacobian(c, t, x, J, n, fs);     /* fs: scratch until the stages */
        stats[S_JAC] += 1;
        double dt = 1.4901161193847656e-08 * pmax(1.0, fabs(t));
        diagram_eval(c, RHS, t + dt, x, ft);
        for (i64 i = 0; i < n; i++) ft[i] = (ft[i] - f0[i]) / dt;
        stats[S_RHS] += 1;
        stats[S_JVALID] = 1;
    }
    stats[S_FRESH] = 0;
    int st = newton_factor(c, J, n, 1.0 / (RODAS5P_GAMMA * h), LU, piv);
    stats[S_LU] += 1;
    if (st != OK) return INFINITY;
    for (int s = 0; s < 8; s++) {
        double *U = ROW(K, 1 + s);
        if (s == 0) {
            for (i64 i = 0; i < n; i++) U[i] = f0[i] + RODAS5P_D[0] * h * ft[i];
        } else {
            for (i64 i = 0; i < n; i++) xn[i] = x[i];
            for (int j = 0; j < s; j++) {
                double a = RODAS5P_A[s * 8 + j];
                const double *Uj = ROW(K, 1 + j);
                if (a != 0.0)
                    for (i64 i = 0; i < n; i++) xn[i] += a * Uj[i];
            }
            diagram_eval(c, RHS, t + RODAS5P_CT[s] * h, xn, fs);
            stats[S_RHS] += 1;
            double dh = RODAS5P_D[s] * h;
            for (i64 i = 0; i < n; i++) U[i] = fs[i] + dh * ft[i];
            for (int j = 0; j < s; j++) {
                double cj = RODAS5P_C[s * 8 + j] / h;
                const double *Uj = ROW(K, 1 + j);
                for (i64 i = 0; i < n; i++) U[i] += cj * Uj[i];
            }
        }
        newton_solve(c, LU, piv, n, U);
    }
    for (i64 i = 0; i < n; i++) {
        double v = x[i];
        for (int j = 0; j < 8; j++) v += RODAS5P_B[j] * K[(1 + j) * n + i];
        xn[i] = v;
    }
    return err_norm(x, xn, ROW(K, 8), n, rtol, atol);
}

static double method_step(Ctx *c, i64 mid, double t, double h, const double *x, double *xn,
                          double *K, i64 n, double *J, double *LU, i64 *piv, double rtol,
                          double atol, i64 *stats) {
    if (mid == RODAS5P) return rodas5p_step(c, t, h, x, xn, K, n, J, LU, piv, rtol, atol, stats);
    if (mid == DP45) return dp45_step(c, t, h, x, xn, K, n, rtol, atol, stats);
    if (mid == BS23) return bs23_step(c, t, h, x, xn, K, n, rtol, atol, stats);
    if (mid == RK4) return rk4_step(c, t, h, x, xn, K, n, stats);
    return -1.0;   /* no step function for this id: step_loop returns UNKNOWN_METHOD */
}

/* Rodas5P's dense-output coefficients H_0 U, H_1 U, H_2 U of the step just taken, into
 * D[0:n], D[n:2n], D[2n:3n]: computed once per step rather than once per output time and
 * max-hold probe (the same sums, so the same values as the template's dense_eval) */
static void dense_prepare(const double *K, i64 n, double *D) {
    for (i64 i = 0; i < n; i++) {
        double d0 = 0.0, d1 = 0.0, d2 = 0.0;
        for (int j = 0; j < 8; j++) {
            double u = K[(1 + j) * n + i];
            d0 += RODAS5P_H[0 * 8 + j] * u;
            d1 += RODAS5P_H[1 * 8 + j] * u;
            d2 += RODAS5P_H[2 * 8 + j] * u;
        }
        D[i] = d0;
        D[n + i] = d1;
        D[2 * n + i] = d2;
    }
}

/* the template's dense_eval; *ready says whether D holds this step's coefficients */
static void dense_eval(i64 mid, double h, double s, const double *x, const double *xn,
                       const double *f0, const double *f1, const double *K, i64 n, double *out,
                       double *D, int *ready) {
    double s1 = 1.0 - s;
    if (mid == RODAS5P) {
        if (!*ready) {
            dense_prepare(K, n, D);
            *ready = 1;
        }
        for (i64 i = 0; i < n; i++)
            out[i] = s1 * x[i] + s * (xn[i] + s1 * (D[i] + s * (D[n + i] + s * D[2 * n + i])));
        return;
    }
    double h00 = (1.0 + 2.0 * s) * s1 * s1;
    double h10 = s * s1 * s1;
    double h01 = s * s * (3.0 - 2.0 * s);
    double h11 = -s * s * s1;
    for (i64 i = 0; i < n; i++)
        out[i] = h00 * x[i] + h10 * h * f0[i] + h01 * xn[i] + h11 * h * f1[i];
}

static int on_grid(double t, double t0, double dt) {
    double m = floor((t - t0) / dt + 0.5);
    return fabs(t - (t0 + m * dt)) <= 1e-9 * pmax(1.0, fabs(t));
}

static double next_grid(double t, double t0, double dt) {
    double m = floor((t - t0) / dt + 0.5);
    double tg = t0 + m * dt;
    if (tg <= t + 1e-9 * pmax(1.0, fabs(t))) tg = t0 + (m + 1.0) * dt;
    return tg;
}

/* the first sample time of the sampled blocks after t (inf without one) */
static double next_sample(Ctx *c, double t, double t0) {
    double tn = INFINITY;
    for (i64 k = 0; k < c->nsd; k++) tn = pmin(tn, next_grid(t, t0, c->sample_dt[k]));
    return tn;
}

/* marks in c->sample_due the periods on the grid at t (the sample function reads which
   blocks are due there); 1 if any is */
static int sample_due(Ctx *c, double t, double t0) {
    int any = 0;
    for (i64 k = 0; k < c->nsd; k++) {
        c->sample_due[k] = on_grid(t, t0, c->sample_dt[k]);
        any |= (int)c->sample_due[k];
    }
    return any;
}

static double probe_holds(Ctx *c, i64 mid, double t, double t1, const double *x,
                          const double *xn, const double *f0, const double *f1, const double *K,
                          i64 n, double *xg, i64 *stats, double t0, double *D, int *ready) {
    i64 nmh = c->nmh;
    double h = t1 - t;
    double first = -1.0;
    c->probing[0] = 1;
    for (i64 k = 0; k < nmh; k++) c->hold_mode[k] = HOLD_SKIP;
    for (i64 k = 0; k < nmh; k++) {
        double dt = c->hold_dt[k];
        double tg = next_grid(t, t0, dt);
        c->hold_mode[k] = HOLD_PROBE;
        while (tg < t1 - 1e-9 * pmax(1.0, fabs(t1))) {
            if (first >= 0.0 && tg >= first) break;
            dense_eval(mid, h, (tg - t) / h, x, xn, f0, f1, K, n, xg, D, ready);
            c->clock[0] = tg;
            stats[S_PROBES] += 1;
            if (diagram_eval(c, AFTER_STEP, tg, xg, xg) == HOLD_UPDATED) {
                first = tg;
                break;
            }
            tg = next_grid(tg, t0, dt);
        }
        c->hold_mode[k] = HOLD_SKIP;
    }
    c->probing[0] = 0;
    return first;
}

static void set_hold_modes(Ctx *c, double t_prev, double t, double t0, int fixed) {
    for (i64 k = 0; k < c->nmh; k++) {
        double dt = c->hold_dt[k];
        if (on_grid(t, t0, dt) || (fixed && next_grid(t_prev, t0, dt) <= t))
            c->hold_mode[k] = HOLD_COMMIT;
        else
            c->hold_mode[k] = HOLD_SKIP;
    }
    c->clock[0] = t;
}

static int step_loop(Ctx *c, i64 mid, double *tf, double t_stop, double *x, i64 n,
                     const double *out_t, const Rec *rec,
                     i64 *io, i64 *stats, const double *ctl, double *K, double *J, double *LU,
                     i64 *piv, double *xn, double *f1, double *xg, double *D) {
    double rtol = ctl[0], atol = ctl[1], h_max = ctl[2], max_steps = ctl[3], x_limit = ctl[4];
    int adaptive = ctl[5] != 0.0;
    int dense_out = ctl[6] != 0.0;
    int check_stiff = ctl[7] != 0.0;
    i64 nmh = c->nmh;
    double t = tf[F_T], h = tf[F_H], t0 = tf[F_T0];
    diagram_eval(c, RHS, t, x, ROW(K, 0));
    stats[S_RHS] += 1;
    stats[S_FRESH] = 1;
    stats[S_JVALID] = 0;
    double fac_max = 5.0;
    double h_acc = -1.0, err_acc = 1.0, t_cut = -1.0;
    int pinned = 0, explicit_ok = 1;
    for (;;) {
        int landing = 0;
        double h_use, t_target = 0.0;
        if (adaptive) {
            if (t >= t_stop - 1e-12 * pmax(1.0, fabs(t))) break;
            if ((double)(stats[S_STEPS] + stats[S_REJECTED]) >= max_steps) {
                tf[F_T] = t;
                return MAX_STEPS;
            }
            h = pmin(h, h_max);
            t_target = t_stop;
            if (!dense_out && io[0] < io[1] && out_t[io[0]] < t_target) t_target = out_t[io[0]];
            if (t_cut > t && t_cut < t_target) t_target = t_cut;
            if (c->nsd > 0) t_target = pmin(t_target, next_sample(c, t, t0));
            if (t + h >= t_target - 1e-12 * pmax(1.0, fabs(t))) {
                h_use = t_target - t;
                landing = 1;
            } else {
                h_use = h;
            }
            if (h_use < 1e-13 * pmax(1.0, fabs(t))) {
                if (landing && io[0] < io[1] && t_target == out_t[io[0]]) {
                    emit(c, t, x, n, rec, io);
                    continue;
                }
                stats[S_BAD] = -1;
                tf[F_T] = t;
                return STEP_TOO_SMALL;
            }
        } else {
            i64 kstep = stats[S_STEPS];
            t = t0 + (double)kstep * h;
            if (t >= t_stop - 1e-9 * h) break;
            h_use = h;
        }
        if (dense_out && c->nd > 0 && c->hist_meta[1] + 2 > c->hist_meta[2]) {
            tf[F_T] = t;
            tf[F_H] = h;
            return HISTORY_FULL;
        }
        i64 m = mid;
        if (mid == RODAS5P && pinned && explicit_ok) m = BS23;
        double err = method_step(c, m, t, h_use, x, xn, K, n, J, LU, piv, rtol, atol, stats);
        if (err < 0.0) {
            tf[F_T] = t;
            return UNKNOWN_METHOD;
        }
        stats[S_FRESH] = 0;
        int dense_ready = 0;      /* D is not this step's yet */
        if (m != mid && !(err <= 1.0)) {
            stats[S_JVALID] = 0;
            explicit_ok = 0;
            stats[S_REJECTED] += 1;
            continue;
        }
        if (adaptive && !(err <= 1.0)) {
            double fac;
            if (!(err == err)) {
                i64 bad = check_state(xn, n, x_limit);
                if (bad >= 0 && h_use < 1e-10 * pmax(1.0, fabs(t))) {
                    stats[S_BAD] = bad;
                    tf[F_T] = t;
                    return DIVERGED;
                }
                fac = 0.1;
            } else {
                fac = pmax(0.1, 0.9 * pow(err, -0.2));
            }
            h = h_use * fac;
            fac_max = 1.0;
            stats[S_REJECTED] += 1;
            continue;           /* t, x unchanged: J stays valid for the retry */
        }
        stats[S_JVALID] = 0;    /* the step is taken, or cut at a max-hold update */
        double t1;
        if (adaptive) t1 = landing ? t_target : t + h_use;
        else t1 = t0 + (double)(stats[S_STEPS] + 1) * h;
        int swept = 0;
        int late_slope = m == RODAS5P;
        if (m == DP45 || m == BS23) {
            for (i64 i = 0; i < n; i++) f1[i] = K[6 * n + i];
        } else if (!late_slope) {
            diagram_eval(c, RHS, t1, xn, f1);
            stats[S_RHS] += 1;
        }
        if (nmh > 0 && adaptive) {
            i64 probes = stats[S_PROBES];
            double tg = probe_holds(c, m, t, t1, x, xn, ROW(K, 0), f1, K, n, xg, stats, t0, D,
                                    &dense_ready);
            swept = stats[S_PROBES] != probes;
            if (tg > 0.0) {
                t_cut = tg;
                h = tg - t;
                stats[S_CUTS] += 1;
                continue;
            }
        }
        int cut_landed = t_cut >= 0.0 && t1 >= t_cut - 1e-12 * pmax(1.0, fabs(t1));
        if (m != mid) stats[S_EXPLICIT] += 1;
        if (check_stiff && mid == DP45 && !(landing && h_use < h)) {
            double num = 0.0, den = 0.0;
            for (i64 i = 0; i < n; i++) {
                double a = K[6 * n + i] - K[5 * n + i];
                double b = xn[i] - K[7 * n + i];
                num += a * a;
                den += b * b;
            }
            if (den > 0.0) {
                double hrho = h_use * sqrt(num / den);
                tf[F_HRHO] = hrho;
                if (hrho > 3.25) {
                    stats[S_NONSTIFF] = 0;
                    stats[S_STIFF_RUN] += 1;
                    if (stats[S_STIFF_RUN] >= 15 && stats[S_STIFF] == 0) {
                        stats[S_STIFF] = 1;
                        tf[F_T_STIFF] = t1;
                        tf[F_HRHO_STIFF] = hrho;
                    }
                } else {
                    stats[S_NONSTIFF] += 1;
                    if (stats[S_NONSTIFF] >= 6) stats[S_STIFF_RUN] = 0;
                }
            }
        }
        if (dense_out) {
            while (io[0] < io[1] && out_t[io[0]] < t1 - 1e-12 * pmax(1.0, fabs(t1))) {
                double to = out_t[io[0]];
                dense_eval(m, h_use, (to - t) / (t1 - t), x, xn, ROW(K, 0), f1, K, n, xg, D,
                           &dense_ready);
                emit(c, to, xg, n, rec, io);
                swept = 1;
            }
        }
        if (dense_out && c->nd > 0 && m == mid) {
            for (i64 k = 0; k < nmh; k++) c->hold_mode[k] = HOLD_SKIP;
            double tm = t + 0.5 * (t1 - t);
            dense_eval(m, h_use, 0.5, x, xn, ROW(K, 0), f1, K, n, xg, D, &dense_ready);
            c->clock[0] = tm;
            diagram_eval(c, HISTORY_POINT, tm, xg, xg);
            swept = 1;
        }
        if (late_slope) {
            diagram_eval(c, RHS, t1, xn, f1);
            stats[S_RHS] += 1;
            swept = 0;
        }
        double t_prev = t;
        t = t1;
        for (i64 i = 0; i < n; i++) {
            x[i] = xn[i];
            K[i] = f1[i];
        }
        stats[S_STEPS] += 1;
        tf[F_T] = t;
        tf[F_ERR] = err;
        i64 bad = check_state(x, n, x_limit);
        if (bad >= 0) {
            stats[S_BAD] = bad;
            return DIVERGED;
        }
        double nrm = 0.0;
        for (i64 i = 0; i < n; i++) {
            if (fabs(x[i]) > nrm) {
                nrm = fabs(x[i]);
                bad = i;
            }
        }
        double ref = pmax(tf[F_GROW_N], 1.0);
        if (nrm > GROWTH_FACTOR * ref && t - tf[F_GROW_T] <= GROWTH_WINDOW) {
            stats[S_BAD] = bad;
            tf[F_GROW_RATE] = log(nrm / ref) / pmax(t - tf[F_GROW_T], 1e-300);
            return DIVERGED_GROWTH;
        }
        if (t - tf[F_GROW_T] >= GROWTH_WINDOW) {
            tf[F_GROW_T] = t;
            tf[F_GROW_N] = nrm;
        }
        int sampled = c->nsd > 0 && sample_due(c, t, t0);
        if (sampled && c->sample(t, (i64)(intptr_t)x) != 0) {
            tf[F_H] = h;
            return STOPPED;
        }
        if (nmh > 0) set_hold_modes(c, t_prev, t, t0, !adaptive);
        int st;
        if (swept || sampled) st = diagram_eval(c, AFTER_STEP, t, x, x);
        else st = diagram_eval(c, AFTER_STEP_EVALUATED, t, x, x);
        if (st == HISTORY_FULL) {
            tf[F_H] = h;
            return HISTORY_FULL;
        }
        if (st == HOLD_UPDATED || sampled) {
            diagram_eval(c, RHS, t, x, ROW(K, 0));
            stats[S_RHS] += 1;
        }
        stats[S_FRESH] = 1;
        if (adaptive) {
            while (io[0] < io[1] && out_t[io[0]] <= t + 1e-12 * pmax(1.0, fabs(t)))
                emit(c, t, x, n, rec, io);
            if (!landing || h_use >= h) {
                double fac = err == 0.0 ? 5.0 : pmin(fac_max, pmax(0.2, 0.9 * pow(err, -0.2)));
                if (m == RODAS5P) {
                    if (h_acc > 0.0 && err > 0.0) {
                        double fac_p = 0.9 * (h_use / h_acc) * pow(err_acc / (err * err), 0.2);
                        fac = pmin(fac, pmax(0.2, fac_p));
                    }
                    h_acc = h_use;
                    err_acc = pmax(1e-2, err);
                }
                h = h_use * fac;
            }
            fac_max = 5.0;
            if (cut_landed || st == HOLD_UPDATED) {
                t_cut = -1.0;
                if (!pinned) explicit_ok = 1;
                pinned = 1;
                for (i64 k = 0; k < nmh; k++) {
                    double hg = next_grid(t, t0, c->hold_dt[k]) - t;
                    if (hg < h) h = hg;
                }
            } else {
                pinned = 0;
            }
        } else {
            /* out_t is the caller's output times: a fixed-step run records each at the
               first step at or after it, and reports that step's time (as the template) */
            while (io[0] < io[1] && out_t[io[0]] <= t + 1e-9 * h) {
                ((double *)out_t)[io[0]] = t;
                emit(c, t, x, n, rec, io);
            }
        }
        if (c->report != NULL && t >= tf[F_REPORT]) {
            tf[F_T] = t;
            if (c->report(t) != 0) {
                tf[F_H] = h;
                return STOPPED;
            }
        }
    }
    tf[F_T] = t;
    tf[F_H] = h;
    return OK;
}

/* ---------------------------------------------------- generic versions */
static int fd_jacobian(Ctx *c, double t, const double *x, double *J, i64 n, double *f0,
                       double *fp, double *xp) {
    diagram_eval(c, RHS, t, x, f0);
    return fd_columns(c, t, x, J, n, f0, fp, xp);
}

/* J = df/dx by forward differences given f0 = f(t, x) (n evaluations) */
static int fd_columns(Ctx *c, double t, const double *x, double *J, i64 n, const double *f0,
                      double *fp, double *xp) {
    for (i64 i = 0; i < n; i++) xp[i] = x[i];
    for (i64 j = 0; j < n; j++) {
        double d = 1.4901161193847656e-08 * pmax(1.0, fabs(x[j]));
        xp[j] = x[j] + d;
        d = xp[j] - x[j];
        diagram_eval(c, RHS, t, xp, fp);
        for (i64 i = 0; i < n; i++) J[i * n + j] = (fp[i] - f0[i]) / d;
        xp[j] = x[j];
    }
    return OK;
}

static int dense_factor(const double *J, i64 n, double cc, double *LU, i64 *piv) {
    for (i64 i = 0; i < n; i++) {
        for (i64 j = 0; j < n; j++) LU[i * n + j] = -J[i * n + j];
        LU[i * n + i] += cc;
    }
    for (i64 k = 0; k < n; k++) {
        i64 p = k;
        double m = fabs(LU[k * n + k]);
        for (i64 i = k + 1; i < n; i++) {
            if (fabs(LU[i * n + k]) > m) {
                m = fabs(LU[i * n + k]);
                p = i;
            }
        }
        piv[k] = p;
        if (!(m > 0.0) || !isfinite(m)) return SINGULAR;
        if (p != k) {
            for (i64 j = 0; j < n; j++) {
                double tmp = LU[k * n + j];
                LU[k * n + j] = LU[p * n + j];
                LU[p * n + j] = tmp;
            }
        }
        double inv = 1.0 / LU[k * n + k];
        for (i64 i = k + 1; i < n; i++) {
            double l = LU[i * n + k] * inv;
            LU[i * n + k] = l;
            if (l != 0.0)
                for (i64 j = k + 1; j < n; j++) LU[i * n + j] -= l * LU[k * n + j];
        }
    }
    return OK;
}

static void dense_solve(const double *LU, i64 n, const i64 *piv, double *b) {
    for (i64 k = 0; k < n; k++) {
        i64 p = piv[k];
        if (p != k) {
            double tmp = b[k];
            b[k] = b[p];
            b[p] = tmp;
        }
    }
    for (i64 i = 0; i < n; i++) {
        double s = b[i];
        for (i64 j = 0; j < i; j++) s -= LU[i * n + j] * b[j];
        b[i] = s;
    }
    for (i64 i = n - 1; i >= 0; i--) {
        double s = b[i];
        for (i64 j = i + 1; j < n; j++) s -= LU[i * n + j] * b[j];
        b[i] = s / LU[i * n + i];
    }
}

/* ------------------------------------------------------------------------ entry points
 * Each returns its result (a status), or the code of a failure the Python source raises
 * (BLOCK_RAISED, ERR_*), which _cstepper.py turns into the same RuntimeError. */
EXPORT int ivdrem_step_loop(const i64 *waddr, const i64 *wshape, double *P, i64 mid,
                            double *tf, double t_stop, double *x, i64 n, double *out_t,
                            double *out_y, double *out_x, const i64 *rec_layout, i64 *io,
                            i64 *stats, double *ctl, double *K, double *J, double *LU,
                            i64 *piv, double *xn, double *f1, double *xg, double *D) {
    Ctx c;
    bind_ctx(&c, waddr, wshape, P);
    int code = setjmp(c.exit);
    if (code) return code;
    Rec rec = {out_y, out_x, rec_layout[0], rec_layout[1], rec_layout[2], rec_layout[3],
               rec_layout[4], rec_layout[5]};
    return step_loop(&c, mid, tf, t_stop, x, n, out_t, &rec, io, stats,
                     ctl, K, J, LU, piv, xn, f1, xg, D);
}

EXPORT int ivdrem_diagram_eval(const i64 *waddr, const i64 *wshape, double *P, i64 mode,
                               double t, double *x, double *out) {
    Ctx c;
    bind_ctx(&c, waddr, wshape, P);
    int code = setjmp(c.exit);
    if (code) return code;
    return diagram_eval(&c, mode, t, x, out);
}

EXPORT int ivdrem_diagram_jacobian(const i64 *waddr, const i64 *wshape, double *P, double t,
                                   double *x, i64 n, double *J, double *tmp) {
    Ctx c;
    bind_ctx(&c, waddr, wshape, P);
    int code = setjmp(c.exit);
    if (code) return code;
    return diagram_jacobian(&c, t, x, J, n, tmp);
}

/* lengths of the loop's J and LU (work arrays the caller allocates): dense for a diagram
 * called back, in the filled LU pattern of the tables otherwise (slu_factor) */
EXPORT void ivdrem_work_sizes(const i64 *waddr, const i64 *wshape, i64 n, i64 *out) {
    Ctx c;
    bind_ctx(&c, waddr, wshape, NULL);
    if (c.callback) {
        out[0] = n * n;
        out[1] = (n + 2) * n;
        return;
    }
    i64 nnz = int_table(&c, T_LU_ROWPTR).p[n];
    out[0] = nnz;
    out[1] = nnz + LU_WORK_ROWS * n;
}

EXPORT int ivdrem_fd_jacobian(const i64 *waddr, const i64 *wshape, double *P, double t,
                              double *x, i64 n, double *J, double *f0, double *fp, double *xp) {
    Ctx c;
    bind_ctx(&c, waddr, wshape, P);
    int code = setjmp(c.exit);
    if (code) return code;
    return fd_jacobian(&c, t, x, J, n, f0, fp, xp);
}

EXPORT int ivdrem_lowest_eigenpair(const i64 *waddr, const i64 *wshape, double *u, i64 nvec,
                                   i64 nmat, double *lam) {
    Ctx c;
    bind_ctx(&c, waddr, wshape, NULL);
    int code = setjmp(c.exit);
    if (code) return code;
    lam[0] = lowest_eigenpair(&c, u, nvec, nmat);
    return OK;
}

EXPORT int ivdrem_hist_lookup(const i64 *waddr, const i64 *wshape, double tq, i64 off,
                              i64 size, double *out) {
    Ctx c;
    bind_ctx(&c, waddr, wshape, NULL);
    hist_lookup(&c, tq, off, size, out);
    return OK;
}

EXPORT int ivdrem_slu_factor(const double *J, i64 n, double cc, double *LU, i64 *piv,
                             const i64 *perm, const i64 *rowptr, const int32_t *colidx,
                             const i64 *diagp, const i64 *panel_rows, i64 npanels,
                             const i64 *panel_kptr, const i64 *panel_k) {
    SluPattern pt = {perm, rowptr, diagp, panel_rows, panel_kptr, panel_k, colidx, npanels};
    return slu_factor(J, n, cc, LU, piv, &pt);
}

EXPORT void ivdrem_slu_solve(double *LU, i64 n, const i64 *perm, const i64 *rowptr,
                             const int32_t *colidx, const i64 *diagp, double *b) {
    SluPattern pt = {perm, rowptr, diagp, NULL, NULL, NULL, colidx, 0};
    slu_solve(LU, n, &pt, b);
}

EXPORT int ivdrem_dense_factor(const double *J, i64 n, double cc, double *LU, i64 *piv) {
    return dense_factor(J, n, cc, LU, piv);
}

EXPORT void ivdrem_dense_solve(const double *LU, i64 n, const i64 *piv, double *b) {
    dense_solve(LU, n, piv, b);
}
