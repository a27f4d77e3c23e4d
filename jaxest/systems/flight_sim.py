"""Flight-test simulator for the flight-path reconstruction model (:mod:`jaxest.systems.flight`).

The true flight is a trajectory of eq 26 driven by maneuver commands on body rates:

- ``elevator``: a 3-2-1-1 multistep (unit 1 s) in pitch rate;
- ``aileron``: bank-to-bank, 0 -> +30 deg -> -30 deg -> 0, in coordinated turns;
- ``rudder``: a yaw-rate doublet followed by a decaying Dutch roll.

Its "aircraft" is deliberately simple but physically consistent (:func:`true_inputs`): lift, and so
a_z, grows with angle of attack and dynamic pressure, side force a_y with sideslip, a_x holds the
speed, and the body rates are the commands plus those of a coordinated turn. Angle of attack,
sideslip, airspeed and altitude then follow from the kinematics themselves (a pitch-rate step
raises alpha, which the extra lift brings back; a yaw-rate step builds sideslip). The trajectory is
integrated by RK4 on a grid 16 times finer than the sample rate (an independent reference for the
filters' one-step-per-sample discretisation) and sampled at the given rate (10 Hz and 32 Hz in the
paper).

The sensors (:func:`corrupt`) then apply eq 27 and 28 with the true biases and scale factors and
white Gaussian noise at HFB-320 levels (docs/papers/svd_ekf.md).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxest.systems.flight import (
    DEG,
    GRAVITY,
    N_IN,
    N_KIN,
    FlightObservation,
    LeverArms,
    kinematics,
)

__all__ = [
    "MANEUVERS", "DURATION", "FINE_STEPS", "TRIM", "INPUT_STD", "OUTPUT_STD",
    "PARAMETER_STD", "LEVER_ARMS", "commands", "true_inputs", "TrueFlight", "true_flight",
    "FlightRecord", "corrupt", "draw_parameters", "initial_guess",
]  # fmt: skip

#: the simulated maneuvers, one record each
MANEUVERS = ("elevator", "aileron", "rudder")
#: length of every maneuver record, s
DURATION = 20.0
#: fine integration steps per sample
FINE_STEPS = 16

#: trim condition: airspeed (m/s), alpha = theta (rad), heading (rad), altitude (m)
TRIM = {"V": 120.0, "alpha": 3.0 * DEG, "psi": 30.0 * DEG, "h": 3000.0}

#: sensor noise std (HFB-320 levels, docs/papers/svd_ekf.md): a_x, a_y, a_z (m/s^2), p, q, r (rad/s)
INPUT_STD = np.array([0.02, 0.02, 0.05, 0.033 * DEG, 0.033 * DEG, 0.033 * DEG])
#: V (m/s), beta, alpha, theta, phi (rad), h (m)
OUTPUT_STD = np.array([0.13, 0.057 * DEG, 0.057 * DEG, 0.025 * DEG, 0.025 * DEG, 0.5])

#: prior std of the 16 parameters: input biases (O(0.1 m/s^2), O(0.3 deg/s)), output biases,
#: scale factors
PARAMETER_STD = np.array(
    [0.1, 0.1, 0.1, 0.3 * DEG, 0.3 * DEG, 0.3 * DEG,
     0.5, 0.5 * DEG, 0.5 * DEG, 0.3 * DEG, 0.3 * DEG, 5.0,
     0.03, 0.05, 0.05, 0.005]
)  # fmt: skip

#: vane positions of a nose boom (m)
LEVER_ARMS = LeverArms(x_beta=8.0, z_beta=0.5, x_alpha=8.0, y_alpha=0.5)

_EDGE = 0.15  # s, rise time of the smoothed steps
_ALPHA_ZERO_LIFT = -3.0 * DEG
_SIDE_FORCE = -15.0  # a_y per radian of sideslip, m/s^2
_SPEED_LAG = 20.0  # s


def _pulse(t, start, end):
    """A smoothed unit pulse on [start, end]."""
    return 0.5 * (jnp.tanh((t - start) / _EDGE) - jnp.tanh((t - end) / _EDGE))


def commands(maneuver: str, t) -> tuple:
    """Commanded body rates (p, q, r) of ``maneuver`` at time ``t`` (rad/s), on top of the
    coordinated-turn rates."""
    zero = jnp.zeros_like(t)
    if maneuver == "elevator":  # 3-2-1-1 starting at 3 s
        s = _pulse(t, 3, 6) - _pulse(t, 6, 8) + _pulse(t, 8, 9) - _pulse(t, 9, 10)
        return zero, 2.0 * DEG * s, zero
    if maneuver == "aileron":  # bank to bank: +30, -30, 0 deg at 12 deg/s
        s = _pulse(t, 2, 4.5) - _pulse(t, 7, 12) + _pulse(t, 14.5, 17)
        return 12.0 * DEG * s, zero, zero
    if maneuver == "rudder":  # doublet 3-5-7 s, then a decaying Dutch roll
        s = _pulse(t, 3, 5) - _pulse(t, 5, 7)
        tail = t - 7.0
        dutch = jnp.where(tail > 0, jnp.exp(-0.4 * tail) * jnp.sin(2 * np.pi * 0.35 * tail), 0.0)
        r = 1.5 * DEG * s + 2.0 * DEG * dutch
        return 0.5 * 2.0 * DEG * dutch, zero, r
    raise ValueError(f"maneuver: unknown maneuver {maneuver!r}; choose from {', '.join(MANEUVERS)}")


def true_inputs(x, t, maneuver: str):
    """The true inputs [a_x, a_y, a_z, p, q, r] of the simple aircraft in state ``x`` at ``t``:
    lift specific force proportional to (alpha - alpha_0L) V^2 (trimmed at 1 g), side force
    proportional to beta, a speed hold on a_x, and the commanded rates plus those of a coordinated
    turn, Omega = g tan(phi) / V about the vertical."""
    u, v, w, phi, theta = x[0], x[1], x[2], x[3], x[4]
    speed = jnp.sqrt(u**2 + v**2 + w**2)
    alpha, beta = jnp.arctan2(w, u), jnp.arcsin(v / speed)
    alpha0, v0 = TRIM["alpha"], TRIM["V"]
    lift = (alpha - _ALPHA_ZERO_LIFT) / (alpha0 - _ALPHA_ZERO_LIFT) * (speed / v0) ** 2
    a_x = GRAVITY * math.sin(alpha0) - (speed - v0) / _SPEED_LAG
    a_y = _SIDE_FORCE * beta
    a_z = -GRAVITY * math.cos(alpha0) * lift
    p_cmd, q_cmd, r_cmd = commands(maneuver, t)
    turn_rate = GRAVITY * jnp.tan(phi) / speed
    q = q_cmd + turn_rate * jnp.sin(phi) * jnp.cos(theta)
    r = r_cmd + turn_rate * jnp.cos(phi) * jnp.cos(theta)
    return jnp.stack([a_x, a_y, a_z, p_cmd, q, r])


class TrueFlight(eqx.Module):
    """A true flight sampled at ``rate_hz``: times, kinematic states, true inputs."""

    t: Float[Array, " T"]
    states: Float[Array, "T 7"]
    inputs: Float[Array, "T 6"]
    rate_hz: float = eqx.field(static=True)

    @property
    def dt(self) -> float:
        return 1.0 / self.rate_hz


def true_flight(maneuver: str, rate_hz: float, duration: float = DURATION, dtype=jnp.float64):
    """Integrate eq 26 with :func:`true_inputs` from trim by RK4 with ``FINE_STEPS`` steps per
    sample and return the samples at ``rate_hz``."""
    commands(maneuver, jnp.zeros(()))  # validates the name
    if rate_hz <= 0:
        raise ValueError(f"rate_hz: must be positive, got {rate_hz}")
    n_samples = int(round(duration * rate_hz))
    h = 1.0 / (rate_hz * FINE_STEPS)
    V, alpha = TRIM["V"], TRIM["alpha"]
    x0 = [V * np.cos(alpha), 0.0, V * np.sin(alpha), 0.0, alpha, TRIM["psi"], TRIM["h"]]
    x0 = jnp.asarray(x0, dtype=dtype)
    rates = lambda x, t: kinematics(x, true_inputs(x, t, maneuver))

    # times in the state's precision: a float64 t (i * h under x64) made a float32 flight's
    # inputs float64, a TypeError from the scan
    def fine_step(x, i):
        t = (i * h).astype(x.dtype)
        k1 = rates(x, t)
        k2 = rates(x + 0.5 * h * k1, t + 0.5 * h)
        k3 = rates(x + 0.5 * h * k2, t + 0.5 * h)
        k4 = rates(x + h * k3, t + h)
        return x + (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4), None

    def sample(x, k):
        t = (k / rate_hz).astype(x.dtype)
        inputs = true_inputs(x, t, maneuver)
        x_next, _ = jax.lax.scan(fine_step, x, k * FINE_STEPS + jnp.arange(FINE_STEPS))
        return x_next, (t, x, inputs)

    ks = jnp.arange(n_samples)
    _, (t, states, inputs) = jax.jit(lambda a: jax.lax.scan(sample, a, ks))(x0)
    return TrueFlight(t=t.astype(dtype), states=states, inputs=inputs, rate_hz=float(rate_hz))


class FlightRecord(eqx.Module):
    """Measured data of one simulated flight and the truth behind it."""

    measured_inputs: Float[Array, "T 6"]
    measurements: Float[Array, "T 6"]
    true_states: Float[Array, "T 23"]


@eqx.filter_jit  # one program where op-by-op evaluation compiled 49
def corrupt(flight: TrueFlight, parameters, key, input_std=INPUT_STD, output_std=OUTPUT_STD,
            lever_arms: LeverArms = LEVER_ARMS) -> FlightRecord:  # fmt: skip
    """Sensors of eq 27-28: measured inputs u_m = u - b_in - eta and measurements
    z = h(x, b) + zeta with the true rates at the vanes. ``parameters`` are the 16 true values."""
    dtype = flight.states.dtype
    parameters = jnp.asarray(parameters, dtype)
    T = flight.t.shape[0]
    k_in, k_out = jax.random.split(key)
    eta = jax.random.normal(k_in, (T, N_IN), dtype) * jnp.asarray(input_std, dtype)
    zeta = jax.random.normal(k_out, (T, N_IN), dtype) * jnp.asarray(output_std, dtype)
    measured_inputs = flight.inputs - parameters[:N_IN] - eta
    true_states = jnp.concatenate(
        [flight.states, jnp.broadcast_to(parameters, (T, parameters.shape[0]))], axis=1
    )
    # h takes [u(k), u(k+1)] and corrects the rates by b; give it the true rates (b removed)
    rates_as_measured = flight.inputs - parameters[:N_IN]
    observe = jax.vmap(FlightObservation(lever_arms), in_axes=(0, 0))
    clean = observe(true_states, jnp.concatenate([rates_as_measured, rates_as_measured], axis=1))
    return FlightRecord(measured_inputs, clean + zeta, true_states)


def draw_parameters(key, dtype=jnp.float64, parameter_std=PARAMETER_STD):
    """True sensor parameters of one flight, drawn from their prior N(0, diag(parameter_std^2))."""
    std = jnp.asarray(parameter_std, dtype)
    return std * jax.random.normal(key, std.shape, dtype)


def initial_guess(true_state0, key, kinematic_std):
    """A filter's initial mean: the true kinematic state plus an error drawn from
    N(0, diag(kinematic_std^2)), and the parameters' prior mean 0."""
    kin = true_state0[:N_KIN]
    std = jnp.asarray(kinematic_std, kin.dtype)
    kin = kin + std * jax.random.normal(key, kin.shape, kin.dtype)
    return jnp.concatenate([kin, jnp.zeros_like(true_state0[N_KIN:])])
