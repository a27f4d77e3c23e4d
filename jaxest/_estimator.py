"""The estimator protocol: abstract types every filter, smoother pass and observer subclasses
(:class:`AbstractEstimator` has the protocol, :class:`AbstractAssociativeEstimator` its
associative form, :class:`AbstractResult` what every result holds)."""

from __future__ import annotations

import abc
from collections.abc import Callable
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Int

from jaxest._checks import check_resumed_arguments
from jaxest._status import StatusSummary
from jaxest.models import check_time_axes
from jaxest.scan import associative_scan


class AbstractResult(StatusSummary):
    """What every estimator's result has beside its own fields.

    ``status`` holds the flags of each step (``None`` where the caller did not save it);
    ``any_status`` is their bitwise OR over the whole run, always kept; ``final_state`` is the
    estimator's state after the last step, from which filtering resumes on new data
    (``run(..., state=result.final_state, k0=T)``); ``saved`` holds the caller's
    ``SaveAt(fn=...)`` of each step's output, or ``None``. ``flags`` and ``ok``: as every
    result's (:class:`~jaxest._status.StatusSummary`).
    """

    final_state: eqx.AbstractVar[Any]
    status: eqx.AbstractVar[Int[Array, " T"] | None]
    any_status: eqx.AbstractVar[Int[Array, ""] | None]
    saved: eqx.AbstractVar[Any]


class AbstractEstimator(eqx.Module):
    """Root of every estimator: an ``eqx.Module`` whose fields are its hyperparameters, with

    - ``init(model, prior) -> state``: the state before the first measurement. It gets no key:
      an estimator that samples (an ensemble) draws in ``step``, from that step's key;
    - ``step(model, state, k, y_k, u_k, key_k) -> (state, output)``, pure: no Python branching
      on values, so it runs under ``jit``, ``vmap``, ``grad`` and inside ``lax.scan``. ``k`` is
      the step index and ``key_k`` this step's PRNG key (``None`` unless the caller gave
      ``key=``): the driver owns time and randomness, states hold neither. The state it returns
      has the structure, shapes and dtypes of the one it was given (the run carries it from
      step to step). ``output`` is a Module (or dataclass) of this step's arrays, whose
      fields :class:`~jaxest.SaveAt` chooses from, with a ``status`` field: an int32 scalar of
      the bits of a :class:`~jaxest.StatusFlag` (:func:`~jaxest.status_where` and
      :func:`~jaxest.finite_status` make one), 0 where the step went well;
    - ``result(outputs, final_state) -> result``: packs the stacked outputs (those the caller
      chose to save, the others ``None``) into the estimator's :class:`AbstractResult`;
    - ``check(model, ys, inputs, prior)``: argument checks run before anything is traced
      (``ValueError`` naming the argument);
    - ``resume(model, state)``: the state to carry on from a given one (``run(..., state=...)``),
      which may come from another estimator (default: as it is);
    - ``check_steps(model, first, count)``: that the arrays read at the step index (time-varying
      matrices) cover the steps of a run, resumed runs included (``check`` is skipped there).

    :func:`jaxest.run` drives any estimator over a sequence, and names the part of this protocol
    a ``step`` breaks where the run fails inside its trace; users with their own loop
    (closed-loop control, online use) call ``step`` themselves. docs/estimators.md writes an
    ensemble Kalman filter this way.

    An estimator whose steps compose associatively subclasses
    :class:`AbstractAssociativeEstimator` instead: it describes each step as an element and gives
    the combination rule, and ``run`` then uses :func:`jaxest.scan.associative_scan` (O(log T)
    depth); its ``init``/``step`` come from the same pieces, so the sequential and parallel paths
    share one implementation.
    """

    #: True for estimators that sample: ``run`` then requires ``key=``
    needs_key: ClassVar[bool] = False
    #: the output fields saved when the caller does not choose (``None``: all of them)
    default_fields: ClassVar[tuple[str, ...] | None] = None
    #: whether a sequential :func:`jaxest.run` recomputes each step in the reverse pass when the
    #: caller does not choose (its ``checkpoint=None``): the estimator's measured better default
    checkpoint_by_default: ClassVar[bool] = False
    #: what a recomputed step keeps from the forward pass (a ``jax.checkpoint`` policy; None:
    #: nothing, every value is recomputed)
    checkpoint_policy: ClassVar[Callable | None] = None

    @abc.abstractmethod
    def init(self, model, prior):
        """The state before the first measurement."""

    @abc.abstractmethod
    def step(self, model, state, k, y, u, key):
        """Process measurement ``y`` (index ``k``, input ``u``): ``(next state, output)``."""

    @abc.abstractmethod
    def result(self, outputs, final_state) -> AbstractResult:
        """The result Module from the stacked outputs and the final state."""

    def check(self, model, ys, inputs, prior) -> None:
        """Raise ``ValueError`` naming the argument for malformed arguments (default: none)."""

    def check_resumed(self, model, ys, inputs, state) -> None:
        """:meth:`check` for a run resumed from ``state`` (``run(..., state=...)``), which has
        no prior: raise ``ValueError`` naming the argument for malformed ``ys`` and ``inputs``
        (default: :func:`jaxest._checks.check_resumed_arguments`, with the state's ``mean``
        where it has one)."""
        check_resumed_arguments(model, ys, inputs, getattr(state, "mean", None))

    def resume(self, model, state):
        """The state this estimator carries on from ``state`` (``run(..., state=...)``), which
        may be another estimator's final state: ``state`` as it is (default). The Gaussian
        filters convert one another's states here, whatever form holds P."""
        return state

    def check_steps(self, model, first: int, count: int) -> None:
        """Raise ``ValueError`` where an array read at the time index (a time-varying matrix of
        the model or of the estimator) does not cover the steps ``first`` .. ``first + count -
        1`` of a run, which :func:`jaxest.run` checks on every call, resumed runs included
        (``first`` = 0 where ``k0`` is traced: at least ``count`` steps; default: the built-in
        Gaussian models' matrices, :func:`jaxest.models.check_time_axes`)."""
        check_time_axes(model, first, count)

    def derivative_fields(self, model) -> tuple[str, ...]:
        """The output fields :meth:`with_derivatives` needs of a run on ``model`` from a prior:
        :func:`jaxest.run` stacks them whatever the caller saves and drops those the caller did
        not ask for once the derivatives are attached (default: none)."""
        return ()

    def with_derivatives(self, result, model, prior, ys, inputs, ks):
        """``result`` of a run from ``prior`` over ``ys`` (time indices ``ks``) with the
        estimator's own derivative rules attached to its outputs, where it has any (the Kalman
        filter's log-likelihood, :mod:`jaxest.filters.fisher`); default: ``result`` as it is,
        differentiated by autodiff through the steps."""
        return result


class AbstractAssociativeEstimator(AbstractEstimator):
    """An estimator whose steps are elements combined by an associative operation.

    ``prior_element(model, prior)`` describes the prior, ``element(model, k, y, u)`` one step,
    ``combine(earlier, later)`` composes two consecutive stretches, and
    ``output(model, previous, prefix, k)`` reads the step output from the prefixes before and
    after step k: the combinations of the prior with elements 0..k-1 and 0..k (a filter's
    prediction x(k|k-1) is the one, its log-likelihood up to k the other). ``combine`` must be
    associative; ``run`` then may evaluate all prefixes with
    :func:`jaxest.scan.associative_scan`. The sequential ``init``/``step`` below use the same pieces.
    """

    @abc.abstractmethod
    def prior_element(self, model, prior):
        """The element of the prior."""

    @abc.abstractmethod
    def element(self, model, k, y, u):
        """The element of step ``k`` (no dependence on other steps)."""

    @abc.abstractmethod
    def combine(self, earlier, later):
        """The element of ``earlier`` followed by ``later`` (associative)."""

    @abc.abstractmethod
    def output(self, model, previous, prefix, k):
        """The output of step ``k`` from the prefix elements (prior, 0, ..., k-1), ``previous``
        (the prior's own element at k = 0), and (prior, 0, ..., k), ``prefix``."""

    def finish_run(self, outputs, first, final):
        """``(outputs, final state)`` of a whole associative run from its outputs, the prior's
        element ``first`` and the last prefix ``final``: where the estimator adds what only the
        whole run can show (a status, a total); default: ``(outputs, final)``."""
        return outputs, final

    def init(self, model, prior):
        return self.prior_element(model, prior)

    def step(self, model, state, k, y, u, key):
        prefix = self.combine(state, self.element(model, k, y, u))
        return prefix, self.output(model, state, prefix, k)


def associative_prefixes(estimator: AbstractAssociativeEstimator, model, prior, ks, ys, us):
    """Every step's prefixes before and after it, (prior, 0..k-1) and (prior, 0..k), stacked
    over k, in O(log T) depth."""
    elements = jax.vmap(lambda k, y, u: estimator.element(model, k, y, u))(ks, ys, us)
    first = estimator.prior_element(model, prior)
    stacked = jax.tree.map(lambda a, b: jnp.concatenate([a[None], b]), first, elements)
    prefixes = associative_scan(jax.vmap(estimator.combine), stacked)  # (prior, 0..k), k = -1..T-1
    return tuple(jax.tree.map(lambda a: a[s], prefixes) for s in (slice(-1), slice(1, None)))


def associative_outputs(estimator: AbstractAssociativeEstimator, model, prior, ks, ys, us):
    """All step outputs and the final state of an associative estimator, in O(log T) depth."""
    previous, prefixes = associative_prefixes(estimator, model, prior, ks, ys, us)
    outputs = jax.vmap(lambda p, q, k: estimator.output(model, p, q, k))(previous, prefixes, ks)
    first = jax.tree.map(lambda a: a[0], previous)  # the prior's element
    final = jax.tree.map(lambda a: a[-1], prefixes)
    return estimator.finish_run(outputs, first, final)
