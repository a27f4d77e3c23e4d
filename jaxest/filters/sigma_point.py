"""Sigma-point Kalman filters (unscented, cubature, Gauss-Hermite) in three forms.

One step, with (Wm, Wc, xi) from the point set (:mod:`jaxest.filters.sigma_points`) and A a
square root of the covariance held by the form (A A^T = P):

Measurement update at x(k|k-1), P(k|k-1) (points redrawn from the predicted moments)::

    X_i = x + A xi_i,  Y_i = h(X_i),  yhat = sum Wm_i Y_i                              (1)
    S   = sum Wc_i (Y_i - yhat)(Y_i - yhat)^T + R,  C = sum Wc_i (X_i - x)(Y_i - yhat)^T  (2)
    K   = C S^-1,  x(k|k) = x + K (y - yhat)                                             (3)
    P(k|k) = sum Wc_i (dX_i - K dY_i)(dX_i - K dY_i)^T + K R K^T  (= P - K S K^T)        (4)

Time update at x(k|k), P(k|k)::

    X_i = x + A xi_i,  x(k+1|k) = sum Wm_i f(X_i),
    P(k+1|k) = sum Wc_i (f(X_i) - x(k+1|k))(...)^T + G Q G^T                             (5)

The innovation is e = y - yhat and the log-likelihood term log N(e; 0, S). With
``noise="augmented"`` the noise enters through the model's ``sample_transition(x, u, k, w)`` and
``sample_observation(x, u, k, v)`` (non-additive noise): the points are drawn for [x; w] ~
N([x; 0], diag(P, Q)) and [x; v] ~ N([x; 0], diag(P, R)), and the additive Q, R terms drop out of
(2), (4), (5).

Forms (how P is held; each sum of weighted outer products in (2), (4), (5) is evaluated in it):

- ``"covariance"``: P itself, A = chol(P).
- ``"sqrt"``: the lower Cholesky factor L (A = L); each sum is the triangular factor of the QR
  of the stacked rows sqrt(Wc_i) dX_i^T and noise square-root rows, followed by a rank-one
  Cholesky downdate for each negative weight. P is never formed; the sigma points are the same as
  the covariance form's.
- ``"svd"``: P = U diag(D)^2 U^T; each sum is the SVD of the same stacked rows (an
  eigendecomposition of the small matrix diag(s^2) - c c^T folds in negative weights), so no
  Cholesky factor of an indefinite matrix is ever taken. A is the lower-triangular factor of the
  QR of (U D)^T, i.e. chol(P) without forming P: the points, and so the filter, are the
  covariance form's on every model, only the arithmetic differs. (A = U D would lay the points
  along the principal axes of P: another quadrature rule, which on bearings-only tracking puts a
  whole slab of Gauss-Hermite points, weight 1/6, behind the sensor at once and lost runs the
  covariance form keeps.)

The SVD form is differentiated through its eigen-factors by :func:`eigen_tangent`: the exact
derivative where eigenvalues are distinct and, where they repeat (P0 = c I), the finite tangent
that reproduces the covariance tangent exactly (no division by a zero eigen-gap).
"""

from __future__ import annotations

import abc
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxest._checks import check_gaussian_prior
from jaxest.filters.base import (
    AbstractGaussianFilter,
    CholeskyFactor,
    Covariance,
    GaussianState,
    StepOutput,
    SVDFactor,
)
from jaxest.filters.common import LOG_2PI, gaussian_loglik, masked_measurement, step_status
from jaxest.filters.sigma_points import (
    AbstractSigmaPoints,
    CubaturePoints,
    GaussHermitePoints,
    UnscentedPoints,
)
from jaxest.linalg import (
    cho_solve_lower,
    cholesky,
    cov_from_factor,
    factor_psd_or_nan,
    keep_factors,
    right_svd,
    solve_triangular,
    symmetrize,
    tria,
)

FORMS = ("covariance", "sqrt", "svd")
NOISES = ("additive", "augmented")


# --------------------------------------------------------------------------------------------
# Factor primitives: Cholesky downdate, eigen-factors with a safe tangent


def cholesky_downdate(L, v):
    """Lower L' with L' L'^T = L L^T - v v^T by hyperbolic rotations (Golub & Van Loan,
    Matrix Computations, 4th ed., 6.5.4); NaN where L L^T - v v^T is not positive definite."""
    n = L.shape[-1]
    idx = jnp.arange(n)
    columns = []
    for j in range(n):
        col = L[:, j]
        r = jnp.sqrt(col[j] ** 2 - v[j] ** 2)
        c, s = r / col[j], v[j] / col[j]
        new = jnp.where(idx > j, (col - s * v) / c, jnp.where(idx == j, r, 0.0))
        v = jnp.where(idx > j, c * v - s * new, 0.0)
        columns.append(new)
    return jnp.stack(columns, axis=-1)


def eigen_tangent(U, D, dP):
    """Tangent (dU, dD) of P = U diag(D)^2 U^T (U orthogonal) for the covariance tangent dP.

    With K = U^T dP U and lambda = D^2: dD_i = K_ii / (2 D_i) and dU = U Omega with
    Omega_ij = K_ij / (lambda_j - lambda_i) for distinct eigenvalues (the eigenvector
    derivative), K_ij / (2 lambda_j) within a repeated eigenvalue (a non-rotating choice there).
    Either way dU D^2 U^T + U D^2 dU^T + 2 U D dD U^T = dP exactly, and the tangent is finite
    where eigenvalues repeat; it is infinite only for a zero eigenvalue (flagged by ``status``).
    """
    K = U.T @ dP @ U
    lam = D**2
    gap = lam[None, :] - lam[:, None]
    tol = 100.0 * jnp.finfo(lam.dtype).eps * jnp.max(lam)
    distinct = jnp.abs(gap) > tol
    denominator = jnp.where(distinct, gap, 2.0 * lam[None, :])
    safe = jnp.where(denominator == 0, 1.0, denominator)
    off = ~jnp.eye(D.shape[0], dtype=bool)
    omega = jnp.where(off & (denominator != 0), K / safe, 0.0)
    safe_D = jnp.where(D > 0, D, 1.0)
    dD = jnp.where(D > 0, jnp.diag(K) / (2.0 * safe_D), 0.0)
    return U @ omega, dD


@jax.custom_jvp
def eigen_factor(P):
    """:func:`~jaxest.linalg.factor_psd_or_nan` (U, D with P = U diag(D)^2 U^T, D descending;
    D NaN where P is indefinite beyond rounding, so an indefinite Q, R or prior shows in the
    status under ``jit`` instead of being clipped to a different model) with the tangent of U
    and D themselves, not only of P: the SVD form's sigma points depend on U diag(D)."""
    return factor_psd_or_nan(P)


@eigen_factor.defjvp
def _eigen_factor_jvp(primals, tangents):
    (P,), (dP,) = primals, tangents
    U, D = keep_factors(*eigen_factor(P))
    return (U, D), eigen_tangent(U, D, symmetrize(dP))


@jax.custom_jvp
def rows_factor(plus, minus):
    """U, D with U diag(D)^2 U^T = plus^T plus - minus^T minus, from the SVD of ``plus`` (and,
    if ``minus`` has rows, the eigendecomposition of diag(s^2) - (minus V)^T (minus V) in the
    basis V of its right singular vectors). Negative eigenvalues are clipped to D = 0."""
    n = plus.shape[-1]
    if plus.shape[0] < n:
        plus = jnp.concatenate([plus, jnp.zeros((n - plus.shape[0], n), plus.dtype)])
    s, V = right_svd(plus)
    if minus.shape[0] == 0:
        return V, s
    c = minus @ V
    w, E = jnp.linalg.eigh(symmetrize(jnp.diag(s**2) - c.T @ c))
    return V @ E[:, ::-1], jnp.sqrt(jnp.clip(w[::-1], 0.0))


@rows_factor.defjvp
def _rows_factor_jvp(primals, tangents):
    (plus, minus), (d_plus, d_minus) = primals, tangents
    U, D = keep_factors(*rows_factor(plus, minus))
    dP = plus.T @ d_plus - minus.T @ d_minus
    return (U, D), eigen_tangent(U, D, dP + dP.T)


# --------------------------------------------------------------------------------------------
# The three forms: how a weighted sum of outer products, a gain and a likelihood are evaluated


def _split_weights(Wc):
    """Indices of the positive and of the negative weights (static: weights are NumPy)."""
    return np.flatnonzero(Wc > 0), np.flatnonzero(Wc < 0)


class AbstractForm(eqx.Module):
    """How a sigma-point filter holds P. Noise enters as a square root B (B B^T = N)."""

    factor_type: ClassVar[type]

    @abc.abstractmethod
    def square_root(self, factor):
        """A with A A^T = P, the matrix the sigma points are drawn with."""

    @abc.abstractmethod
    def combine(self, dev, Wc, noise_sqrt):
        """The factor of sum_i Wc_i dev_i dev_i^T + B B^T (dev: rows; B: ``noise_sqrt``)."""

    @abc.abstractmethod
    def gain_and_loglik(self, S_factor, C, e, num_observed):
        """K = C S^-1, log N(e; 0, S) and S, from the factor of S."""

    @abc.abstractmethod
    def status(self, factor):
        """``NOT_POSITIVE_DEFINITE`` unless the factor holds a positive definite matrix."""

    def noise_sqrt(self, N):
        """A square root B of the noise covariance N (B B^T = N)."""
        return cholesky(N)

    def from_cov(self, P):
        return self.factor_type.from_cov(P)


class CovarianceForm(AbstractForm):
    factor_type = Covariance

    def square_root(self, factor):
        return cholesky(factor.matrix)

    def combine(self, dev, Wc, noise_sqrt):
        w = jnp.asarray(Wc, dev.dtype)
        return Covariance(symmetrize(dev.T @ (w[:, None] * dev) + noise_sqrt @ noise_sqrt.T))

    def gain_and_loglik(self, S_factor, C, e, num_observed):
        S = S_factor.matrix
        S_chol = cholesky(S)
        K = cho_solve_lower(S_chol, C.T).T
        loglik = gaussian_loglik(solve_triangular(S_chol, e, lower=True), S_chol, num_observed)
        return K, loglik, S

    def status(self, factor):
        return step_status(factor.matrix, cov=factor.matrix)


class SquareRootForm(AbstractForm):
    factor_type = CholeskyFactor

    def square_root(self, factor):
        return factor.chol

    def combine(self, dev, Wc, noise_sqrt):
        plus, minus = _split_weights(Wc)
        rows = jnp.sqrt(jnp.asarray(Wc[plus], dev.dtype))[:, None] * dev[plus]
        L = tria(jnp.concatenate([rows.T, noise_sqrt], 1))
        for i in minus:
            L = cholesky_downdate(L, np.sqrt(-Wc[i]).astype(dev.dtype) * dev[i])
        return CholeskyFactor(L)

    def gain_and_loglik(self, S_factor, C, e, num_observed):
        S_chol = S_factor.chol
        K = cho_solve_lower(S_chol, C.T).T
        loglik = gaussian_loglik(solve_triangular(S_chol, e, lower=True), S_chol, num_observed)
        return K, loglik, S_chol @ S_chol.T

    def status(self, factor):
        return step_status(factor.chol, cov_factor=factor.chol)


class SVDForm(AbstractForm):
    factor_type = SVDFactor

    def square_root(self, factor):
        """chol(P) from the factors, as the lower-triangular factor of the QR of (U D)^T (P is
        not formed; D = 0 gives a zero column, not a failure): the covariance form's points.
        U D itself would put the point grid on the principal axes, a different quadrature."""
        return tria(factor.U * factor.D)

    def combine(self, dev, Wc, noise_sqrt):
        plus, minus = _split_weights(Wc)
        rows = jnp.sqrt(jnp.asarray(Wc[plus], dev.dtype))[:, None] * dev[plus]
        neg = jnp.sqrt(jnp.asarray(-Wc[minus], dev.dtype))[:, None] * dev[minus]
        return SVDFactor(*rows_factor(jnp.concatenate([rows, noise_sqrt.T]), neg))

    def gain_and_loglik(self, S_factor, C, e, num_observed):
        U, D = S_factor.U, S_factor.D
        K = ((C @ U) / D**2) @ U.T
        whitened = (U.T @ e) / D
        logdet = 2.0 * jnp.sum(jnp.log(D))
        loglik = -0.5 * (num_observed * LOG_2PI + logdet + whitened @ whitened)
        return K, loglik, cov_from_factor(U, D)

    def status(self, factor):
        return step_status(factor.U, factor.D, positive=jnp.all(factor.D > 0))

    def noise_sqrt(self, N):
        U, D = eigen_factor(N)
        return U * D

    def from_cov(self, P):
        return SVDFactor(*eigen_factor(P))


FORM_TYPES = {"covariance": CovarianceForm, "sqrt": SquareRootForm, "svd": SVDForm}


# --------------------------------------------------------------------------------------------
# The filter


def _draw(mean, A, xi):
    """Sigma points mean + A xi_i as rows."""
    return mean + xi @ A.T


def _weighted_mean(W, Z):
    return jnp.asarray(W, Z.dtype) @ Z


class AbstractSigmaPointFilter(AbstractGaussianFilter):
    """A sigma-point Kalman filter (module docstring, eqs 1-5). A concrete filter gives its point
    set through :meth:`point_set`; ``form`` ("covariance", "sqrt", "svd") says how P is held and
    ``noise`` ("additive", "augmented") how the noise enters.

    Saved with ``SaveAt(fields=(..., "factor", "predicted_factor"))`` the factored forms also
    return their factors of P(k|k) and P(k|k-1). ``innovation`` is y - yhat (eq 1) and
    ``innovation_cov`` the sigma-point S (eq 2).
    """

    form: eqx.AbstractVar[str]
    noise: eqx.AbstractVar[str]

    @abc.abstractmethod
    def point_set(self) -> AbstractSigmaPoints:
        """The sigma-point set of this filter."""

    def __check_init__(self):
        if self.form not in FORMS:
            raise ValueError(f"form: must be one of {FORMS}, got {self.form!r}")
        if self.noise not in NOISES:
            raise ValueError(f"noise: must be one of {NOISES}, got {self.noise!r}")

    @property
    def factor_type(self):
        return FORM_TYPES[self.form].factor_type

    @property
    def needs_positive_definite_Q(self):
        """The covariance and square-root forms take a Cholesky factor of Q."""
        return self.form != "svd"

    def factor_form(self) -> AbstractForm:
        """The operations of this filter's ``form``."""
        return FORM_TYPES[self.form]()

    def init(self, model, prior) -> GaussianState:
        check_gaussian_prior(prior)
        zero = jnp.zeros((), jnp.result_type(prior.mean))
        return GaussianState(prior.mean, self.factor_form().from_cov(prior.cov), zero)

    def check(self, model, ys, inputs, prior) -> None:
        super().check(model, ys, inputs, prior)
        n = np.shape(prior.mean)[0]
        if self.noise == "augmented":
            u0 = None if inputs is None else jax.tree.map(lambda a: a[0], inputs)
            n_w = np.shape(model.process_noise(prior.mean, u0, 0)[1])[-1]
            n_v = np.shape(model.measurement_cov(0))[-1]
            for size in (n + n_w, n + n_v):
                self.point_set().check_dimension(size)
        else:
            self.point_set().check_dimension(n)

    def _points(self, n, dtype):
        xi, Wm, Wc = self.point_set().unit_points(n)
        return jnp.asarray(xi, dtype), Wm, Wc

    def measurement_update(self, form, model, x, factor, k, y, u):
        """Eqs 1-4: x(k|k), its factor, e, S and the log-likelihood term."""
        n, m = x.shape[0], y.shape[0]
        A = form.square_root(factor)
        if self.noise == "augmented":
            R_sqrt = form.noise_sqrt(model.measurement_cov(k))
            xi, Wm, Wc = self._points(n + m, x.dtype)
            X = _draw(x, A, xi[:, :n])
            V = xi[:, n:] @ R_sqrt.T
            Y = jax.vmap(lambda s, v: model.sample_observation(s, u, k, v))(X, V)
            R = jnp.zeros((m, m), x.dtype)
        else:
            xi, Wm, Wc = self._points(n, x.dtype)
            X = _draw(x, A, xi)
            Y = jax.vmap(lambda s: model.h(s, u, k))(X)
            R = model.measurement_cov(k)
        y_pred = _weighted_mean(Wm, Y)
        meas = masked_measurement(y, y_pred, (Y - y_pred).T, R)  # missing rows of dY zeroed
        dY = meas.H.T
        dX = X - _weighted_mean(Wm, X)
        # augmented: R = 0, so meas.R is the unit variance of the missing rows only
        noise = meas.R if self.noise == "augmented" else form.noise_sqrt(meas.R)
        C = dX.T @ (jnp.asarray(Wc, x.dtype)[:, None] * dY)
        K, loglik, S = form.gain_and_loglik(
            form.combine(dY, Wc, noise), C, meas.innovation, meas.num_observed
        )
        x_post = x + K @ meas.innovation
        post = form.combine(dX - dY @ K.T, Wc, K @ noise)  # eq 4
        return x_post, post, meas.innovation, S, loglik

    def propagate(self, form, model, x, factor, k, u):
        """The points of the time update at x(k|k): state deviations X_i - x (rows), f(X_i),
        the weights Wm, Wc and the square root of the additive noise G Q G^T (zero columns
        when the noise is augmented)."""
        n = x.shape[0]
        A = form.square_root(factor)
        G, Q = model.process_noise(x, u, k)
        if self.noise == "augmented":
            xi, Wm, Wc = self._points(n + Q.shape[-1], x.dtype)
            X = _draw(x, A, xi[:, :n])
            W = xi[:, n:] @ form.noise_sqrt(Q).T
            FX = jax.vmap(lambda s, w: model.sample_transition(s, u, k, w))(X, W)
            noise = jnp.zeros((n, 0), x.dtype)
        else:
            xi, Wm, Wc = self._points(n, x.dtype)
            X = _draw(x, A, xi)
            FX = jax.vmap(lambda s: model.f(s, u, k))(X)
            noise = G @ form.noise_sqrt(Q)
        return X - _weighted_mean(Wm, X), FX, Wm, Wc, noise

    def time_update(self, form, model, x, factor, k, u):
        """Eq 5: x(k+1|k) and its factor."""
        _, FX, Wm, Wc, noise = self.propagate(form, model, x, factor, k, u)
        x_next = _weighted_mean(Wm, FX)
        return x_next, form.combine(FX - x_next, Wc, noise)

    def update_predict(self, model, x, factor, k, y, u):
        form = self.factor_form()
        x_post, post, e, S, loglik = self.measurement_update(form, model, x, factor, k, y, u)
        x_next, factor_next = self.time_update(form, model, x_post, post, k, u)
        status = step_status(x_next, loglik) | form.status(post) | form.status(factor_next)
        out = StepOutput(
            x, factor.cov, x_post, post.cov, e, S, loglik, status,
            predicted_factor=factor, factor=post,
        )  # fmt: skip
        return x_next, factor_next, out


class UKF(AbstractSigmaPointFilter):
    """The unscented Kalman filter (Julier & Uhlmann; scaled points of Wan & van der Merwe,
    :class:`~jaxest.filters.sigma_points.UnscentedPoints`). The defaults alpha = 1, beta = 2,
    kappa = 0 keep every weight non-negative; small alpha (e.g. 1e-3) gives a large negative
    Wc_0, which the ``"sqrt"`` form meets with a Cholesky downdate."""

    alpha: float = eqx.field(static=True, default=1.0, converter=float)
    beta: float = eqx.field(static=True, default=2.0, converter=float)
    kappa: float = eqx.field(static=True, default=0.0, converter=float)
    form: str = eqx.field(static=True, default="covariance")
    noise: str = eqx.field(static=True, default="additive")

    def __check_init__(self):
        self.point_set()  # raises ValueError naming alpha, beta or kappa

    def point_set(self):
        return UnscentedPoints(self.alpha, self.beta, self.kappa)


class CubatureKF(AbstractSigmaPointFilter):
    """Arasaratnam & Haykin's cubature Kalman filter (2n points +-sqrt(n) e_i, equal weights);
    the UKF with alpha = 1, beta = 0, kappa = 0."""

    form: str = eqx.field(static=True, default="covariance")
    noise: str = eqx.field(static=True, default="additive")

    def point_set(self):
        return CubaturePoints()


class GaussHermiteKF(AbstractSigmaPointFilter):
    """The Gauss-Hermite Kalman filter (Ito & Xiong, 2000): ``order``^n points, exact for
    polynomial moments up to degree 2 ``order`` - 1 per coordinate."""

    order: int = eqx.field(static=True, default=3)
    form: str = eqx.field(static=True, default="covariance")
    noise: str = eqx.field(static=True, default="additive")

    def __check_init__(self):
        self.point_set()  # raises ValueError naming order

    def point_set(self):
        return GaussHermitePoints(self.order)


__all__ = ["AbstractSigmaPointFilter", "CubatureKF", "GaussHermiteKF", "UKF"]
