"""Pieces every Gaussian filter shares: missing-data masking, the likelihood term, status checks, and the covariance-form step that also serves as the reference derivative of
the factored (SVD) filters."""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from jaxest._status import Status, finite_status
from jaxest.linalg import cholesky, mm, mv, sandwich, solve_triangular, symmetrize

#: a Python float: computing it with jnp would start the XLA backend at import (which
#: jax.distributed.initialize forbids) and fix it in float32 before x64 is switched on
LOG_2PI = math.log(2.0 * math.pi)


class Measurement(eqx.Module):
    """A measurement with its missing (NaN) entries neutralised.

    Missing rows get H = 0, innovation 0 and unit, uncorrelated noise, so they carry no
    information and contribute nothing but a constant that :attr:`num_observed` removes from
    the likelihood: exactly the missing rows are skipped, with R restricted to the observed ones.
    """

    innovation: Float[Array, " m"]
    H: Float[Array, "m n"]
    R: Float[Array, "m m"]
    num_observed: Float[Array, ""]


def masked_measurement(y, y_pred, H, R) -> Measurement:
    observed = ~jnp.isnan(y)  # only NaN is missing: +-inf propagates and sets NONFINITE
    mask = observed.astype(H.dtype)
    e = jnp.where(observed, y - y_pred, 0.0)
    both = mask[:, None] * mask[None, :]
    R_masked = both * R + jnp.diag(1.0 - mask)
    return Measurement(e, mask[:, None] * H, R_masked, jnp.sum(mask))


def gaussian_loglik(whitened, S_chol, num_observed):
    """log N(e; 0, S) over the observed entries, from S = S_chol S_chol^T (lower) and the
    whitened innovation S_chol^-1 e."""
    logdet = 2.0 * jnp.sum(jnp.log(jnp.abs(jnp.diag(S_chol))))
    return -0.5 * (num_observed * LOG_2PI + logdet + whitened @ whitened)


def factor_status(L) -> Int[Array, ""]:
    """``NOT_POSITIVE_DEFINITE`` unless the Cholesky factor L is finite with a positive diagonal."""
    return _definite_bit(jnp.all(jnp.isfinite(L)) & jnp.all(jnp.diag(L) > 0))


def definiteness_status(P) -> Int[Array, ""]:
    """``NOT_POSITIVE_DEFINITE`` unless P has a finite Cholesky factor with a positive diagonal."""
    return factor_status(cholesky(symmetrize(P)))


def whitened_innovation(P, meas: Measurement):
    """The innovation covariance S = H P H^T + R, its Cholesky factor S_chol, and S_chol^-1 H P
    and S_chol^-1 e: one triangular solve serves the gain, P H^T S^-1 e = (S_chol^-1 H P)^T
    (S_chol^-1 e), and the likelihood (:func:`gaussian_loglik`)."""
    n = P.shape[0]
    HP = mm(meas.H, P)
    S = symmetrize(mm(HP, meas.H.T) + meas.R)
    S_chol = cholesky(S)
    Z = solve_triangular(
        S_chol, jnp.concatenate([HP, meas.innovation[:, None]], axis=1), lower=True
    )
    return S, S_chol, Z[:, :n], Z[:, n]


def joseph_update(x, P, meas: Measurement):
    """Covariance-form measurement update with the Joseph form of P+ (Bucy & Joseph).

    Returns x+, P+, the innovation covariance S = H P H^T + R, its Cholesky factor and the
    whitened innovation S_chol^-1 e (:func:`whitened_innovation`).
    """
    S, S_chol, whitened_HP, whitened = whitened_innovation(P, meas)
    K = solve_triangular(S_chol.T, whitened_HP, lower=False).T
    IKH = jnp.eye(x.shape[0], dtype=P.dtype) - mm(K, meas.H)
    P_post = symmetrize(sandwich(IKH, P) + sandwich(K, meas.R))
    return x + mv(K, meas.innovation), P_post, S, S_chol, whitened


def predicted_cov(P, F, G, Q):
    """Eq 7: P(k+1|k) = F P(k|k) F^T + G Q G^T."""
    return symmetrize(sandwich(F, P) + sandwich(G, Q))


def covariance_predict(model, x, P, u, k):
    """Eqs 6-7: x(k+1|k) = f(x(k|k), u_k), P(k+1|k) (:func:`predicted_cov`)."""
    x_next, F, G, Q = model.transition(x, u, k)
    return x_next, predicted_cov(P, F, G, Q)


def covariance_step(model, x, P, y, u, k):
    """One step of the conventional (Joseph) Kalman filter / EKF on (x(k|k-1), P(k|k-1)).

    Returns x(k+1|k), P(k+1|k) and the float parts of the step output
    (filtered mean and covariance, innovation, its covariance, log-likelihood term).
    """
    y_pred, H, R = model.observation(x, u, k)
    meas = masked_measurement(y, y_pred, H, R)
    x_post, P_post, S, S_chol, whitened = joseph_update(x, P, meas)
    loglik = gaussian_loglik(whitened, S_chol, meas.num_observed)
    x_next, P_next = covariance_predict(model, x_post, P_post, u, k)
    return x_next, P_next, (x_post, P_post, meas.innovation, S, loglik)


def step_status(*arrays, cov=None, cov_factor=None, positive=None) -> Int[Array, ""]:
    """Status bits of one step: non-finite values, and loss of definiteness of ``cov``, of the
    covariance whose Cholesky factor ``cov_factor`` is at hand, or as a filter's own boolean
    test ``positive`` of its factors says."""
    status = finite_status(*arrays)
    if cov is not None:
        status = status | definiteness_status(cov)
    if cov_factor is not None:
        status = status | factor_status(cov_factor)
    if positive is not None:
        status = status | _definite_bit(positive)
    return status


def _definite_bit(positive) -> Int[Array, ""]:
    return jnp.where(positive, Status.OK, Status.NOT_POSITIVE_DEFINITE).astype(jnp.int32)
