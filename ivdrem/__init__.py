"""ivdrem: composite adaptive disturbance rejection for n-DoF robots via IV-based DREM.

Implements Glushchenko & Lastochkin, "Composite Adaptive Disturbance Rejection in
Robotics via Instrumental Variables based DREM", as python-control block diagrams.
"""
__version__ = "0.1.0"

# numba's caches in ivdrem's cache directory, never in the installed package (before any
# module of ivdrem imports numba)
from ._cache_home import use_own_numba_cache as _use_own_numba_cache

_use_own_numba_cache()
