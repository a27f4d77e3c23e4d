"""Parallel-in-time RTS smoother: the backward pass as a reverse associative scan.

Särkkä & García-Fernández 2021 (IEEE TAC 66(1), its parallel RTS smoother). From the filter result, element k
(k < T-1) stands for p(x_k | x_{k+1}, y_0..y_k) = N(x_k; E_k x_{k+1} + g_k, L_k) with

    E_k = P(k|k) F_k^T P(k+1|k)^-1   (the RTS gain),
    g_k = x(k|k) - E_k x(k+1|k),      L_k = P(k|k) - E_k P(k+1|k) E_k^T,                  (1)

and the last element is E = 0, g = x(T-1|T-1), L = P(T-1|T-1). Combining the element k with the
(already combined) later stretch s:

    E = E_k E_s,   g = E_k g_s + g_k,   L = E_k L_s E_k^T + L_k;                           (2)

the suffix ending at T-1 has E = 0 and (g, L) = x(k|T), P(k|T). F_k is linearised at x(k|k) as
in :func:`~jaxest.rts_smooth`, so both give the same numbers (exact for linear models). The
lag-one cross covariances Cov(x_{k+1}, x_k | y_0..y_{T-1}) = P(k+1|T) E_k^T (Shumway & Stoffer,
Time Series Analysis, Property 6.3) follow from the gains.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from jaxest._status import finite_status
from jaxest.filters.base import FilterResult
from jaxest.filters.common import factor_status
from jaxest.linalg import after, cholesky, mm, symmetrize
from jaxest.scan import associative_scan
from jaxest.smoothers.rts import (
    SmootherResult,
    backward_consistency_status,
    backward_steps,
    smoother_gain,
    transition_cross_covariance,
)


def smoother_gains(model, result: FilterResult, inputs=None, k0=0):
    """Eq (1)'s RTS gains E_k, k = k0..k0+T-2 (shape (T-1, n, n)), F_k linearised at x(k|k).

    Their batched Cholesky waits for every output of the filter: otherwise it can run beside the
    square-root parallel filter's batched QR of its outputs and deadlock jaxlib 0.10 on CPU
    (n > 8; :func:`~jaxest.linalg.after`)."""
    T = result.mean.shape[0]
    pred_cov = after(result.predicted_cov[1:], result)
    cross_covariance = transition_cross_covariance(model)

    def gain(k, mean, cov, pred_cov_next, u):
        return smoother_gain(cross_covariance(k, mean, cov, u), pred_cov_next)

    steps, u_seq = backward_steps(T, inputs, k0)
    return jax.vmap(gain)(steps, result.mean[:-1], result.cov[:-1], pred_cov, u_seq)


class SmootherElement(eqx.Module):
    """Eq (1): x_k = E x_{k+1} + g + N(0, L)."""

    E: jax.Array
    g: jax.Array
    L: jax.Array


def combine(later: SmootherElement, earlier: SmootherElement) -> SmootherElement:
    """Eq (2); the reverse scan (:func:`jaxest.scan.associative_scan`) passes the later stretch first."""
    E = earlier.E
    return SmootherElement(
        E @ later.E, E @ later.g + earlier.g, symmetrize(E @ later.L @ E.T + earlier.L)
    )


@eqx.filter_jit
def parallel_rts_smooth(model, result: FilterResult, inputs=None, k0=0):
    """x(k|T), P(k|T) by the reverse associative scan of eqs (1)-(2) (a
    :class:`~jaxest.SmootherResult`); what :func:`~jaxest.rts_smooth` with ``parallel=True``
    runs."""
    gains = smoother_gains(model, result, inputs, k0)
    pred_mean, pred_cov = result.predicted_mean[1:], result.predicted_cov[1:]
    g = result.mean[:-1] - jnp.einsum("kij,kj->ki", gains, pred_mean)
    L = symmetrize(result.cov[:-1] - gains @ pred_cov @ jnp.swapaxes(gains, -1, -2))
    n = result.mean.shape[-1]
    last = SmootherElement(jnp.zeros((1, n, n), g.dtype), result.mean[-1:], result.cov[-1:])
    elements = jax.tree.map(
        lambda a, b: jnp.concatenate([a, b]), SmootherElement(gains, g, L), last
    )
    suffixes = associative_scan(jax.vmap(combine), elements, reverse=True)
    cross = mm(suffixes.L[1:], jnp.swapaxes(gains, -1, -2))
    # one step of the sequential recursion's covariance from the scan's own P(k+1|T)
    sequential = L + mm(gains, cross)
    # one batched factorisation, after the scan (whose gains were factorised): two at once can
    # deadlock jaxlib 0.10 on CPU (jaxest.linalg.after)
    roots = cholesky(after(symmetrize(jnp.concatenate([suffixes.L, sequential])), suffixes.g))
    smoothed_roots, sequential_roots = roots[: len(suffixes.L)], roots[len(suffixes.L) :]
    status = jax.vmap(finite_status)(suffixes.g, suffixes.L)
    status = status | jax.vmap(factor_status)(smoothed_roots)
    status = status | backward_consistency_status(
        suffixes.g, smoothed_roots, result.mean[:-1], pred_mean, gains, sequential_roots
    )
    return SmootherResult(suffixes.g, suffixes.L, status | result.status, cross, result.flags)


__all__ = ["parallel_rts_smooth", "smoother_gains"]
