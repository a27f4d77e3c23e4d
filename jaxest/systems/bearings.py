"""Bearings-only target tracking: the benchmark of Gordon, Salmond & Smith (1993, "Novel approach to
nonlinear/non-Gaussian Bayesian state estimation", IEE Proc. F 140(2), sec. 4), on which the EKF
is known to lose the target.

A target moves in the plane with nearly constant velocity; state (x, x', y, y'), unit sampling
interval; a sensor fixed at the origin measures only the bearing::

    x_{k+1} = F x_k + G w_k,   F = [[1, 1, 0, 0], [0, 1, 0, 0], [0, 0, 1, 1], [0, 0, 0, 1]],
    G = [[1/2, 0], [1, 0], [0, 1/2], [0, 1]],   w_k ~ N(0, q^2 I_2), q = 0.001,
    z_k = atan2(y_k, x_k) + v_k,   v_k ~ N(0, r^2), r = 0.005 rad,

with the true initial state [-0.05, 0.001, 0.7, -0.055] and the prior N(m_0, P_0),
m_0 = the true state, P_0 = diag(0.1^2, 0.005^2, 0.1^2, 0.01^2), over 24 steps (the paper's
values). Range is observed only through the prior and the slight curvature of the track; the
target passes close to the sensor, where the bearing changes fast and linearisations fail.
"""

from __future__ import annotations

import jax.numpy as jnp

import jaxest as je

__all__ = [
    "PROCESS_STD", "BEARING_STD", "X0", "PRIOR_STD", "NUM_STEPS", "bearing", "model", "prior",
]  # fmt: skip

#: q: standard deviation of each component of the process noise w_k (x and y, through G)
PROCESS_STD = 0.001
#: r: standard deviation of the bearing noise v_k, rad
BEARING_STD = 0.005
#: the true initial state (x, x', y, y'), also the prior's mean
X0 = (-0.05, 0.001, 0.7, -0.055)
#: standard deviations of the prior about X0, per state
PRIOR_STD = (0.1, 0.005, 0.1, 0.01)
#: steps of a simulated track
NUM_STEPS = 24


def bearing(x, u=None):
    """z = atan2(y, x): the bearing from the sensor at the origin."""
    return jnp.arctan2(x[2:3], x[0:1])


def model(dtype=jnp.float64, process_std=PROCESS_STD, bearing_std=BEARING_STD):
    """The nearly-constant-velocity target with a bearing sensor (module docstring)."""
    one = jnp.asarray([[1.0, 1.0], [0.0, 1.0]], dtype)
    zero = jnp.zeros((2, 2), dtype)
    F = jnp.block([[one, zero], [zero, one]])
    g = jnp.asarray([[0.5], [1.0]], dtype)
    G = jnp.block([[g, jnp.zeros((2, 1), dtype)], [jnp.zeros((2, 1), dtype), g]])
    return je.NonlinearGaussian(
        f=lambda x, u=None: F @ x,
        h=bearing,
        Q=jnp.asarray(process_std**2, dtype) * jnp.eye(2, dtype=dtype),
        R=jnp.asarray([[bearing_std**2]], dtype),
        noise_gain=lambda x, u=None: G,
        jac_f=lambda x, u=None: F,
    )


def prior(dtype=jnp.float64) -> je.Gaussian:
    """N(m_0, P_0) of the paper: centred on the true initial state."""
    return je.Gaussian(jnp.asarray(X0, dtype), jnp.diag(jnp.asarray(PRIOR_STD, dtype) ** 2))
