"""A law registered with a gain of its own (``kappa``), as a new built-in law would be: with
no edit of a file of the package, it runs in a study over its gain, and, registered with a
sampled form, in the sampled controller, its C library and its controller FMU.

(tests/test_experiment.py runs the same law from ``closed_loop`` and from a configuration.)

* a study: ``run_study`` over a grid of ``leak_kappa.kappa`` (2 short runs, on a Dask
  cluster in this process, which knows the law); the table has the gain's column, and each
  run's θ̂(t_end) and step count are those of the same run from ``closed_loop`` with the
  gain given by hand, bit for bit;
* a sampled form: the C step exists only for the built-in laws, so the test law runs the
  step of σ-modification (``sampled_as``), whose code it gets; its gain rides in the
  controller's parameter table (made from the registry when read), the generated header
  (``IVC_P_KAPPA``), the C library's parameter vector (read back from C) and the FMU's
  variables, each as the registry declares it, and is read by no step: the controller runs
  σ-modification's step, bit for bit the Python reference of that law, the C library equal
  to it to 1e-12.  Once the law is removed, its gain is gone from the table.
"""
from __future__ import annotations

import ctypes
import re
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from ivdrem import blocks as block_library
from ivdrem import laws as registry
from ivdrem.diagrams import closed_loop
from ivdrem.experiments import run_study
from ivdrem.experiments.experiment import Experiment
from ivdrem.models import get_model
from ivdrem.sim import simulate

NAME, SECTION = "leak-kappa", "leak_kappa"
KAPPA = registry.Key("float", **registry.in_range(0, 1e6, open_lo=True), unit="1/s",
                     doc="leak rate kappa of the test law (1/s)")


def _leak_law(**entry):
    """ϑ_c = κ(θ* − θ̂), θ* the model's θ: a gain no built-in law has."""
    def build(ctx):
        return [block_library.sigma_modification_term(
            ctx.ntheta, ctx.params["kappa"], ctx.model.theta_values)], []
    return registry.Law(NAME, build, "leak with kappa", "#135790", section=SECTION,
                        defaults={"kappa": 0.25}, keys={"kappa": KAPPA}, **entry)


@pytest.fixture
def registered(request):
    """Register the test law (with the entries the test's parameter gives) for one test."""
    law = registry.register_law(_leak_law(**getattr(request, "param", {})))
    try:
        yield law
    finally:
        registry.LAWS.pop(NAME, None)


def _theta_hat_end(response):
    labels = list(response.output_labels)
    rows = [i for i, s in enumerate(labels) if re.fullmatch(r"theta_hat\[\d+\]", s)]
    return np.asarray(response.outputs)[rows, -1]


# ----------------------------------------------------------------------------- a study
def test_a_study_over_its_gain_equals_closed_loop_run_by_run(registered, tmp_path):
    from dask.distributed import LocalCluster
    grid = [0.5, 2.0]
    study = {"experiment": {"t_end": 0.2, "laws": [NAME]},
             "study": {"grid": {f"{SECTION}.kappa": grid}}}
    # worker threads of this process: they see the law this test registered (a built-in
    # law is registered in every worker process by importing ivdrem.laws)
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                      dashboard_address=None) as cluster:
        result = run_study(study, tmp_path / "study", scheduler=cluster.scheduler_address,
                           progress=False)
    table = result.results
    assert list(table[f"{SECTION}.kappa"]) == grid
    assert list(table["law"]) == [NAME, NAME] and list(table["status"]) == ["ok", "ok"]
    ends = []
    for run, (_, row) in zip(result.runs, table.iterrows()):
        kappa = row[f"{SECTION}.kappa"]
        setup = Experiment.from_config(run.config).law(NAME)
        assert setup.gains == {"kappa": kappa}
        by_hand = simulate(closed_loop(NAME, gains={"kappa": kappa}), 0.2,
                           dt_out=float(run.config["experiment"]["dt_out"]), progress=False,
                           **setup.solver)
        end = _theta_hat_end(by_hand)
        study_end = np.array([row[f"theta_hat[{i}]"] for i in range(end.size)])
        assert study_end.tobytes() == end.tobytes(), (kappa, study_end, end)
        assert row["steps"] == by_hand.stats["steps"]
        ends.append(end)
    assert not np.array_equal(ends[0], ends[1])       # the gain reached the runs


# ----------------------------------------------------------------------------- a sampled form
SIGMA = "sigma-modification"


def _run(ctrl, steps=200):
    """τ_k and θ̂ of `ctrl` on a measured motion q = 0.3 sin(2t + i), its derivative."""
    taus = []
    for k in range(steps):
        t = k * ctrl.h
        q = 0.3 * np.sin(2.0 * t + np.arange(ctrl.n))
        dq = 0.6 * np.cos(2.0 * t + np.arange(ctrl.n))
        taus.append(ctrl.step(t, q, dq))
    return np.array(taus), np.asarray(ctrl.theta_hat)


@pytest.mark.parametrize("registered", [{"sampled_as": SIGMA}], indirect=True)
def test_a_sampled_form_is_derived_without_an_edit_of_the_controller(registered):
    from ivdrem.controller.clib import CController
    from ivdrem.controller.codegen import generate_controller_sources, law_macro
    from ivdrem.controller.fmu_export import generate_controller_fmu_sources
    from ivdrem.controller.parameters import (PARAMETERS, STRUCTURAL, TUNABLE,
                                              controller_arguments, param_layout,
                                              param_vector)
    from ivdrem.controller.sampled import SampledController
    model = get_model("two-link")
    # the registry: the law has the code of the step it runs
    assert NAME in registry.sampled_laws() and registry.sampled_step(NAME) == SIGMA
    assert registry.law_codes()[NAME] == registry.get_law(SIGMA).sampled_code
    # the table: an entry per numeric gain the registry's laws with a sampled form declare,
    # read from the registry (not a list of names), this law's kappa among them
    declared = {k for n in registry.sampled_laws() for k in registry.get_law(n).defaults
                if registry.get_law(n).keys[k].kind in registry.NUMERIC_KINDS}
    names = [p.name for p in PARAMETERS]
    assert "kappa" in declared and declared <= set(names)
    kappa = PARAMETERS[names.index("kappa")]
    assert kappa.size == "1" and kappa.declared() == (KAPPA.unit, KAPPA.doc)
    assert "kappa" in TUNABLE and "kappa" not in STRUCTURAL
    # the Python reference: kappa in its vector and back
    ref = SampledController(model, NAME, kappa=0.5)
    at = dict(zip(names, np.cumsum([0] + [s for _, s, _ in param_layout(model)])))
    par = param_vector(ref)
    assert par[at["kappa"]] == 0.5 and ref.gains["kappa"] == 0.5
    assert controller_arguments(model, NAME, par)["kappa"] == 0.5
    assert SampledController(model, NAME).gains["kappa"] == 0.25       # the law's default
    with pytest.raises(ValueError, match=r"kappa must be > 0"):
        SampledController(model, NAME, kappa=-1.0)
    with pytest.raises(TypeError, match=r"unexpected keyword argument\(s\) 'kapa'; the "
                                        r"gains of the laws with a sampled form: .*kappa"):
        SampledController(model, NAME, kapa=0.5)
    # the generated header: kappa's index, the law's macro at the step's code
    header = generate_controller_sources(model)["ivdrem_controller.h"]
    idx = dict(re.findall(r"#define IVC_P_(\w+)\s+(\d+)", header))
    assert int(idx["KAPPA"]) == at["kappa"] and f"[1] {KAPPA.doc}" in header
    macros = dict(re.findall(r"#define (IVC_LAW_\w+)\s+(\d+)", header))
    assert macros[law_macro(NAME)] == macros[law_macro(SIGMA)]
    # the controller FMU's variables: kappa, tunable, as the registry declares it
    xml = generate_controller_fmu_sources(model, NAME, kappa=0.5)["modelDescription.xml"]
    var = next(v for v in ET.fromstring(xml).iter("ScalarVariable") if v.get("name") == "kappa")
    assert (var.get("causality"), var.get("variability")) == ("parameter", "tunable")
    assert var.get("description") == KAPPA.doc and float(var.find("Real").get("start")) == 0.5
    # its unit, 1/s, in the FMU's unit definitions as FMI's base units
    assert var.find("Real").get("unit") == "1/s"
    unit = next(u for u in ET.fromstring(xml).iter("Unit") if u.get("name") == "1/s")
    assert unit.find("BaseUnit").attrib == {"s": "-1"}
    # a configuration that sets the gain: the design `fmu export --controller --config`
    # exports takes it, through the Experiment
    from ivdrem.controller.fmu_export import controller_design
    from ivdrem.experiments.config import read_config
    design = controller_design(Experiment.from_config(read_config(overrides={
        "experiment.laws": [NAME], f"{SECTION}.kappa": 0.5})), NAME)
    assert design["kappa"] == 0.5
    # the C library: its parameter vector holds kappa (read back from C), and it runs the
    # step of sigma-modification, as the Python reference does
    c = CController(model, NAME, kappa=0.5)
    get = c.lib.ivc_get_param
    get.restype, get.argtypes = ctypes.c_double, [ctypes.c_void_p, ctypes.c_int]
    assert c.index["kappa"] == at["kappa"] and get(c._c, c.index["kappa"]) == 0.5
    tau_c, th_c = _run(c)
    tau_py, th_py = _run(SampledController(model, NAME, kappa=0.5))
    tau_sigma, th_sigma = _run(SampledController(model, SIGMA))
    assert tau_py.tobytes() == tau_sigma.tobytes() and th_py.tobytes() == th_sigma.tobytes()
    scale = np.abs(tau_py).max()
    assert np.abs(tau_c - tau_py).max() <= 1e-12 * scale
    assert np.abs(th_c - th_py).max() <= 1e-12 * np.abs(th_py).max()
    assert np.abs(th_py).max() > 0                 # the law acted
    # kappa read by no step: another value, the same run
    tau_other, _ = _run(SampledController(model, NAME, kappa=7.0))
    assert tau_other.tobytes() == tau_py.tobytes()
    # gone with the law: the table follows the registry
    registry.LAWS.pop(NAME)
    assert "kappa" not in [p.name for p in PARAMETERS]
    assert "IVC_P_KAPPA" not in generate_controller_sources(model)["ivdrem_controller.h"]


@pytest.mark.parametrize("entry, message", [
    ({"sampled_as": "no-such-law"}, "must name a registered law with a sampled step"),
    ({"sampled_as": SIGMA, "sampled_code": 9}, "then the law has no sampled_code"),
])
def test_a_shared_step_names_a_law_with_a_step_of_its_own(entry, message):
    with pytest.raises(ValueError, match=message):
        registry.register_law(_leak_law(**entry))
    assert NAME not in registry.LAWS


def test_a_sampled_law_declares_every_gain():
    """A law with a sampled form whose gain has no Key (no unit, doc or size) is refused
    by the table's derivation, naming the gain."""
    law = registry.Law("no-key", _leak_law().build, "no key", "#246802", section="no_key",
                       defaults={"rho": 1.0}, keys={}, sampled_as=SIGMA)
    registry.register_law(law)
    try:
        with pytest.raises(ValueError, match="law 'no-key' has a sampled form but does not "
                                             "declare its gain 'rho'"):
            registry.sampled_gains()
    finally:
        registry.LAWS.pop("no-key")


@pytest.mark.parametrize("unit, base", [("1/s", {"s": "-1"}), ("rad/s", {"s": "-1", "rad": "1"}),
                                        ("N.m", {"kg": "1", "m": "2", "s": "-2"}),
                                        ("kg.m^2", {"kg": "1", "m": "2"}),
                                        ("N.m.s/rad", {"kg": "1", "m": "2", "s": "-1",
                                                       "rad": "-1"})])
def test_a_gain_unit_becomes_fmi_base_units(unit, base):
    """A gain's unit, as its Key declares it, in FMI's BaseUnit exponents (N = kg m s^-2)."""
    attrs = dict(re.findall(r'(\w+)="(-?\d+)"', registry.base_unit(unit)))
    assert attrs == base


def test_a_unit_an_fmu_cannot_express_is_refused_at_the_declaration():
    with pytest.raises(ValueError, match=r"unit 'furlong/s': 'furlong' is not one of"):
        registry.Key("float", unit="furlong/s", doc="a rate")
