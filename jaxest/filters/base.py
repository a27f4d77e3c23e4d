"""The Gaussian filter family: its state, step output, result, and abstract base.

Every Gaussian filter carries x(k|k-1), its predicted covariance in the filter's own
representation (a :class:`AbstractCovarianceFactor`: the covariance itself, a Cholesky factor,
SVD factors U, D or the information matrix) and the running log-likelihood. A concrete filter is
:class:`AbstractGaussianFilter` plus a class-level factor type and one method, ``update_predict``:
the prior check, ``init``, ``check`` and ``result`` are written once, here.
"""

from __future__ import annotations

import abc
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from jaxest._checks import check_gaussian_arguments, check_gaussian_prior
from jaxest._estimator import AbstractEstimator, AbstractResult
from jaxest._status import finite_status
from jaxest.linalg import (
    FACTORS,
    chol_inverse,
    cholesky,
    cov_from_factor,
    factor_psd_or_nan,
    inv_spd,
)


class AbstractCovarianceFactor(eqx.Module):
    """A covariance P held in some factored form; ``cov`` gives P itself. Concrete factors
    also have a classmethod ``from_cov(P)``, which :meth:`AbstractGaussianFilter.init` uses."""

    #: whether the factor is itself a square root of P (Cholesky, SVD), which keeps variances
    #: far below eps times the largest that P formed in the working dtype loses
    is_square_root: ClassVar[bool] = False

    @property
    @abc.abstractmethod
    def cov(self) -> Float[Array, "n n"]:
        """P."""

    @property
    def square_root(self) -> Float[Array, "n n"]:
        """Some L with L L^T = P (any leading axes): the factor itself where it is one
        (:attr:`is_square_root`), else the Cholesky factor of P."""
        return cholesky(self.cov)


class Covariance(AbstractCovarianceFactor):
    """P itself."""

    matrix: Float[Array, "n n"]

    @classmethod
    def from_cov(cls, P):
        return cls(P)

    @property
    def cov(self):
        return self.matrix


class CholeskyFactor(AbstractCovarianceFactor):
    """Lower-triangular S with P = S S^T."""

    is_square_root: ClassVar[bool] = True
    chol: Float[Array, "n n"]

    @classmethod
    def from_cov(cls, P):
        return cls(cholesky(P))

    @property
    def cov(self):
        return self.chol @ jnp.swapaxes(self.chol, -1, -2)

    @property
    def square_root(self):
        return self.chol


class SVDFactor(AbstractCovarianceFactor):
    """P = U diag(D)^2 U^T, U orthogonal, D >= 0 (the SVD filters' factors)."""

    is_square_root: ClassVar[bool] = True
    U: Float[Array, "n n"]
    D: Float[Array, " n"]

    @classmethod
    def from_cov(cls, P):
        """U, D of P; D NaN for an indefinite P (:func:`~jaxest.linalg.factor_psd_or_nan`)."""
        return cls(*factor_psd_or_nan(P))

    @property
    def cov(self):
        return cov_from_factor(self.U, self.D)

    @property
    def square_root(self):
        return self.U * self.D[..., None, :]


class InformationMatrix(AbstractCovarianceFactor):
    """Y = P^-1 (the information filter's form)."""

    info: Float[Array, "n n"]

    @classmethod
    def from_cov(cls, P):
        return cls(inv_spd(P))

    @property
    def cov(self):
        return chol_inverse(cholesky(self.info))


def check_gaussian_state(state, name: str) -> None:
    """A ``ValueError`` where ``state``, given to the Gaussian filter ``name`` to resume from,
    is not a Gaussian filter's :class:`GaussianState`."""
    if not isinstance(state, GaussianState):
        raise ValueError(
            f"state: {name} resumes from a Gaussian filter's state (its result.final_state), "
            f"got {type(state).__name__}"
        )


def resume_gaussian(state, factor_type: type[AbstractCovarianceFactor], name: str):
    """``state``, a Gaussian filter's :class:`GaussianState`, with P held as ``factor_type``
    (converted through P where another filter held it otherwise); ``name``: the resuming
    filter's, for the ``ValueError`` any other state gets."""
    check_gaussian_state(state, name)
    if not isinstance(state.factor, factor_type):
        return GaussianState(state.mean, factor_type.from_cov(state.factor.cov), state.loglik)
    return state


class GaussianState(eqx.Module):
    """x(k|k-1), P(k|k-1) in the filter's factor, and log p(y_0, ..., y_{k-1})."""

    mean: Float[Array, " n"]
    factor: AbstractCovarianceFactor
    loglik: Float[Array, ""]


class StepOutput(eqx.Module):
    """What one filter step emits (stacked over time by the driver; unsaved fields ``None``)."""

    predicted_mean: Float[Array, " n"] | None
    predicted_cov: Float[Array, "n n"] | None
    mean: Float[Array, " n"] | None
    cov: Float[Array, "n n"] | None
    innovation: Float[Array, " m"] | None
    innovation_cov: Float[Array, "m m"] | None
    loglik: Float[Array, ""] | None
    status: Int[Array, ""] | None
    predicted_factor: AbstractCovarianceFactor | None = None
    factor: AbstractCovarianceFactor | None = None

    def with_covariances_checked(self) -> StepOutput:
        """This output, its status ``NONFINITE`` where a covariance it outputs is not finite. A
        factored filter's covariance can overflow while the factor it carries stays finite (S
        S^T of a float32 Cholesky factor past 1.8e19), which its own status does not see."""
        covariances = (self.predicted_cov, self.cov, self.innovation_cov)
        return eqx.tree_at(lambda out: out.status, self, self.status | finite_status(*covariances))


class FilterResult(AbstractResult):
    """What every Gaussian filter returns (fields the caller did not save are ``None``).

    ``predicted_*`` are the one-step predictions x(k|k-1), P(k|k-1) used to process y_k;
    ``mean``/``cov`` are the filtered x(k|k), P(k|k). ``innovation`` is y_k - h(x(k|k-1)) with
    NaN (missing) entries set to zero; ``innovation_cov`` its covariance. ``loglik_terms`` are the
    Gaussian log-likelihood terms of the observed entries; ``status`` holds
    :class:`~jaxest.Status` bits per step. Factored filters also give their factors
    (``factor``, ``predicted_factor``) when saved with ``SaveAt(fields=(..., "factor"))``.
    """

    final_state: GaussianState
    status: Int[Array, " T"] | None = None
    any_status: Int[Array, ""] | None = None
    saved: object = None
    mean: Float[Array, "T n"] | None = None
    cov: Float[Array, "T n n"] | None = None
    predicted_mean: Float[Array, "T n"] | None = None
    predicted_cov: Float[Array, "T n n"] | None = None
    innovation: Float[Array, "T m"] | None = None
    innovation_cov: Float[Array, "T m m"] | None = None
    loglik_terms: Float[Array, " T"] | None = None
    factor: AbstractCovarianceFactor | None = None
    predicted_factor: AbstractCovarianceFactor | None = None

    @property
    def loglik(self) -> Float[Array, ""]:
        """Total log-likelihood log p(y_0, ..., y_{T-1}) (kept whatever was saved)."""
        return self.final_state.loglik


class AbstractGaussianFilter(AbstractEstimator):
    """A Gaussian filter: ``factor_type`` says how P is held, ``update_predict`` is the step.

    ``needs_positive_definite_Q``: the filter factors or inverts Q (checked before tracing).
    """

    factor_type: ClassVar[type[AbstractCovarianceFactor]]
    needs_positive_definite_Q: ClassVar[bool] = False
    #: the result class (a subclass where a filter raises flags of its own)
    result_type: ClassVar[type[FilterResult]] = FilterResult
    default_fields: ClassVar[tuple[str, ...]] = (
        "predicted_mean", "predicted_cov", "mean", "cov",
        "innovation", "innovation_cov", "loglik", "status",
    )  # fmt: skip

    @property
    def checkpoint_by_default(self) -> bool:
        """Whether gradients through :func:`jaxest.run` recompute each step in the reverse pass
        by default: where P is held as itself (a covariance or information matrix) or as SVD
        factors, not as a square-root (Cholesky or QR) factor.

        The reverse pass of a small filter is bound by how many arrays it stores and reads back
        per step, not by arithmetic. Measured on the Duffing map (2 states, T = 1000,
        value_and_grad, docs/performance.md): 1.4-2.8x faster on one sequence and 2-2.7x under
        ``vmap`` for the EKFs and the UKF, 1.4-1.6x and 1.6-2.3x for the SVD filters; the
        23-state flight model's Kalman filter 8 % slower on one sequence, 19 % faster over 10
        runs under ``vmap``, its SVD filters 14-25 % and 11-12 % faster. The square-root forms
        gained nothing measurable."""
        return self.factor_type in (Covariance, InformationMatrix, SVDFactor)

    @property
    def checkpoint_policy(self):
        """What a step recomputed in the reverse pass keeps from the forward pass: for SVD
        factors, the factors themselves (:data:`jaxest.linalg.FACTORS`); else nothing.

        SVD factors are not unique where singular values repeat (P0 = I, isotropic Q). A
        recomputed step can round its way to other singular vectors than the forward pass gave
        the next step, and the derivative rules, which map covariance tangents to factor
        tangents through the factors, then disagree from one step to the next: recomputing
        everything gave a UKF's SVD form with P0 = I a gradient 1e-3 off (relative), under the
        test suite's XLA flags. Keeping the factors also skips their recomputation, which made
        this faster than both storing everything and recomputing everything."""
        if self.factor_type is SVDFactor:
            return jax.checkpoint_policies.save_only_these_names(FACTORS)
        return None

    @abc.abstractmethod
    def update_predict(self, model, x, factor, k, y, u) -> tuple:
        """Measurement update with y_k at (x(k|k-1), P(k|k-1)), then prediction to k+1.

        Returns ``(x(k+1|k), factor(k+1|k), output)`` with ``output`` a :class:`StepOutput`.
        """

    def init(self, model, prior) -> GaussianState:
        check_gaussian_prior(prior)
        zero = jnp.zeros((), jnp.result_type(prior.mean))
        return GaussianState(prior.mean, self.factor_type.from_cov(prior.cov), zero)

    def resume(self, model, state) -> GaussianState:
        """Another Gaussian filter's state with P in this filter's form (``factor_type``)."""
        return resume_gaussian(state, self.factor_type, type(self).__name__)

    def step(self, model, state: GaussianState, k, y, u, key=None):
        state = self.resume(model, state)
        x_next, factor_next, output = self.update_predict(model, state.mean, state.factor, k, y, u)
        output = output.with_covariances_checked()
        return GaussianState(x_next, factor_next, state.loglik + output.loglik), output

    def result(self, outputs: StepOutput, final_state: GaussianState) -> FilterResult:
        return self.result_type(
            mean=outputs.mean,
            cov=outputs.cov,
            predicted_mean=outputs.predicted_mean,
            predicted_cov=outputs.predicted_cov,
            innovation=outputs.innovation,
            innovation_cov=outputs.innovation_cov,
            loglik_terms=outputs.loglik,
            status=outputs.status,
            final_state=final_state,
            factor=outputs.factor,
            predicted_factor=outputs.predicted_factor,
        )

    def check(self, model, ys, inputs, prior) -> None:
        check_gaussian_arguments(
            model, ys, inputs, prior, positive_Q=self.needs_positive_definite_Q
        )
