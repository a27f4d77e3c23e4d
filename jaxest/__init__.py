"""jaxest: differentiable state estimation in JAX.

Every filter, smoother and observer is an equinox Module with a pure ``init``/``step`` pair that
``jit``s, ``vmap``s and differentiates (:class:`AbstractEstimator` has the protocol); one driver,
:func:`run`, runs any of them over a sequence.
"""

import warnings as _warnings

from jaxest import memory_maps as _memory_maps
from jaxest._checks import check_gaussian_arguments as check_gaussian_arguments
from jaxest._estimator import (
    AbstractAssociativeEstimator as AbstractAssociativeEstimator,
    AbstractEstimator as AbstractEstimator,
    AbstractResult as AbstractResult,
)
from jaxest._priors import Gaussian as Gaussian
from jaxest._run import SaveAt as SaveAt, raise_if_failed as raise_if_failed, run as run
from jaxest._status import (
    Status as Status,
    StatusFlag as StatusFlag,
    finite_status as finite_status,
    status_where as status_where,
)
from jaxest.batching import vmap_minor as vmap_minor, vmap_minor_fallbacks as vmap_minor_fallbacks
from jaxest.em import EMResult as EMResult, EMStatus as EMStatus, fit_em as fit_em
from jaxest.filters import (
    EKF as EKF,
    SVDEKF as SVDEKF,
    UKF as UKF,
    AbstractCovarianceFactor as AbstractCovarianceFactor,
    AbstractGaussianFilter as AbstractGaussianFilter,
    AbstractProposal as AbstractProposal,
    AbstractSigmaPointFilter as AbstractSigmaPointFilter,
    AbstractSVDFilter as AbstractSVDFilter,
    CholeskyFactor as CholeskyFactor,
    Covariance as Covariance,
    CubatureKF as CubatureKF,
    FilterResult as FilterResult,
    GaussHermiteKF as GaussHermiteKF,
    GaussianState as GaussianState,
    GaussianTransition as GaussianTransition,
    ImprovedSVDKF as ImprovedSVDKF,
    ImprovedSVDResult as ImprovedSVDResult,
    ImprovedSVDStatus as ImprovedSVDStatus,
    InformationFilter as InformationFilter,
    InformationFormResult as InformationFormResult,
    InformationMatrix as InformationMatrix,
    InformationStatus as InformationStatus,
    IteratedEKF as IteratedEKF,
    KalmanFilter as KalmanFilter,
    ParallelFilterResult as ParallelFilterResult,
    ParallelKalmanFilter as ParallelKalmanFilter,
    ParallelStatus as ParallelStatus,
    ParticleFilter as ParticleFilter,
    ParticleResult as ParticleResult,
    ParticleStatus as ParticleStatus,
    SquareRootKF as SquareRootKF,
    SteadyStateGain as SteadyStateGain,
    SteadyStateKalmanFilter as SteadyStateKalmanFilter,
    SteadyStateResult as SteadyStateResult,
    SteadyStateStatus as SteadyStateStatus,
    StepOutput as StepOutput,
    SVDFactor as SVDFactor,
    resample as resample,
    steady_state_gain as steady_state_gain,
)
from jaxest.linalg import astype as astype
from jaxest.models import (
    AbstractGaussianModel as AbstractGaussianModel,
    LinearGaussian as LinearGaussian,
    NonlinearGaussian as NonlinearGaussian,
    Simulation as Simulation,
    simulate as simulate,
)
from jaxest.montecarlo import monte_carlo as monte_carlo
from jaxest.observers import (
    AdaptiveObserver as AdaptiveObserver,
    ContinuousLTV as ContinuousLTV,
    DiscreteAdaptiveObserver as DiscreteAdaptiveObserver,
    DiscreteLTV as DiscreteLTV,
    InputEffectiveness as InputEffectiveness,
    ObserverPrior as ObserverPrior,
    ObserverStatus as ObserverStatus,
)
from jaxest.riccati import (
    RiccatiSolution as RiccatiSolution,
    RiccatiStatus as RiccatiStatus,
    lqr_gain as lqr_gain,
    solve_care as solve_care,
    solve_dare as solve_dare,
    solve_filter_care as solve_filter_care,
    solve_filter_dare as solve_filter_dare,
)
from jaxest.scaling import ScaledState as ScaledState, scale_state as scale_state
from jaxest.smoothers import SmootherResult as SmootherResult, rts_smooth as rts_smooth
from jaxest.smoothers.iterated import (
    IteratedSmootherResult as IteratedSmootherResult,
    iterated_smooth as iterated_smooth,
)
from jaxest.smoothers.sigma_point_rts import sigma_point_rts_smooth as sigma_point_rts_smooth
from jaxest.smoothers.steady_state import (
    arma_innovation_model as arma_innovation_model,
    steady_state_smooth as steady_state_smooth,
)
from jaxest.smoothers.wiener import WienerSmoother as WienerSmoother, wiener_smooth as wiener_smooth
from jaxest.tune import (
    FitResult as FitResult,
    fit as fit,
    log_variance_standard_errors as log_variance_standard_errors,
    log_variances as log_variances,
    neg_loglik as neg_loglik,
    supervised_mse as supervised_mse,
)

# a warning before XLA:CPU's compiled programs exhaust the process's memory mappings, which
# kills it (jaxest.memory_maps); a no-op where they cannot be counted
_memory_maps.watch()

#: the public API, which the documentation's API reference lists (tests/test_api_reference.py
#: checks it names every public import above)
__all__ = [
    "AbstractAssociativeEstimator", "AbstractCovarianceFactor", "AbstractEstimator",
    "AbstractGaussianFilter", "AbstractGaussianModel", "AbstractProposal", "AbstractResult",
    "AbstractSVDFilter", "AbstractSigmaPointFilter", "AdaptiveObserver", "CholeskyFactor",
    "ContinuousLTV", "Covariance", "CubatureKF", "DiscreteAdaptiveObserver", "DiscreteLTV", "EKF",
    "EMResult", "EMStatus", "FilterResult", "FitResult", "GaussHermiteKF", "Gaussian",
    "GaussianState", "GaussianTransition", "ImprovedSVDKF", "ImprovedSVDResult",
    "ImprovedSVDStatus", "InformationFilter",
    "InformationFormResult", "InformationMatrix", "InformationStatus", "InputEffectiveness",
    "IteratedEKF", "IteratedSmootherResult", "KalmanFilter", "LinearGaussian", "NonlinearGaussian",
    "ObserverPrior", "ObserverStatus", "ParallelFilterResult", "ParallelKalmanFilter",
    "ParallelStatus", "ParticleFilter", "ParticleResult", "ParticleStatus", "RiccatiSolution",
    "RiccatiStatus", "SVDEKF", "SVDFactor", "SaveAt", "ScaledState", "Simulation",
    "SmootherResult", "SquareRootKF", "Status", "StatusFlag", "SteadyStateGain",
    "SteadyStateKalmanFilter", "SteadyStateResult", "SteadyStateStatus", "StepOutput", "UKF", "WienerSmoother", "arma_innovation_model",
    "astype", "check_gaussian_arguments", "finite_status", "fit", "fit_em", "iterated_smooth",
    "log_variance_standard_errors", "log_variances", "lqr_gain", "monte_carlo", "neg_loglik",
    "raise_if_failed", "resample", "rts_smooth", "run", "scale_state", "sigma_point_rts_smooth",
    "simulate", "solve_care", "solve_dare", "solve_filter_care", "solve_filter_dare",
    "status_where", "steady_state_gain", "steady_state_smooth", "supervised_mse", "vmap_minor",
    "vmap_minor_fallbacks", "wiener_smooth",
]  # fmt: skip


def filter(estimator, model, ys, *args, **kwargs):  # noqa: A001 - the deprecated name
    """Deprecated alias of :func:`run` (``filter`` shadows a Python builtin)."""
    _warnings.warn("jaxest.filter is deprecated: use jaxest.run", DeprecationWarning, stacklevel=2)
    if "init" in kwargs:
        kwargs["prior"] = kwargs.pop("init")
    return run(estimator, model, ys, *args, **kwargs)
