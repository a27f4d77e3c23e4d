"""The estimators every test runs over, registered once."""

from jaxest.filters import EKF, SVDEKF, ImprovedSVDKF, InformationFilter, KalmanFilter, SquareRootKF

#: every Gaussian filter that runs on any Gaussian model (the steady-state filter needs a
#: time-invariant linear one and has its own tests)
GAUSSIAN_FILTERS = [KalmanFilter, EKF, InformationFilter, SquareRootKF, SVDEKF, ImprovedSVDKF]
GAUSSIAN_FILTER_IDS = [f.__name__ for f in GAUSSIAN_FILTERS]
#: the filters that factor or invert Q, so Q must be positive definite
NEED_POSITIVE_Q = [InformationFilter, SquareRootKF]
