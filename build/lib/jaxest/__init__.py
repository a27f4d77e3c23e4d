"""jaxest: differentiable state estimation in JAX.

Every filter, smoother and observer is an equinox Module with a pure ``init``/``step`` pair that
``jit``s, ``vmap``s and differentiates; see :mod:`jaxest.run` for the protocol.
"""

from jaxest.filters import EKF, SVDEKF, ImprovedSVDKF, InformationFilter, KalmanFilter, SquareRootKF
from jaxest.models import LinearGaussian, NonlinearGaussian, Simulation, simulate
from jaxest.montecarlo import monte_carlo
from jaxest.riccati import lqr_gain, solve_care, solve_dare
from jaxest.run import FilterResult, Gaussian, Status, filter, run
from jaxest.smoothers import SmootherResult, rts_smooth
from jaxest.smoothers.steady_state import (
    SteadyStateKalmanFilter,
    arma_innovation_model,
    steady_state_gain,
    steady_state_smooth,
)
from jaxest.smoothers.wiener import WienerSmoother, wiener_smooth
from jaxest.tune import fit, neg_loglik, supervised_mse

__all__ = [
    "EKF",
    "SVDEKF",
    "FilterResult",
    "Gaussian",
    "ImprovedSVDKF",
    "InformationFilter",
    "KalmanFilter",
    "LinearGaussian",
    "NonlinearGaussian",
    "Simulation",
    "SmootherResult",
    "SquareRootKF",
    "Status",
    "SteadyStateKalmanFilter",
    "WienerSmoother",
    "arma_innovation_model",
    "filter",
    "fit",
    "lqr_gain",
    "monte_carlo",
    "neg_loglik",
    "rts_smooth",
    "run",
    "simulate",
    "solve_care",
    "solve_dare",
    "steady_state_gain",
    "steady_state_smooth",
    "supervised_mse",
    "wiener_smooth",
]
