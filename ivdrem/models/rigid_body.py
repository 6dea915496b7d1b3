"""Rigid-body kernels of a serial (or tree) arm: a recursive Newton-Euler formulation that is
linear in the link parameters, written once as numba-compilable Python.

Conventions (the same as Pinocchio's, so that its functions check these):

* body ``j`` has the frame of joint ``j`` (after the joint's motion); its pose in the frame
  of its parent body ``parent[j]`` is ``(Rp[j] E_j(q_j), pp[j])`` for a revolute joint of
  unit axis ``axis[j]`` (``E_j = exp([axis] q_j)``), ``(Rp[j], pp[j] + Rp[j] axis q_j)`` for
  a prismatic one; ``parent[j] < j`` and ``-1`` is the fixed base;
* spatial vectors are 6-vectors, linear part first: a motion ``(v, w)``, a force ``(f, n)``;
* the 10 standard parameters of a link, about the origin of its joint frame (Pinocchio's
  ``Inertia.toDynamicParameters``):
  ``(m, m c_x, m c_y, m c_z, I_xx, I_xy, I_yy, I_xz, I_yz, I_zz)``.

With ``V_j``, ``A_j`` the spatial velocity and acceleration of body ``j`` (the base
accelerates at ``-g``: gravity enters as a base acceleration), the body force is linear in
the link's parameters ``pi_j`` (docs/models.md):

    f_j = I_j A_j + V_j x* (I_j V_j) = Phi_b(V_j, A_j) pi_j          (6 x 10)

and the joint torque is ``tau_i = S_i^T sum_{j in subtree(i)} X*_{i<-j} f_j``, so the joint
torque regressor ``Y(q, w, a)`` (rnea = ``Y pi``) has blocks
``Y[i, 10 j : 10 j + 10] = S_i^T X*_{i<-j} Phi_b(V_j, A_j)``.  The regressors of the paper
(Property 1) follow from it: with the velocity terms ``c(w) = C(q, w) w`` a quadratic form
and ``C`` Christoffel-consistent (``C(q, x) y = C(q, y) x``), ``C(q, x) y`` is its polar form

    C(q, x) y = (s_x s_y / 4) [c(x/s_x + y/s_y) - c(x/s_x - y/s_y)]    (any s_x, s_y != 0)

(scaled by the largest entries, so that neither difference cancels).  Derivatives with
respect to ``q`` are exact forward-mode derivatives of the recursion (``_rb_forward`` and
``_rb_project`` with ``tangent=True``): along a direction ``d``, ``dX_j = -d_j (S_j x) X_j``
for the motion transform of every joint type, so that

    dV_j = X_j dV_p - d_j S_j x (X_j V_p)
    dA_j = X_j dA_p - d_j S_j x (X_j A_p) + dV_j x (S_j w_j)
    d(X_j^T F) = X_j^T dF + d_j X_j^T (S_j x* F).

The regressors' derivatives (``*_jac``, many columns at one q) project a body force onto a
joint by the joint's axis in the body's frame instead, ``Y[k, 10 j + c] = (X_{j<-k} S_k) .
Phi_b[j][:, c]`` (``_rb_axes``, computed once per q), with the axes' tangent
``d(X_{j<-k} S_k) = X_j d(X_{p<-k} S_k) - d_j S_j x (X_{j<-k} S_k)``; the one second
derivative, of ``Phi_dM`` with respect to ``q``, is the tangent of that tangent
(``_rb_mass_tangent2``).  Every function computes in the dtype of ``q`` (float64).
"""
from __future__ import annotations

import numpy as np

__all__ = ["KERNELS", "C_KERNELS", "C_CHOLESKY", "C_JAC_KERNELS", "SINGULAR_INERTIA_MESSAGE",
           "PIVOT_RTOL"]

#: The message of the error raised where M(q) is not positive definite.
SINGULAR_INERTIA_MESSAGE = "inertia matrix M(q) is not positive definite (singular inertia)"

#: The rule for "M(q) is positive definite", the same in every language (docs/models.md):
#: every pivot d_j of its Cholesky factorisation is finite and d_j > PIVOT_RTOL * max_i M_ii.
PIVOT_RTOL = 1e-13


def _rb_kinematics(q: "const real[N]", jtype: "const int[N]", axis: "const float[N,3]",
                   Rp: "const float[N,3,3]", pp: "const float[N,3]", R: "real[N,3,3]",
                   p: "real[N,3]"):
    # pose (R[j], p[j]) of body j in its parent's frame
    n = q.shape[0]
    for j in range(n):
        ux = axis[j, 0]
        uy = axis[j, 1]
        uz = axis[j, 2]
        if jtype[j] == 0:
            c = np.cos(q[j])
            s = np.sin(q[j])
            t = 1.0 - c
            # Rodrigues: E = c I + s [u]x + t u u^T
            e00 = c + t * ux * ux
            e01 = t * ux * uy - s * uz
            e02 = t * ux * uz + s * uy
            e10 = t * ux * uy + s * uz
            e11 = c + t * uy * uy
            e12 = t * uy * uz - s * ux
            e20 = t * ux * uz - s * uy
            e21 = t * uy * uz + s * ux
            e22 = c + t * uz * uz
            for r in range(3):
                a0 = Rp[j, r, 0]
                a1 = Rp[j, r, 1]
                a2 = Rp[j, r, 2]
                R[j, r, 0] = a0 * e00 + a1 * e10 + a2 * e20
                R[j, r, 1] = a0 * e01 + a1 * e11 + a2 * e21
                R[j, r, 2] = a0 * e02 + a1 * e12 + a2 * e22
                p[j, r] = pp[j, r]
        else:
            for r in range(3):
                for c2 in range(3):
                    R[j, r, c2] = Rp[j, r, c2]
                p[j, r] = pp[j, r] + (Rp[j, r, 0] * ux + Rp[j, r, 1] * uy
                                      + Rp[j, r, 2] * uz) * q[j]


def _rb_xmotion(R: "const real[N,3,3]", p: "const real[N,3]", j: "int", m: "const real[6]",
                out: "real[6]"):
    # motion m (parent frame) in the frame of body j: (R^T (m_l - p x m_a), R^T m_a)
    tl0 = m[0] - (p[j, 1] * m[5] - p[j, 2] * m[4])
    tl1 = m[1] - (p[j, 2] * m[3] - p[j, 0] * m[5])
    tl2 = m[2] - (p[j, 0] * m[4] - p[j, 1] * m[3])
    for r in range(3):
        out[r] = R[j, 0, r] * tl0 + R[j, 1, r] * tl1 + R[j, 2, r] * tl2
        out[3 + r] = R[j, 0, r] * m[3] + R[j, 1, r] * m[4] + R[j, 2, r] * m[5]


def _rb_cross_motion(a: "const real[6]", b: "const real[6]", out: "real[6]", scale: "real"):
    # out += scale * (a x b) for motions: (a_w x b_l + a_v x b_w, a_w x b_w)
    out[0] += scale * (a[4] * b[2] - a[5] * b[1] + a[1] * b[5] - a[2] * b[4])
    out[1] += scale * (a[5] * b[0] - a[3] * b[2] + a[2] * b[3] - a[0] * b[5])
    out[2] += scale * (a[3] * b[1] - a[4] * b[0] + a[0] * b[4] - a[1] * b[3])
    out[3] += scale * (a[4] * b[5] - a[5] * b[4])
    out[4] += scale * (a[5] * b[3] - a[3] * b[5])
    out[5] += scale * (a[3] * b[4] - a[4] * b[3])


def _rb_subspace(jtype: "const int[N]", axis: "const float[N,3]", j: "int", s: "real",
                 out: "real[6]"):
    # out = S_j s (the joint's motion for joint velocity s)
    for r in range(6):
        out[r] = 0.0
    off = 3 if jtype[j] == 0 else 0
    for r in range(3):
        out[off + r] = axis[j, r] * s


def _rb_forward(R: "const real[N,3,3]", p: "const real[N,3]", parent: "const int[N]",
                jtype: "const int[N]", axis: "const float[N,3]", w: "const real[N]",
                acc: "const real[N]", a0: "const real[6]", tangent: "bool",
                d: "const real[N]", V: "real[N,6]", A: "real[N,6]", dV: "real[N,6]",
                dA: "real[N,6]"):
    # V_j = X_j V_p + S_j w_j;  A_j = X_j A_p + S_j acc_j + V_j x (S_j w_j); tangents along d
    n = w.shape[0]
    t6 = np.empty(6, dtype=V.dtype)
    sw = np.empty(6, dtype=V.dtype)
    sa = np.empty(6, dtype=V.dtype)
    for j in range(n):
        pa = parent[j]
        _rb_subspace(jtype, axis, j, w[j], sw)
        _rb_subspace(jtype, axis, j, acc[j], sa)
        if pa < 0:
            for r in range(6):
                V[j, r] = sw[r]
            _rb_xmotion(R, p, j, a0, t6)
            for r in range(6):
                A[j, r] = t6[r] + sa[r]
            if tangent:
                for r in range(6):
                    dV[j, r] = 0.0
                    dA[j, r] = 0.0
                # d(X_j a0) = -d_j S_j x (X_j a0)
                _rb_subspace(jtype, axis, j, 1.0, sa)
                _rb_cross_motion(sa, t6, dA[j], -d[j])
        else:
            _rb_xmotion(R, p, j, V[pa], t6)
            for r in range(6):
                V[j, r] = t6[r] + sw[r]
            if tangent:
                _rb_xmotion(R, p, j, dV[pa], dV[j])
                _rb_subspace(jtype, axis, j, 1.0, sa)
                _rb_cross_motion(sa, t6, dV[j], -d[j])
                _rb_subspace(jtype, axis, j, acc[j], sa)
            _rb_xmotion(R, p, j, A[pa], t6)
            for r in range(6):
                A[j, r] = t6[r] + sa[r]
            if tangent:
                _rb_xmotion(R, p, j, dA[pa], dA[j])
                _rb_subspace(jtype, axis, j, 1.0, sa)
                _rb_cross_motion(sa, t6, dA[j], -d[j])
        _rb_cross_motion(V[j], sw, A[j], 1.0)
        if tangent:
            _rb_cross_motion(dV[j], sw, dA[j], 1.0)


def _rb_body_regressor(V1: "const real[6]", V2: "const real[6]", A: "const real[6]",
                       scale: "real", out: "real[6,10]"):
    # out (6 x 10) += scale * [L(A) + Q(V1, V2)]: the body force regressor
    # Phi_b(V, A) = L(A) + Q(V, V), linear part L and bilinear part Q of
    # f = m a - h x al + w x (m v - h x w),
    # n = I al + h x a + w x (I w + h x v) + v x (m v - h x w)    (V = (v, w), A = (a, al))
    v0 = V2[0]
    v1 = V2[1]
    v2 = V2[2]
    w0 = V2[3]
    w1 = V2[4]
    w2 = V2[5]
    x0 = V1[0]
    x1 = V1[1]
    x2 = V1[2]
    o0 = V1[3]
    o1 = V1[4]
    o2 = V1[5]
    a0 = A[0]
    a1 = A[1]
    a2 = A[2]
    b0 = A[3]
    b1 = A[4]
    b2 = A[5]
    # mass: f = a + o x v
    out[0, 0] += scale * (a0 + o1 * v2 - o2 * v1)
    out[1, 0] += scale * (a1 + o2 * v0 - o0 * v2)
    out[2, 0] += scale * (a2 + o0 * v1 - o1 * v0)
    # first moment h = e_k: f = al x e + o x (w x e); n = e x a + o x (e x v) + x x (w x e)
    for k in range(3):
        e0 = 1.0 if k == 0 else 0.0
        e1 = 1.0 if k == 1 else 0.0
        e2 = 1.0 if k == 2 else 0.0
        # w x e
        c0 = w1 * e2 - w2 * e1
        c1 = w2 * e0 - w0 * e2
        c2 = w0 * e1 - w1 * e0
        out[0, 1 + k] += scale * (b1 * e2 - b2 * e1 + o1 * c2 - o2 * c1)
        out[1, 1 + k] += scale * (b2 * e0 - b0 * e2 + o2 * c0 - o0 * c2)
        out[2, 1 + k] += scale * (b0 * e1 - b1 * e0 + o0 * c1 - o1 * c0)
        # e x v
        d0 = e1 * v2 - e2 * v1
        d1 = e2 * v0 - e0 * v2
        d2 = e0 * v1 - e1 * v0
        out[3, 1 + k] += scale * (e1 * a2 - e2 * a1 + o1 * d2 - o2 * d1 + x1 * c2 - x2 * c1)
        out[4, 1 + k] += scale * (e2 * a0 - e0 * a2 + o2 * d0 - o0 * d2 + x2 * c0 - x0 * c2)
        out[5, 1 + k] += scale * (e0 * a1 - e1 * a0 + o0 * d1 - o1 * d0 + x0 * c1 - x1 * c0)
    # rotational inertia (Ixx, Ixy, Iyy, Ixz, Iyz, Izz): n = E al + o x (E w)
    for k in range(6):
        # E = symmetric unit matrix of entry (r, c)
        r = 0 if k < 2 else (1 if k == 2 else (0 if k == 3 else (1 if k == 4 else 2)))
        c = 0 if k == 0 else (1 if k < 3 else 2)
        eb0 = 0.0 * b0
        eb1 = 0.0 * b0
        eb2 = 0.0 * b0
        ew0 = 0.0 * w0
        ew1 = 0.0 * w0
        ew2 = 0.0 * w0
        # (E x)_r += x_c, (E x)_c += x_r (once if r == c)
        bc = b0 if c == 0 else (b1 if c == 1 else b2)
        br = b0 if r == 0 else (b1 if r == 1 else b2)
        wc = w0 if c == 0 else (w1 if c == 1 else w2)
        wr = w0 if r == 0 else (w1 if r == 1 else w2)
        if r == 0:
            eb0 += bc
            ew0 += wc
        elif r == 1:
            eb1 += bc
            ew1 += wc
        else:
            eb2 += bc
            ew2 += wc
        if r != c:
            if c == 0:
                eb0 += br
                ew0 += wr
            elif c == 1:
                eb1 += br
                ew1 += wr
            else:
                eb2 += br
                ew2 += wr
        out[3, 4 + k] += scale * (eb0 + o1 * ew2 - o2 * ew1)
        out[4, 4 + k] += scale * (eb1 + o2 * ew0 - o0 * ew2)
        out[5, 4 + k] += scale * (eb2 + o0 * ew1 - o1 * ew0)


def _rb_project(R: "const real[N,3,3]", p: "const real[N,3]", parent: "const int[N]",
                jtype: "const int[N]", axis: "const float[N,3]", Pb: "const real[N,6,10]",
                tangent: "bool", d: "const real[N]", dPb: "const real[N,6,10]",
                Y: "real[N,NSTD]", dY: "real[N,NSTD]"):
    # Y[i, 10 j + c] = S_i^T X*_{i<-j} Pb[j][:, c] over the ancestors i of j (and tangents)
    n = Pb.shape[0]
    F = np.empty((6, 10), dtype=Pb.dtype)
    G = np.empty((6, 10), dtype=Pb.dtype)
    for i in range(n):
        for c in range(10 * n):
            Y[i, c] = 0.0
            if tangent:
                dY[i, c] = 0.0
    for j in range(n):
        for r in range(6):
            for c in range(10):
                F[r, c] = Pb[j, r, c]
                if tangent:
                    G[r, c] = dPb[j, r, c]
        k = j
        while k >= 0:
            off = 3 if jtype[k] == 0 else 0
            ux = axis[k, 0]
            uy = axis[k, 1]
            uz = axis[k, 2]
            for c in range(10):
                Y[k, 10 * j + c] = ux * F[off, c] + uy * F[off + 1, c] + uz * F[off + 2, c]
                if tangent:
                    dY[k, 10 * j + c] = ux * G[off, c] + uy * G[off + 1, c] + uz * G[off + 2, c]
            pk = parent[k]
            if pk < 0:
                break
            dk = d[k]
            for c in range(10):
                f0 = F[0, c]
                f1 = F[1, c]
                f2 = F[2, c]
                n0 = F[3, c]
                n1 = F[4, c]
                n2 = F[5, c]
                if tangent:
                    # G <- G + d_k (S_k x* F), then both to the parent frame
                    if jtype[k] == 0:     # S = (0, u): S x* F = (u x f, u x n)
                        G[0, c] += dk * (uy * f2 - uz * f1)
                        G[1, c] += dk * (uz * f0 - ux * f2)
                        G[2, c] += dk * (ux * f1 - uy * f0)
                        G[3, c] += dk * (uy * n2 - uz * n1)
                        G[4, c] += dk * (uz * n0 - ux * n2)
                        G[5, c] += dk * (ux * n1 - uy * n0)
                    else:                 # S = (u, 0): S x* F = (0, u x f)
                        G[3, c] += dk * (uy * f2 - uz * f1)
                        G[4, c] += dk * (uz * f0 - ux * f2)
                        G[5, c] += dk * (ux * f1 - uy * f0)
                    g0 = G[0, c]
                    g1 = G[1, c]
                    g2 = G[2, c]
                    h0 = G[3, c]
                    h1 = G[4, c]
                    h2 = G[5, c]
                    for r in range(3):
                        G[r, c] = R[k, r, 0] * g0 + R[k, r, 1] * g1 + R[k, r, 2] * g2
                        G[3 + r, c] = R[k, r, 0] * h0 + R[k, r, 1] * h1 + R[k, r, 2] * h2
                    G[3, c] += p[k, 1] * G[2, c] - p[k, 2] * G[1, c]
                    G[4, c] += p[k, 2] * G[0, c] - p[k, 0] * G[2, c]
                    G[5, c] += p[k, 0] * G[1, c] - p[k, 1] * G[0, c]
                # f_p = R f;  n_p = R n + p x f_p
                for r in range(3):
                    F[r, c] = R[k, r, 0] * f0 + R[k, r, 1] * f1 + R[k, r, 2] * f2
                    F[3 + r, c] = R[k, r, 0] * n0 + R[k, r, 1] * n1 + R[k, r, 2] * n2
                F[3, c] += p[k, 1] * F[2, c] - p[k, 2] * F[1, c]
                F[4, c] += p[k, 2] * F[0, c] - p[k, 0] * F[2, c]
                F[5, c] += p[k, 0] * F[1, c] - p[k, 1] * F[0, c]
            k = pk


def _rb_scale(x: "const real[N]") -> "float":
    # largest modulus of x (a constant factor of the polar form, never differentiated)
    s = 0.0
    for i in range(x.shape[0]):
        ai = abs(x[i])
        if ai > s:
            s = ai
    return s


def _rb_bodies(q: "const real[N]", x: "const real[N]", y: "const real[N]", acc: "const real[N]",
               grav: "real", tangent: "bool", d: "const real[N]", parent: "const int[N]",
               jtype: "const int[N]", axis: "const float[N,3]", Rp: "const float[N,3,3]",
               pp: "const float[N,3]", gvec: "const float[3]", R: "real[N,3,3]", p: "real[N,3]",
               Pb: "real[N,6,10]", dPb: "real[N,6,10]"):
    # body regressors (and tangents along d) of C(q, x) y + M(q) acc + grav * G(q), and the
    # bodies' poses (R, p)
    _rb_kinematics(q, jtype, axis, Rp, pp, R, p)
    _rb_body_terms(R, p, x, y, acc, grav, tangent, d, parent, jtype, axis, gvec, Pb, dPb)


def _rb_body_terms(R: "const real[N,3,3]", p: "const real[N,3]", x: "const real[N]",
                   y: "const real[N]", acc: "const real[N]", grav: "real", tangent: "bool",
                   d: "const real[N]", parent: "const int[N]", jtype: "const int[N]",
                   axis: "const float[N,3]", gvec: "const float[3]", Pb: "real[N,6,10]",
                   dPb: "real[N,6,10]"):
    # body regressors (and tangents along d) of C(q, x) y + M(q) acc + grav * G(q) at the
    # bodies' poses (R, p) of q
    n = x.shape[0]
    dt = Pb.dtype
    V = np.empty((n, 6), dtype=dt)
    A = np.empty((n, 6), dtype=dt)
    dV = np.empty((n, 6), dtype=dt)
    dA = np.empty((n, 6), dtype=dt)
    w = np.empty(n, dtype=dt)
    z = np.zeros(n, dtype=dt)
    a0 = np.zeros(6, dtype=dt)
    z6 = np.zeros(6, dtype=dt)
    for j in range(n):
        for r in range(6):
            for c in range(10):
                Pb[j, r, c] = 0.0
                if tangent:
                    dPb[j, r, c] = 0.0
    for r in range(3):
        a0[r] = -grav * gvec[r]
    sx = _rb_scale(x)
    sy = _rb_scale(y)
    same = sx > 0.0
    for i in range(n):
        if x[i] != y[i]:
            same = False
    if same:
        # C(q, x) x + M acc + grav G in one pass: the Newton-Euler recursion itself
        _rb_forward(R, p, parent, jtype, axis, x, acc, a0, tangent, d, V, A, dV, dA)
        for j in range(n):
            _rb_body_regressor(V[j], V[j], A[j], 1.0, Pb[j])
            if tangent:
                _rb_body_regressor(dV[j], V[j], dA[j], 1.0, dPb[j])
                _rb_body_regressor(V[j], dV[j], z6, 1.0, dPb[j])
        return
    # acceleration and gravity pass (the base accelerates at -g); none without either (it
    # would add exact zeros to the zeros Pb starts from: the same bits)
    moves = grav != 0.0
    for i in range(n):
        if acc[i] != 0.0:
            moves = True
    if moves:
        _rb_forward(R, p, parent, jtype, axis, z, acc, a0, tangent, d, V, A, dV, dA)
        for j in range(n):
            _rb_body_regressor(z6, z6, A[j], 1.0, Pb[j])
            if tangent:
                _rb_body_regressor(z6, z6, dA[j], 1.0, dPb[j])
    # velocity terms: the polar form of c(w) = C(q, w) w
    if sx > 0.0 and sy > 0.0:
        for r in range(6):
            a0[r] = 0.0
        for si in range(2):
            sgn = 1.0 - 2.0 * si
            for i in range(n):
                w[i] = x[i] / sx + sgn * y[i] / sy
            _rb_forward(R, p, parent, jtype, axis, w, z, a0, tangent, d, V, A, dV, dA)
            wt = sgn * 0.25 * sx * sy
            for j in range(n):
                _rb_body_regressor(V[j], V[j], A[j], wt, Pb[j])
                if tangent:
                    _rb_body_regressor(dV[j], V[j], dA[j], wt, dPb[j])
                    _rb_body_regressor(V[j], dV[j], z6, wt, dPb[j])


def _rb_links(q: "const real[N]", x: "const real[N]", y: "const real[N]", acc: "const real[N]",
              grav: "real", tangent: "bool", d: "const real[N]", parent: "const int[N]",
              jtype: "const int[N]", axis: "const float[N,3]", Rp: "const float[N,3,3]",
              pp: "const float[N,3]", gvec: "const float[3]", Y: "real[N,NSTD]",
              dY: "real[N,NSTD]"):
    # the link part Y[:, :10 n] of the regressor of C(q, x) y + M(q) acc + grav * G(q)
    n = q.shape[0]
    Pb = np.empty((n, 6, 10), dtype=Y.dtype)
    dPb = np.empty((n, 6, 10), dtype=Y.dtype)
    R = np.empty((n, 3, 3), dtype=Y.dtype)
    p = np.empty((n, 3), dtype=Y.dtype)
    _rb_bodies(q, x, y, acc, grav, tangent, d, parent, jtype, axis, Rp, pp, gvec, R, p, Pb, dPb)
    _rb_project(R, p, parent, jtype, axis, Pb, tangent, d, dPb, Y, dY)


def _rb_backward(R: "const real[N,3,3]", p: "const real[N,3]", parent: "const int[N]",
                 jtype: "const int[N]", axis: "const float[N,3]", f: "real[N,6]",
                 tau: "real[N]"):
    # tau_j = the joint axis' component of the body force f_j, accumulating each f_j into
    # its parent's frame on the way to the base (children have higher index; f is changed)
    n = f.shape[0]
    for j in range(n - 1, -1, -1):
        off = 3 if jtype[j] == 0 else 0
        tau[j] = axis[j, 0] * f[j, off] + axis[j, 1] * f[j, off + 1] + axis[j, 2] * f[j, off + 2]
        pa = parent[j]
        if pa >= 0:
            fl0 = R[j, 0, 0] * f[j, 0] + R[j, 0, 1] * f[j, 1] + R[j, 0, 2] * f[j, 2]
            fl1 = R[j, 1, 0] * f[j, 0] + R[j, 1, 1] * f[j, 1] + R[j, 1, 2] * f[j, 2]
            fl2 = R[j, 2, 0] * f[j, 0] + R[j, 2, 1] * f[j, 1] + R[j, 2, 2] * f[j, 2]
            f[pa, 0] += fl0
            f[pa, 1] += fl1
            f[pa, 2] += fl2
            f[pa, 3] += (R[j, 0, 0] * f[j, 3] + R[j, 0, 1] * f[j, 4] + R[j, 0, 2] * f[j, 5]
                         + p[j, 1] * fl2 - p[j, 2] * fl1)
            f[pa, 4] += (R[j, 1, 0] * f[j, 3] + R[j, 1, 1] * f[j, 4] + R[j, 1, 2] * f[j, 5]
                         + p[j, 2] * fl0 - p[j, 0] * fl2)
            f[pa, 5] += (R[j, 2, 0] * f[j, 3] + R[j, 2, 1] * f[j, 4] + R[j, 2, 2] * f[j, 5]
                         + p[j, 0] * fl1 - p[j, 1] * fl0)


def _rb_rnea(q: "const real[N]", x: "const real[N]", y: "const real[N]", acc: "const real[N]",
             grav: "real", pi: "const real[NSTD]", parent: "const int[N]",
             jtype: "const int[N]", axis: "const float[N,3]", Rp: "const float[N,3,3]",
             pp: "const float[N,3]", gvec: "const float[3]", tau: "real[N]"):
    # tau = C(q, x) y + M(q) acc + grav G(q) of the links with standard parameters pi:
    # the body forces Phi_b pi_j, accumulated towards the base (children have higher index)
    n = q.shape[0]
    Pb = np.empty((n, 6, 10))
    R = np.empty((n, 3, 3))
    p = np.empty((n, 3))
    _rb_bodies(q, x, y, acc, grav, False, q, parent, jtype, axis, Rp, pp, gvec, R, p, Pb, Pb)
    f = np.zeros((n, 6))
    for j in range(n):
        for r in range(6):
            s = 0.0
            for c in range(10):
                s += Pb[j, r, c] * pi[10 * j + c]
            f[j, r] = s
    _rb_backward(R, p, parent, jtype, axis, f, tau)


def _rb_mass(q: "const real[N]", pi: "const real[NSTD]", parent: "const int[N]",
             jtype: "const int[N]", axis: "const float[N,3]", Rp: "const float[N,3,3]",
             pp: "const float[N,3]", out: "real[N,N]"):
    # M(q) of the links with standard parameters pi, column k the torques of a unit
    # acceleration of joint k (no velocity, no gravity): only k's descendants accelerate
    n = q.shape[0]
    R = np.empty((n, 3, 3))
    p = np.empty((n, 3))
    _rb_kinematics(q, jtype, axis, Rp, pp, R, p)
    A = np.zeros((n, 6))
    f = np.zeros((n, 6))
    tau = np.empty(n)
    for k in range(n):
        for j in range(n):
            for r in range(6):
                A[j, r] = 0.0
                f[j, r] = 0.0
        _rb_subspace(jtype, axis, k, 1.0, A[k])
        for j in range(k + 1, n):
            if parent[j] >= k:
                _rb_xmotion(R, p, j, A[parent[j]], A[j])
        for j in range(k, n):
            # f = I A about the joint frame: (m a - h x al, I al + h x a)
            o = 10 * j
            a0 = A[j, 0]
            a1 = A[j, 1]
            a2 = A[j, 2]
            b0 = A[j, 3]
            b1 = A[j, 4]
            b2 = A[j, 5]
            f[j, 0] = pi[o] * a0 - (pi[o + 2] * b2 - pi[o + 3] * b1)
            f[j, 1] = pi[o] * a1 - (pi[o + 3] * b0 - pi[o + 1] * b2)
            f[j, 2] = pi[o] * a2 - (pi[o + 1] * b1 - pi[o + 2] * b0)
            f[j, 3] = (pi[o + 4] * b0 + pi[o + 5] * b1 + pi[o + 7] * b2 + pi[o + 2] * a2
                       - pi[o + 3] * a1)
            f[j, 4] = (pi[o + 5] * b0 + pi[o + 6] * b1 + pi[o + 8] * b2 + pi[o + 3] * a0
                       - pi[o + 1] * a2)
            f[j, 5] = (pi[o + 7] * b0 + pi[o + 8] * b1 + pi[o + 9] * b2 + pi[o + 1] * a1
                       - pi[o + 2] * a0)
        _rb_backward(R, p, parent, jtype, axis, f, tau)
        for i in range(n):
            out[i, k] = tau[i]


def _rb_cholesky(A: "real[N,N]") -> "int":
    # A <- L, A = L L^T (Golub & Van Loan, Alg. 4.2.1), in A's lower triangle; returns 0, or
    # 1 when A fails the package's one rule for "positive definite" (docs/models.md): a
    # pivot d_j not finite or d_j <= PIVOT_RTOL max_i A_ii.  The one Cholesky of the
    # Python side (the C face's cholesky_solve is its C twin, tests/test_c_face.py).
    n = A.shape[0]
    dmax = A[0, 0]
    for i in range(1, n):
        if A[i, i] > dmax:
            dmax = A[i, i]
    if not (dmax > 0.0 and dmax < np.inf):
        return 1
    for j in range(n):
        dd = A[j, j]
        for k in range(j):
            dd -= A[j, k] * A[j, k]
        if not (dd > PIVOT_RTOL * dmax and dd < np.inf):
            return 1
        dd = np.sqrt(dd)
        A[j, j] = dd
        for i in range(j + 1, n):
            s = A[i, j]
            for k in range(j):
                s -= A[i, k] * A[j, k]
            A[i, j] = s / dd
    return 0


def _rb_cholesky_solve(L: "const real[N,N]", b: "real[N]"):
    # b <- (L L^T)^-1 b with the factor of _rb_cholesky
    n = b.shape[0]
    for i in range(n):
        s = b[i]
        for k in range(i):
            s -= L[i, k] * b[k]
        b[i] = s / L[i, i]
    for i in range(n - 1, -1, -1):
        s = b[i]
        for k in range(i + 1, n):
            s -= L[k, i] * b[k]
        b[i] = s / L[i, i]


def _rb_spd_solve(Mq, b):
    # b <- Mq^-1 b by Cholesky (Mq is overwritten by its factor); raises when M(q) fails
    # the one rule
    if _rb_cholesky(Mq) != 0:
        raise ValueError(SINGULAR_INERTIA_MESSAGE)
    _rb_cholesky_solve(Mq, b)


# ---------------------------------------------------------------- a model's functions
# What a URDF model's functions do (ivdrem.models.urdf: its Python and its C face call these
# with the chain's constant arrays and workspaces): the standard regressor Y of (n, NSTD)
# (links, then viscous friction at column fv, Coulomb at fc, armature at ia; -1: none), the
# base parameters its columns `base` (theta = K pi, docs/models.md), pi(theta) the standard
# vector with the base values in their columns and 0 elsewhere (Y pi = Y_base theta).

def _rb_std(q: "const real[N]", x: "const real[N]", y: "const real[N]", acc: "const real[N]",
            grav: "real", fdq: "const real[N]", fric: "bool", arm: "bool", tangent: "bool",
            d: "const real[N]", parent: "const int[N]", jtype: "const int[N]",
            axis: "const float[N,3]", Rp: "const float[N,3,3]", pp: "const float[N,3]",
            gvec: "const float[3]", fv: "int", fc: "int", ia: "int", width: "float",
            Y: "real[N,NSTD]", dY: "real[N,NSTD]"):
    # the standard regressor of C(q, x) y + M(q) acc + grav G(q) (+ F(fdq) if fric,
    # + armature acc if arm) and its tangent along d
    _rb_links(q, x, y, acc, grav, tangent, d, parent, jtype, axis, Rp, pp, gvec, Y, dY)
    _rb_joint_terms(acc, fdq, fric, arm, tangent, fv, fc, ia, width, Y, dY)


def _rb_joint_terms(acc: "const real[N]", fdq: "const real[N]", fric: "bool", arm: "bool",
                    tangent: "bool", fv: "int", fc: "int", ia: "int", width: "float",
                    Y: "real[N,NSTD]", dY: "real[N,NSTD]"):
    # the columns after the links' of the standard regressor: friction F(fdq) if fric,
    # armature acc if arm, 0 otherwise (their tangents along q are 0)
    n = acc.shape[0]
    ns = Y.shape[1]
    for i in range(n):
        for k in range(10 * n, ns):
            Y[i, k] = 0.0
            if tangent:
                dY[i, k] = 0.0
        if fric:
            if fv >= 0:
                Y[i, fv + i] = fdq[i]
            if fc >= 0:
                Y[i, fc + i] = np.tanh(fdq[i] / width)
        if arm:
            if ia >= 0:
                Y[i, ia + i] = acc[i]


# ------------------------------------------- the regressor at given poses, by the joint axes
# What the regressors' derivatives evaluate, many times at one q: the poses (R, p) and the
# joint axes in the bodies' frames computed once, and the projection of a body force onto
# the joints above it a dot product with such an axis (Featherstone, Rigid Body Dynamics
# Algorithms, sec. 2.9: S_k^T X*_{k<-j} f = (X_{j<-k} S_k) . f) instead of carrying the
# force through every frame on the way (_rb_project).

def _rb_axes(R: "const real[N,3,3]", p: "const real[N,3]", parent: "const int[N]",
             jtype: "const int[N]", axis: "const float[N,3]", Sx: "real[N,N,6]"):
    # Sx[j, k] = X_{j<-k} S_k: the motion of joint k at unit rate in the frame of body j (the
    # velocity of body j it causes), for k = j and the ancestors of j; 0 for the other k
    n = parent.shape[0]
    for j in range(n):
        for k in range(n):
            for r in range(6):
                Sx[j, k, r] = 0.0
        _rb_subspace(jtype, axis, j, 1.0, Sx[j, j])
        pa = parent[j]
        k = pa
        while k >= 0:
            _rb_xmotion(R, p, j, Sx[pa, k], Sx[j, k])
            k = parent[k]


def _rb_axes_tangent(R: "const real[N,3,3]", p: "const real[N,3]", parent: "const int[N]",
                     jtype: "const int[N]", axis: "const float[N,3]", Sx: "const real[N,N,6]",
                     d: "const real[N]", dSx: "real[N,N,6]"):
    # the tangent of Sx along d: dSx[j, k] = X_j dSx[parent j, k] - d_j S_j x Sx[j, k] (the
    # derivative of the motion transform, dX_j = -d_j (S_j x) X_j); dSx[j, j] = 0
    n = parent.shape[0]
    sa = np.empty(6, dtype=dSx.dtype)
    for j in range(n):
        for k in range(n):
            for r in range(6):
                dSx[j, k, r] = 0.0
        pa = parent[j]
        k = pa
        if k >= 0:
            _rb_subspace(jtype, axis, j, 1.0, sa)
        while k >= 0:
            _rb_xmotion(R, p, j, dSx[pa, k], dSx[j, k])
            _rb_cross_motion(sa, Sx[j, k], dSx[j, k], -d[j])
            k = parent[k]


def _rb_project_axes(Sx: "const real[N,N,6]", dSx: "const real[N,N,6]",
                     parent: "const int[N]", Pb: "const real[N,6,10]",
                     dPb: "const real[N,6,10]", tangent: "bool", Y: "real[N,NSTD]",
                     dY: "real[N,NSTD]"):
    # Y[k, 10 j + c] = Sx[j, k] . Pb[j][:, c] for k = j and the ancestors of j, 0 for the
    # others (as _rb_project); the tangent dSx . Pb + Sx . dPb
    n = Pb.shape[0]
    acc = np.empty(10, dtype=Y.dtype)
    dacc = np.empty(10, dtype=Y.dtype)
    for i in range(n):
        for c in range(10 * n):
            Y[i, c] = 0.0
            if tangent:
                dY[i, c] = 0.0
    for j in range(n):
        # a body at rest in every sense (the bodies below a unit acceleration of a joint
        # further out) adds nothing: its entries stay 0
        still = True
        for r in range(6):
            for c in range(10):
                if Pb[j, r, c] != 0.0 or (tangent and dPb[j, r, c] != 0.0):
                    still = False
                    break
            if not still:
                break
        k = -1 if still else j
        while k >= 0:
            # the ten columns side by side (ten independent sums, each over r in order)
            for c in range(10):
                acc[c] = Sx[j, k, 0] * Pb[j, 0, c]
                if tangent:
                    dacc[c] = Sx[j, k, 0] * dPb[j, 0, c] + dSx[j, k, 0] * Pb[j, 0, c]
            for r in range(1, 6):
                sr = Sx[j, k, r]
                for c in range(10):
                    acc[c] += sr * Pb[j, r, c]
                if tangent:
                    dsr = dSx[j, k, r]
                    for c in range(10):
                        dacc[c] += sr * dPb[j, r, c] + dsr * Pb[j, r, c]
            for c in range(10):
                Y[k, 10 * j + c] = acc[c]
                if tangent:
                    dY[k, 10 * j + c] = dacc[c]
            k = parent[k]


def _rb_axes_tangent2(R: "const real[N,3,3]", p: "const real[N,3]", parent: "const int[N]",
                      jtype: "const int[N]", axis: "const float[N,3]",
                      dSd: "const real[N,N,6]", dSe: "const real[N,N,6]", d: "const real[N]",
                      e: "const real[N]", ddS: "real[N,N,6]"):
    # the tangent along e of dSd (the tangent of Sx along d; dSe the tangent along e):
    # ddS[j, k] = X_j ddS[parent j, k] - e_j S_j x (X_j dSd[parent j, k]) - d_j S_j x dSe[j, k]
    n = parent.shape[0]
    sa = np.empty(6, dtype=ddS.dtype)
    t6 = np.empty(6, dtype=ddS.dtype)
    for j in range(n):
        for k in range(n):
            for r in range(6):
                ddS[j, k, r] = 0.0
        pa = parent[j]
        k = pa
        if k >= 0:
            _rb_subspace(jtype, axis, j, 1.0, sa)
        while k >= 0:
            _rb_xmotion(R, p, j, ddS[pa, k], ddS[j, k])
            _rb_xmotion(R, p, j, dSd[pa, k], t6)
            _rb_cross_motion(sa, t6, ddS[j, k], -e[j])
            _rb_cross_motion(sa, dSe[j, k], ddS[j, k], -d[j])
            k = parent[k]


def _rb_accelerations2(R: "const real[N,3,3]", p: "const real[N,3]", parent: "const int[N]",
                       jtype: "const int[N]", axis: "const float[N,3]", acc: "const real[N]",
                       d: "const real[N]", e: "const real[N]", A: "real[N,6]",
                       dA: "real[N,6]", eA: "real[N,6]", deA: "real[N,6]"):
    # the bodies' accelerations A_j = X_j A_p + S_j acc_j of joint accelerations acc alone
    # (no velocity, no gravity: M(q) acc), their tangents along d and e, and the tangent
    # along e of the one along d (dX_j = -d_j (S_j x) X_j, as _rb_forward):
    #   dA_j = X_j dA_p - d_j S_j x T,  T = X_j A_p;  eA_j = X_j eA_p - e_j S_j x T
    #   deA_j = X_j deA_p - e_j S_j x (X_j dA_p) - d_j S_j x eA_j
    n = acc.shape[0]
    sa = np.empty(6, dtype=A.dtype)
    t6 = np.empty(6, dtype=A.dtype)
    for j in range(n):
        pa = parent[j]
        _rb_subspace(jtype, axis, j, acc[j], sa)
        if pa < 0:
            for r in range(6):
                A[j, r] = sa[r]
                dA[j, r] = 0.0
                eA[j, r] = 0.0
                deA[j, r] = 0.0
        else:
            _rb_xmotion(R, p, j, A[pa], t6)
            for r in range(6):
                A[j, r] = t6[r] + sa[r]
            _rb_subspace(jtype, axis, j, 1.0, sa)
            _rb_xmotion(R, p, j, dA[pa], dA[j])
            _rb_cross_motion(sa, t6, dA[j], -d[j])
            _rb_xmotion(R, p, j, eA[pa], eA[j])
            _rb_cross_motion(sa, t6, eA[j], -e[j])
            _rb_xmotion(R, p, j, deA[pa], deA[j])
            _rb_xmotion(R, p, j, dA[pa], t6)
            _rb_cross_motion(sa, t6, deA[j], -e[j])
            _rb_cross_motion(sa, eA[j], deA[j], -d[j])


def _rb_mass_tangent2(R: "const real[N,3,3]", p: "const real[N,3]", Sx: "const real[N,N,6]",
                      dSd: "const real[N,N,6]", dSe: "const real[N,N,6]",
                      ddS: "const real[N,N,6]", acc: "const real[N]", d: "const real[N]",
                      e: "const real[N]", parent: "const int[N]", jtype: "const int[N]",
                      axis: "const float[N,3]", ddY: "real[N,NSTD]"):
    # the tangent along e of the tangent along d of the standard regressor of M(q) acc (the
    # links' columns; the armature's, acc, does not depend on q: 0).  With Y[k, 10 j + c] =
    # Sx[j, k] . L(A_j)[:, c] (L the body regressor of an acceleration, linear):
    #   ddY = ddS . L(A) + dSd . L(eA) + dSe . L(dA) + Sx . L(deA)
    n = acc.shape[0]
    ns = ddY.shape[1]
    A = np.empty((n, 6), dtype=ddY.dtype)
    dA = np.empty((n, 6), dtype=ddY.dtype)
    eA = np.empty((n, 6), dtype=ddY.dtype)
    deA = np.empty((n, 6), dtype=ddY.dtype)
    L0 = np.zeros((6, 10), dtype=ddY.dtype)
    Ld = np.zeros((6, 10), dtype=ddY.dtype)
    Le = np.zeros((6, 10), dtype=ddY.dtype)
    Lde = np.zeros((6, 10), dtype=ddY.dtype)
    z6 = np.zeros(6, dtype=ddY.dtype)
    yc = np.empty(10, dtype=ddY.dtype)
    _rb_accelerations2(R, p, parent, jtype, axis, acc, d, e, A, dA, eA, deA)
    for i in range(n):
        for c in range(ns):
            ddY[i, c] = 0.0
    for j in range(n):
        for r in range(6):
            for c in range(10):
                L0[r, c] = 0.0
                Ld[r, c] = 0.0
                Le[r, c] = 0.0
                Lde[r, c] = 0.0
        _rb_body_regressor(z6, z6, A[j], 1.0, L0)
        _rb_body_regressor(z6, z6, dA[j], 1.0, Ld)
        _rb_body_regressor(z6, z6, eA[j], 1.0, Le)
        _rb_body_regressor(z6, z6, deA[j], 1.0, Lde)
        k = j
        while k >= 0:
            for c in range(10):
                s = ddS[j, k, 0] * L0[0, c] + dSd[j, k, 0] * Le[0, c]
                yc[c] = s + dSe[j, k, 0] * Ld[0, c] + Sx[j, k, 0] * Lde[0, c]
            for r in range(1, 6):
                s0 = ddS[j, k, r]
                s1 = dSd[j, k, r]
                s2 = dSe[j, k, r]
                s3 = Sx[j, k, r]
                for c in range(10):
                    yc[c] += s0 * L0[r, c] + s1 * Le[r, c]
                    yc[c] += s2 * Ld[r, c] + s3 * Lde[r, c]
            for c in range(10):
                ddY[k, 10 * j + c] = yc[c]
            k = parent[k]


def _rb_std_at(R: "const real[N,3,3]", p: "const real[N,3]", Sx: "const real[N,N,6]",
               dSx: "const real[N,N,6]", x: "const real[N]", y: "const real[N]",
               acc: "const real[N]", grav: "real", fdq: "const real[N]", fric: "bool",
               arm: "bool", tangent: "bool", d: "const real[N]", parent: "const int[N]",
               jtype: "const int[N]", axis: "const float[N,3]", gvec: "const float[3]",
               fv: "int", fc: "int", ia: "int", width: "float", Y: "real[N,NSTD]",
               dY: "real[N,NSTD]"):
    # _rb_std at the poses (R, p) and axes Sx of q (and dSx, their tangent along d)
    n = x.shape[0]
    Pb = np.empty((n, 6, 10), dtype=Y.dtype)
    dPb = np.empty((n, 6, 10), dtype=Y.dtype)
    _rb_body_terms(R, p, x, y, acc, grav, tangent, d, parent, jtype, axis, gvec, Pb, dPb)
    _rb_project_axes(Sx, dSx, parent, Pb, dPb, tangent, Y, dY)
    _rb_joint_terms(acc, fdq, fric, arm, tangent, fv, fc, ia, width, Y, dY)


def _rb_select(Y: "const real[N,NSTD]", base: "const int[NTHETA]", out: "real[N,NTHETA]"):
    # the base columns of the standard regressor
    n = Y.shape[0]
    nb = out.shape[1]
    for i in range(n):
        for b in range(nb):
            out[i, b] = Y[i, base[b]]


def _rb_select_column(Y: "const real[N,NSTD]", base: "const int[NTHETA]", ncol: "int",
                      col: "int", out: "real[N,NTHETA,ncol]"):
    # column col of a regressor's derivative: the base columns of Y (as _rb_select)
    n = Y.shape[0]
    nb = base.shape[0]
    for i in range(n):
        for b in range(nb):
            out[i, b, col] = Y[i, base[b]]


def _rb_pi(theta: "const real[NTHETA]", base: "const int[NTHETA]", pi: "real[NSTD]"):
    # standard parameters with K pi = theta: the base ones in their columns, the others 0
    ns = pi.shape[0]
    nb = theta.shape[0]
    for k in range(ns):
        pi[k] = 0.0
    for b in range(nb):
        pi[base[b]] = theta[b]


def _rb_Phi_M(q: "const real[N]", a: "const real[N]", parent: "const int[N]",
              jtype: "const int[N]", axis: "const float[N,3]", Rp: "const float[N,3,3]",
              pp: "const float[N,3]", gvec: "const float[3]", base: "const int[NTHETA]",
              fv: "int", fc: "int", ia: "int", width: "float", Y: "real[N,NSTD]",
              out: "real[N,NTHETA]"):
    # Phi_M^T(q, a) = d(M a)/dtheta
    n = q.shape[0]
    z = np.zeros(n)
    _rb_std(q, z, z, a, 0.0, z, False, True, False, q, parent, jtype, axis, Rp, pp, gvec,
            fv, fc, ia, width, Y, Y)
    _rb_select(Y, base, out)


def _rb_Phi_C(q: "const real[N]", dq: "const real[N]", v: "const real[N]",
              parent: "const int[N]", jtype: "const int[N]", axis: "const float[N,3]",
              Rp: "const float[N,3,3]", pp: "const float[N,3]", gvec: "const float[3]",
              base: "const int[NTHETA]", fv: "int", fc: "int", ia: "int", width: "float",
              Y: "real[N,NSTD]", out: "real[N,NTHETA]"):
    # Phi_C^T(q, dq, v) = d(C(q, dq) v)/dtheta
    n = q.shape[0]
    z = np.zeros(n)
    _rb_std(q, dq, v, z, 0.0, z, False, False, False, q, parent, jtype, axis, Rp, pp, gvec,
            fv, fc, ia, width, Y, Y)
    _rb_select(Y, base, out)


def _rb_Phi_dM(q: "const real[N]", dq: "const real[N]", a: "const real[N]",
               parent: "const int[N]", jtype: "const int[N]", axis: "const float[N,3]",
               Rp: "const float[N,3,3]", pp: "const float[N,3]", gvec: "const float[3]",
               base: "const int[NTHETA]", fv: "int", fc: "int", ia: "int", width: "float",
               Y: "real[N,NSTD]", dY: "real[N,NSTD]", out: "real[N,NTHETA]"):
    # Phi_dM^T(q, dq, a) = d(Mdot a)/dtheta: the forward-mode derivative along dq
    n = q.shape[0]
    z = np.zeros(n)
    _rb_std(q, z, z, a, 0.0, z, False, False, True, dq, parent, jtype, axis, Rp, pp, gvec,
            fv, fc, ia, width, Y, dY)
    _rb_select(dY, base, out)


def _rb_Phi_G(q: "const real[N]", parent: "const int[N]", jtype: "const int[N]",
              axis: "const float[N,3]", Rp: "const float[N,3,3]", pp: "const float[N,3]",
              gvec: "const float[3]", base: "const int[NTHETA]", fv: "int", fc: "int",
              ia: "int", width: "float", Y: "real[N,NSTD]", out: "real[N,NTHETA]"):
    # Phi_G^T(q) = dG/dtheta
    n = q.shape[0]
    z = np.zeros(n)
    _rb_std(q, z, z, z, 1.0, z, False, False, False, q, parent, jtype, axis, Rp, pp, gvec,
            fv, fc, ia, width, Y, Y)
    _rb_select(Y, base, out)


def _rb_Phi_F(dq: "const real[N]", base: "const int[NTHETA]", fv: "int", fc: "int",
              width: "float", Y: "real[N,NSTD]", out: "real[N,NTHETA]"):
    # Phi_F^T(dq) = dF/dtheta
    n = dq.shape[0]
    ns = Y.shape[1]
    for i in range(n):
        for k in range(ns):
            Y[i, k] = 0.0
        if fv >= 0:
            Y[i, fv + i] = dq[i]
        if fc >= 0:
            Y[i, fc + i] = np.tanh(dq[i] / width)
    _rb_select(Y, base, out)


def _rb_Phi(q: "const real[N]", dq: "const real[N]", v: "const real[N]", dv: "const real[N]",
            parent: "const int[N]", jtype: "const int[N]", axis: "const float[N,3]",
            Rp: "const float[N,3,3]", pp: "const float[N,3]", gvec: "const float[3]",
            base: "const int[NTHETA]", fv: "int", fc: "int", ia: "int", width: "float",
            Y: "real[N,NSTD]", out: "real[N,NTHETA]"):
    # Phi^T(q, dq, v, dv) = Phi_M^T(q, dv) + Phi_C^T(q, dq, v) + Phi_F^T(dq) + Phi_G^T(q)
    _rb_std(q, dq, v, dv, 1.0, dq, True, True, False, q, parent, jtype, axis, Rp, pp, gvec,
            fv, fc, ia, width, Y, Y)
    _rb_select(Y, base, out)


def _rb_M(q: "const real[N]", theta: "const real[NTHETA]", parent: "const int[N]",
          jtype: "const int[N]", axis: "const float[N,3]", Rp: "const float[N,3,3]",
          pp: "const float[N,3]", base: "const int[NTHETA]", ia: "int", pi: "real[NSTD]",
          out: "real[N,N]"):
    # the inertia matrix M(q) (links, + armature)
    n = q.shape[0]
    _rb_pi(theta, base, pi)
    _rb_mass(q, pi, parent, jtype, axis, Rp, pp, out)
    if ia >= 0:
        for k in range(n):
            out[k, k] += pi[ia + k]


def _rb_C(q: "const real[N]", dq: "const real[N]", theta: "const real[NTHETA]",
          parent: "const int[N]", jtype: "const int[N]", axis: "const float[N,3]",
          Rp: "const float[N,3,3]", pp: "const float[N,3]", gvec: "const float[3]",
          base: "const int[NTHETA]", pi: "real[NSTD]", out: "real[N,N]"):
    # the Coriolis matrix C(q, dq) (Christoffel-consistent), column k = C(q, dq) e_k
    n = q.shape[0]
    _rb_pi(theta, base, pi)
    z = np.zeros(n)
    e = np.zeros(n)
    tau = np.empty(n)
    for k in range(n):
        e[k] = 1.0
        _rb_rnea(q, dq, e, z, 0.0, pi, parent, jtype, axis, Rp, pp, gvec, tau)
        e[k] = 0.0
        for i in range(n):
            out[i, k] = tau[i]


def _rb_G(q: "const real[N]", theta: "const real[NTHETA]", parent: "const int[N]",
          jtype: "const int[N]", axis: "const float[N,3]", Rp: "const float[N,3,3]",
          pp: "const float[N,3]", gvec: "const float[3]", base: "const int[NTHETA]",
          pi: "real[NSTD]", out: "real[N]"):
    # gravity G(q)
    n = q.shape[0]
    _rb_pi(theta, base, pi)
    z = np.zeros(n)
    _rb_rnea(q, z, z, z, 1.0, pi, parent, jtype, axis, Rp, pp, gvec, out)


def _rb_F(dq: "const real[N]", theta: "const real[NTHETA]", base: "const int[NTHETA]",
          fv: "int", fc: "int", width: "float", pi: "real[NSTD]", out: "real[N]"):
    # friction F(dq)
    n = dq.shape[0]
    _rb_pi(theta, base, pi)
    for i in range(n):
        out[i] = 0.0
        if fv >= 0:
            out[i] += pi[fv + i] * dq[i]
        if fc >= 0:
            out[i] += pi[fc + i] * np.tanh(dq[i] / width)


def _rb_forward_dynamics(q: "const real[N]", dq: "const real[N]", tau: "const real[N]",
                         theta: "const real[NTHETA]", parent: "const int[N]",
                         jtype: "const int[N]", axis: "const float[N,3]",
                         Rp: "const float[N,3,3]", pp: "const float[N,3]",
                         gvec: "const float[3]", base: "const int[NTHETA]", fv: "int",
                         fc: "int", ia: "int", width: "float", pi: "real[NSTD]",
                         out: "real[N]") -> "int":
    # qdd solving M(q) qdd = tau - C(q, dq) dq - F(dq) - G(q); 0, or 1 when M(q) fails the
    # one rule of _rb_cholesky (out then undefined)
    n = q.shape[0]
    b = np.empty(n)
    f = np.empty(n)
    Mq = np.empty((n, n))
    z = np.zeros(n)
    _rb_F(dq, theta, base, fv, fc, width, pi, f)
    _rb_pi(theta, base, pi)
    _rb_rnea(q, dq, dq, z, 1.0, pi, parent, jtype, axis, Rp, pp, gvec, b)
    for i in range(n):
        out[i] = tau[i] - b[i] - f[i]
    _rb_M(q, theta, parent, jtype, axis, Rp, pp, base, ia, pi, Mq)
    if _rb_cholesky(Mq) != 0:
        return 1
    _rb_cholesky_solve(Mq, out)
    return 0


# ------------------------------------------------------- the regressors' derivatives
# out[i, b, arg * n + m] = d Phi[i, b] / d arg[m], the arguments in signature order (what
# the blocks' Jacobians use: ivdrem.blocks.jacobians).  Each function computes the poses and
# the joint axes at q once (_rb_axes) and every column from them (_rb_std_at): d/dq_m the
# exact forward-mode derivative of the recursion along e_m (tangent=True, the axes' tangent
# _rb_axes_tangent), d/d of a linear argument the regressor at e_m (C(q, x) y is bilinear,
# M(q) a linear).  d/dq of Phi_dM (a second derivative of M(q) a) by the tangent of the
# tangent (_rb_mass_tangent2).


def _rb_Phi_M_jac(q: "const real[N]", a: "const real[N]",
                  parent: "const int[N]", jtype: "const int[N]",
                  axis: "const float[N,3]", Rp: "const float[N,3,3]", pp: "const float[N,3]",
                  gvec: "const float[3]", base: "const int[NTHETA]", fv: "int", fc: "int",
                  ia: "int", width: "float", Y: "real[N,NSTD]",
                  dY: "real[N,NSTD]", out: "real[N,NTHETA,N2]"):
    # d Phi_M / d(q, a)
    n = q.shape[0]
    ncol = out.shape[2]
    z = np.zeros(n)
    e = np.zeros(n)
    R = np.empty((n, 3, 3))
    p = np.empty((n, 3))
    Sx = np.empty((n, n, 6))
    dSx = np.empty((n, n, 6))
    _rb_kinematics(q, jtype, axis, Rp, pp, R, p)
    _rb_axes(R, p, parent, jtype, axis, Sx)
    for m in range(n):
        e[m] = 1.0
        _rb_axes_tangent(R, p, parent, jtype, axis, Sx, e, dSx)
        _rb_std_at(R, p, Sx, dSx, z, z, a, 0.0, z, False, True, True, e, parent, jtype, axis,
                   gvec, fv, fc, ia, width, Y, dY)
        _rb_select_column(dY, base, ncol, m, out)
        _rb_std_at(R, p, Sx, dSx, z, z, e, 0.0, z, False, True, False, e, parent, jtype,
                   axis, gvec, fv, fc, ia, width, Y, Y)
        _rb_select_column(Y, base, ncol, n + m, out)
        e[m] = 0.0


def _rb_Phi_C_jac(q: "const real[N]", dq: "const real[N]", v: "const real[N]",
                  parent: "const int[N]", jtype: "const int[N]",
                  axis: "const float[N,3]", Rp: "const float[N,3,3]", pp: "const float[N,3]",
                  gvec: "const float[3]", base: "const int[NTHETA]", fv: "int", fc: "int",
                  ia: "int", width: "float",
                  Y: "real[N,NSTD]", dY: "real[N,NSTD]", out: "real[N,NTHETA,N3]"):
    # d Phi_C / d(q, dq, v); at v = dq (the regression filter's) the columns of dq and v
    # are equal
    n = q.shape[0]
    ncol = out.shape[2]
    nb = base.shape[0]
    same = True
    for i in range(n):
        if dq[i] != v[i]:
            same = False
    z = np.zeros(n)
    e = np.zeros(n)
    R = np.empty((n, 3, 3))
    p = np.empty((n, 3))
    Sx = np.empty((n, n, 6))
    dSx = np.empty((n, n, 6))
    _rb_kinematics(q, jtype, axis, Rp, pp, R, p)
    _rb_axes(R, p, parent, jtype, axis, Sx)
    for m in range(n):
        e[m] = 1.0
        _rb_axes_tangent(R, p, parent, jtype, axis, Sx, e, dSx)
        _rb_std_at(R, p, Sx, dSx, dq, v, z, 0.0, z, False, False, True, e, parent, jtype,
                   axis, gvec, fv, fc, ia, width, Y, dY)
        _rb_select_column(dY, base, ncol, m, out)
        _rb_std_at(R, p, Sx, dSx, e, v, z, 0.0, z, False, False, False, e, parent, jtype,
                   axis, gvec, fv, fc, ia, width, Y, Y)
        _rb_select_column(Y, base, ncol, n + m, out)
        if same:
            # C(q, e_m) v = C(q, v) e_m (Christoffel-consistent C): the column just computed
            for i in range(n):
                for b in range(nb):
                    out[i, b, 2 * n + m] = out[i, b, n + m]
        else:
            _rb_std_at(R, p, Sx, dSx, dq, e, z, 0.0, z, False, False, False, e, parent, jtype,
                       axis, gvec, fv, fc, ia, width, Y, Y)
            _rb_select_column(Y, base, ncol, 2 * n + m, out)
        e[m] = 0.0


def _rb_Phi_dM_jac(q: "const real[N]", dq: "const real[N]", a: "const real[N]",
                   parent: "const int[N]", jtype: "const int[N]",
                   axis: "const float[N,3]", Rp: "const float[N,3,3]", pp: "const float[N,3]",
                   gvec: "const float[3]", base: "const int[NTHETA]", fv: "int", fc: "int",
                   ia: "int", width: "float",
                   Y: "real[N,NSTD]", dY: "real[N,NSTD]", out: "real[N,NTHETA,N3]"):
    # d Phi_dM / d(q, dq, a); d/dq_m the tangent along e_m of the tangent along dq (the
    # second derivative of M(q) a, _rb_mass_tangent2)
    n = q.shape[0]
    ncol = out.shape[2]
    z = np.zeros(n)
    e = np.zeros(n)
    R = np.empty((n, 3, 3))
    p = np.empty((n, 3))
    Sx = np.empty((n, n, 6))
    dSx = np.empty((n, n, 6))
    dSq = np.empty((n, n, 6))
    ddS = np.empty((n, n, 6))
    _rb_kinematics(q, jtype, axis, Rp, pp, R, p)
    _rb_axes(R, p, parent, jtype, axis, Sx)
    _rb_axes_tangent(R, p, parent, jtype, axis, Sx, dq, dSq)
    for m in range(n):
        e[m] = 1.0
        _rb_axes_tangent(R, p, parent, jtype, axis, Sx, e, dSx)
        _rb_axes_tangent2(R, p, parent, jtype, axis, dSq, dSx, dq, e, ddS)
        _rb_mass_tangent2(R, p, Sx, dSq, dSx, ddS, a, dq, e, parent, jtype, axis, Y)
        _rb_select_column(Y, base, ncol, m, out)
        _rb_std_at(R, p, Sx, dSx, z, z, a, 0.0, z, False, False, True, e, parent, jtype,
                   axis, gvec, fv, fc, ia, width, Y, dY)
        _rb_select_column(dY, base, ncol, n + m, out)
        _rb_std_at(R, p, Sx, dSq, z, z, e, 0.0, z, False, False, True, dq, parent, jtype,
                   axis, gvec, fv, fc, ia, width, Y, dY)
        _rb_select_column(dY, base, ncol, 2 * n + m, out)
        e[m] = 0.0


def _rb_Phi_G_jac(q: "const real[N]", parent: "const int[N]", jtype: "const int[N]",
                  axis: "const float[N,3]", Rp: "const float[N,3,3]", pp: "const float[N,3]",
                  gvec: "const float[3]", base: "const int[NTHETA]", fv: "int", fc: "int",
                  ia: "int", width: "float", Y: "real[N,NSTD]", dY: "real[N,NSTD]",
                  out: "real[N,NTHETA,N]"):
    # d Phi_G / dq
    n = q.shape[0]
    ncol = out.shape[2]
    z = np.zeros(n)
    e = np.zeros(n)
    R = np.empty((n, 3, 3))
    p = np.empty((n, 3))
    Sx = np.empty((n, n, 6))
    dSx = np.empty((n, n, 6))
    _rb_kinematics(q, jtype, axis, Rp, pp, R, p)
    _rb_axes(R, p, parent, jtype, axis, Sx)
    for m in range(n):
        e[m] = 1.0
        _rb_axes_tangent(R, p, parent, jtype, axis, Sx, e, dSx)
        _rb_std_at(R, p, Sx, dSx, z, z, z, 1.0, z, False, False, True, e, parent, jtype,
                   axis, gvec, fv, fc, ia, width, Y, dY)
        _rb_select_column(dY, base, ncol, m, out)
        e[m] = 0.0


def _rb_Phi_F_jac(dq: "const real[N]", base: "const int[NTHETA]", fv: "int", fc: "int",
                  width: "float", Y: "real[N,NSTD]", out: "real[N,NTHETA,N]"):
    # d Phi_F / d dq (diagonal: joint m's friction depends on dq_m only)
    n = dq.shape[0]
    ns = Y.shape[1]
    ncol = out.shape[2]
    for m in range(n):
        for i in range(n):
            for k in range(ns):
                Y[i, k] = 0.0
        if fv >= 0:
            Y[m, fv + m] = 1.0
        if fc >= 0:
            th = np.tanh(dq[m] / width)
            Y[m, fc + m] = (1.0 - th * th) / width
        _rb_select_column(Y, base, ncol, m, out)


def _rb_Phi_jac(q: "const real[N]", dq: "const real[N]", v: "const real[N]",
                dv: "const real[N]", parent: "const int[N]", jtype: "const int[N]",
                  axis: "const float[N,3]", Rp: "const float[N,3,3]", pp: "const float[N,3]",
                  gvec: "const float[3]", base: "const int[NTHETA]", fv: "int", fc: "int",
                  ia: "int", width: "float", Y: "real[N,NSTD]", dY: "real[N,NSTD]",
                out: "real[N,NTHETA,N4]"):
    # d Phi / d(q, dq, v, dv); at v = dq (the plant's and the instrument's) the columns of
    # dq and v differ by the friction's alone
    n = q.shape[0]
    ncol = out.shape[2]
    nb = base.shape[0]
    same = True
    for i in range(n):
        if dq[i] != v[i]:
            same = False
    z = np.zeros(n)
    e = np.zeros(n)
    dF = np.empty((n, nb, n))
    R = np.empty((n, 3, 3))
    p = np.empty((n, 3))
    Sx = np.empty((n, n, 6))
    dSx = np.empty((n, n, 6))
    _rb_Phi_F_jac(dq, base, fv, fc, width, Y, dF)
    _rb_kinematics(q, jtype, axis, Rp, pp, R, p)
    _rb_axes(R, p, parent, jtype, axis, Sx)
    for m in range(n):
        e[m] = 1.0
        _rb_axes_tangent(R, p, parent, jtype, axis, Sx, e, dSx)
        _rb_std_at(R, p, Sx, dSx, dq, v, dv, 1.0, dq, True, True, True, e, parent, jtype,
                   axis, gvec, fv, fc, ia, width, Y, dY)
        _rb_select_column(dY, base, ncol, m, out)
        _rb_std_at(R, p, Sx, dSx, e, v, z, 0.0, z, False, False, False, e, parent, jtype,
                   axis, gvec, fv, fc, ia, width, Y, Y)
        _rb_select_column(Y, base, ncol, n + m, out)
        for i in range(n):
            for b in range(nb):
                if same:
                    # C(q, dq) e_m = C(q, e_m) dq (Christoffel-consistent C)
                    out[i, b, 2 * n + m] = out[i, b, n + m]
                out[i, b, n + m] += dF[i, b, m]
        if not same:
            _rb_std_at(R, p, Sx, dSx, dq, e, z, 0.0, z, False, False, False, e, parent, jtype,
                       axis, gvec, fv, fc, ia, width, Y, Y)
            _rb_select_column(Y, base, ncol, 2 * n + m, out)
        _rb_std_at(R, p, Sx, dSx, z, z, e, 0.0, z, False, True, False, e, parent, jtype,
                   axis, gvec, fv, fc, ia, width, Y, Y)
        _rb_select_column(Y, base, ncol, 3 * n + m, out)
        e[m] = 0.0


#: The kernels, in dependency order (their source goes into every rigid-body model's code).
KERNELS = (_rb_kinematics, _rb_xmotion, _rb_cross_motion, _rb_subspace, _rb_forward,
           _rb_body_regressor, _rb_project, _rb_scale, _rb_body_terms, _rb_bodies, _rb_links,
           _rb_backward, _rb_rnea, _rb_mass, _rb_cholesky, _rb_cholesky_solve, _rb_spd_solve,
           _rb_joint_terms, _rb_std, _rb_select, _rb_select_column, _rb_pi, _rb_Phi_M,
           _rb_Phi_C, _rb_Phi_dM, _rb_Phi_G, _rb_Phi_F, _rb_Phi, _rb_M, _rb_C, _rb_G, _rb_F,
           _rb_forward_dynamics, _rb_axes, _rb_axes_tangent, _rb_project_axes,
           _rb_axes_tangent2, _rb_accelerations2, _rb_mass_tangent2, _rb_std_at,
           _rb_Phi_M_jac, _rb_Phi_C_jac, _rb_Phi_dM_jac, _rb_Phi_G_jac, _rb_Phi_F_jac,
           _rb_Phi_jac)

#: The kernels of a model's C face (:mod:`ivdrem.models._c_printer`), in dependency order.
C_KERNELS = (_rb_kinematics, _rb_xmotion, _rb_cross_motion, _rb_subspace, _rb_forward,
             _rb_body_regressor, _rb_project, _rb_scale, _rb_body_terms, _rb_bodies, _rb_links,
             _rb_backward, _rb_rnea, _rb_mass, _rb_cholesky, _rb_cholesky_solve,
             _rb_joint_terms, _rb_std, _rb_select, _rb_pi, _rb_Phi_M, _rb_Phi_C, _rb_Phi_dM,
             _rb_Phi_G, _rb_Phi_F, _rb_Phi, _rb_M, _rb_C, _rb_G, _rb_F, _rb_forward_dynamics)

#: The regressors' derivatives in q and q̇ and what they call beyond the C face: the rest
#: of the compiled engine's C library of a model (:mod:`ivdrem.models._c_engine`).
C_JAC_KERNELS = (_rb_axes, _rb_axes_tangent, _rb_project_axes, _rb_axes_tangent2,
                 _rb_accelerations2, _rb_mass_tangent2, _rb_std_at,
                 _rb_select_column, _rb_Phi_M_jac, _rb_Phi_C_jac, _rb_Phi_dM_jac,
                 _rb_Phi_G_jac, _rb_Phi_F_jac, _rb_Phi_jac)

#: The Cholesky alone: the C face of every model (a symbolic one too) prints it.
C_CHOLESKY = (_rb_cholesky, _rb_cholesky_solve)
