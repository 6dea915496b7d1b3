"""The Jacobian program's builder helpers against their definitions, element by element
(ivdrem.sim.jacobian: the column-by-column row sets and each slot's first multiply-add that
the builder takes in one pass over numpy arrays)."""
import numpy as np
import pytest

from ivdrem.sim.jacobian import _first_terms, _rows_of_columns


@pytest.mark.parametrize("shape, density, seed", [((7, 11), 0.3, 0), ((40, 3), 0.05, 1),
                                                  ((1, 50), 0.5, 2), ((30, 30), 0.0, 3),
                                                  ((25, 60), 1.0, 4)])
def test_rows_of_columns_is_the_column_by_column_definition(shape, density, seed):
    sub = np.random.default_rng(seed).random(shape) < density
    lo = 13
    want = {c: set((lo + np.flatnonzero(sub[:, c])).tolist())
            for c in range(shape[1]) if sub[:, c].any()}
    got = _rows_of_columns(sub, lo)
    assert got == want and list(got) == list(want)        # the same columns, in order


@pytest.mark.parametrize("seed", range(4))
def test_first_terms_is_each_slots_first_occurrence(seed):
    rng = np.random.default_rng(seed)
    n_slots = 50
    dst = rng.integers(0, n_slots - 5, size=300)            # the last slots never reached
    first, unreached = _first_terms(dst, n_slots)
    seen, want = set(), []
    for d in dst.tolist():
        want.append(d not in seen)
        seen.add(d)
    assert first.tolist() == want
    assert unreached.dtype == np.int64
    assert unreached.tolist() == sorted(set(range(n_slots)) - seen)
    assert _first_terms(np.zeros(0, dtype=np.int64), 3)[1].tolist() == [0, 1, 2]
