"""Simulation of the set-membership examples: uniform noise in a box (Duffing, pendulum)."""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float


def simulate_box_noise(
    keys,
    transition: Callable,
    observe: Callable,
    x0: Float[Array, " n"],
    bias: Float[Array, "N m"],
    process_bound,
    measurement_bound,
):
    """Truth and measurements for steps k = 1..N (N = ``len(bias)``): x_k = f(x_{k-1}) + w_{k-1},
    y_k = h(x_k) + b_k + v_k, with w and v drawn uniformly from the boxes of half-widths
    ``process_bound`` and ``measurement_bound`` (scalars or one per component). ``keys`` are the
    keys of w and of v. Returns ``(states, ys)``, (N, n) and (N, m), in ``bias``'s dtype."""
    key_w, key_v = keys
    dtype = bias.dtype
    wbar = jnp.asarray(process_bound, dtype)
    vbar = jnp.asarray(measurement_bound, dtype)
    w = jax.random.uniform(key_w, (bias.shape[0], x0.shape[0]), dtype, -wbar, wbar)
    v = jax.random.uniform(key_v, bias.shape, dtype, -vbar, vbar)

    def body(x, w_k):
        x_next = transition(x) + w_k
        return x_next, x_next

    _, states = jax.lax.scan(body, jnp.asarray(x0, dtype), w)
    return states, jax.vmap(observe)(states) + bias + v
