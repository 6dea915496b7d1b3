"""A configuration or study file as a TOML table, and :class:`ConfigError`, without the
library: the command line refuses a missing, unreadable or invalid file before it imports
python-control and SciPy (``ivdrem.cli``), with the message ``ivdrem.experiments.config``
gives it (which imports both from here)."""
from __future__ import annotations

from pathlib import Path

from ._paths import InputFileError, read_input_bytes

try:
    import tomllib
except ImportError:  # pragma: no cover - Python < 3.11
    import tomli as tomllib

__all__ = ["ConfigError", "read_toml"]


class ConfigError(ValueError):
    """An invalid experiment configuration (raised before any simulation)."""


def read_toml(path, what: str = "config file", error=None) -> tuple[dict, str]:
    """(table, text) of a TOML file; a missing, unreadable, non-UTF-8 or invalid file raises
    `error` (default ConfigError) naming `what` and the path."""
    error = ConfigError if error is None else error
    p = Path(path)
    try:    # a FIFO, a device or a runaway file: refused, never read (ivdrem._paths)
        text = read_input_bytes(p, what).decode("utf-8")
    except FileNotFoundError:
        raise error(f"{what} '{p}' not found") from None
    except IsADirectoryError:
        raise error(f"{what} '{p}' is a directory, not a file") from None
    except InputFileError as exc:
        raise error(str(exc)) from None
    except UnicodeDecodeError as exc:
        raise error(f"{what} '{p}' is not UTF-8 text (TOML must be UTF-8): "
                    f"byte {exc.object[exc.start]:#04x} at offset {exc.start}") from None
    except OSError as exc:
        raise error(f"{what} '{p}' cannot be read: {exc}") from None
    try:
        return tomllib.loads(text), text
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{what} '{p}' is not valid TOML: {exc}") from None
