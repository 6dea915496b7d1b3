"""A symbolic model read back from its card (``ivdrem.models.card``) without sympy.

Each test checks the card's model against the model built in sympy (its numbers, its key,
its generated source, its symbolic content), or that a stale or foreign card is never read.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from ivdrem.models import CardModel, get_model, planar_arm, two_link
from ivdrem.models import card as card_module


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("IVDREM_CACHE_DIR", str(tmp_path))
    return tmp_path / "models" / "cards"


def _same_model(read, built):
    assert read.name == built.name and read.n == built.n and read.ntheta == built.ntheta
    assert read.key == built.key
    np.testing.assert_array_equal(read.theta_values, built.theta_values)
    assert read.theta_names == built.theta_names
    assert read.parameter_units == built.parameter_units


def test_the_second_get_model_reads_the_card_and_gives_the_same_model(cache):
    first = get_model("planar-2")
    assert not isinstance(first, CardModel)        # built in sympy, its card written
    assert len(list(cache.glob("*.json"))) == 1
    second = get_model("planar-2")
    assert isinstance(second, CardModel)
    built = planar_arm(2)
    _same_model(second, built)
    assert second.source("") == built.generate_source("")
    # the numeric functions agree with the sympy model's on a random state
    rng = np.random.default_rng(0)
    q, dq, v, dv = (rng.standard_normal(2) for _ in range(4))
    np.testing.assert_array_equal(second.regressor(q, dq, v, dv), built.regressor(q, dq, v, dv))


def test_the_symbolic_content_is_built_on_first_use_and_is_the_models(cache):
    get_model("two-link")
    read = get_model("two-link")
    assert read._symbolic is None                  # nothing symbolic asked for yet
    built = two_link()
    assert read.M == built.M and read.C == built.C and read.Phi_M == built.Phi_M
    assert {str(k): v for k, v in read.constants.items()} == {"g": 9.81}
    assert read._symbolic is not None


def test_a_run_of_a_carded_model_does_not_import_sympy(tmp_path):
    code = ("import sys; from ivdrem.experiments.config import read_config, resolve_config, model_from_config; "
            "m = model_from_config(resolve_config(read_config(overrides={'model.name': 'planar-2'}))[0]); "
            "m.jit_functions; print(type(m).__name__, 'sympy' in sys.modules)")
    env = {**os.environ, "IVDREM_CACHE_DIR": str(tmp_path)}
    outs = [subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                           env=env, timeout=300) for _ in range(2)]
    assert [o.returncode for o in outs] == [0, 0], [o.stderr[-2000:] for o in outs]
    assert outs[0].stdout.split() == ["EulerLagrangeModel", "True"]   # the first builds it
    assert outs[1].stdout.split() == ["CardModel", "False"]


def test_other_options_are_another_card(cache):
    get_model("two-link")
    get_model("two-link", g=9.0)
    assert len(list(cache.glob("*.json"))) == 2
    read = get_model("two-link", g=9.0)
    assert isinstance(read, CardModel)
    _same_model(read, two_link(g=9.0))
    assert read.key != get_model("two-link").key
    # the card of planar-3 is not planar-2's
    get_model("planar-3")
    _same_model(get_model("planar-3"), planar_arm(3))


def test_a_changed_ivdrem_source_never_reads_an_old_card(cache, monkeypatch):
    import ivdrem.compile_cache as sim_cache
    get_model("two-link")
    assert isinstance(get_model("two-link"), CardModel)
    monkeypatch.setattr(sim_cache, "package_digest", lambda: "another ivdrem")
    assert not isinstance(get_model("two-link"), CardModel)   # built again, a card of its own
    assert len(list(cache.glob("*.json"))) == 2


def test_a_damaged_card_is_built_again_and_rewritten(cache):
    get_model("two-link")
    (path,) = cache.glob("*.json")
    good = path.read_text()
    for bad in ("{not json", json.dumps({"recipe": "another model"}),
                good.replace('"ntheta": 5', '"ntheta": 4')):
        path.write_text(bad)
        model = get_model("two-link")
        _same_model(model, two_link())
        if bad.startswith("{not") or "another" in bad:
            assert not isinstance(model, CardModel) and path.read_text() == good


def test_a_card_standing_for_another_model_is_refused_when_used(cache):
    get_model("two-link")
    (path,) = cache.glob("*.json")
    card = json.loads(path.read_text())
    card["key"] = "0" * 64
    path.write_text(json.dumps(card))
    read = get_model("two-link")
    with pytest.raises(RuntimeError, match="does not match the model built from its recipe"):
        read.M


def test_options_that_are_not_plain_values_are_built_every_time(cache):
    th = np.array([1.3, 0.28, 0.32, 0.4, 1.4])
    assert not isinstance(get_model("two-link", theta=th), CardModel)
    assert not isinstance(get_model("two-link", theta=th), CardModel)
    assert not list(cache.glob("*.json"))


def test_bad_options_raise_as_the_sympy_model_does(cache):
    with pytest.raises(TypeError):
        get_model("two-link", friction=True)
    with pytest.raises(ValueError, match="theta_values"):
        get_model("planar-2", theta_values=[1.0])
    assert not list(cache.glob("*.json"))


def test_an_unwritable_cache_still_gives_the_model(cache, monkeypatch):
    import errno

    import ivdrem._atomic

    def full(path, text, *a, **k):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))
    monkeypatch.setattr(ivdrem._atomic, "write_text_atomic", full)
    _same_model(get_model("two-link"), two_link())
    assert not list(cache.glob("*.json"))


def test_two_processes_writing_the_card_at_once_both_succeed(tmp_path):
    code = ("from ivdrem.models import get_model; m = get_model('planar-2'); "
            "print(type(m).__name__, m.key)")
    env = {**os.environ, "IVDREM_CACHE_DIR": str(tmp_path)}
    procs = [subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, env=env, text=True) for _ in range(2)]
    outs = [p.communicate(timeout=300) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], [e for _, e in outs]
    keys = {o.split()[1] for o, _ in outs}
    assert keys == {planar_arm(2).key}
    cards = list((tmp_path / "models" / "cards").glob("*.json"))
    assert len(cards) == 1 and json.loads(cards[0].read_text())["key"] == planar_arm(2).key
    assert not list((tmp_path / "models" / "cards").glob(".*.tmp"))


def test_a_card_model_pickles_with_its_recipe(cache):
    import pickle
    get_model("two-link")
    read = pickle.loads(pickle.dumps(get_model("two-link")))
    assert isinstance(read, CardModel)
    assert read.M == two_link().M


def test_the_card_format_is_part_of_the_recipe():
    assert f'"format": {card_module.CARD_FORMAT}' in card_module._recipe_text("two-link", {})


def test_the_plant_fmu_of_a_card_model_is_the_sympy_models(cache):
    """The FMU export reads the symbolic content (M, C, G, F, constants) through the card;
    its generated files must be the sympy model's, byte for byte."""
    from ivdrem.fmu.export import generate_sources
    get_model("planar-2")
    read = get_model("planar-2")
    assert isinstance(read, CardModel)
    assert generate_sources(read) == generate_sources(planar_arm(2))


def test_the_c_face_of_a_carded_model_is_read_without_sympy(tmp_path):
    """The C face (model.c_source) of a card model comes from the cache by key, without
    building the sympy model, and is the sympy model's text."""
    code = ("import sys, hashlib; from ivdrem.models import get_model; "
            "m = get_model('planar-2'); src = m.c_source('ivc_'); "
            "print(type(m).__name__, 'sympy' in sys.modules, "
            "hashlib.sha256(src.encode()).hexdigest())")
    env = {**os.environ, "IVDREM_CACHE_DIR": str(tmp_path)}
    outs = [subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                           env=env, timeout=300) for _ in range(2)]
    assert [o.returncode for o in outs] == [0, 0], [o.stderr[-2000:] for o in outs]
    first, second = (o.stdout.split() for o in outs)
    assert first[:2] == ["EulerLagrangeModel", "True"]
    assert second[:2] == ["CardModel", "False"]
    assert first[2:] == second[2:]                 # the same text
