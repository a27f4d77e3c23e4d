"""Gaussian filters; each is used as ``jaxest.filter(Filter(), model, ys, inputs, init=prior)``."""

from jaxest.filters.kalman import EKF, InformationFilter, KalmanFilter
from jaxest.filters.sqrt_kf import SquareRootKF
from jaxest.filters.svd_ekf import SVDEKF, ImprovedSVDKF

__all__ = ["EKF", "SVDEKF", "ImprovedSVDKF", "InformationFilter", "KalmanFilter", "SquareRootKF"]
