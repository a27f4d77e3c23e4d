"""The nonlinear ellipsoidal set-membership filter (Chai & Sun 2007, §2; NOTES.md §2).

Model (eqs 1-4): x_{k+1} = f(x_k, u_k) + w_k,  y_k = h(x_k, u_k) + v_k, with unknown but bounded
noise |w_i| <= wbar_i, |v_i| <= vbar_i and x at the first measurement in the prior ellipsoid.
The filter carries an ellipsoid E(c_k, P_k) guaranteed to contain the true state:

- measurement update (eqs 18-36): h is linearised at c; its Lagrange remainder is bounded over
  the ellipsoid's bounding box (eq 20) and added to vbar (eq 21); each measurement row is a strip
  (eqs 23-25) intersected with the ellipsoid in turn (eqs 27-36);
- time update (eqs 7-17): f is linearised at c, P <- F P F^T (eq 15) and the box of half-widths
  wbar + remainder bound (eqs 11-13) is added one segment at a time (eqs 16-17); c <- f(c) (eq 14).

What happens in the two failure modes (both reported in ``status``):

- **Empty intersection** (``Status.EMPTY_SET``): the measurements at step k are inconsistent with
  the predicted set, so the model (the noise bounds, or a healthy sensor) is wrong: a guaranteed
  fault alarm (§3). The filter then discards that step's measurements and carries the predicted
  ellipsoid forward, which still contains the state when the fault is in the sensors.
- **Unbounded set** (``Status.UNBOUNDED``): the set's size passed ``max_radius`` or lost positive
  definiteness or finiteness (e.g. a filter that never sees x_1 of the Duffing system: its
  remainder bound grows like P_11^{3/2}). The set then contains everything: the filter stops
  updating, never signals an empty set again, and reports a shape of +inf on the diagonal; the
  flag stays set for the rest of the run.

A NaN entry of y_k means "no measurement from that sensor at step k" (its strip is skipped);
the fault-isolation banks of :mod:`jaxest.setmembership.fdi` feed sensor subsets this way.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from jaxest.run import Status, check_finite_status, run
from jaxest.setmembership.ellipsoid import (
    Ellipsoid,
    add_box,
    contains,
    intersect_strip,
    is_positive_definite,
)
from jaxest.setmembership.interval import remainder_bound


class BoundedNoiseModel(eqx.Module):
    """x_{k+1} = f(x_k, u_k) + w_k,  y_k = h(x_k, u_k) + v_k,  |w| <= process_bound,
    |v| <= measurement_bound (element-wise half-widths of the boxes W and V, eqs 3-4).

    ``f(x, u)`` and ``h(x, u)`` are written in ``jax.numpy`` (``u`` is ``None`` without inputs).
    The remainder bounds default to the automatic interval bound of
    :func:`~jaxest.setmembership.interval.remainder_bound`; ``f_remainder(center, shape, u)`` /
    ``h_remainder(center, shape, u)`` may replace it by a closed form (it must be guaranteed).
    """

    f: Callable
    h: Callable
    process_bound: Float[Array, " n"]
    measurement_bound: Float[Array, " m"]
    f_remainder: Callable | None = None
    h_remainder: Callable | None = None

    @property
    def state_dim(self) -> int:
        return self.process_bound.shape[-1]

    @property
    def obs_dim(self) -> int:
        return self.measurement_bound.shape[-1]

    def linearise(self, fn, custom_bound, center, shape, u):
        """``(fn(c), d fn/dx (c), remainder half-widths over E(c, P))``."""
        g = lambda x: fn(x, u)
        value, jac = g(center), jax.jacfwd(g)(center)
        if custom_bound is not None:
            bound = custom_bound(center, shape, u)
        else:
            bound = remainder_bound(g, center, shape)
        return value, jac, bound


class SMFState(eqx.Module):
    center: Float[Array, " n"]
    shape: Float[Array, "n n"]
    unbounded: Bool[Array, ""]


class SMFOutput(eqx.Module):
    center: Float[Array, " n"]
    shape: Float[Array, "n n"]
    remainder: Float[Array, " n"]  #: remainder bound of f used in the time update after step k
    measurement_remainder: Float[Array, " m"]  #: remainder bound of h used at step k
    status: Int[Array, ""]


class SMFResult(eqx.Module):
    """Filtered ellipsoids E(center[k], shape[k]) after y_k, and per-step :class:`Status` bits.

    ``remainder[k]`` is the bound of f's remainder (eq 11) used to predict from k to k+1 and
    ``measurement_remainder[k]`` that of h (eq 20) used at step k. Where ``unbounded`` the shape
    is +inf on the diagonal (the set is the whole space).
    """

    center: Float[Array, "T n"]
    shape: Float[Array, "T n n"]
    remainder: Float[Array, "T n"]
    measurement_remainder: Float[Array, "T m"]
    status: Int[Array, " T"]

    @property
    def inconsistent(self) -> Bool[Array, " T"]:
        """True at the steps whose measurements had an empty intersection with the set."""
        return (self.status & Status.EMPTY_SET) != 0

    @property
    def unbounded(self) -> Bool[Array, " T"]:
        return (self.status & Status.UNBOUNDED) != 0

    def contains(self, states: Float[Array, "T n"]) -> Bool[Array, " T"]:
        """Whether states[k] lies in the k-th ellipsoid (always true where unbounded)."""
        bounded_shape = jnp.where(
            self.unbounded[:, None, None], jnp.eye(states.shape[-1]), self.shape
        )
        inside = jax.vmap(contains)(self.center, bounded_shape, states)
        return inside | self.unbounded


class SetMembershipFilter(eqx.Module):
    """The nonlinear ellipsoidal SMF (module docstring). ``max_radius``: the set counts as
    unbounded once some sqrt(P_ii) exceeds it (default: 1 / sqrt(eps) of the dtype)."""

    max_radius: float | None = None

    def init(self, model: BoundedNoiseModel, prior: Ellipsoid) -> SMFState:
        center, shape = jnp.asarray(prior.center), jnp.asarray(prior.shape)
        return SMFState(center, shape, jnp.zeros((), bool))

    def _limit(self, dtype):
        if self.max_radius is not None:
            return self.max_radius**2
        return 1.0 / jnp.finfo(dtype).eps

    def measurement_update(self, model, center, shape, y, u):
        """Eqs 18-36; returns ``(center, shape, empty, remainder)``."""
        h_c, H, alpha = model.linearise(model.h, model.h_remainder, center, shape, u)
        half_widths = model.measurement_bound + alpha  # eq 21
        new_center, new_shape, empty = center, shape, jnp.zeros((), bool)
        for i in range(H.shape[0]):
            observed = ~jnp.isnan(y[i])
            z = jnp.where(observed, y[i], 0.0) - h_c[i] + H[i] @ center  # eq 24
            c_i, P_i, empty_i = intersect_strip(new_center, new_shape, H[i], z, half_widths[i])
            new_center = jnp.where(observed, c_i, new_center)
            new_shape = jnp.where(observed, P_i, new_shape)
            empty = empty | (observed & empty_i)
        # an inconsistent measurement set is discarded: carry the predicted set forward
        return (
            jnp.where(empty, center, new_center),
            jnp.where(empty, shape, new_shape),
            empty,
            alpha,
        )

    def time_update(self, model, center, shape, u):
        """Eqs 7-17; returns ``(center, shape, remainder)``."""
        f_c, F, alpha = model.linearise(model.f, model.f_remainder, center, shape, u)
        shape = add_box(F @ shape @ F.T, model.process_bound + alpha)  # eqs 15-17, 12-13
        return f_c, shape, alpha

    def predict(self, model: BoundedNoiseModel, prior: Ellipsoid, u=None) -> Ellipsoid:
        """The time update of ``prior`` alone: the set one step later, without a measurement."""
        center, shape, _ = self.time_update(model, prior.center, prior.shape, u)
        return Ellipsoid(center, shape)

    def step(self, model, state: SMFState, y, u):
        c, P, empty, alpha_h = self.measurement_update(model, state.center, state.shape, y, u)
        empty = empty & ~state.unbounded
        c_next, P_next, alpha_f = self.time_update(model, c, P, u)
        diag = jnp.diagonal(P_next)
        healthy = (
            jnp.all(jnp.isfinite(P_next))
            & jnp.all(jnp.isfinite(c_next))
            & jnp.all(diag <= self._limit(P.dtype))
            & is_positive_definite(P_next)
        )
        unbounded_next = state.unbounded | ~healthy
        frozen = lambda new, old: jnp.where(unbounded_next, old, new)
        new_state = SMFState(
            frozen(c_next, state.center), frozen(P_next, state.shape), unbounded_next
        )
        n = P.shape[-1]
        everything = jnp.where(jnp.eye(n, dtype=bool), jnp.inf, 0.0).astype(P.dtype)
        status = (
            jnp.where(empty, Status.EMPTY_SET, 0)
            | jnp.where(state.unbounded, Status.UNBOUNDED, 0)
            | check_finite_status(c)
        ).astype(jnp.int32)
        output = SMFOutput(
            center=c,
            shape=jnp.where(state.unbounded, everything, P),
            remainder=jnp.where(state.unbounded, jnp.inf, alpha_f),
            measurement_remainder=jnp.where(state.unbounded, jnp.inf, alpha_h),
            status=status,
        )
        return new_state, output

    def result(self, outputs: SMFOutput, final_state: SMFState) -> SMFResult:
        return SMFResult(
            outputs.center,
            outputs.shape,
            outputs.remainder,
            outputs.measurement_remainder,
            outputs.status,
        )


def set_membership_filter(
    model: BoundedNoiseModel,
    ys,
    prior: Ellipsoid,
    inputs=None,
    estimator: SetMembershipFilter | None = None,
) -> SMFResult:
    """Run the SMF over ``ys`` (shape (T, m); NaN = no measurement) from ``prior``, the ellipsoid
    holding the state at the first measurement. Arguments are checked before tracing."""
    check_smf_arguments(model, ys, prior, inputs)
    return run(estimator or SetMembershipFilter(), model, jnp.asarray(ys), inputs, prior)


def check_smf_arguments(model, ys, prior, inputs):
    """Raise ``ValueError`` naming the argument for malformed SMF arguments."""
    import numpy as np

    from jaxest.checks import check_matrix, check_sequence, is_concrete

    if not isinstance(model, BoundedNoiseModel):
        raise ValueError(f"model: expected a BoundedNoiseModel, got {type(model).__name__}")
    if not isinstance(prior, Ellipsoid):
        raise ValueError(f"prior: expected an Ellipsoid(center, shape), got {type(prior).__name__}")
    n, m = model.state_dim, model.obs_dim
    check_sequence("ys", ys, dim=m)
    if inputs is not None:
        check_sequence("inputs", inputs, length=np.shape(ys)[0])
    if np.shape(prior.center) != (n,):
        raise ValueError(f"prior.center: expected shape ({n},), got {np.shape(prior.center)}")
    check_matrix("prior.shape", prior.shape, (n, n), spd=True)
    for name in ("process_bound", "measurement_bound"):
        value = getattr(model, name)
        if np.ndim(value) != 1:
            raise ValueError(
                f"model.{name}: expected a vector of half-widths, got shape {np.shape(value)}"
            )
        if is_concrete(value) and not np.all(np.asarray(value) >= 0):
            raise ValueError(f"model.{name}: half-widths must be non-negative")
