"""Status flags: failure under ``jit`` is data, not an exception.

Every step of every estimator returns an integer ``status`` whose bits are flags of an
:class:`enum.IntFlag`. The core knows only the flags every estimator can raise
(:class:`Status`); a family extends them with its own (:meth:`StatusFlag.extend`), so the
set-membership filter's ``EMPTY_SET`` or the observer's ``NOT_EXCITED`` are not the core's business.
Each flag carries a message that says what to do, used by ``throw=True``.
"""

from __future__ import annotations

import enum

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Int


class StatusFlag(enum.IntFlag):
    """Base of every family's flags: ``OK`` (0) and the core bits, plus the family's own."""

    @classmethod
    def describe(cls, code) -> str:
        """Names of the flags set in ``code`` (``"OK"`` for 0 only): bits that are not this
        family's (another family's flags, read with the core's :class:`Status`) are named as
        such, not dropped."""
        code = int(code)
        names = [flag.name for flag in cls if flag.value and code & flag.value]
        other = code & ~sum(flag.value for flag in cls)
        if other:
            names.append(f"bits {other} not in {cls.__name__} (another family's flags)")
        return ", ".join(names) if names else "OK"

    @classmethod
    def extend(cls, name: str, **flags: tuple[int, str]) -> type[StatusFlag]:
        """A new flag type with this one's flags and ``flags``: name -> (new bit, advice)."""
        taken = {flag.value for flag in cls}
        for flag_name, (value, advice) in flags.items():
            if value in taken or value <= 0 or value & (value - 1):
                raise ValueError(f"{flag_name}: {value} is not a new single bit")
            ADVICE[flag_name] = advice
        members = {"OK": 0, **{flag.name: flag.value for flag in cls}}
        extended = StatusFlag(name, {**members, **{k: v for k, (v, _) in flags.items()}})
        inherited = ", ".join(flag.name for flag in cls if flag.value)
        own = "; ".join(f"{k} ({v}): {advice}" for k, (v, advice) in flags.items())
        extended.__doc__ = f"Status flags: {cls.__name__}'s ({inherited}) and {own}."
        return extended

    @classmethod
    def explain(cls, code) -> str:
        """What each flag set in ``code`` means and what to do about it."""
        code = int(code)
        lines = [f"{flag.name}: {ADVICE.get(flag.name, '')}" for flag in cls if flag.value & code]
        return "\n".join(lines) if lines else "OK"


class Status(StatusFlag):
    """The core's flags: those every estimator may raise, and ``SMOOTHER_INCONSISTENT``, which
    the parallel smoothers raise in their filter's family."""

    OK = 0
    NONFINITE = 1  #: a mean, covariance or likelihood term is NaN or infinite
    NOT_POSITIVE_DEFINITE = 2  #: a covariance (or its factor) lost positive definiteness
    #: a parallel-in-time smoother's result breaks the backward recursion it solves; a core bit
    #: (high, clear of every family's own) because a smoother's result carries its filter's family
    SMOOTHER_INCONSISTENT = 1 << 30


#: what to do about each flag, shown by ``throw=True``; families add theirs through ``extend``
ADVICE = {
    "NONFINITE": (
        "a value became NaN or infinite: check the measurements for +-inf (NaN marks a missing "
        "one), the model for overflow, and the noise covariances for zeros a filter inverts"
    ),
    "NOT_POSITIVE_DEFINITE": (
        "a covariance lost positive definiteness in floating point: use a factored filter "
        "(SquareRootKF, ImprovedSVDKF) or float64"
    ),
    "SMOOTHER_INCONSISTENT": (
        "the parallel smoother's x(k|T) or P(k|T) disagrees with one step of the backward "
        "recursion from its own x(k+1|T), P(k+1|T) by more than half a standard deviation or "
        "half the variance in some direction: the associative scan's products of smoother "
        "gains lost precision (large gains, where P(k+1|k) is ill-conditioned: a nearly "
        "singular Q, in float32); use the sequential smoother (parallel=False, with "
        "square_root=True in float32) or float64"
    ),
}


def status_where(condition, flag) -> jnp.ndarray:
    """``flag`` where ``condition`` holds, else 0, as int32."""
    return jnp.where(condition, int(flag), 0).astype(jnp.int32)


def finite_status(*arrays) -> jnp.ndarray:
    """``Status.NONFINITE`` if any entry of ``arrays`` is not finite, else 0."""
    finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(a)) for a in arrays]))
    return status_where(~finite, Status.NONFINITE)


class StatusSummary(eqx.Module):
    """What every jaxest result with a status has: ``flags``, the family that names its bits
    (``result.flags.describe(result.any_status)``, :func:`~jaxest.raise_if_failed`), and
    ``ok``, whether ``any_status`` (the subclass's: its flags OR'ed over the run) is OK, per run
    under ``vmap``.

    Subclasses declare their fields (``status`` among them) themselves: an abstract field
    declared here would come first among a subclass's constructor arguments."""

    flags = Status  #: the family of the status bits; a subclass with flags of its own sets it

    @property
    def ok(self) -> jax.Array:
        """True where every step finished with status OK."""
        return self.any_status == 0


class StatusOverSteps(StatusSummary):
    """A result that always keeps its ``status`` with one entry per step (or iteration) on the
    last axis: a smoother's, a simulation's, EM's."""

    @property
    def any_status(self) -> Int[Array, "*runs"]:
        """The flags of every step, OR'ed."""
        return jnp.bitwise_or.reduce(self.status, axis=-1)


class StatusOfOne(StatusSummary):
    """A result with one ``status`` for the whole computation: ``fit``'s, a Riccati solution's."""

    @property
    def any_status(self) -> Int[Array, "*runs"]:
        """The status (one computation: nothing to OR)."""
        return self.status
