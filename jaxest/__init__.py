"""jaxest: differentiable state estimation in JAX.

Every filter, smoother and observer is an equinox Module with a pure ``init``/``step`` pair that
``jit``s, ``vmap``s and differentiates (:mod:`jaxest.estimator` has the protocol); one driver,
:func:`run`, runs any of them over a sequence.
"""

import warnings as _warnings

from jaxest.checks import check_gaussian_arguments as check_gaussian_arguments
from jaxest.estimator import (
    AbstractAssociativeEstimator as AbstractAssociativeEstimator,
)
from jaxest.estimator import (
    AbstractEstimator as AbstractEstimator,
)
from jaxest.estimator import (
    AbstractResult as AbstractResult,
)
from jaxest.filters import (
    EKF as EKF,
)
from jaxest.filters import (
    SVDEKF as SVDEKF,
)
from jaxest.filters import (
    AbstractCovarianceFactor as AbstractCovarianceFactor,
)
from jaxest.filters import (
    AbstractGaussianFilter as AbstractGaussianFilter,
)
from jaxest.filters import (
    AbstractSVDFilter as AbstractSVDFilter,
)
from jaxest.filters import (
    CholeskyFactor as CholeskyFactor,
)
from jaxest.filters import (
    Covariance as Covariance,
)
from jaxest.filters import (
    FilterResult as FilterResult,
)
from jaxest.filters import (
    GaussianState as GaussianState,
)
from jaxest.filters import (
    ImprovedSVDKF as ImprovedSVDKF,
)
from jaxest.filters import (
    InformationFilter as InformationFilter,
)
from jaxest.filters import (
    InformationMatrix as InformationMatrix,
)
from jaxest.filters import (
    KalmanFilter as KalmanFilter,
)
from jaxest.filters import (
    SquareRootKF as SquareRootKF,
)
from jaxest.filters import (
    StepOutput as StepOutput,
)
from jaxest.filters import (
    SVDFactor as SVDFactor,
)
from jaxest.models import (
    AbstractGaussianModel as AbstractGaussianModel,
)
from jaxest.models import (
    LinearGaussian as LinearGaussian,
)
from jaxest.models import (
    NonlinearGaussian as NonlinearGaussian,
)
from jaxest.models import (
    Simulation as Simulation,
)
from jaxest.models import (
    simulate as simulate,
)
from jaxest.montecarlo import monte_carlo as monte_carlo
from jaxest.priors import Gaussian as Gaussian
from jaxest.riccati import lqr_gain as lqr_gain
from jaxest.riccati import solve_care as solve_care
from jaxest.riccati import solve_dare as solve_dare
from jaxest.run import SaveAt as SaveAt
from jaxest.run import raise_if_failed as raise_if_failed
from jaxest.run import run as run
from jaxest.smoothers import SmootherResult as SmootherResult
from jaxest.smoothers import rts_smooth as rts_smooth
from jaxest.smoothers.steady_state import (
    SteadyStateKalmanFilter as SteadyStateKalmanFilter,
)
from jaxest.smoothers.steady_state import (
    arma_innovation_model as arma_innovation_model,
)
from jaxest.smoothers.steady_state import (
    steady_state_gain as steady_state_gain,
)
from jaxest.smoothers.steady_state import (
    steady_state_smooth as steady_state_smooth,
)
from jaxest.smoothers.wiener import WienerSmoother as WienerSmoother
from jaxest.smoothers.wiener import wiener_smooth as wiener_smooth
from jaxest.status import Status as Status
from jaxest.status import StatusFlag as StatusFlag
from jaxest.tune import fit as fit
from jaxest.tune import neg_loglik as neg_loglik
from jaxest.tune import supervised_mse as supervised_mse


def filter(estimator, model, ys, *args, **kwargs):  # noqa: A001 - the deprecated name
    """Deprecated alias of :func:`run` (``filter`` shadows a Python builtin)."""
    _warnings.warn("jaxest.filter is deprecated: use jaxest.run", DeprecationWarning, stacklevel=2)
    if "init" in kwargs:
        kwargs["prior"] = kwargs.pop("init")
    return run(estimator, model, ys, *args, **kwargs)
