"""The closed loop of FMUs as an SSP 1.0 file: the controller FMU wired to the plant FMU.

``write_ssp(controller_fmu, plant_fmu, path)`` writes ``path`` (a .ssp zip: the two FMUs
under resources/ and SystemStructure.ssd) with the connections plant.q, plant.dq ->
controller.q, controller.dq and controller.tau -> plant.tau, and the plant's start values
q0, dq0 as a parameter binding.  The plant's tau_d input is left open: a host sets it (the
paper's disturbance) or leaves it 0.  :func:`libcosim_ssp_loop` runs the file in libcosim.
"""
from __future__ import annotations

import os
import zipfile
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from .._atomic import new_tempfile
from .fmu_loop import run_libcosim
from .loop import PAPER_DISTURBANCE, paper_q0

__all__ = ["write_ssp", "libcosim_ssp_loop"]


def _connectors(md, kinds):
    out = []
    for v in md.modelVariables:
        if v.causality in kinds:
            out.append(f'          <ssd:Connector name={quoteattr(v.name)} kind="{v.causality}">'
                       '<ssc:Real/></ssd:Connector>')
    return "\n".join(out)


def write_ssp(controller_fmu, plant_fmu, path, *, q0=None, dq0=None,
              t_end=300.0):
    """Write the SSP file of the loop; returns its path.  ``q0``: the plant's q(0), default
    the paper's (:func:`~ivdrem.controller.loop.paper_q0`)."""
    q0 = paper_q0() if q0 is None else q0
    from fmpy import read_model_description
    mc = read_model_description(str(controller_fmu))
    mp = read_model_description(str(plant_fmu))
    n = sum(1 for v in mp.modelVariables if v.name.startswith("q["))
    dq0 = np.zeros(n) if dq0 is None else np.asarray(dq0, float)
    from .fmu_loop import controller_period
    h = controller_period(controller_fmu)
    starts = "\n".join(
        f'                  <ssv:Parameter name="{nm}[{i}]"><ssv:Real value="{float(val[i])!r}"/>'
        '</ssv:Parameter>' for nm, val in (("q", q0), ("dq", dq0)) for i in range(n))
    conns = []
    for i in range(n):
        for s in ("q", "dq"):
            conns.append(f'      <ssd:Connection startElement="plant" startConnector="{s}[{i}]" '
                         f'endElement="controller" endConnector="{s}[{i}]"/>')
        conns.append(f'      <ssd:Connection startElement="controller" startConnector="tau[{i}]" '
                     f'endElement="plant" endConnector="tau[{i}]"/>')
    ssd = f"""<?xml version="1.0" encoding="UTF-8"?>
<ssd:SystemStructureDescription version="1.0" name="ivdrem_closed_loop"
    xmlns:ssc="http://ssp-standard.org/SSP1/SystemStructureCommon"
    xmlns:ssd="http://ssp-standard.org/SSP1/SystemStructureDescription"
    xmlns:ssv="http://ssp-standard.org/SSP1/SystemStructureParameterValues"
    generationTool="ivdrem">
  <ssd:System name="closed_loop" description="sampled controller (delay 1) around the robot plant; Jacobi, step {h}">
    <ssd:Elements>
      <ssd:Component name="plant" type="application/x-fmu-sharedlibrary" source="resources/Plant.fmu">
        <ssd:Connectors>
{_connectors(mp, ("input", "output"))}
        </ssd:Connectors>
        <ssd:ParameterBindings>
          <ssd:ParameterBinding>
            <ssd:ParameterValues>
              <ssv:ParameterSet version="1.0" name="initial_state">
                <ssv:Parameters>
{starts}
                </ssv:Parameters>
              </ssv:ParameterSet>
            </ssd:ParameterValues>
          </ssd:ParameterBinding>
        </ssd:ParameterBindings>
      </ssd:Component>
      <ssd:Component name="controller" type="application/x-fmu-sharedlibrary" source="resources/Controller.fmu">
        <ssd:Connectors>
{_connectors(mc, ("input", "output"))}
        </ssd:Connectors>
      </ssd:Component>
    </ssd:Elements>
    <ssd:Connections>
{chr(10).join(conns)}
    </ssd:Connections>
  </ssd:System>
  <ssd:DefaultExperiment startTime="0" stopTime="{float(t_end)!r}"/>
</ssd:SystemStructureDescription>
"""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = new_tempfile(path.parent, path.name)
    try:
        with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as zf:
            zf.writestr("SystemStructure.ssd", ssd)
            zf.write(str(plant_fmu), "resources/Plant.fmu")
            zf.write(str(controller_fmu), "resources/Controller.fmu")
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def _controller_period(ssp_path):
    """The controller FMU's h (its parameter), read from the FMU inside the SSP file."""
    import tempfile
    from .fmu_loop import controller_period
    with zipfile.ZipFile(ssp_path) as zf, tempfile.TemporaryDirectory() as tmp:
        inner = Path(tmp) / "Controller.fmu"
        inner.write_bytes(zf.read("resources/Controller.fmu"))
        return controller_period(inner)


def libcosim_ssp_loop(ssp_path, t_end, *, q0=None, dq0=None,
                      disturbance=PAPER_DISTURBANCE, every=100):
    """Run an SSP file of :func:`write_ssp` in libcosim (its SSP loader and fixed-step
    algorithm, step = the controller FMU's parameter h), the disturbance set on the plant's
    open tau_d input before each step by an override manipulator; record as
    :func:`ivdrem.controller.fmu_loop.fmpy_closed_loop` but from t = every h.  libcosimpy
    0.0.6 loads the connections but does not apply the parameter binding to the plant's q,
    dq (outputs with initial="exact"; measured: q(0) = 0), so q0, dq0 are set again here
    with ``real_initial_value``."""
    from libcosimpy.CosimExecution import CosimExecution
    from libcosimpy.CosimLogging import CosimLogLevel, log_output_level
    from .fmu_loop import _steps
    q0 = paper_q0() if q0 is None else q0    # the paper's q(0) by default
    h = _controller_period(ssp_path)
    log_output_level(CosimLogLevel.ERROR)
    ex = CosimExecution.from_ssp_file(str(ssp_path), step_size=int(round(h * 1e9)))
    ip = ex.slave_index_from_instance_name("plant")
    ic = ex.slave_index_from_instance_name("controller")
    vr_p = {v.name.decode() if isinstance(v.name, bytes) else v.name: v.reference
            for v in ex.slave_variables(ip)}
    vr_c = {v.name.decode() if isinstance(v.name, bytes) else v.name: v.reference
            for v in ex.slave_variables(ic)}
    n = sum(1 for k in vr_p if k.startswith("q["))
    nth = sum(1 for k in vr_c if k.startswith("theta_hat["))
    dq0 = np.zeros(n) if dq0 is None else dq0
    for i in range(n):
        ex.real_initial_value(ip, vr_p[f"q[{i}]"], float(q0[i]))
        ex.real_initial_value(ip, vr_p[f"dq[{i}]"], float(dq0[i]))
    steps = _steps(t_end, h)
    return run_libcosim(ex, ip, ic, vr_p, vr_c, n, nth, steps, h, every, disturbance)
