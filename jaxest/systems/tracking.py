"""A 2-D constant-velocity tracking model with position measurements: the core issue's tuning
demonstration (Q and R diagonal, both identifiable from the measurements)."""

from __future__ import annotations

import jax.numpy as jnp

import jaxest as je

__all__ = ["DT", "Q_DIAG", "R_DIAG", "model", "prior"]

#: sampling interval, s
DT = 0.1
#: true process noise variances (position, position, velocity, velocity)
Q_DIAG = (1e-3, 1e-3, 4e-2, 1e-2)
#: true measurement noise variances (the two positions)
R_DIAG = (0.04, 0.09)


def model(dtype=jnp.float64, q_diag=Q_DIAG, r_diag=R_DIAG) -> je.LinearGaussian:
    eye, zero = jnp.eye(2, dtype=dtype), jnp.zeros((2, 2), dtype)
    F = jnp.block([[eye, DT * eye], [zero, eye]])
    H = jnp.concatenate([eye, zero], axis=1)
    return je.LinearGaussian(
        F, H, jnp.diag(jnp.asarray(q_diag, dtype)), jnp.diag(jnp.asarray(r_diag, dtype))
    )


def prior(dtype=jnp.float64) -> je.Gaussian:
    return je.Gaussian(jnp.zeros(4, dtype), jnp.diag(jnp.asarray([1.0, 1.0, 0.25, 0.25], dtype)))
