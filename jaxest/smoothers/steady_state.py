"""Steady-state Kalman machinery of the fixed-interval Wiener smoother paper (Sun & Cui, 2003, §2).

For the time-invariant model x(t+1) = Phi x(t) + Gamma w(t), y(t) = H x(t) + v(t):

- the steady-state gain (lemma 1, eqs 3-5) and :class:`~jaxest.SteadyStateKalmanFilter` live in
  :mod:`jaxest.filters.steady_state` beside the other filters;
- :func:`arma_innovation_model` (lemma 2, eqs 6-7): A(q^-1) y(t) = Psi(q^-1) eps(t) with
  Psi(q^-1) = det(I - Psi_f q^-1) and A(q^-1) = Psi(q^-1) I - H Phi adj(I - Psi_f q^-1) K q^-1;
- :func:`fixed_point_smooth` (lemma 3, eqs 8-9): x(t|t+i) = x(t|t+i-1) + K_i eps(t+i),
  K_i = Sigma [(I - K H)^T Phi^T]^i H^T (H Sigma H^T + R)^-1;
- :func:`steady_state_smooth` (eq 15): x(t|N) = x(t|t) + sum_{i=1}^{N-t} K_i eps(t+i) for every t,
  the sum evaluated by one backward recursion, so the cost is linear in N.

Time convention (the library's): the prior mean is x(0|-1), the first update uses y(0), so
x(0|0) = x(0|-1) + K (y(0) - H x(0|-1)); measurements y(0), ..., y(N) (N + 1 samples).
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from jaxest._priors import Gaussian
from jaxest._run import run
from jaxest._status import StatusOverSteps
from jaxest.filters.steady_state import (
    SteadyStateGain,
    SteadyStateKalmanFilter,
    SteadyStateStatus,
    check_steady_state_gain,
    steady_state_gain,
)
from jaxest.linalg import working_precision_by_default
from jaxest.models import LinearGaussian


class ArmaInnovationModel(eqx.Module):
    """Lemma 2, eqs 6-7: A(q^-1) y(t) = Psi(q^-1) I_m eps(t), with the polynomial coefficients
    stored by increasing power of q^-1 (``ar[0] = I``, ``ma[0] = 1``)."""

    ar: Float[Array, "n+1 m m"]  #: A_0, ..., A_n
    ma: Float[Array, " n+1"]  #: psi_0, ..., psi_n of Psi(q^-1) = det(I - Psi_f q^-1)
    adj: Float[Array, "n n n"]  #: adj(I - Psi_f q^-1) = sum_j adj[j] q^-j


def characteristic_polynomial(M: Float[Array, "n n"]):
    """det(I - M z) = sum_j c_j z^j and adj(I - M z) = sum_j B_j z^j by the Faddeev-LeVerrier
    recursion B_0 = I, c_j = -tr(M B_{j-1}) / j, B_j = M B_{j-1} + c_j I (exact in exact
    arithmetic and differentiable; meant for the small n of state-space models)."""
    n = M.shape[0]
    eye = jnp.eye(n, dtype=M.dtype)
    coeffs, adj = [jnp.ones((), M.dtype)], [eye]
    for j in range(1, n + 1):
        MB = M @ adj[-1]
        c = -jnp.trace(MB) / j
        coeffs.append(c)
        if j < n:
            adj.append(MB + c * eye)
    return jnp.stack(coeffs), jnp.stack(adj)


def arma_innovation_model(gain: SteadyStateGain) -> ArmaInnovationModel:
    """Eq 7: Psi = det(I - Psi_f q^-1), D = Psi I_m, A = D - H Phi adj(I - Psi_f q^-1) K q^-1.
    Compiled as one program (docs/performance.md, "First calls outside jit")."""
    check_steady_state_gain(gain)
    return _arma_innovation_model(gain)


@eqx.filter_jit
def _arma_innovation_model(gain: SteadyStateGain) -> ArmaInnovationModel:
    psi, adj = characteristic_polynomial(gain.Psi_f)
    m = gain.H.shape[0]
    eye = jnp.eye(m, dtype=psi.dtype)
    lagged = jnp.einsum("ij,ajk,kl->ail", gain.H @ gain.Phi, adj, gain.K)  # H Phi B_j K
    ar = psi[:, None, None] * eye - jnp.concatenate([jnp.zeros((1, m, m), psi.dtype), lagged])
    return ArmaInnovationModel(ar, psi, adj)


def fixed_point_gains(gain: SteadyStateGain, count: int) -> Float[Array, "count n m"]:
    """K_1, ..., K_count of eq 9, K_i = Sigma [(I - K H)^T Phi^T]^i H^T Q_eps^-1."""

    def body(P, _):
        P = gain.smoother_transition @ P
        return P, gain.Sigma @ P

    _, gains = jax.lax.scan(body, gain.innovation_gain, None, length=count)
    return gains


@working_precision_by_default
def fixed_point_smooth(
    gain: SteadyStateGain, filtered_mean: Float[Array, " n"], later_innovations: Float[Array, "L m"]
) -> Float[Array, "L+1 n"]:
    """Lemma 3, eq 8: x(t|t+i) = x(t|t+i-1) + K_i eps(t+i) for i = 1..L from x(t|t), given the
    innovations eps(t+1), ..., eps(t+L); returns x(t|t), x(t|t+1), ..., x(t|t+L)."""
    K = fixed_point_gains(gain, later_innovations.shape[0])
    increments = jnp.einsum("inm,im->in", K, later_innovations)
    path = filtered_mean + jnp.cumsum(increments, axis=0)
    return jnp.concatenate([filtered_mean[None], path])


def backward_gain_sum(
    gain: SteadyStateGain, signal: Float[Array, "T m"], terminal: Float[Array, " n"] | None = None
) -> Float[Array, "T n"]:
    """Sigma S(t) with S(t) = sum_{i=1}^{T-1-t} [(I - K H)^T Phi^T]^i H^T Q_eps^-1 signal(t+i)
    + [(I - K H)^T Phi^T]^{T-1-t} terminal, i.e. sum_i K_i signal(t+i) (eqs 12 and 15) plus a
    decaying end term, by the backward recursion S(T-1) = terminal (default 0),
    S(t) = (I - K H)^T Phi^T (H^T Q_eps^-1 signal(t+1) + S(t+1)): O(T) work and memory."""
    M, Hq = gain.smoother_transition, gain.innovation_gain

    def body(S_next, s_next):
        S = M @ (Hq @ s_next + S_next)
        return S, S

    end = jnp.zeros(gain.Phi.shape[:1], signal.dtype) if terminal is None else terminal
    _, S = jax.lax.scan(body, end, signal[1:], reverse=True)
    return jnp.concatenate([S, end[None]]) @ gain.Sigma.T


class SteadyStateSmootherResult(StatusOverSteps):
    """x(t|N), x(t|t) and eps(t) for t = 0..N (eq 15), and the steady-state filter's
    :data:`~jaxest.filters.steady_state.SteadyStateStatus` bits per step (``NO_STEADY_STATE``
    and ``NONFINITE`` where the gain has no accurate solution:
    :func:`~jaxest.filters.steady_state.steady_state_gain` gives NaN then)."""

    flags: ClassVar = SteadyStateStatus

    mean: Float[Array, "T n"]
    filtered_mean: Float[Array, "T n"]
    innovation: Float[Array, "T m"]
    status: Int[Array, " T"]


@working_precision_by_default
def steady_state_smooth(
    model: LinearGaussian,
    ys: Float[Array, "T m"],
    *,
    prior: Gaussian,
    gain: SteadyStateGain | None = None,
) -> SteadyStateSmootherResult:
    """The non-recursive steady-state fixed-interval smoother, eq 15: the steady-state filter
    (eq 3) forward, then x(t|N) = x(t|t) + sum_{i=1}^{N-t} K_i eps(t+i) by one backward pass.
    ``gain`` is :func:`steady_state_gain` of the model (solved here when not given).

    The filter starts at x(0|-1) = ``prior.mean`` with the steady-state covariance Sigma, which
    it keeps throughout: ``prior.cov`` is not used (the smoother is exact when it equals Sigma;
    for the transient from another covariance use :func:`~jaxest.rts_smooth` of a
    :class:`~jaxest.KalmanFilter` run)."""
    gain = steady_state_gain(model) if gain is None else gain
    filtered = run(SteadyStateKalmanFilter(gain), model, ys, prior=prior)
    mean = filtered.mean + backward_gain_sum(gain, filtered.innovation)
    return SteadyStateSmootherResult(mean, filtered.mean, filtered.innovation, filtered.status)


__all__ = [
    "ArmaInnovationModel",
    "SteadyStateSmootherResult",
    "arma_innovation_model",
    "characteristic_polynomial",
    "fixed_point_gains",
    "fixed_point_smooth",
    "steady_state_smooth",
]
