/* ivdrem_controller.c: the sampled controller of the paper (eqs. 7-21), plain C99.
 *
 * Hand-written core of the generated controller library (ivdrem/controller/codegen.py);
 * the model's sizes and regressors come from the generated controller_model.h/.c.  The
 * algorithm is that of the Python reference ivdrem/controller/sampled.py, step for step
 * (docs/controller.md): outputs at t_k from the states at t_k, then every state advanced
 * over [t_k, t_k + h] with its sampled inputs held, by exact updates of the linear filters.
 * No allocation after ivc_init; no dependency but libm.
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "ivdrem_controller.h"

#define NQT (IVC_NQ * IVC_NTHETA)
#define NM (IVC_NTHETA + IVC_NTHETA * IVC_NTHETA)
/* The multi-rate mixing's budget: a sample spends at most IVC_MIX_BUDGET units (n
 * multiply-adds each; 6000 units took 0.1-0.2 ms on the Panda at load 8-15) on the job,
 * and a job does as many sweeps as mix_every * IVC_MIX_BUDGET hold (ntheta = 43: 11 at m = 20,
 * 29 at m = 50), at least IVC_MIX_SWEEPS (then a sample spends more: m < 14) and at most 80.  A
 * job that reaches its cap ends there, converged or not, its rotations the next job's warm
 * start.  Measured on the Panda (bench_controller.py's motion, T = 40 s, the mixing every
 * 20 samples, 60 s): 4-5 sweeps (the last one finding nothing to rotate) after t = 36 s,
 * at most 7 after t = 1.9 s, up to 20 while the window starts (t <= 0.12 s, the composite
 * term still off). */
#define IVC_MIX_BUDGET 6000.0
#define IVC_MIX_SWEEPS 8
static double mix_job_units(int sweeps);

/* the phases of the max-hold's lambda_min job (lam_begin, lam_work) and the most bisection
 * steps it takes (about 54 reach eps ||S||) */
enum { LAM_HOUSE = 0, LAM_BISECT = 1, LAM_DONE = 2 };
#define IVC_LAM_BISECT 64
static double lam_job_units(void);

/* the phases of the mixing job (mix_begin, mix_work) */
enum { MIX_ROWS = 0, MIX_SWEEP = 1, MIX_FINISH = 2, MIX_COMPLETE = 3, MIX_DET = 4, MIX_RESULT = 5,
       MIX_DONE = 6 };

/* the whole state but the window's ring of block sums: plain doubles, copied as bytes */
typedef struct {
    double k;                                   /* samples taken (exact below 2^53) */
    double Phi_f[NQT], Phi_Mf[NQT], u_f[IVC_NQ], theta_hat[IVC_NTHETA];
    double zf[IVC_NQ], xi[NQT], eta[NQT], X_xi[NQT], X_eta[NQT], zeta[NQT], Yavg[NM];
    double tau_prev[IVC_NQ], tau[IVC_NQ], tau_d_hat[IVC_NQ], Delta;
    double held[NM], lambda_min_held;           /* composite learning: (Y_b, Psi_b)(t_e) */
    double D_held[IVC_NTHETA], calY_held[IVC_NTHETA]; /* the mixing (17) in use */
    double qd[IVC_NQ], dqd[IVC_NQ];             /* the reference at the last sample */
    /* the mixing job (mix_begin, mix_work): its input (Y, Psi), U, V (after a job: the next
     * warm start), sig, result, and where it stands */
    double mix_in[NM], mix_U[IVC_NTHETA * IVC_NTHETA], mix_V[IVC_NTHETA * IVC_NTHETA];
    double mix_sig[IVC_NTHETA], mix_D[IVC_NTHETA], mix_calY[IVC_NTHETA], mix_coef[IVC_NTHETA];
    double mix_W[IVC_NTHETA * IVC_NTHETA];      /* P = Psi / s, then det U's elimination */
    double mix_phase, mix_j, mix_k, mix_sweep, mix_rotated, mix_warm, mix_nrm, mix_s, mix_suv;
    double mix_det, mix_m;
    double has_warm;
    /* the max-hold's lambda_min job (lam_begin, lam_work): its input (Y_b, Psi_b), the
     * symmetric part being reduced, the tridiagonal (d, e), where it stands, its value */
    double lam_in[NM], lam_S[IVC_NTHETA * IVC_NTHETA], lam_d[IVC_NTHETA], lam_e[IVC_NTHETA];
    double lam_phase, lam_k, lam_iter, lam_lo, lam_hi, lam_tol, lam_pivmin, lam_scale, lam_value;
    /* window (15a): partial block, running sum, shadow sum, previous sample */
    double P[NM], S[NM], shadow[NM], g_prev[NM];
    double pos, i, nshadow, has_prev;
} ivc_state;

struct ivc_controller {
    double par[IVC_NPAR];
    int law, delay, corrected, block;           /* structural, fixed at ivc_init */
    int design, mixing, mix_every, gravity, ref_kind;
    long nb;                                    /* blocks in the ring */
    double h, T;
    double mix_units;                           /* the mixing job's budget per sample */
    int mix_sweeps;                             /* ... and its most sweeps (mix_every > 1) */
    double lam_units;                           /* the max-hold job's budget per sample */
    ivc_state s;
    double *ring;                               /* nb x NM block sums */
    char msg[256];
};

/* the message of a refusal: one line, at most 255 characters */
static void say(char *msg, const char *fmt, double a, double b) { snprintf(msg, 256, fmt, a, b); }

static void fail(ivc_controller *c, const char *fmt, double a, double b) {
    if (c) say(c->msg, fmt, a, b);
}

const char *ivc_message(const ivc_controller *c) { return c ? c->msg : "no controller"; }

size_t ivc_window_bytes(const ivc_controller *c) {
    return c ? (size_t)c->nb * NM * sizeof(double) + 4 * NM * sizeof(double) : 0;
}

void ivc_default_params(double *par) { memcpy(par, IVC_PAR_DEFAULTS, sizeof IVC_PAR_DEFAULTS); }

/* a whole number in 0..last */
static int is_code(double v, int last) { return v >= 0 && v <= last && floor(v) == v; }

static int check_params(char *msg, const double *par) {
    int i;
    for (i = 0; i < IVC_NPAR; i++)
        if (isnan(par[i])) { say(msg, "parameter %g is NaN", (double)i, 0); return IVC_ERR_ARG; }
    if (!(par[IVC_P_H] > 0 && isfinite(par[IVC_P_H])))
        { say(msg, "h = %g must be > 0 and finite%s", par[IVC_P_H], 0); return IVC_ERR_ARG; }
    if (!(par[IVC_P_DELTA_MU] > 0 && par[IVC_P_DELTA_MU] < 1))
        { say(msg, "delta_mu = %g must lie in (0, 1)%.0s", par[IVC_P_DELTA_MU], 0); return IVC_ERR_ARG; }
    if (!(par[IVC_P_MU0] >= 0 && par[IVC_P_MU1] > 0 && par[IVC_P_MU_MAX] >= par[IVC_P_MU1]))
        { say(msg, "need mu0 >= 0 and mu_max >= mu1 > 0 (mu1 = %g, mu_max = %g)",
               par[IVC_P_MU1], par[IVC_P_MU_MAX]); return IVC_ERR_ARG; }
    for (i = 0; i < IVC_NTHETA; i++)
        if (!(par[IVC_P_GAMMA_DIAG + i] > 0 && isfinite(par[IVC_P_GAMMA_DIAG + i])))
            { say(msg, "Gamma[%g] = %g must be > 0", (double)i, par[IVC_P_GAMMA_DIAG + i]); return IVC_ERR_ARG; }
    if (!(par[IVC_P_L] > 0 && par[IVC_P_T] > 0 && par[IVC_P_F0] > 0 && par[IVC_P_P] >= 1
          && par[IVC_P_GAMMA] > 0 && par[IVC_P_SIGMA] > 0 && par[IVC_P_EPSILON] > 0
          && par[IVC_P_F_REL] > 0 && par[IVC_P_GUARD] > 0))
        { say(msg, "l, T, F0, gamma, sigma, epsilon, f_rel, guard must be > 0 and p >= 1 (p = %g, T = %g)",
               par[IVC_P_P], par[IVC_P_T]); return IVC_ERR_ARG; }
    for (i = 0; i < IVC_NQ; i++) {
        if (!(par[IVC_P_TAU_MAX + i] > 0))
            { say(msg, "tau_max[%g] = %g must be > 0 (inf: no limit)", (double)i, par[IVC_P_TAU_MAX + i]); return IVC_ERR_ARG; }
        if (!(par[IVC_P_TAU_RATE_MAX + i] > 0))
            { say(msg, "tau_rate_max[%g] = %g must be > 0 (inf: no limit)", (double)i, par[IVC_P_TAU_RATE_MAX + i]); return IVC_ERR_ARG; }
    }
    if (!is_code(par[IVC_P_LAW], IVC_LAW_LAST))
        { say(msg, "law = %g is not a law code 0..%g", par[IVC_P_LAW], IVC_LAW_LAST); return IVC_ERR_ARG; }
    if (!is_code(par[IVC_P_DELAY], 1))
        { say(msg, "delay = %g must be 0 or 1%.0s", par[IVC_P_DELAY], 0); return IVC_ERR_ARG; }
    if (!is_code(par[IVC_P_DESIGN], IVC_DESIGN_INERTIA_SCALED))
        { say(msg, "design = %g is not a design code (0 paper, 1 inertia-scaled)%.0s", par[IVC_P_DESIGN], 0); return IVC_ERR_ARG; }
    if (!is_code(par[IVC_P_INJECTION], 1))
        { say(msg, "injection = %g must be 0 (theta_hat) or 1 (theta_nominal)%.0s", par[IVC_P_INJECTION], 0); return IVC_ERR_ARG; }
    if (!is_code(par[IVC_P_GRAVITY], IVC_GRAVITY_ROBOT))
        { say(msg, "gravity = %g is not a gravity code (0 controller, 1 robot)%.0s", par[IVC_P_GRAVITY], 0); return IVC_ERR_ARG; }
    if (!is_code(par[IVC_P_MIXING], IVC_MIXING_CHANNEL))
        { say(msg, "mixing = %g is not a mixing code (0 paper, 1 eigen, 2 channel)%.0s", par[IVC_P_MIXING], 0); return IVC_ERR_ARG; }
    if (!(par[IVC_P_MIX_EVERY] >= 1 && par[IVC_P_MIX_EVERY] <= 1e6 && floor(par[IVC_P_MIX_EVERY]) == par[IVC_P_MIX_EVERY]))
        { say(msg, "mix_every = %g must be a whole number >= 1%.0s", par[IVC_P_MIX_EVERY], 0); return IVC_ERR_ARG; }
    if (!is_code(par[IVC_P_REF_KIND], 1) || (par[IVC_P_REF_KIND] == 1 && !(par[IVC_P_FR_OMEGA_F] > 0 && isfinite(par[IVC_P_FR_OMEGA_F]))))
        { say(msg, "ref_kind = %g must be 0 (sinusoid) or 1 (Fourier, with fr_omega_f = %g > 0)",
               par[IVC_P_REF_KIND], par[IVC_P_FR_OMEGA_F]); return IVC_ERR_ARG; }
    {   /* the window (15a): T a whole number of samples h, divisible by block */
        int law = (int)par[IVC_P_LAW];
        double h = par[IVC_P_H], T = par[IVC_P_T], N = floor(T / h + 0.5), block = par[IVC_P_BLOCK];
        if (!(block >= 1 && floor(block) == block))
            { say(msg, "block = %g must be a whole number >= 1%.0s", block, 0); return IVC_ERR_ARG; }
        if ((law == IVC_LAW_IV_DREM || law == IVC_LAW_DREM || law == IVC_LAW_COMPOSITE_LEARNING)
            && (fabs(N * h - T) > 1e-9 * T || fmod(N, block) != 0 || N / block > 1e8))
            { say(msg, "the window T / h = %.9g must be a whole number of samples divisible by "
                   "block = %g (choose T a multiple of h block)", T / h, block); return IVC_ERR_ARG; }
    }
    return IVC_OK;
}

int ivc_check_params(const double *par, char *msg, size_t len) {
    char buf[256];
    int st;
    buf[0] = 0;
    st = check_params(buf, par);
    if (msg && len) snprintf(msg, len, "%s", buf);
    return st;
}

int ivc_reset(ivc_controller *c) {
    int i;
    if (!c) return IVC_ERR_STATE;
    memset(&c->s, 0, sizeof c->s);
    for (i = 0; i < IVC_NTHETA; i++) c->s.theta_hat[i] = c->par[IVC_P_THETA_HAT0 + i];
    c->s.mix_phase = MIX_DONE;                  /* nothing to finish; its result: 0 */
    c->s.lam_phase = LAM_DONE;
    if (c->ring) memset(c->ring, 0, (size_t)c->nb * NM * sizeof(double));
    c->msg[0] = 0;
    return IVC_OK;
}

ivc_controller *ivc_init(const double *par, char *msg, size_t len) {
    ivc_controller *c;
    double h, T, N;
    int law, block, delay;
    char buf[256];
    if (ivc_check_params(par, buf, sizeof buf) != IVC_OK) {
        if (msg && len) snprintf(msg, len, "%s", buf);
        return NULL;
    }
    law = (int)par[IVC_P_LAW];
    delay = (int)par[IVC_P_DELAY];
    block = (int)par[IVC_P_BLOCK];
    h = par[IVC_P_H];
    T = par[IVC_P_T];
    N = floor(T / h + 0.5);
    c = (ivc_controller *)calloc(1, sizeof *c);
    if (!c) { if (msg && len) snprintf(msg, len, "out of memory"); return NULL; }
    memcpy(c->par, par, sizeof c->par);
    c->law = law;
    c->delay = delay;
    c->corrected = par[IVC_P_CORRECTED] != 0;
    c->block = block;
    c->design = (int)par[IVC_P_DESIGN];
    c->mixing = (int)par[IVC_P_MIXING];
    c->mix_every = (int)par[IVC_P_MIX_EVERY];
    c->gravity = (int)par[IVC_P_GRAVITY];
    c->ref_kind = (int)par[IVC_P_REF_KIND];
    {   /* the multi-rate mixing: its sweeps, and its whole work spread over the period */
        int sw = IVC_MIX_SWEEPS;
        while (sw < 80 && mix_job_units(sw + 1) <= c->mix_every * IVC_MIX_BUDGET) sw++;
        c->mix_sweeps = sw;
        c->mix_units = ceil(mix_job_units(sw) / c->mix_every);
    }
    /* the max-hold's job: its fixed work spread over the mix_every samples of a period */
    c->lam_units = ceil(lam_job_units() / c->mix_every);
    c->h = h;
    c->T = T;
    c->nb = (law == IVC_LAW_IV_DREM || law == IVC_LAW_DREM || law == IVC_LAW_COMPOSITE_LEARNING)
            ? (long)(N / block) : 0;
    if (c->nb) {
        c->ring = (double *)calloc((size_t)c->nb * NM, sizeof(double));
        if (!c->ring) {
            free(c);
            if (msg && len) snprintf(msg, len, "out of memory for the window (%g blocks)", N / block);
            return NULL;
        }
    }
    ivc_reset(c);
    return c;
}

void ivc_free(ivc_controller *c) {
    if (!c) return;
    free(c->ring);
    free(c);
}

/* the parameters that fix the memory or the meaning of the state: the header's
 * IVC_IS_STRUCTURAL, generated from ivdrem.controller.parameters (STRUCTURAL) */
static int is_structural(int index) { return IVC_IS_STRUCTURAL(index); }

int ivc_set_param(ivc_controller *c, int index, double value) {
    double par[IVC_NPAR];
    if (!c) return IVC_ERR_STATE;
    if (index < 0 || index >= IVC_NPAR) { fail(c, "no parameter %g%.0s", index, 0); return IVC_ERR_ARG; }
    if (is_structural(index)) {
        if (value == c->par[index]) return IVC_OK;
        fail(c, "parameter %g is structural (fixed at ivc_init)%.0s", index, 0);
        return IVC_ERR_ARG;
    }
    memcpy(par, c->par, sizeof par);
    par[index] = value;
    if (check_params(c->msg, par) != IVC_OK) return IVC_ERR_ARG;
    c->par[index] = value;
    return IVC_OK;
}

double ivc_get_param(const ivc_controller *c, int index) {
    return (c && index >= 0 && index < IVC_NPAR) ? c->par[index] : NAN;
}

/* ------------------------------------------------------------------ state save/restore */
size_t ivc_state_size(const ivc_controller *c) {
    return c ? sizeof(ivc_state) + sizeof c->par + (size_t)c->nb * NM * sizeof(double) : 0;
}

int ivc_get_state(const ivc_controller *c, void *buf, size_t size) {
    unsigned char *b = (unsigned char *)buf;
    if (!c || !buf || size != ivc_state_size(c)) return IVC_ERR_ARG;
    memcpy(b, &c->s, sizeof c->s);
    memcpy(b + sizeof c->s, c->par, sizeof c->par);
    if (c->nb) memcpy(b + sizeof c->s + sizeof c->par, c->ring, (size_t)c->nb * NM * sizeof(double));
    return IVC_OK;
}

int ivc_set_state(ivc_controller *c, const void *buf, size_t size) {
    const unsigned char *b = (const unsigned char *)buf;
    double par[IVC_NPAR];
    if (!c || !buf) return IVC_ERR_ARG;
    if (size != ivc_state_size(c)) { fail(c, "state of %g bytes, expected %g", (double)size,
                                          (double)ivc_state_size(c)); return IVC_ERR_ARG; }
    memcpy(par, b + sizeof c->s, sizeof par);
    {
        int i;
        for (i = 0; i < IVC_NPAR; i++)
            if (is_structural(i) && par[i] != c->par[i]) {
                fail(c, "state of another configuration (parameter %g: %g; structural)", (double)i, par[i]);
                return IVC_ERR_ARG;
            }
    }
    memcpy(&c->s, b, sizeof c->s);
    memcpy(c->par, par, sizeof par);
    if (c->nb) memcpy(c->ring, b + sizeof c->s + sizeof c->par, (size_t)c->nb * NM * sizeof(double));
    return IVC_OK;
}

/* ------------------------------------------------------------------ small numerics */
static double mu_sat(const double *par, double t) {
    double m = par[IVC_P_MU0] * t + par[IVC_P_MU1];
    return m >= par[IVC_P_MU_MAX] ? par[IVC_P_MU_MAX] : m;
}

/* int_t^{t+h} min(mu0 s + mu1, mu_max) ds in closed form (ivdrem.controller.discrete) */
static double mu_integral(const double *par, double t, double h) {
    double mu0 = par[IVC_P_MU0], mu1 = par[IVC_P_MU1], mx = par[IVC_P_MU_MAX];
    double t1 = t + h, ts = mu0 > 0 ? (mx - mu1) / mu0 : INFINITY;
    if (t1 <= ts) return mu0 * 0.5 * (t1 * t1 - t * t) + mu1 * h;
    if (t >= ts) return mx * h;
    return mu0 * 0.5 * (ts * ts - t * t) + mu1 * (ts - t) + mx * (t1 - ts);
}

static double phi1(double z) { return z == 0.0 ? 1.0 : expm1(z) / z; }

/* ------------------------------------------------------------------ the mixing (17) as a job
 * The mixing step (17) in the variants of ivdrem.blocks._kernels.mixing_values
 * (docs/mixing.md), from a one-sided Jacobi SVD of P = Psi / s, s = 1 + ||Psi||_F:
 *   paper   (E4)  Delta = det P, calY = adj(P) Y / s;
 *   eigen         Delta = sign(det P) prod r_j, r_j = sigma_j / (sigma_j + f),
 *                 f = f_rel ||Psi||_F / s, calY = adj(P) Y / (s prod (sigma_j + f));
 *   channel       m the smallest singular value, C = adj(P) / prod_{j != m} sigma_j,
 *                 c_i = sqrt(C_ii^2 + guard^2 ||C_i,:||^2), Delta_i = s s_UV sigma_m / c_i,
 *                 calY_i = (C Y)_i / c_i.
 * Delta has one entry (paper, eigen) or IVC_NTHETA (channel).
 *
 * One-sided Jacobi SVD: P V = U diag(sig), V a product of rotations (det V = +1), U
 * orthogonal (columns of zero singular values completed by Gram-Schmidt), s_UV = det(U).
 * "paper" starts from V = I with tolerance 1e-16; "eigen" and "channel" from the rotations
 * of the previous mixing (the window moves little between two mixings: a few sweeps instead
 * of ten or twenty) with LAPACK's tolerance sqrt(n) eps; a pair (j, k) is rotated while
 * |u_j . u_k| > tol |u_j| |u_k|.
 *
 * The work is a resumable job (mix_begin, then mix_work with a budget) so that the
 * multi-rate controller spreads one mixing over the mix_every samples of a mixing period
 * (docs/controller.md, "Real arms: reference, mixing, multi-rate").  The budget counts
 * units of n multiply-adds; the job's arithmetic, and so its result, does not depend on
 * how it is sliced, and no piece of it is larger than n^2 multiply-adds (one column of
 * U = P V0, one Jacobi pair, one column's completion, one step of det U's elimination, one
 * row of the result).  U and V are stored column by column (U[j n + i] = U_ij): a rotation
 * and the dot products of a pair run over two contiguous columns.  Phases: the columns of
 * U = P V0, Jacobi pairs, the singular values, the completion of U, det U, the variant's
 * result, row by row.  With mix_every > 1 a job ends after mix_sweeps sweeps (IVC_MIX_BUDGET),
 * converged or not (the next job starts from its rotations), so that its whole work fits
 * the period's budget: no sample finishes a long job at once. */

/* s_UV (V diag(coef) U^T)_i. Y / div: row i of the adjugate-weighted regression of (17) */
static double adjugate_row_times(const double *U, const double *V, const double *coef,
                                 double suv, const double *Y, double div, int i) {
    enum { n = IVC_NTHETA };
    int j, k;
    double acc = 0;
    for (j = 0; j < n; j++) {
        double cij = 0;                          /* adj(P)_ij = s_UV sum_k V_ik pi_k U_jk */
        for (k = 0; k < n; k++) cij += V[k * n + i] * coef[k] * U[k * n + j];
        acc += suv * cij * Y[j];
    }
    return acc / div;
}

/* prod_{j != i} x_j, by prefix and suffix products (no division) */
static void products_without(const double *x, double *out) {
    int i;
    double pre = 1.0, suf = 1.0;
    for (i = 0; i < IVC_NTHETA; i++) { out[i] = pre; pre *= x[i]; }
    for (i = IVC_NTHETA - 1; i >= 0; i--) { out[i] *= suf; suf *= x[i]; }
}

/* the whole work (units) of a multi-rate mixing job of at most `sweeps` sweeps: the
 * columns of U (warm: n units each), the sweeps (3 units a pair, 8 more when it rotates),
 * the singular values (n), det U (sum of (n - k)^2 / n), the result (n a row), and n more
 * for the completion of U's columns (none but while Psi is singular) */
static double mix_job_units(int sweeps) {
    double nt = IVC_NTHETA, pairs = 0.5 * nt * (nt - 1), det = 0;
    int k;
    for (k = 0; k < IVC_NTHETA; k++) det += (nt - k) * (nt - k) / nt;
    return nt * nt + sweeps * 11.0 * pairs + nt + det + nt * nt + nt;
}

/* start a mixing of (Y, Psi) = yp (copied: the job's input is that of this sample) */
static void mix_begin(ivc_controller *c, const double *yp) {
    enum { n = IVC_NTHETA };
    ivc_state *s = &c->s;
    const double *Psi = yp + n;
    double big = 0, ss = 0;
    int i, k;
    memcpy(s->mix_in, yp, sizeof s->mix_in);
    for (k = 0; k < n * n; k++) if (fabs(Psi[k]) > big) big = fabs(Psi[k]);
    if (big > 0) for (k = 0; k < n * n; k++) { double q = Psi[k] / big; ss += q * q; }
    s->mix_nrm = big * sqrt(ss);
    s->mix_s = 1.0 + s->mix_nrm;
    s->mix_j = 0; s->mix_k = 1; s->mix_sweep = 0; s->mix_rotated = 0;
    if (c->mixing == IVC_MIXING_EIGEN && s->mix_nrm == 0.0) {
        s->mix_D[0] = 0.0;
        for (i = 0; i < n; i++) s->mix_calY[i] = 0.0;
        s->mix_phase = MIX_DONE;
        return;
    }
    for (k = 0; k < n * n; k++) s->mix_W[k] = Psi[k] / s->mix_s;   /* P, row major */
    s->mix_warm = c->mixing != IVC_MIXING_PAPER && s->has_warm != 0;
    if (!s->mix_warm) {                /* V = I; U = P, column by column in MIX_ROWS */
        for (i = 0; i < n * n; i++) s->mix_V[i] = 0.0;
        for (i = 0; i < n; i++) s->mix_V[i * n + i] = 1.0;
    }
    s->mix_phase = MIX_ROWS;
}

/* the variant's coefficients pi_k of adj(P) = s_UV V diag(pi) U^T, and Delta (paper, eigen) or
 * the index of the smallest singular value (channel): the result's set-up, O(n) */
static void mix_result_setup(ivc_controller *c) {
    enum { n = IVC_NTHETA };
    ivc_state *s = &c->s;
    const double *sig = s->mix_sig;
    double *coef = s->mix_coef, r[n], d, suv = s->mix_suv;
    int j, k, m;
    if (c->mixing == IVC_MIXING_PAPER) {
        products_without(sig, coef);
        d = suv;
        for (k = 0; k < n; k++) d *= sig[k];
        s->mix_D[0] = d;
    } else if (c->mixing == IVC_MIXING_EIGEN) {
        double f = c->par[IVC_P_F_REL] * s->mix_nrm / s->mix_s;
        for (k = 0; k < n; k++) r[k] = sig[k] / (sig[k] + f);
        products_without(r, coef);
        for (k = 0; k < n; k++) coef[k] /= sig[k] + f;   /* pi_k / prod_j (sigma_j + f) */
        d = suv;
        for (k = 0; k < n; k++) d *= r[k];
        s->mix_D[0] = d;
    } else {
        m = 0;
        for (k = 1; k < n; k++) if (sig[k] < sig[m]) m = k;
        for (k = 0; k < n; k++) coef[k] = k == m ? 1.0 : sig[m] / sig[k];
        for (k = 0; k < n; k++) if (k != m && !(sig[k] > 0.0)) {   /* rank <= n - 2: adj = 0 */
            for (j = 0; j < n; j++) coef[j] = 0.0;
            break;
        }
        s->mix_m = m;
    }
}

/* row i of the variant's result (calY_i; channel: Delta_i too), n^2 multiply-adds */
static void mix_result_row(ivc_controller *c, int i) {
    enum { n = IVC_NTHETA };
    ivc_state *s = &c->s;
    const double *U = s->mix_U, *V = s->mix_V, *coef = s->mix_coef, *Y = s->mix_in;
    double suv = s->mix_suv, sc = s->mix_s;
    if (c->mixing != IVC_MIXING_CHANNEL) {
        s->mix_calY[i] = adjugate_row_times(U, V, coef, suv, Y, sc, i);
    } else {
        double guard = c->par[IVC_P_GUARD], Ci[n], r2 = 0, acc = 0, cc;
        int j, k;
        for (j = 0; j < n; j++) {
            double cij = 0;
            for (k = 0; k < n; k++) cij += V[k * n + i] * coef[k] * U[k * n + j];
            Ci[j] = suv * cij;
        }
        for (j = 0; j < n; j++) { r2 += Ci[j] * Ci[j]; acc += Ci[j] * Y[j]; }
        cc = sqrt(Ci[i] * Ci[i] + guard * guard * r2);
        if (cc > 0.0) { s->mix_calY[i] = acc / cc; s->mix_D[i] = sc * suv * s->mix_sig[(int)s->mix_m] / cc; }
        else { s->mix_calY[i] = 0.0; s->mix_D[i] = 0.0; }
    }
}

/* Advance the job by about `budget` units of n multiply-adds (budget < 0: to the end);
 * returns the units spent. */
static double mix_work(ivc_controller *c, double budget) {
    enum { n = IVC_NTHETA };
    ivc_state *s = &c->s;
    double *U = s->mix_U, *V = s->mix_V, *sig = s->mix_sig, spent = 0;
    const double *P = s->mix_W;                 /* Psi / s until det U needs the room */
    double tol = c->mixing == IVC_MIXING_PAPER ? 1e-16 : sqrt((double)n) * 2.220446049250313e-16;
    int i, j, k, max_sweeps = c->mix_every > 1 ? c->mix_sweeps : 80;
    while (s->mix_phase != MIX_DONE && (budget < 0 || spent < budget)) {
        if (s->mix_phase == MIX_ROWS) {          /* column j of U = P V0 (warm) or of P */
            double *Uj = U + (int)s->mix_j * n;
            j = (int)s->mix_j;
            if (s->mix_warm) {
                const double *Vj = V + j * n;
                for (i = 0; i < n; i++) {
                    double acc = 0;
                    for (k = 0; k < n; k++) acc += P[i * n + k] * Vj[k];
                    Uj[i] = acc;
                }
                spent += n;
            } else {
                for (i = 0; i < n; i++) Uj[i] = P[i * n + j];
                spent += 1;
            }
            if (++s->mix_j == n) {
                s->mix_j = 0; s->mix_k = 1;
                s->mix_phase = n > 1 ? MIX_SWEEP : MIX_FINISH;
            }
        } else if (s->mix_phase == MIX_SWEEP) {   /* one pair (j, k) of the cyclic sweep */
            double a = 0, b = 0, g = 0, zeta, t, cs, sn, *Uj, *Uk, *Vj, *Vk;
            j = (int)s->mix_j;
            k = (int)s->mix_k;
            Uj = U + j * n; Uk = U + k * n; Vj = V + j * n; Vk = V + k * n;
            for (i = 0; i < n; i++) {
                a += Uj[i] * Uj[i];
                b += Uk[i] * Uk[i];
                g += Uj[i] * Uk[i];
            }
            spent += 3;
            if (!(g == 0.0 || fabs(g) <= tol * sqrt(a * b))) {
                s->mix_rotated = 1;
                zeta = (b - a) / (2.0 * g);
                t = (zeta >= 0 ? 1.0 : -1.0) / (fabs(zeta) + sqrt(1.0 + zeta * zeta));
                cs = 1.0 / sqrt(1.0 + t * t);
                sn = cs * t;
                for (i = 0; i < n; i++) {
                    double uj = Uj[i], uk = Uk[i];
                    Uj[i] = cs * uj - sn * uk;
                    Uk[i] = sn * uj + cs * uk;
                }
                for (i = 0; i < n; i++) {
                    double vj = Vj[i], vk = Vk[i];
                    Vj[i] = cs * vj - sn * vk;
                    Vk[i] = sn * vj + cs * vk;
                }
                spent += 8;
            }
            if (++s->mix_k == n) {                /* next pair; a sweep ends at (n-2, n-1) */
                if (++s->mix_j == n - 1) {
                    s->mix_sweep += 1;
                    if (!s->mix_rotated || s->mix_sweep == max_sweeps) {
                        s->mix_phase = MIX_FINISH;
                        if (c->mixing != IVC_MIXING_PAPER) s->has_warm = 1;  /* V: the next warm start */
                    }
                    s->mix_rotated = 0;
                    s->mix_j = 0;
                }
                s->mix_k = s->mix_j + 1;
            }
        } else if (s->mix_phase == MIX_FINISH) {  /* sig, U's columns normalised */
            for (j = 0; j < n; j++) {
                double sq = 0, *Uj = U + j * n;
                for (i = 0; i < n; i++) sq += Uj[i] * Uj[i];
                sig[j] = sqrt(sq);
                if (sig[j] > 0) for (i = 0; i < n; i++) Uj[i] /= sig[j];
            }
            spent += n;
            s->mix_j = 0;
            s->mix_phase = MIX_COMPLETE;
        } else if (s->mix_phase == MIX_COMPLETE) {
            /* column j of a zero singular value: completed to an orthonormal basis by
             * Gram-Schmidt from the unit vectors */
            double *Uj = U + (int)s->mix_j * n;
            j = (int)s->mix_j;
            if (!(sig[j] > 0)) {
                int e;
                for (e = 0; e < n; e++) {
                    double nrm = 0;
                    for (i = 0; i < n; i++) Uj[i] = (i == e);
                    for (k = 0; k < n; k++) {
                        double d = 0, *Uk = U + k * n;
                        if (k == j || (sig[k] == 0 && k > j)) continue;
                        for (i = 0; i < n; i++) d += Uk[i] * Uj[i];
                        for (i = 0; i < n; i++) Uj[i] -= d * Uk[i];
                        spent += 2;
                    }
                    for (i = 0; i < n; i++) nrm += Uj[i] * Uj[i];
                    nrm = sqrt(nrm);
                    if (nrm > 0.5) { for (i = 0; i < n; i++) Uj[i] /= nrm; break; }
                }
            }
            spent += 1;
            if (++s->mix_j == n) {                /* det U by LU, from U row by row */
                for (i = 0; i < n; i++) for (k = 0; k < n; k++) s->mix_W[i * n + k] = U[k * n + i];
                s->mix_det = 1.0;
                s->mix_j = 0;
                s->mix_phase = MIX_DET;
            }
        } else if (s->mix_phase == MIX_DET) {     /* step k of det_lu's elimination */
            double *A = s->mix_W;
            int p;
            k = (int)s->mix_j;
            p = k;
            for (i = k + 1; i < n; i++) if (fabs(A[i * n + k]) > fabs(A[p * n + k])) p = i;
            if (A[p * n + k] == 0.0) { s->mix_det = 0.0; k = n - 1; }
            else {
                if (p != k) {
                    for (j = 0; j < n; j++) { double t = A[k * n + j]; A[k * n + j] = A[p * n + j]; A[p * n + j] = t; }
                    s->mix_det = -s->mix_det;
                }
                s->mix_det *= A[k * n + k];
                for (i = k + 1; i < n; i++) {
                    double f = A[i * n + k] / A[k * n + k];
                    for (j = k + 1; j < n; j++) A[i * n + j] -= f * A[k * n + j];
                }
            }
            spent += (double)(n - k) * (n - k) / n;
            if (++s->mix_j >= n) {
                s->mix_suv = s->mix_det < 0 ? -1.0 : 1.0;    /* det V = +1 */
                mix_result_setup(c);
                s->mix_j = 0;
                s->mix_phase = MIX_RESULT;
            }
        } else {                                  /* MIX_RESULT: row i */
            mix_result_row(c, (int)s->mix_j);
            spent += n;
            if (++s->mix_j == n) s->mix_phase = MIX_DONE;
        }
    }
    return spent;
}


/* the finished mixing held from now on (Delta per channel for "channel", else one value) */
static void mix_apply(ivc_controller *c) {
    ivc_state *s = &c->s;
    int i;
    for (i = 0; i < IVC_NTHETA; i++) {
        s->D_held[i] = c->mixing == IVC_MIXING_CHANNEL ? s->mix_D[i] : s->mix_D[0];
        s->calY_held[i] = s->mix_calY[i];
    }
}

/* w(t) of ivdrem.blocks._kernels.start_weight: 0 before t_on, the C1 ramp 3x^2 - 2x^3 over
 * t_ramp, then 1 (the composite term of the scale-free mixings starts at t = T) */
static double start_weight(double t, double t_on, double t_ramp) {
    double x;
    if (t >= t_on + t_ramp) return 1.0;
    if (t <= t_on) return 0.0;
    x = (t - t_on) / t_ramp;
    return x * x * (3.0 - 2.0 * x);
}

/* the reference q_d, dq_d, ddq_d at t: the sinusoid A sin(w t + phi) + c, or the Fourier
 * series of ivdrem.blocks.sources.fourier_series:
 * q_d,i = c_i + sum_l (a_il sin(l w t) - b_il cos(l w t)) / (l w) */
static void reference(const ivc_controller *c, double t, double *qd, double *dqd, double *ddqd) {
    const double *par = c->par;
    int i, l;
    for (i = 0; i < IVC_NQ; i++) {
        if (c->ref_kind == 0) {
            double arg = par[IVC_P_TR_OMEGA + i] * t + par[IVC_P_TR_PHASE + i];
            double sn = sin(arg), cs = cos(arg), A0 = par[IVC_P_TR_AMPLITUDE + i], w = par[IVC_P_TR_OMEGA + i];
            qd[i] = A0 * sn + par[IVC_P_TR_OFFSET + i];
            dqd[i] = A0 * w * cs;
            ddqd[i] = -A0 * w * w * sn;
        } else {
            double q = 0, dq = 0, ddq = 0;
            for (l = 0; l < IVC_NH; l++) {
                double w = par[IVC_P_FR_OMEGA_F] * (l + 1), sn = sin(w * t), cs = cos(w * t);
                double a = par[IVC_P_FR_A + i * IVC_NH + l], b = par[IVC_P_FR_B + i * IVC_NH + l];
                q += (a * sn - b * cs) / w;
                dq += a * cs + b * sn;
                ddq += (b * cs - a * sn) * w;
            }
            qd[i] = par[IVC_P_TR_OFFSET + i] + q;
            dqd[i] = dq;
            ddqd[i] = ddq;
        }
    }
}

/* ------------------------------------------------------------------ the max-hold's lambda_min as a job
 * Composite learning's max-hold (35) holds (Y_b, Psi_b)(t_k) when lambda_min of the symmetric
 * part S of Psi_b beats the running maximum and epsilon.  lambda_min(S) by Householder
 * tridiagonalization T = Q^T S Q (Golub & Van Loan, Matrix Computations, Alg. 8.3.1; LAPACK
 * dsytd2) and Sturm-sequence bisection on T for its smallest eigenvalue (G&VL 8.4.1, LAPACK
 * dstebz/dlaebz): backward stable, lambda_min to about eps ||S||, the accuracy of LAPACK's
 * dsyevd that the Python reference calls (numpy.linalg.eigvalsh); 4/3 n^3 flops and no
 * iteration but the bisection's, where the cyclic Jacobi rotations it replaces took 6-10
 * sweeps of 3 n^3 (8.7 ms per sample on the Panda, ntheta = 43).  S is scaled by a power of two
 * (exact) so that max |S_ij| lies in [0.5, 1).
 *
 * A resumable job as the mixing's (lam_begin, then lam_work with a budget in units of n
 * multiply-adds): with mix_every = m > 1 the candidate of t_k (k a multiple of m) is decided
 * at t_k+m and the job's slices run on the m samples between; its work is fixed (n - 2
 * reflections, at most IVC_LAM_BISECT bisection steps), so the per-sample budget always
 * finishes it within the period. */

/* units of n multiply-adds of the reflection k (the trailing block is (n-k-1) x (n-k-1)) */
static double lam_house_units(int k) {
    double m = IVC_NTHETA - k - 1;
    return (3.0 * m * m + 5.0 * m) / IVC_NTHETA;
}

/* the whole job's units: symmetrize, n - 2 reflections, the bisection (a division a row) */
static double lam_job_units(void) {
    double u = IVC_NTHETA + 8.0 * IVC_LAM_BISECT;
    int k;
    for (k = 0; k + 2 < IVC_NTHETA; k++) u += lam_house_units(k);
    return u;
}

/* start the job on the window's output y = (Y_b, Psi_b) (copied: the candidate of this sample) */
static void lam_begin(ivc_controller *c, const double *y) {
    enum { n = IVC_NTHETA };
    ivc_state *s = &c->s;
    const double *Psi = y + n;
    double big = 0, *S = s->lam_S;
    int i, j, e;
    memcpy(s->lam_in, y, sizeof s->lam_in);
    for (i = 0; i < n * n; i++) if (fabs(Psi[i]) > big) big = fabs(Psi[i]);
    s->lam_scale = 1.0;
    if (big > 0 && isfinite(big)) { frexp(big, &e); s->lam_scale = ldexp(1.0, e); }
    for (i = 0; i < n; i++)
        for (j = 0; j < n; j++) S[i * n + j] = 0.5 * (Psi[i * n + j] + Psi[j * n + i]) / s->lam_scale;
    s->lam_k = 0;
    s->lam_iter = -1;                           /* the bisection's bounds not set yet */
    s->lam_phase = LAM_HOUSE;
}

/* the number of eigenvalues of T (d, e) <= x: the negative pivots of LDL^T of T - x I */
static int sturm_count(const double *d, const double *e, double x, double pivmin) {
    int i, cnt = 0;
    double q = d[0] - x;
    if (q <= pivmin) { cnt++; if (q > -pivmin) q = -pivmin; }
    for (i = 1; i < IVC_NTHETA; i++) {
        q = (d[i] - x) - e[i - 1] * e[i - 1] / q;
        if (q <= pivmin) { cnt++; if (q > -pivmin) q = -pivmin; }
    }
    return cnt;
}

/* Advance the job by about `budget` units (budget < 0: to the end); returns the units spent.
 * When it ends, lam_value holds lambda_min(sym Psi_b) of lam_in. */
static double lam_work(ivc_controller *c, double budget) {
    enum { n = IVC_NTHETA };
    ivc_state *s = &c->s;
    double *S = s->lam_S, *d = s->lam_d, *e = s->lam_e, spent = 0;
    int i, j;
    while (s->lam_phase != LAM_DONE && (budget < 0 || spent < budget)) {
        if (s->lam_phase == LAM_HOUSE) {         /* reflection k: column k below the diagonal */
            int k = (int)s->lam_k, m = n - k - 1;
            if (k + 2 >= n) {                    /* the last 2 x 2 (or 1 x 1) block */
                for (i = k; i < n; i++) d[i] = S[i * n + i];
                if (k + 1 < n) e[k] = S[(k + 1) * n + k];
                e[n - 1] = 0.0;
                s->lam_phase = LAM_BISECT;
                continue;
            }
            {
                double v[n], p[n], ss = 0, vv = 0, alpha, tau, vp = 0, K;
                const double *A0 = S + (k + 1) * n + (k + 1);        /* trailing block, stride n */
                for (i = 0; i < m; i++) { v[i] = S[(k + 1 + i) * n + k]; ss += v[i] * v[i]; }
                d[k] = S[k * n + k];
                if (ss == 0.0) e[k] = 0.0;       /* already tridiagonal in this column */
                else {
                    alpha = v[0] >= 0 ? -sqrt(ss) : sqrt(ss);
                    v[0] -= alpha;
                    for (i = 0; i < m; i++) vv += v[i] * v[i];
                    tau = 2.0 / vv;
                    for (i = 0; i < m; i++) {    /* p = tau A v */
                        double acc = 0;
                        for (j = 0; j < m; j++) acc += A0[i * n + j] * v[j];
                        p[i] = tau * acc;
                        vp += v[i] * p[i];
                    }
                    K = 0.5 * tau * vp;
                    for (i = 0; i < m; i++) p[i] -= K * v[i];      /* w = p - K v */
                    for (i = 0; i < m; i++) {    /* A <- A - v w^T - w v^T */
                        double *row = S + (k + 1 + i) * n + (k + 1), vi = v[i], wi = p[i];
                        for (j = 0; j < m; j++) row[j] -= vi * p[j] + wi * v[j];
                    }
                    e[k] = alpha;
                }
            }
            spent += lam_house_units(k);
            s->lam_k += 1;
        } else {                                  /* LAM_BISECT: one step on [lo, hi] */
            double eps = 2.220446049250313e-16, lo = s->lam_lo, hi = s->lam_hi, mid;
            if (s->lam_iter < 0) {               /* Gershgorin's interval holds every eigenvalue */
                double emax = 0;
                lo = INFINITY; hi = -INFINITY;
                for (i = 0; i < n; i++) {
                    double r = (i > 0 ? fabs(e[i - 1]) : 0.0) + (i + 1 < n ? fabs(e[i]) : 0.0);
                    if (d[i] - r < lo) lo = d[i] - r;
                    if (d[i] + r > hi) hi = d[i] + r;
                    if (i + 1 < n && e[i] * e[i] > emax) emax = e[i] * e[i];
                }
                s->lam_pivmin = 2.2250738585072014e-308 * (emax > 1.0 ? emax : 1.0);
                s->lam_tol = eps * (fabs(lo) > fabs(hi) ? fabs(lo) : fabs(hi));
                lo -= 2.0 * s->lam_tol + s->lam_pivmin;
                hi += 2.0 * s->lam_tol + s->lam_pivmin;
                s->lam_iter = 0;
            }
            if (!(hi - lo > 2.0 * eps * (fabs(lo) > fabs(hi) ? fabs(lo) : fabs(hi)) + s->lam_tol)
                || s->lam_iter >= IVC_LAM_BISECT) {
                s->lam_value = 0.5 * (lo + hi) * s->lam_scale;
                s->lam_phase = LAM_DONE;
            } else {
                mid = 0.5 * (lo + hi);
                if (sturm_count(d, e, mid, s->lam_pivmin) >= 1) hi = mid; else lo = mid;
                s->lam_iter += 1;
                spent += 8.0;
            }
            s->lam_lo = lo;
            s->lam_hi = hi;
        }
    }
    return spent;
}

/* the max-hold of (35): hold (Y_b, Psi_b) = y when lam beats the running maximum and epsilon */
static void max_hold(ivc_controller *c, double lam, const double *y) {
    ivc_state *s = &c->s;
    if (lam > s->lambda_min_held && lam > c->par[IVC_P_EPSILON]) {
        s->lambda_min_held = lam;
        memcpy(s->held, y, sizeof s->held);
    }
}

/* the window (15a): trapezoid on the samples in a ring of block sums, shadow-sum reset
 * (ivdrem.controller.window.BlockWindow, same operations in the same order) */
static void window_push(ivc_controller *c, const double *g, double *y) {
    ivc_state *s = &c->s;
    int j;
    double hh = 0.5 * c->h, *old;
    long pos;
    if (s->has_prev != 0) {
        for (j = 0; j < NM; j++) s->P[j] += hh * (s->g_prev[j] + g[j]);
        s->i += 1;
        if (s->i == c->block) {
            pos = (long)s->pos;
            old = c->ring + pos * NM;
            for (j = 0; j < NM; j++) {
                s->S[j] += s->P[j] - old[j];
                old[j] = s->P[j];
                s->shadow[j] += s->P[j];
            }
            s->pos = (double)((pos + 1) % c->nb);
            s->nshadow += 1;
            if (s->nshadow == (double)c->nb) {
                for (j = 0; j < NM; j++) { s->S[j] = s->shadow[j]; s->shadow[j] = 0.0; }
                s->nshadow = 0;
            }
            for (j = 0; j < NM; j++) s->P[j] = 0.0;
            s->i = 0;
        }
    }
    memcpy(s->g_prev, g, sizeof s->g_prev);
    s->has_prev = 1;
    old = c->ring + (long)s->pos * NM;
    {
        double f = s->i / c->block;
        for (j = 0; j < NM; j++) y[j] = (s->P[j] + s->S[j]) - f * old[j];
    }
}

/* ------------------------------------------------------------------ the step */
int ivc_step(ivc_controller *c, double t, const double *q, const double *dq, double *tau_out) {
    enum { n = IVC_NQ, nth = IVC_NTHETA };
    const double *par;
    ivc_state *s;
    double qd[n], dqd[n], ddqd[n], e[n], de[n], r[n], v[n], dv[n], tau[n], applied[n];
    double x[n], fb[n], g_hat[n], acting[n], tdh[n], chi[n];
    double A[NQT], B[NQT], C[NQT], PM[NQT], E[NQT], Pi[NQT], obs[NQT], phi[NQT];
    double F1[NQT], F2[NQT], F3[NQT], F4[NQT];
    double theta_c[nth], b[nth], g[NM], y[NM], a[nth];
    double h, tk, mu, alpha, l, I, d1, d2, dl;
    int i, j, k, nominal;
    if (!c) return IVC_ERR_STATE;
    par = c->par;
    nominal = par[IVC_P_INJECTION] != 0;
    s = &c->s;
    h = c->h;
    tk = s->k * h;
    if (!(fabs(t - tk) <= 1e-9 * (fabs(tk) > 1.0 ? fabs(tk) : 1.0))) {
        fail(c, "step at t = %.17g, expected t = %.17g (fixed step h)", t, tk);
        return IVC_ERR_ARG;
    }
    if (!q || !dq || !tau_out) { fail(c, "null pointer argument%.0s%.0s", 0, 0); return IVC_ERR_ARG; }
    for (i = 0; i < n; i++)
        if (!isfinite(q[i]) || !isfinite(dq[i])) {
            fail(c, "non-finite measurement at t = %g (joint %g); state unchanged", tk, (double)i);
            return IVC_ERR_NONFINITE;
        }
    alpha = par[IVC_P_ALPHA];
    l = par[IVC_P_L];
    reference(c, tk, qd, dqd, ddqd);
    for (i = 0; i < n; i++) {
        e[i] = qd[i] - q[i];
        de[i] = dqd[i] - dq[i];
        r[i] = de[i] + alpha * e[i];
        v[i] = dqd[i] + alpha * e[i];
        dv[i] = ddqd[i] + alpha * de[i];
    }
    mu = mu_sat(par, tk);
    ivc_Phi(q, dq, v, dv, A);
    ivc_Phi_C(q, dq, r, B);
    ivc_Phi_dM(q, dq, r, C);
    ivc_Phi_M(q, r, PM);
    if (!nominal) {
        for (k = 0; k < NQT; k++) {
            obs[k] = mu * (PM[k] - s->Phi_Mf[k]) - s->Phi_f[k];     /* Pi^T - Phi^T   (8) */
            Pi[k] = obs[k] + A[k];
        }
    } else {
        /* the injection at theta_nominal (a momentum observer on M(q, theta_nominal)):
         * chi = mu (Phi_M^T(q, r) - Phi_Mf^T) theta_nominal, obs = -Phi_f^T, and the
         * adaptation (11) reads Pi_X^T = Phi^T - Phi_f^T (docs/controller.md) */
        for (i = 0; i < n; i++) {
            double acc = 0;
            for (j = 0; j < nth; j++)
                acc += (mu * (PM[i * nth + j] - s->Phi_Mf[i * nth + j])) * par[IVC_P_THETA_NOMINAL + j];
            chi[i] = acc;
        }
        for (k = 0; k < NQT; k++) {
            obs[k] = -s->Phi_f[k];
            Pi[k] = A[k] - s->Phi_f[k];
        }
    }
    /* composite term vartheta_c(theta_hat) = b_c - a theta_hat */
    for (i = 0; i < nth; i++) a[i] = 0.0;
    if (c->law == IVC_LAW_COMPOSITE_LEARNING) {
        for (i = 0; i < nth; i++) {
            double acc = 0;
            for (j = 0; j < nth; j++) acc += s->held[nth + i * nth + j] * s->theta_hat[j];
            theta_c[i] = par[IVC_P_GAMMA] * (s->held[i] - acc);            /* (35) */
        }
    } else if (c->law == IVC_LAW_IV_DREM || c->law == IVC_LAW_DREM) {
        double gw, t_on = 0.0, t_ramp = 0.0, Dmin;
        if (c->mix_every == 1) {                                         /* (17), E4 */
            mix_begin(c, s->Yavg);
            mix_work(c, -1.0);
            mix_apply(c);
        } else if (fmod(s->k, (double)c->mix_every) == 0.0) {            /* multi-rate */
            mix_work(c, -1.0);        /* a job longer than its budget ends here (early on) */
            mix_apply(c);             /* the mixing of (Y, Psi)(t_k - m h) */
            mix_begin(c, s->Yavg);    /* ... and that of (Y, Psi)(t_k), applied at t_k + m h */
        }
        if (c->mixing != IVC_MIXING_PAPER) { t_on = c->T; t_ramp = IVC_START_RAMP_REL * c->T; }
        gw = par[IVC_P_GAMMA] * start_weight(tk, t_on, t_ramp);
        Dmin = s->D_held[0];
        for (i = 0; i < nth; i++) {
            double Dl = s->D_held[i];
            if (Dl < Dmin) Dmin = Dl;
            theta_c[i] = gw * Dl * (s->calY_held[i] - Dl * s->theta_hat[i]);   /* (21) */
            a[i] = gw * Dl * Dl;
        }
        s->Delta = Dmin;
    } else if (c->law == IVC_LAW_SIGMA_MODIFICATION) {
        for (i = 0; i < nth; i++) {
            theta_c[i] = par[IVC_P_SIGMA] * (par[IVC_P_THETA_STAR + i] - s->theta_hat[i]);  /* E5 */
            a[i] = par[IVC_P_SIGMA];
        }
    } else {
        for (i = 0; i < nth; i++) theta_c[i] = 0.0;
    }
    /* the feedback of (9): x = (K + delta_mu mu) r ("paper"), or M(q, theta_nominal) x
     * ("inertia-scaled"; M x = Phi_M^T(q, x) theta, Property 1) */
    for (i = 0; i < n; i++) {
        double kr = 0;
        for (j = 0; j < n; j++) kr += par[IVC_P_K + i * n + j] * r[j];
        x[i] = kr + par[IVC_P_DELTA_MU] * mu * r[i];
    }
    if (c->design == IVC_DESIGN_INERTIA_SCALED) {
        ivc_Phi_M(q, x, F1);
        for (i = 0; i < n; i++) {
            double acc = 0;
            for (j = 0; j < nth; j++) acc += F1[i * nth + j] * par[IVC_P_THETA_NOMINAL + j];
            fb[i] = acc;
        }
    } else {
        for (i = 0; i < n; i++) fb[i] = x[i];
    }
    /* gravity "robot": the robot adds g_hat(q) = G(q, theta_nominal) = Phi_G^T(q) theta */
    if (c->gravity == IVC_GRAVITY_ROBOT) {
        ivc_Phi_G(q, F4);
        for (i = 0; i < n; i++) {
            double acc = 0;
            for (j = 0; j < nth; j++) acc += F4[i * nth + j] * par[IVC_P_THETA_NOMINAL + j];
            g_hat[i] = acc;
        }
    } else {
        for (i = 0; i < n; i++) g_hat[i] = 0.0;
    }
    for (i = 0; i < n; i++) {                                            /* (9) */
        double pt = 0, ot = 0, tmax = par[IVC_P_TAU_MAX + i];
        for (j = 0; j < nth; j++) { pt += Pi[i * nth + j] * s->theta_hat[j]; ot += obs[i * nth + j] * s->theta_hat[j]; }
        if (nominal) { pt = pt + chi[i]; ot = chi[i] + ot; }
        tau[i] = (fb[i] + pt) - s->u_f[i];
        if (c->gravity == IVC_GRAVITY_ROBOT) tau[i] = tau[i] - g_hat[i];
        if (tau[i] > tmax) tau[i] = tmax;                                /* the command's limits */
        if (tau[i] < -tmax) tau[i] = -tmax;
        if (s->k == 0 && par[IVC_P_FIRST_ZERO] != 0) tau[i] = 0.0;
        else if (s->k > 0 && isfinite(par[IVC_P_TAU_RATE_MAX + i])) {
            double dmax = h * par[IVC_P_TAU_RATE_MAX + i];
            if (tau[i] > s->tau[i] + dmax) tau[i] = s->tau[i] + dmax;
            if (tau[i] < s->tau[i] - dmax) tau[i] = s->tau[i] - dmax;
        }
        if (!isfinite(tau[i])) {
            fail(c, "non-finite torque at t = %g (joint %g): the loop diverged", tk, (double)i);
            return IVC_ERR_DIVERGED;
        }
        tdh[i] = -ot + s->u_f[i];                                        /* Section 4 */
    }
    /* the torque acting on the arm (the robot adds g_hat), which the filters see */
    for (i = 0; i < n; i++) {
        acting[i] = c->gravity == IVC_GRAVITY_ROBOT ? tau[i] + g_hat[i] : tau[i];
        applied[i] = c->delay == 0 ? acting[i]
                   : (c->gravity == IVC_GRAVITY_ROBOT ? s->tau[i] + g_hat[i] : s->tau_prev[i]);
        s->tau_d_hat[i] = tdh[i];
    }
    /* regression (13) at t_k: xi, eta advanced from t_k-1 with their inputs linear
     * between the samples (first-order hold), then phi^T = l (Phi_M^T(q, dq) - xi) + eta */
    ivc_Phi_M(q, dq, E);
    ivc_Phi_C(q, dq, dq, F1);
    ivc_Phi_dM(q, dq, dq, F2);
    ivc_Phi_F(dq, F3);
    ivc_Phi_G(q, F4);
    dl = exp(-l * h);
    for (k = 0; k < NQT; k++) {
        double Xe = ((F1[k] - F2[k]) + F3[k]) + F4[k];
        if (s->k > 0) {
            double w = h * phi1(-l * h), sl;                       /* (1 - d)/l */
            sl = (E[k] - s->X_xi[k]) / h;
            s->xi[k] = (E[k] - sl * w) + dl * (s->xi[k] - s->X_xi[k]);
            sl = (Xe - s->X_eta[k]) / h;
            s->eta[k] = (Xe - sl * w) + dl * (s->eta[k] - s->X_eta[k]);
        }
        s->X_xi[k] = E[k];
        s->X_eta[k] = Xe;
        phi[k] = l * (E[k] - s->xi[k]) + s->eta[k];
    }
    if (c->nb) {
        const double *inst = c->law == IVC_LAW_IV_DREM ? s->zeta : phi;
        for (i = 0; i < nth; i++) {                                      /* (15a) */
            double acc = 0;
            for (k = 0; k < n; k++) acc += inst[k * nth + i] * s->zf[k];
            g[i] = acc;
            for (j = 0; j < nth; j++) {
                acc = 0;
                for (k = 0; k < n; k++) acc += inst[k * nth + i] * phi[k * nth + j];
                g[nth + i * nth + j] = acc;
            }
        }
        window_push(c, g, y);
        if (c->law == IVC_LAW_COMPOSITE_LEARNING) {                      /* max-hold */
            if (c->mix_every == 1) {             /* lambda_min of t_k decides at t_k */
                lam_begin(c, y);
                lam_work(c, -1.0);
                max_hold(c, s->lam_value, y);
            } else {
                /* multi-rate: the candidate (Y_b, Psi_b)(t_k), k a multiple of m, is decided
                 * at t_k+m; the job's slices run on the samples between */
                if (fmod(s->k, (double)c->mix_every) == 0.0) {
                    if (s->k > 0) {
                        lam_work(c, -1.0);       /* nothing left: the budget covers the job */
                        max_hold(c, s->lam_value, s->lam_in);
                    }
                    lam_begin(c, y);
                }
                lam_work(c, c->lam_units);
            }
        }
    }
    /* ---- advance every state over [t_k, t_k + h], inputs held */
    I = mu_integral(par, tk, h);
    d1 = exp(-I);
    d2 = c->corrected ? d1 * (mu / mu_sat(par, tk + h)) : d1;            /* E1 */
    for (k = 0; k < NQT; k++) {
        double X = A[k] - B[k] + C[k];
        s->Phi_f[k] = X + d1 * (s->Phi_f[k] - X);                         /* (7) */
        s->Phi_Mf[k] = PM[k] + d2 * (s->Phi_Mf[k] - PM[k]);
    }
    for (i = 0; i < n; i++) {
        s->u_f[i] = -applied[i] + d1 * (s->u_f[i] + applied[i]);
        s->zf[i] = applied[i] + dl * (s->zf[i] - applied[i]);
    }
    if (c->law == IVC_LAW_IV_DREM) {
        ivc_Phi(qd, dqd, dqd, ddqd, A);                                  /* (14) */
        for (k = 0; k < NQT; k++) s->zeta[k] = A[k] + dl * (s->zeta[k] - A[k]);
    }
    if (c->law == IVC_LAW_IV_DREM || c->law == IVC_LAW_DREM) {         /* (15b) */
        double p = par[IVC_P_P], F0 = par[IVC_P_F0];
        double f = (pow(tk, p) + F0) / (pow(tk + h, p) + F0);
        for (k = 0; k < NM; k++) s->Yavg[k] = y[k] + f * (s->Yavg[k] - y[k]);
    }
    for (j = 0; j < nth; j++) {                                          /* (11) */
        double acc = 0, G = par[IVC_P_GAMMA_DIAG + j];
        for (k = 0; k < n; k++) acc += Pi[k * nth + j] * r[k];
        b[j] = acc + theta_c[j];
        s->theta_hat[j] = s->theta_hat[j] + h * phi1(-G * a[j] * h) * G * b[j];
    }
    for (i = 0; i < n; i++) {
        s->tau_prev[i] = acting[i]; s->tau[i] = tau[i]; tau_out[i] = tau[i];
        s->qd[i] = qd[i]; s->dqd[i] = dqd[i];
    }
    /* the multi-rate mixing's slice of this sample (after the outputs: it serves t_k+m) */
    if (c->mix_every > 1 && (c->law == IVC_LAW_IV_DREM || c->law == IVC_LAW_DREM))
        mix_work(c, c->mix_units);
    s->k += 1;
    return IVC_OK;
}

int ivc_outputs(const ivc_controller *c, double *theta_hat, double *tau_d_hat, double *Delta,
                double *tau) {
    if (!c) return IVC_ERR_STATE;
    if (theta_hat) memcpy(theta_hat, c->s.theta_hat, sizeof c->s.theta_hat);
    if (tau_d_hat) memcpy(tau_d_hat, c->s.tau_d_hat, sizeof c->s.tau_d_hat);
    if (Delta) *Delta = c->s.Delta;
    if (tau) memcpy(tau, c->s.tau, sizeof c->s.tau);
    return IVC_OK;
}

double ivc_time(const ivc_controller *c) { return c ? c->s.k * c->h : NAN; }

int ivc_reference(const ivc_controller *c, double *q_d, double *dq_d) {
    if (!c) return IVC_ERR_STATE;
    if (q_d) memcpy(q_d, c->s.qd, sizeof c->s.qd);
    if (dq_d) memcpy(dq_d, c->s.dqd, sizeof c->s.dqd);
    return IVC_OK;
}
