"""Inertial measurements: the data a sequence carries (:mod:`.data`) and on-manifold preintegration
(:mod:`.preintegration`, Forster et al. TRO 2017)."""

from .data import EUROC_ADIS16448, ImuData, ImuNoise, ImuWindow, window
from .preintegration import NavState, Preintegrated, ResidualJacobians, correct, preintegrate, residual, residual_jacobians

__all__ = ["ImuData", "ImuNoise", "ImuWindow", "window", "EUROC_ADIS16448", "Preintegrated", "NavState", "ResidualJacobians",
           "preintegrate", "correct", "residual", "residual_jacobians"]
