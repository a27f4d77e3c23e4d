"""Sigma-point Rauch-Tung-Striebel smoother (unscented / cubature RTS; Särkkä, Unscented
Rauch-Tung-Striebel smoother, IEEE TAC 2008, eqs 15-17) for the result of any sigma-point filter.

Backward pass k = T-2, ..., 0 with the filter's own points X_i drawn from x(k|k), P(k|k)
(the square root of its form) and f(X_i) (or f(X_i, W_i) with augmented noise)::

    D_k    = sum_i Wc_i (X_i - x(k|k)) (f(X_i) - x(k+1|k))^T
    C_k    = D_k P(k+1|k)^-1
    x(k|T) = x(k|k) + C_k (x(k+1|T) - x(k+1|k))
    P(k|T) = P(k|k) + C_k (P(k+1|T) - P(k+1|k)) C_k^T

x(k+1|k), P(k+1|k) are the filter's predictions (the same points gave them). On a linear model
D_k = P(k|k) F^T and this is the RTS smoother (:func:`~jaxest.rts_smooth`).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from jaxest.filters.base import FilterResult
from jaxest.filters.sigma_point import AbstractSigmaPointFilter
from jaxest.linalg import working_precision_by_default
from jaxest.smoothers.rts import SmootherResult, backward_pass, check_smoother_arguments


@working_precision_by_default
def sigma_point_rts_smooth(
    model, result: FilterResult, filter: AbstractSigmaPointFilter, *, inputs=None, k0=0
) -> SmootherResult:
    """Smooth the :class:`~jaxest.FilterResult` that ``filter`` (a sigma-point filter: its point
    set, form and noise mode are reused) produced on ``model`` (``inputs`` and ``k0`` as given
    to :func:`jaxest.run`).

    The result must hold the filtered and predicted means and covariances and the status (the
    default :class:`~jaxest.SaveAt`).
    """
    if not isinstance(filter, AbstractSigmaPointFilter):
        raise ValueError(
            f"filter: expected a sigma-point filter (UKF, CubatureKF, GaussHermiteKF), "
            f"got {type(filter).__name__}; use jaxest.rts_smooth for the others"
        )
    check_smoother_arguments("sigma_point_rts_smooth", model, result, inputs, k0)
    return _smooth(model, result, filter, inputs, jnp.asarray(k0))  # one program for any k0


@eqx.filter_jit
def _smooth(model, result: FilterResult, filter: AbstractSigmaPointFilter, inputs, k0):
    form = filter.factor_form()

    def cross_covariance(k, mean, cov, u):  # D_k of the module docstring
        dX, FX, Wm, Wc, _ = filter.propagate(form, model, mean, form.from_cov(cov), k, u)
        dF = FX - jnp.asarray(Wm, FX.dtype) @ FX
        return dX.T @ (jnp.asarray(Wc, FX.dtype)[:, None] * dF)

    return backward_pass(result, inputs, cross_covariance, k0)


__all__ = ["sigma_point_rts_smooth"]
