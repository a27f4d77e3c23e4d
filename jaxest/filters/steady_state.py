"""The steady-state Kalman filter of a time-invariant linear model (Sun & Cui 2003, lemma 1).

For x(t+1) = Phi x(t) + Gamma w(t), y(t) = H x(t) + v(t):

- :func:`steady_state_gain` (lemma 1, eqs 4-5): Sigma, the steady-state one-step prediction
  covariance, K = Sigma H^T (H Sigma H^T + R)^-1 and Psi_f = (I - K H) Phi;
- :class:`SteadyStateKalmanFilter` (eq 3): x(t+1|t+1) = Psi_f x(t|t) + K y(t+1), a Gaussian filter
  like the others, run by ``jaxest.run``.

The steady-state smoothers built on them are in :mod:`jaxest.smoothers.steady_state`
(docs/papers/wiener.md).
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from jaxest._checks import check_complete, check_gaussian_prior
from jaxest._priors import Gaussian
from jaxest._status import Status, StatusOfOne, finite_status, status_where
from jaxest.filters.base import (
    AbstractCovarianceFactor,
    AbstractGaussianFilter,
    FilterResult,
    GaussianState,
    StepOutput,
    check_gaussian_state,
)
from jaxest.filters.common import gaussian_loglik
from jaxest.linalg import symmetrize, working_precision_by_default
from jaxest.models import LinearGaussian
from jaxest.riccati import RiccatiStatus, solve_filter_dare


class SteadyStateGain(StatusOfOne):
    """Lemma 1: the steady state of the Kalman filter of a time-invariant linear model, and the
    :class:`~jaxest.RiccatiStatus` of the Riccati solution it comes from (NaN Sigma, K and
    Q_eps where that is not OK: under ``jit`` where there is no stabilising solution, which
    :func:`steady_state_gain` raises for outside it, or wherever the solver cannot reach one
    to working precision, ``INACCURATE``: float32 on an ill-conditioned model)."""

    #: the status flags of the Riccati solution
    flags: ClassVar = RiccatiStatus

    Phi: Float[Array, "n n"]
    H: Float[Array, "m n"]
    Sigma: Float[Array, "n n"]  #: steady-state prediction covariance P(t|t-1), eq 5
    K: Float[Array, "n m"]  #: filter gain, eq 4
    innovation_cov: Float[Array, "m m"]  #: Q_eps = H Sigma H^T + R
    status: Int[Array, ""]  #: the Riccati solution's status bits (0 = OK)

    @property
    def Psi_f(self) -> Float[Array, "n n"]:
        """Psi_f = (I - K H) Phi, the (stable) filter transition matrix of eq 3."""
        return (jnp.eye(self.Phi.shape[0], dtype=self.Phi.dtype) - self.K @ self.H) @ self.Phi

    @property
    def smoother_transition(self) -> Float[Array, "n n"]:
        """(I - K H)^T Phi^T, whose powers make the fixed-point gains of eq 9."""
        eye = jnp.eye(self.Phi.shape[0], dtype=self.Phi.dtype)
        return (eye - self.K @ self.H).T @ self.Phi.T

    @property
    def innovation_gain(self) -> Float[Array, "n m"]:
        """H^T Q_eps^-1, the last factor of eq 9."""
        return jnp.linalg.solve(self.innovation_cov, self.H).T

    @property
    def filtered_cov(self) -> Float[Array, "n n"]:
        """P(t|t) = Sigma - K Q_eps K^T."""
        return symmetrize(self.Sigma - self.K @ self.innovation_cov @ self.K.T)


def check_time_invariant(model) -> None:
    """The steady-state theory needs a time-invariant :class:`~jaxest.LinearGaussian` model
    without inputs; raise ``ValueError`` naming the offending part otherwise."""
    if not isinstance(model, LinearGaussian):
        raise ValueError(f"model: expected jaxest.LinearGaussian, got {type(model).__name__}")
    for name in ("B", "D"):
        if getattr(model, name) is not None:
            raise ValueError(f"model.{name}: the steady-state smoothers take no inputs")
    for name in ("F", "H", "Q", "R", "G"):
        value = getattr(model, name)
        if value is not None and jnp.ndim(value) != 2:
            raise ValueError(
                f"model.{name}: must be time-invariant (a matrix), got shape {jnp.shape(value)}"
            )


@working_precision_by_default
def steady_state_gain(model: LinearGaussian) -> SteadyStateGain:
    """Sigma from the filter Riccati equation (eq 5), ``solve_filter_dare(Phi, H, Gamma Q
    Gamma^T, R)``, then K (eq 4) and Q_eps. Concrete (F, H) without a stabilising solution raise
    a ``ValueError`` naming them; a solution whose status is not OK (under ``jit``, or one the
    solver cannot certify, eagerly too) gives NaN, and the gain's ``status`` says why (``ok``:
    it is OK)."""
    check_time_invariant(model)
    R = model.measurement_cov(0)
    solution = solve_filter_dare(model.F, model.H, _state_noise_cov(model), R)
    return _gain(model.F, model.H, R, solution)


@eqx.filter_jit
def _state_noise_cov(model: LinearGaussian) -> Float[Array, "n n"]:
    """Gamma Q Gamma^T, the covariance of the noise on the state, compiled as one program."""
    G, Q = model.process_noise(None, None, 0)
    return symmetrize(G @ Q @ G.T)


@jax.jit
def _gain(Phi, H, R, solution) -> SteadyStateGain:
    """K (eq 4) and Q_eps from the Riccati solution, compiled as one program
    (docs/performance.md, "First calls outside jit")."""
    Sigma = jnp.where(solution.ok, solution.X, jnp.nan)
    Qe = symmetrize(H @ Sigma @ H.T + R)
    K = jnp.linalg.solve(Qe, H @ Sigma).T
    return SteadyStateGain(Phi, H, Sigma, K, Qe, solution.status)


class SteadyStateFactor(AbstractCovarianceFactor):
    """The steady-state filter's "factor" of P(t|t-1): the constant gain and the Cholesky factor
    of the innovation covariance, computed once in ``init``; ``cov`` is Sigma."""

    gain: SteadyStateGain
    innovation_chol: Float[Array, "m m"]

    @property
    def cov(self):
        return self.gain.Sigma


def check_steady_state_gain(gain, *, none: bool = False) -> None:
    """``gain`` is a :class:`SteadyStateGain` (or ``None`` where ``none``), ``ValueError`` naming
    it otherwise."""
    if not (isinstance(gain, SteadyStateGain) or none and gain is None):
        allowed = "None or a SteadyStateGain" if none else "a SteadyStateGain"
        raise ValueError(
            f"gain: expected {allowed} (steady_state_gain(model)), got {type(gain).__name__}"
        )


SteadyStateStatus = Status.extend(
    "SteadyStateStatus",
    NO_STEADY_STATE=(
        4,
        "the steady-state gain has no accurate Riccati solution, so the estimates are NaN: "
        "gain.flags.describe(gain.status) (gain = steady_state_gain(model)) says why: no "
        "stabilising solution where (F, H) is not detectable or (F, G Q^1/2) has a mode on the "
        "unit circle it cannot reach, INACCURATE for float32 on an ill-conditioned model (use "
        "float64, or a KalmanFilter, which needs no steady state)",
    ),
)
"""The steady-state filter's and smoother's status flags: the core's and NO_STEADY_STATE, set
at every step where the gain's :class:`~jaxest.RiccatiStatus` is not OK."""


class SteadyStateResult(FilterResult):
    """:class:`~jaxest.FilterResult` whose status bits are :data:`SteadyStateStatus`."""

    flags: ClassVar = SteadyStateStatus


class SteadyStateKalmanFilter(AbstractGaussianFilter):
    """Lemma 1 / eq 3: the Kalman filter with its steady-state gain, x(t|t) = x(t|t-1) +
    K (y(t) - H x(t|t-1)), x(t+1|t) = Phi x(t|t), i.e. x(t+1|t+1) = Psi_f x(t|t) + K y(t+1).

    Only the prior's mean is used (x(0|-1)): the steady state presumes the filter started at
    t0 -> -infinity, so the reported covariances are the constant Sigma and P(t|t). No missing
    (NaN) measurements (``ValueError`` when ``ys`` is concrete). ``gain`` is
    :func:`steady_state_gain` of the model (computed in ``init`` when not given).
    """

    gain: SteadyStateGain | None = None
    factor_type = SteadyStateFactor
    result_type = SteadyStateResult

    def __check_init__(self):
        check_steady_state_gain(self.gain, none=True)

    def init(self, model, prior: Gaussian) -> GaussianState:
        check_gaussian_prior(prior)
        zero = jnp.zeros((), jnp.result_type(prior.mean))
        return GaussianState(prior.mean, self._factor(model), zero)

    def resume(self, model, state) -> GaussianState:
        """Another Gaussian filter's state: its mean and log-likelihood, with the steady state's
        Sigma in place of its covariance (as :meth:`init` takes only the prior's mean)."""
        check_gaussian_state(state, type(self).__name__)
        if isinstance(state.factor, SteadyStateFactor):
            return state
        return GaussianState(state.mean, self._factor(model), state.loglik)

    def _factor(self, model) -> SteadyStateFactor:
        gain = steady_state_gain(model) if self.gain is None else self.gain
        return SteadyStateFactor(gain, jnp.linalg.cholesky(gain.innovation_cov))

    def check(self, model, ys, inputs, prior) -> None:
        check_time_invariant(model)
        super().check(model, ys, inputs, prior)
        if self.gain is not None and jnp.shape(self.gain.K) != jnp.shape(model.H)[::-1]:
            raise ValueError(
                f"gain: is for {jnp.shape(self.gain.K)[0]} states and {jnp.shape(self.gain.K)[1]}"
                f" measurements, the model has {jnp.shape(model.H)[1]} and "
                f"{jnp.shape(model.H)[0]}"
            )
        check_complete(ys, "the steady-state gain is for complete measurements (use KalmanFilter)")

    def update_predict(self, model, x, factor: SteadyStateFactor, k, y, u):
        g = factor.gain
        e = y - g.H @ x
        x_post = x + g.K @ e
        S_chol = factor.innovation_chol
        z = jax.scipy.linalg.solve_triangular(S_chol, e, lower=True)
        loglik = gaussian_loglik(z, S_chol, e.shape[0])
        x_next = g.Phi @ x_post
        no_gain = status_where(g.status != 0, SteadyStateStatus.NO_STEADY_STATE)
        status = finite_status(x_next, loglik) | no_gain
        out = StepOutput(x, g.Sigma, x_post, g.filtered_cov, e, g.innovation_cov, loglik, status)
        return x_next, factor, out
