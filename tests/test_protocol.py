"""The Core v2 protocol from outside the package: a new estimator is one subclass and gets
``run``, ``monte_carlo`` and ``fit``; associative estimators run in parallel; the caller chooses
what is saved; results resume; PRNG keys and ``throw`` come from the driver."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import jaxest as je
from jaxest.setmembership.status import SetStatus

DT = 0.5


class AlphaBetaState(eqx.Module):
    position: jax.Array
    velocity: jax.Array


class AlphaBetaOutput(eqx.Module):
    mean: jax.Array | None
    status: jax.Array | None


class AlphaBetaResult(je.AbstractResult):
    final_state: AlphaBetaState
    mean: jax.Array | None = None
    status: jax.Array | None = None
    any_status: jax.Array | None = None
    saved: object = None


class AlphaBetaTracker(je.AbstractEstimator):
    """Kalata's alpha-beta tracker: gains from the tracking index lambda = sigma_a T^2 / sigma_v
    of the model's (white-acceleration) Q and R; it is the steady-state Kalman filter of the
    constant-velocity model with G = [T^2/2, T]^T."""

    def gains(self, model):
        lam = jnp.sqrt(model.Q[0, 0]) * DT**2 / jnp.sqrt(model.R[0, 0])
        r = (4.0 + lam - jnp.sqrt(8.0 * lam + lam**2)) / 4.0
        alpha = 1.0 - r**2
        beta = 2.0 * (2.0 - alpha) - 4.0 * jnp.sqrt(1.0 - alpha)
        return alpha, beta

    def init(self, model, prior):
        return AlphaBetaState(prior.mean[0], prior.mean[1])

    def step(self, model, state, k, y, u, key):
        alpha, beta = self.gains(model)
        e = y[0] - state.position
        position = state.position + alpha * e
        velocity = state.velocity + beta / DT * e
        mean = jnp.stack([position, velocity])
        status = je.finite_status(mean)
        return AlphaBetaState(position + DT * velocity, velocity), AlphaBetaOutput(mean, status)

    def result(self, outputs, final_state):
        return AlphaBetaResult(final_state=final_state, mean=outputs.mean, status=outputs.status)


def constant_velocity(sigma_a=0.3, sigma_v=1.0):
    F = jnp.asarray([[1.0, DT], [0.0, 1.0]])
    G = jnp.asarray([[DT**2 / 2], [DT]])
    H = jnp.asarray([[1.0, 0.0]])
    return je.LinearGaussian(F, H, jnp.asarray([[sigma_a**2]]), jnp.asarray([[sigma_v**2]]), G=G)


PRIOR = je.Gaussian(jnp.zeros(2), 10.0 * jnp.eye(2))


def test_new_estimator_runs_through_run_monte_carlo_and_fit():
    model = constant_velocity()
    sim = je.simulate(model, PRIOR, 400, jax.random.PRNGKey(0))
    tracked = je.run(AlphaBetaTracker(), model, sim.y, prior=PRIOR)
    steady = je.run(je.SteadyStateKalmanFilter(), model, sim.y, prior=PRIOR)
    # Kalata's closed form is the steady-state Kalman filter of this model (independent check)
    np.testing.assert_allclose(tracked.mean, steady.mean, rtol=1e-9, atol=1e-9)
    assert bool(tracked.ok) and tracked.status.shape == (400,)

    final_errors = je.monte_carlo(
        lambda key: (
            je.run(AlphaBetaTracker(), model, (s := je.simulate(model, PRIOR, 100, key)).y,
                   prior=PRIOR).mean[-1] - s.states[-1]
        ),
        jax.random.PRNGKey(1),
        64,
    )  # fmt: skip
    assert final_errors.shape == (64, 2) and np.all(np.isfinite(final_errors))

    wrong = constant_velocity(sigma_a=3.0)  # ten times the true acceleration noise
    batch = je.monte_carlo(lambda key: je.simulate(model, PRIOR, 100, key), jax.random.key(2), 8)
    loss = je.supervised_mse(AlphaBetaTracker(), batch.y, batch.states, prior=PRIOR)
    fitted = je.fit(wrong, loss, ("Q",), optimizer=optax.adam(0.1), num_steps=60)
    assert fitted.losses[-1] < 0.9 * fitted.losses[0]
    assert abs(math.log(float(fitted.model.Q[0, 0]) / 0.09)) < abs(math.log(9.0 / 0.09))


class InformationElement(eqx.Module):
    """Information-form evidence about a constant theta: Lambda = sum H^T R^-1 H, eta = ..."""

    info: jax.Array
    vector: jax.Array


class LeastSquaresOutput(eqx.Module):
    mean: jax.Array | None
    prediction: jax.Array | None  # H_k theta(k-1), y_k's prediction: needs the previous prefix
    status: jax.Array | None


class LeastSquaresResult(je.AbstractResult):
    final_state: InformationElement
    mean: jax.Array | None = None
    prediction: jax.Array | None = None
    status: jax.Array | None = None
    any_status: jax.Array | None = None
    saved: object = None


class RecursiveLeastSquares(je.AbstractAssociativeEstimator):
    """theta from y_k = H_k theta + v_k: evidence adds up, so the steps are associative."""

    R: jax.Array

    def prior_element(self, model, prior):
        info = jnp.linalg.inv(prior.cov)
        return InformationElement(info, info @ prior.mean)

    def element(self, model, k, y, u):
        H = model[k]
        return InformationElement(
            H.T @ jnp.linalg.solve(self.R, H), H.T @ jnp.linalg.solve(self.R, y)
        )

    def combine(self, earlier, later):
        return InformationElement(earlier.info + later.info, earlier.vector + later.vector)

    def output(self, model, previous, prefix, k):
        mean = jnp.linalg.solve(prefix.info, prefix.vector)
        prediction = model[k] @ jnp.linalg.solve(previous.info, previous.vector)
        return LeastSquaresOutput(mean, prediction, je.finite_status(mean))

    def result(self, outputs, final_state):
        return LeastSquaresResult(final_state=final_state, mean=outputs.mean,
                                  prediction=outputs.prediction,
                                  status=outputs.status)  # fmt: skip


def test_associative_estimator_parallel_equals_sequential_and_batch_least_squares():
    rng = np.random.default_rng(0)
    T, p, m = 37, 3, 2
    Hs = jnp.asarray(rng.normal(size=(T, m, p)))
    theta = rng.normal(size=p)
    ys = jnp.asarray(np.einsum("tmp,p->tm", Hs, theta) + 0.1 * rng.normal(size=(T, m)))
    prior = je.Gaussian(jnp.zeros(p), 100.0 * jnp.eye(p))
    rls = RecursiveLeastSquares(0.01 * jnp.eye(m))
    parallel = je.run(rls, Hs, ys, prior=prior)
    sequential = je.run(rls, Hs, ys, prior=prior, parallel=False)
    np.testing.assert_allclose(parallel.mean, sequential.mean, rtol=1e-10)
    # output k sees the prefix before step k too: the prior mean at k = 0, then the estimate
    # from y_0..y_{k-1}, in both paths
    np.testing.assert_allclose(parallel.prediction, sequential.prediction, rtol=1e-10)
    np.testing.assert_allclose(parallel.prediction[0], Hs[0] @ prior.mean, atol=1e-12)
    before = np.einsum("tmp,tp->tm", Hs[1:], np.asarray(parallel.mean[:-1]))
    np.testing.assert_allclose(parallel.prediction[1:], before, rtol=1e-10)
    # the last estimate is the regularised batch least-squares solution
    A = np.concatenate([np.asarray(Hs).reshape(T * m, p), np.eye(p) * 0.1 / 10.0])  # whitened
    b = np.concatenate([np.asarray(ys).reshape(-1), np.zeros(p)])
    np.testing.assert_allclose(parallel.mean[-1], np.linalg.lstsq(A, b, rcond=None)[0], rtol=1e-9)
    with pytest.raises(ValueError, match="parallel"):
        je.run(je.KalmanFilter(), constant_velocity(), ys[:, :1], prior=PRIOR, parallel=True)


def linear_problem(T=60):
    model = constant_velocity()
    return model, je.simulate(model, PRIOR, T, jax.random.PRNGKey(3)).y


def test_save_chooses_what_is_kept():
    model, ys = linear_problem()
    full = je.run(je.SVDEKF(), model, ys, prior=PRIOR)
    lean = je.run(je.SVDEKF(), model, ys, prior=PRIOR, save=je.SaveAt(fields=()))
    assert lean.cov is None and lean.mean is None and lean.status is None
    np.testing.assert_allclose(lean.loglik, full.loglik, rtol=1e-12)
    np.testing.assert_allclose(lean.loglik, jnp.sum(full.loglik_terms), rtol=1e-12)
    assert int(lean.any_status) == 0 and bool(lean.ok)
    own = je.run(
        je.SVDEKF(), model, ys, prior=PRIOR,
        save=je.SaveAt(fields=("mean", "factor"), fn=lambda out: out.cov[0, 0]),
    )  # fmt: skip
    np.testing.assert_allclose(own.saved, full.cov[:, 0, 0], rtol=1e-12)
    # the parallel path applies fn per step too (it was given the stacked outputs at once)
    parallel = je.run(je.ParallelKalmanFilter(), model, ys, prior=PRIOR,
                      save=je.SaveAt(fields=(), fn=lambda out: out.mean[0]))  # fmt: skip
    np.testing.assert_allclose(parallel.saved, full.mean[:, 0], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(own.factor.cov, full.cov, rtol=1e-10, atol=1e-12)
    sqrt = je.run(je.SquareRootKF(), model, ys, prior=PRIOR, save=je.SaveAt(fields=("factor",)))
    np.testing.assert_allclose(sqrt.factor.cov, full.cov, rtol=1e-9, atol=1e-12)
    assert np.allclose(np.triu(np.asarray(sqrt.factor.chol[5]), 1), 0.0)
    with pytest.raises(ValueError, match="save"):
        je.run(je.KalmanFilter(), model, ys, prior=PRIOR, save=je.SaveAt(fields=("means",)))
    # a field name alone was read as its letters; a plain string raised an AttributeError
    assert je.SaveAt(fields="mean").fields == ("mean",)
    with pytest.raises(ValueError, match="^save: expected a jaxest.SaveAt or None, got str"):
        je.run(je.KalmanFilter(), model, ys, prior=PRIOR, save="mean")


@pytest.mark.parametrize("Filter", [je.KalmanFilter, je.SVDEKF, je.SquareRootKF])
def test_resume_from_final_state_equals_one_run(Filter):
    model, ys = linear_problem()
    whole = je.run(Filter(), model, ys, prior=PRIOR)
    first = je.run(Filter(), model, ys[:25], prior=PRIOR)
    rest = je.run(Filter(), model, ys[25:], state=first.final_state, k0=25)
    np.testing.assert_allclose(rest.mean, whole.mean[25:], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(rest.loglik, whole.loglik, rtol=1e-12)


def test_a_resumed_run_checks_its_arguments():
    """A run resumed from a state (no prior) skipped every check: a model with B run without its
    inputs gave means 5.6 off with status OK, ys one column too wide NaN means, inputs of the
    wrong length an unnamed scan error, a 1-D ys an IndexError. They are named as for a run
    from a prior, for the Gaussian filters and the particle filter."""
    model, ys = linear_problem()
    with_input = eqx.tree_at(lambda m: m.B, model, jnp.ones((2, 1)), is_leaf=lambda x: x is None)
    inputs = jnp.ones((ys.shape[0], 1))
    key = jax.random.key(0)
    for filt in (je.KalmanFilter(), je.UKF(), je.ParticleFilter(50)):
        first = je.run(filt, with_input, ys[:25], prior=PRIOR, inputs=inputs[:25], key=key)
        resume = lambda ys, inputs, filt=filt, state=first.final_state: je.run(
            filt, with_input, ys, state=state, k0=25, inputs=inputs, key=key
        )
        cases = (
            (ys[25:], None, "^inputs: the model has input matrices"),
            (jnp.concatenate([ys[25:], ys[25:]], axis=1), inputs[25:], "^ys: expected 1 column"),
            (ys[25:], inputs[25:30], "^inputs: has 5 time steps but the measurements have"),
            (ys[25:, 0], inputs[25:], r"^ys: expected shape \(T, d\)"),
            (ys[25:].at[3, 0].set(jnp.inf), inputs[25:], "^ys: contains"),
        )
        for bad_ys, bad_inputs, match in cases:
            with pytest.raises(ValueError, match=match):
                resume(bad_ys, bad_inputs)
        assert bool(resume(ys[25:], inputs[25:]).ok)


def test_a_prior_beside_a_state_is_refused_before_tracing():
    """``prior=`` beside ``state=`` was ignored without a word (the run resumed from the state);
    it is named before the estimator is traced. ``state=None`` beside a prior is a run from it."""
    model, ys = linear_problem()
    first = je.run(AlphaBetaTracker(), model, ys[:25], prior=PRIOR)
    traced = []

    class Traced(AlphaBetaTracker):
        def resume(self, model, state):
            traced.append(state)
            return state

    with pytest.raises(ValueError, match="^prior and state: a run starts from a prior or resumes"):
        je.run(Traced(), model, ys[25:], prior=PRIOR, state=first.final_state, k0=25)
    assert traced == []
    again = je.run(AlphaBetaTracker(), model, ys[:25], prior=PRIOR, state=None)
    np.testing.assert_array_equal(again.mean, first.mean)


def test_a_filter_resumes_from_another_filters_state():
    """Each Gaussian filter takes another's final state, whatever form holds P there (it raised
    a TypeError or AttributeError), the steady-state filter its mean; the particle filter draws
    its particles from a Gaussian filter's predicted state; states of another kind are named."""
    model, ys = linear_problem()
    whole = je.run(je.KalmanFilter(), model, ys, prior=PRIOR)
    handovers = [(je.KalmanFilter(), je.SquareRootKF()), (je.SquareRootKF(), je.SVDEKF()),
                 (je.SVDEKF(), je.InformationFilter()), (je.InformationFilter(), je.UKF()),
                 (je.UKF(form="sqrt"), je.ParallelKalmanFilter()),
                 (je.KalmanFilter(), je.ParallelKalmanFilter(square_root=False))]  # fmt: skip
    for before, after in handovers:
        first = je.run(before, model, ys[:25], prior=PRIOR)
        rest = je.run(after, model, ys[25:], state=first.final_state, k0=25)
        np.testing.assert_allclose(rest.mean, whole.mean[25:], rtol=1e-9, atol=1e-10)
        np.testing.assert_allclose(rest.loglik, whole.loglik, rtol=1e-10)
    first = je.run(je.SquareRootKF(), model, ys[:25], prior=PRIOR)
    # the steady-state filter takes the mean (and log-likelihood) and holds its own Sigma
    steady = je.run(je.SteadyStateKalmanFilter(), model, ys[25:], state=first.final_state, k0=25)
    fresh = je.run(je.SteadyStateKalmanFilter(), model, ys[25:],
                   prior=je.Gaussian(first.final_state.mean, PRIOR.cov))  # fmt: skip
    np.testing.assert_allclose(steady.mean, fresh.mean, rtol=1e-12)
    np.testing.assert_allclose(steady.loglik, first.loglik + fresh.loglik, rtol=1e-12)
    particles = je.run(je.ParticleFilter(4000), model, ys[25:], state=first.final_state, k0=25,
                       key=jax.random.key(0))  # fmt: skip
    spread = np.sqrt(np.diagonal(np.asarray(whole.cov[25:]), axis1=1, axis2=2))
    assert np.max(np.abs(particles.mean - whole.mean[25:]) / spread) < 0.2
    assert abs(float(particles.loglik - whole.loglik)) < 1.0
    with pytest.raises(ValueError, match="^state: KalmanFilter resumes from a Gaussian"):
        je.run(je.KalmanFilter(), model, ys[50:], state=particles.final_state, k0=50)
    with pytest.raises(ValueError, match="^state: holds 4000 particles, this ParticleFilter 10"):
        je.run(je.ParticleFilter(10), model, ys[50:], state=particles.final_state, k0=50,
               key=jax.random.key(1))  # fmt: skip


class NoisyTracker(AlphaBetaTracker):
    """An estimator that samples: it jitters its estimate with the step's key."""

    needs_key = True

    def step(self, model, state, k, y, u, key):
        state, out = super().step(model, state, k, y, u, key)
        return state, AlphaBetaOutput(out.mean + jax.random.normal(key, (2,)), out.status)


def test_driver_splits_the_key_per_step():
    model, ys = linear_problem()
    with pytest.raises(ValueError, match="key"):
        je.run(NoisyTracker(), model, ys, prior=PRIOR)
    a = je.run(NoisyTracker(), model, ys, prior=PRIOR, key=jax.random.key(0)).mean
    b = je.run(NoisyTracker(), model, ys, prior=PRIOR, key=jax.random.key(0)).mean
    c = je.run(NoisyTracker(), model, ys, prior=PRIOR, key=jax.random.key(1)).mean
    clean = je.run(AlphaBetaTracker(), model, ys, prior=PRIOR).mean
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)
    jitter = np.asarray(a - clean)
    assert abs(np.corrcoef(jitter[:-1, 0], jitter[1:, 0])[0, 1]) < 0.3  # fresh draws each step


def test_a_resumed_run_continues_the_draws_of_one_run():
    model, ys = linear_problem()
    key = jax.random.key(0)
    whole = je.run(NoisyTracker(), model, ys, prior=PRIOR, key=key)
    first = je.run(NoisyTracker(), model, ys[:25], prior=PRIOR, key=key)
    rest = je.run(NoisyTracker(), model, ys[25:], state=first.final_state, k0=25, key=key)
    np.testing.assert_allclose(rest.mean, whole.mean[25:], rtol=1e-12, atol=1e-12)


def test_throw_raises_with_advice():
    model, ys = linear_problem()
    bad = je.LinearGaussian(model.F, model.H, model.Q, jnp.asarray([[jnp.nan]]), G=model.G)
    quiet = jax.jit(lambda m: je.run(je.KalmanFilter(), m, ys, prior=PRIOR))(bad)
    assert not bool(quiet.ok) and "NONFINITE" in je.Status.describe(quiet.any_status)
    with pytest.raises(Exception, match="NONFINITE"):
        jax.jit(lambda m: je.run(je.KalmanFilter(), m, ys, prior=PRIOR, throw=True).mean)(bad)


class SetFamilyResult(AlphaBetaResult):
    flags = SetStatus


def _failure_message(function, *args) -> str:
    with pytest.raises(Exception) as raised:  # equinox's runtime error
        jax.block_until_ready(function(*args))
    return str(raised.value)


def test_throw_gives_the_advice_of_the_set_flags_only():
    """The message of ``throw=True`` / ``raise_if_failed`` gave the advice of every flag of the
    family, set or not; it gives that of each flag set in any run (under jit, under vmap and
    over a batch axis) and no other."""
    from jaxest._status import ADVICE

    def failed(code, family=SetFamilyResult):
        return je.raise_if_failed(family(final_state=None, any_status=code)).any_status

    def check(message, set_flags):
        for flag in SetStatus:
            advice = f"{flag.name}: {ADVICE[flag.name]}"
            assert (advice in message) is (flag in set_flags), (flag, message)

    single = int(SetStatus.NOT_POSITIVE_DEFINITE)
    check(_failure_message(jax.jit(failed), jnp.int32(single)), {SetStatus.NOT_POSITIVE_DEFINITE})
    two = SetStatus.EMPTY_SET | SetStatus.RECOVERED
    check(_failure_message(failed, jnp.int32(two)), {SetStatus.EMPTY_SET, SetStatus.RECOVERED})
    runs = jnp.asarray([0, SetStatus.UNBOUNDED, SetStatus.NONFINITE], jnp.int32)
    for batched in (jax.jit(jax.vmap(failed)), failed):
        check(_failure_message(batched, runs), {SetStatus.UNBOUNDED, SetStatus.NONFINITE})
    # bits of no flag of the family (64 is not a Status flag): named as such, no advice
    foreign = _failure_message(lambda c: failed(c, AlphaBetaResult), jnp.int32(64))
    assert "not Status's" in foreign and not any(a in foreign for a in ADVICE.values())
    assert int(failed(jnp.int32(0))) == 0


def test_status_flags_extend_per_family():
    Family = je.Status.extend("Family", STUCK=(64, "unstick it"))
    assert Family.NONFINITE == je.Status.NONFINITE and Family.STUCK == 64
    assert Family.describe(65) == "NONFINITE, STUCK" and je.Status.describe(0) == "OK"
    # read with the core's flags, a family's bit is named, not described as OK (it was)
    assert je.Status.describe(65) == "NONFINITE, bits 64 not in Status (another family's flags)"
    assert "unstick it" in Family.explain(64)
    with pytest.raises(ValueError, match="STUCK"):
        je.Status.extend("Clash", STUCK=(2, "taken"))


def test_every_result_with_a_status_answers_as_an_estimators_does():
    """A smoother's, a simulation's, EM's, ``fit``'s and a Riccati solution's result have
    ``any_status`` (the steps' flags OR'ed), ``ok`` and ``flags`` as an estimator's result has,
    so ``raise_if_failed`` takes each (it refused them as not a jaxest result; the network
    filter's designs are checked in test_network); a smoother's
    flags are its filter's family, whose bits its status carries."""
    model, ys = linear_problem(T=20)
    parallel = je.run(je.ParallelKalmanFilter(), model, ys, prior=PRIOR)
    Q = model.G @ model.Q @ model.G.T
    plain = je.LinearGaussian(model.F, model.H, Q + 1e-3 * jnp.eye(2), model.R)  # G = I, for EM
    results = {
        "simulation": je.simulate(model, PRIOR, 20, jax.random.PRNGKey(0)),
        "smoother": je.rts_smooth(model, parallel),
        "iterated smoother": je.iterated_smooth(model, ys, prior=PRIOR, num_iters=2),
        "steady-state smoother": je.steady_state_smooth(model, ys, prior=PRIOR),
        "EM": je.fit_em(plain, ys, prior=PRIOR, num_iters=2),
        "fit": je.fit(model, je.neg_loglik(je.KalmanFilter(), ys[None], prior=PRIOR), num_steps=2),
        "Riccati": je.solve_filter_dare(model.F, model.H, Q, model.R),
        "steady-state gain": je.steady_state_gain(plain),
    }
    assert results["smoother"].flags is je.ParallelStatus is results["iterated smoother"].flags
    assert results["EM"].flags is je.EMStatus and results["Riccati"].flags is je.RiccatiStatus
    for name, result in results.items():
        steps = jnp.atleast_1d(result.status)
        assert int(result.any_status) == int(np.bitwise_or.reduce(np.asarray(steps))) == 0, name
        assert bool(result.ok) and isinstance(je.raise_if_failed(result), type(result)), name
        flag = max(result.flags)  # the family's own bit where it has one
        where = (lambda r: r.smoothed.status) if name == "iterated smoother" else None
        flagged = eqx.tree_at(where or (lambda r: r.status), result, replace_fn=lambda s: s | flag)
        assert int(flagged.any_status) == flag and not bool(flagged.ok), name
        with pytest.raises(Exception, match=flag.name):
            je.raise_if_failed(flagged)


@pytest.mark.parametrize("dtype, rtol", [(jnp.float64, 1e-12), (jnp.float32, 1e-5)])
def test_checkpoint_stores_less_and_changes_no_value_or_gradient(dtype, rtol):
    """``checkpoint=True`` recomputes each step in the reverse pass: the same loss and gradient
    (under jit and vmap) from a compiled gradient that keeps a fraction of the intermediates."""
    from jaxest.systems.duffing import Duffing

    identity = lambda x, u=None: x
    Q, R = 1e-5 * jnp.eye(2, dtype=dtype), 1e-4 * jnp.eye(2, dtype=dtype)
    prior = je.Gaussian(jnp.asarray([0.2, 0.3], dtype), 0.01 * jnp.eye(2, dtype=dtype))
    truth = je.NonlinearGaussian(Duffing(), identity, Q, R)
    ys = je.simulate(truth, prior, 400, jax.random.PRNGKey(1)).y

    def loss(q_scale, checkpoint):
        model = je.NonlinearGaussian(Duffing(), identity, q_scale * Q, R)
        result = je.run(je.EKF(), model, ys, prior=prior, checkpoint=checkpoint)
        return result.loglik + jnp.sum(result.mean)

    scales = jnp.asarray([0.5, 1.3, 2.0], dtype)
    value_and_grad = {
        ck: jax.jit(jax.vmap(jax.value_and_grad(loss), (0, None)), static_argnums=1)
        for ck in (False, True)
    }
    stored, recomputed = (value_and_grad[ck](scales, ck) for ck in (False, True))
    for a, b in zip(recomputed, stored, strict=True):
        assert a.dtype == dtype
        np.testing.assert_allclose(a, b, rtol=rtol)
    temp = {
        ck: value_and_grad[ck].lower(scales, ck).compile().memory_analysis().temp_size_in_bytes
        for ck in (False, True)
    }
    assert temp[True] < temp[False] / 4


def _gradient_temp_bytes(estimator, model, ys, prior, checkpoint) -> int:
    """Temporary memory of the compiled gradient of ``run``'s log-likelihood (or, for an
    estimator without one, its means' sum) with respect to the model's Q."""

    def loss(Q):
        result = je.run(
            estimator, eqx.tree_at(lambda m: m.Q, model, Q), ys, prior=prior,
            checkpoint=checkpoint,
        )  # fmt: skip
        return result.loglik if hasattr(result, "loglik") else result.mean.sum()

    grad = jax.jit(jax.grad(loss))
    return grad.lower(model.Q).compile().memory_analysis().temp_size_in_bytes


def test_checkpoint_defaults_to_the_estimators_choice():
    """``checkpoint=None`` (the default) is the estimator's ``checkpoint_by_default``: the EKF's
    and the SVD-EKF's compiled gradients store what ``checkpoint=True`` stores, the alpha-beta
    tracker's what ``checkpoint=False`` stores; an associative estimator runs in parallel
    without complaint."""
    model = constant_velocity()
    ys = je.simulate(model, PRIOR, 400, jax.random.PRNGKey(3)).y
    for estimator, default in ((je.EKF(), True), (je.SVDEKF(), True), (AlphaBetaTracker(), False)):
        assert estimator.checkpoint_by_default is default
        temp = {
            ck: _gradient_temp_bytes(estimator, model, ys, PRIOR, ck) for ck in (None, True, False)
        }
        assert temp[True] < temp[False]  # the two settings compile differently here
        assert temp[None] == temp[default]
    assert je.UKF().checkpoint_by_default and je.IteratedEKF().checkpoint_by_default
    assert je.EKF().checkpoint_policy is None  # recomputes everything
    # P held as SVD factors: recomputed, keeping the factors of the forward pass (they are not
    # unique; the property's docstring says why)
    for svd_form in (je.UKF(form="svd"), je.SVDEKF(), je.ImprovedSVDKF()):
        assert svd_form.checkpoint_by_default and svd_form.checkpoint_policy is not None
    for square_root in (je.UKF(form="sqrt"), je.SquareRootKF()):  # measured no faster
        assert not square_root.checkpoint_by_default
    parallel = je.run(je.ParallelKalmanFilter(), model, ys, prior=PRIOR)
    sequential = je.run(je.KalmanFilter(), model, ys, prior=PRIOR)
    np.testing.assert_allclose(parallel.loglik, sequential.loglik, rtol=1e-9)


def test_checkpoint_is_checked_before_tracing():
    model, ys = linear_problem()
    with pytest.raises(ValueError, match="^checkpoint: expected True, False or None"):
        je.run(je.KalmanFilter(), model, ys, prior=PRIOR, checkpoint="yes")
    with pytest.raises(ValueError, match="^checkpoint: .*parallel=False"):
        je.run(je.ParallelKalmanFilter(), model, ys, prior=PRIOR, checkpoint=True)
    sequential = je.run(je.ParallelKalmanFilter(), model, ys, prior=PRIOR, parallel=False)
    checkpointed = je.run(
        je.ParallelKalmanFilter(), model, ys, prior=PRIOR, parallel=False, checkpoint=True
    )
    np.testing.assert_allclose(checkpointed.loglik, sequential.loglik, rtol=1e-12)


class FloatStatus(AlphaBetaTracker):
    def step(self, model, state, k, y, u, key):
        state, output = super().step(model, state, k, y, u, key)
        return state, AlphaBetaOutput(output.mean, output.status.astype(float))


class GrowingState(AlphaBetaTracker):
    def step(self, model, state, k, y, u, key):
        state, output = super().step(model, state, k, y, u, key)
        return AlphaBetaState(jnp.stack([state.position] * 2), state.velocity), output


class ThreeOutputs(AlphaBetaTracker):
    def step(self, model, state, k, y, u, key):
        return (*super().step(model, state, k, y, u, key), None)


def test_a_step_that_breaks_the_protocol_is_named():
    """A float or int64 status, a state that changes shape, a step that returns three things:
    JAX's errors from inside the scan named a carry ("carry[0]") or bitwise_or's dtype."""
    model, ys = constant_velocity(), jnp.zeros((5, 1))
    for estimator, message in [
        (FloatStatus(), r"FloatStatus.step's output.status must be an int32 scalar .*float64\[\]"),
        (GrowingState(), r"GrowingState.step changed its state.position from float64\[\] to "
                         r"float64\[2\]"),
        (ThreeOutputs(), r"ThreeOutputs.step must return \(state, output\), got a tuple of 3"),
    ]:  # fmt: skip
        with pytest.raises(ValueError, match="^estimator: " + message):
            je.run(estimator, model, ys, prior=PRIOR)


class BoolStatus(AlphaBetaTracker):
    def step(self, model, state, k, y, u, key):
        state, output = super().step(model, state, k, y, u, key)
        return state, AlphaBetaOutput(output.mean, ~jnp.all(jnp.isfinite(output.mean)))


class BoolStatusLeastSquares(RecursiveLeastSquares):
    def output(self, model, previous, prefix, k):
        output = super().output(model, previous, prefix, k)
        return LeastSquaresOutput(output.mean, output.prediction, output.status != 0)


def test_a_bool_status_is_named():
    """A bool status ran sequentially, its True read as NONFINITE whatever the step meant by it
    (its stacked status a bool array), and failed in parallel with lax.reduce's dtype error."""
    model = constant_velocity()
    ys = je.simulate(model, PRIOR, 10, jax.random.PRNGKey(0)).y
    message = r"^estimator: {}.step's output.status must be an int32 scalar .*got bool\[\]"
    with pytest.raises(ValueError, match=message.format("BoolStatus")):
        je.run(BoolStatus(), model, ys, prior=PRIOR)
    Hs = jnp.asarray(np.random.default_rng(0).normal(size=(10, 1, 2)))
    prior = je.Gaussian(jnp.zeros(2), jnp.eye(2))
    for parallel in (True, False):
        with pytest.raises(ValueError, match=message.format("BoolStatusLeastSquares")):
            je.run(BoolStatusLeastSquares(jnp.eye(1)), Hs, ys, prior=prior, parallel=parallel)


class TupleResult(AlphaBetaTracker):
    def result(self, outputs, final_state):
        return outputs.mean, final_state


def test_a_result_that_is_not_a_jaxest_result_is_named():
    """``result`` returning something else than an AbstractResult failed with an AttributeError
    from inside run (a tuple has no any_status)."""
    with pytest.raises(ValueError, match=r"^estimator: TupleResult.result must return a jaxest"
                                         r".AbstractResult .*got tuple"):  # fmt: skip
        je.run(TupleResult(), constant_velocity(), jnp.zeros((5, 1)), prior=PRIOR)


@pytest.mark.slow
def test_the_documented_ensemble_filter_runs_and_approaches_the_kalman_filter():
    """docs/estimators.md's code, run as written: its ensemble Kalman filter through run,
    monte_carlo and neg_loglik with a key, within half a standard deviation of the Kalman filter
    at 2000 members."""
    import re
    from pathlib import Path

    page = (Path(__file__).resolve().parents[1] / "docs" / "estimators.md").read_text()
    namespace = {"__name__": "docs_estimators"}
    exec(compile("\n".join(re.findall(r"```python\n(.*?)```", page, re.S)), "estimators.md", "exec"),
         namespace)  # fmt: skip
    assert float(namespace["error"]) < 0.5
    assert abs(float(namespace["ensemble"].loglik - namespace["kalman"].loglik)) < 2.0
    assert namespace["runs"].shape == (20, 100, 2) and int(namespace["ensemble"].any_status) == 0
    assert np.isfinite(float(jax.grad(namespace["loss"])(namespace["model"]).R[0, 0]))
