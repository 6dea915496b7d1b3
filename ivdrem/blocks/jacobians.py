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


def mixing_jacobian(t, x, u, jac, ntheta):
    # inputs   u = [Y (nθ), Psi (nθ*nθ row-major)];  outputs y = [Delta, calY (nθ)]
    # With s = 1 + ||Psi||_F, P = Psi/s, A = adj(P), Delta = det P, calY = A Y / s (eq. 17):
    #   dDelta/dPsi_kl = A_lk / s - nθ Delta g_kl / s             (d det = tr(A dP))
    #   dcalY/dY       = A / s
    #   dcalY/dPsi_kl  = (A'[E_kl] Y) / s^2 - nθ (A Y) g_kl / s^2   (adj homogeneous, degree nθ-1)
    # g_kl = ds/dPsi_kl = Psi_kl / ||Psi||_F (0 at Psi = 0), and A'[E] the derivative of the
    # adjugate in the direction E, from the Faddeev-LeVerrier recursion differentiated
    # (a polynomial identity, exact for singular P too: Psi is singular at every start).
    n = ntheta
    nn = n * n
    big = 0.0
    for k in range(nn):
        big = max(big, abs(u[n + k]))
    ss = 0.0
    if big > 0.0:
        for k in range(nn):
            r = u[n + k] / big
            ss += r * r
    nrm = big * math.sqrt(ss)
    s = 1.0 + nrm
    P = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            P[i, j] = u[n + i * n + j] / s
    # Faddeev-LeVerrier: M_1 = I, M_{k+1} = P M_k - tr(P M_k)/k I; adj(P) = (-1)^(n+1) M_n
    Ms = np.zeros((n + 1, n, n))
    for i in range(n):
        Ms[1, i, i] = 1.0
    AM = np.empty((n, n))
    c = 0.0
    for k in range(1, n + 1):
        tr = 0.0
        for i in range(n):
            for j in range(n):
                acc = 0.0
                for l in range(n):
                    acc += P[i, l] * Ms[k, l, j]
                AM[i, j] = acc
            tr += AM[i, i]
        c = -tr / k
        if k < n:
            for i in range(n):
                for j in range(n):
                    Ms[k + 1, i, j] = AM[i, j]
                Ms[k + 1, i, i] += c
    sign = 1.0 if n % 2 == 1 else -1.0
    det = -sign * c
    A = np.empty((n, n))
    AY = np.empty(n)
    for i in range(n):
        acc = 0.0
        for j in range(n):
            A[i, j] = sign * Ms[n, i, j]
            acc += A[i, j] * u[j]
        AY[i] = acc
    inv_s = 1.0 / s
    inv_s2 = inv_s * inv_s
    for i in range(n):                     # dcalY / dY
        for j in range(n):
            jac[1 + i, j] = A[i, j] * inv_s
    dM = np.empty((n, n))
    dAM = np.empty((n, n))
    for a in range(n):
        for b in range(n):
            col = n + a * n + b
            g = u[col] / nrm if nrm > 0.0 else 0.0
            jac[0, col] = A[b, a] * inv_s - n * det * g * inv_s
            # dM_1 = 0; dM_{k+1} = E_ab M_k + P dM_k - tr(.)/k I; A'[E_ab] = sign dM_n
            for i in range(n):
                for j in range(n):
                    dM[i, j] = 0.0
            for k in range(1, n):
                tr = 0.0
                for i in range(n):
                    for j in range(n):
                        acc = 0.0
                        if k > 1:
                            for l in range(n):
                                acc += P[i, l] * dM[l, j]
                        if i == a:
                            acc += Ms[k, b, j]
                        dAM[i, j] = acc
                    tr += dAM[i, i]
                dc = -tr / k
                for i in range(n):
                    for j in range(n):
                        dM[i, j] = dAM[i, j]
                    dM[i, i] += dc
            for i in range(n):
                acc = 0.0
                for j in range(n):
                    acc += dM[i, j] * u[j]
                jac[1 + i, col] = (sign * acc - n * AY[i] * g) * inv_s2


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
    # inputs   u = [Delta, calY (nθ), theta_hat (nθ)]
    # output   theta_c_i = gamma Delta (calY_i - Delta theta_hat_i)                  (eq. 21)
    nth = jac.shape[0]                     # rows: the nθ outputs (no states)
    D = u[0]
    for i in range(nth):
        jac[i, 0] = gamma * (u[1 + i] - 2.0 * D * u[1 + nth + i])
        jac[i, 1 + i] = gamma * D
        jac[i, 1 + nth + i] = -gamma * D * D


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
