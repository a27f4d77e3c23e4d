"""The nonlinear ellipsoidal set-membership filter (Chai & Sun 2007, §2; docs/papers/smf.md).

Model (eqs 1-4): x_{k+1} = f(x_k, u_k) + w_k,  y_k = h(x_k, u_k) + v_k, with unknown but bounded
noise |w_i| <= wbar_i, |v_i| <= vbar_i and x at the first measurement in the prior ellipsoid.
The filter carries an ellipsoid E(c_k, P_k) guaranteed to contain the true state:

- measurement update (eqs 18-36): h is linearised at c; its Lagrange remainder is bounded over
  the ellipsoid's bounding box (eq 20) and added to vbar (eq 21); each measurement row is a strip
  (eqs 23-25) intersected with the ellipsoid in turn (eqs 27-36);
- time update (eqs 7-17): f is linearised at c, P <- F P F^T (eq 15) and the box of half-widths
  wbar + remainder bound (eqs 11-13) is added one segment at a time (eqs 16-17); c <- f(c) (eq 14).

What happens in the failure modes (each reported in ``status``):

- **Empty intersection** (``Status.EMPTY_SET``): the measurements at step k are inconsistent with
  the predicted set, so the model (the noise bounds, or a healthy sensor) is wrong: a guaranteed
  fault alarm (§3). The filter then discards that step's measurements and carries the predicted
  ellipsoid forward, which still contains the state when the fault is in the sensors.
- **Unbounded set** (``Status.UNBOUNDED``): the filtered or predicted set's size passed
  ``max_radius``, or it lost finiteness, positive definiteness or a condition number the
  arithmetic can carry (``SetStatus.ILL_CONDITIONED`` beside it), e.g. a filter that never sees
  x_1 of the Duffing system: its remainder bound grows like P_11^{3/2}. The set then contains
  everything: the filter stops updating and reports a shape of +inf on the diagonal, from the
  step whose filtered set went bad (one step later when only the prediction did).
- **Unknown remainder bound** (``Status.NONFINITE``): a remainder bound that is NaN (f or h
  evaluated outside its domain over the set, e.g. ``log`` or ``arcsin`` of an interval wholly
  outside theirs, or a closed form that failed) or infinite (a closed form's, or an enclosure
  that overflowed) bounds nothing. A measurement row with one is skipped, so the set stays
  guaranteed, and flagged (an infinite bound of h's had been used as a strip of infinite
  width, with status OK); f's makes the predicted set unbounded.
- **Recovery** (``Status.RECOVERED``, eqs R1-R3 of docs/papers/smf.md): the flag stays set until a
  step whose observed measurement rows alone guarantee a bounded set: h affine in x (its remainder
  bound over the whole space is exactly zero) and the rows constrain every direction (rank n,
  condition within ``max_condition``). The strips then lie in the ellipsoid centred at the
  weighted least-squares point (:func:`~jaxest.setmembership.ellipsoid.strips_ellipsoid`); it is
  the filtered set of that step, and the filter runs on from it (its prediction as usual) with
  UNBOUNDED cleared. While lost, strips that no state satisfies are an EMPTY_SET alarm;
  otherwise a lost filter never signals an empty set. For an h that is
  not affine no recovery is guaranteed (nothing bounds its linearisation error over an unbounded
  set): the flag stays set for the rest of the run, as it does with ``recover=False``.

A NaN entry of y_k means "no measurement from that sensor at step k" (its strip is skipped);
the fault-isolation banks of :mod:`jaxest.setmembership.fdi` feed sensor subsets this way. An
infinite entry is a reading that no bounded noise around a finite h(x) explains: an EMPTY_SET
alarm, as any inconsistent reading is (a lost filter, for an affine h).
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from jaxest._checks import (
    as_array,
    check_flag,
    check_precision,
    check_prior_arrays,
    check_sequence,
    first_input,
    is_concrete,
)
from jaxest._estimator import AbstractEstimator, AbstractResult
from jaxest._run import run
from jaxest._status import finite_status as check_finite_status
from jaxest.linalg import working_precision
from jaxest.models import call_with_optional
from jaxest.setmembership.ellipsoid import (
    Ellipsoid,
    add_box,
    condition_number,
    contains,
    intersect_strip,
    linear_image,
    max_condition,
    strips_ellipsoid,
)
from jaxest.setmembership.interval import remainder_bound
from jaxest.setmembership.rounding import diagonal_scaling, whole_space
from jaxest.setmembership.status import SetStatus as Status


class BoundedNoiseModel(eqx.Module):
    """x_{k+1} = f(x_k, u_k) + w_k,  y_k = h(x_k, u_k) + v_k,  |w| <= process_bound,
    |v| <= measurement_bound (element-wise half-widths of the boxes W and V, eqs 3-4).

    The bounds may be given as Python lists (converted to arrays). ``f`` and ``h`` are written in
    ``jax.numpy`` and take ``(x)``, ``(x, u)`` or ``(x, u, k)`` (``u`` is ``None`` without
    inputs); with one measurement ``h`` may return a scalar.
    The remainder bounds default to the automatic interval bound of
    :func:`~jaxest.setmembership.interval.remainder_bound`; ``f_remainder(center, shape, u)`` /
    ``h_remainder(center, shape, u)`` may replace it by a closed form (it must be guaranteed):
    half-widths of shape (n,) / (m,); a negative one is taken as unknown, as a NaN one (the row
    is skipped, and the status says ``NONFINITE``).
    """

    f: Callable
    h: Callable
    process_bound: Float[Array, " n"] = eqx.field(converter=jnp.asarray)
    measurement_bound: Float[Array, " m"] = eqx.field(converter=jnp.asarray)
    f_remainder: Callable | None = None
    h_remainder: Callable | None = None

    @property
    def state_dim(self) -> int:
        return self.process_bound.shape[-1]

    @property
    def obs_dim(self) -> int:
        return self.measurement_bound.shape[-1]

    def transition(self, x, u=None, k=0) -> Float[Array, " n"]:
        """f(x, u) (step ``k``)."""
        return jnp.reshape(call_with_optional(self.f, x, u, k), (self.state_dim,))

    def observation(self, x, u=None, k=0) -> Float[Array, " m"]:
        """h(x, u) as a vector of the m measurements (step ``k``)."""
        return jnp.reshape(call_with_optional(self.h, x, u, k), (self.obs_dim,))

    def linearise(self, fn, center, u, k):
        """``(fn(c), d fn/dx (c))`` for ``fn`` one of :meth:`transition`, :meth:`observation`."""
        g = lambda x: fn(x, u, k)
        return g(center), jax.jacfwd(g)(center)

    def remainder(self, name: str, center, shape, u, k):
        """Half-widths of the remainder of f (``name`` "f") or h ("h") linearised at c, over
        E(c, P) (eqs 11, 20): its closed-form bound (``f_remainder`` / ``h_remainder``) if
        given, else the automatic interval bound."""
        fn, custom_bound = (
            (self.transition, self.f_remainder)
            if name == "f"
            else (self.observation, self.h_remainder)
        )
        if custom_bound is not None:
            # a negative half-width bounds nothing (it narrowed the strip below the noise bound,
            # and the set lost the truth with status OK): unknown, as a NaN one, and flagged
            bound = jnp.asarray(custom_bound(center, shape, u))
            return jnp.where(bound >= 0, bound, jnp.nan)
        try:
            return remainder_bound(lambda x: fn(x, u, k), center, shape)
        except NotImplementedError as error:
            raise NotImplementedError(
                f"{name}: its automatic remainder bound cannot be computed ({error}); give "
                f"{name}_remainder=(center, shape, u) -> half-widths, a guaranteed bound of "
                "your own, or write it with operations jaxest.setmembership.interval has rules for"
            ) from error


class SMFState(eqx.Module):
    center: Float[Array, " n"]
    shape: Float[Array, "n n"]
    unbounded: Bool[Array, ""]


class SMFOutput(eqx.Module):
    center: Float[Array, " n"] | None
    shape: Float[Array, "n n"] | None
    remainder: Float[Array, " n"] | None  #: remainder bound of f for the time update after k
    measurement_remainder: Float[Array, " m"] | None  #: remainder bound of h used at step k
    status: Int[Array, ""] | None
    predicted_center: Float[Array, " n"] | None = None  #: the set before y_k
    predicted_shape: Float[Array, "n n"] | None = None


class SMFResult(AbstractResult):
    """Filtered ellipsoids E(center[k], shape[k]) after y_k, and per-step :class:`Status` bits.

    ``remainder[k]`` is the bound of f's remainder (eq 11) used to predict from k to k+1 and
    ``measurement_remainder[k]`` that of h (eq 20) used at step k. Where ``unbounded`` the shape
    is +inf on the diagonal (the set is the whole space). ``predicted_center``/``predicted_shape``
    are the sets before y_k (the prior at k = 0), kept when asked for:
    ``run(..., save=SaveAt(fields=(..., "predicted_center", "predicted_shape")))``.
    """

    flags = Status

    final_state: SMFState
    center: Float[Array, "T n"] | None = None
    shape: Float[Array, "T n n"] | None = None
    remainder: Float[Array, "T n"] | None = None
    measurement_remainder: Float[Array, "T m"] | None = None
    status: Int[Array, " T"] | None = None
    any_status: Int[Array, ""] | None = None
    saved: object = None
    predicted_center: Float[Array, "T n"] | None = None
    predicted_shape: Float[Array, "T n n"] | None = None

    @property
    def inconsistent(self) -> Bool[Array, " T"]:
        """True at the steps whose measurements had an empty intersection with the set."""
        return (self.status & Status.EMPTY_SET) != 0

    @property
    def unbounded(self) -> Bool[Array, " T"]:
        return (self.status & Status.UNBOUNDED) != 0

    def contains(self, states: Float[Array, "T n"]) -> Bool[Array, " T"]:
        """Whether states[k] lies in the k-th ellipsoid (always true where unbounded). Compiled
        as one program (docs/performance.md, "First calls outside jit")."""
        got = as_array("states", states).shape
        if got != self.center.shape:  # JAX's broadcasting or vmap error named no argument
            raise ValueError(
                f"states: expected one state per step, shape {self.center.shape}, got {got}"
            )
        return self._contains(states)

    @eqx.filter_jit
    def _contains(self, states):
        bounded_shape = jnp.where(
            self.unbounded[:, None, None], jnp.eye(states.shape[-1]), self.shape
        )
        inside = jax.vmap(contains)(self.center, bounded_shape, states)
        return inside | self.unbounded


class SetMembershipFilter(AbstractEstimator):
    """The nonlinear ellipsoidal SMF (module docstring).

    A set is trusted while its shape matrix is finite, positive definite, has condition number
    at most :func:`~jaxest.setmembership.ellipsoid.max_condition` (kappa n eps <= 2^-10) once
    scaled to a unit diagonal (so whatever the states' units) and every
    sqrt(P_ii) is at most ``max_radius``. The conditioning check guards the arithmetic; the
    radius limit catches a set growing in every direction, which stays well conditioned. Its
    default is b sqrt(kappa_max), b the least positive noise half-width and kappa_max
    :func:`~jaxest.setmembership.ellipsoid.max_condition` in float64 whatever the dtype: about
    2 10^6 / sqrt(n) noise widths, the same size in float32 as in float64 (docs/papers/smf.md,
    "Unbounded sets", says why).

    With ``recover`` (the default) a filter that lost its set re-initialises from the
    measurement strips alone at the first step where that is guaranteed (:meth:`recovery`,
    ``Status.RECOVERED``); without it an unbounded filter stays unbounded.
    """

    max_radius: float | None = None
    recover: bool = eqx.field(static=True, default=True)
    default_fields = ("center", "shape", "remainder", "measurement_remainder", "status")

    def __check_init__(self):
        check_flag("recover", self.recover)
        if self.max_radius is not None and is_concrete(self.max_radius):
            if not (np.ndim(self.max_radius) == 0 and 0 < float(self.max_radius) < np.inf):
                raise ValueError(f"max_radius: must be a positive number, got {self.max_radius!r}")

    def init(self, model: BoundedNoiseModel, prior: Ellipsoid) -> SMFState:
        center, shape = jnp.asarray(prior.center), jnp.asarray(prior.shape)
        return SMFState(center, shape, jnp.zeros((), bool))

    def _limit(self, model, dtype):
        """max_radius^2 (the default from the noise half-widths, class docstring)."""
        if self.max_radius is not None:
            return jnp.asarray(self.max_radius**2, dtype)
        bounds = jnp.concatenate([model.process_bound, model.measurement_bound]).astype(dtype)
        smallest = jnp.min(jnp.where(bounds > 0, bounds, jnp.inf))
        n = model.state_dim
        return jnp.where(jnp.isfinite(smallest), smallest**2, 1.0) * max_condition(jnp.float64, n)

    def _trusted(self, model, center, shape):
        """``(trusted, conditioned)``: the set passes every check / the conditioning one, on
        C = D^-1 P D^-1 (:func:`~jaxest.setmembership.rounding.diagonal_scaling`), the matrix
        whose smallest eigenvalue the rounding bounds divide by (eqs O1, O2, O6). P's own
        condition number changes with the states' units: a temperature in kelvin beside
        concentrations made a float32 filter declare every set unbounded from its prior."""
        _, correlation, _ = diagonal_scaling(shape)
        conditioned = condition_number(correlation) <= max_condition(shape.dtype, shape.shape[-1])
        trusted = (
            conditioned
            & jnp.all(jnp.isfinite(shape))
            & jnp.all(jnp.isfinite(center))
            & jnp.all(jnp.diagonal(shape) <= self._limit(model, shape.dtype))
        )
        return trusted, conditioned

    @working_precision
    def measurement_update(self, model, center, shape, y, u, k, linearised):
        """Eqs 18-36, with h(c) and its Jacobian H at c given (``linearised``); returns
        ``(center, shape, empty, remainder)``."""
        h_c, H = linearised
        alpha = model.remainder("h", center, shape, u, k)
        half_widths = model.measurement_bound + alpha  # eq 21
        new_center, new_shape, empty = center, shape, jnp.zeros((), bool)
        for i in range(H.shape[0]):
            # a row with a NaN or infinite remainder bound bounds nothing: skipped (``step``
            # flags it)
            observed = jnp.isfinite(y[i]) & jnp.isfinite(half_widths[i])
            # an infinite reading lies in no strip of finite half-width around a finite h(x)
            impossible = jnp.isinf(y[i]) & jnp.isfinite(half_widths[i])
            z = jnp.where(observed, y[i], 0.0) - h_c[i] + H[i] @ center  # eq 24
            # a skipped row's NaN half-width kept out of the arithmetic, or its gradient is NaN
            half_width = jnp.where(observed, half_widths[i], 1.0)
            c_i, P_i, empty_i = intersect_strip(new_center, new_shape, H[i], z, half_width)
            new_center = jnp.where(observed, c_i, new_center)
            new_shape = jnp.where(observed, P_i, new_shape)
            empty = empty | (observed & empty_i) | impossible
        # an inconsistent measurement set is discarded: carry the predicted set forward
        return (
            jnp.where(empty, center, new_center),
            jnp.where(empty, shape, new_shape),
            empty,
            alpha,
        )

    @working_precision
    def time_update(self, model, center, shape, u, k=0):
        """Eqs 7-17; returns ``(center, shape, remainder)``."""
        f_c, F = model.linearise(model.transition, center, u, k)
        alpha = model.remainder("f", center, shape, u, k)
        image, image_error = linear_image(F, shape)  # eq 15
        shape = add_box(image, model.process_bound + alpha, image_error)  # eqs 16-17, 12-13
        return f_c, shape, alpha

    def predict(self, model: BoundedNoiseModel, prior: Ellipsoid, u=None, k=0) -> Ellipsoid:
        """The time update of ``prior`` (at step ``k``) alone: the set one step later, without a
        measurement. Compiled as one program, once for every step ``k`` (docs/performance.md,
        "First calls outside jit")."""
        check_model_and_prior(model, prior)
        return self._predict(model, prior, u, jnp.asarray(k))

    @eqx.filter_jit
    def _predict(self, model, prior, u, k):
        center, shape, _ = self.time_update(model, prior.center, prior.shape, u, k)
        return Ellipsoid(center, shape)

    def check(self, model, ys, inputs, prior) -> None:
        check_smf_arguments(model, ys, prior, inputs)

    @working_precision
    def recovery(self, model, center, y, u, k, linearised):
        """The set the measured strips alone guarantee (eqs R1-R3, docs/papers/smf.md), for a
        filter that lost its set, with h(c) and H at c given (``linearised``); returns
        ``(center, shape, possible, inconsistent)``.

        Guaranteed only when h is affine in x, h(x) = H x + h(0): proved by the remainder bound
        of h (the model's own, automatic or closed-form) over the whole space being exactly
        zero. For an h that is not affine no bound on the linearisation error holds over an
        unbounded set, so there is no recovery. ``possible``: h affine, no reading infinite and
        the observed rows (finite entries of y) constrain every direction
        (:func:`strips_ellipsoid`); ``inconsistent``: h affine, and an infinite reading (an affine
        h is finite everywhere) or no state satisfies the rows (eq R3).
        """
        h_c, H = linearised
        everything = whole_space(model.state_dim, center.dtype)
        bound = model.remainder("h", center, everything, u, k)
        affine = jnp.all(bound == 0)
        observed = jnp.isfinite(y)
        impossible = jnp.any(jnp.isinf(y))
        z = jnp.where(observed, y, 0.0) - h_c + H @ center  # eq 24, exact for affine h
        c, P, bounded, inconsistent = strips_ellipsoid(H, z, model.measurement_bound, observed)
        return c, P, affine & bounded & ~impossible, affine & (inconsistent | impossible)

    @working_precision
    def step(self, model, state: SMFState, k, y, u, key=None):
        linearised = model.linearise(model.observation, state.center, u, k)
        c, P, empty, alpha_h = self.measurement_update(
            model, state.center, state.shape, y, u, k, linearised
        )
        empty = empty & ~state.unbounded
        restart = jnp.zeros((), bool)
        if self.recover:  # a lost filter's set is the strips' alone (eq R2) where guaranteed
            c_r, P_r, possible, inconsistent = self.recovery(
                model, state.center, y, u, k, linearised
            )
            restart = state.unbounded & possible
            empty = empty | (state.unbounded & inconsistent)  # eq R3
            c, P = jnp.where(restart, c_r, c), jnp.where(restart, P_r, P)
            alpha_h = jnp.where(restart, 0.0, alpha_h)  # h is affine
        lost = state.unbounded & ~restart  # the predicted set is the whole space
        trusted, conditioned = self._trusted(model, c, P)
        recovered = restart & trusted
        # flagged at the step the filtered set goes bad; cleared at the step it is recovered
        unbounded = (state.unbounded & ~recovered) | ~trusted
        c_next, P_next, alpha_f = self.time_update(model, c, P, u, k)
        trusted_next, conditioned_next = self._trusted(model, c_next, P_next)
        unbounded_next = unbounded | ~trusted_next
        frozen = lambda new, old: jnp.where(unbounded_next, old, new)
        new_state = SMFState(
            frozen(c_next, state.center), frozen(P_next, state.shape), unbounded_next
        )
        everything = whole_space(P.shape[-1], P.dtype)
        ill = ~lost & ~(conditioned & conditioned_next)
        # a NaN or infinite remainder bound bounds nothing: its measurement row was skipped
        # (measurement_update; the set stays guaranteed) or the predicted set is lost
        # (UNBOUNDED), and the step says why
        unknown_remainder = (~lost & jnp.any(~jnp.isnan(y) & ~jnp.isfinite(alpha_h))) | (
            ~unbounded & jnp.any(~jnp.isfinite(alpha_f))
        )
        status = (
            jnp.where(empty, Status.EMPTY_SET, 0)
            | jnp.where(unbounded, Status.UNBOUNDED, 0)
            | jnp.where(ill, Status.ILL_CONDITIONED, 0)
            | jnp.where(recovered, Status.RECOVERED, 0)
            | jnp.where(unknown_remainder, Status.NONFINITE, 0)
            | check_finite_status(c)
        ).astype(jnp.int32)
        output = SMFOutput(
            center=c,
            shape=jnp.where(unbounded, everything, P),
            remainder=jnp.where(unbounded, jnp.inf, alpha_f),
            measurement_remainder=jnp.where(lost, jnp.inf, alpha_h),
            status=status,
            predicted_center=state.center,
            predicted_shape=jnp.where(state.unbounded, everything, state.shape),
        )
        return new_state, output

    def result(self, outputs: SMFOutput, final_state: SMFState) -> SMFResult:
        return SMFResult(
            final_state=final_state,
            center=outputs.center,
            shape=outputs.shape,
            remainder=outputs.remainder,
            measurement_remainder=outputs.measurement_remainder,
            status=outputs.status,
            predicted_center=outputs.predicted_center,
            predicted_shape=outputs.predicted_shape,
        )


def set_membership_filter(
    model: BoundedNoiseModel,
    ys,
    *,
    prior: Ellipsoid,
    inputs=None,
    estimator: SetMembershipFilter | None = None,
    **run_options,
) -> SMFResult:
    """Run the SMF over ``ys`` (shape (T, m), or (T,) with one measurement; NaN = no
    measurement) from ``prior``, the ellipsoid holding the state at the first measurement:
    :func:`jaxest.run` with the default filter. Arguments are checked before tracing."""
    estimator = estimator or SetMembershipFilter()
    if isinstance(model, BoundedNoiseModel) and model.obs_dim == 1 and jnp.ndim(ys) == 1:
        ys = jnp.reshape(ys, (-1, 1))
    return run(estimator, model, ys, prior=prior, inputs=inputs, **run_options)


def check_model_and_prior(model, prior) -> None:
    """``model`` a :class:`BoundedNoiseModel` with vectors of non-negative half-widths and
    ``prior`` an :class:`Ellipsoid` of its state's size, real, finite and positive definite
    (``ValueError`` naming the argument; values checked where concrete)."""
    if not isinstance(model, BoundedNoiseModel):
        raise ValueError(f"model: expected a BoundedNoiseModel, got {type(model).__name__}")
    if not isinstance(prior, Ellipsoid):
        raise ValueError(f"prior: expected an Ellipsoid(center, shape), got {type(prior).__name__}")
    for name in ("process_bound", "measurement_bound"):
        value = getattr(model, name)
        if np.ndim(value) != 1:
            raise ValueError(
                f"model.{name}: expected a vector of half-widths (one per state or measurement),"
                f" got shape {np.shape(value)}"
            )
        if is_concrete(value) and not np.all(np.asarray(value) >= 0):
            raise ValueError(f"model.{name}: half-widths must be non-negative")
    check_prior_arrays(prior, "center", "shape", model.state_dim)


def check_smf_arguments(model, ys, prior, inputs):
    """Raise ``ValueError`` naming the argument for malformed SMF arguments."""
    check_model_and_prior(model, prior)
    n, m = model.state_dim, model.obs_dim
    check_sequence("ys", ys, dim=m)
    if inputs is not None:
        check_sequence("inputs", inputs, length=np.shape(ys)[0])
    check_precision(model, ys, prior)
    u0 = None if inputs is None else jax.tree.map(first_input, inputs)
    for name, fn, size in (("model.f", model.f, n), ("model.h", model.h, m)):
        try:
            value = jax.eval_shape(
                lambda x, u, fn=fn: call_with_optional(fn, x, u, 0), prior.center, u0
            )
        except Exception as error:  # the user's function failed on a state of the prior's shape
            raise ValueError(
                f"{name}: calling it with x of shape ({n},) and the first input failed: "
                f"{type(error).__name__}: {error}"
            ) from error
        if value.shape not in ((size,), ()) or (value.shape == () and size != 1):
            raise ValueError(f"{name}: expected it to return shape ({size},), got {value.shape}")
        if value.dtype != jnp.result_type(prior.center):  # the step was blamed for its state
            raise ValueError(
                f"{name}: returns {value.dtype} for a {jnp.result_type(prior.center)} state (a "
                "constant of another precision in it, e.g. a NumPy float64 array, promotes "
                "it); the sets are carried in the prior's dtype"
            )
    for name, bound, size in (("model.f_remainder", model.f_remainder, n),
                              ("model.h_remainder", model.h_remainder, m)):  # fmt: skip
        if bound is None:
            continue
        try:
            value = jax.eval_shape(bound, prior.center, prior.shape, u0)
        except Exception as error:  # the user's bound failed on the prior's shapes
            raise ValueError(
                f"{name}: calling it with the prior's center and shape and the first input "
                f"failed: {type(error).__name__}: {error}"
            ) from error
        if getattr(value, "shape", None) != (size,):  # a (3,) bound for one row was broadcast
            got = getattr(value, "shape", type(value).__name__)
            raise ValueError(f"{name}: expected half-widths of shape ({size},), got {got}")
