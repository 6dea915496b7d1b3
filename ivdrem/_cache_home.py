"""Where ivdrem keeps what it compiles, decided before anything is compiled.

Read by ``ivdrem/__init__.py`` before numba is imported, so it imports nothing heavy.
numba writes the machine code of a ``cache=True`` function beside its source by default:
for the functions in ivdrem's own files (``blocks/_kernels.py``,
``models/_rigid_body_jit.py``, ...) that is the installed package, i.e. site-packages,
which ``pip uninstall`` then leaves behind (about 10 MB).  ivdrem points numba at
``CACHE_DIR/numba`` instead, unless the user chose a place (``NUMBA_CACHE_DIR`` set, even
empty: numba's own default then).
"""
from __future__ import annotations

import os
from pathlib import Path

__all__ = ["cache_dir", "numba_cache_dir", "use_own_numba_cache"]


def cache_dir() -> Path:
    """$IVDREM_CACHE_DIR, else $XDG_CACHE_HOME/ivdrem (default ~/.cache/ivdrem)."""
    d = os.environ.get("IVDREM_CACHE_DIR")
    if d:
        return Path(d)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "ivdrem"


def numba_cache_dir() -> Path:
    """Where numba keeps ivdrem's machine code: ``cache_dir()/numba``."""
    return cache_dir() / "numba"


def use_own_numba_cache() -> None:
    """Set ``NUMBA_CACHE_DIR`` to :func:`numba_cache_dir` unless the user set it (child
    processes, a study's workers, inherit it); if numba was imported first, tell its
    configuration too (numba reads the variable once, at its import).  And have numba read
    the prebuilt machine code of ivdrem's own functions after that cache
    (``ivdrem._prebuilt``: an import hook, numba is not imported here)."""
    from ._prebuilt import install_numba_hook
    install_numba_hook()
    if "NUMBA_CACHE_DIR" in os.environ:
        return
    where = str(numba_cache_dir())
    os.environ["NUMBA_CACHE_DIR"] = where
    import sys
    config = sys.modules.get("numba.core.config")
    if config is not None:
        config.CACHE_DIR = where
