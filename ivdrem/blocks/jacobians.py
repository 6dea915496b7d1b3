"""Analytic local Jacobians of the blocks (``BlockSpec.jacobian``), in closed form.

Each kernel ``name_jacobian(t, x, u, jac, *params)`` takes the block's flat state and
input vectors and its parameters (the same as its update/output kernels) and writes the
dense local Jacobian ``jac[(ny + nx), (nx + nu)]``: rows are the outputs then the state
derivatives, columns the states then the inputs; ``jac`` is zero on entry, and only the
nonzeros are written.  The compiled engine chains them through the connection map
(:mod:`ivdrem.sim.jacobian`) instead of differencing the block.  Every kernel is tested
against central differences of the block's own kernels (tests/test_jacobian.py).

Blocks without one here are differenced alone (forward differences of their kernels).
"""
from __future__ import annotations

import math

import numpy as np

from ._kernels import spd_solve, mixing_derivatives


def mixing_jacobian(t, x, u, jac, ntheta, variant, f_rel, guard):
    # inputs   u = [Y (nθ), Psi (nθ*nθ row-major)];  outputs y = [Delta, calY (nθ), log10|Delta|]
    # Closed form at O(nθ^3) from the signed SVD of Psi/s (eq. 17 and its variants,
    # docs/mixing.md): d det = tr(adj dP), the adjugate's derivative as three rank-one
    # pieces (exact at singular Psi: no division by a singular value that can vanish alone)
    mixing_derivatives(variant, u[0:ntheta], u[ntheta:ntheta + ntheta * ntheta], f_rel,
                       guard, jac)


def control_law_jacobian(t, x, u, jac, K, delta_mu, ntheta):
    # inputs   u = [r (n), mu, Pi^T (n*nθ), theta_hat (nθ), u_f (n)]
    # output   tau_i = (K r)_i + delta_mu mu r_i + (Pi^T theta_hat)_i - u_f_i      (eq. 9)
    n = K.shape[0]
    mu = u[n]
    p0 = n + 1
    t0 = p0 + n * ntheta
    f0 = t0 + ntheta
    for i in range(n):
        for j in range(n):
            jac[i, j] = K[i, j]
        jac[i, i] += delta_mu * mu
        jac[i, n] = delta_mu * u[i]
        for j in range(ntheta):
            jac[i, p0 + i * ntheta + j] = u[t0 + j]
            jac[i, t0 + j] = u[p0 + i * ntheta + j]
        jac[i, f0 + i] = -1.0


def inertia_scaled_control_law_jacobian(t, x, u, jac, K, delta_mu, ntheta, theta_nominal,
                                        nominal):
    # inputs   u = [q (n), r (n), mu, Pi^T (n*nθ), theta_hat (nθ), u_f (n)]; nominal = 1:
    #          and chi (n) (the observer's injection at theta_nominal, added to tau)
    # output   tau = M̂(q) w + Pi^T theta_hat - u_f (+ chi), w = (K + delta_mu mu) r,
    #          M̂(q) w = Phi_M^T(q, w) theta_nominal             (eq. 9 inertia-scaled, Property 1)
    # d tau/dq = dPhi_M^T(q, w)/dq theta_nominal; d tau/dw = M̂(q) (Phi_M is linear in w)
    n = K.shape[0]
    c_r = n
    c_mu = 2 * n
    p0 = c_mu + 1
    t0 = p0 + n * ntheta
    f0 = t0 + ntheta
    q = u[0:n]
    r = u[c_r:c_r + n]
    mu = u[c_mu]
    w = np.empty(n)
    for i in range(n):
        s = delta_mu * mu * r[i]
        for j in range(n):
            s += K[i, j] * r[j]
        w[i] = s
    dPM = np.empty((n, ntheta, 2 * n))      # d/(q, w)
    model.Phi_M_jac(q, w, dPM)
    Mh = np.zeros((n, n))
    for i in range(n):
        for c in range(n):
            sq = 0.0
            sw = 0.0
            for j in range(ntheta):
                sq += dPM[i, j, c] * theta_nominal[j]
                sw += dPM[i, j, n + c] * theta_nominal[j]
            jac[i, c] = sq
            Mh[i, c] = sw
    for i in range(n):
        smu = 0.0
        for c in range(n):
            smu += Mh[i, c] * r[c]
            s = delta_mu * mu * Mh[i, c]
            for k in range(n):
                s += Mh[i, k] * K[k, c]
            jac[i, c_r + c] = s
        jac[i, c_mu] = delta_mu * smu
        for j in range(ntheta):
            jac[i, p0 + i * ntheta + j] = u[t0 + j]
            jac[i, t0 + j] = u[p0 + i * ntheta + j]
        jac[i, f0 + i] = -1.0
        if nominal != 0.0:
            jac[i, f0 + n + i] = 1.0


def adaptation_law_jacobian(t, x, u, jac, Gamma):
    # states   x = theta_hat (nθ);  inputs u = [Pi^T (n*nθ), r (n), theta_c (nθ)]
    # output   y = theta_hat;  dtheta_hat = Gamma (Pi r + theta_c)                   (eq. 11)
    nth = x.shape[0]
    n = (u.shape[0] - nth) // (nth + 1)
    m = n * nth
    for i in range(nth):
        jac[i, i] = 1.0
    for i in range(nth):
        row = nth + i
        for k in range(n):
            acc = 0.0
            for j in range(nth):
                # d/dPi^T[k, j] = Gamma_ij r_k ; d/dr_k = sum_j Gamma_ij Pi^T[k, j]
                jac[row, nth + k * nth + j] = Gamma[i, j] * u[m + k]
                acc += Gamma[i, j] * u[k * nth + j]
            jac[row, nth + m + k] = acc
        for j in range(nth):
            jac[row, nth + m + n + j] = Gamma[i, j]


def drem_term_jacobian(t, x, u, jac, gamma):
    # inputs   u = [Delta, calY (nθ), theta_hat (nθ), w]
    # output   theta_c_i = w gamma Delta (calY_i - Delta theta_hat_i)                (eq. 21)
    nth = jac.shape[0]                     # rows: the nθ outputs (no states)
    w = u[1 + 2 * nth]
    g = gamma * w
    D = u[0]
    for i in range(nth):
        jac[i, 0] = g * (u[1 + i] - 2.0 * D * u[1 + nth + i])
        jac[i, 1 + i] = g * D
        jac[i, 1 + nth + i] = -g * D * D
        jac[i, 1 + 2 * nth] = gamma * D * (u[1 + i] - D * u[1 + nth + i])


def composite_learning_term_jacobian(t, x, u, jac, gamma):
    # inputs   u = [Y_b (nθ), Psi_b (nθ*nθ), theta_hat (nθ)]
    # output   theta_c_i = gamma (Y_b_i - (Psi_b theta_hat)_i)                       (eq. 35)
    nth = jac.shape[0]                     # rows: the nθ outputs (no states)
    t0 = nth + nth * nth
    for i in range(nth):
        jac[i, i] = gamma
        for j in range(nth):
            jac[i, nth + i * nth + j] = -gamma * u[t0 + j]
            jac[i, t0 + j] = -gamma * u[nth + i * nth + j]


def extension_jacobian(t, x, u, jac, n, ntheta, has_instrument):
    # inputs   u = [z (n), phi^T (n*nθ)] + [zeta^T (n*nθ)] if has_instrument
    # outputs  y = [zeta z (nθ), zeta phi^T (nθ*nθ)], zeta := phi without instrument
    m = n * ntheta
    p0 = n
    z0 = n + m if has_instrument == 1 else n       # where zeta^T sits in u
    for a in range(ntheta):
        for i in range(n):
            zia = u[z0 + i * ntheta + a]
            jac[a, i] = zia                                       # d(zeta z)_a / dz_i
            jac[a, z0 + i * ntheta + a] += u[i]                   # ... / dzeta^T[i, a]
            for b in range(ntheta):
                row = ntheta + a * ntheta + b
                jac[row, p0 + i * ntheta + b] += zia              # d(zeta phi^T)_ab / dphi^T[i, b]
                jac[row, z0 + i * ntheta + a] += u[p0 + i * ntheta + b]   # ... / dzeta^T[i, a]


# ---------------------------------------------------------- blocks calling the robot model
# These use the regressors' exact derivatives generated from the sympy model
# (model.Phi_jac etc., ivdrem.models.euler_lagrange): out[i, j, a*n + m] = dR[i, j]/dw_a[m]
# over the regressor's vector arguments w_0, w_1, ... in signature order.

def plant_jacobian(t, x, u, jac, theta):
    # states   x = [q (n), dq (n)];  inputs u = [tau (n), tau_d (n)];  outputs y = [q, dq]
    # M(q) qdd + ID0(q, dq) = tau + tau_d with ID(q, dq, a) = M a + C dq + F + G =
    # Phi^T(q, dq, dq, a) theta (Property 1, linear in theta), so at a = qdd      (eq. 1)
    #   dqdd/d(q, dq) = -M^{-1} dID/d(q, dq)   (dq fills two argument slots of Phi)
    #   dqdd/dtau = dqdd/dtau_d = M^{-1}
    n = x.shape[0] // 2
    nth = theta.shape[0]
    q = x[0:n]
    dq = x[n:2 * n]
    tau = np.empty(n)
    for i in range(n):
        tau[i] = u[i] + u[n + i]
    qdd = np.empty(n)
    model.forward_dynamics(q, dq, tau, theta, qdd)
    Mq = np.empty((n, n))
    model.M(q, theta, Mq)
    dPhi = np.empty((n, nth, 4 * n))
    model.Phi_jac(q, dq, dq, qdd, dPhi)
    B = np.zeros((n, 3 * n))            # [-dID/dq, -dID/ddq, I], then M^{-1} of it
    for i in range(n):
        for m in range(n):
            sq = 0.0
            sd = 0.0
            for j in range(nth):
                sq += dPhi[i, j, m] * theta[j]
                sd += (dPhi[i, j, n + m] + dPhi[i, j, 2 * n + m]) * theta[j]
            B[i, m] = -sq
            B[i, n + m] = -sd
        B[i, 2 * n + i] = 1.0
    spd_solve(Mq, B)
    for i in range(n):
        jac[i, i] = 1.0                     # y.q = q
        jac[n + i, n + i] = 1.0             # y.dq = dq
        jac[2 * n + i, n + i] = 1.0         # dq/dt = dq
        for m in range(2 * n):
            jac[3 * n + i, m] = B[i, m]
        for m in range(n):
            jac[3 * n + i, 2 * n + m] = B[i, 2 * n + m]
            jac[3 * n + i, 3 * n + m] = B[i, 2 * n + m]


def torque_observer_jacobian(t, x, u, jac, n, ntheta, literal_e1, nominal, theta_nominal):
    # states   x = [Phi_f (m), Phi_Mf (m), u_f (n)], m = n nθ (n x nθ row-major)
    # inputs   u = [q, dq, r, v, dv (n each), mu, dmu, tau (n), theta_hat (nθ)]
    # outputs  y = [Pi (m), u_f (n), tau_d_hat (n)]; rows of dx start at m + 2n
    #   Pi^T = mu (Phi_M^T(q,r) - Phi_Mf^T) + Phi^T(q,dq,v,dv) - Phi_f^T            (8)
    #   tau_d_hat = -(mu (Phi_M^T(q,r) - Phi_Mf^T) - Phi_f^T) theta_hat + u_f
    # nominal = 1 (the injection at theta_nominal): y = [Pi (m), u_f, tau_d_hat, chi (n)],
    # rows of dx start at m + 3n
    #   Pi^T = Phi^T(q,dq,v,dv) - Phi_f^T;  chi = mu (Phi_M^T(q,r) - Phi_Mf^T) theta_nominal
    #   tau_d_hat = -(chi - Phi_f^T theta_hat) + u_f
    #   dPhi_f = mu (Phi^T - Phi_C^T(q,dq,r) + Phi_dM^T(q,dq,r) - Phi_f)             (7)
    #   dPhi_Mf = g (Phi_M^T(q,r) - Phi_Mf), g = mu + (1 - literal_e1) dmu/mu        (7)
    #   du_f = mu (-tau - u_f)                                                       (7)
    m = n * ntheta
    nx = 2 * m + n
    q = u[0:n]
    dq = u[n:2 * n]
    r = u[2 * n:3 * n]
    v = u[3 * n:4 * n]
    dv = u[4 * n:5 * n]
    mu = u[5 * n]
    dmu = u[5 * n + 1]
    ct = nx + 5 * n + 2                  # column of tau
    cth = ct + n                         # column of theta_hat
    cmu = nx + 5 * n
    th = u[5 * n + 2 + n:5 * n + 2 + n + ntheta]
    PM = np.empty((n, ntheta))
    P = np.empty((n, ntheta))
    PC = np.empty((n, ntheta))
    PD = np.empty((n, ntheta))
    model.Phi_M(q, r, PM)
    model.Phi(q, dq, v, dv, P)
    model.Phi_C(q, dq, r, PC)
    model.Phi_dM(q, dq, r, PD)
    dPM = np.empty((n, ntheta, 2 * n))      # d/(q, r)
    dP = np.empty((n, ntheta, 4 * n))       # d/(q, dq, v, dv)
    dPC = np.empty((n, ntheta, 3 * n))      # d/(q, dq, r)
    dPD = np.empty((n, ntheta, 3 * n))      # d/(q, dq, r)
    model.Phi_M_jac(q, r, dPM)
    model.Phi_jac(q, dq, v, dv, dP)
    model.Phi_C_jac(q, dq, r, dPC)
    model.Phi_dM_jac(q, dq, r, dPD)
    g = mu + (1.0 - literal_e1) * dmu / mu
    dg_dmu = 1.0 - (1.0 - literal_e1) * dmu / (mu * mu)
    dg_ddmu = (1.0 - literal_e1) / mu
    nom = nominal != 0.0
    rd = m + 3 * n if nom else m + 2 * n     # first row of the state derivatives
    ytd = m + n                              # first row of tau_d_hat
    ych = m + 2 * n                          # first row of chi (nominal)
    for i in range(n):
        for j in range(ntheta):
            k = i * ntheta + j
            e = PM[i, j] - x[m + k]
            # Pi^T
            jac[k, k] = -1.0
            if nom:
                # the injection at theta_nominal: chi_i = mu sum_j e_ij tn_j,
                # tau_d_hat_i = -chi_i + sum_j Phi_f_ij theta_hat_j + u_f_i
                tn = theta_nominal[j]
                jac[ych + i, m + k] = -mu * tn
                jac[ych + i, cmu] += e * tn
                jac[ytd + i, k] = th[j]
                jac[ytd + i, m + k] = mu * tn
                jac[ytd + i, cth + j] = x[k]
                jac[ytd + i, cmu] -= e * tn
            else:
                jac[k, m + k] = -mu
                jac[k, cmu] = e
                # tau_d_hat_i = -sum_j (mu e_ij - Phi_f_ij) theta_hat_j + u_f_i
                jac[ytd + i, k] = th[j]
                jac[ytd + i, m + k] = mu * th[j]
                jac[ytd + i, cth + j] = -(mu * e - x[k])
                jac[ytd + i, cmu] -= e * th[j]
            # dPhi_f, dPhi_Mf
            jac[rd + k, k] = -mu
            jac[rd + k, cmu] = P[i, j] - PC[i, j] + PD[i, j] - x[k]
            jac[rd + m + k, m + k] = -g
            jac[rd + m + k, cmu] = dg_dmu * e
            jac[rd + m + k, cmu + 1] = dg_ddmu * e
            for c in range(n):
                pq = dPM[i, j, c]              # dPhi_M/dq_c
                pr = dPM[i, j, n + c]          # dPhi_M/dr_c
                jac[k, nx + n + c] = dP[i, j, n + c]
                jac[k, nx + 3 * n + c] = dP[i, j, 2 * n + c]
                jac[k, nx + 4 * n + c] = dP[i, j, 3 * n + c]
                if nom:
                    jac[k, nx + c] = dP[i, j, c]
                    tn = theta_nominal[j]
                    jac[ych + i, nx + c] += mu * pq * tn
                    jac[ych + i, nx + 2 * n + c] += mu * pr * tn
                    jac[ytd + i, nx + c] -= mu * pq * tn
                    jac[ytd + i, nx + 2 * n + c] -= mu * pr * tn
                else:
                    jac[k, nx + c] = mu * pq + dP[i, j, c]
                    jac[k, nx + 2 * n + c] = mu * pr
                    jac[ytd + i, nx + c] -= mu * pq * th[j]
                    jac[ytd + i, nx + 2 * n + c] -= mu * pr * th[j]
                jac[rd + k, nx + c] = mu * (dP[i, j, c] - dPC[i, j, c] + dPD[i, j, c])
                jac[rd + k, nx + n + c] = mu * (dP[i, j, n + c] - dPC[i, j, n + c]
                                                + dPD[i, j, n + c])
                jac[rd + k, nx + 2 * n + c] = mu * (dPD[i, j, 2 * n + c] - dPC[i, j, 2 * n + c])
                jac[rd + k, nx + 3 * n + c] = mu * dP[i, j, 2 * n + c]
                jac[rd + k, nx + 4 * n + c] = mu * dP[i, j, 3 * n + c]
                jac[rd + m + k, nx + c] = g * pq
                jac[rd + m + k, nx + 2 * n + c] = g * pr
    for i in range(n):
        jac[m + i, 2 * m + i] = 1.0           # y.u_f = u_f
        jac[ytd + i, 2 * m + i] = 1.0
        jac[rd + 2 * m + i, 2 * m + i] = -mu  # du_f
        jac[rd + 2 * m + i, ct + i] = -mu
        jac[rd + 2 * m + i, cmu] = -u[ct - nx + i] - x[2 * m + i]


def regression_filter_jacobian(t, x, u, jac, l, ntheta):
    # states   x = [z (n), xi (m), eta (m)], m = n nθ;  inputs u = [tau, q, dq] (n each)
    # outputs  y = [z (n), phi (m)]; rows of dx start at n + m                     (13)
    #   phi^T = l (Phi_M^T(q,dq) - xi) + eta;  dz = l (tau - z);
    #   dxi = l (Phi_M^T(q,dq) - xi);
    #   deta = l (Phi_C^T(q,dq,dq) - Phi_dM^T(q,dq,dq) + Phi_F^T(dq) + Phi_G^T(q) - eta)
    n = u.shape[0] // 3
    m = n * ntheta
    nx = n + 2 * m
    q = u[n:2 * n]
    dq = u[2 * n:3 * n]
    dPM = np.empty((n, ntheta, 2 * n))      # d/(q, a) at a = dq
    dPC = np.empty((n, ntheta, 3 * n))      # d/(q, dq, v) at v = dq
    dPD = np.empty((n, ntheta, 3 * n))      # d/(q, dq, a) at a = dq
    dPF = np.empty((n, ntheta, n))
    dPG = np.empty((n, ntheta, n))
    model.Phi_M_jac(q, dq, dPM)
    model.Phi_C_jac(q, dq, dq, dPC)
    model.Phi_dM_jac(q, dq, dq, dPD)
    model.Phi_F_jac(dq, dPF)
    model.Phi_G_jac(q, dPG)
    rd = n + m
    cq = nx + n
    cdq = nx + 2 * n
    for i in range(n):
        jac[i, i] = 1.0                       # y.z = z
        jac[rd + i, i] = -l                   # dz
        jac[rd + i, nx + i] = l
    for i in range(n):
        for j in range(ntheta):
            k = i * ntheta + j
            jac[n + k, n + k] = -l            # phi
            jac[n + k, n + m + k] = 1.0
            jac[rd + n + k, n + k] = -l       # dxi
            jac[rd + n + m + k, n + m + k] = -l   # deta
            for c in range(n):
                jac[n + k, cq + c] = l * dPM[i, j, c]
                jac[n + k, cdq + c] = l * dPM[i, j, n + c]
                jac[rd + n + k, cq + c] = l * dPM[i, j, c]
                jac[rd + n + k, cdq + c] = l * dPM[i, j, n + c]
                jac[rd + n + m + k, cq + c] = l * (dPC[i, j, c] - dPD[i, j, c] + dPG[i, j, c])
                jac[rd + n + m + k, cdq + c] = l * (
                    dPC[i, j, n + c] + dPC[i, j, 2 * n + c] - dPD[i, j, n + c]
                    - dPD[i, j, 2 * n + c] + dPF[i, j, c])


def instrument_jacobian(t, x, u, jac, l):
    # states   x = zeta (m = n nθ);  inputs u = [q_d, dq_d, ddq_d] (n each);  output zeta
    #   dzeta^T = l (Phi^T(q_d, dq_d, dq_d, ddq_d) - zeta^T)                         (14)
    n = u.shape[0] // 3
    m = x.shape[0]
    nth = m // n
    dP = np.empty((n, nth, 4 * n))          # d/(q, dq, v, dv)
    model.Phi_jac(u[0:n], u[n:2 * n], u[n:2 * n], u[2 * n:3 * n], dP)
    for k in range(m):
        jac[k, k] = 1.0                       # y = zeta
        jac[m + k, k] = -l
    for i in range(n):
        for j in range(nth):
            k = i * nth + j
            for c in range(n):
                jac[m + k, m + c] = l * dP[i, j, c]
                jac[m + k, m + n + c] = l * (dP[i, j, n + c] + dP[i, j, 2 * n + c])
                jac[m + k, m + 2 * n + c] = l * dP[i, j, 3 * n + c]


def tracking_error_jacobian(t, x, u, jac, alpha):
    # inputs   u = [q, dq, q_d, dq_d, ddq_d] (n each);  outputs [e, r, v, dv] (n each)
    #          e = q_d - q, r = de + alpha e, v = dq_d + alpha e, dv = ddq_d + alpha de  (3)-(4)
    n = u.shape[0] // 5
    for i in range(n):
        jac[i, i] = -1.0                       # de/dq
        jac[i, 2 * n + i] = 1.0                # de/dq_d
        jac[n + i, i] = -alpha                 # dr/dq
        jac[n + i, n + i] = -1.0               # dr/ddq
        jac[n + i, 2 * n + i] = alpha          # dr/dq_d
        jac[n + i, 3 * n + i] = 1.0            # dr/ddq_d
        jac[2 * n + i, i] = -alpha             # dv/dq
        jac[2 * n + i, 2 * n + i] = alpha      # dv/dq_d
        jac[2 * n + i, 3 * n + i] = 1.0        # dv/ddq_d
        jac[3 * n + i, n + i] = -alpha         # d(dv)/ddq
        jac[3 * n + i, 3 * n + i] = alpha      # d(dv)/ddq_d
        jac[3 * n + i, 4 * n + i] = 1.0        # d(dv)/dddq_d

