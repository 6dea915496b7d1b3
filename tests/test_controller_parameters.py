"""The sampled controller's parameter vector declared once (ivdrem.controller.parameters)
and the laws' sampled forms declared in the law registry (ivdrem.laws).

* the vector and its inverse: the controller of a vector (``controller_arguments``, what
  ``CController.from_params`` and a controller FMU's start values use) has the same vector,
  bit for bit, for every law with a sampled form, both references, both designs;
* the C library's law codes: every ``IVC_LAW_<NAME>`` the hand-written C core reads is a
  macro of the generated header, whose values are the registry's codes (one source, as the
  FMI Reference FMUs' value references);
* the FMU's parameters: one per table entry, tunable and unit as the table says, a law's
  gain described as the registry declares it;
* a law without a sampled form is refused by the controller naming those that have one; a
  law code is not given twice.
"""
from __future__ import annotations

import dataclasses
import re

import pytest

from ivdrem import laws as registry
from ivdrem.controller.codegen import CORE_SOURCE, generate_controller_sources, law_macro
from ivdrem.controller.parameters import (PARAMETERS, STRUCTURAL, TUNABLE, controller_arguments,
                                          param_layout, param_vector)
from ivdrem.controller.sampled import SAMPLED_LAWS, SampledController
from ivdrem.models import get_model

FOURIER = dict(kind="fourier", omega_f=0.5, a=[[0.1, 0.02], [0.05, 0.0]],
               b=[[0.0, 0.01], [0.03, 0.02]], offset=[0.1, -0.2])
#: designs that set every kind of entry away from its default: the Fourier reference,
#: another mixing, design, gravity, injection, limits, first_zero, delay, block
DESIGNS = {
    "default": {},
    "fourier": dict(trajectory=FOURIER, mixing="channel", design="inertia-scaled",
                    gravity="robot", injection="estimate", tau_max=[30.0, 20.0],
                    tau_rate_max=5e3, first_zero=True, delay=1, block=5, mix_every=4,
                    observer_variant="literal", T=10.0, gamma=3.0, sigma=0.2, epsilon=1e-7,
                    theta_star=[1.0, 0.3, 0.3, 0.4, 1.3], theta_hat0=[0.5] * 5, h=2e-3),
}


@pytest.mark.parametrize("design", sorted(DESIGNS))
@pytest.mark.parametrize("law", SAMPLED_LAWS)
def test_the_controller_of_a_vector_has_that_vector(law, design):
    model = get_model("two-link")
    ctrl = SampledController(model, law, **DESIGNS[design])
    par = param_vector(ctrl)
    assert par.size == sum(size for _, size, _ in param_layout(model))
    kwargs = controller_arguments(model, law, par)
    again = param_vector(SampledController(model, law, **kwargs))
    assert again.tobytes() == par.tobytes()
    if design != "default":     # the inverse read the entries that differ from the defaults
        assert kwargs["trajectory"]["kind"] == "fourier" and kwargs["delay"] == 1
        assert kwargs["observer_variant"] == "literal" and kwargs["mixing"] == "channel"


def test_a_vector_of_another_size_or_law_is_refused():
    model = get_model("two-link")
    par = param_vector(SampledController(model, "drem"))
    with pytest.raises(ValueError, match="law code does not match 'iv-drem'"):
        controller_arguments(model, "iv-drem", par)
    with pytest.raises(ValueError, match=f"{par.size - 1} entries .expected {par.size}"):
        controller_arguments(model, "drem", par[:-1])


def test_the_sampled_laws_are_the_registry_s():
    """SAMPLED_LAWS and the codes come from the registry, codes 0..last without a gap."""
    codes = registry.law_codes()
    assert tuple(codes) == SAMPLED_LAWS == registry.sampled_laws()
    assert sorted(codes.values()) == list(range(len(codes)))
    for name in registry.law_names():
        law = registry.get_law(name)
        assert (law.sampled_code is not None) == (name in SAMPLED_LAWS)


def test_the_c_core_reads_the_generated_law_codes():
    """Every IVC_LAW_ name the hand-written C core uses is defined by the generated header,
    with the registry's code; each law with a sampled form has its macro."""
    header = generate_controller_sources(get_model("two-link"))["ivdrem_controller.h"]
    defined = dict(re.findall(r"#define (IVC_LAW_\w+)\s+(\d+)", header))
    used = set(re.findall(r"\bIVC_LAW_\w+", CORE_SOURCE.read_text()))
    assert used and used <= set(defined), used - set(defined)
    for name, code in registry.law_codes().items():
        assert int(defined[law_macro(name)]) == code
    assert int(defined["IVC_LAW_LAST"]) == max(registry.law_codes().values())


def test_a_law_without_a_sampled_form_is_refused_naming_those_with_one():
    law = dataclasses.replace(registry.get_law("sigma-modification"), name="leak-sampled-none",
                              sampled_code=None)
    registry.register_law(law)
    try:
        with pytest.raises(ValueError, match="'leak-sampled-none' has no sampled form; choose "
                                             "one of iv-drem, composite-learning"):
            SampledController(get_model("two-link"), "leak-sampled-none")
    finally:
        registry.LAWS.pop("leak-sampled-none")


def test_a_law_code_is_not_given_twice():
    law = dataclasses.replace(registry.get_law("none"), name="none-again")
    with pytest.raises(ValueError, match="sampled_code 4 .*'none' has it"):
        registry.register_law(law)
    assert "none-again" not in registry.LAWS


def test_the_fmu_parameters_follow_the_table_and_the_registry():
    """One FMU parameter per entry of the table (the hidden delay apart), tunable and unit
    as it says; a law's gain
    described as the registry declares it (Key.doc, Key.unit)."""
    import xml.etree.ElementTree as ET
    from ivdrem.controller.fmu_export import generate_controller_fmu_sources
    model = get_model("two-link")
    xml = generate_controller_fmu_sources(model, "iv-drem")["modelDescription.xml"]
    pars = {v.get("name"): v for v in ET.fromstring(xml).iter("ScalarVariable")
            if v.get("causality") == "parameter"}
    hidden = {p.name for p in PARAMETERS if p.hidden}
    assert hidden == {"delay"}          # the FMU's delay is its own (one sample), not a parameter
    assert len(pars) == sum(size for name, size, _ in param_layout(model) if name not in hidden)
    for p in PARAMETERS:
        if p.hidden:
            continue
        v = pars[p.name] if p.name in pars else pars[f"{p.name}[0]"]
        assert v.get("variability") == ("tunable" if p.name in TUNABLE else "fixed"), p.name
        unit, doc = p.declared()
        assert v.get("description") == doc, p.name
        real = v.find("Real")
        assert (real.get("unit") or "") == unit, p.name
    for gain in ("T", "p", "F0", "sigma", "epsilon", "theta_star"):   # one doc each
        keys = {registry.get_law(n).keys[gain] for n in SAMPLED_LAWS
                if gain in (registry.get_law(n).keys or {})}
        assert len({(k.unit, k.doc) for k in keys}) == 1, gain
        k = keys.pop()
        assert registry.gain_declaration(gain) == (k.unit, k.doc) and k.doc, gain
    assert pars["T"].find("Real").get("unit") == "s"
    # declared twice, (21) by iv-drem and drem, (35) by composite-learning: both named
    assert pars["gamma"].get("description") == "gain gamma of the composite term (21) or (35)"
    assert {"h", "T", "law", "block", "delay"} <= set(STRUCTURAL)
    assert not set(STRUCTURAL) & set(TUNABLE)


def test_the_c_library_fixes_the_structural_parameters():
    """ivc_set_param refuses a new value of a structural entry (the header's
    IVC_IS_STRUCTURAL, generated from the table) and takes every other entry."""
    from ivdrem.controller.clib import CController, CControllerError
    c = CController(get_model("two-link"), "iv-drem")
    for p in PARAMETERS:
        i = c.index[p.name]
        if p.structural:
            c.set_param(p.name, c.par[i])                    # the same value: nothing changes
            with pytest.raises(CControllerError, match="structural"):
                c.set_param(p.name, c.par[i] + 1.0)
        else:
            c.set_param(p.name, c.par[i])
