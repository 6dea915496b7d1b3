"""ivdrem's runs use one BLAS thread; outside them the user's setting is untouched."""
from threadpoolctl import threadpool_info

from ivdrem._threads import one_blas_thread


def _blas_threads():
    return [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]


def test_one_blas_thread_inside_and_restored_after():
    import numpy as np
    np.linalg.svd(np.eye(3))              # loads numpy's BLAS
    import scipy.linalg                   # and scipy's, which numba's LAPACK calls use
    scipy.linalg.svd(np.eye(3))
    before = _blas_threads()
    assert before
    with one_blas_thread():
        assert set(_blas_threads()) == {1}
    assert _blas_threads() == before


def test_the_command_line_runs_inside_the_limit(monkeypatch):
    import ivdrem.cli as cli
    seen = []
    monkeypatch.setattr(cli, "_main", lambda argv=None: seen.append(set(_blas_threads())) or 0)
    assert cli.main(["paper"]) == 0
    assert seen == [{1}]
