"""Parallel-in-time Kalman filter: the filter as an associative scan (O(log T) depth).

Elements (Särkkä & García-Fernández 2021, "Temporal parallelization of Bayesian smoothers",
IEEE TAC 66(1), its parallel Kalman filter). An element a = (A, b, C, eta, J, c) over a stretch of steps with
entry state z and exit state x stands for

    p(x | z, y's of the stretch) = N(x; A z + b, C),
    p(y's of the stretch | z)     = exp(c + eta^T z - z^T J z / 2).                         (1)

jaxest's step k updates with y_k and predicts with u_k, so element k has entry x_k and exit
x_{k+1}: since y_k and x_{k+1} are independent given x_k,

    A = F_k, b = B_k u_k, C = G Q G^T, eta = H^T R^-1 r, J = H^T R^-1 H,
    c = log N(r; 0, R),  r = y_k - D_k u_k,                                                 (2)

over the observed rows (NaN rows are removed by ``masked_measurement``: zero rows of H and r,
unit R, and ``num_observed`` counts the rest, so a wholly missing y_k gives eta = 0, J = 0,
c = 0). The prior element is A = 0, b = m0, C = P0, eta = 0, J = 0, c = 0. Combining the earlier
element i with the later j (with M = (I + C_i J_j)^-1):

    A = A_j M A_i,            b = A_j M (b_i + C_i eta_j) + b_j,   C = A_j M C_i A_j^T + C_j,
    eta = A_i^T M^T (eta_j - J_j b_i) + eta_i,                     J = A_i^T M^T J_j A_i + J_i,
    c = c_i + c_j - ln det(I + C_i J_j)/2 - b_i^T M^T J_j b_i / 2
        + eta_j^T M b_i + eta_j^T M C_i eta_j / 2.                                          (3)

The last line is the Gaussian integral of exp(-x^T J_j x/2 + eta_j^T x) against N(A_i z + b_i,
C_i) that the paper leaves out (it has no likelihood); it makes c of the prefix (prior, 0..k) the log-likelihood
log p(y_0..y_k), since a prefix has A = 0, eta = 0, J = 0 and its (b, C) = x(k+1|k), P(k+1|k).

Square-root form (default; Yaghoobi, Corenflos, Hostettler & Särkkä 2022, "Parallel square-root
statistical linear regression for inference in nonlinear state space models").
Written in homogeneous coordinates z^ = [z; 1], an element is x^ = A^ z^ + U^ e (e ~ N(0, I)),
p(y's | z) = exp(logc - |Z^T z^|^2 / 2), with

    A^ = [[A, b], [0, 1]],   U^ = [[U], [0]] (U U^T = C),   Z Z^T = [[J, -eta], [-eta^T, g]],

(n+1) x (n+1) factors; b and eta are folded into A^ and Z, and the constant -g/2 of (1) into
Z's last row. Eq (3) with b = 0 and eta = 0 then reads, with V = Z_j^T U_i and tria(X) the
lower-triangular L with L L^T = X X^T (QR of X^T),

    Xi = tria([V^T, I]) (Xi Xi^T = I + U_i^T J_j U_i),   Om = tria([V, I]) (I + Z_j^T C_i Z_j),
    A^ = A^_j (I - U_i Xi^-T Xi^-1 U_i^T Z_j Z_j^T) A^_i,
    U^ = tria([A^_j U_i Xi^-T, U_j]),   Z = tria([A^_i^T Z_j Om^-T, Z_i]),
    logc = logc_i + logc_j - sum ln |diag Xi|     (ln det(I + C_i J_j) = 2 sum ln |diag Xi|). (4)

For a prefix (A = 0) the likelihood is logc - |last row of Z|^2 / 2: a sum of squares formed by
QR, where eq (3)'s c is a difference of large terms (r^T R^-1 r against its completion of the
square), which loses every digit in float32 once R is small. Element k is A^ = [[F, B u], [0, 1]],
U = G chol(Q), Z^T = [R^-1/2 H, -R^-1/2 r] (observed rows), logc = -(m_obs ln 2 pi + ln det R)/2.
This is the paper's combination with its 2n x 2n triangularisation split into two n x 2n ones
(its Xi11 and Xi22 are Xi and Z_j Om^-T up to an orthogonal factor): both pre-arrays contain I,
so they have full rank and QR's derivative exists, whereas the paper's pre-array is
rank-deficient whenever J_j is (fewer measurements than states, missing data). U^ and Z enter
(4) only through U^ U^^T and Z Z^T, so their own tria uses the tangent dL = dX Q (X^T = Q R),
which is a valid tangent of L L^T whatever the rank (:func:`jaxest.linalg.tria_gram`).

Outputs. The prefix (prior, 0..k) gives x(k+1|k); step k's output needs x(k|k-1), P(k|k-1),
which the prefix before it, (prior, 0..k-1), holds (the protocol hands ``output`` both), and
y_k, which rides along in each element (``combine`` keeps the later one). The output of step k
is the sequential filter's own update of x(k|k-1), P(k|k-1) with y_k
(:class:`~jaxest.KalmanFilter` or :class:`~jaxest.SquareRootKF`), so innovations, their
covariances and the per-step log-likelihood terms are computed by the same code as the
sequential filters'.

A check on the log-likelihood. The prefix's log-likelihood is log p(y_0..y_k) and the previous
prefix's log p(y_0..y_{k-1}), so in exact arithmetic

    loglik(prefix) - loglik(previous) = log N(y_k; y(k|k-1), S_k),                          (5)

the step's term that the sequential update computes from x(k|k-1), P(k|k-1). The two sides come
from different arithmetic (a tree of combinations against one update), and their largest
discrepancy over the steps, relative to |loglik(prefix)| + |loglik(previous)| + |term| + 1, was
0.09-290 times the relative error of the last prefix's (combined) log-likelihood against a
float64 sequential filter where that was below 0.5 (T = 10^4, R from 10^-1 to 10^-6 x SPD, both
forms, float32 and float64; ``benchmarks/parallel_accuracy.py``, docs/parallel.md, two runs on
2026-12-01). Where it exceeds sqrt(eps) -- the relation holds to fewer than half the digits of
the dtype -- the step's status gets ``ParallelStatus.LOGLIK_INCONSISTENT``. That is what the
standard form does in float32 once R is small (eq (3)'s c is a difference of large terms): at
R = 10^-4 x SPD its combined log-likelihood came out +5.6e5 for -3.2e4, and at R = 10^-2 x SPD
it was off by 2.4e-3, both flagged, and its means were off by 5 % at 10^-4; the square-root
form stays unflagged down to R = 10^-4 x SPD in float32 (docs/parallel.md).

Summed over the run, eq (5) reads

    loglik(final) - loglik(prior) = sum over k of the steps' terms,                         (5')

and the associative run checks that too, relative to |loglik(final)| + |loglik(prior)| + the
sum of |term| + 1, flagging the last step. A step's check cannot see a drift spread over many
steps: the standard form in float32 (6 states, 3 measurements, R from 10^-2 to 1, T = 500) was
off by 0.015 nats a step, each within its step's tolerance of about 1.7 nats, and by 7.4 nats
(2.9e-3 relative) in all, with status OK.

The total. The sum of the terms is the log-likelihood the filter reports, as the sequential
filters do:

    log p(y_0..y_{T-1}) = loglik(prior) + sum over k of log N(y_k; y(k|k-1), S_k),             (6)

in both paths (a parallel run sums the terms in O(log T) depth; a sequential one adds each as
it goes), and the combined log-likelihood of the last prefix serves as eq (5')'s check. Each
term is computed from the prefix's x(k|k-1), P(k|k-1) by the sequential update, so it carries
the errors of the means and covariances, not the cancellation of eq (3)'s c. Against the
float64 sequential filter (T = 10^4, R = s x SPD, ``benchmarks/parallel_accuracy.py``,
2026-12-01) the sum's relative error was below that of the combined total in the standard
form (float32, s = 10^-3: 8.1e-6 against 0.73; float64, s = 10^-5: 6.5e-13 against 3.7e-6),
but at float32, s = 10^-6, where the means are NaN (flagged ``NONFINITE``); in the square-root
form the two were alike (float32: within a factor of 4, s = 10^-6: 4.0e-3 against 1.0e-3, both
flagged; float64: both below 4e-13). On the drift problem of ``tests/test_parallel_accuracy.py``
(like the one above; the combined total 3.6 nats off) the sum is 0.005 nats off in a parallel
run and 0.002 in a sequential one, which had reported the combined total too (0.16 nats off).
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from jaxest._checks import check_flag, check_gaussian_arguments, check_gaussian_prior
from jaxest._estimator import AbstractAssociativeEstimator
from jaxest._status import Status, status_where
from jaxest.filters.base import (
    AbstractGaussianFilter,
    CholeskyFactor,
    Covariance,
    FilterResult,
    GaussianState,
    resume_gaussian,
)
from jaxest.filters.common import gaussian_loglik, masked_measurement
from jaxest.filters.kalman import KalmanFilter
from jaxest.filters.sqrt_kf import SquareRootKF
from jaxest.linalg import cholesky, sandwich, solve_triangular, symmetrize, tria, tria_gram
from jaxest.models import LinearGaussian

ParallelStatus = Status.extend(
    "ParallelStatus",
    LOGLIK_INCONSISTENT=(
        4,
        "the parallel filter's combined log-likelihood disagrees with the sequential update's "
        "terms (module docstring, eq (5), on the last step eq (5')): the combinations lost "
        "precision, and the means and covariances they give (and the terms computed from them) "
        "may have too; use the square-root form (ParallelKalmanFilter(square_root=True)) or "
        "float64",
    ),
)
"""The parallel Kalman filter's status flags: the core's and LOGLIK_INCONSISTENT."""


def loglik_discrepancy(prefix, before, term):
    """Eq (5)'s discrepancy |loglik(prefix) - loglik(previous) - term| (``prefix`` - ``before``)
    and its scale |prefix| + |before| + |term| + 1."""
    scale = jnp.abs(prefix) + jnp.abs(before) + jnp.abs(term) + 1
    return jnp.abs(prefix - before - term), scale


def loglik_consistency_status(discrepancy, scale) -> jnp.ndarray:
    """``LOGLIK_INCONSISTENT`` where eq (5) or (5') fails: the discrepancy exceeds sqrt(eps) of
    the scale (:func:`loglik_discrepancy`, :func:`run_loglik_discrepancy`)."""
    tolerance = jnp.sqrt(jnp.finfo(jnp.result_type(discrepancy)).eps)
    return status_where(~(discrepancy <= tolerance * scale), ParallelStatus.LOGLIK_INCONSISTENT)


def run_loglik_discrepancy(first, final, terms):
    """Eq (5') of the module docstring, |loglik(final) - loglik(first) - sum of ``terms``|, and
    its scale |loglik(final)| + |loglik(first)| + sum |terms| + 1."""
    scale = jnp.abs(final) + jnp.abs(first) + jnp.sum(jnp.abs(terms)) + 1
    return jnp.abs(final - first - jnp.sum(terms)), scale


class ParallelFilterResult(FilterResult):
    """:class:`~jaxest.FilterResult` whose status bits are :data:`ParallelStatus`."""

    flags: ClassVar = ParallelStatus


def square_factor(X, cols: int):
    """L with ``cols`` columns and L L^T = X X^T, for X of shape (r, p), r <= cols."""
    if X.shape[1] > cols:
        X = tria_gram(X)
    return jnp.concatenate([X, jnp.zeros((X.shape[0], cols - X.shape[1]), X.dtype)], axis=1)


class Element(eqx.Module):
    """Eq (1): ``cov`` is C (standard) or U (square root), ``info`` J or Z."""

    A: Float[Array, "n n"]
    b: Float[Array, " n"]
    cov: Float[Array, "n n"]
    eta: Float[Array, " n"]
    info: Float[Array, "n n"]
    logc: Float[Array, ""]

    @property
    def mean(self):
        return self.b

    @property
    def factor(self):
        return self.cov

    @property
    def loglik(self):
        return self.logc


def combine_standard(e: Element, l: Element) -> Element:
    """Eq (3) for the earlier element ``e`` and the later ``l``."""
    n = e.b.shape[0]
    eye = jnp.eye(n, dtype=e.b.dtype)
    lu = jax.scipy.linalg.lu_factor(eye + e.cov @ l.info)
    rhs = jnp.concatenate([e.A, (e.b + e.cov @ l.eta)[:, None], e.cov], axis=1)
    X = jax.scipy.linalg.lu_solve(lu, rhs)
    MA, Mb_eta, MC = X[:, :n], X[:, n], X[:, n + 1 :]
    Mb = Mb_eta - MC @ l.eta
    logdet = jnp.sum(jnp.log(jnp.abs(jnp.diag(lu[0]))))
    logc = (
        e.logc + l.logc - 0.5 * logdet - 0.5 * Mb @ (l.info @ e.b)
        + l.eta @ Mb + 0.5 * l.eta @ (MC @ l.eta)
    )  # fmt: skip
    return Element(
        A=l.A @ MA,
        b=l.A @ Mb_eta + l.b,
        cov=symmetrize(l.A @ MC @ l.A.T + l.cov),
        eta=MA.T @ (l.eta - l.info @ e.b) + e.eta,
        info=symmetrize(MA.T @ l.info @ e.A + e.info),
        logc=logc,
    )


class SquareRootElement(eqx.Module):
    """Eq (4)'s element in homogeneous coordinates [z; 1]: ``A`` = [[A, b], [0, 1]],
    ``U`` = [[U], [0]] and ``Z`` with exp(logc - |Z^T [z; 1]|^2 / 2) = p(y's | z)."""

    A: Float[Array, "n+1 n+1"]
    U: Float[Array, "n+1 n+1"]
    Z: Float[Array, "n+1 n+1"]
    logc: Float[Array, ""]

    @property
    def mean(self):
        return self.A[:-1, -1]

    @property
    def factor(self):
        return self.U[:-1, :-1]

    @property
    def loglik(self):
        """logc - |Z^T [z; 1]|^2 / 2 for a prefix, whose Z has only its last row."""
        return self.logc - 0.5 * jnp.sum(self.Z[-1] ** 2)


def combine_square_root(e: SquareRootElement, l: SquareRootElement) -> SquareRootElement:
    """Eq (4) for the earlier element ``e`` and the later ``l``, in homogeneous coordinates."""
    N = e.A.shape[0]
    eye = jnp.eye(N, dtype=e.A.dtype)
    V = l.Z.T @ e.U
    pre = jnp.stack([jnp.concatenate([V.T, eye], 1), jnp.concatenate([V, eye], 1)])
    Xi_Om = tria(pre)  # Xi and Om
    # both triangular solves in one batched call (one LAPACK call at a time, jaxest.montecarlo)
    rhs = jnp.stack([jnp.concatenate([e.U.T, V.T], 1), jnp.concatenate([l.Z.T, 0 * eye], 1)])
    W = jax.scipy.linalg.solve_triangular(Xi_Om, rhs, lower=True)
    Xi, K, KV, Om_Z = Xi_Om[0], W[0, :, :N], W[0, :, N:], W[1, :, :N]
    # K = Xi^-1 U_i^T, KV = Xi^-1 U_i^T Z_j, Om_Z = Om^-1 Z_j^T
    M = eye - K.T @ KV @ l.Z.T  # (I + C_i J_j)^-1
    U, Z = tria_gram(jnp.stack([jnp.concatenate([l.A @ K.T, l.U], 1),
                           jnp.concatenate([e.A.T @ Om_Z.T, e.Z], 1)]))  # fmt: skip
    logdet = jnp.sum(jnp.log(jnp.abs(jnp.diag(Xi))))  # ln det(I + C_i J_j) / 2
    return SquareRootElement(l.A @ M @ e.A, U, Z, e.logc + l.logc - logdet)


def homogeneous(A, b, U, Z, logc) -> SquareRootElement:
    """The element of x = A z + b + U e, p(y | z) = exp(logc - |Z^T [z; 1]|^2 / 2) with Z of
    shape (n+1, p)."""
    n = b.shape[0]
    bottom = jnp.concatenate([jnp.zeros(n, b.dtype), jnp.ones(1, b.dtype)])
    A_hat = jnp.concatenate([jnp.concatenate([A, b[:, None]], 1), bottom[None]], 0)
    U_hat = jnp.concatenate([square_factor(U, n + 1), jnp.zeros((1, n + 1), b.dtype)], 0)
    return SquareRootElement(A_hat, U_hat, square_factor(Z, n + 1), logc)


class ParallelElement(eqx.Module):
    """An element of eq (3) or (4) and its last step's y_k - D_k u_k (NaN where y_k is
    missing)."""

    element: Element | SquareRootElement
    y: Float[Array, " m"]


class ParallelKalmanFilter(AbstractAssociativeEstimator):
    """Parallel-in-time Kalman filter for :class:`~jaxest.LinearGaussian` models (module
    docstring): ``je.run`` evaluates it with :func:`jaxest.scan.associative_scan`, O(log T) depth.

    ``square_root=True`` (default) combines Cholesky-type factors, eq (4), and updates like
    :class:`~jaxest.SquareRootKF` (Q must be positive definite); ``square_root=False`` uses the
    covariance form, eq (3), and updates like :class:`~jaxest.KalmanFilter`. Its result is a
    :class:`~jaxest.FilterResult` whose ``final_state`` is the :class:`~jaxest.GaussianState`
    x(T|T-1), P(T|T-1), log p(y_0..y_{T-1}), so ``rts_smooth``, ``monte_carlo``, ``fit`` and
    resuming (``run(..., state=result.final_state)``, sequentially) work as for the others.
    Second derivatives (``jax.hessian``) need ``square_root=False``: the square-root form's
    are NaN (docs/robustness.md, "Second derivatives").
    """

    square_root: bool = eqx.field(static=True, default=True)
    default_fields: ClassVar[tuple[str, ...]] = AbstractGaussianFilter.default_fields
    result_type: ClassVar[type[FilterResult]] = ParallelFilterResult

    def __check_init__(self):
        check_flag("square_root", self.square_root)

    @property
    def _update(self):
        return SquareRootKF() if self.square_root else KalmanFilter()

    @property
    def _factor_type(self):
        return CholeskyFactor if self.square_root else Covariance

    def _combine_one(self, e, l):
        return (combine_square_root if self.square_root else combine_standard)(e, l)

    def _from_gaussian(self, mean, factor, loglik):
        """The prefix element of N(mean, P) (``factor``: P, or its Cholesky factor) and the
        log-likelihood so far."""
        n = mean.shape[0]
        zero = jnp.zeros((n, n), mean.dtype)
        if self.square_root:
            return homogeneous(zero, mean, factor, jnp.zeros((n + 1, 1), mean.dtype), loglik)
        return Element(zero, mean, factor, jnp.zeros_like(mean), zero, loglik)

    def prior_element(self, model, prior) -> ParallelElement:
        check_gaussian_prior(prior)
        cov = cholesky(prior.cov) if self.square_root else prior.cov
        element = self._from_gaussian(prior.mean, cov, jnp.zeros((), jnp.result_type(prior.mean)))
        return ParallelElement(element, self._no_measurement(model, prior.mean.dtype))

    @staticmethod
    def _no_measurement(model, dtype):
        return jnp.full((model.R.shape[-1],), jnp.nan, dtype)

    def element(self, model, k, y, u) -> ParallelElement:
        """Eq (2), in homogeneous coordinates for the square-root form."""
        n = model.F.shape[-1]
        dtype = jnp.result_type(model.F, y)
        zero = jnp.zeros(n, dtype)
        b, F, G, Q = model.transition(zero, u, k)
        y_pred, H, R = model.observation(zero, u, k)
        meas = masked_measurement(y, y_pred, H, R)
        R_chol = cholesky(meas.R)
        W = solve_triangular(
            R_chol, jnp.concatenate([meas.H, meas.innovation[:, None]], 1), lower=True
        )
        Hw, rw = W[:, :n], W[:, n]  # R^-1/2 H, R^-1/2 r
        F, b = F.astype(dtype), b.astype(dtype)
        if self.square_root:  # |Z^T [z; 1]|^2 = |Hw z - rw|^2
            normaliser = gaussian_loglik(jnp.zeros_like(rw), R_chol, meas.num_observed)
            Z = jnp.concatenate([Hw.T, -rw[None]], 0)
            element = homogeneous(F, b, G @ cholesky(Q), Z, normaliser)
        else:
            logc = gaussian_loglik(rw, R_chol, meas.num_observed)
            C, J = symmetrize(sandwich(G, Q)), symmetrize(Hw.T @ Hw)
            element = Element(F, b, C, Hw.T @ rw, J, logc)
        return ParallelElement(element, y - y_pred)

    def combine(self, earlier: ParallelElement, later: ParallelElement) -> ParallelElement:
        return ParallelElement(self._combine_one(earlier.element, later.element), later.y)

    def output(self, model, previous: ParallelElement, prefix: ParallelElement, k):
        """Step k's output: the sequential update of x(k|k-1), P(k|k-1) (``previous``) with
        y_k, its status checked against eq (5)."""
        before, after = previous.element, prefix.element
        factor = self._factor_type(before.factor)
        # the input's part of y_k is already removed, so u = None; the prediction is discarded
        _, _, out = self._update.update_predict(model, before.mean, factor, k, prefix.y, None)
        out = out.with_covariances_checked()
        inconsistent = loglik_consistency_status(
            *loglik_discrepancy(after.loglik, before.loglik, out.loglik)
        )
        return eqx.tree_at(lambda o: o.status, out, out.status | inconsistent)

    def finish_run(self, outputs, first: ParallelElement, final: ParallelElement):
        """Eq (5') over the whole run, its flag on the last step; the final state's
        log-likelihood is the prior's plus the steps' terms, eq (6)."""
        inconsistent = loglik_consistency_status(
            *run_loglik_discrepancy(first.element.loglik, final.element.loglik, outputs.loglik)
        )
        status = outputs.status.at[-1].set(outputs.status[-1] | inconsistent)
        outputs = eqx.tree_at(lambda o: o.status, outputs, status)
        return outputs, self._gaussian(final, first.element.loglik + jnp.sum(outputs.loglik))

    def _gaussian(self, prefix: ParallelElement, loglik) -> GaussianState:
        """The state x(k+1|k), P(k+1|k) that ``prefix`` holds, with the log-likelihood so far."""
        element = prefix.element
        return GaussianState(element.mean, self._factor_type(element.factor), loglik)

    def init(self, model, prior) -> GaussianState:
        first = self.prior_element(model, prior)
        return self._gaussian(first, first.element.loglik)

    def resume(self, model, state) -> GaussianState:
        """Another Gaussian filter's state with P in this filter's form."""
        return resume_gaussian(state, self._factor_type, type(self).__name__)

    def step(self, model, state: GaussianState, k, y, u, key=None):
        state = self.resume(model, state)
        own = state.factor.chol if self.square_root else state.factor.cov
        previous = ParallelElement(
            self._from_gaussian(state.mean, own, state.loglik),
            self._no_measurement(model, state.mean.dtype),
        )
        prefix = self.combine(previous, self.element(model, k, y, u))
        output = self.output(model, previous, prefix, k)
        return self._gaussian(prefix, state.loglik + output.loglik), output  # eq (6)

    def result(self, outputs, final_state) -> FilterResult:
        return AbstractGaussianFilter.result(self, outputs, final_state)

    def check(self, model, ys, inputs, prior) -> None:
        if not isinstance(model, LinearGaussian):
            raise ValueError(
                f"model: ParallelKalmanFilter needs a jaxest.LinearGaussian model, "
                f"got {type(model).__name__}"
            )
        check_gaussian_arguments(model, ys, inputs, prior, positive_Q=self.square_root)
        if jnp.shape(ys)[0] == 0:
            raise ValueError("ys: has no steps (T = 0): the associative scan needs one")


__all__ = ["ParallelFilterResult", "ParallelKalmanFilter", "ParallelStatus"]
