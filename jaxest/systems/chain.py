"""Benchmark for the network filter: N masses in a chain, coupled by springs.

Mass i (state x_i = [position, velocity]) is tied to the ground by a spring ``k_ground`` and a
damper ``damping``, to its neighbours i +- 1 by springs ``k_near`` and to i +- 2 by springs
``k_far``. Its coupling vector z_i (h = 4) holds the four spring forces it receives,
z_i[c] = k_c (p_j - p_i) for j = i-2, i-1, i+1, i+2 (zero where the chain ends), so
L_ij = k e_c e_p^T for the neighbour j and L_ii = -sum of them (self-coupling, docs/papers/network.md).
A random force of intensity ``q_force`` drives each mass (plus a small ``q_position`` on the
position), and each node measures its position (noise intensity ``r_position``) and, with
``force_sensors=True``, the four spring forces it receives (``r_force``), as Sanders et al. need
for a node that does not hear a neighbour (lemma 1). Without force sensors only structures in
which every node hears everyone it is coupled to admit a filter.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaxest.network.structure import LargeScaleSystem

__all__ = ["OFFSETS", "mass_chain", "initial_prior"]

OFFSETS = (-2, -1, 1, 2)  #: neighbour offsets of the four coupling components


def mass_chain(
    N: int,
    *,
    mass: float = 1.0,
    k_ground: float = 1.0,
    damping: float = 0.2,
    k_near: float = 0.5,
    k_far: float = 0.2,
    q_force: float = 0.1,
    q_position: float = 1e-3,
    r_position: float = 0.01,
    r_force: float = 0.05,
    force_sensors: bool = True,
    dtype=jnp.float64,
) -> LargeScaleSystem:
    """The chain of ``N`` masses as a :class:`LargeScaleSystem` (n = 2, h = 4, p = 2, q = 5 with
    force sensors, else q = 1)."""
    if N < 1:
        raise ValueError(f"N: need at least one mass, got {N}")
    n, h = 2, len(OFFSETS)
    near, far = np.zeros((N, N, h, n)), np.zeros((N, N, h, n))  # unit springs
    for i in range(N):
        for c, d in enumerate(OFFSETS):
            if 0 <= i + d < N:
                unit = near if abs(d) == 1 else far
                unit[i, i + d, c, 0] += 1.0
                unit[i, i, c, 0] -= 1.0
    params = (mass, k_ground, damping, k_near, k_far, q_force, q_position, r_position, r_force)
    # NumPy for numbers (no per-operation dispatch), jnp for traced parameters (jit/vmap/grad)
    xp = np if all(isinstance(v, int | float | np.number) for v in params) else jnp
    L = k_near * xp.asarray(near) + k_far * xp.asarray(far)
    A = (
        xp.asarray([[0.0, 1.0], [0.0, 0.0]])
        + xp.asarray([[0.0, 0.0], [-1.0, 0.0]]) * (k_ground / mass)
        + xp.asarray([[0.0, 0.0], [0.0, -1.0]]) * (damping / mass)
    )
    C = xp.asarray([[0.0] * h, [1.0] * h]) * (1.0 / mass)
    q = 1 + h if force_sensors else 1
    H1 = np.zeros((q, n))
    H1[0, 0] = 1.0
    H2 = np.zeros((q, h))
    if force_sensors:
        H2[1:, :] = np.eye(h)
    R = xp.diag(xp.stack([xp.asarray(r_position)] + [xp.asarray(r_force)] * (q - 1)))
    Q = xp.diag(xp.stack([xp.asarray(q_position), xp.asarray(q_force)]))
    tile = lambda M: jnp.asarray(xp.broadcast_to(M, (N, *M.shape)), dtype)
    return LargeScaleSystem(
        A=tile(A),
        C=tile(C),
        F=tile(np.eye(n)),
        L=jnp.asarray(L, dtype),
        H1=tile(H1),
        H2=tile(H2),
        Q=tile(Q),
        R=tile(R),
    )


def initial_prior(N: int, dtype=jnp.float64, position_sd: float = 0.5, velocity_sd: float = 0.5):
    """Prior N(0, diag(position_sd^2, velocity_sd^2)) on every mass: mean (N, 2), cov (N, 2, 2)."""
    cov = np.diag([position_sd**2, velocity_sd**2])
    return jnp.zeros((N, 2), dtype), jnp.asarray(np.broadcast_to(cov, (N, 2, 2)), dtype)
