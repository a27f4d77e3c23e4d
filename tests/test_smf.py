"""The nonlinear ellipsoidal SMF and fault detection/isolation: agreement with an independent NumPy
loop, the containment guarantee, alarms, the unbounded-set behaviour, transforms (the quick study
and its compiled programs: test_smf_fdi_batch.py)."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxest as je
from jaxest import run
from jaxest.setmembership import fdi
from jaxest.setmembership.ellipsoid import Ellipsoid
from jaxest.setmembership.smf import (
    BoundedNoiseModel,
    SetMembershipFilter,
    SMFResult,
    set_membership_filter,
)
from jaxest.setmembership.status import SetStatus as Status
from jaxest.studies import smf_fdi
from jaxest.systems import duffing
from jaxest.systems._box_noise import simulate_box_noise
from tests import benchmark_scripts
from tests.lowering import programs_compiled

reference = benchmark_scripts.load("smf")


def _filter_runs(keys, L, closed_form_bound=True, mask=(True, True)):
    return _compiled_runs(L, closed_form_bound)(keys, jnp.asarray(mask))


@functools.cache  # the sensor masks share one program
def _compiled_runs(L, closed_form_bound):
    model, prior = duffing.model(closed_form_bound), smf_fdi.first_prior(closed_form_bound)

    def one(key, mask):
        states, ys = smf_fdi.simulate_run(key, L)
        result = run(SetMembershipFilter(), model, fdi.sensor_subset(ys, mask), prior=prior)
        return states, ys, result

    return jax.jit(jax.vmap(one, in_axes=(0, None)))


@pytest.mark.parametrize("mask", [(True, True), (True, False)])
def test_matches_numpy_reference(mask):
    keys = jax.random.split(jax.random.key(1), 3)
    _, ys, result = _filter_runs(keys, 1, mask=mask)
    prior = smf_fdi.first_prior(True)
    model = duffing.model(True)
    for r in range(3):
        centres, shapes, empties = reference.numpy_smf(
            np.asarray(ys[r]), np.asarray(prior.center), np.asarray(prior.shape),
            np.asarray(model.process_bound), np.asarray(model.measurement_bound), mask,
        )  # fmt: skip
        np.testing.assert_allclose(result.center[r], centres, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(result.shape[r], shapes, rtol=1e-9, atol=1e-14)
        np.testing.assert_array_equal(result.inconsistent[r], empties)


def test_fault_free_sets_contain_the_state_and_never_alarm():
    keys = jax.random.split(jax.random.key(2), 40)
    for mask in ((True, True), (True, False), (False, True)):
        states, _, result = _filter_runs(keys, None, closed_form_bound=False, mask=mask)
        assert bool(jnp.all(jax.vmap(lambda r, s: r.contains(s))(result, states)))
        assert not bool(jnp.any(result.status & (Status.EMPTY_SET | Status.NONFINITE)))


def test_large_bias_is_detected_at_its_onset_and_never_before():
    keys = jax.random.split(jax.random.key(3), 10)
    _, _, result = _filter_runs(keys, 20.0)  # bias 0.23, far beyond the noise bound
    first = np.asarray(fdi.first_alarm(result.inconsistent))
    np.testing.assert_array_equal(first, duffing.FAULT_START)


def _unstable_model(dtype):
    """x1 grows (never observed), x2 is measured: the set must grow without bound."""
    f = lambda x, u: jnp.stack([1.5 * x[0] + 0.2 * x[0] ** 2, 0.5 * x[1]])
    return BoundedNoiseModel(
        f, lambda x, u: x[1:], jnp.full(2, 0.01, dtype), jnp.full(1, 0.01, dtype)
    )


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_unbounded_set_is_reported_not_nan(dtype):
    model = _unstable_model(dtype)
    prior = Ellipsoid(jnp.asarray([0.5, 0.0], dtype), 0.01 * jnp.eye(2, dtype=dtype))
    ys = jnp.zeros((60, 1), dtype)
    result = jax.jit(lambda ys: set_membership_filter(model, ys, prior=prior))(ys)
    unbounded = np.asarray(result.unbounded)
    assert unbounded[-1] and not unbounded[0]
    start = np.argmax(unbounded)
    assert np.all(unbounded[start:])  # absorbing
    assert np.all(np.isfinite(result.center))
    assert np.all(np.isinf(np.diagonal(result.shape[start:], axis1=1, axis2=2)))
    assert not np.any(np.asarray(result.inconsistent[start:]))
    assert np.all(np.asarray(result.contains(jnp.full((60, 2), 1e9, dtype)))[start:])


def test_a_pole_inside_the_set_makes_it_unbounded_not_wrong():
    # f has a pole at x1 = -0.05 and the state starts at -0.0495, inside the step-0 set, which
    # spans the pole: f's remainder bound over it is +inf. add_box skipped that infinite segment
    # (its test a > 0 is false for NaN) and predicted a finite set, centre 1.7 and radius 6.4,
    # that missed f(x) = 19.95: every later step raised a guaranteed fault alarm (EMPTY_SET)
    # with no fault, and no set held the state.
    f = lambda x: jnp.stack([x[0] + 0.01 / (x[0] + 0.05), 0.9 * x[1]])
    model = BoundedNoiseModel(f, lambda x: x, jnp.full(2, 1e-3), jnp.full(2, 1e-2))
    states = [jnp.asarray([-0.0495, 0.01])]
    for _ in range(9):
        states.append(f(states[-1]))
    states = jnp.stack(states)
    ys = states + 0.5e-2 * jnp.asarray([1.0, -1.0])
    prior = Ellipsoid(jnp.asarray([-0.03, 0.0]), 0.01 * jnp.eye(2))
    result = jax.jit(lambda ys: run(SetMembershipFilter(), model, ys, prior=prior))(ys)
    status = np.asarray(result.status)
    assert not np.any(status & Status.EMPTY_SET)
    # the predicted set is lost after step 0 (flagged there), and h = x recovers it at step 1
    assert status[0] & Status.ILL_CONDITIONED and status[1] & Status.RECOVERED
    assert np.all(np.asarray(result.contains(states)))


def _decay():
    """x_{k+1} = 0.9 x_k, both states measured with an error of 0.005 inside the bound 0.01:
    ``(f, states, ys, bounds, prior)``."""
    f = lambda x: 0.9 * x
    states = jnp.stack([0.9**k * jnp.asarray([0.3, -0.2]) for k in range(8)])
    ys = states + 0.5e-2 * jnp.asarray([1.0, -1.0])
    bounds = (jnp.full(2, 1e-3), jnp.full(2, 1e-2))
    return f, states, ys, bounds, Ellipsoid(jnp.zeros(2), 0.25 * jnp.eye(2))


@pytest.mark.parametrize("unknown", [np.nan, np.inf])
def test_an_unknown_remainder_bound_skips_its_row_and_is_flagged(unknown):
    """A remainder bound that is NaN or infinite bounds nothing. h's: its row is skipped (the sets
    still hold the state) and the step is flagged NONFINITE, where the strip used to be skipped
    silently (an infinite bound was a strip of infinite width, with status OK); f's: the
    predicted set is unbounded, flagged NONFINITE at the step that computed it."""
    f, states, ys, bounds, prior = _decay()
    ys = ys.at[5, 1].set(jnp.nan)  # missing: its unknown bound plays no part
    nan_row = lambda c, P, u: jnp.asarray([0.0, unknown])
    skipped = BoundedNoiseModel(f, lambda x: x, *bounds, h_remainder=nan_row)
    result = run(SetMembershipFilter(), skipped, ys, prior=prior)
    status = np.asarray(result.status)
    assert np.all(status[[0, 1, 2, 3, 4, 6, 7]] == Status.NONFINITE) and status[5] == Status.OK
    assert np.all(np.asarray(result.contains(states)))
    first_row_only = BoundedNoiseModel(f, lambda x: x[:1], bounds[0], bounds[1][:1])
    alone = run(SetMembershipFilter(), first_row_only, ys[:, :1], prior=prior)
    np.testing.assert_allclose(result.shape, alone.shape, rtol=1e-12)  # as if the row were not
    unknown_f = lambda c, P, u: jnp.full_like(c, unknown)
    # one row: no recovery from the strips alone
    lost = BoundedNoiseModel(f, lambda x: x[:1], bounds[0], bounds[1][:1], f_remainder=unknown_f)
    status = np.asarray(run(SetMembershipFilter(), lost, ys[:, :1], prior=prior).status)
    assert status[0] & Status.NONFINITE and np.all(status[1:] & Status.UNBOUNDED)


def test_a_step_written_as_a_cast_is_flagged_not_linearised_away():
    """h(x) = x + 0.015 (x > 0.1) on the first state: JAX differentiates the cast as a constant,
    so its remainder bound was 0 and the strip, linearised at the prior's centre below the
    step, held x_1 in [0.31, 0.33] where it is 0.3: a set without the state, status OK. The
    step lies inside the box: the bound is unknown (NaN), its row is skipped and flagged."""
    f, states, _, bounds, prior = _decay()
    h = lambda x: x + jnp.asarray([0.015, 0.0]) * (x > 0.1).astype(x.dtype)
    ys = jax.vmap(h)(states) + 0.5e-2 * jnp.asarray([1.0, -1.0])
    result = run(SetMembershipFilter(), BoundedNoiseModel(f, h, *bounds), ys, prior=prior)
    assert np.all(np.asarray(result.status) & Status.NONFINITE)
    assert np.all(np.asarray(result.contains(states)))

    # the skipped row's NaN stays out of the gradient (it made it NaN): central differences
    def log_volume(w):
        model = BoundedNoiseModel(f, h, jnp.full(2, w), bounds[1])
        return jnp.linalg.slogdet(run(SetMembershipFilter(), model, ys, prior=prior).shape[-1])[1]

    w, eps = bounds[0][0], 1e-7
    fd = (log_volume(w + eps) - log_volume(w - eps)) / (2 * eps)
    np.testing.assert_allclose(jax.jit(jax.grad(log_volume))(w), fd, rtol=1e-6)


def test_a_function_the_interval_bound_cannot_evaluate_is_named_with_the_way_out():
    f, _, ys, bounds, prior = _decay()
    for model, name, primitive in (
        (
            BoundedNoiseModel(lambda x: jax.lax.digamma(x + 3), lambda x: x, *bounds),
            "f",
            "digamma",
        ),  # fmt: skip
        (BoundedNoiseModel(f, lambda x: x + jax.lax.lgamma(x + 3), *bounds), "h", "lgamma"),
    ):
        with pytest.raises(NotImplementedError, match=f"^{name}: .*'{primitive}'.*{name}_rem"):
            run(SetMembershipFilter(), model, ys, prior=prior)


@pytest.mark.parametrize("reading", [np.inf, -np.inf])
def test_an_infinite_reading_is_an_alarm_not_a_missing_measurement(reading):
    """An infinite y lies in no strip around a finite h(x): EMPTY_SET at its step, where it used
    to be skipped with status OK as a NaN (missing) one is, so a sensor stuck at inf went
    unnoticed. The step's readings are discarded, as for any alarm."""
    f, states, ys, bounds, prior = _decay()
    model = BoundedNoiseModel(f, lambda x: x, *bounds)
    result = jax.jit(lambda ys: run(SetMembershipFilter(), model, ys, prior=prior))(
        ys.at[3, 0].set(reading)
    )
    assert np.flatnonzero(np.asarray(result.status)).tolist() == [3]
    assert result.status[3] == Status.EMPTY_SET
    assert np.all(np.asarray(result.contains(states)))
    discarded = run(SetMembershipFilter(), model, ys.at[3].set(jnp.nan), prior=prior)
    np.testing.assert_array_equal(result.shape, discarded.shape)


def test_a_float_exponent_keeps_the_truth_in_the_set():
    """h = x ** 3.0 (pow, not integer_pow) over a prior reaching below 0: the update excluded the
    true x = -1 with status OK (set [-1.300, -1.181]) and the prediction with f = x ** 3.0 missed
    f(-1.3); both now equal those of x ** 3."""
    prior = Ellipsoid(jnp.asarray([-0.6]), jnp.asarray([[0.49]]))
    for h in (lambda x: x**3.0, lambda x: x**3):
        model = BoundedNoiseModel(lambda x: x, h, [0.01], [0.01])
        result = run(SetMembershipFilter(), model, jnp.asarray([[-1.0]]), prior=prior)
        assert int(result.status[0]) == 0 and bool(result.contains(jnp.asarray([[-1.0]]))[0])
    for f in (lambda x: x**3.0, lambda x: x**3):
        model = BoundedNoiseModel(f, lambda x: x, [0.01], [0.01])
        predicted = SetMembershipFilter().predict(model, prior)
        assert (-2.197 - float(predicted.center[0])) ** 2 <= float(predicted.shape[0, 0])


def test_a_closed_form_remainder_bound_is_checked():
    """A user's h_remainder of the wrong shape was broadcast, and a negative one narrowed the strip
    below the noise bound: the set [0.09, 0.11] lost the true x = 0 with status OK."""
    prior = Ellipsoid(jnp.zeros(1), jnp.eye(1))
    model = lambda bound: BoundedNoiseModel(lambda x: x, lambda x: x, [0.01], [0.1],
                                            h_remainder=bound)  # fmt: skip
    with pytest.raises(
        ValueError, match=r"^model.h_remainder: expected half-widths of shape \(1,\)"
    ):
        set_membership_filter(
            model(lambda c, P, u: jnp.zeros(3)), jnp.asarray([[0.1]]), prior=prior
        )
    with pytest.raises(ValueError, match="^model.f_remainder: calling it"):
        set_membership_filter(BoundedNoiseModel(lambda x: x, lambda x: x, [0.01], [0.1],
                                                f_remainder=lambda c, P: jnp.zeros(1)),
                              jnp.asarray([[0.1]]), prior=prior)  # fmt: skip
    # true x = 0 and v = 0.1, on its bound
    negative = set_membership_filter(model(lambda c, P, u: -0.09 * jnp.ones(1)),
                                     jnp.asarray([[0.1]]), prior=prior)  # fmt: skip
    assert Status.NONFINITE in Status(int(negative.status[0]))
    assert bool(negative.contains(jnp.zeros((1, 1)))[0])


def test_a_singular_jacobian_keeps_the_predicted_set_bounded():
    """F P F^T is flat where f's Jacobian is singular. The box added to it gives a bounded set,
    where the filter used to flag ILL_CONDITIONED and then UNBOUNDED for good: a state driven by
    noise alone (over 50 runs the sets hold the truth and nothing is flagged), and the logistic
    map predicted from its vertex (f'(0.5) = 0) as from a point beside it."""
    f = lambda x: jnp.stack([0.9 * x[0] + x[1], 0.0 * x[1]])  # x_2 = w_2 at every step
    bounds = (jnp.asarray([0.01, 0.05]), jnp.asarray([0.1]))
    model = BoundedNoiseModel(f, lambda x: x[:1], *bounds)
    prior = Ellipsoid(jnp.asarray([1.0, 0.0]), 0.1 * jnp.eye(2))

    def one(key):
        states, ys = simulate_box_noise(
            jax.random.split(key), f, lambda x: x[:1], jnp.asarray([1.0, 0.0]),
            jnp.zeros((41, 1)), *bounds,
        )  # fmt: skip
        result = run(SetMembershipFilter(), model, ys[1:], prior=SetMembershipFilter().predict(
            model, Ellipsoid(states[0], 0.01 * jnp.eye(2))
        ))  # fmt: skip
        return result.status, result.contains(states[1:])

    status, inside = jax.jit(jax.vmap(one))(jax.random.split(jax.random.key(3), 50))
    assert not np.any(np.asarray(status)) and np.all(np.asarray(inside))

    @jax.jit
    def log_volume(w):  # through a flat prediction at every step: no NaN from its solve
        noisy = BoundedNoiseModel(f, lambda x: x[:1], bounds[0].at[1].set(w), bounds[1])
        ys = jnp.linspace(0.5, 1.0, 15)[:, None]
        return jnp.sum(
            jnp.linalg.slogdet(run(SetMembershipFilter(), noisy, ys, prior=prior).shape)[1]
        )

    central = (log_volume(0.05 + 1e-6) - log_volume(0.05 - 1e-6)) / 2e-6
    np.testing.assert_allclose(jax.grad(log_volume)(0.05), central, rtol=1e-6)
    logistic = BoundedNoiseModel(lambda x: 3.7 * x * (1 - x), lambda x: x, [0.01], [0.05])
    at, beside = (
        SetMembershipFilter().predict(logistic, Ellipsoid(jnp.asarray([c]), jnp.asarray([[0.01]])))
        for c in (0.5, 0.5 + 1e-9)
    )
    # beside it F = -7.4e-9 adds |F| sqrt(P) = 7.4e-10 to the half-width 0.047: 3e-8 relative
    np.testing.assert_allclose(at.shape, beside.shape, rtol=1e-7)


def test_float32_carries_sets_many_noise_widths_across():
    # process noise 0.0005, measurement noise 0.05: the first filtered sets are about 0.09 in
    # radius, 180 of the least half-width. float32 keeps the sets float64 keeps (the default
    # radius limit was 64 least half-widths in float32, 0.032 here: it flagged them unbounded).
    bounds = (0.0005, 0.05)
    simulate = lambda key: simulate_box_noise(
        jax.random.split(key), duffing.Duffing(), duffing.observe, jnp.asarray(duffing.X0),
        jnp.zeros((60, 2)), *bounds,
    )  # fmt: skip
    states, ys = jax.vmap(simulate)(jax.random.split(jax.random.key(6), 20))
    results = {}
    for dtype in (jnp.float32, jnp.float64):
        dynamics = duffing.Duffing()
        model = BoundedNoiseModel(
            dynamics, duffing.observe, jnp.full(2, bounds[0], dtype), jnp.full(2, bounds[1], dtype),
            f_remainder=dynamics.remainder_bound,
        )  # fmt: skip
        prior = SetMembershipFilter().predict(model, duffing.prior(dtype))
        one = lambda y: run(SetMembershipFilter(), model, y, prior=prior)  # noqa: B023
        results[dtype] = jax.jit(jax.vmap(one))(ys.astype(dtype))
    single = results[jnp.float32]
    assert not np.any(np.asarray(single.status))
    inside = jax.vmap(lambda r, s: r.contains(s))(single, states.astype(jnp.float32))
    assert np.all(np.asarray(inside))
    radii = lambda r: np.sqrt(np.diagonal(np.asarray(r.shape, np.float64), axis1=-2, axis2=-1))
    assert np.max(radii(single)) > 2 * 0.032
    np.testing.assert_allclose(radii(single), radii(results[jnp.float64]), rtol=1e-2)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_filter_under_jit_vmap_grad(dtype):
    _, ys, _ = _filter_runs(jax.random.split(jax.random.key(4), 2), None)
    ys = ys.astype(dtype)[:, :30]
    prior = Ellipsoid(jnp.asarray(duffing.X0, dtype), 0.01 * jnp.eye(2, dtype=dtype))

    def log_volume(w):
        model = duffing.model(closed_form_bound=True, dtype=dtype)
        model = BoundedNoiseModel(
            model.f, model.h, jnp.full(2, w), model.measurement_bound, model.f_remainder
        )
        result = run(SetMembershipFilter(), model, ys[0], prior=prior)
        return jnp.linalg.slogdet(result.shape[-1])[1]

    batched = jax.jit(
        jax.vmap(
            lambda y: run(SetMembershipFilter(), duffing.model(True, dtype), y, prior=prior).shape
        )
    )(ys)
    assert batched.dtype == dtype and batched.shape == (2, 30, 2, 2)
    w = jnp.asarray(duffing.PROCESS_BOUND, dtype)
    grad = jax.jit(jax.grad(log_volume))(w)
    eps = 1e-4 if dtype == jnp.float32 else 1e-7
    fd = (log_volume(w + eps) - log_volume(w - eps)) / (2 * eps)
    assert np.isfinite(grad) and grad > 0  # more process noise, a larger set
    np.testing.assert_allclose(grad, fd, rtol=5e-2 if dtype == jnp.float32 else 1e-4)


def test_isolation_decisions_and_scores():
    # filter 0 (method 1: sensor 1 only) empty at steps 3 and 5; filter 1 never
    inconsistent = np.zeros((2, 6), bool)
    inconsistent[0, [2, 4]] = True
    m1 = np.asarray(fdi.isolation_decisions(inconsistent, 1))
    np.testing.assert_array_equal(m1[:, 0], inconsistent[0])
    # method 2 bank: filter i sees every sensor but i; sensor 1 faulty -> filter 1 (sensor 2 only) fine
    m2 = np.asarray(fdi.isolation_decisions(inconsistent[::-1], 2))
    np.testing.assert_array_equal(m2[:, 0], inconsistent[0])
    assert not m2[:, 1].any()
    both = np.ones((2, 6), bool)  # every filter empty: no sensor isolated by method 2
    assert not np.asarray(fdi.isolation_decisions(both, 2)).any()
    # three sensors, sensor 0 faulty: filters 1 and 2 (which see it) go empty at different steps
    three = np.zeros((3, 8), bool)
    three[1, [2, 6]] = True
    three[2, 4] = True
    same = np.asarray(fdi.isolation_decisions(three, 2))
    assert not same.any()  # never both empty at one step
    by_step = np.asarray(fdi.isolation_decisions(three, 2, reading="by_step"))
    np.testing.assert_array_equal(by_step[:, 0], np.arange(8) >= 4)  # once both have been empty
    assert not by_step[:, 1:].any()
    with pytest.raises(ValueError, match="^reading:"):
        fdi.isolation_decisions(three, 2, reading="eventually")
    alarms = np.zeros((4, 10), bool)
    alarms[0, 1] = True  # step 2: a false alarm
    alarms[1, 6] = True  # step 7: delay 2 from fault_start 5
    alarms[2, 4] = True  # step 5: delay 0
    s = fdi.score(alarms, fault_start=5)
    assert s["false_alarm_rate"] == 0.25 and s["missed_rate"] == 0.5
    assert (s["min_delay"], s["max_delay"], s["mean_delay"]) == (0, 2, 1.0)
    assert abs(fdi.chi_square_threshold(2, 0.01) - 9.21034) < 1e-4
    assert abs(fdi.chi_square_threshold(3, 0.05) - 7.814728) < 1e-4
    # a negative significance doubled the bracket forever; 1.5 gave 6e-61 (-0.81 at 2 dof)
    for dof, significance in ((3, -0.05), (3, 1.5), (2, 1.5), (2, 0.0)):
        with pytest.raises(ValueError, match="^significance: must lie in"):
            fdi.chi_square_threshold(dof, significance)
    for dof in (0, 2.0, True):
        with pytest.raises(ValueError, match="^dof: must be a positive integer"):
            fdi.chi_square_threshold(dof, 0.05)


def test_arguments_are_checked_before_tracing():
    model, prior = duffing.model(), duffing.prior()
    with pytest.raises(ValueError, match="ys"):
        set_membership_filter(model, jnp.zeros((5, 3)), prior=prior)
    with pytest.raises(ValueError, match="prior.shape"):
        set_membership_filter(model, jnp.zeros((5, 2)), prior=Ellipsoid(prior.center, -jnp.eye(2)))
    with pytest.raises(ValueError, match="prior"):
        set_membership_filter(model, jnp.zeros((5, 2)), prior=(prior.center, prior.shape))
    with pytest.raises(ValueError, match="process_bound"):
        bad = BoundedNoiseModel(model.f, model.h, -model.process_bound, model.measurement_bound)
        set_membership_filter(bad, jnp.zeros((5, 2)), prior=prior)
    # these ran: NaN sets with a status at every step, a radius limit squared (-1 acted as 1)
    # or NaN (every set unbounded), and a TypeError from inside the scan
    with pytest.raises(ValueError, match="^prior.center: contains NaN"):
        nan_center = Ellipsoid(prior.center.at[0].set(jnp.nan), prior.shape)
        set_membership_filter(model, jnp.zeros((5, 2)), prior=nan_center)
    for radius in (-1.0, float("nan"), 0.0):
        with pytest.raises(ValueError, match="^max_radius: must be a positive number"):
            SetMembershipFilter(max_radius=radius)
    with pytest.raises(ValueError, match="^prior: is float32, narrower"):
        narrow = Ellipsoid(prior.center.astype(jnp.float32), prior.shape.astype(jnp.float32))
        set_membership_filter(model, jnp.zeros((5, 2)), prior=narrow)
    # these raised JAX's errors, which named no argument, or ran: predict on a non-symmetric set
    with pytest.raises(ValueError, match="^prior.center: must be real floating point"):
        set_membership_filter(
            model, jnp.zeros((5, 2)), prior=Ellipsoid(jnp.zeros(2, int), prior.shape)
        )
    with pytest.raises(ValueError, match="^ys: expected an array, got list"):
        set_membership_filter(model, [[0.0, 0.0]] * 5, prior=prior)
    with pytest.raises(ValueError, match="^prior.center: expected shape \\(2,\\)"):
        SetMembershipFilter().predict(model, Ellipsoid(jnp.zeros(3), jnp.eye(3)))
    with pytest.raises(ValueError, match="^prior.shape: must be symmetric"):
        SetMembershipFilter().predict(model, Ellipsoid(prior.center, prior.shape.at[0, 1].add(1.0)))
    with pytest.raises(ValueError, match="^used: expected one entry per sensor"):
        fdi.sensor_subset(jnp.zeros((5, 2)), jnp.array([True, False, True]))
    with pytest.raises(ValueError, match="^alarms: expected \\(runs, T\\) with at least one"):
        fdi.score(np.zeros((0, 5), bool), fault_start=2)  # NaN rates and NumPy warnings
    result = SMFResult(None, center=jnp.zeros((5, 2)), shape=jnp.ones((5, 2, 2)))
    with pytest.raises(ValueError, match="^states: expected one state per step, shape \\(5, 2\\)"):
        result.contains(jnp.zeros((4, 2)))


def test_bounds_given_as_python_numbers_or_lists():
    """Lists are arrays; a scalar bound is named, not an AttributeError."""
    model = duffing.model(False, jnp.float64)
    as_list = BoundedNoiseModel(model.f, model.h, [0.005, 0.005], [0.01, 0.01])
    prior = duffing.prior(jnp.float64)
    ys = jnp.full((5, 2), 0.25)
    reference = set_membership_filter(model, ys, prior=prior)
    listed = set_membership_filter(as_list, ys, prior=prior)
    np.testing.assert_allclose(listed.shape, reference.shape, rtol=1e-12)
    scalar = BoundedNoiseModel(model.f, model.h, 0.005, [0.01, 0.01])
    with pytest.raises(ValueError, match="model.process_bound"):
        set_membership_filter(scalar, ys, prior=prior)


def test_ill_conditioned_set_is_flagged_at_its_step():
    """A prior of condition 1e13 scaled to a unit diagonal (beyond kappa n eps <= 2^-10): flagged
    ILL_CONDITIONED and UNBOUNDED at step 0, never reported as an empty set or a bounded set."""
    model = BoundedNoiseModel(
        lambda x, u: x, lambda x, u: x[1:], jnp.full(2, 0.01), jnp.full(1, 100.0)
    )  # a measurement too coarse to cut the prior
    turn = jnp.asarray([[1.0, -1.0], [1.0, 1.0]]) / jnp.sqrt(2.0)  # thin and at 45 degrees
    prior = Ellipsoid(jnp.zeros(2), turn @ jnp.diag(jnp.array([1.0, 1e-13])) @ turn.T)
    result = set_membership_filter(model, jnp.zeros((3, 1)), prior=prior)
    status = np.asarray(result.status)
    assert status[0] & Status.ILL_CONDITIONED and status[0] & Status.UNBOUNDED
    assert np.all(np.asarray(result.unbounded)) and not np.any(np.asarray(result.inconsistent))


def test_state_only_functions_scalar_measurements_and_predicted_sets():
    """f(x) and a scalar h(x) with ys of shape (T,) give what f(x, u) and a vector h give; the
    predicted sets saved on request are the prior and the time updates of the filtered sets; an
    h of the wrong shape is named before tracing."""
    with jax.enable_x64(True):
        pendulum = lambda x: jnp.stack([x[0] + 0.1 * x[1], x[1] - 0.1 * jnp.sin(x[0])])
        short = BoundedNoiseModel(pendulum, lambda x: jnp.sin(x[0]), [1e-3, 1e-3], [0.02])
        full = BoundedNoiseModel(
            lambda x, u: pendulum(x), lambda x, u: jnp.sin(x[:1]), [1e-3, 1e-3], [0.02]
        )
        prior = Ellipsoid(jnp.array([0.3, 0.0]), 0.01 * jnp.eye(2))
        ys = 0.3 * jnp.cos(0.3 * jnp.arange(40.0))
        fields = ("center", "shape", "status", "predicted_center", "predicted_shape")
        ours = set_membership_filter(short, ys, prior=prior, save=je.SaveAt(fields=fields))
        reference = set_membership_filter(full, ys[:, None], prior=prior)
        # Two programs, which XLA may fuse and round differently: after 40 steps of strip
        # intersections the shapes differed by up to 5e-13 (relative) under the suite's compile
        # flags (jaxest.xla_flags), under 1e-13 without them; a wrong bound or function moves them
        # by more than 1e-6.
        np.testing.assert_allclose(ours.shape, reference.shape, rtol=1e-11)
        np.testing.assert_allclose(ours.center, reference.center, rtol=1e-11)
        assert reference.predicted_shape is None  # not kept unless asked for
        np.testing.assert_array_equal(ours.predicted_shape[0], prior.shape)
        smf = SetMembershipFilter()
        for k in (0, 17, 38):
            step = smf.predict(short, Ellipsoid(ours.center[k], ours.shape[k]), None, k)
            np.testing.assert_allclose(ours.predicted_shape[k + 1], step.shape, rtol=1e-13)
            np.testing.assert_allclose(ours.predicted_center[k + 1], step.center, rtol=1e-13)
        wrong = BoundedNoiseModel(pendulum, lambda x: x, [1e-3, 1e-3], [0.02])
        with pytest.raises(ValueError, match=r"^model.h: expected it to return shape \(1,\)"):
            set_membership_filter(wrong, ys, prior=prior)
    # a float64 constant in h promoted a float32 run's sets: the step was blamed for its state
    f32 = lambda a: jnp.asarray(a, jnp.float32)
    promoting = BoundedNoiseModel(
        lambda x: x, lambda x: jnp.sin(x[:1]) + np.float64(0.1), f32([1e-3, 1e-3]), f32([0.02])
    )
    with pytest.raises(ValueError, match=r"^model.h: returns float64 for a float32 state"):
        set_membership_filter(
            promoting, f32(ys), prior=Ellipsoid(f32(prior.center), f32(prior.shape))
        )


def test_predict_and_contains_outside_jit_compile_one_program_each():
    """Called outside ``jit``, as in a notebook, ``predict`` and ``contains`` compile one program
    each (op by op, a first ``predict`` on the Duffing model compiled 154)."""
    model = BoundedNoiseModel(
        lambda x: 0.9 * x + 0.05 * x**2, lambda x: x[:2], [1e-3] * 3, [0.01, 0.01]
    )  # three states: a model no other test here runs
    prior = Ellipsoid(jnp.array([0.1, 0.2, 0.3]), 0.01 * jnp.eye(3))
    smf = SetMembershipFilter()
    assert programs_compiled(smf.predict, model, prior) <= 2
    result = set_membership_filter(model, 0.1 * jnp.ones((20, 2)), prior=prior)
    far = result.center + 10.0
    assert programs_compiled(result.contains, result.center) <= 2
    assert np.all(np.asarray(result.contains(result.center)))
    assert not np.any(np.asarray(result.contains(far)))


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_the_states_units_do_not_lose_the_set(dtype):
    """A damped pendulum with its rate in units 300 times smaller (every bound scaled alike) is
    the same system: its sets are those of the first in the new units, all bounded and holding
    the state. In float32 the conditioning check read P's own condition number, 9e4 for the
    prior, beyond kappa n eps <= 2^-10 (8 192): every set was declared unbounded from step 0."""
    units = jnp.asarray([1.0, 300.0], dtype)
    pendulum = lambda x: jnp.stack([x[0] + 0.1 * x[1], 0.95 * x[1] - 0.1 * jnp.sin(x[0])])
    in_units = lambda x: units * pendulum(x / units)
    rng = np.random.default_rng(3)
    states = [np.asarray([0.3, 0.1])]
    for _ in range(59):
        states.append(np.asarray(pendulum(states[-1])) + rng.uniform(-1e-3, 1e-3, 2))
    states = np.stack(states)
    ys = np.sin(states[:, :1]) + rng.uniform(-0.02, 0.02, (60, 1))
    results = []
    for scale, f in ((jnp.ones(2), pendulum), (units, in_units)):
        h = lambda x: jnp.sin(x[:1])  # the first state keeps its units
        model = BoundedNoiseModel(f, h, jnp.asarray(1e-3 * scale, dtype), jnp.full(1, 0.02, dtype))
        prior = Ellipsoid(
            (jnp.asarray([0.3, 0.1]) * scale).astype(dtype), jnp.diag(0.01 * scale**2).astype(dtype)
        )
        result = jax.jit(lambda ys: run(SetMembershipFilter(), model, ys, prior=prior))(
            jnp.asarray(ys, dtype)
        )
        assert not np.any(np.asarray(result.status)), np.asarray(result.status)
        assert np.all(np.asarray(result.contains(jnp.asarray(states * scale, dtype))))
        results.append(result)
    plain, scaled = results
    np.testing.assert_allclose(scaled.center / units, plain.center, rtol=1e-3, atol=1e-6)
    np.testing.assert_allclose(
        scaled.shape / (units[:, None] * units[None, :]), plain.shape, rtol=1e-3, atol=1e-9
    )
