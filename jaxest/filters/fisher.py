"""The derivative of the Kalman filter's log-likelihood on a linear-Gaussian model in closed form,
by Fisher's identity, instead of autodiff through the recursion.

For x_{k+1} = F_k x_k + B_k u_k + w_k, w_k ~ N(0, Q_k), y_k = H_k x_k + D_k u_k + v_k,
v_k ~ N(0, R_k), x_0 ~ N(m0, P0) and any parameter theta (the matrices, the prior, the
measurements y_k or the inputs u_k), p(y) = int p(x, y) dx gives Fisher's identity

    d/dtheta log p(y | theta) = E[ d/dtheta log p(x, y | theta) | y ],                    (1)

the expectation over the smoothed posterior p(x | y, theta). With the posterior held at theta_hat
(the RTS smoother's x(k|T), P(k|T) and lag-one cross covariances C_k = P(k+1,k|T), a
:class:`~jaxest.SmootherResult`), (1) is the gradient at theta = theta_hat of the expected
complete-data log-likelihood (the EM objective of :mod:`jaxest.em`), up to constants

    L(theta) = l(x_0 - m0, P0)  +  sum_{k=0}^{T-2} l(x_{k+1} - F_k x_k - B_k u_k, Q_k)
             + sum_{k=0}^{T-1} l(y_k - H_k x_k - D_k u_k, R_k),                           (2)

    l(r, S) = E[ -1/2 ln det S - 1/2 r^T S^-1 r ]
            = -1/2 ln det S - 1/2 tr( S^-1 (Cov r + E[r] E[r]^T) ),                       (3)

with Cov(x_{k+1} - F x_k) = P(k+1|T) - F C_k^T - C_k F^T + F P(k|T) F^T and
Cov(y_k - H x_k) = H P(k|T) H^T. Written out (symmetric S; r_bar = E[r]):

    dL/dS  = 1/2 S^-1 (Cov r + r_bar r_bar^T - S) S^-1        for S = P0, Q_k, R_k,
    dL/dm0 = P0^-1 (x(0|T) - m0),
    dL/dF_k = Q_k^-1 (r_bar x(k|T)^T + C_k - F_k P(k|T)),      dL/dB_k = Q_k^-1 r_bar u_k^T,
    dL/dH_k = R_k^-1 (e_bar x(k|T)^T - H_k P(k|T)),            dL/dD_k = R_k^-1 e_bar u_k^T,
    dL/dy_k = -R_k^-1 e_bar,   dL/du_k = B_k^T Q_k^-1 r_bar + D_k^T R_k^-1 e_bar,        (4)

e_bar = y_k - H_k x(k|T) - D_k u_k. Here they are not formed: the rule's tangent, their inner
product with the parameters' tangents, is ``jax.jvp`` of (2)-(3) at the fixed smoothed moments,
through the model's own ``transition`` / ``observation`` (time-varying matrices and inputs
included), and (3) carries its own derivative in closed form (:func:`expected_logpdf`).
Missing (NaN) entries of y_k leave their term out: (2) is written with the filter's masked
measurement (:func:`~jaxest.filters.common.masked_measurement`), whose R has the observed block
and an identity elsewhere and whose H rows and innovation are zero there, so the missing rows
add a constant and their entries of R, H, D and y_k get zero gradient, as in autodiff.

(1) needs the filter's log-likelihood to be log p(y) exactly, which the Kalman filter's is on a
linear-Gaussian model, and (3) needs P0, Q_k and R_k to have densities. Models with a noise gain
G are left to autodiff (G Q G^T may be singular), and so are runs whose P0 or Q is singular or
nearly so (:func:`has_density`) where :func:`jaxest.run` sees their values
(``KalmanFilter.for_arguments``); where it sees only tracers (under ``jit``), the rule's
tangent is NaN at such a covariance rather than a wrong number. Cost: one RTS smoother and a
batched (not sequential) evaluation of (3) over the steps, against autodiff's reverse sweep
through every step of the filter.
Covariance gradients are symmetric: they are the derivatives along symmetric perturbations (the
filter uses P0 unsymmetrised, so autodiff's gradient for it need not be symmetric; the symmetric
parts agree).

The rule is a ``custom_jvp``: its tangent is that inner product, linear in the parameters'
tangents, so reverse mode (``grad``) transposes it and forward mode (``jvp``, ``jax.hessian`` =
forward over reverse) differentiates the smoother and (4) by autodiff, which is exact: (4)
equals the gradient of log p(y) at every theta. A forward-mode derivative of (2) is what the
rule needs; it also traces faster than the gradient and an inner product (the linear 4 x 2
Kalman log-likelihood's gradient: 0.73 against 0.85 s).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxest.filters.base import FilterResult
from jaxest.filters.common import masked_measurement
from jaxest.linalg import chol_inverse, cholesky, logdet_chol, mm, mv, symmetrize
from jaxest.smoothers.rts import SmootherResult, rts_smooth


@jax.custom_jvp
def expected_logpdf(residual_mean, residual_cov, cov):
    """Eq (3): E[ln N(r; 0, S)] + const for r with the given mean and covariance, S = ``cov``
    (symmetrised, so its gradient is symmetric). S^-1 is formed, not solved with: under ``vmap``
    over the steps a time-invariant S is then factored and inverted once.

    Differentiated by eq (4)'s dL/dS, with dL/d(Cov r) = -1/2 S^-1 and dL/dr_bar = -S^-1 r_bar,
    not by autodiff through the Cholesky factor and the inverse: the gradient of (2) then traces
    and compiles about a fifth faster (linear 4 x 2 and 6 x 3 Kalman log-likelihoods)."""
    return _expected_logpdf_terms(residual_mean, residual_cov, cov)[0]


def _expected_logpdf_terms(residual_mean, residual_cov, cov):
    """Eq (3)'s value, S^-1 and M = Cov r + r_bar r_bar^T."""
    L = cholesky(symmetrize(cov))
    S_inv = chol_inverse(L)
    second_moment = residual_cov + jnp.outer(residual_mean, residual_mean)
    return -0.5 * (logdet_chol(L) + jnp.sum(S_inv * second_moment)), S_inv, second_moment


def has_density(cov) -> jax.Array:
    """Whether eq (3) can be evaluated for S = ``cov``: its Cholesky factor exists, and the
    squared ratio of its largest to its smallest pivot, a lower bound on cond(S), stays within
    n cond eps <= 2^-10 (a singular Q, such as a noise that drives some states only, factors
    with a pivot of rounding size, and (4) then multiplies rounding errors by S^-1)."""
    diagonal = jnp.diagonal(cholesky(symmetrize(cov)))
    n = diagonal.shape[-1]
    kappa = (jnp.max(diagonal) / jnp.min(diagonal)) ** 2
    return jnp.all(jnp.isfinite(diagonal)) & (n * kappa * jnp.finfo(diagonal.dtype).eps <= 2**-10)


@expected_logpdf.defjvp
def _expected_logpdf_jvp(primals, tangents):
    """dL/dS = 1/2 S^-1 (M - S) S^-1 (eq (4)), symmetrised, and the two gradients above. The
    tangent is linear in (dr_bar, d Cov r, dS) through element-wise products and a dot, so reverse
    mode transposes it (``mm`` only on primals: ``jaxest.linalg.mm`` says why)."""
    residual_mean, _, _ = primals
    d_mean, d_residual_cov, d_cov = tangents
    value, S_inv, second_moment = _expected_logpdf_terms(*primals)
    d_value_d_cov = 0.5 * (symmetrize(mm(mm(S_inv, second_moment), S_inv)) - S_inv)
    tangent = (
        jnp.sum(d_value_d_cov * d_cov)
        - 0.5 * jnp.sum(S_inv * d_residual_cov)
        - jnp.vdot(mv(S_inv, residual_mean), d_mean)
    )
    # NaN, not a wrong number, where S has no density that (3) can use (:func:`has_density`)
    return value, tangent * jnp.where(has_density(primals[2]), 1.0, jnp.nan)


def expected_complete_loglik(model, prior, ys, inputs, ks, mo: SmootherResult):
    """Eq (2) at the parameters (model, prior, ys, inputs) for the fixed smoothed moments ``mo``."""
    T = ys.shape[0]
    u_now = None if inputs is None else jax.tree.map(lambda a: a[:-1], inputs)

    def dynamics(k, mean, cov, mean_next, cov_next, cross, u):
        pred, F, _, Q = model.transition(mean, u, k)
        FC = mm(F, cross.T)
        residual_cov = cov_next - FC - FC.T + mm(mm(F, cov), F.T)
        return expected_logpdf(mean_next - pred, residual_cov, Q)

    def measurement(k, mean, cov, y, u):
        y_pred, H, R = model.observation(mean, u, k)
        meas = masked_measurement(y, y_pred, H, R)
        return expected_logpdf(meas.innovation, mm(mm(meas.H, cov), meas.H.T), meas.R)

    first = expected_logpdf(mo.mean[0] - prior.mean, mo.cov[0], prior.cov)
    steps = jax.vmap(dynamics)(
        ks[: T - 1], mo.mean[:-1], mo.cov[:-1], mo.mean[1:], mo.cov[1:], mo.cross_cov, u_now
    )
    observations = jax.vmap(measurement)(ks, mo.mean, mo.cov, ys, inputs)
    return first + jnp.sum(steps) + jnp.sum(observations)


@jax.custom_jvp
def fisher_loglik(loglik, model, prior, ys, inputs, ks, filtered: FilterResult):
    """``loglik`` (the Kalman filter's log p(y) of ``model``, no G, from ``prior`` over ``ys``
    with time indices ``ks``), differentiated by eqs (1)-(4) (module docstring). ``filtered``:
    that run's result with the fields the smoother needs (:func:`jaxest.run` keeps them for
    this rule whatever the caller saves: ``KalmanFilter.derivative_fields``)."""
    return loglik


@fisher_loglik.defjvp
def _fisher_loglik_jvp(primals, tangents):
    loglik, model, prior, ys, inputs, ks, filtered = primals
    _, d_model, d_prior, d_ys, d_inputs, _, _ = tangents
    moments = rts_smooth(model, filtered, inputs=inputs, k0=ks[0])
    _, tangent = jax.jvp(
        lambda *params: expected_complete_loglik(*params, ks, moments),
        (model, prior, ys, inputs),
        (d_model, d_prior, d_ys, d_inputs),
    )
    return loglik, tangent
