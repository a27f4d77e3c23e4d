"""Expectation-maximisation for linear-Gaussian models (Shumway & Stoffer 1982).

For x_{k+1} = F x_k + B u_k + w_k, y_k = H x_k + D u_k + v_k (G = I), x_0 ~ N(m0, P0), each
iteration runs the Kalman filter and RTS smoother at the current parameters (E-step) and
maximises the expected complete-data log-likelihood in closed form (M-step). With the smoothed
moments x(k|T), P(k|T) and the lag-one cross covariances P(k+1,k|T) = P(k+1|T) E_k^T (E_k the RTS
gain; :attr:`~jaxest.SmootherResult.cross_cov`), and z_k = [x_k; u_k],

    S_zz = sum_k E[z_k z_k^T],  S_zt = sum_k E[z_k t_k^T],  S_tt = sum_k E[t_k t_k^T]        (1)

for the dynamics (t_k = x_{k+1}, k = 0..T-2) and for the measurements (t_k = y_k, k = 0..T-1).
Each is a linear regression t = W z + noise with W = [F, B] (or [H, D]):

    W_a = (S_ta - W_b S_ba) S_aa^-1   (a: the free blocks of W, b: the held ones),
    Sigma = (S_tt - W S_zt - S_zt^T W^T + W S_zz W^T) / N,                                  (2)

Sigma = Q (N = T-1) or R (N = T). W_a does not depend on Sigma (all rows share the regressors),
so (2) maximises over (W_a, Sigma) jointly; with W held it maximises over Sigma alone, and with
Sigma held over W_a alone (its minimiser is Sigma-free). The prior: m0 = x(0|T),
P0 = P(0|T) + (x(0|T) - m0)(x(0|T) - m0)^T. Every step is a maximisation of the expected
complete-data log-likelihood over some parameters with the others held, so the log-likelihood
does not decrease from one iteration to the next (Dempster, Laird & Rubin 1977, Theorem 1).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxest._checks import (
    check_complete,
    check_gaussian_arguments,
    check_gaussian_prior,
    check_positive_int,
)
from jaxest._priors import Gaussian
from jaxest._run import run
from jaxest.filters.kalman import KalmanFilter
from jaxest.filters.parallel import ParallelKalmanFilter
from jaxest.linalg import cho_solve_lower, cholesky, symmetrize, working_precision_by_default
from jaxest.models import LinearGaussian
from jaxest.smoothers.rts import SmootherResult, rts_smooth

#: the parameters fit_em estimates; any of them may be held fixed
PARAMETERS = ("F", "B", "Q", "H", "D", "R", "prior.mean", "prior.cov")


class EMResult(eqx.Module):
    """The fitted model and prior, and ``logliks[i]``: log p(y) before the i-th M-step."""

    model: LinearGaussian
    prior: Gaussian
    logliks: Float[Array, " num_iters"]


class Moments(eqx.Module):
    """Smoothed x(k|T), P(k|T), the lag-one cross covariances P(k+1,k|T), and log p(y)."""

    mean: Float[Array, "T n"]
    cov: Float[Array, "T n n"]
    cross: Float[Array, "T-1 n n"]
    loglik: Float[Array, ""]


def kalman_smooth(
    model, ys, *, prior, inputs=None, parallel: bool
) -> tuple[SmootherResult, Float[Array, ""]]:
    """x(k|T), P(k|T) (a :class:`~jaxest.SmootherResult`) and log p(y) of a linear-Gaussian
    model: ``KalmanFilter`` and ``rts_smooth``, or with ``parallel`` the square-root
    ``ParallelKalmanFilter`` and ``rts_smooth(..., parallel=True)``. The E-step below, and each
    iteration of :func:`~jaxest.iterated_smooth`."""
    filt = ParallelKalmanFilter() if parallel else KalmanFilter()
    filtered = run(filt, model, ys, prior=prior, inputs=inputs, parallel=parallel)
    return rts_smooth(model, filtered, inputs=inputs, parallel=parallel), filtered.loglik


def e_step(model, prior, ys, inputs, parallel: bool) -> Moments:
    """Filter and RTS-smooth at the current parameters (in parallel form if ``parallel``)."""
    smoothed, loglik = kalman_smooth(model, ys, prior=prior, inputs=inputs, parallel=parallel)
    return Moments(smoothed.mean, smoothed.cov, smoothed.cross_cov, loglik)


def regression_stats(mo: Moments, ys, inputs):
    """Eq (1) for the dynamics and for the measurements: (S_zz, S_zt, S_tt, N) each."""
    x, P, T = mo.mean, mo.cov, mo.mean.shape[0]
    u = jnp.zeros((T, 0), x.dtype) if inputs is None else inputs
    z = jnp.concatenate([x, u], axis=1)
    n = x.shape[1]

    def zz(index):
        S = z[index].T @ z[index]
        return S.at[:n, :n].add(jnp.sum(P[index], axis=0))

    head = slice(0, T - 1)
    S_zx = z[head].T @ x[1:]
    dynamics = (zz(head), S_zx.at[:n].add(jnp.sum(mo.cross, axis=0).T),
                x[1:].T @ x[1:] + jnp.sum(P[1:], axis=0), T - 1)  # fmt: skip
    emission = (zz(slice(0, T)), z.T @ ys, ys.T @ ys, T)
    return dynamics, emission


def regress(stats, W, cov, free: np.ndarray, fit_cov: bool):
    """Eq (2): the free columns ``free`` of W, then the noise covariance (if ``fit_cov``)."""
    S_zz, S_zt, S_tt, N = stats
    held = np.setdiff1d(np.arange(W.shape[1]), free)
    if free.size:
        rhs = S_zt[free] - S_zz[np.ix_(free, held)] @ W[:, held].T
        W = W.at[:, free].set(cho_solve_lower(cholesky(S_zz[np.ix_(free, free)]), rhs).T)
    if fit_cov:
        cross = W @ S_zt
        cov = symmetrize(S_tt - cross - cross.T + W @ S_zz @ W.T) / N
    return W, cov


def m_step(model: LinearGaussian, prior: Gaussian, mo: Moments, ys, inputs, fixed: frozenset):
    """The closed-form maximisation, eq (2), holding the parameters in ``fixed``."""
    n, p = model.F.shape[0], 0 if inputs is None else inputs.shape[1]
    dynamics, emission = regression_stats(mo, ys, inputs)

    def columns(state_name, input_name):
        state = [] if state_name in fixed else list(range(n))
        extra = [] if p == 0 or input_name in fixed else list(range(n, n + p))
        return np.array(state + extra, dtype=int)

    def weights(M, N):
        return M if p == 0 else jnp.concatenate([M, N], axis=1)

    FB, Q = regress(
        dynamics, weights(model.F, model.B), model.Q, columns("F", "B"), "Q" not in fixed
    )
    HD, R = regress(
        emission, weights(model.H, model.D), model.R, columns("H", "D"), "R" not in fixed
    )
    model = eqx.tree_at(lambda m: (m.F, m.Q, m.H, m.R), model, (FB[:, :n], Q, HD[:, :n], R))
    if p:
        model = eqx.tree_at(lambda m: (m.B, m.D), model, (FB[:, n:], HD[:, n:]))
    mean = prior.mean if "prior.mean" in fixed else mo.mean[0]
    cov = prior.cov
    if "prior.cov" not in fixed:
        d = mo.mean[0] - mean
        cov = symmetrize(mo.cov[0] + jnp.outer(d, d))
    return model, Gaussian(mean, cov)


@eqx.filter_jit
def _fit_em(model, prior, ys, inputs, num_iters: int, fixed: frozenset, parallel: bool):
    def body(carry, _):
        model, prior = carry
        moments = e_step(model, prior, ys, inputs, parallel)
        return m_step(model, prior, moments, ys, inputs, fixed), moments.loglik

    (model, prior), logliks = jax.lax.scan(body, (model, prior), None, length=num_iters)
    return EMResult(model, prior, logliks)


@working_precision_by_default
def fit_em(
    model: LinearGaussian,
    ys,
    *,
    prior: Gaussian,
    num_iters: int,
    fixed=(),
    inputs=None,
    parallel: bool = False,
) -> EMResult:
    """Fit F, B, Q, H, D, R and the prior of a linear-Gaussian model by EM (module docstring).

    Args:
        model: the initial :class:`~jaxest.LinearGaussian`, time-invariant, with G = I (no
            ``G``); with ``inputs``, ``B`` and ``D`` are given (zeros to start from nothing).
        ys: complete measurements, shape (T, m) (no NaN).
        prior: the initial :class:`~jaxest.Gaussian` prior on x_0.
        num_iters: EM iterations (one ``lax.scan``: compiled once per shapes).
        fixed: names from :data:`PARAMETERS` held at their initial values.
        inputs: known inputs u_k, shape (T, p), or ``None``.
        parallel: E-step by the parallel filter and smoother instead of the sequential ones.

    Returns an :class:`EMResult`; ``logliks[i]`` is log p(y) before the i-th M-step (as
    dynamax's ``fit_em`` reports it), non-decreasing in i.
    """
    _check(model, ys, prior, num_iters, fixed, inputs)
    ys = jnp.asarray(ys)
    inputs = None if inputs is None else jnp.asarray(inputs)
    return _fit_em(model, prior, ys, inputs, num_iters, frozenset(fixed), parallel)


def _check(model, ys, prior, num_iters, fixed, inputs):
    if not isinstance(model, LinearGaussian):
        raise ValueError(f"model: fit_em needs a jaxest.LinearGaussian, got {type(model).__name__}")
    if model.G is not None:
        raise ValueError("model.G: fit_em estimates Q for G = I; build the model without G")
    for name in ("F", "H", "Q", "R", "B", "D"):
        value = getattr(model, name)
        if value is not None and np.ndim(value) != 2:
            raise ValueError(f"model.{name}: fit_em needs a time-invariant model (a 2-D matrix)")
    if inputs is not None and (model.B is None or model.D is None):
        raise ValueError("inputs: fit_em with inputs needs model.B and model.D (zeros to start)")
    if isinstance(fixed, str) or any(name not in PARAMETERS for name in fixed):
        raise ValueError(f"fixed: expected names from {PARAMETERS}, got {fixed!r}")
    check_positive_int("num_iters", num_iters)
    check_gaussian_prior(prior, model.F.shape[-1])
    check_gaussian_arguments(model, ys, inputs, prior)
    check_complete(ys, "fit_em needs complete measurements")
    dynamics = ({"F", "Q"} | ({"B"} if model.B is not None else set())) - set(fixed)
    if dynamics and np.shape(ys)[0] < 2:
        raise ValueError(
            f"ys: has {np.shape(ys)[0]} steps; estimating {sorted(dynamics)} needs a transition "
            f"(at least 2 steps), or hold them in fixed"
        )


__all__ = ["EMResult", "fit_em"]
