"""The derivative of the Kalman filter's log-likelihood on a linear-Gaussian model in closed form,
by Fisher's identity, instead of autodiff through the recursion.

For x_{k+1} = F_k x_k + B_k u_k + w_k, w_k ~ N(0, Q_k), y_k = H_k x_k + D_k u_k + v_k,
v_k ~ N(0, R_k), x_0 ~ N(m0, P0) and any parameter theta (the matrices, the prior, the
measurements y_k or the inputs u_k), p(y) = int p(x, y) dx gives Fisher's identity

    d/dtheta log p(y | theta) = E[ d/dtheta log p(x, y | theta) | y ],                    (1)

the expectation over the smoothed posterior. Taken term by term over log p(x, y) (the prior's,
each transition's and each measurement's Gaussian log-density), with the smoothed moments of
the disturbances x_0 - m0, w_k and v_k written by the disturbance smoother (Koopman and
Shephard, "Exact score for time series models in state space form", Biometrika 1992; Durbin
and Koopman, *Time Series Analysis by State Space Methods*, 2nd ed., sections 4.5 and 7.3.3):

    d log p(y) = 1/2 <rho_0 rho_0^T - N_0, dP0> + rho_0^T dm0
               + sum_{k=0}^{T-2} 1/2 <rho_{k+1} rho_{k+1}^T - N_{k+1}, dQ_k>
                                 + rho_{k+1}^T (dF_k x(k|T) + dB_k u_k)
                                 - <dF_k, N_{k+1} F_k P(k|k)>
               + sum_{k=0}^{T-1} 1/2 <w_k w_k^T - D_k, dR_k>
                                 + w_k^T (dH_k x(k|T) + dD_k u_k - dy_k)
                                 - <dH_k, Z_k^T>,                                         (2)

<A, B> = sum_ij A_ij B_ij. The quantities come from one backward pass over the filter's steps,
with e_k, S_k = H_k P(k|k-1) H_k^T + R_k and K_k = P(k|k-1) H_k^T S_k^-1 the innovation, its
covariance and the gain of the filter's update at k (P(0|-1) = P0), from rho_T = 0, N_T = 0:

    lambda_k = F_k^T rho_{k+1},             Lambda_k = F_k^T N_{k+1} F_k,
    w_k   = S_k^-1 e_k - K_k^T lambda_k,    D_k = S_k^-1 + K_k^T Lambda_k K_k,
    rho_k = H_k^T w_k + lambda_k,           N_k = H_k^T S_k^-1 H_k
                                                  + (I - K_k H_k)^T Lambda_k (I - K_k H_k),
    x(k|T) = x(k|k) + P(k|k) lambda_k,      Z_k = (I - P(k|k) Lambda_k) K_k.              (3)

They are the disturbances' smoothed moments scaled by their covariances' inverses:
rho_{k+1} = Q_k^-1 E[w_k | y] and N_{k+1} = Q_k^-1 (Q_k - Cov[w_k | y]) Q_k^-1, w_k and D_k
the same for v_k with R_k, rho_0 and N_0 for x_0 - m0 with P0; N_{k+1} F_k P(k|k) = -Q_k^-1
Cov[w_k, x_k | y] and Z_k = -Cov[x_k, v_k | y] R_k^-1. Formed so, no covariance but S_k is
inverted: (2) holds at a singular Q_k or P0 too (log p(y) is smooth there), and nothing is lost
to rounding where Q_k or R_k is far below the state's uncertainty. The form this module had
before, 1/2 Q^-1 (Cov r + r_bar r_bar^T - Q) Q^-1 with Cov r = P(k+1|T) - F C^T - C F^T +
F P(k|T) F^T from the RTS smoother, subtracts covariances of the state's size and multiplies the
difference by Q^-1 twice (R^-1 likewise): with the prior's variance 1, at Q = 1e-12 its
gradient in Q was off by half its size in float64 and by 7e7 times in float32, and at R = 1e-7
its gradient in H by 17 % in float32; this form is within 2e-12 (float64) and 1.1e-4 (float32,
where autodiff is within 6.2e-4) of float64 autodiff on the same grid
(``benchmarks/fisher_rule.py``).

Missing (NaN) entries of y_k leave their term out: (2) and (3) are written with the filter's
masked measurement (:func:`~jaxest.filters.common.masked_measurement`), whose R has the observed
block and an identity elsewhere and whose H rows and innovation are zero there, so the missing
rows get w = 0 and zero gradient in their entries of R, H, D and y_k, as in autodiff.

(1) needs the filter's log-likelihood to be log p(y) exactly, which the Kalman filter's is on a
linear-Gaussian model; models with a noise gain G are left to autodiff. Covariance gradients
are symmetric: they are the derivatives along symmetric perturbations (the filter uses P0
unsymmetrised, so autodiff's gradient for it need not be symmetric; the symmetric parts agree).
Cost: the backward pass (3) and a batched (not sequential) evaluation of (2) over the steps,
against autodiff's reverse sweep through every step of the filter.

The rule is a ``custom_jvp``: its tangent is (2), linear in the parameters' tangents, taken by
``jax.jvp`` of :func:`score_surrogate` through the model's own ``transition`` / ``observation``
(time-varying matrices and inputs included) with (3) held fixed. Reverse mode (``grad``)
transposes it, and forward mode (``jvp``, ``jax.hessian`` = forward over reverse)
differentiates (3) by autodiff, which is exact: (2) equals the gradient of log p(y) at every
theta.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from jaxest.filters.base import FilterResult
from jaxest.filters.common import masked_measurement
from jaxest.linalg import chol_inverse, cholesky, mm, mv, symmetrize

#: the fields of the filter's result that :func:`disturbance_smooth` reads
NEEDED = ("mean", "cov", "predicted_mean", "predicted_cov")


class Scores(eqx.Module):
    """Eq (3) at every step k: what (2) multiplies the parameters' tangents by."""

    rho: Float[Array, "T n"]
    N: Float[Array, "T n n"]
    w: Float[Array, "T m"]
    D: Float[Array, "T m m"]
    Z: Float[Array, "T n m"]
    cross: Float[Array, "T n n"]  #: N_{k+1} F_k P(k|k), the last step's zero
    smoothed_mean: Float[Array, "T n"]


def disturbance_smooth(model, filtered: FilterResult, ys, inputs, ks) -> Scores:
    """Eq (3): the backward pass over a Kalman filter's run of ``model`` (its predicted and
    filtered means and covariances in ``filtered``) over ``ys`` at time indices ``ks``."""
    n = filtered.mean.shape[-1]

    def backward(carry, args):
        rho_next, N_next = carry
        k, pred_mean, pred_cov, mean, cov, y, u = args
        _, F, _, _ = model.transition(mean, u, k)
        lam, Lam = mv(F.T, rho_next), symmetrize(mm(mm(F.T, N_next), F))
        y_pred, H, R = model.observation(pred_mean, u, k)
        meas = masked_measurement(y, y_pred, H, R)
        PHt = mm(pred_cov, meas.H.T)
        S_inv = chol_inverse(cholesky(symmetrize(mm(meas.H, PHt) + meas.R)))
        K = mm(PHt, S_inv)
        I_KH = jnp.eye(n, dtype=K.dtype) - mm(K, meas.H)
        w = mv(S_inv, meas.innovation) - mv(K.T, lam)
        D = symmetrize(S_inv + mm(mm(K.T, Lam), K))
        rho = mv(meas.H.T, w) + lam
        N = symmetrize(mm(mm(meas.H.T, S_inv), meas.H) + mm(mm(I_KH.T, Lam), I_KH))
        Z = K - mm(mm(cov, Lam), K)
        cross = mm(mm(N_next, F), cov)
        return (rho, N), Scores(rho, N, w, D, Z, cross, mean + mv(cov, lam))

    zeros = jnp.zeros_like(filtered.mean[0])
    last = (zeros, jnp.zeros_like(filtered.cov[0]))
    args = (
        ks, filtered.predicted_mean, filtered.predicted_cov, filtered.mean, filtered.cov, ys,
        inputs,
    )  # fmt: skip
    return jax.lax.scan(backward, last, args, reverse=True)[1]


def score_surrogate(model, prior, ys, inputs, ks, scores: Scores):
    """A function of the parameters (model, prior, ys, inputs) whose tangent, with ``scores``
    held fixed, is eq (2); its value is not used."""
    T = ys.shape[0]
    u_now = None if inputs is None else jax.tree.map(lambda a: a[:-1], inputs)

    def dynamics(k, mean, u, rho_next, N_next, cross):
        pred, F, _, Q = model.transition(mean, u, k)
        second = jnp.outer(rho_next, rho_next) - N_next
        return 0.5 * jnp.sum(second * Q) + jnp.vdot(rho_next, pred) - jnp.sum(F * cross)

    def measurement(k, mean, y, u, w, D, Z):
        y_pred, H, R = model.observation(mean, u, k)
        meas = masked_measurement(y, y_pred, H, R)
        second = jnp.outer(w, w) - D
        return 0.5 * jnp.sum(second * meas.R) - jnp.vdot(w, meas.innovation) - jnp.sum(meas.H * Z.T)

    sc = scores
    first = 0.5 * jnp.sum((jnp.outer(sc.rho[0], sc.rho[0]) - sc.N[0]) * prior.cov)
    first = first + jnp.vdot(sc.rho[0], prior.mean)
    steps = jax.vmap(dynamics)(
        ks[: T - 1], sc.smoothed_mean[:-1], u_now, sc.rho[1:], sc.N[1:], sc.cross[:-1]
    )
    observations = jax.vmap(measurement)(ks, sc.smoothed_mean, ys, inputs, sc.w, sc.D, sc.Z)
    return first + jnp.sum(steps) + jnp.sum(observations)


@jax.custom_jvp
def fisher_loglik(loglik, model, prior, ys, inputs, ks, filtered: FilterResult):
    """``loglik`` (the Kalman filter's log p(y) of ``model``, no G, from ``prior`` over ``ys``
    with time indices ``ks``), differentiated by eqs (1)-(3) (module docstring). ``filtered``:
    that run's result with the fields the backward pass needs (:func:`jaxest.run` keeps them
    for this rule whatever the caller saves: ``KalmanFilter.derivative_fields``)."""
    return loglik


@fisher_loglik.defjvp
def _fisher_loglik_jvp(primals, tangents):
    loglik, model, prior, ys, inputs, ks, filtered = primals
    _, d_model, d_prior, d_ys, d_inputs, _, _ = tangents
    scores = disturbance_smooth(model, filtered, ys, inputs, ks)
    _, tangent = jax.jvp(
        lambda *params: score_surrogate(*params, ks, scores),
        (model, prior, ys, inputs),
        (d_model, d_prior, d_ys, d_inputs),
    )
    return loglik, tangent
