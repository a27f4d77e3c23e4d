"""Gaussian filters, each run as ``jaxest.run(Filter(), model, ys, prior=prior)``."""

from jaxest.filters.base import (
    AbstractCovarianceFactor as AbstractCovarianceFactor,
    AbstractGaussianFilter as AbstractGaussianFilter,
    CholeskyFactor as CholeskyFactor,
    Covariance as Covariance,
    FilterResult as FilterResult,
    GaussianState as GaussianState,
    InformationMatrix as InformationMatrix,
    StepOutput as StepOutput,
    SVDFactor as SVDFactor,
)
from jaxest.filters.iterated import IteratedEKF as IteratedEKF
from jaxest.filters.kalman import (
    EKF as EKF,
    InformationFilter as InformationFilter,
    InformationFormResult as InformationFormResult,
    InformationStatus as InformationStatus,
    KalmanFilter as KalmanFilter,
)
from jaxest.filters.parallel import (
    ParallelFilterResult as ParallelFilterResult,
    ParallelKalmanFilter as ParallelKalmanFilter,
    ParallelStatus as ParallelStatus,
)
from jaxest.filters.particle import (
    AbstractProposal as AbstractProposal,
    GaussianTransition as GaussianTransition,
    ParticleFilter as ParticleFilter,
    ParticleResult as ParticleResult,
    ParticleStatus as ParticleStatus,
    resample as resample,
)
from jaxest.filters.sigma_point import (
    UKF as UKF,
    AbstractSigmaPointFilter as AbstractSigmaPointFilter,
    CubatureKF as CubatureKF,
    GaussHermiteKF as GaussHermiteKF,
)
from jaxest.filters.sqrt_kf import SquareRootKF as SquareRootKF
from jaxest.filters.steady_state import (
    SteadyStateGain as SteadyStateGain,
    SteadyStateKalmanFilter as SteadyStateKalmanFilter,
    SteadyStateResult as SteadyStateResult,
    SteadyStateStatus as SteadyStateStatus,
    steady_state_gain as steady_state_gain,
)
from jaxest.filters.svd_ekf import (
    SVDEKF as SVDEKF,
    AbstractSVDFilter as AbstractSVDFilter,
    ImprovedSVDKF as ImprovedSVDKF,
    ImprovedSVDResult as ImprovedSVDResult,
    ImprovedSVDStatus as ImprovedSVDStatus,
)
