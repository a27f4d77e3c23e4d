"""The one driver: runs any estimator over a measurement sequence.

:func:`run` checks the arguments (``estimator.check``, before anything is traced), then scans
``estimator.step`` over ``(k, y_k, u_k, key_k)`` with ``lax.scan`` -- or, for an
:class:`~jaxest.AbstractAssociativeEstimator`, evaluates every prefix with
:func:`jaxest.scan.associative_scan` -- and packs the outputs with ``estimator.result``. What is stored is the
caller's choice (:class:`SaveAt`): a 10^4-step, 10^4-run study asking for log-likelihoods only
holds no per-step covariances.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from equinox.internal import unvmap_any  # what eqx.error_if itself reads a batch with

from jaxest._checks import check_flag, check_key, concrete_k0, first_input
from jaxest._estimator import (
    AbstractAssociativeEstimator,
    AbstractEstimator,
    AbstractResult,
    associative_outputs,
)
from jaxest._status import StatusFlag
from jaxest.linalg import working_precision_by_default


class SaveAt(eqx.Module):
    """What :func:`run` keeps of each step's output.

    ``fields``: the output fields stacked over time, a name or a sequence of names (``None``:
    the estimator's defaults; ``()``: none -- the result then holds the final state,
    ``any_status`` and what the state accumulates, e.g. a Gaussian filter's total
    log-likelihood). ``fn``: a function of each step's output
    whose values are stacked into ``result.saved`` (e.g. ``lambda out: out.mean[:2]``).
    """

    fields: tuple[str, ...] | None = eqx.field(static=True, default=None)
    fn: Callable | None = eqx.field(static=True, default=None)

    def __init__(self, fields: Sequence[str] | None = None, fn: Callable | None = None):
        if isinstance(fields, str):  # one name, not its letters
            fields = (fields,)
        self.fields = None if fields is None else tuple(fields)
        self.fn = fn


def _keep(output, fields: tuple[str, ...] | None):
    """``output`` with the fields not in ``fields`` set to ``None``."""
    if fields is None:
        return output
    names = [f.name for f in dataclasses.fields(output)]
    unknown = set(fields) - set(names)
    if unknown:
        raise ValueError(f"save: {sorted(unknown)} are not output fields; choose from {names}")
    return dataclasses.replace(output, **{n: None for n in names if n not in fields})


@eqx.filter_jit
def _run(estimator, model, ys, inputs, prior, state, k0, key, save, parallel, checkpoint):
    T = ys.shape[0]
    ks = k0 + jnp.arange(T)
    fields = estimator.default_fields if save.fields is None else save.fields
    # what the estimator's derivative rules need beside the caller's fields, dropped after
    extra = () if state is not None or fields is None else estimator.derivative_fields(model)
    extra = tuple(f for f in extra if f not in fields)

    def keep(output, stacked=False):
        """The kept fields, ``save.fn`` of each step (``stacked``: of every step's output at
        once) and the status."""
        fn = None if save.fn is None else jax.vmap(save.fn) if stacked else save.fn
        saved = None if fn is None else fn(output)
        if jnp.result_type(output.status) != jnp.int32:  # named by check_step_protocol
            raise TypeError(f"output.status is {jnp.result_type(output.status)}, not int32")
        return _keep(output, None if fields is None else fields + extra), saved, output.status

    if parallel:
        outputs, final = associative_outputs(estimator, model, prior, ks, ys, inputs)
        outputs, saved, status = keep(outputs, stacked=True)
        any_status = jax.lax.reduce(status, jnp.int32(0), jax.lax.bitwise_or, (0,))
    else:
        # one key per step index, so a run resumed at k0 draws what one run would have drawn
        keys = None if key is None else jax.vmap(jax.random.fold_in, (None, 0))(key, ks)
        first = estimator.init(model, prior) if state is None else estimator.resume(model, state)

        def body(carry, args):
            state, any_status = carry
            k, y, u, key_k = args
            state, output = estimator.step(model, state, k, y, u, key_k)
            kept, saved, status = keep(output)
            return (state, any_status | status), (kept, saved)

        (final, any_status), (outputs, saved) = jax.lax.scan(
            jax.checkpoint(body, policy=estimator.checkpoint_policy) if checkpoint else body,
            (first, jnp.zeros((), jnp.int32)),
            (ks, ys, inputs, keys),
        )
    result = estimator.result(outputs, final)
    if not isinstance(result, AbstractResult):
        raise ValueError(
            f"estimator: {type(estimator).__name__}.result must return a jaxest.AbstractResult "
            f"(its final_state, status, any_status and saved fields beside its own), got "
            f"{type(result).__name__}"
        )
    if state is None:
        result = estimator.with_derivatives(result, model, prior, ys, inputs, ks)
    if extra:
        result = dataclasses.replace(result, **dict.fromkeys(extra))
    return eqx.tree_at(
        lambda r: (r.any_status, r.saved),
        result,
        (any_status, saved),
        is_leaf=lambda x: x is None,
    )


def check_estimator(estimator) -> None:
    """``estimator`` is a jaxest estimator (``ValueError`` naming it otherwise)."""
    if not isinstance(estimator, AbstractEstimator):
        raise ValueError(
            f"estimator: expected a jaxest estimator (an AbstractEstimator), "
            f"got {type(estimator).__name__}"
        )


@working_precision_by_default
def run(
    estimator: AbstractEstimator,
    model,
    ys,
    *args,
    prior: Any = None,
    inputs=None,
    key=None,
    state=None,
    k0: int = 0,
    save: SaveAt | None = None,
    parallel: bool | None = None,
    checkpoint: bool | None = None,
    throw: bool = False,
):
    """Run ``estimator`` over the measurements ``ys`` (leading axis = time; NaN = missing).

    Args:
        estimator: any :class:`~jaxest.AbstractEstimator` (``KalmanFilter()``, ``SVDEKF()``...).
        model: the model the estimator reads.
        ys: measurements, shape (T, m).
        prior: what ``estimator.init`` takes (a :class:`~jaxest.Gaussian` for the Gaussian
            filters), the belief about the state at the first measurement.
        inputs: known inputs u_k with leading axis T (an array, or a pytree of arrays for a
            nonlinear model's functions; a linear model's are (T, p)), or ``None``.
        key: PRNG key for estimators that sample; step k draws with ``fold_in(key, k)``, so
            a run resumed with the same key (``state=``, ``k0=``) continues the draws of one
            run instead of repeating the first chunk's.
        state: resume from this state (e.g. ``result.final_state``) instead of ``prior``
            (``ValueError`` where both are given);
            ``k0`` is then the index of the first of ``ys`` (the number of steps already done);
            a time-varying model keeps its whole time axis, read at the absolute step k. The
            run's arguments are checked as for a prior, but for the prior itself
            (:meth:`~jaxest.AbstractEstimator.check_resumed`). A ``k0`` traced under ``jit``
            cannot be checked against the time axis beyond its needing as many steps as ``ys``:
            a step past its end reads its last matrix (JAX clamps the index).
        save: what to keep of each step (:class:`SaveAt`; default: the estimator's fields).
        parallel: :func:`jaxest.scan.associative_scan` (O(log T) depth) instead of ``lax.scan``; only for
            associative estimators, the default for them.
        checkpoint: reverse-mode differentiation recomputes each step from its carried state
            (``jax.checkpoint`` on the scanned step) instead of storing the step's
            intermediates: per step it keeps the carried state (beside what ``save`` keeps)
            and what the estimator's ``checkpoint_policy`` names (the SVD filters' factors).
            Values and gradients agree to rounding either way; the speed does not
            (docs/performance.md). ``None``: the estimator's ``checkpoint_by_default``
            (recompute for the Gaussian filters that hold P as a covariance, information matrix
            or SVD factors, store for the others; that property says why). Sequential runs
            only.
        throw: raise (``eqx.error_if``) if any step's status is not OK, with what to do.

    Arguments are checked before anything is traced: bad input raises ``ValueError`` naming the
    argument. Compiled once per estimator, model structure and shapes; inside a user's ``jit``
    it inlines. Numerical trouble under ``jit`` shows in ``result.status``. Matrix products are
    traced in full precision (float32 means float32 on GPUs whose default is TF32) unless the
    caller set one (:func:`jaxest.linalg.working_precision_by_default`).
    """
    if args:
        raise ValueError(
            f"prior: pass prior, inputs and key by keyword, run(estimator, model, ys, "
            f"prior=..., inputs=...); got {len(args)} extra positional argument(s)"
        )
    check_estimator(estimator)
    if prior is not None and state is not None:
        raise ValueError(
            "prior and state: a run starts from a prior or resumes from a state "
            "(state=result.final_state, k0=...), not both; pass one of them"
        )
    check_flag("parallel", parallel, none=True)
    check_flag("checkpoint", checkpoint, none=True)
    check_flag("throw", throw)
    associative = isinstance(estimator, AbstractAssociativeEstimator)
    if parallel is None:
        parallel = associative and state is None
    if parallel and not associative:
        raise ValueError(f"parallel: {type(estimator).__name__} is not associative")
    if parallel and state is not None:
        raise ValueError("parallel: resuming from a state is sequential; pass parallel=False")
    if not (save is None or isinstance(save, SaveAt)):
        raise ValueError(f"save: expected a jaxest.SaveAt or None, got {type(save).__name__}")
    if checkpoint and parallel:
        raise ValueError(
            "checkpoint: recomputes the steps of a sequential run; pass parallel=False with it"
        )
    if checkpoint is None:
        checkpoint = estimator.checkpoint_by_default and not parallel
    if estimator.needs_key and key is None:
        raise ValueError(f"key: {type(estimator).__name__} samples; pass key=jax.random.key(...)")
    if key is not None:
        check_key("key", key)
    if state is None:
        estimator.check(model, ys, inputs, prior)
    else:
        estimator.check_resumed(model, ys, inputs, state)
    # a traced k0 (a resumed run under jit) still needs as many steps as ys has: read past the
    # end, a time-varying matrix's index was clamped to its last step with status OK
    first = concrete_k0(k0, "ys[0]")
    estimator.check_steps(model, 0 if first is None else first, np.shape(ys)[0])
    try:
        result = _run(
            estimator, model, jnp.asarray(ys), inputs, prior, state, k0, key,
            save or SaveAt(), parallel, checkpoint,
        )  # fmt: skip
    except (TypeError, AttributeError, ValueError) as error:
        check_step_protocol(estimator, model, jnp.asarray(ys), inputs, prior, state, key, error)
        raise
    if throw:
        result = raise_if_failed(result)
    return result


def check_step_protocol(estimator, model, ys, inputs, prior, state, key, error) -> None:
    """Where a run failed inside its trace (``error``), a ``ValueError`` saying which part of the
    protocol (:class:`~jaxest.AbstractEstimator`) the estimator's ``step`` broke, as far as one
    abstract step shows: JAX's own errors name a scan carry or a tracer's attribute, and a
    status of another dtype than int32 fails the trace (a bool's True would read as NONFINITE,
    whatever the step meant). An associative estimator's parallel run is checked by its
    sequential step, made of the same pieces. Returns where the step keeps the protocol (the
    caller re-raises ``error``)."""
    name = type(estimator).__name__

    def one_step():
        first = estimator.init(model, prior) if state is None else estimator.resume(model, state)
        u = None if inputs is None else jax.tree.map(first_input, inputs)
        k = None if key is None else jax.random.fold_in(key, 0)
        return first, estimator.step(model, first, jnp.zeros((), jnp.int32), ys[0], u, k)

    try:
        first, stepped = jax.eval_shape(one_step)
    except Exception:  # noqa: BLE001 - the step fails on its own: error says more
        return
    if not (isinstance(stepped, tuple) and len(stepped) == 2):
        got = f"a tuple of {len(stepped)}" if isinstance(stepped, tuple) else type(stepped).__name__
        raise ValueError(
            f"estimator: {name}.step must return (state, output), got {got}"
        ) from error
    new_state, output = stepped
    status = getattr(output, "status", None)
    if not isinstance(status, jax.ShapeDtypeStruct):
        raise ValueError(
            f"estimator: {name}.step's output has no array field status (the step's flags)"
        ) from error
    if status.shape != () or status.dtype != jnp.int32:
        raise ValueError(
            f"estimator: {name}.step's output.status must be an int32 scalar (jaxest.status_where"
            f" and finite_status make one), got {status.dtype}{list(status.shape)}"
        ) from error
    before, after = (jax.tree_util.tree_flatten_with_path(s) for s in (first, new_state))
    if before[1] != after[1]:
        raise ValueError(
            f"estimator: {name}.step returned a state of another structure than it was given "
            f"({before[1]} -> {after[1]}); the run carries the state from step to step"
            + ("" if state is None else f" (is state= a state of {name}'s kind?)")
        ) from error
    for (path, old), (_, new) in zip(before[0], after[0], strict=True):
        if (old.shape, old.dtype) != (new.shape, new.dtype):
            raise ValueError(
                f"estimator: {name}.step changed its state{jax.tree_util.keystr(path)} from "
                f"{old.dtype}{list(old.shape)} to {new.dtype}{list(new.shape)}; the run carries "
                f"the state from step to step, so it keeps its shapes and dtypes"
            ) from error


def raise_if_failed(result: AbstractResult):
    """``result``, raising (``eqx.branched_error_if``, works under ``jit``) if its status is not
    OK.

    The message says what to do about each of the family's flags (``result.flags``) set in
    ``any_status`` (in any run, under ``vmap`` or over a batch axis): the set flags, known at run
    time only, choose it among the messages of every combination of the family's flags
    (:func:`_failure_messages`). Every jaxest result with a status is taken: an estimator's, a
    smoother's, a simulation's, EM's, ``fit``'s, a Riccati solution, a steady-state gain, a
    network design.
    """
    if not (hasattr(result, "flags") and hasattr(result, "any_status")):
        raise ValueError(f"result: expected a jaxest result, got {type(result).__name__}")
    flags = [flag for flag in result.flags if flag.value]
    # bit i: flags[i] is set in some run (unvmap_any: across a vmap's runs too)
    index = sum(
        unvmap_any((result.any_status & flag.value) != 0).astype(jnp.int32) << i
        for i, flag in enumerate(flags)
    )
    messages = _failure_messages(result.flags)
    return eqx.branched_error_if(result, result.any_status != 0, index, messages)


@functools.cache
def _failure_messages(flags: type[StatusFlag]) -> tuple[str, ...]:
    """:func:`raise_if_failed`'s message for each combination of the family ``flags``'s flags:
    entry i explains the flags whose bits are set in i (bit j: the family's j-th flag); entry 0
    serves a status of another family's bits only."""
    values = [flag.value for flag in flags if flag.value]
    head = "a step's status is not OK; result.any_status has the flags.\n"
    other = (
        f"Its bits are not {flags.__name__}'s flags (another family's: "
        f"result.flags.describe(result.any_status) names them)"
    )
    return tuple(
        head + flags.explain(sum(v for j, v in enumerate(values) if i >> j & 1)) if i
        else head + other
        for i in range(2 ** len(values))
    )  # fmt: skip
