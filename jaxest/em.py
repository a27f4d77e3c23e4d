"""Expectation-maximisation for linear-Gaussian models (Shumway & Stoffer 1982).

For x_{k+1} = F x_k + B u_k + w_k, y_k = H x_k + D u_k + v_k (G = I), x_0 ~ N(m0, P0), each
iteration runs the Kalman filter and RTS smoother at the current parameters (E-step) and
maximises the expected complete-data log-likelihood in closed form (M-step). With the smoothed
moments x(k|T), P(k|T) and the lag-one cross covariances P(k+1,k|T) = P(k+1|T) E_k^T (E_k the RTS
gain; :attr:`~jaxest.SmootherResult.cross_cov`), and z_k = [x_k; u_k], there are two linear
regressions t_k = W z_k + noise: the dynamics (t_k = x_{k+1}, k = 0..T-2, W = [F, B], noise
covariance Sigma = Q, N = T-1 terms) and the measurements (t_k = y_k, k = 0..T-1, W = [H, D],
Sigma = R, N = T). With the sums S_ab = sum_k E[a_k b_k^T] over the smoothed distribution, the
maximiser over the free columns a of W (the held ones b keep their values) and over Sigma is

    W_a = (S_ta - W_b S_ba) S_aa^-1,   Sigma = E_W / N,
    E_W = sum_k E[(t_k - W z_k)(t_k - W z_k)^T].                                             (1)

W_a does not depend on Sigma (all rows share the regressors), so (1) maximises over (W_a, Sigma)
jointly; with W held it maximises over Sigma alone, and with Sigma held over W_a alone (its
minimiser is Sigma-free). The textbook form, E_W = S_tt - W S_zt - S_zt^T W^T + W S_zz W^T, is
a difference of sums the size of the signal whose result is the size of the noise: in float32,
with Q and R 1e-6 of the prior's variance, it lost Q's digits and EM went NaN within 30-110
iterations. So both are computed from the residuals of the current W0 (the same maximiser in
exact arithmetic, a step of iterative refinement in rounded), with E[.] and C for the smoothed
means and covariances, C_zz,k = blockdiag(P(k|T), 0), and for the dynamics C_tz,k =
[P(k+1,k|T), 0], C_tt,k = P(k+1|T) (for the measurements both zero):

    r_k = E[t_k] - W0 E[z_k],
    G = sum_k E[(t_k - W0 z_k) z_k^T] = sum_k (r_k E[z_k]^T + C_tz,k - W0 C_zz,k),
    W_a = W0_a + G_a S_aa^-1,                                                                 (2)
    E_W = sum_k [e_k e_k^T + C_tt,k - W C_tz,k^T - C_tz,k W^T + W C_zz,k W^T],
    e_k = E[t_k] - W E[z_k].                                                                  (3)

(2) is (1) since G_a = S_ta - W0_a S_aa - W0_b S_ba. The prior: m0 = x(0|T),
P0 = P(0|T) + (x(0|T) - m0)(x(0|T) - m0)^T. Every step is a maximisation of the expected
complete-data log-likelihood over some parameters with the others held, so the log-likelihood
does not decrease from one iteration to the next (Dempster, Laird & Rubin 1977, Theorem 1).

Status. Each iteration's flags (:data:`EMStatus`, ``EMResult.status``) gather what can go wrong
under ``jit`` without an exception: the E-step filter's and smoother's own flags, a fitted Q, R
or P0 singular to working precision (``DEGENERATE_COVARIANCE``: with too few steps for the
parameters fitted, (1)'s Sigma is singular, and the next E-step turns it into NaN), and a
log-likelihood below the previous iteration's by more than sqrt(eps) of their size
(``LOGLIK_DECREASED``), which the theorem rules out in exact arithmetic. Not flagged: covariances
that shrink toward zero as a whole where the likelihood is unbounded (the pivots stay near 1).
One step fitting R and the prior (F and Q fixed), 1 state: R fell to 7e-34 and P0 to 1e-35
over 1000 iterations while log p(y) climbed to +36.7, status OK; two steps fitting everything
went the same way more slowly. A log-likelihood that keeps climbing says so; fit fewer
parameters or give more data.

Precision. With (2)-(3), float32 fits of random 4-state systems with Q and R 1e-6 of the
prior's variance ended within 0.06 nats of float64's, where the textbook form went NaN in 19 of
20 (flagged). At 1e-8 the covariance-form E-step (``KalmanFilter`` and the RTS smoother) loses
P(k|k) in float32 from the first iteration (flagged ``NOT_POSITIVE_DEFINITE``);
``square_root=True`` runs it on Cholesky factors, as the parallel E-step always does
(docs/robustness.md, "EM in float32", has the measurements).
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from jaxest._checks import (
    check_complete,
    check_flag,
    check_gaussian_arguments,
    check_gaussian_prior,
    check_positive_int,
    check_precision,
)
from jaxest._priors import Gaussian
from jaxest._run import SaveAt, raise_if_failed, run
from jaxest._status import StatusOverSteps, finite_status, status_where
from jaxest.filters.kalman import KalmanFilter
from jaxest.filters.parallel import ParallelKalmanFilter, ParallelStatus
from jaxest.filters.sqrt_kf import SquareRootKF
from jaxest.linalg import (
    after,
    cho_solve_lower,
    cholesky,
    symmetrize,
    working_precision_by_default,
)
from jaxest.models import LinearGaussian
from jaxest.smoothers.rts import SmootherResult, rts_smooth

#: the parameters fit_em estimates; any of them may be held fixed
PARAMETERS = ("F", "B", "Q", "H", "D", "R", "prior.mean", "prior.cov")


EMStatus = ParallelStatus.extend(
    "EMStatus",
    DEGENERATE_COVARIANCE=(
        8,
        "a fitted covariance (Q, R or the prior's P0) is singular to working precision or not "
        "finite: the data do not determine it (too few steps for the parameters fitted, or a "
        "state the measurements do not see); hold it in fixed, fit fewer parameters or give "
        "more data",
    ),
    LOGLIK_DECREASED=(
        16,
        "the log-likelihood fell from one EM iteration to the next by more than sqrt(eps) of "
        "its size, which EM rules out in exact arithmetic: the E-step lost precision (use "
        "square_root=True or float64) or a fitted covariance is nearly singular (see "
        "DEGENERATE_COVARIANCE)",
    ),
)
"""``fit_em``'s status flags: the E-step filter's and smoother's (the core's and the parallel
filter's) and EM's own (module docstring)."""


class EMResult(StatusOverSteps):
    """The fitted model and prior; ``logliks[i]``: log p(y) before the i-th M-step;
    ``status[i]``: the :data:`EMStatus` flags of iteration i, from its E-step (the filter and
    smoother at the parameters of ``logliks[i]``), from the parameters its M-step fitted, and
    ``LOGLIK_DECREASED`` where ``logliks[i]`` fell below ``logliks[i - 1]``."""

    #: the status flags of fit_em (``throw=True`` and ``describe`` use them)
    flags: ClassVar = EMStatus

    model: LinearGaussian
    prior: Gaussian
    logliks: Float[Array, " num_iters"]
    status: Int[Array, " num_iters"]


class Moments(eqx.Module):
    """Smoothed x(k|T), P(k|T), the lag-one cross covariances P(k+1,k|T), log p(y), and the
    filter's and smoother's flags OR'ed over the steps."""

    mean: Float[Array, "T n"]
    cov: Float[Array, "T n n"]
    cross: Float[Array, "T-1 n n"]
    loglik: Float[Array, ""]
    status: Int[Array, ""]


def smoothing_filter(parallel: bool, square_root: bool = False):
    """The filter :func:`kalman_smooth` runs: the square-root ``ParallelKalmanFilter`` with
    ``parallel``, ``SquareRootKF`` with ``square_root``, else ``KalmanFilter``."""
    if parallel:
        return ParallelKalmanFilter()
    return SquareRootKF() if square_root else KalmanFilter()


def kalman_smooth(
    model, ys, *, prior, inputs=None, parallel: bool, square_root: bool = False
) -> tuple[SmootherResult, Float[Array, ""]]:
    """x(k|T), P(k|T) (a :class:`~jaxest.SmootherResult`) and log p(y) of a linear-Gaussian
    model: ``KalmanFilter`` and ``rts_smooth``; with ``square_root``, ``SquareRootKF`` and
    ``rts_smooth(..., square_root=True)`` on its Cholesky factors; with ``parallel``, the
    square-root ``ParallelKalmanFilter`` and the parallel smoother on its factors (in float32 the
    covariance-form parallel smoother left 2 of 20 EM fits 0.6 and 4.1 nats short with status
    OK, and it was only 4-9 % faster). The E-step below, and each iteration of
    :func:`~jaxest.iterated_smooth`."""
    square_root = square_root or parallel
    filt = smoothing_filter(parallel, square_root)
    save = SaveAt(fields=filt.default_fields + ("factor",)) if square_root else None
    filtered = run(filt, model, ys, prior=prior, inputs=inputs, parallel=parallel, save=save)
    smoothed = rts_smooth(
        model, filtered, inputs=inputs, parallel=parallel, square_root=square_root
    )
    return smoothed, filtered.loglik


def e_step(model, prior, ys, inputs, parallel: bool, square_root: bool) -> Moments:
    """Filter and RTS-smooth at the current parameters (``kalman_smooth``)."""
    smoothed, loglik = kalman_smooth(
        model, ys, prior=prior, inputs=inputs, parallel=parallel, square_root=square_root
    )
    status = jnp.bitwise_or.reduce(smoothed.status, axis=-1)  # the filter's included
    return Moments(smoothed.mean, smoothed.cov, smoothed.cross_cov, loglik, status)


class Regression(eqx.Module):
    """One regression t_k = W z_k + noise of the module docstring, as the E-step knows it: the
    smoothed means of z_k and t_k, and the sums over k of their smoothed covariances."""

    z: Float[Array, "N d"]
    t: Float[Array, "N m"]
    C_zz: Float[Array, "d d"]
    C_tz: Float[Array, "m d"]
    C_tt: Float[Array, "m m"]


def regressions(mo: Moments, ys, inputs) -> tuple[Regression, Regression]:
    """The dynamics' and the measurements' :class:`Regression` (module docstring)."""
    x, P, T = mo.mean, mo.cov, mo.mean.shape[0]
    u = jnp.zeros((T, 0), x.dtype) if inputs is None else inputs
    z = jnp.concatenate([x, u], axis=1)
    n, d = x.shape[1], z.shape[1]

    def states_block(C, rows):  # C in the leading rows and the state columns, zero elsewhere
        return jnp.zeros((rows, d), x.dtype).at[: C.shape[0], :n].set(C)

    C_xx_head, C_xx_tail = jnp.sum(P[:-1], axis=0), jnp.sum(P[1:], axis=0)
    C_next_x = jnp.sum(mo.cross, axis=0)
    dynamics = Regression(z[:-1], x[1:], states_block(C_xx_head, d),
                          states_block(C_next_x, n), C_xx_tail)  # fmt: skip
    m = ys.shape[1]
    emission = Regression(z, ys, states_block(C_xx_head + P[-1], d),
                          jnp.zeros((m, d), x.dtype), jnp.zeros((m, m), x.dtype))  # fmt: skip
    return dynamics, emission


def regress(reg: Regression, W, cov, free: np.ndarray, fit_cov: bool):
    """Eq (2): the free columns ``free`` of W, then eq (3)'s noise covariance (if ``fit_cov``),
    both from the residuals of the current W."""
    residual = reg.t - reg.z @ W.T
    if free.size:
        z_a = reg.z[:, free]
        S_aa = z_a.T @ z_a + reg.C_zz[np.ix_(free, free)]
        G_a = residual.T @ z_a + reg.C_tz[:, free] - W @ reg.C_zz[:, free]
        W = W.at[:, free].add(cho_solve_lower(cholesky(S_aa), G_a.T).T)
        residual = reg.t - reg.z @ W.T
    if fit_cov:
        cross = W @ reg.C_tz.T
        E_W = residual.T @ residual + reg.C_tt - cross - cross.T + W @ reg.C_zz @ W.T
        cov = symmetrize(E_W) / reg.z.shape[0]
    return W, cov


def m_step(model: LinearGaussian, prior: Gaussian, mo: Moments, ys, inputs, fixed: frozenset):
    """The closed-form maximisation, eqs (2) and (3), holding the parameters in ``fixed``."""
    n, p = model.F.shape[0], 0 if inputs is None else inputs.shape[1]
    dynamics, emission = regressions(mo, ys, inputs)

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


def fitted_status(model: LinearGaussian, prior: Gaussian, fixed: frozenset) -> Int[Array, ""]:
    """``NONFINITE`` where a parameter is not finite, ``DEGENERATE_COVARIANCE`` where a fitted
    covariance C (Q, R, P0; those held in ``fixed`` are the caller's) is singular as far as its
    dtype can tell: a pivot L_ii^2 of its Cholesky factor (component i's variance given the
    components before it) below sqrt(eps) C_ii, or not finite. A covariance singular in exact
    arithmetic comes out of (3) with pivots of 0.8-2.2 eps C_ii or none (20 fits of
    ``tests/test_em.py``'s degenerate problem, float64), and which of the two is rounding's
    choice; the fits of well-posed problems there had 0.19-1.0. The factorisations run one
    after the other (:func:`~jaxest.linalg.after`: above 8 states they are LAPACK calls, and
    two at once can deadlock jaxlib 0.10 on the CPU)."""
    fitted = {"Q": model.Q, "R": model.R, "prior.cov": prior.cov}
    factors, degenerate = [], jnp.zeros((), bool)
    for name, cov in fitted.items():
        if name not in fixed:
            factors.append(cholesky(after(cov, factors)))
            pivots = jnp.diagonal(factors[-1]) ** 2 / jnp.diagonal(cov)
            tolerance = jnp.sqrt(jnp.finfo(cov.dtype).eps)
            degenerate |= ~jnp.all(pivots >= tolerance)  # False for NaN: degenerate
    return finite_status(*jax.tree.leaves((model, prior))) | status_where(
        degenerate, EMStatus.DEGENERATE_COVARIANCE
    )


def decrease_status(logliks: Float[Array, " num_iters"]) -> Int[Array, " num_iters"]:
    """``LOGLIK_DECREASED`` at each i where logliks[i] < logliks[i - 1] by more than sqrt(eps)
    of |logliks[i]| + |logliks[i - 1]| + 1."""
    earlier, later = logliks[:-1], logliks[1:]
    tolerance = jnp.sqrt(jnp.finfo(logliks.dtype).eps) * (jnp.abs(earlier) + jnp.abs(later) + 1)
    fell = jnp.concatenate([jnp.zeros(1, bool), earlier - later > tolerance])
    return status_where(fell, EMStatus.LOGLIK_DECREASED)


@eqx.filter_jit
def _fit_em(model, prior, ys, inputs, num_iters: int, fixed: frozenset, parallel, square_root):
    def body(carry, _):
        model, prior = carry
        moments = e_step(model, prior, ys, inputs, parallel, square_root)
        model, prior = m_step(model, prior, moments, ys, inputs, fixed)
        status = moments.status | fitted_status(model, prior, fixed)
        return (model, prior), (moments.loglik, status)

    (model, prior), (logliks, status) = jax.lax.scan(body, (model, prior), None, length=num_iters)
    return EMResult(model, prior, logliks, status | decrease_status(logliks))


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
    square_root: bool = False,
    throw: bool = False,
) -> EMResult:
    """Fit F, B, Q, H, D, R and the prior of a linear-Gaussian model by EM (module docstring).

    Args:
        model: the initial :class:`~jaxest.LinearGaussian`, time-invariant, with G = I (no
            ``G``); with ``inputs``, ``B`` and ``D`` are given (zeros to start from nothing).
        ys: complete measurements, shape (T, m) (no NaN).
        prior: the initial :class:`~jaxest.Gaussian` prior on x_0.
        num_iters: EM iterations (one ``lax.scan``: compiled once per shapes).
        fixed: names from :data:`PARAMETERS` held at their initial values (one name alone,
            or a sequence of them).
        inputs: known inputs u_k, shape (T, p), or ``None``.
        parallel: E-step by the parallel filter and smoother instead of the sequential ones.
        square_root: the sequential E-step on Cholesky factors (``SquareRootKF`` and
            ``rts_smooth(..., square_root=True)``), for float32 where Q and R are far below the
            prior's spread (module docstring); 2.1-2.8 times the time. The parallel E-step
            always runs on factors.
        throw: raise (``eqx.error_if``, also under ``jit``) if an iteration's status is not
            OK, with what each flag means.

    Returns an :class:`EMResult`; ``logliks[i]`` is log p(y) before the i-th M-step (as
    dynamax's ``fit_em`` reports it), non-decreasing in i; ``status[i]`` the iteration's
    :data:`EMStatus` flags (``result.ok``: all OK).
    """
    fixed = (fixed,) if isinstance(fixed, str) else fixed  # one name, not its letters
    _check(model, ys, prior, num_iters, fixed, inputs, parallel, square_root)
    check_flag("throw", throw)
    ys = jnp.asarray(ys)
    inputs = None if inputs is None else jnp.asarray(inputs)
    result = _fit_em(model, prior, ys, inputs, num_iters, frozenset(fixed), parallel, square_root)
    return raise_if_failed(result) if throw else result


def _check(model, ys, prior, num_iters, fixed, inputs, parallel, square_root):
    if not isinstance(model, LinearGaussian):
        raise ValueError(f"model: fit_em needs a jaxest.LinearGaussian, got {type(model).__name__}")
    if model.G is not None:
        raise ValueError("model.G: fit_em estimates Q for G = I; build the model without G")
    for name in ("F", "H", "Q", "R", "B", "D"):
        value = getattr(model, name)
        if value is not None and np.ndim(value) != 2:
            raise ValueError(f"model.{name}: fit_em needs a time-invariant model (a 2-D matrix)")
        if value is not None and not jnp.issubdtype(jnp.result_type(value), jnp.floating):
            raise ValueError(
                f"model.{name}: is {jnp.result_type(value)}; fit_em updates the matrices in their "
                f"own dtype (an integer F was fitted as integers), so give floating point"
            )
    if inputs is not None and (model.B is None or model.D is None):
        raise ValueError("inputs: fit_em with inputs needs model.B and model.D (zeros to start)")
    if any(name not in PARAMETERS for name in fixed):
        raise ValueError(f"fixed: expected names from {PARAMETERS}, got {fixed!r}")
    check_positive_int("num_iters", num_iters)
    check_flag("parallel", parallel)
    check_flag("square_root", square_root)
    check_gaussian_prior(prior, model.F.shape[-1])
    # the square-root filters of the parallel and square_root E-steps factor Q: a singular one
    # gave NaN (status 13)
    check_gaussian_arguments(model, ys, inputs, prior, positive_Q=parallel or square_root)
    check_complete(ys, "fit_em needs complete measurements")
    # EM updates the model as well as the prior, from the prior, the data and the inputs, each
    # matrix in its own dtype: a float32 model with a float64 prior (or a float32 F beside a
    # float64 Q) came out of the first iteration in float64, a TypeError from inside the scan
    dtypes = {
        name: jnp.result_type(getattr(model, name))
        for name in ("F", "H", "Q", "R", "B", "D")
        if getattr(model, name) is not None
    }
    if len(set(dtypes.values())) > 1:
        given = ", ".join(f"{name} {dtype}" for name, dtype in dtypes.items())
        raise ValueError(f"model: fit_em updates its matrices in one dtype, got {given}")
    check_precision(
        None, ys, model, name="model", **{"the prior": jnp.result_type(prior.mean, prior.cov)},
        **({} if inputs is None else {"inputs": inputs}),
    )  # fmt: skip
    dynamics = ({"F", "Q"} | ({"B"} if model.B is not None else set())) - set(fixed)
    if dynamics and np.shape(ys)[0] < 2:
        raise ValueError(
            f"ys: has {np.shape(ys)[0]} steps; estimating {sorted(dynamics)} needs a transition "
            f"(at least 2 steps), or hold them in fixed"
        )


__all__ = ["EMResult", "EMStatus", "fit_em"]
