"""
The controller FMU around the plant FMU
=======================================

The paper's controller at a fixed step of 1 ms (observer, law, IV-DREM adaptation, μ
saturated at 135), exported as an FMI 2.0 co-simulation FMU from its generated C library,
and closed around the 2-link arm's plant FMU in FMPy: the two components a robot's 1 kHz
loop or another simulation tool would run. The plot shows the joint angles following the
paper's reference, and the estimates θ̂ starting to move towards θ (dashed); the
paper's experiment runs 300 s.
"""
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from ivdrem.controller.fmu_export import export_controller_fmu
from ivdrem.controller.fmu_loop import fmpy_closed_loop
from ivdrem.fmu import export_fmu
from ivdrem.models import two_link

model = two_link()
where = Path(tempfile.mkdtemp())                  # the FMUs go to a scratch folder here
plant = export_fmu(model, where / "Plant.fmu")   # FMI 2.0, model exchange + co-simulation
controller = export_controller_fmu(model, where / "Controller.fmu", law="iv-drem",
                                   mu_max=135.0)
rec = fmpy_closed_loop(controller, plant, 5.0)    # t, q, dq, tau, tau_d, theta_hat
print(f"{rec['t'].size} samples; θ̂(5 s) = {np.round(rec['theta_hat'][-1], 3)}")

fig, axes = plt.subplots(2, 1, sharex=True, figsize=(7, 4.5))
axes[0].plot(rec["t"], rec["q"], label=["$q_1$", "$q_2$"])
axes[0].set_ylabel("q (rad)")
axes[0].legend()
axes[1].plot(rec["t"], rec["theta_hat"], label=[rf"$\hat\theta_{j + 1}$" for j in range(5)])
axes[1].hlines(model.theta_values, 0, rec["t"][-1], colors="0.6", linestyles="dashed")
axes[1].set_ylabel(r"$\hat\theta$")
axes[1].legend(loc="center", ncol=5, fontsize="small")
axes[1].set_xlabel("t (s)")
fig.tight_layout()
plt.show()  # a window where there is a display (nothing with MPLBACKEND=Agg)
