"""Reading an FMU's model description, with clear errors for missing or unsuitable files."""
from __future__ import annotations

import shutil
import tempfile
import zipfile
import zlib
from pathlib import Path

__all__ = ["read_description", "extract_fmu"]

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
