"""
A python-control diagram on ivdrem's simulator
==============================================

A python-control user's diagram, written with python-control only: a nonlinear pendulum
(``ct.nlsys``), a PI controller (``ct.tf``) and a summing junction, wired by name with
``ct.interconnect``. ``ivdrem.pycontrol.input_output_response`` takes the same arguments as
``ct.input_output_response`` and returns the same ``TimeResponseData``; both are run and
compared.
"""
import control as ct
import matplotlib.pyplot as plt
import numpy as np

import ivdrem.pycontrol


def pendulum_rhs(t, x, u, params):
    # states x = (angle, rate); input u = torque; g/l = 9.81, damping 0.5
    return [x[1], -9.81 * np.sin(x[0]) - 0.5 * x[1] + u[0]]


pendulum = ct.nlsys(pendulum_rhs, None, inputs="tau", outputs=["phi", "omega"],
                    states=["phi", "omega"], name="pendulum")
pi = ct.tf([20.0, 30.0], [1.0, 0.0], inputs="e", outputs="tau", name="pi")   # 20 + 30/s
error = ct.summing_junction(inputs=["r", "-phi"], output="e", name="error")
loop = ct.interconnect([pendulum, pi, error], inplist="r", outlist=["phi", "omega", "tau"],
                       name="loop")

T = np.linspace(0.0, 5.0, 501)
r = np.where(T >= 0.5, 0.8, 0.0)                      # a step of the reference angle
tight = {"rtol": 1e-8, "atol": 1e-10}               # both simulators to 1e-8
theirs = ct.input_output_response(loop, T, r, solve_ivp_kwargs=tight)   # python-control's
ours = ivdrem.pycontrol.input_output_response(loop, T, r, solve_ivp_kwargs=tight)  # ivdrem's
print(f"largest difference in φ: {np.max(np.abs(ours.outputs[0] - theirs.outputs[0])):.2e} rad")

fig, ax = plt.subplots(figsize=(7, 3.5))
ax.plot(T, r, "k:", label="reference")
ax.plot(theirs.time, theirs.outputs[0], lw=3, alpha=0.4, label="ct.input_output_response")
ax.plot(ours.time, ours.outputs[0], label="ivdrem.pycontrol.input_output_response")
ax.set_xlabel("t (s)")
ax.set_ylabel("φ (rad)")
ax.legend()
fig.tight_layout()
plt.show()  # a window where there is a display (nothing with MPLBACKEND=Agg)
