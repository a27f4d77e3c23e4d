"""The one scan driver, the Gaussian prior and result Modules, and status codes.

Every estimator in jaxest is an ``eqx.Module`` with

- ``init(model, prior) -> state`` and
- ``step(model, state, y_k, u_k) -> (state, output)``, a pure function that runs under
  ``jit``, ``vmap``, ``grad`` and inside ``lax.scan``,

and a ``result(outputs, state)`` that packs the stacked outputs into the estimator's result
Module. :func:`run` drives any of them over a sequence; :func:`filter` adds argument checks for the
Gaussian filters. Users with their own loop call ``step`` themselves.

Failure under ``jit`` is data, not an exception: outputs carry an integer ``status`` per step
whose bits are the :class:`Status` flags below.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int


class Status:
    """Bit flags of the per-step ``status`` field (0 means all is well)."""

    OK = 0
    NONFINITE = 1  #: a mean, covariance or likelihood term is NaN or infinite
    NOT_POSITIVE_DEFINITE = 2  #: a covariance (or its factor) lost positive definiteness
    EMPTY_SET = 4  #: set-membership: measurement inconsistent with the predicted set
    UNBOUNDED = 8  #: set-membership: the set grew without bound (contains everything)
    NOT_EXCITED = 16  #: adaptive observer: persistent excitation lost over the window

    @staticmethod
    def describe(code: int) -> str:
        """Human-readable names of the flags set in ``code``."""
        names = [n for n, v in vars(Status).items() if isinstance(v, int) and v and code & v]
        return ", ".join(names) if names else "OK"


class Gaussian(eqx.Module):
    """A Gaussian prior N(mean, cov) on the state at the first measurement time."""

    mean: Float[Array, " n"]
    cov: Float[Array, "n n"]


class FilterResult(eqx.Module):
    """What every Gaussian filter returns (covariances are always full matrices here).

    ``predicted_*`` are the one-step predictions x(k|k-1), P(k|k-1) used to process y_k;
    ``mean``/``cov`` are the filtered x(k|k), P(k|k). ``innovation`` is y_k - h(x(k|k-1)) with
    NaN (missing) entries set to zero; ``innovation_cov`` its covariance. ``loglik`` is the
    Gaussian log-likelihood of the observed entries; ``status`` holds :class:`Status` bits per step.
    """

    mean: Float[Array, "T n"]
    cov: Float[Array, "T n n"]
    predicted_mean: Float[Array, "T n"]
    predicted_cov: Float[Array, "T n n"]
    innovation: Float[Array, "T m"]
    innovation_cov: Float[Array, "T m m"]
    loglik_terms: Float[Array, " T"]
    status: Int[Array, " T"]

    @property
    def loglik(self) -> Float[Array, ""]:
        """Total log-likelihood log p(y_0, ..., y_{T-1})."""
        return jnp.sum(self.loglik_terms, axis=-1)

    @property
    def ok(self) -> jax.Array:
        """True where every step of the run finished with status OK."""
        return jnp.all(self.status == Status.OK, axis=-1)


def check_finite_status(*arrays) -> Int[Array, ""]:
    """``Status.NONFINITE`` if any entry of ``arrays`` is not finite, else 0."""
    finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(a)) for a in arrays]))
    return jnp.where(finite, Status.OK, Status.NONFINITE).astype(jnp.int32)


@eqx.filter_jit
def run(estimator, model, ys, inputs=None, prior: Any = None):
    """Run ``estimator`` over the measurement sequence ``ys`` (leading axis = time) with one
    ``lax.scan`` and return ``estimator.result(outputs, final_state)``.

    ``inputs`` (leading axis = time, same length as ``ys``) is passed to ``step`` as ``u_k``;
    ``None`` means no inputs. ``prior`` is whatever ``estimator.init`` takes. Compiled once per
    estimator, model structure and shapes (``eqx.filter_jit``); inside a user's ``jit`` it inlines.
    """
    state = estimator.init(model, prior)

    def body(carry, yu):
        y, u = yu
        return estimator.step(model, carry, y, u)

    final, outputs = jax.lax.scan(body, state, (ys, inputs))
    return estimator.result(outputs, final)


def filter(estimator, model, ys, inputs=None, init: Gaussian | None = None) -> FilterResult:
    """Filter ``ys`` with a Gaussian ``estimator`` (``KalmanFilter()``, ``EKF()``, ``SVDEKF()``...).

    Arguments are checked before anything is traced: a malformed model, prior or sequence raises
    ``ValueError`` naming the argument. ``init`` is the prior on the state at the first measurement.
    """
    from jaxest.checks import check_filter_arguments

    check_filter_arguments(model, ys, inputs, init)
    return run(estimator, model, jnp.asarray(ys), inputs, init)
