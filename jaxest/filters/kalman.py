"""Covariance-form Kalman filter / EKF (Joseph update), the paper's EKF (covariance time update,
information-form measurement update, eqs 6-10 of Zhang, Dai & Zhang) and the information filter.

On a :class:`~jaxest.LinearGaussian` model each is an exact Kalman filter; on a
:class:`~jaxest.NonlinearGaussian` model each linearises f at x(k|k) and h at x(k|k-1) (EKF).
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from jaxest._checks import is_concrete
from jaxest.filters.base import (
    AbstractGaussianFilter,
    Covariance,
    FilterResult,
    InformationMatrix,
    StepOutput,
)
from jaxest.filters.common import (
    LOG_2PI,
    covariance_predict,
    covariance_step,
    masked_measurement,
    step_status,
)
from jaxest.filters.fisher import fisher_loglik, has_density
from jaxest.linalg import (
    cho_solve_lower,
    chol_inverse,
    cholesky,
    inv_spd,
    logdet_chol,
    symmetrize,
)
from jaxest.models import LinearGaussian
from jaxest.smoothers.rts import NEEDED

#: :func:`~jaxest.filters.fisher.has_density` of a stack of covariances, compiled once per shape
_have_densities = jax.jit(jax.vmap(has_density))


class KalmanFilter(AbstractGaussianFilter):
    """The conventional covariance-form Kalman filter (EKF on nonlinear models) with the Joseph
    form P+ = (I - K H) P (I - K H)^T + K R K^T of the measurement update.

    ``closed_form_gradient``: on a :class:`~jaxest.LinearGaussian` model without ``G``, run
    from a prior (not resumed from a state), the total log-likelihood ``result.loglik`` is
    differentiated by Fisher's identity (an RTS smoother, :mod:`jaxest.filters.fisher`) instead
    of autodiff through the steps: the same gradient, value_and_grad 1.3-2.3x faster in
    docs/performance.md. Every other output, and every other model, is differentiated by
    autodiff, and so is a run whose P0 or Q is singular or nearly so where :func:`jaxest.run`
    sees their values; under ``jit`` with such a covariance traced the rule's gradient is NaN
    (:func:`jaxest.filters.fisher.has_density`): pass ``False`` there. ``False``: autodiff
    everywhere.
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

    def for_arguments(self, model, prior) -> KalmanFilter:
        """Autodiff instead of the Fisher rule where P0 or a Q_k that :func:`jaxest.run` sees
        has no density the rule can use (:func:`jaxest.filters.fisher.has_density`)."""
        if not self._closed_form(model):
            return self
        if not (is_concrete(prior.cov) and is_concrete(model.Q)):
            return self  # under jit the rule's tangent is NaN at such a covariance instead
        n = jnp.shape(prior.cov)[-1]
        with jax.ensure_compile_time_eval():  # evaluated now, also inside a caller's jit
            covariances = jnp.concatenate(
                [jnp.reshape(c, (-1, n, n)) for c in (prior.cov, model.Q)]
            )
            if bool(jnp.all(_have_densities(covariances))):
                return self
        return dataclasses.replace(self, closed_form_gradient=False)

    def derivative_fields(self, model) -> tuple[str, ...]:
        return NEEDED if self._closed_form(model) else ()

    def with_derivatives(self, result: FilterResult, model, prior, ys, inputs, ks):
        if not self._closed_form(model):
            return result
        filtered = FilterResult(result.final_state, **{f: getattr(result, f) for f in NEEDED})
        loglik = fisher_loglik(result.loglik, model, prior, ys, inputs, ks, filtered)
        return eqx.tree_at(lambda r: r.final_state.loglik, result, loglik)


def information_loglik(e, R_inv, b, P_post, logdet_R, logdet_prior, logdet_post, num_observed):
    """log N(e; 0, S), S = H P- H^T + R, from information-form quantities (matrix determinant
    lemma and Woodbury): ln det S = ln det R + ln det P- - ln det P+,
    e^T S^-1 e = e^T R^-1 e - b^T P+ b with b = H^T R^-1 e."""
    quad = e @ R_inv @ e - b @ P_post @ b
    return -0.5 * (num_observed * LOG_2PI + logdet_R + logdet_prior - logdet_post + quad)


class InformationUpdate(eqx.Module):
    """The information-form measurement update shared by :class:`EKF` and
    :class:`InformationFilter` (eq 9): Y+ = Y- + H^T R^-1 H and what is derived from it."""

    P_post: Float[Array, "n n"]
    info_post: Float[Array, "n n"]  # Y+ = P+^-1
    post_chol: Float[Array, "n n"]  # its Cholesky factor
    HtR_inv: Float[Array, "n m"]  # H^T R^-1
    b: Float[Array, " n"]  # H^T R^-1 e
    S: Float[Array, "m m"]  # innovation covariance H P- H^T + R
    loglik: Float[Array, ""]


def information_update(info_prior, P, logdet_prior, meas) -> InformationUpdate:
    """Eq 9 from the prior information matrix ``info_prior`` = P^-1 (and ln det P), with the
    likelihood term of :func:`information_loglik`."""
    R_chol = cholesky(meas.R)
    R_inv = chol_inverse(R_chol)
    HtR_inv = meas.H.T @ R_inv
    b = HtR_inv @ meas.innovation
    info_post = info_prior + symmetrize(HtR_inv @ meas.H)
    post_chol = cholesky(info_post)
    P_post = chol_inverse(post_chol)
    loglik = information_loglik(
        meas.innovation, R_inv, b, P_post,
        logdet_chol(R_chol), logdet_prior, -logdet_chol(post_chol), meas.num_observed,
    )  # fmt: skip
    S = symmetrize(meas.H @ P @ meas.H.T + meas.R)
    return InformationUpdate(P_post, info_post, post_chol, HtR_inv, b, S, loglik)


class EKF(AbstractGaussianFilter):
    """The paper's EKF, eqs 6-10: covariance-mode time update
    P(k+1|k) = F P(k|k) F^T + G Q G^T (eq 7) and information-mode measurement update
    P(k|k)^-1 = P(k|k-1)^-1 + H^T R^-1 H (eq 9), K = P(k|k) H^T R^-1 (eq 10),
    x(k|k) = x(k|k-1) + K (y - h(x(k|k-1))) (eq 8). Full (correlated) R is allowed."""

    factor_type = Covariance

    def update_predict(self, model, x, factor: Covariance, k, y, u):
        P = factor.matrix
        y_pred, H, R = model.observation(x, u, k)
        meas = masked_measurement(y, y_pred, H, R)
        P_chol = cholesky(P)
        upd = information_update(chol_inverse(P_chol), P, logdet_chol(P_chol), meas)  # eq 9
        x_post = x + upd.P_post @ upd.b  # eqs 8, 10
        x_next, P_next = covariance_predict(model, x_post, upd.P_post, u, k)  # eqs 6-7
        status = step_status(x_next, P_next, upd.loglik, cov=upd.P_post)
        out = StepOutput(x, P, x_post, upd.P_post, meas.innovation, upd.S, upd.loglik, status)
        return x_next, Covariance(P_next), out


class InformationFilter(AbstractGaussianFilter):
    """The information filter: propagates Y = P^-1 and z = Y x.

    Measurement update Y+ = Y- + H^T R^-1 H, z+ = z- + H^T R^-1 (y - h(x-) + H x-); time update
    by the Woodbury form Y(k+1|k) = A - A G (Q^-1 + G^T A G)^-1 G^T A, A = F^-T Y(k|k) F^-1,
    which needs F invertible and Q positive definite (Anderson & Moore, Optimal Filtering, 6.3).
    The state holds x(k|k-1) beside Y; the information vector z = Y x is formed where used.
    """

    factor_type = InformationMatrix
    needs_positive_definite_Q = True

    def update_predict(self, model, x, factor: InformationMatrix, k, y, u):
        Y = factor.info
        Y_chol = cholesky(Y)
        P = chol_inverse(Y_chol)
        y_pred, H, R = model.observation(x, u, k)
        meas = masked_measurement(y, y_pred, H, R)
        upd = information_update(Y, P, -logdet_chol(Y_chol), meas)
        x_post = upd.P_post @ (Y @ x + upd.HtR_inv @ (meas.H @ x) + upd.b)
        x_next, F, G, Q = model.transition(x_post, u, k)
        F_inv_T = jnp.linalg.inv(F).T
        A = symmetrize(F_inv_T @ upd.info_post @ F_inv_T.T)
        inner = inv_spd(Q) + G.T @ A @ G
        Y_next = symmetrize(A - A @ G @ cho_solve_lower(cholesky(inner), G.T @ A))
        status = step_status(x_next, Y_next, upd.loglik, cov_factor=upd.post_chol)
        out = StepOutput(x, P, x_post, upd.P_post, meas.innovation, upd.S, upd.loglik, status)
        return x_next, InformationMatrix(Y_next), out


__all__ = ["EKF", "InformationFilter", "KalmanFilter"]
