"""Persistent excitation over a sliding window (eq 16 of the adaptive-observer paper).

Assumption 2 asks for delta, T > 0 with

    W(t) = int_{t-T}^{t} Gamma^T(s) C^T(s) Sigma(s) C(s) Gamma(s) ds  >=  delta I     (16)

for all t. The observer integrates the integrand over each sample interval and pushes it into a
ring buffer of the last ``window`` intervals; W is their sum and its smallest eigenvalue is the
excitation level. Below ``threshold`` (once the window is full) the excitation is lost: only
C x_tilde -> 0 is then guaranteed, and the step's status carries ``Status.NOT_EXCITED``.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from jaxest._status import Status as CoreStatus
from jaxest.linalg import symmetrize

ObserverStatus = CoreStatus.extend(
    "ObserverStatus",
    NOT_EXCITED=(
        16,
        "persistent excitation was lost over the window: the parameter estimate is not being "
        "corrected; excite the system or hold the estimate",
    ),
)
"""The observers' status flags: the core's and NOT_EXCITED."""
Status = ObserverStatus


class ExcitationWindow(eqx.Module):
    """Ring buffer of the per-interval excitation increments (``window`` x p x p)."""

    increments: Float[Array, "N p p"]
    index: Int[Array, ""]
    count: Int[Array, ""]


def empty_window(window: int, p: int, dtype) -> ExcitationWindow:
    """A window of ``window`` sample intervals holding nothing yet."""
    if window < 1:
        raise ValueError(f"excitation_window: must be at least 1, got {window}")
    zero = jnp.zeros((), jnp.int32)
    return ExcitationWindow(jnp.zeros((window, p, p), dtype), zero, zero)


def push(buffer: ExcitationWindow, increment: Float[Array, "p p"]) -> ExcitationWindow:
    """Add one interval's int Gamma^T C^T Sigma C Gamma ds, dropping the oldest once full."""
    window = buffer.increments.shape[0]
    return ExcitationWindow(
        buffer.increments.at[buffer.index].set(increment),
        (buffer.index + 1) % window,
        jnp.minimum(buffer.count + 1, window),
    )


def gramian(buffer: ExcitationWindow) -> Float[Array, "p p"]:
    """W of eq 16 over the window (the sum of its increments)."""
    return jnp.sum(buffer.increments, axis=0)


def smallest_eigenvalue(W: Float[Array, "p p"]) -> Float[Array, ""]:
    """Smallest eigenvalue of a symmetric W; closed form for p <= 2 (cheap inside a scan)."""
    if W.shape[0] == 1:
        return W[0, 0]
    if W.shape[0] == 2:
        mean, half_gap = 0.5 * (W[0, 0] + W[1, 1]), 0.5 * (W[0, 0] - W[1, 1])
        return mean - jnp.sqrt(half_gap**2 + W[0, 1] * W[1, 0])
    return jnp.linalg.eigvalsh(symmetrize(W))[0]


def excitation_level(buffer: ExcitationWindow) -> Float[Array, ""]:
    """Smallest eigenvalue of W (a diagnostic: no gradient flows through it)."""
    return smallest_eigenvalue(jax.lax.stop_gradient(gramian(buffer)))


def excitation_status(
    buffer: ExcitationWindow, level: Float[Array, ""], threshold: float
) -> Int[Array, ""]:
    """``Status.NOT_EXCITED`` when the window is full and its ``level``
    (:func:`excitation_level` of ``buffer``) is below ``threshold``."""
    full = buffer.count >= buffer.increments.shape[0]
    lost = full & (level < threshold)
    return jnp.where(lost, Status.NOT_EXCITED, Status.OK).astype(jnp.int32)
