"""Covariance-form Kalman filter / EKF (Joseph update), the paper's EKF (covariance time update,
information-form measurement update, eqs 6-10 of Zhang, Dai & Zhang) and the information filter.

On a :class:`~jaxest.LinearGaussian` model each is an exact Kalman filter; on a
:class:`~jaxest.NonlinearGaussian` model each linearises f at x(k|k) and h at x(k|k-1) (EKF).
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from jaxest._status import Status, status_where
from jaxest.filters.base import (
    AbstractGaussianFilter,
    Covariance,
    FilterResult,
    InformationMatrix,
    StepOutput,
)
from jaxest.filters.common import (
    covariance_predict,
    covariance_step,
    gaussian_loglik,
    masked_measurement,
    predicted_cov,
    step_status,
    whitened_innovation,
)
from jaxest.filters.fisher import NEEDED, fisher_loglik
from jaxest.linalg import cho_solve_lower, chol_inverse, cholesky, inv_spd, symmetrize
from jaxest.models import LinearGaussian


class KalmanFilter(AbstractGaussianFilter):
    """The conventional covariance-form Kalman filter (EKF on nonlinear models) with the Joseph
    form P+ = (I - K H) P (I - K H)^T + K R K^T of the measurement update.

    ``closed_form_gradient``: on a :class:`~jaxest.LinearGaussian` model without ``G``, run
    from a prior (not resumed from a state), the total log-likelihood ``result.loglik`` is
    differentiated by Fisher's identity (a disturbance smoother, :mod:`jaxest.filters.fisher`)
    instead of autodiff through the steps: the same gradient, singular Q and P0 included,
    value_and_grad 1.3-2.3x faster in docs/performance.md. Every other output, and every other
    model, is differentiated by autodiff. ``False``: autodiff everywhere.
    """

    factor_type = Covariance
    closed_form_gradient: bool = eqx.field(static=True, default=True)

    def update_predict(self, model, x, factor: Covariance, k, y, u):
        P = factor.matrix
        x_next, P_next, (x_post, P_post, e, S, loglik) = covariance_step(model, x, P, y, u, k)
        status = step_status(x_next, P_next, loglik, cov=P_post)
        out = StepOutput(x, P, x_post, P_post, e, S, loglik, status)
        return x_next, Covariance(P_next), out

    def _closed_form(self, model) -> bool:
        return self.closed_form_gradient and isinstance(model, LinearGaussian) and model.G is None

    def derivative_fields(self, model) -> tuple[str, ...]:
        return NEEDED if self._closed_form(model) else ()

    def with_derivatives(self, result: FilterResult, model, prior, ys, inputs, ks):
        if not self._closed_form(model):
            return result
        filtered = FilterResult(result.final_state, **{f: getattr(result, f) for f in NEEDED})
        loglik = fisher_loglik(result.loglik, model, prior, ys, inputs, ks, filtered)
        return eqx.tree_at(lambda r: r.final_state.loglik, result, loglik)


#: how far the information form may stray from the covariance form before a step is flagged:
#: half a posterior standard deviation for the mean (:func:`correction_gap`), half the variance
#: in any direction for the information filter's Y(k+1|k) (:func:`inverse_gap`)
INCONSISTENCY_TOLERANCE = 0.5

InformationStatus = Status.extend(
    "InformationStatus",
    INFORMATION_INCONSISTENT=(
        4,
        "the information form disagrees with the covariance form: the measurement update moved "
        "the mean more than half a posterior standard deviation away from x + P H^T S^-1 e, or "
        "the information filter's Y(k+1|k) is off the inverse of F P F^T + G Q G^T by more "
        "than half in some direction. Either form may be the one that lost its accuracy: the "
        "information form where R is far below H P H^T for this dtype (use a covariance-form "
        "filter: KalmanFilter, SquareRootKF, ImprovedSVDKF), the covariance form from a prior "
        "far wider than R (use SquareRootKF); float64 serves both (docs/robustness.md)",
    ),
)
"""The information-form filters' status flags (:class:`EKF`, :class:`InformationFilter`,
:class:`~jaxest.SVDEKF`): the core's and INFORMATION_INCONSISTENT."""


class InformationFormResult(FilterResult):
    """:class:`~jaxest.FilterResult` whose status bits are :data:`InformationStatus`."""

    flags: ClassVar = InformationStatus


def covariance_form_terms(P, meas):
    """What the covariance form gives beside an information-form update from P = P(k|k-1):
    the innovation covariance S = H P H^T + R, the likelihood term log N(e; 0, S) and the
    correction P H^T S^-1 e that x(k|k) - x(k|k-1) equals in exact arithmetic.

    The likelihood is taken from S rather than from the information form's own factors (by the
    determinant lemma, e^T S^-1 e = e^T R^-1 e - b^T P+ b): where R is far below H P H^T the
    two terms of that difference are nearly equal and large, and their difference is lost to
    rounding (float32, a position sensor of variance 1e-12 against a predicted variance near
    0.01: the EKF's log-likelihood of 20 steps off by 7e4, tests/test_information_form.py)."""
    S, S_chol, whitened_HP, whitened = whitened_innovation(P, meas)
    loglik = gaussian_loglik(whitened, S_chol, meas.num_observed)
    return S, loglik, whitened_HP.T @ whitened


def correction_gap(correction, expected, info_sqrt) -> Float[Array, ""]:
    """||W^T (correction - expected)|| for Y+ = W W^T: how far an information-form correction
    x(k|k) - x(k|k-1) lies from the covariance form's ``expected`` = P H^T S^-1 e
    (:func:`covariance_form_terms`), in standard deviations of the posterior the filter
    reports (``info_sqrt`` = W, a square root of its information matrix). A diagnostic: no
    derivative flows through it.

    Measured in these units because a gain's rounding is harmless until it moves the mean by
    a fraction of its uncertainty: the 23-state flight SVD-EKF in float32 loses half the digits
    of many corrections (up to 3 % of their size) while straying at most 0.035 standard
    deviations; with a position sensor of variance 1e-10 it strays by up to 22 in a step and
    ends 20 off (docs/robustness.md)."""
    d, info_sqrt = jax.lax.stop_gradient((correction - expected, info_sqrt))
    return jnp.sqrt(jnp.sum((info_sqrt.T @ d) ** 2))


def gap_status(gap) -> Int[Array, ""]:
    """``INFORMATION_INCONSISTENT`` where a ``gap`` between the information and the covariance
    form (:func:`correction_gap`, :func:`inverse_gap`) exceeds :data:`INCONSISTENCY_TOLERANCE`.
    NaN sets no bit (``NONFINITE`` says it)."""
    return status_where(gap > INCONSISTENCY_TOLERANCE, InformationStatus.INFORMATION_INCONSISTENT)


def inverse_gap(info, P) -> Float[Array, ""]:
    """max |L^T Y L - I| for P = L L^T: how far the information matrix ``info`` = Y is from the
    inverse of the covariance form's P, in P's own metric (unchanged by a rescaling of the
    states): the relative error of the variance Y^-1 in its worst direction. A diagnostic like
    :func:`correction_gap`."""
    info, P = jax.lax.stop_gradient((info, P))
    L = cholesky(P)
    return jnp.max(jnp.abs(L.T @ info @ L - jnp.eye(P.shape[0], dtype=P.dtype)))


class InformationUpdate(eqx.Module):
    """The information-form measurement update shared by :class:`EKF` and
    :class:`InformationFilter` (eqs 8-10): Y+ = Y- + H^T R^-1 H and what is derived from it."""

    x_post: Float[Array, " n"]  # x(k|k-1) + P+ H^T R^-1 e (eqs 8, 10)
    P_post: Float[Array, "n n"]
    info_post: Float[Array, "n n"]  # Y+ = P+^-1
    post_chol: Float[Array, "n n"]  # its Cholesky factor
    S: Float[Array, "m m"]  # innovation covariance H P- H^T + R
    loglik: Float[Array, ""]
    status: Int[Array, ""]  # INFORMATION_INCONSISTENT (:func:`gap_status`)


def information_update(x, info_prior, P, meas) -> InformationUpdate:
    """Eqs 8-10 from x(k|k-1), the prior information matrix ``info_prior`` = P^-1 and P, with
    the likelihood term and the consistency check of :func:`covariance_form_terms`."""
    R_chol = cholesky(meas.R)
    HtR_inv = meas.H.T @ chol_inverse(R_chol)
    info_post = info_prior + symmetrize(HtR_inv @ meas.H)  # eq 9
    post_chol = cholesky(info_post)
    P_post = chol_inverse(post_chol)
    correction = P_post @ (HtR_inv @ meas.innovation)  # eqs 8, 10
    S, loglik, expected = covariance_form_terms(P, meas)
    status = gap_status(correction_gap(correction, expected, post_chol))
    return InformationUpdate(x + correction, P_post, info_post, post_chol, S, loglik, status)


class EKF(AbstractGaussianFilter):
    """The paper's EKF, eqs 6-10: covariance-mode time update
    P(k+1|k) = F P(k|k) F^T + G Q G^T (eq 7) and information-mode measurement update
    P(k|k)^-1 = P(k|k-1)^-1 + H^T R^-1 H (eq 9), K = P(k|k) H^T R^-1 (eq 10),
    x(k|k) = x(k|k-1) + K (y - h(x(k|k-1))) (eq 8). Full (correlated) R is allowed.

    The likelihood term comes from S = H P H^T + R, and a step whose correction K e strays from
    the covariance form's by more than half a posterior standard deviation raises
    ``INFORMATION_INCONSISTENT`` (:func:`covariance_form_terms`, :func:`correction_gap`): where R
    is many orders of magnitude below H P H^T the inverse of eq 9 loses its digits first
    (docs/robustness.md)."""

    factor_type = Covariance
    result_type: ClassVar[type[FilterResult]] = InformationFormResult

    def update_predict(self, model, x, factor: Covariance, k, y, u):
        P = factor.matrix
        y_pred, H, R = model.observation(x, u, k)
        meas = masked_measurement(y, y_pred, H, R)
        upd = information_update(x, inv_spd(P), P, meas)  # eqs 8-10
        x_next, P_next = covariance_predict(model, upd.x_post, upd.P_post, u, k)  # eqs 6-7
        status = step_status(x_next, P_next, upd.loglik, cov=upd.P_post) | upd.status
        out = StepOutput(x, P, upd.x_post, upd.P_post, meas.innovation, upd.S, upd.loglik, status)
        return x_next, Covariance(P_next), out


class InformationFilter(AbstractGaussianFilter):
    """The information filter: propagates Y = P^-1 and z = Y x.

    Measurement update Y+ = Y- + H^T R^-1 H, z+ = z- + H^T R^-1 (y - h(x-) + H x-); time update
    by the Woodbury form Y(k+1|k) = A - A G (Q^-1 + G^T A G)^-1 G^T A, A = F^-T Y(k|k) F^-1,
    which needs F invertible and Q positive definite (Anderson & Moore, Optimal Filtering, 6.3).
    The state holds x(k|k-1) beside Y, and the mean's update is the information vector's solved
    for x: x+ = Y+^-1 z+ = x- + Y+^-1 H^T R^-1 (y - h(x-)), without forming z = Y x and
    multiplying it back. The likelihood and ``INFORMATION_INCONSISTENT`` as for :class:`EKF`;
    the flag is also raised where Y(k+1|k) is off the inverse of F P(k|k) F^T + G Q G^T by more
    than :data:`INCONSISTENCY_TOLERANCE` (:func:`inverse_gap`): the Woodbury form subtracts
    nearly equal matrices where P(k|k) is far smaller than the process noise in some direction.
    """

    factor_type = InformationMatrix
    result_type: ClassVar[type[FilterResult]] = InformationFormResult
    needs_positive_definite_Q = True

    def update_predict(self, model, x, factor: InformationMatrix, k, y, u):
        Y = factor.info
        Y_chol = cholesky(Y)
        P = chol_inverse(Y_chol)
        y_pred, H, R = model.observation(x, u, k)
        meas = masked_measurement(y, y_pred, H, R)
        upd = information_update(x, Y, P, meas)
        x_next, F, G, Q = model.transition(upd.x_post, u, k)
        F_inv_T = jnp.linalg.inv(F).T
        A = symmetrize(F_inv_T @ upd.info_post @ F_inv_T.T)
        inner = inv_spd(Q) + G.T @ A @ G
        Y_next = symmetrize(A - A @ G @ cho_solve_lower(cholesky(inner), G.T @ A))
        P_next = predicted_cov(upd.P_post, F, G, Q)  # its covariance form
        status = step_status(x_next, Y_next, upd.loglik, cov_factor=upd.post_chol) | upd.status
        status = status | gap_status(inverse_gap(Y_next, P_next))
        out = StepOutput(x, P, upd.x_post, upd.P_post, meas.innovation, upd.S, upd.loglik, status)
        return x_next, InformationMatrix(Y_next), out


__all__ = ["EKF", "InformationFilter", "InformationFormResult", "InformationStatus", "KalmanFilter"]
