"""The flight-path reconstruction model with the air mass's motion as states.

The paper's model (:mod:`jaxest.systems.flight`) takes turbulence up as input noise: a gust moves
the kinematic velocities u, v, w, which the altitude integrates and the flow sensors read. A gust
moves the air, not the aircraft. :func:`with_wind` appends three states, the wind's north, east
and down components W (m/s, relative to the start of the record: a steady wind is already
absorbed, since the kinematics of eq 26 hold for the air-relative velocity under a steady wind),
each a random walk

    W(k + 1) = W(k) + w_W(k),   w_W ~ N(0, wind_step^2 I),

and the flow sensors (V, beta, alpha of eq 28) see the air-relative velocity

    [u, v, w]_air = [u, v, w] - C_be(phi, theta, psi) W,

C_be the rotation from earth (north, east, down) to body axes. The attitudes and the altitude
see the kinematic states as before. On the ATTAS records this reconciles the sideslip vane's
estimates between maneuvers (``benchmarks/flight_record_agreement.py``, docs/papers/svd_ekf.md).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jax.scipy.linalg import block_diag
from jaxtyping import Array, Float

from jaxest._checks import is_concrete
from jaxest._priors import Gaussian
from jaxest.models import NonlinearGaussian

__all__ = [
    "WIND_STATES", "body_from_earth", "WindObservation", "WindModel", "with_wind",
    "prior_with_wind",
]  # fmt: skip

#: the states :func:`with_wind` appends: the wind's north, east and down components (m/s)
WIND_STATES = ("W_N", "W_E", "W_D")
_N_WIND = len(WIND_STATES)


def body_from_earth(phi, theta, psi) -> Float[Array, "3 3"]:
    """C_be: earth-axis (north, east, down) components to body axes, for yaw ``psi``, pitch
    ``theta`` and roll ``phi`` (the Euler angles of eq 26, rad)."""
    sf, cf, st, ct = jnp.sin(phi), jnp.cos(phi), jnp.sin(theta), jnp.cos(theta)
    ss, cs = jnp.sin(psi), jnp.cos(psi)
    return jnp.array([
        [ct * cs, ct * ss, -st],
        [sf * st * cs - cf * ss, sf * st * ss + cf * cs, sf * ct],
        [cf * st * cs + sf * ss, cf * st * ss - sf * cs, cf * ct],
    ])  # fmt: skip


def _with_wind_block(matrix):
    """blockdiag(``matrix``, I): a block of the wrapped model with the wind's identity block."""
    return block_diag(matrix, jnp.eye(_N_WIND, dtype=matrix.dtype))


def _check_positive(name: str, value, unit: str) -> None:
    if is_concrete(value) and not np.all(np.asarray(value) > 0.0):
        raise ValueError(f"{name}: expected a positive std ({unit}), got {value}")


class _WindTransition(eqx.Module):
    model: NonlinearGaussian

    def __call__(self, x, u):
        return jnp.concatenate([self.model.f(x[:-_N_WIND], u), x[-_N_WIND:]])


class _WindNoiseGain(eqx.Module):
    model: NonlinearGaussian

    def __call__(self, x, u):
        G, _ = self.model.process_noise(x[:-_N_WIND], u, 0)
        return _with_wind_block(G)


class WindObservation(eqx.Module):
    """h of the wrapped model at the air-relative velocity (module docstring)."""

    model: NonlinearGaussian
    names: tuple[str, ...] = eqx.field(static=True)  # the wrapped model's states

    def __call__(self, x, u):
        i = {s: k for k, s in enumerate(self.names)}
        z, wind = x[:-_N_WIND], x[-_N_WIND:]
        body_wind = body_from_earth(z[i["phi"]], z[i["theta"]], z[i["psi"]]) @ wind
        velocity = jnp.array([i["u"], i["v"], i["w"]])
        return self.model.h(z.at[velocity].add(-body_wind), u)


class WindModel(NonlinearGaussian):
    """The model of :func:`with_wind`. Its time update is the wrapped model's (one linearisation)
    with the wind's identity blocks appended: F = blockdiag(F_z, I), G = blockdiag(G_z, I),
    Q = blockdiag(Q_z, wind_step^2 I)."""

    def transition(self, x, u, k):
        z_next, F, G, _ = self.transition_fn.model.transition(x[:-_N_WIND], u, k)
        x_next = jnp.concatenate([z_next, x[-_N_WIND:]])
        return x_next, _with_wind_block(F), _with_wind_block(G), self.Q


def with_wind(model: NonlinearGaussian, names: tuple[str, ...], wind_step):
    """``model`` (a flight model over the states ``names``: :func:`flight.flight_model`, or one
    reduced by :func:`flight.pin_parameters`) with :data:`WIND_STATES` appended, each a random walk
    of ``wind_step`` (m/s per sample). Returns the model and all state names."""
    missing = [s for s in ("u", "v", "w", "phi", "theta", "psi") if s not in names]
    if missing:
        raise ValueError(f"names: the flight model's states {missing} are missing from {names}")
    _check_positive("wind_step", wind_step, "m/s per sample")
    Q = block_diag(model.Q, wind_step**2 * jnp.eye(_N_WIND, dtype=model.Q.dtype))
    wind = WindModel(
        _WindTransition(model),
        WindObservation(model, tuple(names)),
        Q,
        model.R,
        noise_gain=_WindNoiseGain(model),
    )
    return wind, tuple(names) + WIND_STATES


def prior_with_wind(prior: Gaussian, start_std) -> Gaussian:
    """``prior`` of the wrapped model's states with the wind states appended: mean zero (the wind
    is relative to the start) and std ``start_std`` (m/s; a small positive number for "zero", as
    the filters take a positive definite prior), independent of the rest."""
    _check_positive("start_std", start_std, "m/s")
    mean, cov = jnp.asarray(prior.mean), jnp.asarray(prior.cov)
    wind_cov = jnp.square(start_std) * jnp.eye(_N_WIND, dtype=cov.dtype)
    return Gaussian(
        jnp.concatenate([mean, jnp.zeros(_N_WIND, mean.dtype)]), block_diag(cov, wind_cov)
    )
