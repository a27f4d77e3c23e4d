"""Gradient fitting of model matrices (Q, R, P0, ...) with optax or optimistix.

Each fitted matrix is optimised through an unconstrained parameter:

- ``"cholesky"``: P = L L^T, L lower triangular with log-diagonal, so any real parameter is SPD;
- ``"log_diagonal"``: P = diag(exp(theta));
- ``"unconstrained"``: the matrix itself (a transition or measurement matrix F, H).

``free`` masks choose which entries of the parameter move (the others keep their initial value),
e.g. a diagonal-only Cholesky fit, or one variance held fixed.
"""

from __future__ import annotations

import functools
import warnings
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlib
import numpy as np
import optax

from jaxest._checks import (
    check_callable,
    check_key,
    check_matrix,
    check_measurements,
    check_nonnegative_int,
    check_positive_int,
    is_concrete,
)
from jaxest._run import SaveAt, check_estimator, run
from jaxest._status import StatusOfOne, finite_status

if TYPE_CHECKING:
    import optimistix as optx

PARAMETRISATIONS = ("cholesky", "log_diagonal", "unconstrained")


def __getattr__(name: str):
    """``FIXED_STEPS_LBFGS``: L-BFGS for a fit of a fixed number of steps (the studies'
    tuning): optimistix's, with one copy of the loss's gradient in the program (:func:`fit`),
    and tolerances below what a float64 fit reaches, so that the steps decide where it stops.
    Made on first use: importing optimistix takes about 0.12 s, which ``import jaxest`` would
    otherwise pay every time."""
    if name == "FIXED_STEPS_LBFGS":
        return _fixed_steps_lbfgs()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


@functools.cache
def _fixed_steps_lbfgs():
    import optimistix as optx

    return optx.LBFGS(rtol=1e-10, atol=1e-10)


def _unknown(parametrisation) -> ValueError:
    return ValueError(
        f"parametrisation: expected one of {PARAMETRISATIONS}, got {parametrisation!r}"
    )


def to_unconstrained(P, parametrisation: str):
    """The unconstrained parameter of ``P`` (SPD unless ``"unconstrained"``)."""
    if parametrisation == "unconstrained":
        return P
    if parametrisation == "cholesky":
        L = jnp.linalg.cholesky(P)
        return jnp.tril(L, -1) + jnp.diag(jnp.log(jnp.diag(L)))
    if parametrisation == "log_diagonal":
        return jnp.log(jnp.diag(P))
    raise _unknown(parametrisation)


def from_unconstrained(theta, parametrisation: str):
    """The matrix of an unconstrained parameter (inverse of :func:`to_unconstrained`)."""
    if parametrisation == "unconstrained":
        return theta
    if parametrisation == "cholesky":
        L = jnp.tril(theta, -1) + jnp.diag(jnp.exp(jnp.diag(theta)))
        return L @ L.T
    if parametrisation == "log_diagonal":
        return jnp.diag(jnp.exp(theta))
    raise _unknown(parametrisation)


class FitResult(StatusOfOne):
    """The fitted model and the loss of the iterate at each optimiser step: the point an optax
    step starts from, the last point an optimistix minimiser accepted after its step (its first
    step evaluates the start). Either way ``losses[0]`` is the starting loss.

    ``status``: :class:`~jaxest.Status` ``NONFINITE`` where a loss, its gradient (optax) or the
    parameters became NaN or infinite on the way; ``model`` is then the last iterate whose loss
    (and gradient) were finite, not the NaN the optimiser went on with. ``OK`` (0) otherwise."""

    model: eqx.Module
    losses: jax.Array
    status: jax.Array


def _get(model, path: str):
    for name in path.split("."):
        model = getattr(model, name)
    return model


def fit(
    model,
    loss: Callable,
    params: dict[str, str] | Sequence[str] | str = ("Q", "R"),
    *,
    free: dict[str, jax.Array] | None = None,
    optimizer: optax.GradientTransformation | optx.AbstractMinimiser | None = None,
    num_steps: int = 200,
):
    """Minimise ``loss(model)`` over the matrices named in ``params``.

    Args:
        model: any equinox Module (a model, or a pytree holding model and prior).
        loss: ``model -> scalar``, e.g. :func:`neg_loglik` or :func:`supervised_mse`.
        params: attribute paths (``"Q"``, ``"R"``, ``"prior.cov"``...), as one path or a
            sequence of them (Cholesky parametrisation), or a dict path -> ``"cholesky"`` /
            ``"log_diagonal"`` / ``"unconstrained"`` (see the module docstring). The starting
            matrix must be one the parametrisation represents: symmetric positive definite for ``"cholesky"``,
            diagonal with positive entries for ``"log_diagonal"``, and floating point for
            each (``ValueError`` otherwise).
        free: optional path -> boolean mask of the unconstrained parameter's free entries
            (shape n x n for Cholesky, n for log-diagonal).
        optimizer: an optax transformation (default ``optax.adam(0.05)``), or an optimistix
            minimiser such as ``optimistix.LBFGS(rtol=1e-8, atol=1e-8)``. A minimiser's step
            evaluates the loss once (its gradient where the line search accepts the point), so
            the compiled program holds one copy of the loss's gradient (descent-and-search
            minimisers: ``LBFGS``, ``BFGS``, ``NonlinearCG``, ``GradientDescent``). optax's
            line-search methods (``optax.lbfgs()``) work too, but hold three (the line search's
            two branches and the first step) and compile about twice as long: on the svd-ekf
            study's 23-state flight model, 40 steps of either reach the same likelihood, in 23 s
            with ``optimistix.LBFGS`` against 35 s (10 against 24 s compiling;
            ``benchmarks/fit_optimizers.py``). optimistix's
            line search only backtracks (Armijo) where optax's zooms to the Wolfe conditions,
            so on hard or rugged losses optax can get further in as many steps: the parallel
            study's fit of F, H, Q, R and notebook 06's UKF likelihood keep it
            (docs/performance.md). Under ``jax.vmap`` over data sets use an optimistix
            minimiser: on jaxlib 0.10's CPU, XLA miscompiles optax's batched line search, which
            then can loop forever (docs/performance.md); ``fit`` warns
            (:data:`BATCHED_LINE_SEARCH_WARNING`) as it traces one under ``vmap``.
        num_steps: optimiser steps. A minimiser's step is one evaluation of the loss, where an
            optax line search's step may take several: from the same start it needs more steps
            (the sigma-point study's quick tuning, 5 runs: 25 for what optax reaches in 15). It
            stops moving once it meets its tolerances.

    The parametrisations, the steps and the fitted matrices are compiled as one program, with
    the model's arrays concrete in its trace (as ``loss`` would see them called directly).
    """
    check_callable("loss", loss)
    if isinstance(params, str):  # one path, not its letters
        params = (params,)
    if not isinstance(params, dict):
        params = dict.fromkeys(params, "cholesky")
    for path, kind in params.items():
        if kind not in PARAMETRISATIONS:
            raise ValueError(f"params[{path!r}]: expected one of {PARAMETRISATIONS}, got {kind!r}")
        try:
            P = _get(model, path)
        except AttributeError as err:
            raise ValueError(f"params: model has no attribute {path!r}") from err
        if getattr(P, "ndim", 0) != 2:
            raise ValueError(f"params[{path!r}]: expected a constant matrix to fit")
        if not jnp.issubdtype(P.dtype, jnp.floating):  # grad would raise a TypeError in optax
            raise ValueError(
                f"params[{path!r}]: expected a floating-point matrix to fit, got {P.dtype} "
                "(build the model from floating-point arrays)"
            )
        if kind != "unconstrained" and P.shape[0] != P.shape[1]:
            raise ValueError(f"params[{path!r}]: {kind} needs a square matrix, got {P.shape}")
        _check_start(f"params[{path!r}]", P, kind)
    check_nonnegative_int("num_steps", num_steps)
    if not (free is None or isinstance(free, dict)):
        raise ValueError(f"free: expected a dict path -> mask, or None, got {type(free).__name__}")
    free = free or {}
    optimizer = optax.adam(0.05) if optimizer is None else optimizer
    minimiser = _is_minimiser(optimizer)
    if not (minimiser or isinstance(optimizer, optax.GradientTransformation)):
        raise ValueError(
            "optimizer: expected an optax GradientTransformation or an optimistix minimiser, "
            f"got {type(optimizer).__name__}"
        )
    for path, mask in free.items():
        if path not in params:
            raise ValueError(f"free: {path!r} is not one of the fitted params {list(params)}")
        unconstrained = functools.partial(to_unconstrained, parametrisation=params[path])
        shape = jax.eval_shape(unconstrained, _get(model, path))
        if np.shape(mask) != shape.shape:
            raise ValueError(
                f"free[{path!r}]: expected a mask of shape {shape.shape} (the "
                f"{params[path]} parameter), got {np.shape(mask)}"
            )

    def steps():
        """The parametrisations, the optimiser's steps and the fitted matrices, compiled as one
        program (outside ``jit`` the parametrisations ran op by op: 25 small programs besides
        the steps'). The model's arrays stay concrete in its trace, as ``loss`` sees them."""
        theta0 = {p: to_unconstrained(_get(model, p), k) for p, k in params.items()}
        masks = {p: jnp.asarray(free.get(p, jnp.ones_like(t)), t.dtype) for p, t in theta0.items()}

        def matrices(theta):  # in the model's dtype, where a line search steps in float64
            return {
                path: from_unconstrained(
                    theta0[path]
                    + masks[path] * (theta[path] - theta0[path]).astype(masks[path].dtype),
                    kind,
                )
                for path, kind in params.items()
            }

        def objective(theta):
            value = loss(_with_matrices(model, matrices(theta)))
            if jnp.shape(value) != ():  # grad would raise a TypeError
                raise ValueError(f"loss: must return a scalar, got shape {jnp.shape(value)}")
            return value

        minimise = _minimiser_steps if minimiser else _optax_steps
        theta, losses, status = minimise(optimizer, objective, theta0, num_steps)
        return matrices(theta), losses, status

    fitted, losses, status = jax.jit(steps)()
    return FitResult(_with_matrices(model, fitted), losses, status)


def _is_minimiser(optimizer) -> bool:
    """Whether ``optimizer`` is an optimistix minimiser (optimistix imported only to ask)."""
    if isinstance(optimizer, optax.GradientTransformation):
        return False
    import optimistix as optx

    return isinstance(optimizer, optx.AbstractMinimiser)


def _optax_steps(optimizer, objective, theta0, num_steps):
    """``num_steps`` steps of an optax transformation from ``theta0``: the final parameter (or
    the last finite one, :func:`_finite_or_last_finite`), the loss each step started from and
    the status."""
    optimizer = optax.with_extra_args_support(optimizer)
    opt_state0 = optimizer.init(theta0)
    value_and_grad = _value_and_grad(objective, opt_state0)

    def body(carry, _):
        theta, opt_state, last_finite = carry
        value, grads = value_and_grad(theta, state=opt_state)
        updates, opt_state = optimizer.update(
            grads, opt_state, theta, value=value, grad=grads, value_fn=objective
        )
        last_finite = _where_finite((value, grads, theta), theta, last_finite)
        return (optax.apply_updates(theta, updates), opt_state, last_finite), value

    carry0 = (theta0, opt_state0, theta0)
    (theta, _, last_finite), losses = jax.lax.scan(body, carry0, None, num_steps)
    return _finite_or_last_finite(theta, losses, last_finite)


def _where_finite(checked, new, old):
    """``new`` where every leaf of ``checked`` is finite, else ``old``."""
    finite = finite_status(*jax.tree.leaves(checked)) == 0
    return jax.tree.map(lambda a, b: jnp.where(finite, a, b), new, old)


def _finite_or_last_finite(theta, losses, last_finite):
    """``theta`` and ``Status.OK`` where it and every loss are finite, else the last iterate
    whose loss was finite and ``NONFINITE``."""
    status = finite_status(*jax.tree.leaves(theta), losses)
    return _where_finite((theta, losses), theta, last_finite), losses, status


def _minimiser_steps(minimiser, objective, theta0, num_steps):
    """``num_steps`` steps of an optimistix minimiser from ``theta0`` (its own ``init`` and
    ``step``, as ``optimistix.minimise`` runs them, in a ``scan`` so that every step's loss is
    kept): the last accepted parameter (or the last finite one, :func:`_finite_or_last_finite`),
    its loss after each step and the status. Once the minimiser meets its tolerances the
    remaining steps keep its state.

    optimistix makes its own arrays (L-BFGS's history) in the default float, float64 where x64
    is on, and then fails on float32 parameters: the minimiser steps a copy of the parameters
    in the default float (``objective`` evaluates the model in its own dtype)."""
    default = jax.dtypes.canonicalize_dtype(jnp.float64)
    fn = lambda theta, args: (jnp.asarray(objective(theta), default), None)  # no aux output
    start = jax.tree.map(lambda a: a.astype(default), theta0)
    tags = frozenset()
    state0 = minimiser.init(fn, start, None, {}, jax.ShapeDtypeStruct((), default), None, tags)
    if not hasattr(state0, "f_info"):  # where the accepted point's loss is read
        raise ValueError(
            f"optimizer: {type(minimiser).__name__} keeps no accepted point's loss; use a "
            "descent-and-search minimiser (optimistix.LBFGS, BFGS, NonlinearCG, GradientDescent)"
        )
    # the state holds non-array leaves (the descent's linear operator): only arrays are carried
    carried0, static = eqx.partition((start, state0), eqx.is_array)

    def body(carry, _):
        carried, last_finite = carry
        theta, state = eqx.combine(carried, static)
        done = minimiser.terminate(fn, theta, None, {}, state, tags)[0]
        theta, state, _ = minimiser.step(fn, theta, None, {}, state, tags)
        stepped, _ = eqx.partition((theta, state), eqx.is_array)
        carried = jax.tree.map(lambda old, new: jnp.where(done, old, new), carried, stepped)
        theta, state = eqx.combine(carried, static)
        return (carried, _where_finite((state.f_info.f, theta), theta, last_finite)), state.f_info.f

    (carried, last_finite), losses = jax.lax.scan(body, (carried0, start), None, num_steps)
    losses = losses.astype(jnp.result_type(*jax.tree.leaves(theta0)))
    return _finite_or_last_finite(eqx.combine(carried, static)[0], losses, last_finite)


def _with_matrices(model, matrices: dict):
    """``model`` with the matrix at each path of ``matrices`` (``"Q"``, ``"prior.cov"``...)."""
    for path, matrix in matrices.items():
        model = eqx.tree_at(lambda m, path=path: _get(m, path), model, matrix)
    return model


def _check_start(name: str, P, kind: str):
    """The starting matrix must be one the parametrisation represents: SPD for ``"cholesky"``
    (whose parameter is the factor of the lower triangle), diagonal with positive entries for
    ``"log_diagonal"`` (which keeps the diagonal alone). Otherwise the fit would start from NaN
    or from another matrix than the model's, without a word. Checked when concrete."""
    if kind == "cholesky":
        check_matrix(name, P, spd=True)
    elif kind == "log_diagonal" and is_concrete(P):
        a = np.asarray(P, np.float64)
        diagonal = np.diag(a)
        off_diagonal = np.abs(a - np.diag(diagonal))
        if np.any(off_diagonal):
            raise ValueError(
                f"{name}: log_diagonal fits a diagonal matrix; the starting one has off-diagonal "
                f"entries up to {np.max(off_diagonal):.3g} (use cholesky)"
            )
        if not np.all(diagonal > 0):
            raise ValueError(
                f"{name}: log_diagonal needs positive diagonal entries, got {diagonal}"
            )


def _value_and_grad(objective, opt_state):
    """Loss and gradient at the current parameter, as ``(theta, state) -> (value, grads)``. A
    line search (``optax.lbfgs``) keeps both for the point it accepted in its state: they are
    taken from there instead of evaluated again (``optax.value_and_grad_from_state``), and the
    loss passes :func:`_warn_if_batched`."""
    try:
        stored = [optax.tree.get(opt_state, name) for name in ("value", "grad")]
    except KeyError:  # several line searches in one chain: evaluate
        stored = [None]
    if any(s is None for s in stored):
        return lambda theta, state: jax.value_and_grad(objective)(theta)
    from_state = optax.value_and_grad_from_state(objective)

    def from_line_search(theta, state):
        value, grads = from_state(theta, state=state)
        return _warn_if_batched(value), grads

    return from_line_search


def _line_search_miscompiled_here() -> bool:
    """Whether this process runs the XLA seen to miscompile optax's batched line search: jaxlib
    0.10's, on the CPU (docs/performance.md)."""
    return jax.default_backend() == "cpu" and jaxlib.__version__.startswith("0.10.")


#: the warning when optax's line search is traced under ``jax.vmap`` where it was seen to hang
BATCHED_LINE_SEARCH_WARNING = (
    "fit: optax's line search under jax.vmap over data sets; on jaxlib 0.10's CPU, XLA "
    "miscompiles the batched line search of optax.lbfgs(), and some batches loop forever "
    "(docs/performance.md). Use an optimistix minimiser under vmap (optimistix.LBFGS, or "
    "jaxest.tune.FIXED_STEPS_LBFGS)."
)


@jax.custom_jvp
def _warn_if_batched(value):
    """``value``; where ``jax.vmap`` batches it (one loss per data set), on jaxlib 0.10's CPU,
    warns :data:`BATCHED_LINE_SEARCH_WARNING` as the program is traced. (A ``vmap`` whose
    batched values the loss does not depend on leaves it unbatched, and this silent.) Its
    derivative is the identity's: ``custom_vmap`` alone cannot be differentiated."""
    return _batching_alarm(value)


@_warn_if_batched.defjvp
def _warn_if_batched_jvp(primals, tangents):
    return _warn_if_batched(*primals), *tangents


@jax.custom_batching.custom_vmap
def _batching_alarm(value):
    return value


@_batching_alarm.def_vmap
def _batching_alarm_vmap(axis_size, in_batched, value):
    if _line_search_miscompiled_here():
        warnings.warn(BATCHED_LINE_SEARCH_WARNING, RuntimeWarning, stacklevel=1)  # JAX calls this
    return value, in_batched[0]


def _over_runs(
    estimator, ys, inputs, prior, key, save: SaveAt, checkpoint: bool | None, field: str
):
    """``model -> result.<field>`` of :func:`~jaxest.run` on every run of the batch ``ys``
    (runs, T, m) under one ``vmap``: what the losses below are made of. Run i draws with
    ``jax.random.split(key, runs)[i]`` (``key``: ``None`` for estimators that do not sample), the
    same keys at every evaluation."""
    check_estimator(estimator)
    if np.ndim(ys) != 3:
        raise ValueError(
            f"ys: expected a batch of shape (runs, T, m), got {np.shape(ys)} (one sequence: "
            f"ys[None])"
        )
    # the runs' values are tracers under the vmap below: checked here, as run would one of them
    check_measurements(jnp.reshape(ys, (-1, np.shape(ys)[-1])))
    if key is not None:
        check_key("key", key)
    keys = None if key is None else jax.random.split(key, np.shape(ys)[0])

    def values(model):
        def one(y, u, k):
            result = run(
                estimator, model, y, prior=prior, inputs=u, key=k, save=save,
                checkpoint=checkpoint,
            )  # fmt: skip
            return getattr(result, field)

        return jax.vmap(one)(ys, inputs, keys)

    return values


def neg_loglik(
    estimator, ys, *, prior, inputs=None, key=None, checkpoint: bool | None = None
) -> Callable:
    """Loss: minus the mean log-likelihood per run and step of a batch ``ys`` (runs, T, m).

    Only the log-likelihood is kept of each run (``SaveAt(fields=())``): no per-step arrays.
    ``key``: for an estimator that samples (:class:`~jaxest.ParticleFilter`), run i draws with
    ``jax.random.split(key, runs)[i]``, the same at every evaluation (common random numbers), so
    the loss is a deterministic function of the model that an optimiser can descend.
    ``checkpoint``: as :func:`~jaxest.run`'s (``None``: the estimator's default).
    """
    save = SaveAt(fields=())
    logliks = _over_runs(estimator, ys, inputs, prior, key, save, checkpoint, "loglik")
    return lambda model: -jnp.mean(logliks(model)) / ys.shape[1]


def supervised_mse(
    estimator, ys, states, *, prior, inputs=None, key=None, checkpoint: bool | None = None
) -> Callable:
    """Loss: mean squared error of the filtered means against known true ``states`` (runs, T, n).
    ``key`` and ``checkpoint``: as :func:`neg_loglik`'s."""
    save = SaveAt(fields=("mean",))
    means = _over_runs(estimator, ys, inputs, prior, key, save, checkpoint, "mean")

    def loss(model):
        estimates = means(model)
        if estimates.shape != np.shape(states):
            raise ValueError(
                f"states: expected shape {estimates.shape} (runs, T, n: the filtered means), "
                f"got {np.shape(states)}"
            )
        return jnp.mean((estimates - states) ** 2)

    return loss


def log_variances(model):
    """theta = [log diag Q, log diag R] of ``model``: the parameters of a ``"log_diagonal"`` fit of
    Q and R."""
    _check_noise_matrices(model)
    return jnp.concatenate(
        [to_unconstrained(model.Q, "log_diagonal"), to_unconstrained(model.R, "log_diagonal")]
    )


def _check_noise_matrices(model) -> None:
    if not (hasattr(model, "Q") and hasattr(model, "R")):
        raise ValueError(
            f"model: expected a model with noise covariances Q and R (a LinearGaussian or "
            f"NonlinearGaussian), got {type(model).__name__}"
        )


def log_variance_standard_errors(model, loss: Callable, count: int) -> np.ndarray:
    """Standard errors of :func:`log_variances` of ``model`` from the observed Fisher information.

    The information is the Hessian in theta of ``count * loss(model with Q, R = diag(exp
    theta))``, where ``loss`` is a mean negative log-likelihood per measurement (as
    :func:`neg_loglik` returns) and ``count`` is the number of measurements it averages (runs x
    steps). At a maximum-likelihood fit, (theta - truth) / se is then approximately standard
    normal.
    """
    _check_noise_matrices(model)
    check_callable("loss", loss)
    check_positive_int("count", count)
    q = model.Q.shape[-1]

    def total(theta):
        Q, R = (from_unconstrained(t, "log_diagonal") for t in (theta[:q], theta[q:]))
        return count * loss(eqx.tree_at(lambda m: (m.Q, m.R), model, (Q, R)))

    information = np.asarray(jax.jit(jax.hessian(total))(log_variances(model)))
    return np.sqrt(np.diag(np.linalg.inv(information)))
