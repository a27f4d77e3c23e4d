"""Square-root (Cholesky/QR array) Kalman filter: propagates S with P = S S^T.

Time update: QR of the stacked array [S^T F^T; Lq^T G^T] (Lq Lq^T = Q) gives S(k+1|k) as the
transposed triangular factor. Measurement update: the array algorithm on the pre-array
[[Lr, H S], [0, S]] (Lr Lr^T = R): its lower-triangular post-array [[Se, 0], [Kbar, S+]] holds the
innovation factor Se (S_e = Se Se^T), the normalised gain Kbar = K Se and S(k|k).
"""

from __future__ import annotations

import jax.numpy as jnp

from jaxest.filters.base import AbstractGaussianFilter, CholeskyFactor, StepOutput
from jaxest.filters.common import gaussian_loglik, masked_measurement, step_status
from jaxest.linalg import cholesky, solve_triangular, tria


class SquareRootKF(AbstractGaussianFilter):
    """Square-root covariance Kalman filter (EKF on nonlinear models). Q and R positive definite.

    Saved with ``SaveAt(fields=(..., "factor", "predicted_factor"))`` it also returns the
    Cholesky factors S(k|k) and S(k|k-1) it propagates.
    """

    factor_type = CholeskyFactor
    needs_positive_definite_Q = True

    def update_predict(self, model, x, factor: CholeskyFactor, k, y, u):
        S = factor.chol
        n = x.shape[0]
        y_pred, H, R = model.observation(x, u, k)
        meas = masked_measurement(y, y_pred, H, R)
        m = meas.R.shape[0]
        pre = jnp.block([[cholesky(meas.R), meas.H @ S], [jnp.zeros((n, m), S.dtype), S]])
        post = tria(pre)
        Se, Kbar, S_post = post[:m, :m], post[m:, :m], post[m:, m:]
        whitened = solve_triangular(Se, meas.innovation, lower=True)
        x_post = x + Kbar @ whitened
        loglik = gaussian_loglik(whitened, Se, meas.num_observed)
        x_next, F, G, Q = model.transition(x_post, u, k)
        S_next = tria(jnp.concatenate([F @ S_post, G @ cholesky(Q)], 1))
        P_post = S_post @ S_post.T
        status = step_status(x_next, S_next, loglik, positive=jnp.all(jnp.diag(S_post) != 0))
        out = StepOutput(
            x, S @ S.T, x_post, P_post, meas.innovation, Se @ Se.T, loglik, status,
            predicted_factor=factor, factor=CholeskyFactor(S_post),
        )  # fmt: skip
        return x_next, CholeskyFactor(S_next), out
