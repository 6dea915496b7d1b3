"""Experiments: the paper's (paper.py), their configuration (config.py), metrics, studies."""


def __getattr__(name):  # lazy: `ivdrem.experiments.run_study` without importing Dask up front
    if name == "run_study":
        from .study import run_study
        return run_study
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
