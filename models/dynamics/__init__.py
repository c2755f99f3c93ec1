"""Rigid-body dynamics: the paper's RNEIDA/RNEFDA (own code) and a pinocchio backend.

See backends.py for the interface; rne.py for the algorithms.
"""

from models.dynamics.backends import Dynamics, PinocchioDynamics, RneDynamics, make_dynamics

__all__ = ["Dynamics", "PinocchioDynamics", "RneDynamics", "make_dynamics"]
