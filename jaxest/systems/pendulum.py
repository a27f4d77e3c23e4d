"""A damped pendulum with three sensors: the worked example of guaranteed fault detection and
isolation with m = 3 (docs/papers/smf.md, Detection and isolation; the three-sensor section of
notebooks/02_smf_fault_diagnosis.ipynb).

State x = (angle, rate), Euler-discretised at DT:

    f(x) = [x1 + DT x2,  x2 - DT (OMEGA2 sin x1 + DAMPING x2)],   h(x) = [x1, x2, sin x1],

with box noise |w_i| <= PROCESS_BOUND and |v_i| <= MEASUREMENT_BOUND[i] drawn uniformly. As in
the Duffing example (:mod:`jaxest.systems.duffing`), x_0 lies in E_0 = E(X0, P0_SCALE I) at
k = 0 (drawn uniformly inside it) and the measurements are y_1..y_N; the fault is a bias on one
sensor from step FAULT_START on.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from jaxest.setmembership.ellipsoid import Ellipsoid
from jaxest.setmembership.smf import BoundedNoiseModel
from jaxest.systems._box_noise import simulate_box_noise

__all__ = [
    "DT", "OMEGA2", "DAMPING", "PROCESS_BOUND", "MEASUREMENT_BOUND", "NUM_SENSORS", "X0",
    "P0_SCALE", "FAULT_START", "NUM_STEPS", "BIAS", "FAULTY_SENSOR", "transition", "observe",
    "model", "prior", "sensor_bias", "simulate",
]  # fmt: skip

#: sampling interval of the Euler discretisation, s
DT = 0.1
#: squared natural frequency, 1/s^2
OMEGA2 = 4.0
#: damping, 1/s
DAMPING = 0.2
#: bound on each component of the process noise, |w_i| <= PROCESS_BOUND
PROCESS_BOUND = 0.002
#: bounds on the three sensors' noise: angle, rate, sin(angle)
MEASUREMENT_BOUND = (0.02, 0.05, 0.02)
#: number of sensors
NUM_SENSORS = len(MEASUREMENT_BOUND)
#: the centre of the prior set E_0 (angle, rate)
X0 = (0.8, 0.0)
#: the prior set E_0 = E(X0, P0_SCALE I)
P0_SCALE = 0.01
#: the step from which sensor FAULTY_SENSOR carries the bias BIAS, up to NUM_STEPS inclusive
FAULT_START = 50
#: N, the steps of a run (measurements y_1..y_N)
NUM_STEPS = 100
#: the fault: a bias on sensor FAULTY_SENSOR
BIAS = 0.03
#: the faulty sensor, 0-based (0: the angle)
FAULTY_SENSOR = 0


def transition(x: Float[Array, " 2"]) -> Float[Array, " 2"]:
    """f(x): one Euler step of angle'' = -OMEGA2 sin(angle) - DAMPING angle'."""
    angle, rate = x[0], x[1]
    return jnp.stack([angle + DT * rate, rate - DT * (OMEGA2 * jnp.sin(angle) + DAMPING * rate)])


def observe(x: Float[Array, " 2"]) -> Float[Array, " 3"]:
    """h(x) = [angle, rate, sin(angle)]."""
    return jnp.stack([x[0], x[1], jnp.sin(x[0])])


def model(dtype=None) -> BoundedNoiseModel:
    """The bounded-noise model (automatic interval remainder bounds)."""
    dtype = dtype or jnp.result_type(float)
    return BoundedNoiseModel(
        f=transition,
        h=observe,
        process_bound=jnp.full(2, PROCESS_BOUND, dtype),
        measurement_bound=jnp.asarray(MEASUREMENT_BOUND, dtype),
    )


def prior(dtype=None) -> Ellipsoid:
    """E_0 = E(X0, P0_SCALE I), the set holding x_0 (k = 0, before any measurement)."""
    dtype = dtype or jnp.result_type(float)
    return Ellipsoid(jnp.asarray(X0, dtype), P0_SCALE * jnp.eye(2, dtype=dtype))


def sensor_bias(size: float = BIAS, sensor: int = FAULTY_SENSOR, dtype=None) -> Float[Array, "N 3"]:
    """b_k for steps k = 1..NUM_STEPS: ``size`` on ``sensor`` (0-based) from FAULT_START on."""
    if not 0 <= sensor < NUM_SENSORS:
        raise ValueError(f"sensor: expected 0 <= sensor < {NUM_SENSORS}, got {sensor}")
    dtype = dtype or jnp.result_type(float)
    k = jnp.arange(1, NUM_STEPS + 1)
    on = (k[:, None] >= FAULT_START) & (jnp.arange(NUM_SENSORS) == sensor)
    return jnp.where(on, size, 0.0).astype(dtype)


def simulate(key, bias: Float[Array, "N 3"]):
    """Truth and measurements for steps k = 1..N: x_0 uniform in E_0, x_k = f(x_{k-1}) +
    w_{k-1}, y_k = h(x_k) + b_k + v_k, noise uniform in its box. Returns ``(states, ys)``,
    (N, 2) and (N, 3)."""
    dtype = bias.dtype
    k0, kw, kv = jax.random.split(key, 3)
    # uniform in the unit disc, mapped onto E_0 (P0 = P0_SCALE I)
    direction = jax.random.normal(k0, (2,), dtype)
    radius = jnp.sqrt(jax.random.uniform(jax.random.fold_in(k0, 1), (), dtype))
    x0 = jnp.asarray(X0, dtype) + jnp.sqrt(P0_SCALE) * radius * direction / jnp.linalg.norm(
        direction
    )
    bounds = (PROCESS_BOUND, MEASUREMENT_BOUND)
    return simulate_box_noise((kw, kv), transition, observe, x0, bias, *bounds)
