"""The Duffing oscillator of the set-membership paper (Chai & Sun 2007, §4, eqs 38-42, table 1).

x'' + k0 x (1 + kd x^2) + c x' = 0, sampled with Euler's method at T: state (x, x'),

    f(x) = [x1 + T x2,  x2 - T (k0 x1 (1 + kd x1^2) + c x2)]   (eq 39),   h(x) = x   (eq 40),

with box noise |w_i| <= 0.005, |v_i| <= 0.01 drawn uniformly, x_0 = [0.2, 0.3] and the prior
E([0.2, 0.3], 0.01 I). Paper time k = 0, 1, ..., N: x_0 is known to lie in E_0 and the
measurements are y_1..y_N; sensor 1 carries a bias b1 = 0.03 + 0.01 L from k = 50 on.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from jaxest.setmembership.ellipsoid import Ellipsoid
from jaxest.setmembership.smf import BoundedNoiseModel
from jaxest.systems._box_noise import simulate_box_noise

__all__ = [
    "T", "K0", "KD", "C", "PROCESS_BOUND", "MEASUREMENT_BOUND", "X0", "P0_SCALE",
    "FAULT_START", "NUM_STEPS", "Duffing", "observe", "model", "prior", "sensor_bias",
    "simulate",
]  # fmt: skip

#: sampling interval T of the Euler discretisation (table 1)
T = 0.1
#: stiffness k0 (table 1)
K0 = 2.1
#: cubic stiffness kd (table 1)
KD = 3.0
#: damping c (table 1)
C = 0.4
#: bound on each component of the process noise, |w_i| <= PROCESS_BOUND
PROCESS_BOUND = 0.005
#: bound on each component of the measurement noise, |v_i| <= MEASUREMENT_BOUND
MEASUREMENT_BOUND = 0.01
#: the initial state x_0 and the centre of the prior set E_0
X0 = (0.2, 0.3)
#: the prior set E_0 = E(X0, P0_SCALE I)
P0_SCALE = 0.01
#: the paper step from which sensor 1 is biased, up to NUM_STEPS inclusive
FAULT_START = 50
#: N, the paper steps of a run (measurements y_1..y_N)
NUM_STEPS = 100


class Duffing(eqx.Module):
    """The discretised Duffing map f (eq 39); parameters are fields so gradients reach them."""

    T: float = T
    k0: float = K0
    kd: float = KD
    c: float = C

    def __call__(self, x, u=None):
        x1, x2 = x[0], x[1]
        return jnp.stack(
            [x1 + self.T * x2, x2 - self.T * (self.k0 * x1 * (1 + self.kd * x1**2) + self.c * x2)]
        )

    def remainder_bound(self, center, shape, u=None):
        """Closed-form remainder bound (eqs 41-42): only d^2 f2/dx1^2 = -6 T k0 kd x1 is non-zero,
        so alpha = [0, 3 T k0 kd (P11^{3/2} + P11 |c1|)]. Widened by 8 eps (relative) to cover
        its own rounding errors."""
        p11 = shape[0, 0]
        alpha2 = 3 * self.T * self.k0 * self.kd * (p11 * jnp.sqrt(p11) + p11 * jnp.abs(center[0]))
        alpha2 = alpha2 * (1 + 8 * jnp.finfo(shape.dtype).eps)
        return jnp.stack([jnp.zeros_like(alpha2), alpha2])


def observe(x, u=None):
    """h(x) = x (eq 40)."""
    return x


def model(
    closed_form_bound: bool = False,
    dtype=None,
    dynamics: Duffing | None = None,
    noise_scale: float = 1.0,
) -> BoundedNoiseModel:
    """The bounded-noise Duffing model of table 1 (automatic remainder bounds unless
    ``closed_form_bound``, which uses eq 42); both noise bounds times ``noise_scale``."""
    dynamics = dynamics or Duffing()
    dtype = dtype or jnp.result_type(float)
    return BoundedNoiseModel(
        f=dynamics,
        h=observe,
        process_bound=jnp.full(2, noise_scale * PROCESS_BOUND, dtype),
        measurement_bound=jnp.full(2, noise_scale * MEASUREMENT_BOUND, dtype),
        f_remainder=dynamics.remainder_bound if closed_form_bound else None,
    )


def prior(dtype=None) -> Ellipsoid:
    """E_0 = E([0.2, 0.3], 0.01 I), the set holding x_0 (paper k = 0, before any measurement)."""
    dtype = dtype or jnp.result_type(float)
    return Ellipsoid(jnp.asarray(X0, dtype), P0_SCALE * jnp.eye(2, dtype=dtype))


def sensor_bias(L, num_steps: int = NUM_STEPS, dtype=None) -> Float[Array, "N 2"]:
    """b_k for paper steps k = 1..num_steps: 0.03 + 0.01 L on sensor 1 from k = 50 on."""
    dtype = dtype or jnp.result_type(float)
    k = jnp.arange(1, num_steps + 1)
    b1 = jnp.where(k >= FAULT_START, 0.03 + 0.01 * L, 0.0).astype(dtype)
    return jnp.stack([b1, jnp.zeros_like(b1)], axis=-1)


def simulate(
    key,
    bias: Float[Array, "N 2"],
    dynamics: Duffing | None = None,
    x0=None,
    noise_scale: float = 1.0,
):
    """Truth and measurements for paper steps k = 1..N: x_k = f(x_{k-1}) + w_{k-1},
    y_k = x_k + b_k + v_k, noise uniform in its box (half-widths times ``noise_scale``).
    Returns ``(states, ys)``, each (N, 2)."""
    dynamics = dynamics or Duffing()
    x0 = jnp.asarray(X0 if x0 is None else x0, bias.dtype)
    bounds = (noise_scale * PROCESS_BOUND, noise_scale * MEASUREMENT_BOUND)
    return simulate_box_noise(jax.random.split(key), dynamics, observe, x0, bias, *bounds)
