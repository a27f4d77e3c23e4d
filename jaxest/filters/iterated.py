"""The iterated extended Kalman filter: a Gauss-Newton measurement update.

The measurement update seeks the maximum of p(x | y) ~ N(y; h(x), R) N(x; x-, P-), i.e. the
minimum of J(x) = |y - h(x)|^2_{R^-1} + |x - x-|^2_{P^-1}, by Gauss-Newton from x^0 = x-
(Bell & Cathey, The iterated Kalman filter update as a Gauss-Newton method, 1993)::

    H_i = dh/dx(x^i),  e_i = y - h(x^i) - H_i (x- - x^i)                                    (1)
    K_i = P- H_i^T (H_i P- H_i^T + R)^-1,  x^{i+1} = x- + K_i e_i                           (2)

With Levenberg-Marquardt damping lambda > 0 each step also penalises lambda |x - x^i|^2
(Särkkä & Svensson, Levenberg-Marquardt and line-search extended Kalman smoothers, 2020): (2)
is taken with the prior N(x-, P-) replaced by its product with N(x^i, I / lambda), i.e.

    Pt = (P-^-1 + lambda I)^-1 = (I + lambda P-)^-1 P-,  xt = x^i + (I + lambda P-)^-1 (x- - x^i)  (3)

in place of (P-, x-). After N iterations x(k|k) = x^N and
P(k|k) = (I - K H) P- (I - K H)^T + K R K^T with the undamped gain K at the last linearisation
point x^{N-1} (the point that gave x^N). N = 1 is the EKF (x^0 = x-). The innovation, S and the
log-likelihood term are those at x^0 = x-: e = y - h(x-), S = H_0 P- H_0^T + R, as the EKF's, so
they do not depend on N. The time update is the EKF's (f and F at x(k|k)).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from jaxest.filters.base import AbstractGaussianFilter, Covariance, StepOutput
from jaxest.filters.common import (
    Measurement,
    covariance_predict,
    gaussian_loglik,
    joseph_update,
    masked_measurement,
    step_status,
)
from jaxest.linalg import cho_solve_lower, cholesky, symmetrize


def linearised_measurement(model, x_prior, x_lin, y, u, k) -> Measurement:
    """Eq 1: the masked measurement of the model linearised at ``x_lin``, referred to x-."""
    y_pred, H, R = model.observation(x_lin, u, k)
    meas = masked_measurement(y, y_pred, H, R)
    e = meas.innovation - meas.H @ (x_prior - x_lin)
    return Measurement(e, meas.H, meas.R, meas.num_observed)


def damped_prior(x_prior, P, x_lin, damping):
    """Eq 3: the prior (xt, Pt) of a Levenberg-Marquardt step at ``x_lin``."""
    n = x_prior.shape[0]
    chol = cholesky(symmetrize(jnp.eye(n, dtype=P.dtype) + damping * P))
    return x_lin + cho_solve_lower(chol, x_prior - x_lin), symmetrize(cho_solve_lower(chol, P))


class IteratedEKF(AbstractGaussianFilter):
    """Iterated EKF (module docstring): ``iterations`` Gauss-Newton steps (eqs 1-2) in each
    measurement update, optionally Levenberg-Marquardt damped by ``damping`` >= 0 (eq 3);
    ``iterations=1`` (with any damping 0) is the EKF / :class:`~jaxest.KalmanFilter`."""

    iterations: int = eqx.field(static=True, default=5)
    damping: float = eqx.field(static=True, default=0.0, converter=float)

    factor_type = Covariance

    def __check_init__(self):
        if isinstance(self.iterations, bool) or not isinstance(self.iterations, int):
            raise ValueError(f"iterations: must be an integer >= 1, got {self.iterations!r}")
        if self.iterations < 1:
            raise ValueError(f"iterations: must be >= 1, got {self.iterations}")
        if not self.damping >= 0:
            raise ValueError(f"damping: must be >= 0, got {self.damping}")

    def gauss_newton_step(self, model, x, P, x_lin, y, u, k):
        """x^{i+1} from x^i = ``x_lin`` (eq 2, damped by eq 3 when ``damping`` > 0)."""
        if self.damping > 0:
            x, P = damped_prior(x, P, x_lin, self.damping)
        meas = linearised_measurement(model, x, x_lin, y, u, k)
        return joseph_update(x, P, meas)[0]

    def update_predict(self, model, x, factor: Covariance, k, y, u):
        P = factor.matrix

        def undamped_update(x_lin):  # eq 2 at x_lin, and P(k|k) with its gain
            return joseph_update(x, P, linearised_measurement(model, x, x_lin, y, u, k))

        first = linearised_measurement(model, x, x, y, u, k)
        x_post, P_post, S, S_chol, whitened = joseph_update(x, P, first)  # iteration 1: the EKF
        loglik = gaussian_loglik(whitened, S_chol, first.num_observed)
        if self.damping == 0:  # each Gauss-Newton step is the undamped update itself

            def iterate(_, posterior):
                return undamped_update(posterior[0])[:2]

            x_post, P_post = jax.lax.fori_loop(0, self.iterations - 1, iterate, (x_post, P_post))
        else:

            def iterate(_, points):
                _, x_lin = points
                return x_lin, self.gauss_newton_step(model, x, P, x_lin, y, u, k)

            x_last_lin, x_post = jax.lax.fori_loop(0, self.iterations, iterate, (x, x))
            P_post = undamped_update(x_last_lin)[1]
        x_next, P_next = covariance_predict(model, x_post, P_post, u, k)
        status = step_status(x_next, P_next, loglik, cov=P_post)
        out = StepOutput(x, P, x_post, P_post, first.innovation, S, loglik, status)
        return x_next, Covariance(P_next), out


__all__ = ["IteratedEKF"]
