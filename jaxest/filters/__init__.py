"""Gaussian filters, each run as ``jaxest.run(Filter(), model, ys, prior=prior)``."""

from jaxest.filters.base import (
    AbstractCovarianceFactor as AbstractCovarianceFactor,
)
from jaxest.filters.base import (
    AbstractGaussianFilter as AbstractGaussianFilter,
)
from jaxest.filters.base import (
    CholeskyFactor as CholeskyFactor,
)
from jaxest.filters.base import (
    Covariance as Covariance,
)
from jaxest.filters.base import (
    FilterResult as FilterResult,
)
from jaxest.filters.base import (
    GaussianState as GaussianState,
)
from jaxest.filters.base import (
    InformationMatrix as InformationMatrix,
)
from jaxest.filters.base import (
    StepOutput as StepOutput,
)
from jaxest.filters.base import (
    SVDFactor as SVDFactor,
)
from jaxest.filters.kalman import (
    EKF as EKF,
)
from jaxest.filters.kalman import (
    InformationFilter as InformationFilter,
)
from jaxest.filters.kalman import (
    KalmanFilter as KalmanFilter,
)
from jaxest.filters.sqrt_kf import SquareRootKF as SquareRootKF
from jaxest.filters.svd_ekf import (
    SVDEKF as SVDEKF,
)
from jaxest.filters.svd_ekf import (
    AbstractSVDFilter as AbstractSVDFilter,
)
from jaxest.filters.svd_ekf import (
    ImprovedSVDKF as ImprovedSVDKF,
)
