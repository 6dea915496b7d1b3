"""Plants other than ivdrem's own model for the sampled controller (docs/mujoco.md).

* :mod:`ivdrem.plants.mujoco`: the arm as a MuJoCo model (a URDF, a named arm, or the paper's
  2-link and the planar arms written as MJCF), checked at load against ivdrem's model of
  the same arm, and the sampled controller closed around it (extra ``mujoco``);
* :mod:`ivdrem.plants.sensing`: a real robot's sensors and actuator limits between the
  plant and the controller (encoder quantization, velocity by a filtered difference or
  with noise, a measurement delay, torque saturation and rate limit), each an option, off
  by default, seeded.

Nothing here imports MuJoCo until a MuJoCo plant is asked for.
"""
