"""Square-root (Cholesky/QR array) Kalman filter: propagates S with P = S S^T.

Time update: QR of the stacked array [S^T F^T; Lq^T G^T] (Lq Lq^T = Q) gives S(k+1|k) as the
transposed triangular factor. Measurement update: the array algorithm on the pre-array
[[Lr, H S], [0, S]] (Lr Lr^T = R): its lower-triangular post-array [[Se, 0], [Kbar, S+]] holds the
innovation factor Se (S_e = Se Se^T), the normalised gain Kbar = K Se and S(k|k).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from jaxest.filters.common import (
    StepOutput,
    check_prior,
    gaussian_loglik,
    masked_measurement,
    pack_result,
    step_status,
)


class SqrtState(eqx.Module):
    """x(k|k-1), lower factor S of P(k|k-1) and the time index k."""

    mean: Float[Array, " n"]
    chol: Float[Array, "n n"]
    k: Int[Array, ""]


def lower_factor(pre_array_transposed):
    """The lower-triangular L with L L^T = A A^T, for A^T given (QR of A^T)."""
    return jnp.linalg.qr(pre_array_transposed, mode="r").T


class SquareRootKF(eqx.Module):
    """Square-root covariance Kalman filter (EKF on nonlinear models). Q and R positive definite."""

    def init(self, model, prior) -> SqrtState:
        prior = check_prior(prior)
        return SqrtState(prior.mean, jnp.linalg.cholesky(prior.cov), jnp.zeros((), jnp.int32))

    def step(self, model, state: SqrtState, y, u):
        x, S, k = state.mean, state.chol, state.k
        n = x.shape[0]
        y_pred, H, R = model.observation(x, u, k)
        meas = masked_measurement(y, y_pred, H, R)
        m = meas.R.shape[0]
        pre = jnp.block(
            [[jnp.linalg.cholesky(meas.R), meas.H @ S], [jnp.zeros((n, m), S.dtype), S]]
        )
        post = lower_factor(pre.T)
        Se, Kbar, S_post = post[:m, :m], post[m:, :m], post[m:, m:]
        whitened = jax.scipy.linalg.solve_triangular(Se, meas.innovation, lower=True)
        x_post = x + Kbar @ whitened
        loglik = gaussian_loglik(whitened, Se, meas.num_observed)
        x_next, F, G, Q = model.transition(x_post, u, k)
        S_next = lower_factor(jnp.concatenate([S_post.T @ F.T, jnp.linalg.cholesky(Q).T @ G.T]))
        P_post = S_post @ S_post.T
        status = step_status(x_next, S_next, loglik, positive=jnp.all(jnp.diag(S_post) != 0))
        out = StepOutput(x, S @ S.T, x_post, P_post, meas.innovation, Se @ Se.T, loglik, status)
        return SqrtState(x_next, S_next, k + 1), out

    result = staticmethod(pack_result)
