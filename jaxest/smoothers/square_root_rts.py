"""Square-root RTS smoother: the backward pass of :func:`~jaxest.rts_smooth` on Cholesky factors,
P = L L^T, with no difference of covariances.

The covariance form's P(k|T) = P(k|k) + C_k (P(k+1|T) - P(k+1|k)) C_k^T subtracts P(k+1|k)
from P(k+1|T), and its gain C_k = P(k|k) F_k^T P(k+1|k)^-1 inverts P(k+1|k): in float32 both
lose P(k|T) and x(k|T) where P(k+1|k) is ill-conditioned (docs/robustness.md). Here each step
triangularises (:func:`~jaxest.linalg.tria`, QR without forming the products) the joint
square root of x_{k+1} and x_k given y_0..y_k, with Lq Lq^T = Q_k::

    [[F_k L(k|k), G_k Lq], [L(k|k), 0]]  ->  [[L(k+1|k), 0], [M_k, N_k]]  (lower triangular)  (1)

so that L(k+1|k) L(k+1|k)^T = P(k+1|k), M_k L(k+1|k)^T = P(k|k) F_k^T and N_k N_k^T = P(k|k) -
C_k P(k+1|k) C_k^T, the covariance of x_k given x_{k+1}; then::

    C_k    = M_k L(k+1|k)^-1                                  (one triangular solve)       (2)
    L(k|T) = tria([N_k, C_k L(k+1|T)])                                                      (3)
    x(k|T) = x(k|k) + C_k (x(k+1|T) - x(k+1|k))                                             (4)

C_k's error grows with the condition number of L(k+1|k), the square root of P(k+1|k)'s. F_k is
linearised at x(k|k) as in :func:`~jaxest.rts_smooth`, and the two give the same numbers in exact
arithmetic. L(k|k) is the filter's own factor where its result holds one (``SaveAt(fields=(...,
"factor"))`` of :class:`~jaxest.SquareRootKF`, the square-root parallel filter or an SVD filter,
U diag(D) for the latter), else the Cholesky factor of P(k|k). x(k+1|k) in (4) is f(x(k|k)),
computed here: a filter whose predicted mean carries rounding of its own, independent of its
x(k|k)'s (the parallel filter's, in float32), would otherwise leave it uncancelled, multiplied
by C_k (19 smoothed standard deviations on docs/robustness.md's rotation; 0.0014 this way).

Parallel in time: the elements of :mod:`jaxest.smoothers.parallel` (E_k = C_k, g_k = x(k|k) -
C_k x(k+1|k)) with a square root D_k = N_k of their covariance, combined as a sum of squares,
D = tria([E_k D_s, D_k]) (:func:`combine_square_roots`).

Derivatives. The QR of (1) has no derivative where the array is rank deficient (fewer noise
inputs than states), though every output depends on it only through smooth functions of the
covariances. So each sequential step is a custom JVP whose tangent is that of the covariance-form
step at the same point (:func:`covariance_backward_step`), mapped to the factor's by
:func:`~jaxest.linalg.cholesky_tangent` (P(k|T) positive definite), and the parallel pass one
whose tangent is the covariance-form parallel smoother's (:func:`parallel_covariance_pass`).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from jaxest._status import finite_status
from jaxest.filters.base import Covariance, FilterResult
from jaxest.filters.common import predicted_cov
from jaxest.linalg import (
    after,
    cholesky_tangent,
    mm,
    mv,
    root_tangent_to_cov,
    solve_triangular,
    tangent_or_zeros,
    tria,
)
from jaxest.models import psd_root
from jaxest.scan import associative_scan
from jaxest.smoothers.parallel import parallel_rts_smooth
from jaxest.smoothers.rts import (
    SmootherResult,
    backward_consistency_status,
    backward_steps,
    smoothed_step,
    smoother_gain,
)


def filtered_square_roots(result: FilterResult) -> jax.Array:
    """Square roots L(k|k) of the filtered covariances (T, n, n): the filter's factors where its
    result holds them, else the Cholesky factors of ``result.cov``."""
    factor = Covariance(result.cov) if result.factor is None else result.factor
    return factor.square_root


def covariance_backward_step(model, k, u, mean, cov, mean_next, cov_next):
    """One step of the covariance form, with x(k+1|k) = f(x(k|k)) and P(k+1|k) = F P(k|k) F^T
    + G Q G^T: x(k|T), P(k|T) and P(k+1, k|T) = P(k+1|T) C_k^T from x(k|k), P(k|k), x(k+1|T),
    P(k+1|T)."""
    pred_mean_next, F, G, Q = model.transition(mean, u, k)
    pred_cov = predicted_cov(cov, F, G, Q)
    gain = smoother_gain(mm(cov, F.T), pred_cov)
    return smoothed_step(gain, mean, cov, pred_mean_next, pred_cov, mean_next, cov_next)


def joint_factors(model, k, u, mean, root):
    """x(k+1|k) = f(x(k|k)) and eqs (1)-(2): the gain C_k and N_k, N_k N_k^T = P(k|k) - C_k
    P(k+1|k) C_k^T, from x(k|k) and L(k|k)."""
    n = mean.shape[0]
    pred_mean, F, G, Q = model.transition(mean, u, k)
    noise = mm(G, psd_root(Q))
    joint = tria(jnp.block([[mm(F, root), noise], [root, jnp.zeros_like(noise)]]))  # eq (1)
    pred_root, M, N = joint[:n, :n], joint[n:, :n], joint[n:, n:]
    return pred_mean, solve_triangular(pred_root.T, M.T, lower=False).T, N  # eq (2)


@eqx.filter_custom_jvp
def square_root_step(model, k, u, mean, root, mean_next, root_next):
    """Eqs (1)-(4): x(k|T), L(k|T) and P(k+1, k|T) = P(k+1|T) C_k^T, with the covariance form's
    derivative (module docstring)."""
    pred_mean_next, gain, N = joint_factors(model, k, u, mean, root)
    root_s = tria(jnp.concatenate([N, mm(gain, root_next)], 1))  # eq (3)
    mean_s = mean + mv(gain, mean_next - pred_mean_next)  # eq (4)
    return mean_s, root_s, mm(mm(root_next, root_next.T), gain.T)


@square_root_step.def_jvp
def _square_root_step_jvp(primals, tangents):
    model, k, u, mean, root, mean_next, root_next = primals
    t_model, _, t_u, t_mean, t_root, t_mean_next, t_root_next = tangents
    out = square_root_step(*primals)
    gram = lambda L: mm(L, L.T)
    reference = lambda model, u, *arrays: covariance_backward_step(model, k, u, *arrays)
    primal_in = (mean, gram(root), mean_next, gram(root_next))
    tangent_in = (
        tangent_or_zeros(t_mean, mean), root_tangent_to_cov(root, t_root),
        tangent_or_zeros(t_mean_next, mean_next), root_tangent_to_cov(root_next, t_root_next),
    )  # fmt: skip
    _, (d_mean_s, d_cov_s, d_cross) = eqx.filter_jvp(
        reference, (model, u, *primal_in), (t_model, t_u, *tangent_in)
    )
    return out, (d_mean_s, cholesky_tangent(out[1], d_cov_s), d_cross)


def square_root_backward_pass(model, result: FilterResult, inputs, k0=0) -> SmootherResult:
    """Eqs (1)-(4) of the module docstring for k = T-2, ..., 0, k counted from ``k0``."""
    steps, u_seq = backward_steps(result.mean.shape[0], inputs, k0)
    roots = filtered_square_roots(result)

    def backward(carry, args):
        mean_next, root_next = carry
        k, mean, root, u = args
        mean_s, root_s, cross = square_root_step(model, k, u, mean, root, mean_next, root_next)
        status = finite_status(mean_s, root_s)
        return (mean_s, root_s), (mean_s, mm(root_s, root_s.T), cross, status)

    last = (result.mean[-1], roots[-1])
    args = (steps, result.mean[:-1], roots[:-1], u_seq)
    _, (means, covs, cross, status) = jax.lax.scan(backward, last, args, reverse=True)
    last_cov = mm(last[1], last[1].T)
    return SmootherResult(
        jnp.concatenate([means, last[0][None]]),
        jnp.concatenate([covs, last_cov[None]]),
        jnp.concatenate([status, finite_status(last[1])[None]]) | result.status,
        cross,
        result.flags,
    )


class SquareRootElement(eqx.Module):
    """An element of the parallel smoother (:mod:`jaxest.smoothers.parallel`, its eq (1)) with
    a square root D of its covariance: x_k = E x_{k+1} + g + N(0, D D^T)."""

    E: jax.Array
    g: jax.Array
    D: jax.Array


def combine_square_roots(later: SquareRootElement, earlier: SquareRootElement):
    """The parallel smoother's eq (2) with L = D D^T: D = tria([E_k D_s, D_k]), a sum of
    squares."""
    E = earlier.E
    D = tria(jnp.concatenate([E @ later.D, earlier.D], -1))
    return SquareRootElement(E @ later.E, E @ later.g + earlier.g, D)


@eqx.filter_custom_jvp
def parallel_square_root_pass(model, means, roots, inputs, k0):
    """x(k|T), P(k|T) and P(k+1, k|T) by the parallel smoother's reverse associative scan on
    square-root elements: E_k = C_k, g_k = x(k|k) - C_k x(k+1|k), D_k = N_k from eqs (1)-(2)
    (the last: E = 0, g = x(T-1|T-1), D = L(T-1|T-1)), combined by
    :func:`combine_square_roots`; differentiated as the covariance-form parallel smoother
    (:func:`parallel_covariance_pass`); and per step the status of
    :func:`~jaxest.smoothers.rts.backward_consistency_status`."""
    T, n = means.shape
    steps, u_seq = backward_steps(T, inputs, k0)
    factors = lambda k, u, mean, root: joint_factors(model, k, u, mean, root)
    pred_means, gains, N = jax.vmap(factors)(steps, u_seq, means[:-1], roots[:-1])
    g = means[:-1] - jnp.einsum("kij,kj->ki", gains, pred_means)
    last = SquareRootElement(jnp.zeros((1, n, n), g.dtype), means[-1:], roots[-1:])
    elements = jax.tree.map(
        lambda a, b: jnp.concatenate([a, b]), SquareRootElement(gains, g, N), last
    )
    suffixes = associative_scan(jax.vmap(combine_square_roots), elements, reverse=True)
    covs = suffixes.D @ jnp.swapaxes(suffixes.D, -1, -2)
    sequential_roots = tria(jnp.concatenate([N, gains @ suffixes.D[1:]], -1))
    consistency = backward_consistency_status(
        suffixes.g, suffixes.D, means[:-1], pred_means, gains, sequential_roots
    )
    return suffixes.g, covs, covs[1:] @ jnp.swapaxes(gains, -1, -2), consistency


def parallel_covariance_pass(model, means, covs, inputs, k0):
    """The covariance-form parallel smoother (:func:`~jaxest.smoothers.parallel.parallel_rts_smooth`)
    on the same filtered moments, x(k+1|k) = f(x(k|k)), P(k+1|k) = F P(k|k) F^T + G Q G^T."""
    T = means.shape[0]
    steps, u_seq = backward_steps(T, inputs, k0)

    def predicted(k, u, mean, cov):
        pred_mean, F, G, Q = model.transition(mean, u, k)
        return pred_mean, predicted_cov(cov, F, G, Q)

    pred_means, pred_covs = jax.vmap(predicted)(steps, u_seq, means[:-1], covs[:-1])
    moments = FilterResult(
        final_state=None, mean=means, cov=covs,
        predicted_mean=jnp.concatenate([means[:1], pred_means]),
        predicted_cov=jnp.concatenate([covs[:1], pred_covs]),
        status=jnp.zeros(T, jnp.int32),
    )  # fmt: skip
    smoothed = parallel_rts_smooth(model, moments, inputs, k0)
    return smoothed.mean, smoothed.cov, smoothed.cross_cov


@parallel_square_root_pass.def_jvp
def _parallel_square_root_pass_jvp(primals, tangents):
    model, means, roots, inputs, k0 = primals
    t_model, t_means, t_roots, t_inputs, _ = tangents
    out = parallel_square_root_pass(*primals)
    grams = roots @ jnp.swapaxes(roots, -1, -2)
    d_grams = root_tangent_to_cov(roots, t_roots)
    reference = lambda model, means, covs, inputs: parallel_covariance_pass(
        model, means, covs, inputs, k0
    )
    _, d_out = eqx.filter_jvp(
        reference,
        (model, means, grams, inputs),
        (t_model, tangent_or_zeros(t_means, means), d_grams, t_inputs),
    )
    return out, (*d_out, None)


def parallel_square_root_rts_smooth(model, result: FilterResult, inputs, k0) -> SmootherResult:
    """What :func:`~jaxest.rts_smooth` with ``parallel=True, square_root=True`` runs."""
    roots = after(filtered_square_roots(result), result)  # no batched QR beside the filter's
    means, covs, cross, consistency = parallel_square_root_pass(
        model, result.mean, roots, inputs, k0
    )
    status = jax.vmap(finite_status)(means, covs) | consistency
    return SmootherResult(means, covs, status | result.status, cross, result.flags)
