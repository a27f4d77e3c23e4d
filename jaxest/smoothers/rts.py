"""Rauch-Tung-Striebel fixed-interval smoother for the result of any Gaussian filter.

Backward pass k = T-2, ..., 0 with F_k linearised at the filtered mean x(k|k) (exact for linear
models, the extended RTS smoother otherwise)::

    C_k      = P(k|k) F_k^T P(k+1|k)^-1
    x(k|T)   = x(k|k) + C_k (x(k+1|T) - x(k+1|k))
    P(k|T)   = P(k|k) + C_k (P(k+1|T) - P(k+1|k)) C_k^T
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from jaxest._checks import check_flag, check_inputs, concrete_k0, first_input, model_shapes
from jaxest._status import Status, StatusFlag, StatusOverSteps, finite_status, status_where
from jaxest.filters.base import FilterResult
from jaxest.filters.common import definiteness_status
from jaxest.linalg import (
    cho_solve_lower,
    cholesky,
    mm,
    mv,
    sandwich,
    solve_triangular,
    symmetrize,
    working_precision_by_default,
)
from jaxest.models import check_inputs_used, check_time_axes


class SmootherResult(StatusOverSteps):
    """Smoothed means x(k|T), covariances P(k|T), status bits per step, and the lag-one cross
    covariances P(k+1,k|T) = Cov(x_{k+1}, x_k | y_0..y_{T-1}) = P(k+1|T) C_k^T, k = 0..T-2
    (Shumway & Stoffer, Time Series Analysis, Property 6.3), which with the means and
    covariances are the sufficient statistics of EM (:func:`~jaxest.fit_em`).

    ``status`` holds the filter's bits and the smoother's: ``NONFINITE``, and
    ``NOT_POSITIVE_DEFINITE`` where P(k|T) has no Cholesky factor. The backward pass forms
    P(k|T) by a difference, P(k|k) + C_k (P(k+1|T) - P(k+1|k)) C_k^T, which in float32 can
    lose P(k|T) where it is far below P(k+1|k) even after an accurate (square-root) filter
    (docs/robustness.md); ``rts_smooth(..., square_root=True)`` does not. ``flags`` is the
    filter's family (``ParallelStatus`` after a :class:`~jaxest.ParallelKalmanFilter`), whose
    bits ``status`` carries; ``any_status`` and ``ok`` summarise it over the steps."""

    mean: Float[Array, "T n"]
    cov: Float[Array, "T n n"]
    status: Int[Array, " T"]
    cross_cov: Float[Array, "T-1 n n"]
    flags: type[StatusFlag] = eqx.field(static=True, default=Status)


NEEDED = ("mean", "cov", "predicted_mean", "predicted_cov", "status")

#: how far a parallel smoother may stray from one step of its backward recursion before the step
#: is flagged: half a standard deviation for the mean, half the variance in any direction
BACKWARD_TOLERANCE = 0.5


def backward_consistency_status(
    means, roots, filtered_means, pred_means, gains, sequential_roots
) -> Int[Array, " T"]:
    """``SMOOTHER_INCONSISTENT`` at every step (T) where at some step k < T-1 a parallel
    smoother's x(k|T), P(k|T) = L(k|T) L(k|T)^T (``means``, ``roots``, all T) stray from one
    sequential step from its own k+1: x = x(k|k) + C_k (x(k+1|T) - x(k+1|k)) and P = S S^T =
    P(k|k) - C_k P(k+1|k) C_k^T + C_k P(k+1|T) C_k^T (``sequential_roots`` S, the caller's:
    tria([N_k, C_k L(k+1|T)]) on square roots), by more than
    :data:`BACKWARD_TOLERANCE` in S's metric: |S^-1 (x(k|T) - x)| for the mean, max
    |S^-1 P(k|T) S^-T - I| for the covariance. The sequential step applies C_k to a residual,
    where the parallel scan multiplies gains and offsets of the size of C_k x: in float32, with
    gains of 5e3 (a nearly singular Q), means 366 standard deviations off said OK. A diagnostic:
    no derivative flows through it; NaN sets no bit (``NONFINITE`` says it). One batched
    triangular solve (two would run at once: :func:`~jaxest.linalg.after`). Where the status is
    read, it adds about a quarter to a parallel smoother's run time (16-27 %, n = 4 and 12).

    Every step, because the scan's error reaches steps whose own recursion holds: on that
    float32 case 4 471 steps were off by more than half a standard deviation, 35 broke it."""
    means, roots, filtered_means, pred_means, gains, sequential_roots = jax.lax.stop_gradient(
        (means, roots, filtered_means, pred_means, gains, sequential_roots)
    )
    sequential = filtered_means + jnp.einsum("kij,kj->ki", gains, means[1:] - pred_means)
    both = jnp.concatenate([(means[:-1] - sequential)[..., None], roots[:-1]], -1)
    whitened = solve_triangular(sequential_roots, both, lower=True)
    mean_gap = jnp.linalg.norm(whitened[..., 0], axis=-1)
    eye = jnp.eye(means.shape[-1], dtype=means.dtype)
    cov_gap = jnp.max(jnp.abs(mm(whitened[..., 1:], jnp.swapaxes(whitened[..., 1:], -1, -2)) - eye),
                      axis=(-2, -1))  # fmt: skip
    inconsistent = jnp.any(jnp.maximum(mean_gap, cov_gap) > BACKWARD_TOLERANCE)
    flag = status_where(inconsistent, Status.SMOOTHER_INCONSISTENT)
    return jnp.broadcast_to(flag, means.shape[:1])


def check_smoother_arguments(smoother: str, model, result, inputs, k0=0) -> None:
    """``result`` is a Gaussian filter's result holding the fields the smoothers read, of a
    state the size ``model`` propagates, and ``inputs`` and ``k0`` fit both (``ValueError``
    naming the argument: a particle filter's result raised an ``AttributeError``, a model of
    another size a ``TypeError`` from inside the pass, and inputs to a model without B were
    ignored)."""
    if not isinstance(result, FilterResult):
        raise ValueError(
            f"result: {smoother} smooths the FilterResult of a Gaussian filter, got "
            f"{type(result).__name__}"
        )
    missing = [name for name in NEEDED if getattr(result, name) is None]
    if missing:
        raise ValueError(f"result: {smoother} needs {missing}, which were not saved")
    T, n = result.mean.shape[-2:]
    if T == 0:
        raise ValueError(f"result: has no steps (T = 0), nothing for {smoother} to smooth")
    if inputs is not None:
        check_inputs(inputs, T, f"the filter's result has {T}")
    check_inputs_used(model, inputs)
    u0 = None if inputs is None else jax.tree.map(first_input, inputs)
    try:
        f_shape = model_shapes(model, result.mean[0], u0)["f(x)"]
    except ValueError as err:
        raise ValueError(
            f"model: cannot be evaluated at the result's states, of shape ({n},) "
            f"({type(err.__cause__).__name__}: {err.__cause__})"
        ) from err
    if f_shape != (n,):
        raise ValueError(f"model: propagates a state of shape {f_shape}, the result's has ({n},)")
    first = concrete_k0(k0, "the result's first step, as given to run")
    if first is not None:
        check_time_axes(model, first, T)


def check_factors_saved(result: FilterResult) -> None:
    """A ``ValueError`` where ``result`` comes from a filter that propagates a square-root factor
    (its final state holds one) but holds only the covariances, which the square-root smoother
    would factor again in the working dtype."""
    kept = result.final_state.factor
    if kept.is_square_root and result.factor is None:
        raise ValueError(
            f"result: the filter propagated {type(kept).__name__}s but its result holds only the "
            f"covariances, whose Cholesky factors lose in float32 what the filter kept; run it "
            f"with save=SaveAt(fields=(..., 'factor')) for rts_smooth(..., square_root=True)"
        )


@working_precision_by_default
def rts_smooth(
    model,
    result: FilterResult,
    *,
    inputs=None,
    k0=0,
    parallel: bool = False,
    square_root: bool = False,
) -> SmootherResult:
    """Smooth a :class:`~jaxest.FilterResult` of ``model`` (``inputs`` and ``k0``, the time index
    of the result's first step, as given to :func:`jaxest.run`: a time-varying model is read at
    steps k0, k0 + 1, ...).

    The result must hold the filtered and predicted means and covariances and the status
    (the default :class:`~jaxest.SaveAt`). Compiled once per model structure and shapes.
    ``parallel=True``: the same smoother as a reverse associative scan, O(log T) depth
    (:mod:`jaxest.smoothers.parallel`). ``square_root=True``: the same smoother on Cholesky
    factors (:mod:`jaxest.smoothers.square_root_rts`), sequential or parallel: no difference of
    covariances, so P(k|T) stays positive definite and accurate in float32 where the covariance
    form loses it. It starts from the filter's own factors: a factored filter's
    (:class:`~jaxest.SquareRootKF`, the SVD filters) result must hold them
    (``SaveAt(fields=(..., "factor"))``, else ``ValueError``), since a float32 P(k|k) of very
    different spreads loses in its Cholesky factor what the filter's factor kept
    (docs/robustness.md: on 40 random systems every run within 0.011 standard deviations from
    the factors; from the covariances 7 not finite and 2 off with status OK). Other filters'
    results are smoothed from the Cholesky factors of their covariances. Where P(k+1|k) is
    ill-conditioned (a nearly singular Q) the parallel scan's products of large gains can lose
    in float32 what the sequential smoother keeps: both parallel forms then set
    ``SMOOTHER_INCONSISTENT`` (:func:`backward_consistency_status`; docs/robustness.md).
    """
    check_smoother_arguments("rts_smooth", model, result, inputs, k0)
    check_flag("parallel", parallel)
    check_flag("square_root", square_root)
    if square_root:
        check_factors_saved(result)
    if parallel and not square_root:
        from jaxest.smoothers.parallel import parallel_rts_smooth

        return parallel_rts_smooth(model, result, inputs, jnp.asarray(k0))
    # k0 traced: one program for any k0
    k0 = jnp.asarray(k0)
    return _rts_smooth(model, result, inputs, k0, square_root=square_root, parallel=parallel)


@eqx.filter_jit
def _rts_smooth(
    model, result: FilterResult, inputs, k0, *, square_root: bool, parallel: bool
) -> SmootherResult:
    if square_root:
        from jaxest.smoothers import square_root_rts

        if parallel:
            return square_root_rts.parallel_square_root_rts_smooth(model, result, inputs, k0)
        return square_root_rts.square_root_backward_pass(model, result, inputs, k0)
    return backward_pass(result, inputs, transition_cross_covariance(model), k0)


def transition_cross_covariance(model):
    """``(k, x(k|k), P(k|k), u_k) -> P(k|k) F_k^T``, F_k linearised at x(k|k)."""

    def cross_covariance(k, mean, cov, u):
        _, F, _, _ = model.transition(mean, u, k)
        return mm(cov, F.T)

    return cross_covariance


def smoother_gain(cross_cov, pred_cov_next):
    """C_k = D_k P(k+1|k)^-1 for D_k = ``cross_cov`` (through the Cholesky factor)."""
    return cho_solve_lower(cholesky(pred_cov_next), cross_cov.T).T


def smoothed_step(gain, mean, cov, pred_mean_next, pred_cov_next, mean_next, cov_next):
    """x(k|T), P(k|T) (module docstring) and P(k+1, k|T) = P(k+1|T) C_k^T from the gain C_k."""
    mean_s = mean + mv(gain, mean_next - pred_mean_next)
    cov_s = symmetrize(cov + sandwich(gain, cov_next - pred_cov_next))
    return mean_s, cov_s, mm(cov_next, gain.T)


def backward_steps(T: int, inputs, k0):
    """The time indices k0 .. k0 + T - 2 of a backward pass's steps over T filtered states, and
    their inputs u_k (``None`` without inputs)."""
    u_seq = None if inputs is None else jax.tree.map(lambda a: a[:-1], inputs)
    return k0 + jnp.arange(T - 1), u_seq


def backward_pass(result: FilterResult, inputs, cross_covariance, k0=0) -> SmootherResult:
    """The backward pass of the module docstring with C_k = D_k P(k+1|k)^-1, where
    D_k = ``cross_covariance(k, x(k|k), P(k|k), u_k)`` is the filter's covariance of x_k and
    x_{k+1} given y_0..y_k (P(k|k) F_k^T here; the sigma points' in
    :mod:`jaxest.smoothers.sigma_point_rts`), k counted from ``k0``."""
    steps, u_seq = backward_steps(result.mean.shape[0], inputs, k0)

    def backward(carry, args):
        mean_next, cov_next = carry
        k, mean, cov, pred_mean_next, pred_cov_next, u = args
        gain = smoother_gain(cross_covariance(k, mean, cov, u), pred_cov_next)
        mean_s, cov_s, cross = smoothed_step(
            gain, mean, cov, pred_mean_next, pred_cov_next, mean_next, cov_next
        )
        status = finite_status(mean_s, cov_s) | definiteness_status(cov_s)
        return (mean_s, cov_s), (mean_s, cov_s, cross, status)

    last = (result.mean[-1], result.cov[-1])
    args = (
        steps,
        result.mean[:-1],
        result.cov[:-1],
        result.predicted_mean[1:],
        result.predicted_cov[1:],
        u_seq,
    )
    _, (means, covs, cross, status) = jax.lax.scan(backward, last, args, reverse=True)
    return SmootherResult(
        jnp.concatenate([means, last[0][None]]),
        jnp.concatenate([covs, last[1][None]]),
        jnp.concatenate([status, finite_status(last[1])[None]]) | result.status,
        cross,
        result.flags,
    )
