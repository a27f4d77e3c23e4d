"""Flight-path reconstruction model of the SVD-EKF paper (Zhang, Dai & Zhang), section 5.1.

State (eq 31): the 7 kinematic states x = [u, v, w, phi, theta, psi, h] (body velocities in m/s,
Euler angles in rad, altitude in m) augmented with the 16 sensor parameters

    b = [b_ax, b_ay, b_az, b_p, b_q, b_r,  b_V, b_beta, b_alpha, b_theta, b_phi, b_h,
         lam_V, lam_beta, lam_alpha, lam_h],

23 states in all. Parameters are random constants (b' = 0).

Inputs (eq 27): the measured specific forces and body rates u_m = [a_x, a_y, a_z, p, q, r]_m,
corrected by the biases: a_x = a_xm + b_x + eta_x, ..., r = r_m + b_r + eta_r. The process noise is
the input noise eta (see the discretisation below for how it enters).

Kinematics (eq 26, corrected as in docs/papers/svd_ekf.md; the printed phi' line repeats terms)::

    u' = a_x - g sin(theta) + r v - q w
    v' = a_y + g sin(phi) cos(theta) + p w - r u
    w' = a_z + g cos(phi) cos(theta) + q u - p v
    phi'   = p + (q sin(phi) + r cos(phi)) tan(theta)
    theta' = q cos(phi) - r sin(phi)
    psi'   = (q sin(phi) + r cos(phi)) / cos(theta)
    h'     = u sin(theta) - v sin(phi) cos(theta) - w cos(phi) cos(theta)

Discretisation (eq 32): instead of linearising and then discretising, the kinematics are integrated
over each sample interval by classical Runge-Kutta (``substeps`` RK4 steps per interval) with the
measured inputs interpolated linearly between the samples k and k+1. The filters' input at step k
is therefore the 12-vector [u_m(k), u_m(k+1)] (see :func:`interval_inputs`).

Input noise: white noise eta_j of covariance Qc on every sample. Sample j is the end of interval
j - 1 and the start of interval j, so treating the two ends of an interval as independent
(Q = blockdiag(Qc, Qc) on [u_m(k), u_m(k+1)]) makes the process noise of consecutive steps
correlated and, for the filter that assumes it white, halves the variance that accumulates in the
integrated states (a velocity error sum_j dt eta_j becomes sum_j dt (eta_j + eta'_j) / 2): the
filter was overconfident on its own simulation (time-averaged NEES 34 at 10 Hz, 45 at 32 Hz,
against 23). Here each sample's noise enters its step through both ends, G = df/du_m(k) +
df/du_m(k+1) with Q = Qc (:class:`SampleNoiseGain`): the accumulated variance is right and the
steps' noises are independent, up to where within one step the noise is attributed (a shift of
half a sample, which the exact model -- the state augmented by eta_k -- shows to change the NEES
by less than 1 %).

Observations (eq 28), z = [V, beta, alpha, theta, phi, h]::

    V_m     = (1 + lam_V) sqrt(u^2 + v^2 + w^2) + b_V
    beta_m  = (1 + lam_beta)  atan((v + r x_beta - p z_beta) / u) + b_beta
    alpha_m = (1 + lam_alpha) atan((w - q x_alpha + p y_alpha) / u) + b_alpha
    theta_m = theta + b_theta,   phi_m = phi + b_phi,   h_m = (1 + lam_h) h + b_h

with the vane lever arms x_beta, z_beta, x_alpha, y_alpha (known constants, metres) and the
bias-corrected rates p, q, r at sample k.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxest.models import NonlinearGaussian, at_time

__all__ = [
    "GRAVITY", "DEG", "KINEMATIC_STATES", "PARAMETERS", "STATES", "INPUTS", "OUTPUTS", "N_KIN",
    "N_PAR", "N_IN", "N_OUT", "N_STATE", "kinematics", "integrate_interval",
    "FlightTransition", "LeverArms", "FlightObservation", "AT_CG", "SampleNoiseGain",
    "FlightModel", "flight_model", "interval_inputs", "body_velocity", "pin_parameters",
]  # fmt: skip

#: standard gravity, m/s^2
GRAVITY = 9.80665
#: radians per degree (the flight records give angles in degrees)
DEG = np.pi / 180.0

#: the kinematic states: body velocities u, v, w (m/s), Euler angles phi, theta, psi (rad)
#: and altitude h (m)
KINEMATIC_STATES = ("u", "v", "w", "phi", "theta", "psi", "h")
#: the augmented parameters: biases b_* of the six inputs and six outputs, and scale-factor
#: errors lam_* of four outputs (measured = (1 + lam) true + b)
PARAMETERS = (
    "b_ax", "b_ay", "b_az", "b_p", "b_q", "b_r",
    "b_V", "b_beta", "b_alpha", "b_theta", "b_phi", "b_h",
    "lam_V", "lam_beta", "lam_alpha", "lam_h",
)  # fmt: skip
#: the filter's state: the kinematic states, then the parameters
STATES = KINEMATIC_STATES + PARAMETERS
#: the measured inputs: accelerations a_x, a_y, a_z (m/s^2) and body rates p, q, r (rad/s)
INPUTS = ("a_x", "a_y", "a_z", "p", "q", "r")
#: the measured outputs: airspeed V, sideslip beta, angle of attack alpha, pitch and roll
#: angles theta, phi, altitude h
OUTPUTS = ("V", "beta", "alpha", "theta", "phi", "h")

#: number of kinematic states
N_KIN = len(KINEMATIC_STATES)
#: number of augmented parameters
N_PAR = len(PARAMETERS)
#: number of inputs
N_IN = len(INPUTS)
#: number of outputs
N_OUT = len(OUTPUTS)
#: number of states of the filter (kinematic states and parameters)
N_STATE = N_KIN + N_PAR


def kinematics(
    x: Float[Array, " 7"], inputs: Float[Array, " 6"], gravity=GRAVITY
) -> Float[Array, " 7"]:
    """Time derivative of [u, v, w, phi, theta, psi, h] (eq 26, corrected) for the true inputs
    [a_x, a_y, a_z, p, q, r] (specific forces in body axes, body rates)."""
    u, v, w, phi, theta, _, _ = x
    ax, ay, az, p, q, r = inputs
    sphi, cphi = jnp.sin(phi), jnp.cos(phi)
    sth, cth = jnp.sin(theta), jnp.cos(theta)
    turn = q * sphi + r * cphi
    return jnp.stack(
        [
            ax - gravity * sth + r * v - q * w,
            ay + gravity * sphi * cth + p * w - r * u,
            az + gravity * cphi * cth + q * u - p * v,
            p + turn * sth / cth,
            q * cphi - r * sphi,
            turn / cth,
            u * sth - v * sphi * cth - w * cphi * cth,
        ]
    )


def integrate_interval(x, inputs_start, inputs_end, dt, substeps: int = 1, gravity=GRAVITY):
    """Integrate :func:`kinematics` over one interval of length ``dt`` by ``substeps`` RK4 steps,
    the inputs interpolated linearly from ``inputs_start`` to ``inputs_end``.

    Written out rather than taken from diffrax (a dependency): this fixed classical RK4 step *is*
    the filter's discrete model (the paper's), not an ODE solve to a tolerance, and it must be
    traced into every filter step and its Jacobians. diffrax 0.7 ships no classical RK4 tableau,
    and a ``diffeqsolve`` per step would add its solver state and step loop to each step's
    program."""
    h = dt / substeps

    def inputs_at(s):  # s in [0, 1]: fraction of the interval
        return inputs_start + s * (inputs_end - inputs_start)

    for i in range(substeps):
        s0, s_mid, s1 = i / substeps, (i + 0.5) / substeps, (i + 1) / substeps
        u0, u_mid, u1 = inputs_at(s0), inputs_at(s_mid), inputs_at(s1)
        k1 = kinematics(x, u0, gravity)
        k2 = kinematics(x + 0.5 * h * k1, u_mid, gravity)
        k3 = kinematics(x + 0.5 * h * k2, u_mid, gravity)
        k4 = kinematics(x + h * k3, u1, gravity)
        x = x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    return x


class FlightTransition(eqx.Module):
    """f(x^a, u) of eq 32: RK4 over one sample interval, parameters constant.

    ``u`` is [u_m(k), u_m(k+1)] (12 entries); the input biases b[0:6] are added to both ends (eq 27).
    """

    dt: float = eqx.field(static=True)
    substeps: int = eqx.field(static=True, default=1)
    gravity: float = eqx.field(static=True, default=GRAVITY)

    def __call__(self, xa, u):
        x, b = xa[:N_KIN], xa[N_KIN:]
        start, end = u[:N_IN] + b[:N_IN], u[N_IN:] + b[:N_IN]
        x_next = integrate_interval(x, start, end, self.dt, self.substeps, self.gravity)
        return jnp.concatenate([x_next, b])


class LeverArms(eqx.Module):
    """Positions of the flow vanes relative to the centre of gravity (m), eq 28."""

    x_beta: float = eqx.field(static=True, default=0.0)
    z_beta: float = eqx.field(static=True, default=0.0)
    x_alpha: float = eqx.field(static=True, default=0.0)
    y_alpha: float = eqx.field(static=True, default=0.0)


class FlightObservation(eqx.Module):
    """h(x^a, u) of eq 28/33: airspeed, flow angles at the vanes, attitude and altitude."""

    lever_arms: LeverArms = LeverArms()  # noqa: RUF009 - a frozen Module, safe as a default

    def __call__(self, xa, u):
        u_b, v, w, phi, theta, _, h = xa[:N_KIN]
        b = xa[N_KIN:]
        p, q, r = u[3:6] + b[3:6]
        arms = self.lever_arms
        speed = jnp.sqrt(u_b**2 + v**2 + w**2)
        beta = jnp.arctan2(v + r * arms.x_beta - p * arms.z_beta, u_b)
        alpha = jnp.arctan2(w - q * arms.x_alpha + p * arms.y_alpha, u_b)
        b_V, b_beta, b_alpha, b_theta, b_phi, b_h = b[6:12]
        lam_V, lam_beta, lam_alpha, lam_h = b[12:16]
        return jnp.stack(
            [
                (1.0 + lam_V) * speed + b_V,
                (1.0 + lam_beta) * beta + b_beta,
                (1.0 + lam_alpha) * alpha + b_alpha,
                theta + b_theta,
                phi + b_phi,
                (1.0 + lam_h) * h + b_h,
            ]
        )


#: no lever arms: flow angles already reduced to the centre of gravity (as in the ATTAS data)
AT_CG = LeverArms()


class SampleNoiseGain(eqx.Module):
    """G(x^a, u) = df/du_m(k) + df/du_m(k+1): the noise of one input sample, shifting both ends of
    the interval (module docstring, input noise)."""

    transition: FlightTransition

    def __call__(self, xa, u):
        both_ends = lambda eta: self.transition(xa, u + jnp.concatenate([eta, eta]))
        return jax.jacfwd(both_ends)(jnp.zeros(N_IN, jnp.result_type(xa, u)))


class FlightModel(NonlinearGaussian):
    """The model of :func:`flight_model`: a :class:`~jaxest.NonlinearGaussian` whose time update
    reads the noise gain off the transition Jacobian. An input sample's noise shifts both ends of
    the interval exactly as the input biases do (eq 27), so G = df/db_in, the Jacobian's input-bias
    columns with the parameter rows (which f passes through) set to zero: one linearisation of
    RK4 gives F and G. The ``noise_gain`` (:class:`SampleNoiseGain` of the same f, as
    :func:`flight_model` builds it; :func:`~jaxest.simulate` uses it) traces RK4 a second time; in
    the filters that second trace took the EKF's lowering and compiling (10 runs under ``vmap``,
    32 Hz) from 4.9 to 5.8 s."""

    def transition(self, x, u, k):
        mean, F = self.transition_jacobian(x, u, k)
        G = F[:, N_KIN : N_KIN + N_IN].at[N_KIN:].set(0.0)
        return mean, F, G, at_time(self.Q, k)


def flight_model(
    dt: float,
    input_std: Float[Array, " 6"],
    output_std: Float[Array, " 6"],
    lever_arms: LeverArms = AT_CG,
    substeps: int = 1,
) -> FlightModel:
    """The augmented 23-state model (eqs 31-33) with input noise std ``input_std`` (a_x, a_y, a_z in
    m/s^2, p, q, r in rad/s) and measurement noise std ``output_std`` (V in m/s, angles in rad, h in
    m). Its inputs are :func:`interval_inputs` of the measured inputs. The dtype follows the arrays
    given."""
    if not float(dt) > 0:
        raise ValueError(f"dt: must be a positive sample interval in seconds, got {dt}")
    if not (isinstance(substeps, int | np.integer) and substeps >= 1):
        raise ValueError(f"substeps: must be a positive integer, got {substeps!r}")
    transition = FlightTransition(dt=float(dt), substeps=substeps)
    return FlightModel(
        f=transition,
        h=FlightObservation(lever_arms),
        Q=jnp.diag(jnp.asarray(input_std) ** 2),
        R=jnp.diag(jnp.asarray(output_std) ** 2),
        noise_gain=SampleNoiseGain(transition),
    )


def interval_inputs(measured: Float[Array, "T 6"]) -> Float[Array, "T 12"]:
    """[u_m(k), u_m(k+1)] for every step k; the last sample is repeated for the last step (whose
    prediction lies beyond the data and is never used)."""
    measured = jnp.asarray(measured)
    following = jnp.concatenate([measured[1:], measured[-1:]], axis=0)
    return jnp.concatenate([measured, following], axis=1)


def body_velocity(speed, alpha, beta):
    """[u, v, w] from airspeed and flow angles (no lever arm): the inverse of eq 28's first rows."""
    return jnp.stack(
        [
            speed * jnp.cos(alpha) * jnp.cos(beta),
            speed * jnp.sin(beta),
            speed * jnp.sin(alpha) * jnp.cos(beta),
        ],
        axis=-1,
    )


class _Embedding(eqx.Module):
    """x = the full state with the free entries ``free`` set to z and the rest at ``full``."""

    free: tuple[int, ...] = eqx.field(static=True)
    full: Float[Array, " n"]

    def __call__(self, z):
        return self.full.at[np.asarray(self.free)].set(z)


class _PinnedTransition(eqx.Module):
    model: NonlinearGaussian
    embed: _Embedding

    def __call__(self, z, u):
        return self.model.f(self.embed(z), u)[np.asarray(self.embed.free)]


class _PinnedObservation(eqx.Module):
    model: NonlinearGaussian
    embed: _Embedding

    def __call__(self, z, u):
        return self.model.h(self.embed(z), u)


class _PinnedNoiseGain(eqx.Module):
    model: NonlinearGaussian
    embed: _Embedding

    def __call__(self, z, u):
        return self.model.process_noise(self.embed(z), u, 0)[0][np.asarray(self.embed.free)]


class _PinnedModel(NonlinearGaussian):
    """The reduced model of :func:`pin_parameters`. Its time update is the full model's at
    E z + c, reduced: (E^T f, E^T F E, E^T G, Q), one linearisation of the full model (for a
    :class:`FlightModel`, one RK4 trace per step, where linearising the reduced f and calling
    the noise gain would trace it twice)."""

    def transition(self, z, u, k):
        full, embed = self.transition_fn.model, self.transition_fn.embed
        free = np.asarray(embed.free)
        x_next, F, G, Q = full.transition(embed(z), u, k)
        return x_next[free], F[np.ix_(free, free)], G[free], Q


def pin_parameters(model: NonlinearGaussian, pinned: dict[str, float]):
    """``model`` with the sensor parameters named in ``pinned`` held at the given values and
    removed from the state: the reduced state z holds the other entries of x^a (in order),
    x^a = E z + c with E the columns of the identity at the free entries and c the pinned values,
    and

        f_z(z, u) = E^T f(E z + c, u),   h_z(z, u) = h(E z + c, u),   G_z = E^T G(E z + c, u).

    Exact, since parameters are constants (their rows of f return them unchanged). Returns the
    reduced model and the names of its states."""
    unknown = [p for p in pinned if p not in PARAMETERS]
    if unknown:
        raise ValueError(f"pinned: {unknown} are not sensor parameters {PARAMETERS}")
    free = tuple(i for i, s in enumerate(STATES) if s not in pinned)
    full = (
        jnp.zeros(N_STATE, jnp.result_type(model.Q))
        .at[np.array([STATES.index(p) for p in pinned], dtype=int)]
        .set(jnp.asarray(list(pinned.values()), jnp.result_type(model.Q)))
    )
    embed = _Embedding(free, full)
    reduced = _PinnedModel(
        f=_PinnedTransition(model, embed),
        h=_PinnedObservation(model, embed),
        Q=model.Q,
        R=model.R,
        noise_gain=_PinnedNoiseGain(model, embed),
    )
    return reduced, tuple(STATES[i] for i in free)
