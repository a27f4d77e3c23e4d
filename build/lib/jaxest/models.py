"""State-space models as equinox Modules (pytrees: they ``vmap``, ``jit`` and differentiate).

Discrete time, k = 0, 1, ..., T-1::

    x_{k+1} = f(x_k, u_k) + G_k w_k      (or f(x_k, u_k + w_k): noise on the measured input)
    y_k     = h(x_k, u_k) + v_k,          w_k ~ N(0, Q_k),  v_k ~ N(0, R_k)

Every model answers two questions the filters ask, at a linearisation point ``x``:

- ``transition(x, u, k) -> (f(x, u), F, G, Q)``  with F = df/dx and G the noise gain;
- ``observation(x, u, k) -> (h(x, u), H, R)``    with H = dh/dx;

and ``sample_transition(x, u, k, w)`` / ``sample_observation(x, u, k, v)`` for simulation.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float


def at_time(matrix: Array, k, ndim: int = 2) -> Array:
    """``matrix[k]`` if it carries a leading time axis (ndim + 1 dims), else ``matrix``."""
    return matrix[k] if matrix.ndim == ndim + 1 else matrix


class LinearGaussian(eqx.Module):
    """x_{k+1} = F x_k + B u_k + G w_k,  y_k = H x_k + D u_k + v_k.

    Any matrix may carry a leading time axis (shape (T, ...)) for a time-varying model. ``G``
    defaults to the identity (then Q is n x n); ``B``, ``D`` default to no input.
    """

    F: Float[Array, "*T n n"]
    H: Float[Array, "*T m n"]
    Q: Float[Array, "*T q q"]
    R: Float[Array, "*T m m"]
    G: Float[Array, "*T n q"] | None = None
    B: Float[Array, "*T n p"] | None = None
    D: Float[Array, "*T m p"] | None = None

    @property
    def state_dim(self) -> int:
        return self.F.shape[-1]

    @property
    def obs_dim(self) -> int:
        return self.H.shape[-2]

    def noise_gain(self, k):
        if self.G is None:
            return jnp.eye(self.state_dim, dtype=self.F.dtype)
        return at_time(self.G, k)

    def transition(self, x, u, k):
        F = at_time(self.F, k)
        mean = F @ x
        if self.B is not None and u is not None:
            mean = mean + at_time(self.B, k) @ u
        return mean, F, self.noise_gain(k), at_time(self.Q, k)

    def observation(self, x, u, k):
        H = at_time(self.H, k)
        mean = H @ x
        if self.D is not None and u is not None:
            mean = mean + at_time(self.D, k) @ u
        return mean, H, at_time(self.R, k)

    def sample_transition(self, x, u, k, w):
        mean, _, G, _ = self.transition(x, u, k)
        return mean + G @ w

    def sample_observation(self, x, u, k, v):
        return self.observation(x, u, k)[0] + v


class NonlinearGaussian(eqx.Module):
    """x_{k+1} = f(x_k, u_k) + G(x_k, u_k) w_k,  y_k = h(x_k, u_k) + v_k.

    ``f`` and ``h`` are written in ``jax.numpy`` and take ``(x, u)`` (``u`` is ``None`` without
    inputs). Their Jacobians come from ``jax.jacfwd`` unless ``jac_f`` / ``jac_h`` are given.
    Make ``f``/``h`` equinox Modules to let gradients reach their parameters.

    Process noise enters in one of three ways:

    - ``noise_gain=None``: additive, G = I (Q is n x n);
    - ``noise_gain=callable``: G(x, u) (Q is q x q);
    - ``noise_on_input=True``: the measured input is noisy, x_{k+1} = f(x_k, u_k + w_k), so
      G = df/du at (x, u) and Q is the covariance of the input noise (eqs 27 of the SVD-EKF paper).

    ``Q`` and ``R`` may carry a leading time axis.
    """

    f: Callable
    h: Callable
    Q: Float[Array, "*T q q"]
    R: Float[Array, "*T m m"]
    noise_gain: Callable | None = None
    noise_on_input: bool = eqx.field(static=True, default=False)
    jac_f: Callable | None = None
    jac_h: Callable | None = None

    def __check_init__(self):
        if self.noise_on_input and self.noise_gain is not None:
            raise ValueError("noise_gain: give either noise_gain or noise_on_input=True, not both")

    def transition(self, x, u, k):
        mean = self.f(x, u)
        F = self.jac_f(x, u) if self.jac_f is not None else jax.jacfwd(self.f)(x, u)
        if self.noise_on_input:
            G = jax.jacfwd(self.f, argnums=1)(x, u)
        elif self.noise_gain is not None:
            G = self.noise_gain(x, u)
        else:
            G = jnp.eye(x.shape[0], dtype=mean.dtype)
        return mean, F, G, at_time(self.Q, k)

    def observation(self, x, u, k):
        mean = self.h(x, u)
        H = self.jac_h(x, u) if self.jac_h is not None else jax.jacfwd(self.h)(x, u)
        return mean, H, at_time(self.R, k)

    def sample_transition(self, x, u, k, w):
        if self.noise_on_input:
            return self.f(x, u + w)
        if self.noise_gain is not None:
            return self.f(x, u) + self.noise_gain(x, u) @ w
        return self.f(x, u) + w

    def sample_observation(self, x, u, k, v):
        return self.h(x, u) + v


class Simulation(eqx.Module):
    """Output of :func:`simulate`: true states x_0..x_{T-1} and measurements y_0..y_{T-1}."""

    states: Float[Array, "T n"]
    observations: Float[Array, "T m"]

    @property
    def y(self):
        return self.observations


def gaussian_noise(key, cov):
    """Default noise sampler: one draw of N(0, cov)."""
    chol = jnp.linalg.cholesky(cov)
    return chol @ jax.random.normal(key, cov.shape[:1], dtype=cov.dtype)


def simulate(
    model,
    x0,
    num_steps: int,
    key,
    inputs=None,
    process_noise: Callable = gaussian_noise,
    measurement_noise: Callable = gaussian_noise,
) -> Simulation:
    """Draw a true trajectory and its measurements from ``model``.

    ``x0`` is the initial state, or a :class:`~jaxest.Gaussian` to draw it from. The noise
    samplers take ``(key, cov)`` and return one draw (default: Gaussian); pass, e.g., a uniform
    sampler for bounded noise. ``inputs`` has a leading time axis of length ``num_steps``.
    """
    from jaxest.run import Gaussian

    key0, key = jax.random.split(key)
    if isinstance(x0, Gaussian):
        x0 = x0.mean + gaussian_noise(key0, x0.cov)
    keys = jax.random.split(key, (num_steps, 2))
    steps = jnp.arange(num_steps)

    def body(x, args):
        k, (kw, kv), u = args
        y = model.sample_observation(x, u, k, measurement_noise(kv, at_time(model.R, k)))
        x_next = model.sample_transition(x, u, k, process_noise(kw, at_time(model.Q, k)))
        return x_next, (x, y)

    _, (states, ys) = jax.lax.scan(body, jnp.asarray(x0), (steps, keys, inputs))
    return Simulation(states, ys)
