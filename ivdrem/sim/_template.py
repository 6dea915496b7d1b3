"""Stepping code shared verbatim by both engines: the methods and the one loop that runs them.

Written in the numba-compatible subset of Python.  The functions call globals that each
engine supplies:

* ``diagram_eval(mode, t, x, P, W, out)``: mode RHS writes dx/dt into out; mode AFTER_STEP
  pushes the delay history and updates (or probes) the max-holds at an accepted point and
  returns a status; mode RECORD writes the diagram outputs into out.  (One function rather
  than three keeps numba from optimising the diagram code thrice.)
* ``diagram_jacobian(t, x, P, W, J)``, ``newton_factor(W, J, c, LU, piv)``,
  ``newton_solve(W, LU, piv, b)``: df/dx of mode RHS, and the factorisation / solve of
  c I - J used by the Rosenbrock method (W passed so that the compiled engine's stepper
  can reach the diagram's functions, see ivdrem.sim.stepper).  Generic versions an engine may use
  (``fd_jacobian``, ``dense_factor``, ``dense_solve``) are defined at the end.

The reference engine runs these functions in Python with python-control behind the
right-hand side; the compiled engine compiles this source once, for every diagram, into a
stepper module whose diagram functions call each diagram's compiled functions by address
(:mod:`ivdrem.sim.stepper`).  Same code, same semantics.

Structure (integrator apart from the loop): each method is a step function
``*_step(t, h, x, xn, K, J, LU, piv, P, W, rtol, atol, stats)`` that leaves the new state in
xn, returns its error estimate (weighted RMS norm, accept when <= 1; 0 for a fixed-step
method) and leaves in K / D what its dense output needs.  ``integrate`` (which allocates
the work arrays) and ``step_loop`` (the loop on them) own everything else: step-size
control and acceptance, landing on output times and max-hold updates, dense output, the
after-step work (delay history, holds), output rows, divergence and stiffness checks.
Bogacki-Shampine 3(2) (``bs23_step``) is no user method: it takes a Rodas5P run's steps
while max-hold updates pin them to the sampling grid.  The method table (name -> id, step
function, order, properties) is ``ivdrem.sim.methods``; ``method_step``
dispatches on the id, and an id it has no branch for stops the loop with UNKNOWN_METHOD.

Workspace ``W`` (a namedtuple ``ivdrem.sim.simulator.Workspace``; the compiled code indexes
it by position): 0 hist_t[cap], 1 hist_v[cap, nd], 2 hist_d[cap, nd], 3 hist_meta[int64:
start, count, cap, keep_from_time_index], 4 held[nh], 5 score[nmh], 6 ys (block outputs),
7 us (block inputs), 8 u_ext (diagram inputs at the current evaluation, see
``external_inputs``), 9 hold_dt[nmh] (sampling
period of each max-hold), 10 hold_mode[int64, nmh] (HOLD_SKIP / HOLD_COMMIT / HOLD_PROBE at
the next after-step evaluation), 11 hold_time[nmh] (time of the last update, t_e),
12 hold_vec[nmh + 1, nmat] (eigenvector of lambda_min of the held matrix; the last row
the candidate of the latest evaluation), 13 probing[int64, 1]
(1 while the loop probes a hold at an interpolated point: no history push), 14 clock[1]
(time of the current after-step evaluation), 15 u_times[nut] and 16 u_values[nut, nu_ext]
(the table of the diagram inputs over time; empty while they are held constant); then the
compiled engine's kernels, failure and the diagram's tables (``WORKSPACE_LAYOUT``).
"""
import numpy as np

# modes of diagram_eval
RHS = 0
AFTER_STEP = 1
RECORD = 2
AFTER_STEP_EVALUATED = 3   # after_step when the last RHS call was at this (t, x) already
HISTORY_POINT = 4          # after_step at a point inside a step: the delays' history only

# status codes returned by integrate (and by the engines' Jacobian / factorisation)
OK = 0
HOLD_UPDATED = 1
HISTORY_FULL = 2
DIVERGED = 3
STEP_TOO_SMALL = 4
MAX_STEPS = 5
SINGULAR = 6
DIVERGED_GROWTH = 7
BLOCK_RAISED = 8      # a block's compiled kernel raised (compiled engine, ivdrem.sim.stepper)

UNKNOWN_METHOD = 9    # a method id method_step has no branch for (never a fallback)

# method ids: the registry's (ivdrem.sim.methods), imported by absolute name (this source
# also runs as the generated numba stepper module); BS23 is no user method: the explicit
# steps of a Rodas5P run pinned by max-holds
from ivdrem.sim.methods import RK4, DP45, RODAS5P, BS23  # noqa: E402

# max-hold modes for the next after-step evaluation
HOLD_SKIP = 0
HOLD_COMMIT = 1
HOLD_PROBE = 2

# entries of the int64 stats vector
S_STEPS = 0
S_REJECTED = 1
S_RHS = 2
S_BAD = 3          # index of the offending state after DIVERGED / DIVERGED_GROWTH
S_JAC = 4
S_LU = 5
S_STIFF = 6        # 1 once an explicit method was found limited by stability
S_CUTS = 7         # steps cut to land on a max-hold update
S_PROBES = 8       # max-hold evaluations at interpolated grid times
S_STIFF_RUN = 9    # accepted steps with h*rho(J) beyond the stability bound (DOPRI5's IASTI)
S_NONSTIFF = 10    # consecutive accepted steps within it (NONSTI)
S_EXPLICIT = 11    # BS23 steps a Rodas5P run took while max-hold updates pinned its steps
S_FRESH = 12       # 1: K[0] = f(t, x) and the signals W[6], W[7] are still those of (t, x)
N_STATS = 13

# entries of the float tf vector
F_T = 0
F_H = 1
F_T0 = 2
F_T_STIFF = 3      # time at which S_STIFF was set
F_GROW_T = 4       # growth check: reference time and norm
F_GROW_N = 5
F_GROW_RATE = 6    # e-folding rate (1/s) at a DIVERGED_GROWTH stop
F_HRHO = 7         # last h*rho(J) estimate of DP45
F_HRHO_STIFF = 8   # the estimate when S_STIFF was set
F_ERR = 9          # error estimate (weighted RMS norm) of the last accepted step; 0: none
N_TF = 10

# growth-rate divergence: a state norm (>= 1) growing by GROWTH_FACTOR within GROWTH_WINDOW
GROWTH_FACTOR = 1e6
GROWTH_WINDOW = 1.0

# ---------------------------------------------------------------------------- Rodas5P
# Steinebach's Rodas5P (L-stable, stiffly accurate Rosenbrock 5(4), 8 stages, dense output
# of order 4), coefficients as in OrdinaryDiffEq.jl's Rodas5PTableau, in the transformed
# variables of Hairer & Wanner (Solving ODEs II, sec. IV.7): with A = 1/(gamma h) I - J,
#   A U_i = f(t + c_i h, x + sum_j a_ij U_j) + d_i h df/dt + sum_j (C_ij / h) U_j,
#   x_new = x + sum_j b_j U_j  (b = last row of a, plus U_8), error estimate U_8,
#   x(t + s h) = (1-s) x + s (x_new + (1-s) (H_0 U + s (H_1 U + s H_2 U))).
RODAS5P_GAMMA = 0.21193756319429014
RODAS5P_A = np.array([
    [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    [3.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    [2.849394379747939, 0.45842242204463923, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    [-6.954028509809101, 2.489845061869568, -10.358996098473584, 0.0, 0.0, 0.0, 0.0, 0.0],
    [2.8029986275628964, 0.5072464736228206, -0.3988312541770524, -0.04721187230404641,
     0.0, 0.0, 0.0, 0.0],
    [-7.502846399306121, 2.561846144803919, -11.627539656261098, -0.18268767659942256,
     0.030198172008377946, 0.0, 0.0, 0.0],
    [-7.502846399306121, 2.561846144803919, -11.627539656261098, -0.18268767659942256,
     0.030198172008377946, 1.0, 0.0, 0.0],
    [-7.502846399306121, 2.561846144803919, -11.627539656261098, -0.18268767659942256,
     0.030198172008377946, 1.0, 1.0, 0.0]])
RODAS5P_B = np.array([-7.502846399306121, 2.561846144803919, -11.627539656261098,
                      -0.18268767659942256, 0.030198172008377946, 1.0, 1.0, 1.0])
RODAS5P_C = np.array([
    [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    [-14.155112264123755, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    [-17.97296035885952, -2.859693295451294, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    [147.12150275711716, -1.41221402718213, 71.68940251302358, 0.0, 0.0, 0.0, 0.0, 0.0],
    [165.43517024871676, -0.4592823456491126, 42.90938336958603, -5.961986721573306,
     0.0, 0.0, 0.0, 0.0],
    [24.854864614690072, -3.0009227002832186, 47.4931110020768, 5.5814197821558125,
     -0.6610691825249471, 0.0, 0.0, 0.0],
    [30.91273214028599, -3.1208243349937974, 77.79954646070892, 34.28646028294783,
     -19.097331116725623, -28.087943162872662, 0.0, 0.0],
    [37.80277123390563, -3.2571969029072276, 112.26918849496327, 66.9347231244047,
     -40.06618937091002, -54.66780262877968, -9.48861652309627, 0.0]])
RODAS5P_CT = np.array([0.0, 0.6358126895828704, 0.4095798393397535, 0.9769306725060716,
                       0.4288403609558664, 1.0, 1.0, 1.0])
RODAS5P_D = np.array([0.21193756319429014, -0.42387512638858027, -0.3384627126235924,
                      1.8046452872882734, 2.325825639765069, 0.0, 0.0, 0.0])
RODAS5P_H = np.array([
    [25.948786856663858, -2.5579724845846235, 10.433815404888879, -2.3679251022685204,
     0.524948541321073, 1.1241088310450404, 0.4272876194431874, -0.17202221070155493],
    [-9.91568850695171, -0.9689944594115154, 3.0438037242978453, -24.495224566215796,
     20.176138334709044, 15.98066361424651, -6.789040303419874, -6.710236069923372],
    [11.419903575922262, 2.8879645146136994, 72.92137995996029, 80.12511834622643,
     -52.072871366152654, -59.78993625266729, -0.15582684282751913, 4.883087185713722]])

# rows of the stage array K each method uses (K has K_ROWS rows of n)
K_ROWS = 11

# How the compiled engine's stepper compiles these (ivdrem.sim.stepper): everything that
# allocates nothing and returns no array without reference counting (numba's atomic counts
# on the stage views K[i] and on array arguments cost more than the stage arithmetic);
# external_inputs, which returns a workspace array, inlined into its callers.
NO_REFCOUNT = ("copy_into", "hist_index", "quad_slope", "hist_push", "hist_trim",
               "hist_lookup", "emit", "check_state", "err_norm", "rk4_step", "dp45_step",
               "bs23_step", "rodas5p_step", "method_step", "dense_eval", "on_grid", "next_grid",
               "probe_holds", "set_hold_modes", "step_loop", "dense_factor", "dense_solve",
               "hold_update")
#
# numba gives every compiled function its own machine code, holding a copy of all its callees:
# a chain of wrappers compiles the stepper once per link.  So the steps and the max-hold
# helpers, each called from one place, are inlined into the loop, and integrate and
# work_arrays (they only allocate the loop's work arrays) stay Python in both engines.
INLINE = ("external_inputs", "method_step", "rodas5p_step", "dp45_step", "bs23_step",
          "rk4_step", "probe_holds", "set_hold_modes")
PYTHON_LEVEL = ("integrate", "work_arrays")


def copy_into(dst, d0, src, s0, n):
    """dst[d0:d0+n] = src[s0:s0+n] (through views indexed from 0: dst[d0 + i] would
    make numba allow negative indices, and LLVM use gathers and scatters)."""
    d = dst[d0:d0 + n]
    s = src[s0:s0 + n]
    for i in range(n):
        d[i] = s[i]


def hist_index(meta, i):
    return (meta[0] + i) % meta[2]


def quad_slope(ta, va, tb, vb, tc, vc):
    """Slope at ta of the quadratic through (ta, va), (tb, vb), (tc, vc)."""
    return (va * (2.0 * ta - tb - tc) / ((ta - tb) * (ta - tc))
            + vb * (ta - tc) / ((tb - ta) * (tb - tc))
            + vc * (ta - tb) / ((tc - ta) * (tc - tb)))


def hist_push(W, t, v, d, estimate_slope):
    """Append an accepted point (t, v, dv/dt).  Where no derivative is wired
    (estimate_slope[j] = 1) the slope comes from a quadratic through the last 3 points."""
    if W[13][0] != 0:
        return OK                  # probing a max-hold at an interpolated point: no history
    ht = W[0]
    hv = W[1]
    hd = W[2]
    meta = W[3]
    nd = v.shape[0]
    if meta[1] > 0 and t <= ht[hist_index(meta, meta[1] - 1)]:
        # the same accepted point again (e.g. re-pushed after the buffer grew): replace it
        k = hist_index(meta, meta[1] - 1)
        for j in range(nd):
            hv[k, j] = v[j]
            if estimate_slope[j] == 0:
                hd[k, j] = d[j]
        return OK
    if meta[1] >= meta[2]:
        return HISTORY_FULL
    k = hist_index(meta, meta[1])
    ht[k] = t
    for j in range(nd):
        hv[k, j] = v[j]
        hd[k, j] = d[j]
    cnt = meta[1] + 1
    any_est = False
    for j in range(nd):
        if estimate_slope[j] == 1:
            any_est = True
    if not any_est:
        meta[1] = cnt
        return OK
    if cnt >= 3:
        k1 = hist_index(meta, cnt - 2)
        k2 = hist_index(meta, cnt - 3)
        for j in range(nd):
            if estimate_slope[j] == 1:
                hd[k, j] = quad_slope(t, v[j], ht[k1], hv[k1, j], ht[k2], hv[k2, j])
                if cnt == 3:
                    # the first two points got provisional slopes: now that three points
                    # exist, give them the quadratic's slopes too (third order from t0 on)
                    hd[k1, j] = quad_slope(ht[k1], hv[k1, j], t, v[j], ht[k2], hv[k2, j])
                    hd[k2, j] = quad_slope(ht[k2], hv[k2, j], t, v[j], ht[k1], hv[k1, j])
    elif cnt == 2:
        k1 = hist_index(meta, 0)
        for j in range(nd):
            if estimate_slope[j] == 1:
                hd[k, j] = (v[j] - hv[k1, j]) / (t - ht[k1])
    else:
        for j in range(nd):
            if estimate_slope[j] == 1:
                hd[k, j] = 0.0
    meta[1] = cnt
    return OK


def hist_trim(W, t_keep):
    """Forget points no lookup can need any more (all but one before t_keep)."""
    if W[13][0] != 0:
        return
    ht = W[0]
    meta = W[3]
    while meta[1] > 2 and ht[hist_index(meta, 1)] <= t_keep:
        meta[0] = (meta[0] + 1) % meta[2]
        meta[1] -= 1


def hist_lookup(W, tq, off, size, out):
    """Cubic Hermite value of the delayed signal at time tq; before the first point the
    signal holds its initial value."""
    ht = W[0]
    hv = W[1]
    hd = W[2]
    meta = W[3]
    cnt = meta[1]
    if cnt == 0:
        for j in range(size):
            out[j] = 0.0
        return
    kf = hist_index(meta, 0)
    if tq <= ht[kf] or cnt == 1:
        copy_into(out, 0, hv[kf], off, size)
        return
    kl = hist_index(meta, cnt - 1)
    if tq >= ht[kl]:
        copy_into(out, 0, hv[kl], off, size)
        return
    lo = 0
    hi = cnt - 1
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if ht[hist_index(meta, mid)] <= tq:
            lo = mid
        else:
            hi = mid
    a = hist_index(meta, lo)
    b = hist_index(meta, hi)
    h = ht[b] - ht[a]
    s = (tq - ht[a]) / h
    s2 = s * s
    s3 = s2 * s
    h00 = 2.0 * s3 - 3.0 * s2 + 1.0
    h10 = s3 - 2.0 * s2 + s
    h01 = -2.0 * s3 + 3.0 * s2
    h11 = s3 - s2
    va = hv[a, off:off + size]      # (views: see copy_into)
    da = hd[a, off:off + size]
    vb = hv[b, off:off + size]
    db = hd[b, off:off + size]
    for j in range(size):
        out[j] = h00 * va[j] + h10 * h * da[j] + h01 * vb[j] + h11 * h * db[j]


def external_inputs(W, t):
    """The diagram's external inputs at time t, in W[8] (returned).  Without a table
    (W[15] empty) they are held at W[8]; otherwise W[8] becomes the linear interpolant of
    the table at t, extrapolated linearly beyond its ends: python-control's
    input_output_response convention (its ``ufun``), so both see the same u(t)."""
    ue = W[8]
    tt = W[15]
    nt = tt.shape[0]
    if nt < 2:
        return ue
    # i = searchsorted(tt, t, side="left") clipped to [1, nt - 1]: t in [tt[i-1], tt[i]]
    lo = 0
    hi = nt
    while lo < hi:
        mid = (lo + hi) // 2
        if tt[mid] < t:
            lo = mid + 1
        else:
            hi = mid
    i = min(max(lo, 1), nt - 1)
    s = (t - tt[i - 1]) / (tt[i] - tt[i - 1])
    uu = W[16]
    for j in range(ue.shape[0]):
        ue[j] = uu[i - 1, j] * (1.0 - s) + uu[i, j] * s
    return ue


def hold_update(W, k, off, size, nvec, nmat, u, epsilon):
    """Max-hold k (composite learning, eq. 35): keep u when lambda_min of its matrix part beats
    the record and epsilon.  W[10][k] says what to do at this evaluation: HOLD_SKIP (not a
    sampling time of this hold), HOLD_PROBE (report whether it would update, change nothing)
    or HOLD_COMMIT."""
    mode = W[10][k]
    if mode == HOLD_SKIP:
        return 0
    score = W[5]
    # cheap exact rejection: lambda_min(A) <= A_ii and <= v'Av for the unit eigenvector v of
    # the held record (Rayleigh quotients; A's symmetric part has the same ones, so they are
    # read from u directly), so no eigensolver and no allocation while the record stands
    bound = u[nvec]
    for i in range(nmat):
        if u[nvec + i * nmat + i] < bound:
            bound = u[nvec + i * nmat + i]
    vec = W[12]
    if score[k] > 0.0 and bound > score[k]:
        r = 0.0
        for i in range(nmat):
            ri = 0.0
            for j in range(nmat):
                ri += u[nvec + i * nmat + j] * vec[k, j]
            r += vec[k, i] * ri
        if r < bound:
            bound = r
    if not (bound > epsilon and bound > score[k]):
        return 0
    lam = lowest_eigenpair(W, u, nvec, nmat)
    if lam > epsilon and lam > score[k]:
        if mode == HOLD_PROBE:
            return 1
        score[k] = lam
        held = W[4]
        for j in range(size):
            held[off + j] = u[j]
        cand = vec[vec.shape[0] - 1]
        for i in range(nmat):
            vec[k, i] = cand[i]
        W[11][k] = W[14][0]
        return 1
    return 0


def lowest_eigenpair(W, u, nvec, nmat):
    """lambda_min of the symmetric part of the nmat x nmat matrix in u[nvec:], its unit
    eigenvector left in the last row of W[12] (a candidate until the hold commits).  The
    compiled engine replaces this with a LAPACK call on preallocated work arrays
    (ivdrem.sim._diagram); both run LAPACK's dsyevd, as np.linalg.eigh does."""
    A = np.empty((nmat, nmat))
    for i in range(nmat):
        for j in range(nmat):
            A[i, j] = 0.5 * (u[nvec + i * nmat + j] + u[nvec + j * nmat + i])
    w, V = np.linalg.eigh(A)
    cand = W[12][W[12].shape[0] - 1]
    for i in range(nmat):
        cand[i] = V[i, 0]
    return w[0]


def emit(t, x, P, W, out_y, out_x, io):
    """Record the diagram outputs (and, if out_x has columns, the state) as row io[0]."""
    k = io[0]
    diagram_eval(RECORD, t, x, P, W, out_y[k])
    if out_x.shape[1] == x.shape[0]:
        for i in range(x.shape[0]):
            out_x[k, i] = x[i]
    io[0] = k + 1


def check_state(x, x_limit):
    """Index of the first non-finite or exploding state, or -1."""
    for i in range(x.shape[0]):
        v = x[i]
        if not (abs(v) <= x_limit):
            return i
    return -1


def err_norm(x, xn, e, rtol, atol):
    """Weighted RMS norm of the error estimate e (accept the step when <= 1)."""
    n = x.shape[0]
    s = 0.0
    for i in range(n):
        sc = atol + rtol * max(abs(x[i]), abs(xn[i]))
        s += (e[i] / sc) ** 2
    return np.sqrt(s / n)


# ---------------------------------------------------------------------------- methods
def rk4_step(t, h, x, xn, K, J, LU, piv, P, W, rtol, atol, stats):
    """Classical RK4 (fixed step, no error estimate).  K[0] = f(t, x) on entry."""
    n = x.shape[0]
    k1 = K[0]
    k2 = K[1]
    k3 = K[2]
    k4 = K[3]
    xt = K[4]
    for i in range(n):
        xt[i] = x[i] + 0.5 * h * k1[i]
    diagram_eval(RHS, t + 0.5 * h, xt, P, W, k2)
    for i in range(n):
        xt[i] = x[i] + 0.5 * h * k2[i]
    diagram_eval(RHS, t + 0.5 * h, xt, P, W, k3)
    for i in range(n):
        xt[i] = x[i] + h * k3[i]
    diagram_eval(RHS, t + h, xt, P, W, k4)
    for i in range(n):
        xn[i] = x[i] + h / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])
    stats[S_RHS] += 3
    return 0.0


def dp45_step(t, h, x, xn, K, J, LU, piv, P, W, rtol, atol, stats):
    """Dormand-Prince 5(4).  K[0] = f(t, x) on entry; on return K[6] = f(t + h, xn) (FSAL)
    and K[7] the stage-6 state (for the stiffness estimate of the loop)."""
    n = x.shape[0]
    k1 = K[0]
    k2 = K[1]
    k3 = K[2]
    k4 = K[3]
    k5 = K[4]
    k6 = K[5]
    k7 = K[6]
    xt = K[7]
    for i in range(n):
        xt[i] = x[i] + h * (0.2 * k1[i])
    diagram_eval(RHS, t + 0.2 * h, xt, P, W, k2)
    for i in range(n):
        xt[i] = x[i] + h * (3.0 / 40.0 * k1[i] + 9.0 / 40.0 * k2[i])
    diagram_eval(RHS, t + 0.3 * h, xt, P, W, k3)
    for i in range(n):
        xt[i] = x[i] + h * (44.0 / 45.0 * k1[i] - 56.0 / 15.0 * k2[i] + 32.0 / 9.0 * k3[i])
    diagram_eval(RHS, t + 0.8 * h, xt, P, W, k4)
    for i in range(n):
        xt[i] = x[i] + h * (19372.0 / 6561.0 * k1[i] - 25360.0 / 2187.0 * k2[i]
                            + 64448.0 / 6561.0 * k3[i] - 212.0 / 729.0 * k4[i])
    diagram_eval(RHS, t + 8.0 / 9.0 * h, xt, P, W, k5)
    for i in range(n):
        xt[i] = x[i] + h * (9017.0 / 3168.0 * k1[i] - 355.0 / 33.0 * k2[i]
                            + 46732.0 / 5247.0 * k3[i] + 49.0 / 176.0 * k4[i]
                            - 5103.0 / 18656.0 * k5[i])
    diagram_eval(RHS, t + h, xt, P, W, k6)
    for i in range(n):
        xn[i] = x[i] + h * (35.0 / 384.0 * k1[i] + 500.0 / 1113.0 * k3[i]
                            + 125.0 / 192.0 * k4[i] - 2187.0 / 6784.0 * k5[i]
                            + 11.0 / 84.0 * k6[i])
    diagram_eval(RHS, t + h, xn, P, W, k7)
    stats[S_RHS] += 6
    s = 0.0
    for i in range(n):
        e = h * (71.0 / 57600.0 * k1[i] - 71.0 / 16695.0 * k3[i] + 71.0 / 1920.0 * k4[i]
                 - 17253.0 / 339200.0 * k5[i] + 22.0 / 525.0 * k6[i] - 1.0 / 40.0 * k7[i])
        sc = atol + rtol * max(abs(x[i]), abs(xn[i]))
        s += (e / sc) ** 2
    return np.sqrt(s / n)


def bs23_step(t, h, x, xn, K, J, LU, piv, P, W, rtol, atol, stats):
    """Bogacki-Shampine 3(2) (FSAL; Bogacki & Shampine 1989, as in MATLAB's ode23), the
    explicit method of a Rodas5P run's pinned steps.  K[0] = f(t, x) on entry; on return
    K[6] = f(t + h, xn); K[1], K[5] the stages at c = 1/2, 3/4; K[2] the error estimate."""
    n = x.shape[0]
    k1 = K[0]
    k2 = K[1]
    k3 = K[5]
    k4 = K[6]
    xt = K[7]
    for i in range(n):
        xt[i] = x[i] + h * (0.5 * k1[i])
    diagram_eval(RHS, t + 0.5 * h, xt, P, W, k2)
    for i in range(n):
        xt[i] = x[i] + h * (0.75 * k2[i])
    diagram_eval(RHS, t + 0.75 * h, xt, P, W, k3)
    for i in range(n):
        xn[i] = x[i] + h * (2.0 / 9.0 * k1[i] + 1.0 / 3.0 * k2[i] + 4.0 / 9.0 * k3[i])
    diagram_eval(RHS, t + h, xn, P, W, k4)
    stats[S_RHS] += 3
    e = K[2]
    for i in range(n):
        # x_new minus the order-2 solution x + h (7/24 k1 + 1/4 k2 + 1/3 k3 + 1/8 k4)
        e[i] = h * (-5.0 / 72.0 * k1[i] + 1.0 / 12.0 * k2[i] + 1.0 / 9.0 * k3[i]
                    - 1.0 / 8.0 * k4[i])
    return err_norm(x, xn, e, rtol, atol)


def rodas5p_step(t, h, x, xn, K, J, LU, piv, P, W, rtol, atol, stats):
    """Rodas5P (coefficients above), a fresh Jacobian every step (it is not a W-method).

    K[0] = f(t, x) on entry; K[1..8] get the stages U_1..U_8, K[9] df/dt, K[10] scratch.
    Returns the error norm of U_8 (the stiffly accurate embedded solution x_new - U_8), or
    inf when c I - J cannot be factored (the loop shrinks the step)."""
    n = x.shape[0]
    f0 = K[0]
    ft = K[9]
    fs = K[10]
    if stats[S_FRESH] == 1:    # the signals at (t, x) are at hand: no evaluation for them
        diagram_jacobian_at(t, x, P, W, J, f0)
    else:
        diagram_jacobian(t, x, P, W, J)
    stats[S_FRESH] = 0
    stats[S_JAC] += 1
    # df/dt: the diagram is time dependent (mu(t), trajectories); forward difference in t
    dt = 1.4901161193847656e-08 * max(1.0, abs(t))
    diagram_eval(RHS, t + dt, x, P, W, ft)
    for i in range(n):
        ft[i] = (ft[i] - f0[i]) / dt
    st = newton_factor(W, J, 1.0 / (RODAS5P_GAMMA * h), LU, piv)
    stats[S_LU] += 1
    stats[S_RHS] += 1
    if st != OK:
        return np.inf
    for s in range(8):
        U = K[1 + s]
        if s == 0:
            for i in range(n):
                U[i] = f0[i] + RODAS5P_D[0] * h * ft[i]
        else:
            for i in range(n):
                xn[i] = x[i]
            for j in range(s):
                a = RODAS5P_A[s, j]
                Uj = K[1 + j]
                if a != 0.0:
                    for i in range(n):
                        xn[i] += a * Uj[i]
            diagram_eval(RHS, t + RODAS5P_CT[s] * h, xn, P, W, fs)
            stats[S_RHS] += 1
            dh = RODAS5P_D[s] * h
            for i in range(n):
                U[i] = fs[i] + dh * ft[i]
            for j in range(s):
                c = RODAS5P_C[s, j] / h
                Uj = K[1 + j]
                for i in range(n):
                    U[i] += c * Uj[i]
        newton_solve(W, LU, piv, U)
    for i in range(n):
        v = x[i]
        for j in range(8):
            v += RODAS5P_B[j] * K[1 + j][i]
        xn[i] = v
    return err_norm(x, xn, K[8], rtol, atol)


def method_step(mid, t, h, x, xn, K, J, LU, piv, P, W, rtol, atol, stats):
    """One step of method mid (the table's dispatch)."""
    if mid == RODAS5P:
        return rodas5p_step(t, h, x, xn, K, J, LU, piv, P, W, rtol, atol, stats)
    if mid == DP45:
        return dp45_step(t, h, x, xn, K, J, LU, piv, P, W, rtol, atol, stats)
    if mid == BS23:
        return bs23_step(t, h, x, xn, K, J, LU, piv, P, W, rtol, atol, stats)
    if mid == RK4:
        return rk4_step(t, h, x, xn, K, J, LU, piv, P, W, rtol, atol, stats)
    return -1.0        # no step function for this id: step_loop returns UNKNOWN_METHOD


def dense_eval(mid, h, s, x, xn, f0, f1, K, out):
    """State at t + s h (0 <= s <= 1) inside the accepted step x -> xn: Rodas5P's own dense
    output (order 4), otherwise the cubic Hermite interpolant of the end values and slopes
    f0 = f(t, x), f1 = f(t + h, xn) (order 3)."""
    n = x.shape[0]
    s1 = 1.0 - s
    if mid == RODAS5P:
        for i in range(n):
            d0 = 0.0
            d1 = 0.0
            d2 = 0.0
            for j in range(8):
                u = K[1 + j][i]
                d0 += RODAS5P_H[0, j] * u
                d1 += RODAS5P_H[1, j] * u
                d2 += RODAS5P_H[2, j] * u
            out[i] = s1 * x[i] + s * (xn[i] + s1 * (d0 + s * (d1 + s * d2)))
        return
    h00 = (1.0 + 2.0 * s) * s1 * s1
    h10 = s * s1 * s1
    h01 = s * s * (3.0 - 2.0 * s)
    h11 = -s * s * s1
    for i in range(n):
        out[i] = h00 * x[i] + h10 * h * f0[i] + h01 * xn[i] + h11 * h * f1[i]


def on_grid(t, t0, dt):
    """Whether t is a sampling time t0 + m dt (to rounding)."""
    m = np.floor((t - t0) / dt + 0.5)
    return abs(t - (t0 + m * dt)) <= 1e-9 * max(1.0, abs(t))


def next_grid(t, t0, dt):
    """The first sampling time t0 + m dt strictly after t (beyond rounding)."""
    m = np.floor((t - t0) / dt + 0.5)
    tg = t0 + m * dt
    if tg <= t + 1e-9 * max(1.0, abs(t)):
        tg = t0 + (m + 1.0) * dt
    return tg


def probe_holds(mid, t, t1, x, xn, f0, f1, K, xg, P, W, stats, t0):
    """Earliest sampling time in (t, t1) at which some max-hold would update, read from the
    dense output of the step t -> t1; -1 if none.  Nothing is changed."""
    nmh = W[5].shape[0]
    h = t1 - t
    first = -1.0
    W[13][0] = 1
    for k in range(nmh):
        W[10][k] = HOLD_SKIP
    for k in range(nmh):
        dt = W[9][k]
        tg = next_grid(t, t0, dt)
        W[10][k] = HOLD_PROBE
        while tg < t1 - 1e-9 * max(1.0, abs(t1)):
            if first >= 0.0 and tg >= first:
                break
            dense_eval(mid, h, (tg - t) / h, x, xn, f0, f1, K, xg)
            W[14][0] = tg
            stats[S_PROBES] += 1
            if diagram_eval(AFTER_STEP, tg, xg, P, W, xg) == HOLD_UPDATED:
                first = tg
                break
            tg = next_grid(tg, t0, dt)
        W[10][k] = HOLD_SKIP
    W[13][0] = 0
    return first


def set_hold_modes(W, t_prev, t, t0, fixed):
    """Hold modes for the after-step evaluation at t: commit the holds sampled at t (for a
    fixed-step method: sampled in (t_prev, t], the step cannot land on them)."""
    for k in range(W[5].shape[0]):
        dt = W[9][k]
        if on_grid(t, t0, dt) or (fixed and next_grid(t_prev, t0, dt) <= t):
            W[10][k] = HOLD_COMMIT
        else:
            W[10][k] = HOLD_SKIP
    W[14][0] = t


def integrate(mid, tf, t_stop, x, P, W, out_t, out_y, out_x, io, stats, ctl):
    """Advance from tf[F_T] to t_stop with method mid; tf[F_H] is the (initial) step.

    ctl = [rtol, atol, h_max, max_steps, x_limit, adaptive (1/0), dense outputs (1/0),
    stiffness check (1/0)].  io = [next output index, number of outputs].  Adaptive methods
    either land on the requested output times or (dense outputs) record them from the dense
    output; a fixed-step method steps at t0 + k h and records each output at the first step
    at or after it.  Max-holds are sampled on their own grids from the dense output; a step
    in which one would update is cut to end at that sampling time (the update is a
    discontinuity of the right-hand side) and the method restarts there.
    """
    K, J, LU, piv, xn, f1, xg = work_arrays(x.shape[0])
    return step_loop(mid, tf, t_stop, x, P, W, out_t, out_y, out_x, io, stats, ctl,
                     K, J, LU, piv, xn, f1, xg)


def work_arrays(n):
    """The loop's work arrays for n states: stages K, Jacobian J, factor LU, pivots, the
    new state, the end slope and an interpolated state (C stepper's integrate too)."""
    K = np.empty((K_ROWS, n))
    J = np.zeros((n, n))          # a structured Jacobian writes only its pattern
    LU = np.empty((n + 2, n))     # the factor in rows < n; the sparse LU uses the other two
    piv = np.zeros(n, dtype=np.int64)
    return K, J, LU, piv, np.empty(n), np.empty(n), np.empty(n)


def step_loop(mid, tf, t_stop, x, P, W, out_t, out_y, out_x, io, stats, ctl,
              K, J, LU, piv, xn, f1, xg):
    """integrate's loop on the work arrays it allocated (apart, so that the loop is
    compiled without reference counts)."""
    n = x.shape[0]
    rtol = ctl[0]
    atol = ctl[1]
    h_max = ctl[2]
    max_steps = ctl[3]
    x_limit = ctl[4]
    adaptive = ctl[5] != 0.0
    dense_out = ctl[6] != 0.0
    check_stiff = ctl[7] != 0.0
    nmh = W[5].shape[0]
    t = tf[F_T]
    h = tf[F_H]
    t0 = tf[F_T0]
    diagram_eval(RHS, t, x, P, W, K[0])
    stats[S_RHS] += 1
    stats[S_FRESH] = 1
    fac_max = 5.0
    # predictive (Gustafsson) control of the stiff method: the last regular accepted step and
    # its error (floored as in RADAU5), so a growing error shrinks the step before it fails
    h_acc = -1.0
    err_acc = 1.0
    t_cut = -1.0
    pinned = False         # the last step ended on a max-hold update: the next ends on the grid
    explicit_ok = True     # ... and may be an explicit BS23 step while that stays stable
    while True:
        landing = False
        if adaptive:
            if t >= t_stop - 1e-12 * max(1.0, abs(t)):
                break
            if stats[S_STEPS] + stats[S_REJECTED] >= max_steps:
                tf[F_T] = t
                return MAX_STEPS
            h = min(h, h_max)
            t_target = t_stop
            if not dense_out and io[0] < io[1] and out_t[io[0]] < t_target:
                t_target = out_t[io[0]]
            if t_cut > t and t_cut < t_target:
                t_target = t_cut
            if t + h >= t_target - 1e-12 * max(1.0, abs(t)):
                h_use = t_target - t
                landing = True
            else:
                h_use = h
            if h_use < 1e-13 * max(1.0, abs(t)):
                # an output time that coincides with t (within rounding): record it
                if landing and io[0] < io[1] and t_target == out_t[io[0]]:
                    emit(t, x, P, W, out_y, out_x, io)
                    continue
                stats[S_BAD] = -1
                tf[F_T] = t
                return STEP_TOO_SMALL
        else:
            kstep = stats[S_STEPS]
            t = t0 + kstep * h
            if t >= t_stop - 1e-9 * h:
                break
            h_use = h
        if dense_out and W[1].shape[1] > 0 and W[3][1] + 2 > W[3][2]:
            # no room for the midpoint and the end point of the next step in the history
            tf[F_T] = t
            tf[F_H] = h
            return HISTORY_FULL
        # while max-hold updates pin a Rodas5P run's steps to the 1-sample grid, a fresh
        # Jacobian per sample costs as much as ~8 explicit stages: take Bogacki-Shampine
        # steps (3 stages) while they pass the same error control (back to Rodas5P at a
        # rejection, until the next pinned stretch)
        m = mid
        if mid == RODAS5P and pinned and explicit_ok:
            m = BS23
        err = method_step(m, t, h_use, x, xn, K, J, LU, piv, P, W, rtol, atol, stats)
        if err < 0.0:
            tf[F_T] = t
            return UNKNOWN_METHOD
        stats[S_FRESH] = 0       # the stages moved the signals
        if m != mid and not (err <= 1.0):
            explicit_ok = False
            stats[S_REJECTED] += 1
            continue
        if adaptive and not (err <= 1.0):
            if not (err == err):           # NaN: the trial state is not finite
                bad = check_state(xn, x_limit)
                if bad >= 0 and h_use < 1e-10 * max(1.0, abs(t)):
                    stats[S_BAD] = bad
                    tf[F_T] = t
                    return DIVERGED
                fac = 0.1
            else:
                fac = max(0.1, 0.9 * err ** -0.2)
            h = h_use * fac
            fac_max = 1.0
            stats[S_REJECTED] += 1
            continue
        if adaptive:
            t1 = t_target if landing else t + h_use
        else:
            t1 = t0 + (stats[S_STEPS] + 1) * h
        # slope at the new point: the FSAL stage of DP45 / BS23, else one evaluation (it is
        # the first stage of the next step).  Rodas5P's dense output does not read it, so it
        # is evaluated last, after the outputs and the history point inside the step: the
        # signals are then those of the step's end and the after-step sweep is not needed
        swept = False
        late_slope = m == RODAS5P
        if m == DP45 or m == BS23:
            for i in range(n):
                f1[i] = K[6][i]
        elif not late_slope:
            diagram_eval(RHS, t1, xn, P, W, f1)
            stats[S_RHS] += 1
        if nmh > 0 and adaptive:
            probes = stats[S_PROBES]
            tg = probe_holds(m, t, t1, x, xn, K[0], f1, K, xg, P, W, stats, t0)
            # a probe moved the signals; a step that ends on the grid (a pinned step) has
            # none inside it, and its signals are still those of the FSAL stage at t1
            swept = stats[S_PROBES] != probes
            if tg > 0.0:
                t_cut = tg
                h = tg - t
                stats[S_CUTS] += 1
                continue
        cut_landed = t_cut >= 0.0 and t1 >= t_cut - 1e-12 * max(1.0, abs(t1))
        if m != mid:
            # no h*rho(J) estimate for BS23 (no two of its stages share a time, so the
            # drift of a time-dependent loop swamps DOPRI5's estimate): an unstable mode
            # grows into the error estimate, and a rejection returns the run to Rodas5P
            stats[S_EXPLICIT] += 1
        if check_stiff and mid == DP45 and not (landing and h_use < h):
            # Hairer's DOPRI5 test: h*rho(J) ~ h |f(xn) - f(x6)| / |xn - x6| with x6 the
            # stage at c = 1; beyond 3.25 (the stability boundary) 15 times before 6 in a
            # row within it = stiff.  Short steps that land on an output are not counted.
            num = 0.0
            den = 0.0
            for i in range(n):
                num += (K[6][i] - K[5][i]) ** 2
                den += (xn[i] - K[7][i]) ** 2
            if den > 0.0:
                hrho = h_use * np.sqrt(num / den)
                tf[F_HRHO] = hrho
                if hrho > 3.25:
                    stats[S_NONSTIFF] = 0
                    stats[S_STIFF_RUN] += 1
                    if stats[S_STIFF_RUN] >= 15 and stats[S_STIFF] == 0:
                        stats[S_STIFF] = 1
                        tf[F_T_STIFF] = t1
                        tf[F_HRHO_STIFF] = hrho
                else:
                    stats[S_NONSTIFF] += 1
                    if stats[S_NONSTIFF] >= 6:
                        stats[S_STIFF_RUN] = 0
        if dense_out:
            # outputs inside the step from the dense output, before the holds move
            while io[0] < io[1] and out_t[io[0]] < t1 - 1e-12 * max(1.0, abs(t1)):
                to = out_t[io[0]]
                dense_eval(m, h_use, (to - t) / (t1 - t), x, xn, K[0], f1, K, xg)
                emit(to, xg, P, W, out_y, out_x, io)
                swept = True
        if dense_out and W[1].shape[1] > 0 and m == mid:
            # the delay history gets the step's midpoint from the dense output too, so that
            # its cubic Hermite pieces stay short when the steps are long (not for the
            # explicit steps of a pinned run: they end on the 1-sample grid)
            for k in range(nmh):
                W[10][k] = HOLD_SKIP
            tm = t + 0.5 * (t1 - t)
            dense_eval(m, h_use, 0.5, x, xn, K[0], f1, K, xg)
            W[14][0] = tm
            diagram_eval(HISTORY_POINT, tm, xg, P, W, xg)
            swept = True
        if late_slope:
            diagram_eval(RHS, t1, xn, P, W, f1)
            stats[S_RHS] += 1
            swept = False
        # accepted
        t_prev = t
        t = t1
        for i in range(n):
            x[i] = xn[i]
            K[0][i] = f1[i]
        stats[S_STEPS] += 1
        tf[F_T] = t
        tf[F_ERR] = err
        bad = check_state(x, x_limit)
        if bad >= 0:
            stats[S_BAD] = bad
            return DIVERGED
        # growth-rate divergence: far faster than any physical transient of the loop
        nrm = 0.0
        for i in range(n):
            if abs(x[i]) > nrm:
                nrm = abs(x[i])
                bad = i
        ref = max(tf[F_GROW_N], 1.0)
        if nrm > GROWTH_FACTOR * ref and t - tf[F_GROW_T] <= GROWTH_WINDOW:
            stats[S_BAD] = bad
            tf[F_GROW_RATE] = np.log(nrm / ref) / max(t - tf[F_GROW_T], 1e-300)
            return DIVERGED_GROWTH
        if t - tf[F_GROW_T] >= GROWTH_WINDOW:
            tf[F_GROW_T] = t
            tf[F_GROW_N] = nrm
        if nmh > 0:
            set_hold_modes(W, t_prev, t, t0, not adaptive)
        if swept:
            st = diagram_eval(AFTER_STEP, t, x, P, W, x)
        else:
            st = diagram_eval(AFTER_STEP_EVALUATED, t, x, P, W, x)
        if st == HISTORY_FULL:
            tf[F_H] = h
            return HISTORY_FULL
        if st == HOLD_UPDATED:
            diagram_eval(RHS, t, x, P, W, K[0])   # the held values changed: f(t, x) is stale
            stats[S_RHS] += 1
        # every path above ends with the signals of (t, x): the after-step sweep, the FSAL
        # evaluation (AFTER_STEP_EVALUATED) or the re-evaluation after a hold update
        stats[S_FRESH] = 1
        if adaptive:
            while io[0] < io[1] and out_t[io[0]] <= t + 1e-12 * max(1.0, abs(t)):
                emit(t, x, P, W, out_y, out_x, io)
            if not landing or h_use >= h:
                fac = 5.0 if err == 0.0 else min(fac_max, max(0.2, 0.9 * err ** -0.2))
                if m == RODAS5P:
                    # Gustafsson's predictive controller (Hairer & Wanner II, IV.8, (8.21)),
                    # as RADAU5 combines it: the smaller of the standard and predicted steps
                    if h_acc > 0.0 and err > 0.0:
                        fac_p = 0.9 * (h_use / h_acc) * (err_acc / (err * err)) ** 0.2
                        fac = min(fac, max(0.2, fac_p))
                    h_acc = h_use
                    err_acc = max(1e-2, err)
                h = h_use * fac
            fac_max = 5.0
            if cut_landed or st == HOLD_UPDATED:
                # holds that update at one sampling time often update at the next: try
                # to end the next step there rather than cut another step short
                t_cut = -1.0
                if not pinned:
                    explicit_ok = True
                pinned = True
                for k in range(nmh):
                    hg = next_grid(t, t0, W[9][k]) - t
                    if hg < h:
                        h = hg
            else:
                pinned = False
        else:
            while io[0] < io[1] and out_t[io[0]] <= t + 1e-9 * h:
                out_t[io[0]] = t
                emit(t, x, P, W, out_y, out_x, io)
    tf[F_T] = t
    tf[F_H] = h
    return OK


# ------------------------------------------------- generic Jacobian and linear algebra
def diagram_jacobian_at(t, x, P, W, J, f0):
    """df/dx at (t, x) given f0 = f(t, x) with the signals of that evaluation in W; an
    engine with a structured Jacobian replaces this fallback, which ignores them."""
    return diagram_jacobian(t, x, P, W, J)


def fd_jacobian(t, x, P, W, J):
    """J = df/dx of mode RHS by forward differences of the whole right-hand side (n + 1
    evaluations): the fallback when an engine has nothing better."""
    n = x.shape[0]
    f0 = np.empty(n)
    fp = np.empty(n)
    xp = x.copy()
    diagram_eval(RHS, t, x, P, W, f0)
    for j in range(n):
        d = 1.4901161193847656e-08 * max(1.0, abs(x[j]))
        xp[j] = x[j] + d
        d = xp[j] - x[j]
        diagram_eval(RHS, t, xp, P, W, fp)
        for i in range(n):
            J[i, j] = (fp[i] - f0[i]) / d
        xp[j] = x[j]
    return OK


def dense_factor(J, c, LU, piv):
    """LU with partial pivoting of c I - J, in LU (unit lower part below the diagonal) and
    piv (row swapped with row k at step k)."""
    n = J.shape[0]
    for i in range(n):
        for j in range(n):
            LU[i, j] = -J[i, j]
        LU[i, i] += c
    for k in range(n):
        p = k
        m = abs(LU[k, k])
        for i in range(k + 1, n):
            if abs(LU[i, k]) > m:
                m = abs(LU[i, k])
                p = i
        piv[k] = p
        if not (m > 0.0) or not np.isfinite(m):
            return SINGULAR
        if p != k:
            for j in range(n):
                tmp = LU[k, j]
                LU[k, j] = LU[p, j]
                LU[p, j] = tmp
        inv = 1.0 / LU[k, k]
        for i in range(k + 1, n):
            l = LU[i, k] * inv
            LU[i, k] = l
            if l != 0.0:
                for j in range(k + 1, n):
                    LU[i, j] -= l * LU[k, j]
    return OK


def dense_solve(LU, piv, b):
    """b <- (c I - J)^{-1} b for the factorisation of dense_factor."""
    n = b.shape[0]
    for k in range(n):
        p = piv[k]
        if p != k:
            tmp = b[k]
            b[k] = b[p]
            b[p] = tmp
    for i in range(n):
        s = b[i]
        for j in range(i):
            s -= LU[i, j] * b[j]
        b[i] = s
    for i in range(n - 1, -1, -1):
        s = b[i]
        for j in range(i + 1, n):
            s -= LU[i, j] * b[j]
        b[i] = s / LU[i, i]
