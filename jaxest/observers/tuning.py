"""Gradient tuning of the adaptive observer's SPD matrices (M, Sigma, Riccati Q, R) by optax.

Each tuned matrix S is parametrised by its Cholesky factor with a log diagonal,
S = L L^T, L = tril(W, -1) + diag(exp(diag(W))), so every optimizer step keeps it symmetric
positive definite. The loss is averaged over a batch of scenarios with ``vmap``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import optax


def spd_to_raw(S):
    """W with :func:`raw_to_spd` (W) = S (S symmetric positive definite)."""
    L = jnp.linalg.cholesky(S)
    return jnp.tril(L, -1) + jnp.diag(jnp.log(jnp.diag(L)))


def raw_to_spd(W):
    """S = L L^T with L = tril(W, -1) + diag(exp(diag(W)))."""
    L = jnp.tril(W, -1) + jnp.diag(jnp.exp(jnp.diag(W)))
    return L @ L.T


def _with(observer, fields: Sequence[str], raws):
    return eqx.tree_at(
        lambda o: [getattr(o, f) for f in fields], observer, [raw_to_spd(w) for w in raws]
    )


def tune_observer(
    observer,
    loss: Callable,
    scenarios,
    *,
    fields: Sequence[str] = ("M", "Sigma"),
    steps: int = 100,
    learning_rate: float = 0.05,
    callback: Callable | None = None,
):
    """Minimise mean over ``scenarios`` of ``loss(observer, scenario)`` over the SPD ``fields``.

    ``scenarios`` is a pytree whose leaves have a leading batch axis. Adam on the Cholesky
    parameters, with the global gradient norm clipped to 1 and non-finite steps skipped. Returns
    (tuned observer, list of the mean loss before each step). ``callback(step, loss)`` is called
    after each step (for a progress display).
    """
    raws = [spd_to_raw(getattr(observer, f)) for f in fields]

    @eqx.filter_jit
    def value_and_grad(raws):
        def batch_loss(raws):
            tuned = _with(observer, fields, raws)
            return jnp.mean(jax.vmap(lambda s: loss(tuned, s))(scenarios))

        return jax.value_and_grad(batch_loss)(raws)

    optimizer = optax.apply_if_finite(
        optax.chain(optax.clip_by_global_norm(1.0), optax.adam(learning_rate)),
        max_consecutive_errors=5,
    )
    opt_state = optimizer.init(raws)
    history = []
    for i in range(steps):
        value, grads = value_and_grad(raws)
        history.append(float(value))
        updates, opt_state = optimizer.update(grads, opt_state, raws)
        raws = optax.apply_updates(raws, updates)
        if callback is not None:
            callback(i, float(value))
    return _with(observer, fields, raws), history
