"""The particle filter (sequential importance resampling) on the estimator protocol.

N particles x_k^i with normalised weights W_k^i represent p(x_k | y_0..y_k). One step k
(Doucet & Johansen, "A tutorial on particle filtering and smoothing", 2011, sec. 4):

1. draw x_k^i ~ q(x_k | x_{k-1}^i, y_k): the model's transition (bootstrap; Gordon, Salmond &
   Smith 1993) or a user's :class:`AbstractProposal`;
2. weight::

       log w_k^i = log W_{k-1}^i + log g(y_k | x_k^i)
                   + log p(x_k^i | x_{k-1}^i) - log q(x_k^i | x_{k-1}^i, y_k)          (1)

   (the last two cancel for the bootstrap proposal), g the Gaussian measurement density of the
   observed (non-NaN) entries of y_k;
3. the likelihood increment p(y_k | y_0..y_{k-1}) ~= sum_i w_k^i (the W_{k-1} sum to one, and
   are 1/N after a resampling: the resampling-aware increment, Doucet & Johansen eq. 48)
                                                                                        (2)
   and W_k^i = w_k^i / sum_j w_k^j, ESS = 1 / sum_i (W_k^i)^2;
4. if ESS < ``ess_threshold`` N, resample: ancestors a_i drawn by the chosen scheme
   (:func:`resample`), W = 1/N.

The transition to x_{k+1} is computed at the end of step k (it needs u_k), so the state holds,
per particle, the Gaussian p(x_{k+1} | x_k^i) = N(f(x_k^i, u_k, k), A_i A_i^T), A_i = G_i L_Q;
the prior is the first such Gaussian (the driver gives ``init`` no key).

Weights are NaN-safe: a non-finite increment counts as -inf (zero weight). When no particle has
a finite weight, the step sets :attr:`ParticleStatus.WEIGHTS_DEGENERATE`, ignores y_k (weights
stay those of step k-1) and adds log(tiny) of the dtype to the log-likelihood: every output stays
finite.

Gradients (``differentiable=True``): particles are reparameterised (x = m + A z), so derivatives
flow through them, but resampling indices are discrete. Following Scibior & Wood
("Differentiable particle filtering without modifying the forward pass", 2021) the resampled
log-weights are set to log W_{a_i} - stop_gradient(log W_{a_i}) - log N: the forward pass is
unchanged (the value is -log N) and the derivative carries the score d log W_{a_i} of the
ancestor draw. With multinomial resampling at every step (``ess_threshold=1``), the derivative of
the likelihood estimate Z^ = exp(loglik) so obtained is then an *unbiased* estimate of
d p(y_0..y_{T-1}) / d theta (the score-function identity for the ancestors, the pathwise one for
the particles); the derivative of loglik, dZ^/Z^, is a ratio of unbiased estimates: *consistent*
as N grows (bias O(1/N)), not unbiased. Stratified and systematic ancestors are not drawn
independently from W, and an adaptive threshold makes the resampling decision itself depend
on theta, so those choices are consistent but carry a (small) bias. ``differentiable=False``
drops the score term (resampled log-weights are the constant -log N): the plain derivative of
the forward pass, which is biased for every N (it ignores how the ancestors depend on theta).
"""

from __future__ import annotations

import abc
import functools
import math
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from jaxest._checks import (
    check_flag,
    check_gaussian_arguments,
    check_matrix,
    check_resumed_arguments,
    is_concrete,
)
from jaxest._estimator import AbstractEstimator, AbstractResult
from jaxest._priors import Gaussian
from jaxest._status import Status, finite_status, status_where
from jaxest.filters.base import GaussianState
from jaxest.filters.common import gaussian_loglik, masked_measurement
from jaxest.linalg import cholesky, mv, solve_triangular, tria

ParticleStatus = Status.extend(
    "ParticleStatus",
    WEIGHTS_DEGENERATE=(
        64,
        "every particle's weight underflowed or was not finite, so the measurement was ignored: "
        "use more particles, a proposal that looks at y_k, or check the measurement for outliers",
    ),
)
"""The particle filter's status flags: the core's and WEIGHTS_DEGENERATE."""

RESAMPLING = ("systematic", "stratified", "multinomial")


def resample(key, weights: Float[Array, " N"], scheme: str = "systematic") -> Int[Array, " N"]:
    """Ancestor indices a_1..a_N by inverting the weights' CDF at N uniforms u_i:

    - multinomial: u_i iid U(0, 1) (each a_i ~ W independently);
    - stratified: u_i = (i + U_i) / N, U_i iid U(0, 1) (Kitagawa 1996);
    - systematic: u_i = (i + U) / N, one U ~ U(0, 1) (Carpenter, Clifford & Fearnhead 1999):
      particle j gets floor(N W_j) or ceil(N W_j) children.

    ``weights`` are non-negative with a positive sum (normalised here); zero-weight particles
    are never chosen. Known weights that are not (a negative, NaN or infinite weight, or all
    zero, which picked arbitrary particles) are a ``ValueError``.
    """
    if np.ndim(weights) != 1:
        raise ValueError(f"weights: expected a vector, got shape {np.shape(weights)}")
    check_matrix("weights", weights, ndim=1)  # finite where known
    known = np.asarray(weights) if is_concrete(weights) else None
    if known is not None and (np.any(known < 0) or not np.sum(known) > 0):
        raise ValueError("weights: must be non-negative with a positive sum")
    N = weights.shape[0]
    dtype = weights.dtype
    if scheme == "multinomial":
        offsets = None
    elif scheme == "stratified":
        offsets = jax.random.uniform(key, (N,), dtype)
    elif scheme == "systematic":
        offsets = jax.random.uniform(key, (), dtype)
    else:
        raise ValueError(f"resampling: expected one of {RESAMPLING}, got {scheme!r}")
    cdf = jnp.cumsum(weights)
    cdf = cdf / cdf[-1]
    if offsets is None:
        return jnp.minimum(_search_sorted(cdf, jax.random.uniform(key, (N,), dtype)), N - 1)
    ancestors = jax.lax.platform_dependent(
        cpu=lambda: _ancestors_by_counting(cdf, offsets),
        default=lambda: _search_sorted(cdf, (jnp.arange(N, dtype=dtype) + offsets) / N),
    )
    return jnp.minimum(ancestors, N - 1)


def _ancestors_by_counting(cdf, offsets):
    """The stratified or systematic ancestors, u_i = (i + offsets_i) / N (a scalar offset:
    systematic), in O(N) without a search: with b_j = #{i : u_i < cdf_j}, ancestor a_i is
    #{j : b_j <= i} (u is sorted), a cumulative sum of the counts of the b_j. b_j is
    ceil(N cdf_j - U) for the systematic u; for the stratified, with k = floor(N cdf_j), the k
    strata below and stratum k's own u_k if it falls below cdf_j. A zero weight repeats cdf_j,
    hence b_j: no children. The same indices as the search (tests/test_particle.py: 200 keys
    at N = 10^3, 20 at N = 10^5); on the 2-core CPU, systematic at N = 10^5 1.3 against 3.2 ms,
    stratified 3.1 against 9.7 ms, and under ``vmap`` over 200 runs of N = 10^3 2.1 against 3.9
    and 6.3 against 21 ms. Accelerators keep the sort (:func:`_search_sorted`): not measured
    there."""
    N = cdf.shape[0]
    scaled = N * cdf
    if offsets.ndim == 0:
        below = jnp.ceil(scaled - offsets)
    else:
        strata = jnp.clip(jnp.floor(scaled), 0, N)
        own = offsets[jnp.minimum(strata, N - 1).astype(jnp.int32)]
        below = strata + ((strata < N) & (own < scaled - strata))
    below = jnp.clip(below, 0, N).astype(jnp.int32)
    return jnp.cumsum(jnp.zeros(N + 1, jnp.int32).at[below].add(1))[:N]


def _search_sorted(cdf, u):
    """``jnp.searchsorted(cdf, u, side="right")`` by the method that is fastest on the platform:
    the binary search ("scan", a loop of log2 N steps) on the CPU, a sort of cdf and u together
    on accelerators, where each loop step launches kernels. Measured with
    ``benchmarks/particle.py`` (N = 1000, T = 200, same indices): on the 2-core CPU (``--quick``)
    the sort took 2.4-3.5x the binary search's time; on an NVIDIA H100 the binary search took
    2.7x the sort's on one sequence (200 against 74 us per step) and 1.5x under ``vmap`` over
    200 runs (0.97 against 0.65 us per step and run). Multinomial resampling everywhere, and
    stratified and systematic on accelerators (:func:`_ancestors_by_counting` on the CPU)."""

    search = functools.partial(jnp.searchsorted, side="right")
    return jax.lax.platform_dependent(
        cdf, u, cpu=functools.partial(search, method="scan"),
        default=functools.partial(search, method="sort"),
    )  # fmt: skip


class GaussianTransition(eqx.Module):
    """p(x_k | x_{k-1}) of one particle: N(mean, factor factor^T) (for x_0: the prior)."""

    mean: Float[Array, " n"]
    factor: Float[Array, "n n"]

    def sample(self, key):
        """A reparameterised draw mean + factor z, z ~ N(0, I); for transitions stacked on
        leading axes (every particle's), one draw of each from the one key."""
        z = jax.random.normal(key, self.mean.shape, self.mean.dtype)
        return self.mean + mv(self.factor, z)

    def log_prob(self, x):
        """log N(x; mean, factor factor^T) (needs a non-singular covariance)."""
        L = cholesky(self.factor @ self.factor.T)
        whitened = solve_triangular(L, x - self.mean, lower=True)
        return gaussian_loglik(whitened, L, x.shape[0])


class AbstractProposal(eqx.Module):
    """A proposal q(x_k | x_{k-1}, y_k) for :class:`ParticleFilter`, for one particle.

    ``transition`` is that particle's p(x_k | x_{k-1}^i) (a :class:`GaussianTransition`: at
    k = 0, the prior); ``y`` the measurement y_k (NaN = missing), ``u`` and ``k`` its input and
    index. ``sample`` must be reparameterised (a differentiable function of the model and a
    noise draw) for gradients to be meaningful; ``log_prob`` is the log-density of what
    ``sample`` draws.
    """

    @abc.abstractmethod
    def sample(self, model, transition: GaussianTransition, k, y, u, key) -> Float[Array, " n"]:
        """One draw x_k ~ q(. | x_{k-1}, y_k)."""

    @abc.abstractmethod
    def log_prob(self, model, x, transition: GaussianTransition, k, y, u) -> Float[Array, ""]:
        """log q(x | x_{k-1}, y_k)."""


def normalise_log_weights(log_w):
    """log W_i = log w_i - log sum_j w_j, and log sum_j w_j, with the W_i summing to one.

    Normalised relative to the largest log-weight: where the log-weights are huge (a
    measurement far in a tail, 1e16 off in float64 or 1e5 in float32: log-weights near -1e32,
    resp. -1e10), log w_i - logsumexp(log w) rounds the sum's own log(count) away, so k
    log-weights tied by rounding each got W = 1 (a weighted "mean" summing k particles, an ESS
    below one). The shift has no derivative (as in
    ``jax.nn.logsumexp``): the result does not depend on it."""
    peak = jax.lax.stop_gradient(jnp.max(log_w))
    shifted = log_w - peak  # <= 0, and 0 at the largest
    log_sum = jnp.log(jnp.sum(jnp.exp(shifted)))  # in [0, log N]
    return shifted - log_sum, peak + log_sum


class ParticleState(eqx.Module):
    """Per particle: p(x_k | x_{k-1}^i) and log W_{k-1}^i; and log p(y_0..y_{k-1})."""

    transition: GaussianTransition  # batched over particles: mean (N, n), factor (N, n, n)
    log_weights: Float[Array, " N"]
    loglik: Float[Array, ""]


class ParticleOutput(eqx.Module):
    """One step's output: weighted mean and covariance of x_k, ESS, log-likelihood term."""

    mean: Float[Array, " n"] | None
    cov: Float[Array, "n n"] | None
    ess: Float[Array, ""] | None
    loglik: Float[Array, ""] | None
    status: Int[Array, ""] | None
    particles: Float[Array, "N n"] | None
    log_weights: Float[Array, " N"] | None


class ParticleResult(AbstractResult):
    """What :class:`ParticleFilter` returns (unsaved fields ``None``): the weighted mean and
    covariance of x_k given y_0..y_k, the effective sample size before resampling, the
    log-likelihood terms (2), the status bits (:data:`ParticleStatus`), and, when saved, the
    particles x_k^i with their normalised log-weights."""

    flags: ClassVar = ParticleStatus

    final_state: ParticleState
    status: Int[Array, " T"] | None = None
    any_status: Int[Array, ""] | None = None
    saved: object = None
    mean: Float[Array, "T n"] | None = None
    cov: Float[Array, "T n n"] | None = None
    ess: Float[Array, " T"] | None = None
    loglik_terms: Float[Array, " T"] | None = None
    particles: Float[Array, "T N n"] | None = None
    log_weights: Float[Array, "T N"] | None = None

    @property
    def loglik(self) -> Float[Array, ""]:
        """The estimate of log p(y_0, ..., y_{T-1}) (kept whatever was saved)."""
        return self.final_state.loglik


class ParticleFilter(AbstractEstimator):
    """Sequential importance resampling (module docstring: eqs 1-2, gradients).

    Args:
        num_particles: N >= 1.
        resampling: ``"systematic"`` (default), ``"stratified"`` or ``"multinomial"``.
        ess_threshold: resample when ESS < ess_threshold N; in (0, 1] (1: at every step where
            the weights are not all equal).
        proposal: ``None`` for the bootstrap proposal (the model's transition), or an
            :class:`AbstractProposal`.
        differentiable: keep the score of the resampling in the derivative (Scibior & Wood).

    Run as ``jaxest.run(ParticleFilter(...), model, ys, prior=Gaussian(m0, P0), key=key)`` on a
    :class:`~jaxest.LinearGaussian` or :class:`~jaxest.NonlinearGaussian` model (Q positive
    definite; Q_k may depend on u and k, not on x; additive noise x_{k+1} = f(x_k, u_k) + G w_k,
    not ``noise_on_input``, which is a ``ValueError``). Cost O(N) per step.
    """

    needs_key: ClassVar[bool] = True
    default_fields: ClassVar[tuple[str, ...]] = ("mean", "cov", "ess", "loglik", "status")

    num_particles: int = eqx.field(static=True)
    resampling: str = eqx.field(static=True)
    ess_threshold: float = eqx.field(static=True)
    proposal: AbstractProposal | None
    differentiable: bool = eqx.field(static=True)

    def __init__(
        self,
        num_particles: int = 1000,
        resampling: str = "systematic",
        ess_threshold: float = 0.5,
        proposal: AbstractProposal | None = None,
        differentiable: bool = True,
    ):
        if isinstance(num_particles, bool) or not isinstance(num_particles, int):
            raise ValueError(f"num_particles: expected an int, got {num_particles!r}")
        if num_particles < 1:
            raise ValueError(f"num_particles: must be at least 1, got {num_particles}")
        if resampling not in RESAMPLING:
            raise ValueError(f"resampling: expected one of {RESAMPLING}, got {resampling!r}")
        if not (isinstance(ess_threshold, int | float) and 0.0 < ess_threshold <= 1.0):
            raise ValueError(f"ess_threshold: must lie in (0, 1], got {ess_threshold!r}")
        if proposal is not None and not isinstance(proposal, AbstractProposal):
            raise ValueError(
                f"proposal: expected None or an AbstractProposal, got {type(proposal).__name__}"
            )
        check_flag("differentiable", differentiable)
        self.num_particles, self.resampling = num_particles, resampling
        self.ess_threshold, self.proposal = float(ess_threshold), proposal
        self.differentiable = bool(differentiable)

    def check(self, model, ys, inputs, prior) -> None:
        check_gaussian_arguments(model, ys, inputs, prior, positive_Q=True)
        if getattr(model, "noise_on_input", False):
            raise ValueError(
                "model: has its noise on the input (noise_on_input=True), x_{k+1} = f(x_k, u_k + "
                "w_k), whose transition density is not the Gaussian N(f, G Q G^T) the particle "
                "filter samples and weighs (G the linearisation df/du); give the noise as "
                "x_{k+1} = f(x_k, u_k) + G w_k, or filter it with noise='augmented'"
            )

    def check_resumed(self, model, ys, inputs, state) -> None:
        """:meth:`~jaxest.AbstractEstimator.check_resumed` at a particle's predicted mean (or a
        Gaussian filter's state's mean)."""
        particle = isinstance(state, ParticleState)
        mean = state.transition.mean[0] if particle else getattr(state, "mean", None)
        check_resumed_arguments(model, ys, inputs, mean)

    def init(self, model, prior) -> ParticleState:
        N = self.num_particles
        dtype = jnp.result_type(prior.mean)
        chol = cholesky(jnp.asarray(prior.cov, dtype))
        transition = GaussianTransition(
            jnp.broadcast_to(prior.mean, (N, *prior.mean.shape)),
            jnp.broadcast_to(chol, (N, *chol.shape)),
        )
        return ParticleState(transition, jnp.full((N,), -math.log(N), dtype), jnp.zeros((), dtype))

    def resume(self, model, state) -> ParticleState:
        """A particle filter's state as it is; a Gaussian filter's (x(k|k-1), P(k|k-1)) as the
        Gaussian the particles are drawn from, as :meth:`init` draws them from the prior, with
        its log-likelihood carried on."""
        name = type(self).__name__
        if isinstance(state, GaussianState):
            drawn_from = self.init(model, Gaussian(state.mean, state.factor.cov))
            return eqx.tree_at(lambda s: s.loglik, drawn_from, state.loglik)
        if not isinstance(state, ParticleState):
            raise ValueError(
                f"state: {name} resumes from a particle filter's or a Gaussian filter's state "
                f"(result.final_state), got {type(state).__name__}"
            )
        if state.log_weights.shape[-1] != self.num_particles:
            raise ValueError(
                f"state: holds {state.log_weights.shape[-1]} particles, this {name} "
                f"{self.num_particles}"
            )
        return state

    def step(self, model, state: ParticleState, k, y, u, key):
        key_propose, key_resample = jax.random.split(key)
        x, log_increment = self._propose(model, state.transition, k, y, u, key_propose)
        log_increment = jnp.where(jnp.isfinite(log_increment), log_increment, -jnp.inf)
        degenerate = ~jnp.any(jnp.isfinite(log_increment))
        log_w = state.log_weights + jnp.where(degenerate, 0.0, log_increment)  # eq 1
        log_W, log_total = normalise_log_weights(log_w)  # eq 2 (previous weights sum to one)
        tiny = jnp.log(jnp.finfo(log_w.dtype).tiny)
        loglik = jnp.where(degenerate, tiny, log_total)
        W = jnp.exp(log_W)
        mean, cov = weighted_moments(x, W)
        ess = 1.0 / jnp.sum(W**2)
        log_W_next, ancestors = self._resample(log_W, W, ess, key_resample)
        x_next = x[ancestors]
        status = finite_status(mean, cov, loglik) | status_where(
            degenerate, ParticleStatus.WEIGHTS_DEGENERATE
        )
        transition = jax.vmap(lambda xi: model_transition(model, xi, u, k))(x_next)
        output = ParticleOutput(mean, cov, ess, loglik, status, x, log_W)
        return ParticleState(transition, log_W_next, state.loglik + loglik), output

    def _propose(self, model, transition, k, y, u, key):
        """Particles x_k^i and their log-weight increments (eq 1 without log W_{k-1})."""
        if self.proposal is None:  # every particle's draw from one key (docs/sigma_point.md)
            x = transition.sample(key)
            return x, measurement_loglik(model, x, k, y, u)

        def one(t, kk):
            xi = self.proposal.sample(model, t, k, y, u, kk)
            correction = t.log_prob(xi) - self.proposal.log_prob(model, xi, t, k, y, u)
            return xi, correction

        x, correction = jax.vmap(one)(transition, jax.random.split(key, self.num_particles))
        return x, measurement_loglik(model, x, k, y, u) + correction

    def _resample(self, log_W, W, ess, key):
        """Log-weights and ancestors after the ESS-triggered resampling (step 4); W = exp(log_W)."""
        N = self.num_particles
        resampled = ess < self.ess_threshold * N
        drawn = resample(key, W, self.resampling)
        ancestors = jnp.where(resampled, drawn, jnp.arange(N))
        uniform = jnp.full_like(log_W, -math.log(N))
        if self.differentiable:  # Scibior & Wood: value -log N, derivative d log W_{a_i}
            chosen = log_W[drawn]
            uniform = uniform + chosen - jax.lax.stop_gradient(chosen)
        return jnp.where(resampled, uniform, log_W), ancestors

    def result(self, outputs: ParticleOutput, final_state: ParticleState) -> ParticleResult:
        return ParticleResult(
            final_state=final_state,
            status=outputs.status,
            mean=outputs.mean,
            cov=outputs.cov,
            ess=outputs.ess,
            loglik_terms=outputs.loglik,
            particles=outputs.particles,
            log_weights=outputs.log_weights,
        )


def weighted_moments(x, W):
    """sum_i W_i x_i and sum_i W_i (x_i - m)(x_i - m)^T; zero-weight particles (possibly
    non-finite) take no part."""
    x = jnp.where(W[:, None] > 0, x, 0.0)
    mean = W @ x
    d = x - mean
    return mean, (W[:, None] * d).T @ d


def measurement_loglik(model, x, k, y, u) -> Float[Array, " N"]:
    """log g(y_k | x^i) of the observed entries of y_k for every particle (0 if none observed)."""
    y_pred = jax.vmap(lambda xi: model.h(xi, u, k))(x)
    R = model.measurement_cov(k)
    no_jacobian = jnp.zeros((y.shape[0], 0), R.dtype)
    meas = masked_measurement(y, y_pred, no_jacobian, R)  # innovations (N, m)
    L = cholesky(meas.R)
    whitened = solve_triangular(L, meas.innovation.T, lower=True).T
    return jax.vmap(lambda w: gaussian_loglik(w, L, meas.num_observed))(whitened)


def model_transition(model, x, u, k) -> GaussianTransition:
    """p(x_{k+1} | x_k = x) = N(f(x, u_k, k), G Q G^T), with a square factor of G L_Q:
    zero-padded when q < n, reduced by a QR factorisation when q > n."""
    G, Q = model.process_noise(x, u, k)
    A = G @ cholesky(Q)
    n, q = A.shape
    if q < n:
        A = jnp.concatenate([A, jnp.zeros((n, n - q), A.dtype)], axis=1)
    elif q > n:
        A = tria(A)
    return GaussianTransition(model.f(x, u, k), A)
