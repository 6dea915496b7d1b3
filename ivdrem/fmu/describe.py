"""Reading an FMU's model description, with clear errors for missing or unsuitable files."""
from __future__ import annotations

import zipfile
from pathlib import Path

__all__ = ["read_description"]

_INTERFACES = {"model exchange": "modelExchange", "co-simulation": "coSimulation"}


def read_description(path, interface):
    """fmpy ModelDescription of the FMI 2.0 FMU at `path` offering `interface`
    ("model exchange" or "co-simulation")."""
    from fmpy import read_model_description
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"FMU file not found: {path}")
    if path.is_file():
        if not zipfile.is_zipfile(path):
            raise ValueError(f"{path} is not an FMU (not a zip archive)")
        with zipfile.ZipFile(path) as zf:
            if "modelDescription.xml" not in zf.namelist():
                raise ValueError(f"{path} is not an FMU (no modelDescription.xml in the archive)")
    elif not (path / "modelDescription.xml").is_file():
        raise ValueError(f"{path} is not an FMU (no modelDescription.xml in the directory)")
    try:
        md = read_model_description(str(path))
    except Exception as exc:
        raise ValueError(f"{path}: invalid modelDescription.xml: {exc}") from None
    if md.fmiVersion != "2.0":
        raise ValueError(f"{path}: FMI version {md.fmiVersion}, expected 2.0")
    if getattr(md, _INTERFACES[interface]) is None:
        hint = ("; export it with ivdrem.fmu.export_fmu, which provides both"
                if interface == "co-simulation" else "")
        raise ValueError(f"{path}: the FMU does not support {interface}{hint}")
    return md
