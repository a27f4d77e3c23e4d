"""Sigma-point sets: unit points xi_i and weights Wm, Wc of the Gaussian quadrature

    E[g(x)] ~ sum_i Wm_i g(X_i),    Cov[g(x)] ~ sum_i Wc_i (g(X_i) - gbar)(g(X_i) - gbar)^T,

with X_i = m + A xi_i for x ~ N(m, P), A A^T = P (a Cholesky factor, or U D of an SVD).
Every set here is symmetric with sum_i Wc_i xi_i xi_i^T = I, so it is exact for linear g.
The points and weights are NumPy constants computed when the filter is traced (the state
dimension is static); the filter casts them to the working dtype.
"""

from __future__ import annotations

import abc
import itertools

import equinox as eqx
import numpy as np


class AbstractSigmaPoints(eqx.Module):
    """A point set: :meth:`unit_points` gives xi (N x n), Wm (N), Wc (N) for dimension n."""

    @abc.abstractmethod
    def unit_points(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Points xi_i (rows) and weights Wm, Wc of the set for N(0, I_n)."""

    def check_dimension(self, n: int) -> None:
        """Raise ``ValueError`` if the set is not defined for dimension ``n`` (default: it is)."""


class UnscentedPoints(AbstractSigmaPoints):
    """Wan & van der Merwe's scaled unscented points (The unscented Kalman filter for nonlinear
    estimation, 2000, eqs 15): lambda = alpha^2 (n + kappa) - n,

        xi_0 = 0,  xi_{+-i} = +-sqrt(n + lambda) e_i,
        Wm_0 = lambda / (n + lambda),  Wc_0 = Wm_0 + 1 - alpha^2 + beta,
        Wm_i = Wc_i = 1 / (2 (n + lambda)),

    ordered as filterpy's ``MerweScaledSigmaPoints`` (0, +1..+n, -1..-n)."""

    alpha: float = eqx.field(static=True, converter=float)
    beta: float = eqx.field(static=True, converter=float)
    kappa: float = eqx.field(static=True, converter=float)

    def __check_init__(self):
        if not self.alpha > 0:
            raise ValueError(f"alpha: must be > 0, got {self.alpha}")
        if not np.isfinite(self.beta):
            raise ValueError(f"beta: must be finite, got {self.beta}")
        if not np.isfinite(self.kappa):
            raise ValueError(f"kappa: must be finite, got {self.kappa}")

    def check_dimension(self, n: int) -> None:
        if not n + self.kappa > 0:
            raise ValueError(f"kappa: n + kappa must be > 0, got n = {n}, kappa = {self.kappa}")

    def unit_points(self, n):
        self.check_dimension(n)
        lam = self.alpha**2 * (n + self.kappa) - n
        c = n + lam
        eye = np.sqrt(c) * np.eye(n)
        xi = np.concatenate([np.zeros((1, n)), eye, -eye])
        Wm = np.full(2 * n + 1, 0.5 / c)
        Wc = Wm.copy()
        Wm[0] = lam / c
        Wc[0] = lam / c + 1.0 - self.alpha**2 + self.beta
        return xi, Wm, Wc


class CubaturePoints(AbstractSigmaPoints):
    """Arasaratnam & Haykin's third-degree spherical-radial cubature rule (Cubature Kalman
    filters, 2009, eq 38): xi_{+-i} = +-sqrt(n) e_i, all weights 1 / (2n)."""

    def unit_points(self, n):
        eye = np.sqrt(n) * np.eye(n)
        W = np.full(2 * n, 0.5 / n)
        return np.concatenate([eye, -eye]), W, W


class GaussHermitePoints(AbstractSigmaPoints):
    """The tensor product of the ``order``-point Gauss-Hermite rule for N(0, 1) (Ito & Xiong,
    Gaussian filters for nonlinear filtering problems, 2000): ``order``^n points, exact for
    polynomials of degree 2 ``order`` - 1 in each coordinate. ``order`` >= 2 (one point, the
    mean, carries no covariance)."""

    order: int = eqx.field(static=True)

    def __check_init__(self):
        if isinstance(self.order, bool) or not isinstance(self.order, int | np.integer):
            raise ValueError(f"order: must be an integer >= 2, got {self.order!r}")
        if self.order < 2:
            raise ValueError(f"order: must be >= 2, got {self.order}")

    def unit_points(self, n):
        nodes, weights = np.polynomial.hermite_e.hermegauss(self.order)
        weights = weights / np.sqrt(2.0 * np.pi)  # probabilists' weight exp(-x^2/2) -> N(0, 1)
        xi = np.array(list(itertools.product(nodes, repeat=n)))
        W = np.prod(np.array(list(itertools.product(weights, repeat=n))), axis=1)
        return xi, W, W
