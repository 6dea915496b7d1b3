"""
A real arm from its URDF file: the UR5's holding torques
========================================================

``ivdrem.models.arm("ur5")`` reads the UR5's URDF file (from example-robot-data, the
``arms`` extra) into a model in base parameters: ivdrem's own recursive Newton-Euler
regressor Φ, with θ grouped by pivoted QR. ``ivdrem.models.from_urdf("my_arm.urdf")``
does the same for your own file. Here the torque that holds the arm still,
G(q) = Φ(q, 0, 0, 0) θ, is evaluated as the shoulder sweeps, and checked against
Pinocchio's ``computeGeneralizedGravity`` on the same URDF file.
"""
import matplotlib.pyplot as plt
import numpy as np
import pinocchio as pin

from ivdrem.models import arm

ur5 = arm("ur5")
print(f"{ur5.name}: {ur5.n} joints, {ur5.ntheta} base parameters")
print("\n".join(ur5.parameter_table_text().splitlines()[:4]))

shoulder = np.linspace(-np.pi, 0.0, 61)
q = np.zeros((shoulder.size, ur5.n))
q[:, 1] = shoulder                                    # joint 2, the shoulder lift
q[:, 2] = 0.5                                         # the elbow a little bent
zero = np.zeros(ur5.n)
holding = np.array([ur5.inverse_dynamics(qi, zero, zero) for qi in q])   # G(q), N·m

pin_model = ur5.pinocchio_model()
pin_data = pin_model.createData()
reference = np.array([pin.computeGeneralizedGravity(pin_model, pin_data,
                                                    ur5.pinocchio_configuration(qi))
                      for qi in q])
print(f"largest difference from Pinocchio: {np.max(np.abs(holding - reference)):.1e} N·m")

fig, ax = plt.subplots(figsize=(7, 3.5))
for j in range(3):
    ax.plot(np.degrees(shoulder), holding[:, j], label=f"joint {j + 1}")
ax.set_xlabel("shoulder angle q₂ (deg)")
ax.set_ylabel("holding torque G(q) (N·m)")
ax.set_title("UR5: torque that holds the arm, ivdrem's regressor (= Pinocchio)")
ax.legend()
fig.tight_layout()
plt.show()  # a window where there is a display (nothing with MPLBACKEND=Agg)
