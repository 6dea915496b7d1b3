"""Robot models in sympy: the paper's 2-link arm and an n-link planar arm (by name:
:func:`ivdrem.models.get_model`, in :mod:`ivdrem.models.registry`)."""
from __future__ import annotations

import numpy as np
import sympy as sp

from .euler_lagrange import EulerLagrangeModel

__all__ = ["two_link", "planar_arm", "planar_physical_theta", "TWO_LINK_THETA"]

#: The paper's parameter values (Section 4).
TWO_LINK_THETA = (1.3, 0.28, 0.32, 0.4, 1.4)


def two_link(theta=None, g=9.81):
    """The paper's 2-link manipulator (Section 4).

    ``M = [[θ1 + 2θ2 c2, θ3 + θ2 c2], [θ3 + θ2 c2, θ3]]``, potential
    ``P = θ4 g sin(q1+q2) + θ5 g sin(q1)`` so ``G = [θ4 g c12 + θ5 g c1, θ4 g c12]``, ``F = 0``;
    ``C`` from Christoffel symbols equals the paper's
    ``[[-θ2 s2 q̇2, -θ2 s2 (q̇1+q̇2)], [θ2 s2 q̇1, 0]]``.
    ``theta`` defaults to the paper's ``[1.3, 0.28, 0.32, 0.4, 1.4]``.
    """
    q1, q2 = sp.symbols("q1 q2")
    dq1, dq2 = sp.symbols("dq1 dq2")
    th = sp.symbols("theta1:6")
    gs = sp.Symbol("g")
    c2 = sp.cos(q2)
    M = sp.Matrix([[th[0] + 2 * th[1] * c2, th[2] + th[1] * c2],
                   [th[2] + th[1] * c2, th[2]]])
    P = th[3] * gs * sp.sin(q1 + q2) + th[4] * gs * sp.sin(q1)
    return EulerLagrangeModel(
        "two-link", [q1, q2], list(th), M, potential=P, dq=[dq1, dq2],
        constants={gs: float(g)},
        theta_values=TWO_LINK_THETA if theta is None else theta,
        theta_names=[f"theta{i}" for i in range(1, 6)],
        # M entries (theta1..3) are inertias, theta4,5 multiply g in G: first moments
        parameter_units={"theta1": "kg.m2", "theta2": "kg.m2", "theta3": "kg.m2",
                         "theta4": "kg.m", "theta5": "kg.m", "g": "m/s2"})


def _planar_energies(n, dq, q, m, h, J, l, g):
    """Kinetic and potential energy of an n-link planar arm (gravity along -y).

    Link i: mass m_i, first moment h_i = m_i c_i, inertia about its joint
    J_i = I_i + m_i c_i^2 (c_i: joint -> centre of mass distance on the link axis),
    absolute angle phi_i = q_1 + ... + q_i.  With v_Ji the velocity of joint i and
    e_i^perp = (-sin phi_i, cos phi_i):
    T_i = m_i |v_Ji|^2 / 2 + h_i dphi_i (v_Ji . e_i^perp) + J_i dphi_i^2 / 2,
    P_i = m_i g y_Ji + h_i g sin phi_i.
    """
    def rel(j, k):  # phi_k - phi_j for j < k
        return sum(q[j + 1:k + 1], sp.Integer(0))

    dphi = [sum(dq[:i + 1], sp.Integer(0)) for i in range(n)]
    phi = [sum(q[:i + 1], sp.Integer(0)) for i in range(n)]
    T = sp.Integer(0)
    P = sp.Integer(0)
    for i in range(n):
        vJ2 = sp.Integer(0)
        for j in range(i):
            for k in range(i):
                c = sp.cos(rel(min(j, k), max(j, k))) if j != k else 1
                vJ2 += l[j] * l[k] * dphi[j] * dphi[k] * c
        vJe = sum((l[j] * dphi[j] * sp.cos(rel(j, i)) for j in range(i)), sp.Integer(0))
        yJ = sum((l[j] * sp.sin(phi[j]) for j in range(i)), sp.Integer(0))
        T += m[i] * vJ2 / 2 + h[i] * dphi[i] * vJe + J[i] * dphi[i] ** 2 / 2
        P += m[i] * g * yJ + h[i] * g * sp.sin(phi[i])
    return sp.expand(T), sp.expand(P)


def planar_physical_theta(masses, lengths, com=None, inertia=None, friction=None,
                          parameters="base"):
    """Parameter vector of :func:`planar_arm` from physical link data.

    ``masses[i]``, ``lengths[i]``, ``com[i]`` (joint -> centre of mass distance, default
    ``l_i/2``), ``inertia[i]`` (about the centre of mass, default uniform rod ``m l^2/12``),
    ``friction[i]`` (viscous coefficient, appended if given).  ``parameters="full"`` gives
    ``(m_i, m_i c_i, I_i + m_i c_i^2)`` per link; ``"base"`` gives the identifiable
    regrouped ``(H_i, J_i)`` with ``H_i = m_i c_i + l_i sum_{k>i} m_k`` and
    ``J_i = I_i + m_i c_i^2 + l_i^2 sum_{k>i} m_k``.
    """
    m = np.asarray(masses, float)
    l = np.asarray(lengths, float)
    n = m.size
    c = l / 2 if com is None else np.asarray(com, float)
    I = m * l ** 2 / 12 if inertia is None else np.asarray(inertia, float)
    h = m * c
    J = I + m * c ** 2
    if parameters == "full":
        th = np.column_stack([m, h, J]).reshape(-1)
    elif parameters == "base":
        tail = np.array([m[i + 1:].sum() for i in range(n)])
        th = np.column_stack([h + l * tail, J + l ** 2 * tail]).reshape(-1)
    else:
        raise ValueError(f"parameters must be 'base' or 'full', got {parameters!r}")
    if friction is not None:
        th = np.concatenate([th, np.asarray(friction, float).reshape(-1)])
    return th


def planar_arm(n, lengths=None, g=9.81, friction=False, theta_values=None, *,
               parameters="base", masses=None):
    """An n-link planar revolute arm in a vertical plane (gravity along -y).

    Joint angles are relative (``q_i`` is the angle of link i w.r.t. link i-1; ``q = 0`` is
    the arm stretched along +x), link lengths are known constants.  Per link i the dynamics
    are linear in ``π_i = (m_i, m_i c_i, I_i + m_i c_i²)``.  ``M`` is derived symbolically
    as the Hessian of the kinetic energy w.r.t. ``q̇`` and ``G`` from the potential.

    ``parameters="base"`` (default): ``θ = (h_1, J_1, ..., h_n, J_n)`` with the masses
    regrouped into the preceding links (``h_i = m_i c_i + l_i Σ_{k>i} m_k``,
    ``J_i = I_i + m_i c_i² + l_i² Σ_{k>i} m_k``).  These 2n parameters are identifiable;
    the m_i are not (m_1 does not appear at all and m_{i+1} only through those sums), so the
    full set gives a rank-deficient regressor and DREM's Δ ≡ 0.
    ``parameters="full"``: ``θ = (m_1, h_1, J_1, ..., m_n, h_n, J_n)``, literally π_i.
    ``friction=True`` appends viscous coefficients ``f_i`` (``F_i = f_i q̇_i``).

    Defaults: lengths 1 m, uniform rods of ``masses`` (default 2 kg each), viscous friction
    0.1 N m s/rad; ``theta_values`` overrides the computed parameter vector.
    """
    try:
        n_int = int(n)
    except (TypeError, ValueError):
        raise ValueError(f"n must be a positive integer, got {n!r}") from None
    if n_int != n or n_int < 1:
        raise ValueError(f"n must be a positive integer, got {n!r}")
    n = n_int
    if parameters not in ("base", "full"):
        raise ValueError(f"parameters must be 'base' or 'full', got {parameters!r}")
    lengths = np.full(n, 1.0) if lengths is None else np.asarray(lengths, float).reshape(-1)
    if lengths.shape != (n,) or not np.all(np.isfinite(lengths)) or np.any(lengths <= 0):
        raise ValueError(f"lengths must be {n} positive finite numbers, got {lengths}")
    masses = np.full(n, 2.0) if masses is None else np.asarray(masses, float).reshape(-1)
    if masses.shape != (n,):
        raise ValueError(f"masses must have length {n}, got {masses.size}")

    q = list(sp.symbols(f"q1:{n + 1}"))
    dq = list(sp.symbols(f"dq1:{n + 1}"))
    ls = list(sp.symbols(f"l1:{n + 1}"))
    gs = sp.Symbol("g")
    ms = list(sp.symbols(f"m1:{n + 1}"))
    hs = list(sp.symbols(f"h1:{n + 1}"))
    Js = list(sp.symbols(f"J1:{n + 1}"))
    if parameters == "full":
        theta = [s for i in range(n) for s in (ms[i], hs[i], Js[i])]
        m_used = ms
    else:
        theta = [s for i in range(n) for s in (hs[i], Js[i])]
        m_used = [sp.Integer(0)] * n
    T, P = _planar_energies(n, dq, q, m_used, hs, Js, ls, gs)
    # M = Hessian of the kinetic energy (a quadratic form in dq), read off its coefficients
    M = sp.zeros(n, n)
    for monom, coeff in sp.Poly(T, *dq).terms():
        idx = [i for i, e in enumerate(monom) for _ in range(e)]
        if len(idx) != 2:  # pragma: no cover - T is a quadratic form in dq
            raise AssertionError("kinetic energy is not a quadratic form in dq")
        i, j = idx
        if i == j:
            M[i, i] += 2 * coeff
        else:
            M[i, j] += coeff
            M[j, i] += coeff
    M = M.applyfunc(sp.expand)
    F = None
    fric = None
    if friction:
        fs = list(sp.symbols(f"f1:{n + 1}"))
        theta += fs
        F = sp.Matrix([fs[i] * dq[i] for i in range(n)])
        fric = np.full(n, 0.1)
    if theta_values is None:
        theta_values = planar_physical_theta(masses, lengths, friction=fric, parameters=parameters)
    constants = {gs: float(g)}
    constants.update({ls[i]: float(lengths[i]) for i in range(n)})
    kinds = {"m": "kg", "h": "kg.m", "J": "kg.m2", "f": "N.m.s/rad"}
    units = {str(s): kinds[str(s)[0]] for s in theta}
    units.update({str(s): "m" for s in ls}, g="m/s2")
    return EulerLagrangeModel(f"planar-{n}", q, theta, M, potential=P, F=F, dq=dq,
                              constants=constants, theta_values=theta_values,
                              theta_names=[str(s) for s in theta], parameter_units=units)
