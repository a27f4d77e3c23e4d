"""SVD-based filters: P = U diag(D)^2 U^T is propagated through its SVD factors.

- :class:`SVDEKF`: Zhang, Dai & Zhang's SVD-based EKF. Time update (eqs 11-15): the SVD of the
  stacked array [D U^T F^T; Lq^T G^T] (Lq Lq^T = Q) gives U(k+1|k) = V', D(k+1|k) = D'.
  Measurement update in information form (eqs 16-23): with L L^T = R^-1 (eq 17), the SVD of
  [L^T H U; D^-1] (eq 18-19) gives U+ = U V'', D+ = D''^-1, and K = U+ D+^2 U+^T H^T L L^T
  (eq 24). The paper gives no likelihood; it is taken from S = H P H^T + R, and a step whose
  correction K e strays from the covariance form's by more than half a posterior standard
  deviation raises ``INFORMATION_INCONSISTENT``
  (:func:`~jaxest.filters.kalman.covariance_form_terms`): where R is far below H P H^T the
  information form loses its digits (docs/robustness.md).
- :class:`ImprovedSVDKF`: Kulikova & Tsyganova's covariance-form SVD filter (docs/papers/svd_ekf.md):
  no inverse of D or R, PSD Q allowed, Joseph-form covariance and the likelihood from the
  innovation's own SVD. The Joseph form carries the gain's rounding into P+ at second order,
  and where that can reach the posterior's standard deviation in some direction the step raises
  ``GAIN_ROUNDING`` (:func:`gain_rounding`).

Derivatives. The SVD's derivative is NaN when singular values repeat (P0 = c I, isotropic Q),
though every output depends on P only through U D^2 U^T. So each step is a custom JVP whose
tangent is that of the conventional covariance-form step (:func:`covariance_step`) at the same
point, mapped back to factor tangents by :func:`~jaxest.linalg.cov_tangent_to_factor`: gradients
are finite and equal the EKF's.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from jaxest._status import Status, status_where
from jaxest.filters.base import AbstractGaussianFilter, FilterResult, StepOutput, SVDFactor
from jaxest.filters.common import LOG_2PI, covariance_step, masked_measurement, step_status
from jaxest.filters.kalman import (
    InformationFormResult,
    correction_gap,
    covariance_form_terms,
    gap_status,
)
from jaxest.linalg import (
    cholesky,
    cov_from_factor,
    cov_tangent_to_factor,
    factor_psd_or_nan,
    factor_tangent_to_cov,
    keep_factors,
    right_svd,
    solve_triangular,
    symmetrize,
    tangent_or_zeros,
)

#: the Joseph form's rounding (:func:`gain_rounding`) is flagged from the size of the posterior's
#: standard deviation in some direction on
GAIN_ROUNDING_TOLERANCE = 1.0

ImprovedSVDStatus = Status.extend(
    "ImprovedSVDStatus",
    GAIN_ROUNDING=(
        4,
        "the gain's rounding, carried into P(k|k) by the Joseph form, can reach the posterior's "
        "standard deviation in some direction: the variance of the most precisely measured "
        "direction, and the mean along it, are not resolved in this dtype (a measurement "
        "combination far more precise than the prior). Use SquareRootKF, which keeps that "
        "direction, or float64 (docs/robustness.md)",
    ),
)
"""The improved SVD filter's status flags (:class:`ImprovedSVDKF`): the core's and GAIN_ROUNDING."""


class ImprovedSVDResult(FilterResult):
    """:class:`~jaxest.FilterResult` whose status bits are :data:`ImprovedSVDStatus`."""

    flags: ClassVar = ImprovedSVDStatus


def gain_rounding(K, Re, U_post, D_post) -> Float[Array, ""]:
    """max_i eps || |u_i|^T |K| || max(Re)^1/2 / d_i over P+'s singular directions u_i (the
    columns of U+, standard deviations d_i = D+_i): how far the gain's rounding can move P+
    along each, in units of its standard deviation there. A diagnostic: no derivative flows
    through it.

    The Joseph form P+ = (I - K H) P (I - K H)^T + K R K^T is stationary at the optimal gain: a
    gain K + dK gives P+ + dK S dK^T exactly, S = H P H^T + R = Q_Re diag(Re) Q_Re^T. With each
    entry of K rounded, |dK| <= eps |K|, that term adds at most
    (eps || |u|^T |K| || max(Re)^1/2)^2 to the variance along a unit vector u, and x+ moves
    along u by about as much in units of e's scale. Harmless until it is comparable to the
    variance there, which a measurement combination far more precise than the prior makes
    tiny while K grows as its inverse square root. Taken along each direction rather than as
    eps ||K|| against the smallest standard deviation, it does not count a gain's large
    entries for states in large units (metres beside milliradians) against a small variance in
    others. On the Dyer-McReynolds update (R = d^2 I) it was at most 0.29 (float32) and 0.60
    (float64) where P+'s variance along its smallest direction was right to 1 %, and above 1
    from where it was 5-7 % off (float32 d = 5e-4, float64 d = 2e-8) to where it was 10^24
    times too large (docs/robustness.md)."""
    K, Re, U_post, D_post = jax.lax.stop_gradient((K, Re, U_post, D_post))
    eps = jnp.finfo(K.dtype).eps
    along = jnp.sqrt(jnp.sum((jnp.abs(U_post).T @ jnp.abs(K)) ** 2, axis=1))
    return eps * jnp.sqrt(jnp.max(Re)) * jnp.max(along / D_post)


def gain_rounding_status(rounding) -> Int[Array, ""]:
    """``GAIN_ROUNDING`` where :func:`gain_rounding` exceeds :data:`GAIN_ROUNDING_TOLERANCE`.
    NaN sets no bit (``NONFINITE`` says it)."""
    return status_where(rounding > GAIN_ROUNDING_TOLERANCE, ImprovedSVDStatus.GAIN_ROUNDING)


def svd_time_update(U, D, F, noise_rows):
    """Eqs 13-15: U', D' of F U D^2 U^T F^T + N^T N from the SVD of [D U^T F^T; N]."""
    D_next, U_next = right_svd(jnp.concatenate([(D[:, None] * U.T) @ F.T, noise_rows]))
    return U_next, D_next


def sqrt_rows(M):
    """Rows C with C^T C = M for a symmetric PSD M, from its symmetric SVD: diag(s)^1/2 V^T
    (NaN for an indefinite M: :func:`~jaxest.linalg.factor_psd_or_nan`)."""
    V, s = factor_psd_or_nan(M)
    return s[:, None] * V.T


def paper_svd_step(model, x, U, D, y, u, k):
    """One step of the paper's SVD-EKF: measurement update (eqs 16-24), then time update (13-15).
    Its last output is the :func:`~jaxest.filters.kalman.correction_gap` of the update."""
    y_pred, H, R = model.observation(x, u, k)
    meas = masked_measurement(y, y_pred, H, R)
    R_chol = cholesky(meas.R)
    eye_m = jnp.eye(meas.R.shape[0], dtype=R.dtype)
    L = solve_triangular(R_chol, eye_m, lower=True).T  # L L^T = R^-1 (eq 17)
    s, V = right_svd(jnp.concatenate([L.T @ meas.H @ U, jnp.diag(1.0 / D)]))  # eqs 18-19
    U_post, D_post = U @ V, 1.0 / s  # eqs 21-23
    correction = cov_from_factor(U_post, D_post) @ (meas.H.T @ (L @ (L.T @ meas.innovation)))
    x_post = x + correction  # eqs 8, 24
    S, loglik, expected = covariance_form_terms(cov_from_factor(U, D), meas)
    x_next, F, G, Q = model.transition(x_post, u, k)
    U_next, D_next = svd_time_update(U_post, D_post, F, sqrt_rows(Q) @ G.T)
    gap = correction_gap(correction, expected, U_post / D_post)  # Y+ = (U+ / D+)(U+ / D+)^T
    return x_next, U_next, D_next, (x_post, U_post, D_post, meas.innovation, S, loglik, gap)


def improved_svd_step(model, x, U, D, y, u, k):
    """One step of Kulikova & Tsyganova's covariance-form SVD filter (docs/papers/svd_ekf.md).
    Its last output is the :func:`gain_rounding` of the update."""
    y_pred, H, R = model.observation(x, u, k)
    meas = masked_measurement(y, y_pred, H, R)
    R_rows = sqrt_rows(meas.R)  # D_R^1/2 Q_R^T
    # meas. 1: [D_R^1/2 Q_R^T; D-^1/2 Q-^T H^T] = W [D_Re^1/2; 0] Q_Re^T
    Re_sqrt, Q_Re = right_svd(jnp.concatenate([R_rows, (D[:, None] * U.T) @ meas.H.T]))
    P_prior = cov_from_factor(U, D)
    Kbar = P_prior @ meas.H.T @ Q_Re
    Re = Re_sqrt**2
    K = (Kbar / Re) @ Q_Re.T
    ebar = Q_Re.T @ meas.innovation
    x_post = x + Kbar @ (ebar / Re)
    # meas. 2 (Joseph): [D-^1/2 Q-^T (I-KH)^T; D_R^1/2 Q_R^T K^T] = W [D+^1/2; 0] Q+^T
    IKH = jnp.eye(x.shape[0], dtype=U.dtype) - K @ meas.H
    D_post, U_post = right_svd(jnp.concatenate([(D[:, None] * U.T) @ IKH.T, R_rows @ K.T]))
    # masked rows have unit variance and zero innovation: they add ln 1 = 0 and 0 below
    loglik = -0.5 * (meas.num_observed * LOG_2PI + jnp.sum(jnp.log(Re)) + jnp.sum(ebar**2 / Re))
    S = symmetrize((Q_Re * Re) @ Q_Re.T)
    x_next, F, G, Q = model.transition(x_post, u, k)
    U_next, D_next = svd_time_update(U_post, D_post, F, sqrt_rows(Q) @ G.T)
    rounding = gain_rounding(K, Re, U_post, D_post)
    return x_next, U_next, D_next, (x_post, U_post, D_post, meas.innovation, S, loglik, rounding)


@eqx.filter_custom_jvp
def factored_step(model, x, U, D, y, u, k, *, primal):
    """``primal(model, x, U, D, y, u, k)`` with the covariance-level derivative (module docstring)."""
    return primal(model, x, U, D, y, u, k)


@factored_step.def_jvp
def _factored_step_jvp(primals, tangents, *, primal):
    model, x, U, D, y, u, k = primals
    t_model, t_x, t_U, t_D, t_y, t_u, _ = tangents
    x_next, U_next, D_next, (x_post, U_post, D_post, e, S, loglik, diagnostic) = factored_step(
        model, x, U, D, y, u, k, primal=primal
    )
    U_next, D_next, U_post, D_post = keep_factors(U_next, D_next, U_post, D_post)
    out = x_next, U_next, D_next, (x_post, U_post, D_post, e, S, loglik, diagnostic)
    dP = factor_tangent_to_cov(U, D, tangent_or_zeros(t_U, U), tangent_or_zeros(t_D, D))
    ref = lambda model, x, P, y, u: covariance_step(model, x, P, y, u, k)
    _, (dx_next, dP_next, d_outputs) = eqx.filter_jvp(
        ref,
        (model, x, cov_from_factor(U, D), y, u),
        (t_model, tangent_or_zeros(t_x, x), dP, t_y, t_u),
    )
    dU_next, dD_next = cov_tangent_to_factor(U_next, D_next, symmetrize(dP_next))
    dx_post, dP_post, de, dS, dloglik = d_outputs
    dU_post, dD_post = cov_tangent_to_factor(U_post, D_post, symmetrize(dP_post))
    d_outputs = (dx_post, dU_post, dD_post, de, dS, dloglik, None)  # no derivative
    d_outputs = jax.tree.map(
        tangent_or_zeros,
        d_outputs,
        (x_post, U_post, D_post, e, S, loglik, diagnostic),
        is_leaf=lambda t: t is None,
    )
    return out, (dx_next, dU_next, dD_next, d_outputs)


class AbstractSVDFilter(AbstractGaussianFilter):
    """An SVD filter: P = U diag(D)^2 U^T propagated through its factors by the class-level
    ``svd_step`` (one of :func:`paper_svd_step`, :func:`improved_svd_step`), differentiated
    at the covariance level (module docstring); the step's last output, a diagnostic of its
    update, gives its own status bit through the class-level ``diagnostic_status``. Saved with
    ``SaveAt(fields=(..., "factor"))`` it also returns the factors U, D of P(k|k) and P(k|k-1)."""

    factor_type = SVDFactor
    svd_step: ClassVar[staticmethod]
    diagnostic_status: ClassVar[staticmethod]

    def update_predict(self, model, x, factor: SVDFactor, k, y, u):
        x_next, U_next, D_next, (x_post, U_post, D_post, e, S, loglik, diagnostic) = factored_step(
            model, x, factor.U, factor.D, y, u, k, primal=self.svd_step
        )
        P_post = cov_from_factor(U_post, D_post)
        status = step_status(x_next, U_next, D_next, P_post, loglik, positive=jnp.all(D_next > 0))
        status = status | self.diagnostic_status(diagnostic)
        out = StepOutput(
            x, factor.cov, x_post, P_post, e, S, loglik, status,
            predicted_factor=factor, factor=SVDFactor(U_post, D_post),
        )  # fmt: skip
        return x_next, SVDFactor(U_next, D_next), out


class SVDEKF(AbstractSVDFilter):
    """The paper's SVD-based EKF (eqs 11-25). R positive definite (R^-1 is formed); Q may be
    singular, Q = 0 included (its square root comes from a symmetric eigendecomposition), as
    long as P stays positive definite (D^-1 is formed in the measurement update). Its status
    bits are :data:`~jaxest.filters.kalman.InformationStatus`."""

    result_type: ClassVar[type[FilterResult]] = InformationFormResult
    svd_step: ClassVar[staticmethod] = staticmethod(paper_svd_step)
    diagnostic_status: ClassVar[staticmethod] = staticmethod(gap_status)


class ImprovedSVDKF(AbstractSVDFilter):
    """Kulikova & Tsyganova's improved covariance-form SVD filter (docs/papers/svd_ekf.md). Its
    status bits are :data:`ImprovedSVDStatus`."""

    result_type: ClassVar[type[FilterResult]] = ImprovedSVDResult
    svd_step: ClassVar[staticmethod] = staticmethod(improved_svd_step)
    diagnostic_status: ClassVar[staticmethod] = staticmethod(gain_rounding_status)
