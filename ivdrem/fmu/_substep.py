"""The plant FMU's default co-simulation sub-step, in a module of its own: the command
line's parser shows it as ``--substep``'s default, and reading it must not import SymPy
(the exporter's), so that ``ivdrem fmu export`` refuses a bad file or option at once."""

#: Default bound of the co-simulation RK4 sub-step (parameter ``cs_substep``), seconds.
DEFAULT_SUBSTEP = 1e-3
