"""Bad input raises ValueError naming the argument, before anything is traced."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxest as je
from jaxest.filters import SVDEKF, KalmanFilter
from jaxest.setmembership import SetMembershipFilter
from tests.registry import GAUSSIAN_FILTERS, NEED_POSITIVE_Q


def good():
    model = je.LinearGaussian(0.9 * jnp.eye(2), jnp.ones((1, 2)), 0.1 * jnp.eye(2), jnp.eye(1))
    return model, jnp.zeros((10, 1)), je.Gaussian(jnp.zeros(2), jnp.eye(2))


def test_good_arguments_pass():
    model, ys, prior = good()
    # and raise no DeprecationWarning (pyproject.toml makes those of jaxest's calls errors): the
    # matrices a model leaves out (G, B, D: None) went to jnp.ndim, which a later JAX refuses
    assert je.run(KalmanFilter(), model, ys, prior=prior).mean.shape == (10, 2)


@pytest.mark.parametrize(
    "change, match",
    [
        (lambda m, y, p: (m, y[:, :, None], p), "ys"),
        (lambda m, y, p: (m, jnp.zeros((10, 3)), p), r"ys: expected 1 column\(s\)"),
        (lambda m, y, p: (je.LinearGaussian(jnp.eye(3), m.H, m.Q, m.R), y, p), "model.F"),
        (lambda m, y, p: (je.LinearGaussian(m.F, jnp.ones((1, 3)), m.Q, m.R), y, p), "model.H"),
        (lambda m, y, p: (je.LinearGaussian(m.F, m.H, jnp.ones((2, 3)), m.R), y, p), "model.Q"),
        (
            lambda m, y, p: (
                je.LinearGaussian(m.F, m.H, jnp.asarray([[1.0, 0.5], [0.0, 1.0]]), m.R),
                y,
                p,
            ),
            "model.Q: must be symmetric",
        ),
        (
            lambda m, y, p: (
                je.LinearGaussian(m.F, m.H, jnp.asarray([[1.0, 2.0], [2.0, 1.0]]), m.R),
                y,
                p,
            ),
            "model.Q: must be positive",
        ),
        (
            lambda m, y, p: (je.LinearGaussian(m.F, m.H, m.Q, -m.R), y, p),
            "model.R: must be positive definite",
        ),
        (
            lambda m, y, p: (je.LinearGaussian(m.F, m.H, m.Q.at[0, 0].set(jnp.nan), m.R), y, p),
            "model.Q: contains NaN",
        ),
        (
            lambda m, y, p: (
                m,
                y,
                je.Gaussian(jnp.zeros(2), jnp.asarray([[1.0, 0.0], [0.0, jnp.nan]])),
            ),
            "prior.cov: contains NaN",
        ),
        (lambda m, y, p: (m, y, je.Gaussian(jnp.zeros(2), jnp.ones((2, 3)))), "prior.cov"),
        # a NaN prior mean ran, status NONFINITE; the lists below raised TypeErrors from inside
        (lambda m, y, p: (m, y, je.Gaussian(p.mean.at[1].set(jnp.nan), p.cov)), "prior.mean: con"),
        (lambda m, y, p: (m, y.tolist(), p), "^ys: expected an array, got list"),
        (lambda m, y, p: (m, y, je.Gaussian([0.0, 0.0], p.cov)), "^prior.mean: expected an array"),
        (lambda m, y, p: (m, y, je.Gaussian(p.mean, p.cov.tolist())), "^prior.cov: expected an"),
        (
            lambda m, y, p: (je.LinearGaussian(m.F.tolist(), m.H, m.Q, m.R), y, p),
            "^model.F: expected an array, got list",  # it blamed prior.mean
        ),
        (
            lambda m, y, p: (je.LinearGaussian(m.F, m.H, m.Q.tolist(), m.R), y, p),
            "^model.Q: expected an array, got list",  # so did it for Q, R, G, B and D
        ),
        (lambda m, y, p: (m, y, je.Gaussian(jnp.zeros(3), jnp.eye(3))), "prior.mean"),
        (lambda m, y, p: (m, y, (p.mean, p.cov)), "prior"),
        (
            lambda m, y, p: (je.LinearGaussian(jnp.stack([m.F] * 5), m.H, m.Q, m.R), y, p),
            "model.F: time-varying",
        ),
    ],
)
def test_bad_arguments_name_the_argument(change, match):
    model, ys, prior = change(*good())
    with pytest.raises(ValueError, match=match):
        je.run(SVDEKF(), model, ys, prior=prior)


def test_mismatched_input_length():
    model, ys, prior = good()
    model = je.LinearGaussian(model.F, model.H, model.Q, model.R, B=jnp.ones((2, 1)))
    with pytest.raises(ValueError, match="inputs: has 4 time steps but the measurements have 10"):
        je.run(KalmanFilter(), model, ys, inputs=jnp.zeros((4, 1)), prior=prior)
    # one input for the whole run, with no time axis: the message says how to give one per step
    with pytest.raises(ValueError, match=r"has 1 time steps .* jnp\.broadcast_to\(u, \(T,\)"):
        je.run(KalmanFilter(), model, ys, inputs=jnp.ones((1,)), prior=prior)
    # inputs too narrow for the model: the state alone was blamed
    B = jnp.ones((2, 2))
    narrow = je.NonlinearGaussian(lambda x, u: x + B @ u, lambda x, u: x[:1], model.Q, model.R)
    with pytest.raises(ValueError, match=r"^prior.mean or inputs: .* u of shape \(1,\)"):
        je.run(je.EKF(), narrow, ys, inputs=jnp.zeros((10, 1)), prior=prior)


def test_inputs_may_be_a_pytree_and_missing_inputs_are_named():
    """simulate took inputs as a dict of arrays and run refused them ("expected shape (T, d),
    got ()"); a model that reads u, given no inputs, was blamed on prior.mean."""
    T = 12
    f_dict = lambda x, u: jnp.array([0.9 * x[0] + 0.1 * jnp.sin(x[1]), 0.8 * x[1]]) + u["b"]
    f_array = lambda x, u: jnp.array([0.9 * x[0] + 0.1 * jnp.sin(x[1]), 0.8 * x[1]]) + u
    h_dict = lambda x, u: x[:1] ** 3 / 10 + x[1:] * u["a"]
    h_array = lambda x, u: x[:1] ** 3 / 10 + x[1:] * 2.0  # u["a"] is 2 throughout
    cov = 0.1 * jnp.eye(2), 0.5 * jnp.eye(1)
    by_dict, by_array = (
        je.NonlinearGaussian(f_dict, h_dict, *cov),
        je.NonlinearGaussian(f_array, h_array, *cov),
    )
    prior = je.Gaussian(jnp.zeros(2), jnp.eye(2))
    b = jnp.asarray(np.random.default_rng(0).normal(size=(T, 2)))
    inputs = {"a": jnp.full((T,), 2.0), "b": b}
    ys = je.simulate(by_dict, prior, T, jax.random.key(0), inputs=inputs).y
    filtered = je.run(je.EKF(), by_dict, ys, prior=prior, inputs=inputs)
    reference = je.run(je.EKF(), by_array, ys, prior=prior, inputs=b)
    np.testing.assert_allclose(filtered.mean, reference.mean, rtol=1e-12)
    smoothed = je.rts_smooth(by_dict, filtered, inputs=inputs)
    np.testing.assert_allclose(smoothed.mean, je.rts_smooth(by_array, reference, inputs=b).mean,
                               rtol=1e-12)  # fmt: skip
    with pytest.raises(ValueError, match=r"^inputs\['b'\]: has 5 time steps but the measurements"):
        je.run(je.EKF(), by_dict, ys, prior=prior, inputs={**inputs, "b": b[:5]})
    with pytest.raises(ValueError, match=r"^inputs\['a'\]: expected a leading time axis"):
        je.simulate(by_dict, prior, T, jax.random.key(0), inputs={**inputs, "a": 2.0})
    # a NaN input made every later estimate NaN, flagged only as NONFINITE
    gappy = {**inputs, "b": b.at[3, 1].set(jnp.nan)}
    for call in (
        lambda: je.run(je.EKF(), by_dict, ys, prior=prior, inputs=gappy),
        lambda: je.simulate(by_dict, prior, T, jax.random.key(0), inputs=gappy),
        lambda: je.rts_smooth(by_dict, filtered, inputs=gappy),
    ):
        with pytest.raises(ValueError, match=r"^inputs\['b'\]: has NaN or infinite entries"):
            call()
    with pytest.raises(ValueError, match="^inputs: the model cannot be evaluated with u = None"):
        je.run(je.EKF(), by_array, ys, prior=prior)
    with pytest.raises(ValueError, match="^inputs: the model cannot be evaluated with u = None"):
        je.simulate(by_dict, prior, T, jax.random.key(0))
    linear = je.LinearGaussian(0.9 * jnp.eye(2), jnp.ones((1, 2)), *cov, B=jnp.eye(2))
    with pytest.raises(ValueError, match=r"^inputs: a linear model's inputs are a \(T, p\) array"):
        je.run(je.KalmanFilter(), linear, ys, prior=prior, inputs={"b": b})


def test_inputs_to_a_linear_model_without_input_matrices_are_rejected():
    # they were ignored without a word: the estimates came out as if there were no inputs
    model, ys, prior = good()
    with pytest.raises(ValueError, match=r"^inputs: the model has no input matrices"):
        je.run(KalmanFilter(), model, ys, inputs=jnp.ones((10, 1)), prior=prior)
    with pytest.raises(ValueError, match=r"^inputs: the model has no input matrices"):
        je.simulate(model, prior, 10, jax.random.key(0), inputs=jnp.ones((10, 1)))
    # and the other way round: B without inputs was ignored as silently
    driven = je.LinearGaussian(model.F, model.H, model.Q, model.R, B=jnp.ones((2, 1)))
    with pytest.raises(ValueError, match=r"^inputs: the model has input matrices"):
        je.run(KalmanFilter(), driven, ys, prior=prior)
    with pytest.raises(ValueError, match=r"^inputs: the model has input matrices"):
        je.simulate(driven, prior, 10, jax.random.key(0))


def test_input_matrices_must_fit_the_inputs_width_and_the_state():
    """B (n x p) and D (m x p) against the inputs' width p: a B of one column with two inputs
    took their sum (the product broadcast the size 1), with status OK."""
    model, ys, prior = good()
    two = jnp.ones((10, 2))
    cases = [
        (dict(B=jnp.ones((2, 1))), two, r"^model.B: expected trailing shape \(2, 2\)"),
        (
            dict(B=jnp.ones((2, 2))),
            jnp.ones((10, 1)),
            r"^model.B: expected trailing shape \(2, 1\)",
        ),
        (dict(B=jnp.ones((1, 2))), two, r"^model.B: expected trailing shape \(2, 2\)"),
        (dict(D=jnp.ones((1, 1))), two, r"^model.D: expected trailing shape \(1, 2\)"),
    ]
    for matrices, inputs, message in cases:
        wrong = je.LinearGaussian(model.F, model.H, model.Q, model.R, **matrices)
        with pytest.raises(ValueError, match=message):
            je.run(KalmanFilter(), wrong, ys, inputs=inputs, prior=prior)
        with pytest.raises(ValueError, match=message):
            je.simulate(wrong, prior, 10, jax.random.key(0), inputs=inputs)
    fits = je.LinearGaussian(model.F, model.H, model.Q, model.R, B=jnp.ones((2, 2)))
    assert bool(je.run(KalmanFilter(), fits, ys, inputs=two, prior=prior).ok)


def test_dtypes_that_do_not_fit_are_named():
    """A float32 prior with a float64 model, an integer prior mean or covariance and complex
    measurements raised a TypeError from inside the scan (the state changed dtype after one
    step), and the parallel filter returned a complex log-likelihood."""
    model, ys, prior = good()
    narrow = je.Gaussian(prior.mean.astype(jnp.float32), prior.cov.astype(jnp.float32))
    integer = je.Gaussian(jnp.zeros(2, jnp.int32), prior.cov)
    integer_cov = je.Gaussian(prior.mean, jnp.eye(2, dtype=jnp.int32))
    for estimator in (KalmanFilter(), je.ParallelKalmanFilter()):
        with pytest.raises(ValueError, match="^prior: is float32, narrower than"):
            je.run(estimator, model, ys, prior=narrow)
        with pytest.raises(ValueError, match="^prior.mean: must be real floating point"):
            je.run(estimator, model, ys, prior=integer)
        with pytest.raises(ValueError, match="^prior.cov: must be real floating point"):
            je.run(estimator, model, ys, prior=integer_cov)
        with pytest.raises(ValueError, match="^ys: must be real"):
            je.run(estimator, model, ys.astype(jnp.complex128), prior=prior)
    single = je.astype((model, ys, prior), jnp.float32)
    assert bool(je.run(KalmanFilter(), single[0], single[1], prior=single[2]).ok)


def test_simulate_draws_a_singular_noise_and_names_bad_covariances():
    """A noise that drives some states only (Q of rank one, or zero) has no Cholesky factor:
    the simulation was all NaN. It now draws from the eigendecomposition, on the line Q spans
    with its variance; a positive definite Q draws as before; an indefinite or misshapen Q, R
    or x0 is named (they gave NaN or a TypeError from the trace)."""
    from jaxest.models import gaussian_noise

    v = jnp.asarray([0.6, -0.8])
    line = je.LinearGaussian(jnp.zeros((2, 2)), jnp.ones((1, 2)), jnp.outer(v, v), jnp.eye(1))
    states = np.asarray(je.simulate(line, jnp.zeros(2), 4000, jax.random.key(0)).states[1:])
    # on the line: off it by the rounding of v v^T (an eigenvalue of 5.6e-17, a std of 7e-9)
    np.testing.assert_allclose(states @ np.asarray([0.8, 0.6]), 0.0, atol=1e-7)
    assert abs(np.var(states @ np.asarray(v)) - 1.0) < 0.1  # 4000 draws: s.e. of 0.022
    still = je.LinearGaussian(jnp.eye(2), jnp.ones((1, 2)), jnp.zeros((2, 2)), jnp.eye(1))
    np.testing.assert_array_equal(je.simulate(still, jnp.ones(2), 5, jax.random.key(1)).states, 1.0)
    cov, key = jnp.asarray([[2.0, 0.3], [0.3, 1.0]]), jax.random.key(2)
    np.testing.assert_array_equal(
        gaussian_noise(key, cov), jnp.linalg.cholesky(cov) @ jax.random.normal(key, (2,))
    )
    model, _, prior = good()
    flip = jnp.diag(jnp.asarray([1.0, -1.0]))
    cases = [
        (je.LinearGaussian(model.F, model.H, flip * model.Q, model.R), prior, "^model.Q: must be"),
        (je.LinearGaussian(model.F, model.H, model.Q, -model.R), prior, "^model.R: must be"),
        (je.LinearGaussian(model.F, jnp.ones((1, 3)), model.Q, model.R), prior, "^model.H: expected"),
        (model, je.Gaussian(prior.mean, flip), "^x0.cov: must be"),
        (model, prior.mean.at[0].set(jnp.nan), "^x0: contains NaN"),
    ]  # fmt: skip
    for bad, start, message in cases:
        with pytest.raises(ValueError, match=message):
            je.simulate(bad, start, 5, jax.random.key(0))


def test_float32_products_of_low_rank_are_semidefinite_to_their_precision():
    """G Q G^T (G 2 x 1) and g g^T formed in float32 have an eigenvalue of -1.7e-9 and -5e-10,
    which the float64 tolerance (1e-12 of the largest entry) refused: steady_state_smooth
    rejected a model KalmanFilter runs. A float32 matrix indefinite beyond its rounding still
    is named."""
    f32 = lambda a: jnp.asarray(a, jnp.float32)
    model = je.LinearGaussian(
        f32([[0.9, 0.1], [0.0, 0.7]]), f32([[1.0, 0.0]]), f32([[1.3]]), f32([[0.5]]),
        G=f32([[0.3], [0.7]]),
    )  # fmt: skip
    prior = je.Gaussian(f32([0.0, 0.0]), f32(np.eye(2)))
    je.steady_state_smooth(model, f32(np.ones((5, 1))), prior=prior)
    g = np.array([[0.1], [0.5]])
    line = je.LinearGaussian(model.F, model.H, f32(g @ g.T), model.R)
    je.simulate(line, prior, 3, jax.random.key(0))
    with pytest.raises(ValueError, match="^model.Q: must be positive semidefinite"):
        je.simulate(eqx.tree_at(lambda m: m.Q, line, f32([[1.0, 0.0], [0.0, -1e-4]])), prior, 3,
                    jax.random.key(0))  # fmt: skip


def test_simulate_under_jit_flags_what_the_checks_cannot_see():
    """Under ``jit`` an indefinite Q or R is a tracer the checks above cannot read: its draws are
    NaN, and a NaN measurement would pass as a missing one. The simulation's status says so
    from the first step each reaches; a valid model's is OK throughout."""
    model, _, prior = good()
    flip = jnp.diag(jnp.asarray([1.0, -1.0]))

    @jax.jit
    def status(Q, R):
        sim = je.simulate(
            je.LinearGaussian(model.F, model.H, Q, R), prior.mean, 6, jax.random.key(0)
        )
        return sim.status, sim.ok

    steps, ok = status(model.Q, model.R)
    assert bool(ok) and np.all(np.asarray(steps) == je.Status.OK)
    steps, ok = status(model.Q, -model.R)  # every y is NaN
    assert not bool(ok) and np.all(np.asarray(steps) == je.Status.NONFINITE)
    steps, ok = status(flip * model.Q, model.R)  # NaN from x_1 on (x_0 is given)
    assert not bool(ok)
    np.testing.assert_array_equal(np.asarray(steps), [0] + [je.Status.NONFINITE] * 5)


def test_simulate_names_an_initial_state_of_the_wrong_size():
    model, _, _ = good()  # it raised a TypeError from inside the traced scan
    with pytest.raises(ValueError, match=r"^x0: expected shape \(2,\)"):
        je.simulate(model, jnp.zeros(3), 5, jax.random.key(0))
    as_list = je.simulate(model, [1.0, 2.0], 5, jax.random.key(0))  # a list is an initial state
    np.testing.assert_array_equal(as_list.states[0], [1.0, 2.0])
    listed = je.LinearGaussian(model.F.tolist(), model.H, model.Q, model.R)
    with pytest.raises(ValueError, match="^model.F: expected an array, got list"):  # had no shape
        je.simulate(listed, jnp.zeros(2), 5, jax.random.key(0))


def test_time_varying_matrices_must_cover_the_steps_a_run_reads():
    """F[k] past the end of F's time axis reads the last F (JAX clamps indices): a resumed run
    (whose estimator checks are skipped), a model sliced to the remaining steps and a longer
    simulation ran without a word."""
    model, ys, prior = good()
    varying = je.LinearGaussian(jnp.stack([0.9 * jnp.eye(2)] * 10), model.H, model.Q, model.R)
    head = je.run(KalmanFilter(), varying, ys[:5], prior=prior)
    resume = lambda m, y, k0: je.run(KalmanFilter(), m, y, state=head.final_state, k0=k0)
    assert resume(varying, ys[5:], 5).mean.shape == (5, 2)
    with pytest.raises(ValueError, match=r"^model.F: .* fewer than steps 5..14 \(k0 = 5"):
        resume(varying, ys, 5)
    sliced = je.LinearGaussian(varying.F[5:], model.H, model.Q, model.R)
    with pytest.raises(ValueError, match=r"^model.F: time-varying with 5 steps"):
        resume(sliced, ys[5:], 5)
    for bad in (-1, 2.5, True):
        with pytest.raises(ValueError, match="^k0"):
            resume(varying, ys[5:], bad)
    with pytest.raises(ValueError, match=r"^model.F: time-varying with 10 steps"):
        je.simulate(varying, prior, 12, jax.random.key(0))
    with_inputs = je.LinearGaussian(model.F, model.H, model.Q, model.R, B=jnp.ones((2, 1)))
    with pytest.raises(ValueError, match="^inputs"):  # was scan's "different leading axis sizes"
        je.simulate(with_inputs, prior, 12, jax.random.key(0), inputs=jnp.ones((10, 1)))


def test_steady_state_filter_and_smoother_name_missing_measurements():
    # their one gain is for complete measurements: NaN estimates (status NONFINITE) before
    model, ys, prior = good()
    gappy = ys.at[3, 0].set(jnp.nan)
    with pytest.raises(ValueError, match="^ys: has missing .*use KalmanFilter"):
        je.run(je.SteadyStateKalmanFilter(), model, gappy, prior=prior)
    with pytest.raises(ValueError, match="^ys: has missing"):
        je.steady_state_smooth(model, gappy, prior=prior)


def test_smoothers_name_bad_arguments():
    """A particle filter's result raised an AttributeError, a model of another size a TypeError
    from inside the pass, inputs to a model without B were ignored, an empty result an
    IndexError (and so did run with T = 0 and inputs)."""
    model, ys, prior = good()
    result = je.run(KalmanFilter(), model, ys, prior=prior)
    particles = je.run(je.ParticleFilter(8), model, ys, prior=prior, key=jax.random.key(0))
    three = je.LinearGaussian(jnp.eye(3), jnp.ones((1, 3)), jnp.eye(3), jnp.eye(1))
    with_b = je.LinearGaussian(model.F, model.H, model.Q, model.R, B=jnp.ones((2, 1)))
    empty = je.run(KalmanFilter(), with_b, ys[:0], prior=prior, inputs=jnp.ones((0, 1)))
    for smooth in (
        je.rts_smooth,
        lambda m, r, **kw: je.sigma_point_rts_smooth(m, r, je.UKF(), **kw),
    ):
        for args, kwargs, name in [
            ((model, particles), {}, "result"),
            ((three, result), {}, "model"),
            ((model, result), {"inputs": jnp.ones((10, 1))}, "inputs"),
            ((with_b, result), {"inputs": jnp.ones((7, 1))}, "inputs"),
            ((with_b, empty), {"inputs": jnp.ones((0, 1))}, "result"),
        ]:
            with pytest.raises(ValueError, match=f"^{name}"):
                smooth(*args, **kwargs)


def test_nonlinear_model_shapes_checked():
    model = je.NonlinearGaussian(lambda x, u: x[:1], lambda x, u: x, jnp.eye(2), jnp.eye(2))
    with pytest.raises(ValueError, match=r"f\(x\)"):
        je.run(
            KalmanFilter(), model, jnp.zeros((5, 2)), prior=je.Gaussian(jnp.zeros(2), jnp.eye(2))
        )
    # f(x, k) reads the time index where jaxest passes u (None here): the message says how
    # the functions are called
    misread = je.NonlinearGaussian(lambda x, k: x + 0 * k, lambda x, k: x, jnp.eye(2), jnp.eye(2))
    with pytest.raises(ValueError, match=r"with u = None and k = 0 .* \(x, u, k\)"):
        je.run(
            KalmanFilter(), misread, jnp.zeros((5, 2)), prior=je.Gaussian(jnp.zeros(2), jnp.eye(2))
        )
    # a scalar h for one measurement gave an IndexError, a list from f an AttributeError, and
    # simulate took the scalar h (measurements of shape (T,))
    prior = je.Gaussian(jnp.zeros(2), jnp.eye(2))
    scalar = je.NonlinearGaussian(lambda x: x, lambda x: x[0], jnp.eye(2), jnp.eye(1))
    listed = je.NonlinearGaussian(lambda x: [x[0], x[1]], lambda x: x[:1], jnp.eye(2), jnp.eye(1))
    for bad, message in [(scalar, r"^model: its h\(x\) is a scalar"),
                         (listed, r"^model: its f\(x\) is a list, not an array")]:  # fmt: skip
        with pytest.raises(ValueError, match=message):
            je.run(je.EKF(), bad, jnp.zeros((5, 1)), prior=prior)
    with pytest.raises(ValueError, match=r"^model: its h\(x\) is a scalar"):
        je.simulate(scalar, prior, 5, jax.random.key(0))
    with pytest.raises(ValueError, match="noise_gain"):
        je.NonlinearGaussian(
            lambda x, u: x,
            lambda x, u: x,
            jnp.eye(2),
            jnp.eye(2),
            noise_gain=lambda x, u: jnp.eye(2),
            noise_on_input=True,
        )


def test_model_shapes_are_traced_once_per_signature():
    """The shape check traces the model once per structure and shapes: a second run on new
    data neither traces ``f`` again nor compiles; a state of another size is checked anew."""
    traces = []

    def f(x, u):
        traces.append(x.shape)
        return 0.9 * x

    model = je.NonlinearGaussian(f, lambda x, u: x[:1], 0.1 * jnp.eye(2), jnp.eye(1))
    ys, prior = jnp.zeros((10, 1)), je.Gaussian(jnp.zeros(2), jnp.eye(2))
    je.run(KalmanFilter(), model, ys, prior=prior)
    traced = len(traces)
    je.run(KalmanFilter(), model, ys + 1.0, prior=prior)
    assert len(traces) == traced
    with pytest.raises(ValueError, match=r"model.Q: has shape \(2, 2\), expected \(3, 3\)"):
        je.run(KalmanFilter(), model, ys, prior=je.Gaussian(jnp.zeros(3), jnp.eye(3)))


def test_simulate_takes_any_integer_step_count_and_rejects_others():
    """``num_steps`` may be a Python, NumPy or concrete JAX integer (the same draw); a float or
    a negative count raises naming it, as does a key that is not one PRNG key."""
    model, _, prior = good()
    key = jax.random.PRNGKey(0)
    draws = [je.simulate(model, prior, n, key).y for n in (6, np.int64(6), jnp.int32(6))]
    assert draws[0].shape == (6, 1)
    assert all(np.array_equal(draws[0], draw) for draw in draws)
    for bad in (6.0, -1):
        with pytest.raises(ValueError, match="num_steps"):
            je.simulate(model, prior, bad, key)
    # an int seed, an int64 vector or a batch of keys raised JAX's errors, which named no argument
    for bad in (0, jnp.arange(2), jax.random.split(key, 3)):
        with pytest.raises(ValueError, match="^key: expected"):
            je.simulate(model, prior, 6, bad)


def test_missing_rows_are_skipped_exactly():
    """A NaN entry gives the same result as a model without that measurement row."""
    model, _, prior = good()
    full = je.LinearGaussian(
        model.F,
        jnp.asarray([[1.0, 0.0], [0.0, 1.0]]),
        model.Q,
        jnp.asarray([[1.0, 0.3], [0.3, 2.0]]),
    )
    ys = np.random.default_rng(0).normal(size=(10, 2))
    ys[:, 1] = np.nan
    only_first = je.LinearGaussian(
        model.F, jnp.asarray([[1.0, 0.0]]), model.Q, jnp.asarray([[1.0]])
    )
    a = je.run(SVDEKF(), full, jnp.asarray(ys), prior=prior)
    b = je.run(SVDEKF(), only_first, jnp.asarray(ys[:, :1]), prior=prior)
    np.testing.assert_allclose(a.mean, b.mean, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(a.loglik, b.loglik, rtol=1e-12)


# The bad inputs a new user met (Core v2 issue): each named before tracing, or a status under jit.


def test_infinite_measurement_is_an_error_not_missing():
    model, ys, prior = good()
    ys = ys.at[3, 0].set(jnp.inf)
    with pytest.raises(ValueError, match=r"ys: contains \+-inf"):
        je.run(KalmanFilter(), model, ys, prior=prior)
    import jax

    traced = jax.jit(lambda y: je.run(KalmanFilter(), model, y, prior=prior))(ys)
    assert int(traced.status[3]) & je.Status.NONFINITE and not bool(traced.ok)
    missing = je.run(KalmanFilter(), model, ys.at[3, 0].set(jnp.nan), prior=prior)
    assert bool(missing.ok)  # NaN is missing, and only NaN


def test_prior_of_wrong_size_blames_the_prior():
    model, ys, _ = good()
    with pytest.raises(ValueError, match=r"prior.mean: expected shape \(2,\)"):
        je.run(KalmanFilter(), model, ys, prior=je.Gaussian(jnp.zeros(3), jnp.eye(3)))


def test_positional_prior_is_named():
    model, ys, prior = good()
    with pytest.raises(ValueError, match="prior: pass prior, inputs and key by keyword"):
        je.run(KalmanFilter(), model, ys, prior)
    with pytest.raises(ValueError, match="prior: pass"), pytest.warns(DeprecationWarning):
        je.filter(KalmanFilter(), model, ys, prior)


@pytest.mark.parametrize("Filter", NEED_POSITIVE_Q, ids=lambda f: f.__name__)
def test_zero_process_noise_rejected_where_the_filter_needs_q_positive(Filter):
    model, ys, prior = good()
    zero_q = je.LinearGaussian(model.F, model.H, jnp.zeros((2, 2)), model.R)
    with pytest.raises(ValueError, match="model.Q: must be positive definite"):
        je.run(Filter(), zero_q, ys, prior=prior)
    reference = je.run(KalmanFilter(), zero_q, ys + 1.0, prior=prior)
    assert bool(reference.ok)  # Q = 0 is fine for the others, the SVD filters included
    for Other in set(GAUSSIAN_FILTERS) - set(NEED_POSITIVE_Q):
        other = je.run(Other(), zero_q, ys + 1.0, prior=prior)
        np.testing.assert_allclose(other.loglik, reference.loglik, rtol=1e-10)


def test_positive_definite_means_beyond_rounding_whatever_the_units():
    """A rank-one Q = g g^T rounds to a smallest eigenvalue of +1.4e-20, which passed as
    positive definite, and the filters that factor Q returned NaN. Singular beyond rounding is
    judged on the matrix scaled to a unit diagonal, so states in units 1e12 apart still pass."""
    model, ys, prior = good()
    g = jnp.asarray([0.01, 0.1])
    rank_one = je.LinearGaussian(
        model.F, model.H, jnp.asarray([[1e-4, 1e-3], [1e-3, 1e-2]]), model.R
    )
    assert np.min(np.linalg.eigvalsh(np.asarray(rank_one.Q))) > 0  # g g^T, rounded
    np.testing.assert_allclose(rank_one.Q, jnp.outer(g, g), rtol=1e-15)
    with pytest.raises(
        ValueError, match="^model.Q: must be positive definite beyond rounding.*as G"
    ):
        je.run(je.SquareRootKF(), rank_one, ys, prior=prior)
    with pytest.raises(ValueError, match="^prior.cov: must be positive definite beyond rounding"):
        je.run(KalmanFilter(), model, ys, prior=je.Gaussian(prior.mean, rank_one.Q))
    units = jnp.diag(jnp.asarray([1e-6, 1e6]))  # the same system, its second state in other units
    scaled = je.LinearGaussian(units @ model.F @ jnp.linalg.inv(units), model.H @ jnp.linalg.inv(units),
                               units @ model.Q @ units, model.R)  # fmt: skip
    scaled_prior = je.Gaussian(units @ prior.mean, units @ prior.cov @ units)
    want = je.run(je.SquareRootKF(), model, ys, prior=prior)
    got = je.run(je.SquareRootKF(), scaled, ys, prior=scaled_prior)
    np.testing.assert_allclose(got.loglik, want.loglik, rtol=1e-9)


class OwnModel(je.AbstractGaussianModel):
    """A user's model with no Q or R attributes: read through the protocol's methods."""

    scale: float
    m: int = 1

    def f(self, x, u=None, k=0):
        return self.scale * x

    def h(self, x, u=None, k=0):
        return x[: self.m]

    def process_noise(self, x, u, k):
        return jnp.eye(2), 0.1 * jnp.eye(2)

    def measurement_cov(self, k):
        return jnp.eye(self.m)


def test_users_own_model_gets_the_same_checks():
    _, ys, prior = good()
    ys = ys + jnp.linspace(0.0, 1.0, 10)[:, None]
    res = je.run(KalmanFilter(), OwnModel(0.9), ys, prior=prior)
    same = je.LinearGaussian(
        0.9 * jnp.eye(2), jnp.asarray([[1.0, 0.0]]), 0.1 * jnp.eye(2), jnp.eye(1)
    )
    reference = je.run(KalmanFilter(), same, ys, prior=prior)
    np.testing.assert_allclose(res.mean, reference.mean, rtol=1e-12)
    np.testing.assert_allclose(res.loglik, reference.loglik, rtol=1e-12)
    with pytest.raises(ValueError, match=r"ys: expected 2 column\(s\)"):
        je.run(KalmanFilter(), OwnModel(0.9, m=2), ys, prior=prior)
    with pytest.raises(ValueError, match="model: expected a Gaussian model"):
        je.run(KalmanFilter(), object(), ys, prior=prior)


def test_rts_smooth_compiles_once():
    model, ys, prior = good()
    traces = []

    class Counting(OwnModel):
        def f(self, x, u=None, k=0):
            traces.append(1)
            return self.scale * x

    res = je.run(KalmanFilter(), Counting(jnp.asarray(0.9)), ys, prior=prior)
    traces.clear()
    je.rts_smooth(Counting(jnp.asarray(0.9)), res)
    first = len(traces)
    smooth = je.rts_smooth(Counting(jnp.asarray(0.8)), res)
    assert bool(smooth.ok)
    assert first > 0 and len(traces) == first  # the second call reused the compiled smoother


def test_switches_functions_and_results_are_named():
    """A string such as "no" counted as true for every switch; the others raised TypeErrors or
    AttributeErrors from inside, or (an f(x) of the wrong size) were broadcast into the state."""
    model, ys, prior = good()
    result = je.run(KalmanFilter(), model, ys, prior=prior)
    observer = dict(M=jnp.eye(1), Sigma=jnp.eye(1), Q=jnp.eye(2), R=jnp.eye(1))
    short = je.NonlinearGaussian(lambda x: x[:1], lambda x: x[:1], model.Q, model.R)
    cases = [
        ("^parallel: expected True, False or None, got 'no'", lambda: je.run(je.ParallelKalmanFilter(), model, ys, prior=prior, parallel="no")),
        ("^throw: expected True or False, got 'no'", lambda: je.run(KalmanFilter(), model, ys, prior=prior, throw="no")),
        ("^parallel: expected True or False", lambda: je.rts_smooth(model, result, parallel="no")),
        ("^square_root: expected True or False, got 1", lambda: je.rts_smooth(model, result, square_root=1)),
        ("^parallel: expected True or False", lambda: je.iterated_smooth(model, ys, prior=prior, parallel="no")),
        ("^square_root: expected True or False", lambda: je.fit_em(model, ys, prior=prior, num_iters=1, square_root="no")),
        ("^throw: expected True or False", lambda: je.fit_em(model, ys, prior=prior, num_iters=1, throw="no")),
        ("^end_term: expected True or False", lambda: je.wiener_smooth(model, ys, prior=prior, end_term="no")),
        ("^differentiable: expected True or False", lambda: je.ParticleFilter(10, differentiable="no")),
        ("^square_root: expected True or False", lambda: je.ParallelKalmanFilter(square_root="no")),
        ("^recover: expected True or False", lambda: SetMembershipFilter(recover="no")),
        ("^gain: expected None or a SteadyStateGain", lambda: je.SteadyStateKalmanFilter(gain="K")),
        ("^gain: expected a SteadyStateGain", lambda: je.arma_innovation_model("K")),
        ("^free: expected a dict path -> mask", lambda: je.fit(model, lambda m: jnp.sum(m.Q), ["Q"], free=[True])),
        ("^excitation_window: must be a positive integer, got 0", lambda: je.DiscreteAdaptiveObserver(jnp.eye(2), jnp.eye(1), excitation_window=0)),
        ("^excitation_threshold: must be a non-negative number", lambda: je.AdaptiveObserver(**observer, excitation_threshold=-1.0)),
        (r"^model: its f\(x\): has shape \(1,\), expected \(2,\) for a state of size 2 \(x0\)", lambda: je.simulate(short, prior, 5, jax.random.key(0))),
        ("^x0: expected an initial state", lambda: je.simulate(model, "x0", 5, jax.random.key(0))),
        ("^model: expected a model with noise covariances Q and R", lambda: je.log_variances(prior)),
        ("^loss: expected a function, got str", lambda: je.log_variance_standard_errors(model, "nll", 10)),
        ("^result: expected a jaxest result, got str", lambda: je.raise_if_failed("result")),
        ("^fn: expected a function, got NoneType", lambda: je.scan.associative_scan(None, jnp.ones(3))),
        ("^fn: expected a function, got NoneType", lambda: je.vmap_minor(None)),
    ]  # fmt: skip
    for message, call in cases:
        with pytest.raises(ValueError, match=message):
            call()
