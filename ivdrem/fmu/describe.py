"""Reading an FMU's model description, with clear errors for missing or unsuitable files."""
from __future__ import annotations

import shutil
import tempfile
import zipfile
import zlib
from pathlib import Path

__all__ = ["read_description", "extract_fmu", "output_dependencies", "direct_ports"]

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
            _check_crc(path, zf)
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


def _check_crc(path, zf) -> None:
    """Read every member once (an FMU is small): a damaged archive is named here rather
    than as a zlib error halfway through extracting it."""
    try:
        bad = zf.testzip()
    except (zipfile.BadZipFile, zlib.error, EOFError, OSError) as exc:
        raise ValueError(f"{path}: the FMU archive is damaged ({exc}); export it again") from None
    if bad is not None:
        raise ValueError(f"{path}: the FMU archive is damaged (member {bad} fails its CRC "
                         "check); export it again")


def extract_fmu(path) -> str:
    """Extract the FMU archive at `path` into a new temporary directory and return it; on
    any error the directory is removed and a ValueError names the damaged archive."""
    from fmpy import extract
    unzipdir = tempfile.mkdtemp(prefix="ivdrem_fmu_")
    try:
        extract(str(path), unzipdir=unzipdir)
    except BaseException as exc:
        shutil.rmtree(unzipdir, ignore_errors=True)
        if isinstance(exc, (zipfile.BadZipFile, zlib.error, EOFError)):
            raise ValueError(f"{path}: the FMU archive is damaged ({exc}); export it again") \
                from None
        raise
    return unzipdir


def _description_xml(path) -> bytes:
    path = Path(path)
    if path.is_file():
        with zipfile.ZipFile(path) as zf:
            return zf.read("modelDescription.xml")
    return (path / "modelDescription.xml").read_bytes()


def output_dependencies(source) -> dict:
    """What each output depends on, from ``ModelStructure/Outputs`` of an FMI 2.0 model
    description.

    `source` is the FMU (archive or directory) or the XML text itself.  Returns {output
    variable name: frozenset of the names of the variables it depends on, or None}.  None
    means "depends on every known" (the FMI 2.0 standard, section 2.2.8: an ``Unknown``
    without a ``dependencies`` attribute depends on all knowns); an empty set means it
    depends on none.  fmpy's ModelDescription turns both into an empty list, so the XML is
    read here.
    """
    import xml.etree.ElementTree as ET
    if isinstance(source, (bytes, str)) and (isinstance(source, bytes) or source.lstrip().startswith("<")):
        text = source
        where = "modelDescription.xml"
    else:
        text = _description_xml(source)
        where = f"{source}: modelDescription.xml"
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise ValueError(f"{where}: not valid XML ({exc})") from None
    variables = root.findall("ModelVariables/ScalarVariable")

    def name_of(index, what):
        try:
            i = int(index)
        except (TypeError, ValueError):
            i = 0
        if not 1 <= i <= len(variables):
            raise ValueError(f"{where}: ModelStructure {what} refers to variable index "
                             f"{index!r}; there are {len(variables)} ScalarVariables")
        return variables[i - 1].get("name")

    out = {}
    for unknown in root.findall("ModelStructure/Outputs/Unknown"):
        name = name_of(unknown.get("index"), "output")
        deps = unknown.get("dependencies")
        if deps is None:
            out[name] = None
        else:
            out[name] = frozenset(name_of(d, f"dependency of output {name}")
                                  for d in deps.split())
    return out


def direct_ports(dependencies: dict, outputs, ports: dict) -> tuple:
    """The input ports the given outputs depend on (direct feedthrough).

    `dependencies` from :func:`output_dependencies`; `outputs` the output variable names
    of interest; `ports` {port name: [input variable names]}, in port order.  An output
    without dependency information (not listed, or listed without a ``dependencies``
    attribute) depends on every input.
    """
    direct = set()
    for name in outputs:
        deps = dependencies.get(name)
        for port, names in ports.items():
            if deps is None or any(v in deps for v in names):
                direct.add(port)
    return tuple(p for p in ports if p in direct)
