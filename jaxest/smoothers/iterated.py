"""Iterated extended Kalman smoother: Gauss-Newton on the trajectory, sequential or parallel.

Bell 1994 ("The iterated Kalman smoother as a Gauss-Newton method", SIAM J. Optim. 4(3));
parallel in time by Yaghoobi, Corenflos, Hostettler & Särkkä 2021 ("Parallel iterated extended
and sigma-point Kalman smoothers", ICASSP). Each iteration linearises the model about a nominal
trajectory xbar_0..xbar_{T-1},

    x_{k+1} = F_k x_k + (f(xbar_k, u_k) - F_k xbar_k) + G_k w_k,   F_k = df/dx (xbar_k, u_k),
    y_k     = H_k x_k + (h(xbar_k, u_k) - H_k xbar_k) + v_k,       H_k = dh/dx (xbar_k, u_k),   (1)

with G_k = G(xbar_k, u_k): a time-varying :class:`~jaxest.LinearGaussian` whose offsets are its
input matrices B_k, D_k for the input 1. The Kalman filter and RTS smoother of (1) --
:class:`~jaxest.ParallelKalmanFilter` and ``rts_smooth(..., parallel=True, square_root=True)``
on its factors, O(log T) depth, or the sequential ones -- give the next nominal trajectory,
x(k|T) of (1) (:func:`jaxest.em.kalman_smooth`).

With G independent of x and G Q G^T, R, P0 positive definite, the smoothed means of (1) minimise
the quadratic that agrees with the negative log-posterior

    J(x) = |x_0 - m0|^2_{P0^-1} / 2 + sum_{k<T-1} |x_{k+1} - f(x_k, u_k)|^2_{(G Q G^T)^-1} / 2
           + sum_k |y_k - h(x_k, u_k)|^2_{R^-1} / 2                                        (2)

to first order at xbar (missing entries of y_k left out), so an iteration is a Gauss-Newton step
on J and a fixed point is a stationary point of J: the MAP trajectory, where the iteration
converges (Bell 1994). Gauss-Newton is not guaranteed to decrease J; ``changes`` reports each
iteration's step, so non-convergence is visible. The covariances are those of (1) at the last
linearisation, and ``loglik`` is log p(y) of (1).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from jaxest._checks import check_flag, check_gaussian_arguments, check_positive_int, is_concrete
from jaxest._priors import Gaussian
from jaxest._status import StatusFlag
from jaxest.em import kalman_smooth, smoothing_filter
from jaxest.linalg import mv, working_precision_by_default
from jaxest.models import AbstractGaussianModel, LinearGaussian
from jaxest.smoothers.rts import SmootherResult


class IteratedSmootherResult(eqx.Module):
    """The smoother of the last linearisation (``smoothed``: x(k|T), P(k|T), status, cross
    covariances), ``loglik``: log p(y) of that linearisation, and ``changes[i]``: the largest
    |x^(i+1)_k - x^(i)_k| / sqrt(P^(i+1)(k|T)) over k and the state's entries, the step of
    iteration i in posterior standard deviations (converged where it is far below 1)."""

    smoothed: SmootherResult
    loglik: Float[Array, ""]
    changes: Float[Array, " num_iters"]

    @property
    def mean(self) -> Float[Array, "T n"]:
        return self.smoothed.mean

    @property
    def cov(self) -> Float[Array, "T n n"]:
        return self.smoothed.cov

    @property
    def status(self) -> Int[Array, " T"]:
        """The last filter's and smoother's flags per step (``smoothed.status``)."""
        return self.smoothed.status

    @property
    def any_status(self) -> Int[Array, ""]:
        """The flags of every step, OR'ed (``smoothed.any_status``)."""
        return self.smoothed.any_status

    @property
    def ok(self) -> jax.Array:
        """True where every step of the last filter and smoother finished with status OK."""
        return self.smoothed.ok

    @property
    def flags(self) -> type[StatusFlag]:
        """The family of ``status``'s bits (``smoothed.flags``)."""
        return self.smoothed.flags


def linearise(model: AbstractGaussianModel, trajectory, inputs) -> LinearGaussian:
    """Eq (1) about ``trajectory`` (T, n): a time-varying LinearGaussian for the input 1."""
    ks = jnp.arange(trajectory.shape[0])

    def at(k, x, u):
        fx, F, G, Q = model.transition(x, u, k)
        hx, H, R = model.observation(x, u, k)
        return F, H, Q, R, G, (fx - mv(F, x))[:, None], (hx - mv(H, x))[:, None]

    return LinearGaussian(*jax.vmap(at)(ks, trajectory, inputs))


def smooth_linearised(model, trajectory, ys, prior, inputs, parallel: bool):
    """One iteration: the filter and RTS smoother of eq (1) about ``trajectory``."""
    ones = jnp.ones((ys.shape[0], 1), trajectory.dtype)
    linear = linearise(model, trajectory, inputs)
    return kalman_smooth(linear, ys, prior=prior, inputs=ones, parallel=parallel)


@eqx.filter_jit
def _iterated_smooth(model, ys, prior, inputs, initial, num_iters: int, parallel: bool):
    def body(carry, _):
        previous, _ = carry
        smoothed, loglik = smooth_linearised(model, previous.mean, ys, prior, inputs, parallel)
        sd = jnp.sqrt(jnp.diagonal(smoothed.cov, axis1=-2, axis2=-1))
        change = jnp.max(jnp.abs(smoothed.mean - previous.mean) / sd)
        return (smoothed, loglik), change

    T, n = initial.shape
    start = SmootherResult(
        initial, jnp.zeros((T, n, n), initial.dtype), jnp.zeros(T, jnp.int32),
        jnp.zeros((T - 1, n, n), initial.dtype),
        smoothing_filter(parallel).result_type.flags,  # the family of kalman_smooth's filter
    )  # fmt: skip
    zero = jnp.zeros((), initial.dtype)
    (smoothed, loglik), changes = jax.lax.scan(body, (start, zero), None, length=num_iters)
    return IteratedSmootherResult(smoothed, loglik, changes)


@working_precision_by_default
def iterated_smooth(
    model: AbstractGaussianModel,
    ys,
    *,
    prior: Gaussian,
    inputs=None,
    num_iters: int = 10,
    parallel: bool = True,
    initial=None,
) -> IteratedSmootherResult:
    """The iterated extended Kalman smoother of ``model`` (module docstring).

    Args:
        model: any Gaussian model (:class:`~jaxest.NonlinearGaussian`, ...); Jacobians as the
            EKF takes them.
        ys: measurements, shape (T, m); NaN marks a missing entry.
        prior: the :class:`~jaxest.Gaussian` prior on x_0.
        inputs: known inputs u_k with a leading time axis, or ``None``.
        num_iters: linearise-and-smooth iterations (one ``lax.scan``: compiled once).
        parallel: the parallel square-root filter and parallel RTS smoother (O(log T) depth;
            Q must be positive definite), else the sequential Kalman filter and RTS smoother.
        initial: the first nominal trajectory, shape (T, n); ``None``: the prior mean at every
            step. A start far from the posterior (strongly nonlinear models) may need more
            iterations or not converge; an EKF + RTS pass gives a better one
            (``rts_smooth(model, run(EKF(), model, ys, prior=prior)).mean``).

    Returns an :class:`IteratedSmootherResult`.
    """
    check_flag("parallel", parallel)
    # the parallel filter factors Q; the way out is the sequential one, not another filter
    positive_Q = "pass parallel=False" if parallel else False
    check_gaussian_arguments(model, ys, inputs, prior, positive_Q=positive_Q)
    check_positive_int("num_iters", num_iters)
    if np.shape(ys)[0] == 0:
        raise ValueError("ys: has no steps (T = 0), nothing to smooth")
    ys = jnp.asarray(ys)
    T, n = ys.shape[0], prior.mean.shape[0]
    dtype = jnp.result_type(prior.mean, ys)
    if initial is None:
        initial = jnp.broadcast_to(prior.mean, (T, n)).astype(dtype)
    elif np.shape(initial) != (T, n):
        raise ValueError(f"initial: expected shape (T, n) = {(T, n)}, got {np.shape(initial)}")
    elif is_concrete(initial) and not np.all(np.isfinite(np.asarray(initial, np.float64))):
        raise ValueError("initial: contains NaN or infinite entries")
    return _iterated_smooth(
        model, ys, prior, inputs, jnp.asarray(initial, dtype), num_iters, parallel
    )


__all__ = ["IteratedSmootherResult", "iterated_smooth"]
