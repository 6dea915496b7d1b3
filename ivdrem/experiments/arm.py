"""The real-arm experiment's design under its old name: :mod:`ivdrem.diagrams.arm_reference`.

The design lives below the diagrams (``closed_loop`` designs the reference of an arm other
than the paper's); ``ivdrem.experiments.arm`` stays importable as the same module object,
so that a name set on one (a test's monkeypatch) is set on both.
"""
import sys

from ..diagrams import arm_reference

sys.modules[__name__] = arm_reference
