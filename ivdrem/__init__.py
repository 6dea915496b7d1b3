"""ivdrem: composite adaptive disturbance rejection for n-DoF robots via IV-based DREM.

Implements Glushchenko & Lastochkin, "Composite Adaptive Disturbance Rejection in
Robotics via Instrumental Variables based DREM", as python-control block diagrams.
"""
__version__ = "0.1.0"
