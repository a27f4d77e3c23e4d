"""Guaranteed sensor fault detection and isolation with set-membership filters (paper §3), and
the EKF + chi-square test it is compared with.

- **Detection** (eq 37): one SMF fed every sensor; an alarm at step k when the measurement set is
  inconsistent with the predicted set (``Status.EMPTY_SET``). Since the set is guaranteed to hold
  the state when the bounds are right and no sensor is faulty, an alarm proves a fault.
- **Isolation, method 1**: a bank of m SMFs, filter i fed sensor i only; sensor i is declared
  faulty at the first step where filter i's set is empty.
- **Isolation, method 2**: a bank of m SMFs, filter i fed every sensor but i; sensor i is
  declared faulty at step k when filter i is consistent and every other filter j != i is empty.
  The paper's wording allows two readings, both offered (``reading=``): ``"same_step"``, every
  other filter empty at step k itself, which with m >= 3 isolates at the fault's onset or never
  (the other filters need not all meet an inconsistency at one step); and ``"by_step"``, every
  other filter has been empty at some step up to k while filter i has been consistent at every
  step up to k (an empty set is proof of a fault whenever it happened).

With m = 2 sensors method 2 runs the same two filters as method 1 with the labels swapped
(all-but-1 = sensor 2 only); it declares sensor i faulty when method 1 does *and* the other
filter is consistent at that step, which a correct filter always is, so both give the same
decisions unless the guarantee fails. A sensor subset is fed to a filter by setting the other
columns of y to NaN (:func:`sensor_subset`).

Scoring a run with a fault from step ``fault_start`` on: a *false alarm* is any alarm before
``fault_start`` or, for isolation, any decision naming a healthy sensor; a *missed* detection
(isolation) is no (correct) alarm in [fault_start, horizon]; the *delay* is the step of the first
correct alarm minus ``fault_start``.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from jaxest._checks import check_positive_int
from jaxest.linalg import cholesky, solve_triangular


def sensor_subset(ys: Float[Array, "T m"], used: Bool[Array, " m"]) -> Float[Array, "T m"]:
    """``ys`` with the columns of the sensors not ``used`` replaced by NaN (no measurement)."""
    if jnp.shape(used) != jnp.shape(ys)[-1:]:  # JAX's broadcasting error named no argument
        raise ValueError(
            f"used: expected one entry per sensor, shape {jnp.shape(ys)[-1:]}, got {jnp.shape(used)}"
        )
    return jnp.where(jnp.asarray(used)[None, :], ys, jnp.nan)


def bank_masks(m: int, method: int) -> np.ndarray:
    """Sensor masks (m, m) of the isolation banks: row i is what filter i sees."""
    eye = np.eye(m, dtype=bool)
    if method == 1:
        return eye
    if method == 2:
        return ~eye
    raise ValueError(f"method: expected 1 or 2, got {method}")


def isolation_decisions(
    inconsistent: Bool[Array, "*B m T"], method: int, reading: str = "same_step"
) -> Bool[Array, "*B T m"]:
    """decisions[..., k, i]: sensor i is declared faulty at step k, from the bank's per-filter
    inconsistency flags (filter i of the bank of ``method``); leading axes (runs...) broadcast.
    ``reading``: method 2's ``"same_step"`` or ``"by_step"`` (module docstring)."""
    if reading not in ("same_step", "by_step"):
        raise ValueError(f"reading: expected 'same_step' or 'by_step', got {reading!r}")
    flags = jnp.swapaxes(jnp.asarray(inconsistent), -1, -2)  # (..., T, m)
    if method == 1:
        return flags
    if method == 2:
        if reading == "by_step":  # empty at some step up to k
            flags = jnp.cumsum(flags, axis=-2) > 0
        others = jnp.asarray(bank_masks(flags.shape[-1], 2))  # (m, m): j != i
        all_others_empty = jnp.all(jnp.where(others, flags[..., None, :], True), axis=-1)
        return ~flags & all_others_empty
    raise ValueError(f"method: expected 1 or 2, got {method}")


def first_alarm(alarms: Bool[Array, "... T"], first_step: int = 1) -> Int[Array, ...]:
    """The step (numbered from ``first_step``) of the first alarm, or -1 if none."""
    alarms = jnp.asarray(alarms)
    index = jnp.argmax(alarms, axis=-1)
    return jnp.where(jnp.any(alarms, axis=-1), index + first_step, -1)


def score(
    alarms: Bool[Array, "runs T"],
    fault_start: int,
    wrong: Bool[Array, "runs T"] | None = None,
    first_step: int = 1,
) -> dict:
    """Missed and false-alarm rates and delays over runs (module docstring for the definitions).

    ``alarms[r, t]`` is a correct alarm at step t + first_step of run r (for isolation: the faulty
    sensor named); ``wrong`` an alarm naming a healthy sensor (isolation only)."""
    alarms = np.asarray(alarms, bool)
    if alarms.ndim != 2 or alarms.shape[0] == 0:  # no runs gave NaN rates and NumPy warnings
        raise ValueError(f"alarms: expected (runs, T) with at least one run, got {alarms.shape}")
    steps = np.arange(alarms.shape[-1]) + first_step
    before = steps < fault_start
    false_alarm = np.any(alarms & before, axis=-1)
    if wrong is not None:
        false_alarm |= np.any(np.asarray(wrong, bool), axis=-1)
    after = alarms & ~before
    detected = np.any(after, axis=-1)
    delays = (np.argmax(after, axis=-1) + first_step - fault_start)[detected]
    stat = lambda fn: float(fn(delays)) if delays.size else math.nan
    return {
        "missed_rate": float(1.0 - np.mean(detected)),
        "false_alarm_rate": float(np.mean(false_alarm)),
        "min_delay": stat(np.min),
        "max_delay": stat(np.max),
        "mean_delay": stat(np.mean),
    }


def chi_square_threshold(dof: int, significance: float) -> float:
    """The (1 - significance) quantile of the chi-square distribution with ``dof`` degrees of
    freedom (bisection on the regularised incomplete gamma function; exact -2 ln(alpha) for 2)."""
    check_positive_int("dof", dof)
    if not (isinstance(significance, int | float | np.floating) and 0 < significance < 1):
        # a negative one doubled the bracket forever; 1.5 gave 6e-61 or, at 2 dof, -0.81
        raise ValueError(f"significance: must lie in (0, 1), got {significance!r}")
    if dof == 2:
        return -2.0 * math.log(significance)
    cdf = lambda x: float(jax.scipy.special.gammainc(dof / 2.0, x / 2.0))
    lo, hi = 0.0, 1.0
    while cdf(hi) < 1 - significance:
        hi *= 2
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if cdf(mid) < 1 - significance else (lo, mid)
    return hi


def chi_square_alarms(
    innovation: Float[Array, "T m"], innovation_cov: Float[Array, "T m m"], threshold: float
) -> Bool[Array, " T"]:
    """The chi-square test of an EKF's innovations: alarm when nu^T S^{-1} nu > threshold."""
    whitened = solve_triangular(cholesky(innovation_cov), innovation, lower=True)
    return jnp.sum(whitened**2, -1) > threshold
