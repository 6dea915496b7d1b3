"""Stepping code shared verbatim by both engines.

Written in the numba-compatible subset of Python.  The functions call one global that
each engine supplies, ``diagram_eval(mode, t, x, P, W, out)``: mode RHS writes dx/dt
into out; mode AFTER_STEP pushes the delay history and updates max-holds after an
accepted step and returns a status; mode RECORD writes the diagram outputs into out.
(One function rather than three keeps numba from optimising the diagram code thrice.)  The reference engine
runs these functions in Python with python-control behind ``rhs``; the compiled engine
pastes this source into the generated module and numba compiles it with the generated
``rhs``.  Same code, same semantics.

Workspace ``W`` (a tuple): 0 hist_t[cap], 1 hist_v[cap, nd], 2 hist_d[cap, nd],
3 hist_meta[int64: start, count, cap, keep_from_time_index], 4 held[nh], 5 score[nmh],
6 ys (block outputs), 7 us (block inputs), 8 u_ext (diagram inputs, held constant).
"""
import numpy as np

# modes of diagram_eval
RHS = 0
AFTER_STEP = 1
RECORD = 2
AFTER_STEP_EVALUATED = 3   # after_step when the last RHS call was at this (t, x) already

# status codes returned by the chunk functions
OK = 0
HOLD_UPDATED = 1
HISTORY_FULL = 2
DIVERGED = 3
STEP_TOO_SMALL = 4
MAX_STEPS = 5


def copy_into(dst, d0, src, s0, n):
    """dst[d0:d0+n] = src[s0:s0+n] without slice objects (smaller code for numba)."""
    for i in range(n):
        dst[d0 + i] = src[s0 + i]


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
        for j in range(size):
            out[j] = hv[kf, off + j]
        return
    kl = hist_index(meta, cnt - 1)
    if tq >= ht[kl]:
        for j in range(size):
            out[j] = hv[kl, off + j]
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
    for j in range(size):
        out[j] = (h00 * hv[a, off + j] + h10 * h * hd[a, off + j]
                  + h01 * hv[b, off + j] + h11 * h * hd[b, off + j])


def hold_update(W, k, off, size, nvec, nmat, u, epsilon):
    """Max-hold: keep u if lambda_min of its matrix part beats the record and epsilon."""
    A = np.empty((nmat, nmat))
    for i in range(nmat):
        for j in range(nmat):
            A[i, j] = 0.5 * (u[nvec + i * nmat + j] + u[nvec + j * nmat + i])
    lam = np.linalg.eigvalsh(A)[0]
    score = W[5]
    if lam > epsilon and lam > score[k]:
        score[k] = lam
        held = W[4]
        for j in range(size):
            held[off + j] = u[j]
        return 1
    return 0


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


def rk4_chunk(tf, t_stop, x, P, W, out_t, out_y, out_x, io, stats, x_limit):
    """Fixed-step classical RK4 from tf[0] to t_stop with step tf[1].

    Time is t0 + k h (no accumulated rounding); outputs are recorded at the first step at
    or after each requested time.  io = [next output index, number of outputs].
    """
    n = x.shape[0]
    k1 = np.empty(n)
    k2 = np.empty(n)
    k3 = np.empty(n)
    k4 = np.empty(n)
    xt = np.empty(n)
    h = tf[1]
    t0 = tf[2]
    while True:
        kstep = stats[0]
        t = t0 + kstep * h
        if t >= t_stop - 1e-9 * h:
            break
        diagram_eval(RHS, t, x, P, W, k1)
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
            x[i] += h / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])
        stats[0] = kstep + 1
        stats[2] += 4
        t = t0 + (kstep + 1) * h
        tf[0] = t
        bad = check_state(x, x_limit)
        if bad >= 0:
            stats[3] = bad
            return DIVERGED
        st = diagram_eval(AFTER_STEP, t, x, P, W, x)
        if st == HISTORY_FULL:
            return HISTORY_FULL
        while io[0] < io[1] and out_t[io[0]] <= t + 1e-9 * h:
            out_t[io[0]] = t
            emit(t, x, P, W, out_y, out_x, io)
    return OK


def dp45_chunk(tf, t_stop, x, P, W, out_t, out_y, out_x, io, stats, x_limit, rtol, atol,
               h_max, max_steps):
    """Dormand-Prince 5(4) with error control, from tf[0] to t_stop; tf[1] is the step.

    Steps are clipped to land exactly on requested output times.  The error estimate keeps
    the step inside the stability region as mu(t) makes the loop stiffer (SPEC section 9).
    """
    n = x.shape[0]
    k1 = np.empty(n)
    k2 = np.empty(n)
    k3 = np.empty(n)
    k4 = np.empty(n)
    k5 = np.empty(n)
    k6 = np.empty(n)
    k7 = np.empty(n)
    xt = np.empty(n)
    xn = np.empty(n)
    t = tf[0]
    h = tf[1]
    diagram_eval(RHS, t, x, P, W, k1)
    stats[2] += 1
    fac_max = 5.0
    while t < t_stop - 1e-12 * max(1.0, abs(t)):
        if stats[0] + stats[1] >= max_steps:
            return MAX_STEPS
        h = min(h, h_max)
        t_target = t_stop
        if io[0] < io[1] and out_t[io[0]] < t_target:
            t_target = out_t[io[0]]
        landing = False
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
            stats[3] = -1
            tf[0] = t
            return STEP_TOO_SMALL
        for i in range(n):
            xt[i] = x[i] + h_use * (0.2 * k1[i])
        diagram_eval(RHS, t + 0.2 * h_use, xt, P, W, k2)
        for i in range(n):
            xt[i] = x[i] + h_use * (3.0 / 40.0 * k1[i] + 9.0 / 40.0 * k2[i])
        diagram_eval(RHS, t + 0.3 * h_use, xt, P, W, k3)
        for i in range(n):
            xt[i] = x[i] + h_use * (44.0 / 45.0 * k1[i] - 56.0 / 15.0 * k2[i]
                                    + 32.0 / 9.0 * k3[i])
        diagram_eval(RHS, t + 0.8 * h_use, xt, P, W, k4)
        for i in range(n):
            xt[i] = x[i] + h_use * (19372.0 / 6561.0 * k1[i] - 25360.0 / 2187.0 * k2[i]
                                    + 64448.0 / 6561.0 * k3[i] - 212.0 / 729.0 * k4[i])
        diagram_eval(RHS, t + 8.0 / 9.0 * h_use, xt, P, W, k5)
        for i in range(n):
            xt[i] = x[i] + h_use * (9017.0 / 3168.0 * k1[i] - 355.0 / 33.0 * k2[i]
                                    + 46732.0 / 5247.0 * k3[i] + 49.0 / 176.0 * k4[i]
                                    - 5103.0 / 18656.0 * k5[i])
        diagram_eval(RHS, t + h_use, xt, P, W, k6)
        for i in range(n):
            xn[i] = x[i] + h_use * (35.0 / 384.0 * k1[i] + 500.0 / 1113.0 * k3[i]
                                    + 125.0 / 192.0 * k4[i] - 2187.0 / 6784.0 * k5[i]
                                    + 11.0 / 84.0 * k6[i])
        diagram_eval(RHS, t + h_use, xn, P, W, k7)
        stats[2] += 6
        err = 0.0
        for i in range(n):
            e = h_use * (71.0 / 57600.0 * k1[i] - 71.0 / 16695.0 * k3[i]
                         + 71.0 / 1920.0 * k4[i] - 17253.0 / 339200.0 * k5[i]
                         + 22.0 / 525.0 * k6[i] - 1.0 / 40.0 * k7[i])
            sc = atol + rtol * max(abs(x[i]), abs(xn[i]))
            err += (e / sc) ** 2
        err = np.sqrt(err / n)
        if not (err <= 1.0):
            if not (err == err):           # NaN: the trial state is not finite
                bad = check_state(xn, x_limit)
                if bad >= 0 and h_use < 1e-10 * max(1.0, abs(t)):
                    stats[3] = bad
                    tf[0] = t
                    return DIVERGED
                fac = 0.1
            else:
                fac = max(0.1, 0.9 * err ** -0.2)
            h = h_use * fac
            fac_max = 1.0
            stats[1] += 1
            continue
        # accepted
        t = t_target if landing else t + h_use
        for i in range(n):
            x[i] = xn[i]
            k1[i] = k7[i]
        stats[0] += 1
        tf[0] = t
        bad = check_state(x, x_limit)
        if bad >= 0:
            stats[3] = bad
            return DIVERGED
        # the FSAL stage k7 evaluated the diagram at exactly this (t, x): reuse its signals
        st = diagram_eval(AFTER_STEP_EVALUATED, t, x, P, W, x)
        if st == HISTORY_FULL:
            tf[1] = h
            return HISTORY_FULL
        if st == HOLD_UPDATED:
            diagram_eval(RHS, t, x, P, W, k1)        # the held values changed: k1 (FSAL) is stale
            stats[2] += 1
        while io[0] < io[1] and out_t[io[0]] <= t + 1e-12 * max(1.0, abs(t)):
            emit(t, x, P, W, out_y, out_x, io)
        if not landing or h_use >= h:
            fac = 5.0 if err == 0.0 else min(fac_max, max(0.2, 0.9 * err ** -0.2))
            h = h_use * fac
        fac_max = 5.0
    tf[0] = t
    tf[1] = h
    return OK
