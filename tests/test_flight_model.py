"""The flight-path reconstruction model (eq 26-33) against independent formulations."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

from jaxest import xla_flags
from jaxest.models import jacobian_by_linearize
from jaxest.systems import flight
from jaxest.systems.flight import GRAVITY, N_KIN, N_STATE


@pytest.fixture(autouse=True)
def x64():
    """The reference comparisons need float64 (float32 runs ask for float32 arrays explicitly)."""
    with jax.enable_x64(True):
        yield


def dcm_body_to_ned(phi, theta, psi):
    """C such that v_ned = C v_body (3-2-1 Euler angles), written out independently."""
    cf, sf, ct, st, cp, sp = (np.cos(phi), np.sin(phi), np.cos(theta), np.sin(theta),
                              np.cos(psi), np.sin(psi))  # fmt: skip
    rz = np.array([[cp, -sp, 0], [sp, cp, 0], [0, 0, 1]])
    ry = np.array([[ct, 0, st], [0, 1, 0], [-st, 0, ct]])
    rx = np.array([[1, 0, 0], [0, cf, -sf], [0, sf, cf]])
    return rz @ ry @ rx


def skew(w):
    return np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])


def random_state(rng):
    vel = np.array([120.0, 0.0, 5.0]) + rng.normal(size=3) * [5, 3, 3]
    angles = rng.uniform(-0.6, 0.6, size=3) * [1, 0.8, 3]
    return np.concatenate([vel, angles, [2000.0 + rng.normal() * 100]])


def test_kinematics_match_rigid_body_equations():
    """Eq 26 (corrected) against v' = a + C^T g - w x v, C' = C [w x], h' = -(C v)_z."""
    rng = np.random.default_rng(0)
    for _ in range(20):
        x = random_state(rng)
        inputs = rng.normal(size=6) * [1, 1, 1, 0.3, 0.3, 0.3] + [0, 0, -9.8, 0, 0, 0]
        dx = np.asarray(flight.kinematics(jnp.asarray(x), jnp.asarray(inputs)))
        C = dcm_body_to_ned(*x[3:6])
        omega = inputs[3:]
        vel_rate = inputs[:3] + C.T @ [0, 0, GRAVITY] - np.cross(omega, x[:3])
        np.testing.assert_allclose(dx[:3], vel_rate, rtol=1e-12, atol=1e-12)
        eps = 1e-6
        C_dot = (
            dcm_body_to_ned(*(x[3:6] + eps * dx[3:6])) - dcm_body_to_ned(*(x[3:6] - eps * dx[3:6]))
        ) / (2 * eps)
        np.testing.assert_allclose(C_dot, C @ skew(omega), atol=1e-8)
        np.testing.assert_allclose(dx[6], -(C @ x[:3])[2], rtol=1e-12)


def test_one_rk4_step_matches_fine_reference_integration():
    """Eq 32's discretisation: one RK4 step over 0.1 s (10 Hz) with linearly interpolated inputs
    against scipy's adaptive integrator at tolerance 1e-12."""
    rng = np.random.default_rng(1)
    dt = 0.1
    for _ in range(5):
        x = random_state(rng)
        u0 = rng.normal(size=6) * [1, 1, 1, 0.2, 0.2, 0.2] + [0, 0, -9.8, 0, 0, 0]
        u1 = u0 + rng.normal(size=6) * [0.5, 0.5, 0.5, 0.05, 0.05, 0.05]
        rhs = lambda t, s: np.asarray(
            flight.kinematics(jnp.asarray(s), jnp.asarray(u0 + t / dt * (u1 - u0)))
        )
        ref = solve_ivp(rhs, (0, dt), x, rtol=1e-12, atol=1e-12, method="DOP853").y[:, -1]
        one = np.asarray(
            flight.integrate_interval(jnp.asarray(x), jnp.asarray(u0), jnp.asarray(u1), dt)
        )
        four = np.asarray(
            flight.integrate_interval(jnp.asarray(x), jnp.asarray(u0), jnp.asarray(u1), dt, 4)
        )
        err_one, err_four = np.abs(one - ref), np.abs(four - ref)
        assert np.max(err_one[:3]) < 1e-5  # m/s
        assert np.max(err_one[3:6]) < 1e-7  # rad
        assert err_one[6] < 1e-5  # m
        # fourth order: 4 substeps shrink the error by about 4^4
        assert np.max(err_four) < np.max(err_one) / 50 + 1e-12


def test_observation_eq28_by_hand():
    arms = flight.LeverArms(x_beta=8.0, z_beta=0.5, x_alpha=7.0, y_alpha=0.3)
    obs = flight.FlightObservation(arms)
    x = np.array([118.0, 2.0, 6.0, 0.1, 0.05, 1.0, 1500.0])
    b = np.arange(1, 17) * 0.01
    rates = np.array([0.02, -0.03, 0.04])
    u = np.concatenate([[0.1, 0.2, -9.7], rates, np.zeros(6)])
    z = np.asarray(obs(jnp.asarray(np.concatenate([x, b])), jnp.asarray(u)))
    p, q, r = rates + b[3:6]
    expect = [
        (1 + b[12]) * np.sqrt(118.0**2 + 4 + 36) + b[6],
        (1 + b[13]) * np.arctan((2.0 + r * 8.0 - p * 0.5) / 118.0) + b[7],
        (1 + b[14]) * np.arctan((6.0 - q * 7.0 + p * 0.3) / 118.0) + b[8],
        0.05 + b[9],
        0.1 + b[10],
        (1 + b[15]) * 1500.0 + b[11],
    ]
    np.testing.assert_allclose(z, expect, rtol=1e-13)


def _model_and_point(rng, dtype=jnp.float64):
    model = flight.flight_model(
        0.1,
        jnp.full(6, 0.02, dtype),
        jnp.full(6, 0.01, dtype),
        flight.LeverArms(8.0, 0.5, 8.0, 0.5),
    )
    x = jnp.asarray(np.concatenate([random_state(rng), rng.normal(size=16) * 0.01]), dtype)
    u = jnp.asarray(
        np.tile([0.5, 0.1, -9.6, 0.05, -0.02, 0.03], 2) + rng.normal(size=12) * 0.05, dtype
    )
    return model, x, u


def _central_difference(fun, x, eps):
    cols = [(fun(x + eps * e) - fun(x - eps * e)) / (2 * eps) for e in np.eye(x.shape[0])]
    return np.stack(cols, axis=1)


def test_jacobians_match_finite_differences():
    rng = np.random.default_rng(2)
    model, x, u = _model_and_point(rng)
    # compiled, as the filters run them (op by op, each primitive of RK4 would compile alone)
    mean, F, G, Q = eqx.filter_jit(model.transition)(x, u, 0)
    y, H, R = eqx.filter_jit(model.observation)(x, u, 0)
    scale = np.concatenate([[1.0] * 3, [1e-3] * 3, [1.0], [1e-3] * 16])
    f_jit, h_jit = eqx.filter_jit(model.f), eqx.filter_jit(model.h)
    f = lambda z: np.asarray(f_jit(jnp.asarray(z), u))
    F_fd = (
        _central_difference(lambda d: f(np.asarray(x) + scale * d), np.zeros(N_STATE), 1e-3) / scale
    )
    # atol: round-off of h ~ 2000 m over a step of 1e-6 is ~ 2e-7
    np.testing.assert_allclose(F, F_fd, rtol=1e-6, atol=1e-6)
    # G: one sample's noise shifts both ends of the interval
    both_ends = lambda v: np.asarray(f_jit(x, u + jnp.asarray(np.concatenate([v, v]))))
    G_fd = _central_difference(both_ends, np.zeros(6), 1e-4)
    np.testing.assert_allclose(G, G_fd, rtol=1e-6, atol=1e-8)
    # the time update reads G off F; the simulator's noise gain differentiates f in the inputs
    G_sim = eqx.filter_jit(model.process_noise)(x, u, 0)[0]
    np.testing.assert_allclose(G, G_sim, rtol=1e-13, atol=1e-15)
    h = lambda z: np.asarray(h_jit(jnp.asarray(z), u))
    H_fd = (
        _central_difference(lambda d: h(np.asarray(x) + scale * d), np.zeros(N_STATE), 1e-3) / scale
    )
    np.testing.assert_allclose(H, H_fd, rtol=1e-6, atol=1e-9)
    # parameters are constants, the process noise reaches only the kinematic states
    np.testing.assert_array_equal(np.asarray(F)[N_KIN:], np.eye(N_STATE)[N_KIN:])
    np.testing.assert_array_equal(np.asarray(G)[N_KIN:], 0.0)
    assert Q.shape == (6, 6) and R.shape == (6, 6)


def test_input_noise_accumulates_as_the_sample_noise_does():
    """White noise on every input sample, each sample shared by two intervals, propagated through f
    (Monte Carlo): the covariance it adds from step 10 to step 20 is what the filter's linearised
    model adds, P <- F P F^T + G Q G^T with G = df/du_m(k) + df/du_m(k+1). (The difference of two
    horizons leaves out the first and last samples, which shift only one interval each.)
    Independent noise on the two ends of an interval (blockdiag(Qc, Qc) on [u_m(k), u_m(k+1)])
    adds about half on the velocities."""
    rng = np.random.default_rng(3)
    _, x0, u = _model_and_point(rng)
    input_std = jnp.asarray([0.02, 0.03, 0.05, 1e-9, 1e-9, 1e-9])
    model = flight.flight_model(0.1, input_std, jnp.full(6, 0.01))
    draws = 100_000
    eta = jax.random.normal(jax.random.key(0), (draws, 21, 6)) * input_std

    def propagate(noise, steps):  # the truth: sample j's noise shifts the end of j-1, start of j
        def step(x, k):
            return model.f(x, u + jnp.concatenate([noise[k], noise[k + 1]]), k), None

        return jax.lax.scan(step, x0, jnp.arange(steps))[0][:3]

    def accumulate(P_and_x, k):
        P, x = P_and_x
        x_next, F, G, Q = model.transition(x, u, k)
        return (F @ P @ F.T + G @ Q @ G.T, x_next), None

    zero = jnp.zeros((flight.N_STATE, flight.N_STATE))
    added, modelled = [], []
    for steps in (10, 20):
        monte_carlo = jax.vmap(lambda n: propagate(n, steps))
        final = jax.jit(monte_carlo, compiler_options=xla_flags.OPTIMISED_MACHINE_CODE)(eta)
        added.append(np.var(np.asarray(final), axis=0))
        modelled.append(np.diag(jax.lax.scan(accumulate, (zero, x0), jnp.arange(steps))[0][0])[:3])
    assert model.Q.shape == (6, 6)
    # 1e5 draws: the difference of the two variances is good to about 0.9 % (3.5 sigma: 3.2 %)
    np.testing.assert_allclose(added[1] - added[0], modelled[1] - modelled[0], rtol=0.032)
    # ten samples add about 10 dt^2 Qc to the velocity variance (not 10 dt^2 Qc / 2)
    np.testing.assert_allclose(
        modelled[1] - modelled[0], 10 * 0.1**2 * np.asarray(input_std[:3]) ** 2, rtol=0.1
    )


def test_interval_inputs_pairs_samples():
    u = jnp.arange(18.0).reshape(3, 6)
    pairs = flight.interval_inputs(u)
    np.testing.assert_array_equal(pairs[0], np.concatenate([u[0], u[1]]))
    np.testing.assert_array_equal(pairs[2], np.concatenate([u[2], u[2]]))


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_model_under_jit_vmap_grad_keeps_dtype(dtype):
    rng = np.random.default_rng(4)
    model, x, u = _model_and_point(rng, dtype)
    mean, F, G, Q = jax.jit(lambda m, x, u: m.transition(x, u, 0))(model, x, u)
    assert mean.dtype == F.dtype == G.dtype == Q.dtype == dtype
    # vmap and grad each in one jitted program, where op by op they compiled about a hundred
    ys = jax.jit(jax.vmap(model.h, in_axes=(0, None)))(jnp.stack([x, x]), u)
    assert ys.shape == (2, 6) and ys.dtype == dtype
    grad = jax.jit(jax.grad(lambda z: jnp.sum(model.f(z, u)[:3])))(x)
    assert grad.dtype == dtype and bool(jnp.all(jnp.isfinite(grad)))
    np.testing.assert_allclose(
        grad, np.sum(np.asarray(F, np.float64)[:3], axis=0), rtol=1e-4, atol=1e-6
    )


def test_pinned_model_is_the_full_model_with_the_pinned_entries_set():
    """f, h and G of the reduced model against the full model evaluated at E z + c, written out
    here by index; unknown names raise ValueError."""
    rng = np.random.default_rng(3)
    full = flight.flight_model(
        0.04, jnp.asarray([0.02, 0.02, 0.05, 0.001, 0.001, 0.001]), jnp.full(6, 0.01)
    )
    pinned = {"b_V": 0.3, "b_h": -4.0, "b_phi": 0.002}
    reduced, names = flight.pin_parameters(full, pinned)
    free = [i for i, s in enumerate(flight.STATES) if s not in pinned]
    assert names == tuple(flight.STATES[i] for i in free) and len(names) == N_STATE - 3
    x = np.concatenate([[70.0, 1.0, 4.0, 0.1, 0.05, 0.3, 1500.0], rng.normal(0, 0.01, 16)])
    for p, v in pinned.items():
        x[flight.STATES.index(p)] = v
    z, u = jnp.asarray(x[free]), jnp.asarray(rng.normal(0, 0.1, 12))

    @eqx.filter_jit  # one program per model, where op-by-op evaluation compiles hundreds
    def evaluate(model, x):
        _, F_linearized = jacobian_by_linearize(lambda v: model.f(v, u), x)
        noise, transition = model.process_noise(x, u, 0), model.transition(x, u, 0)
        return model.f(x, u), model.h(x, u), noise, transition, F_linearized

    f_full, h_full, (G_full, Q), (_, F_full, _, _), _ = evaluate(full, jnp.asarray(x))
    f, h, (G, Q_reduced), (mean, F, G_step, _), F_reduced = evaluate(reduced, z)
    np.testing.assert_allclose(f, f_full[np.array(free)])
    np.testing.assert_allclose(h, h_full)
    np.testing.assert_allclose(G, G_full[np.array(free)])
    np.testing.assert_array_equal(Q_reduced, Q)
    # the pinned columns are gone from F
    np.testing.assert_allclose(F, F_full[np.ix_(free, free)], atol=1e-12)
    # the time update reduces the full model's; the reduced f and noise gain agree with it
    np.testing.assert_allclose(mean, f, rtol=1e-15)
    np.testing.assert_allclose(G_step, G, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(F, F_reduced, rtol=1e-13, atol=1e-13)
    with pytest.raises(ValueError, match="pinned"):
        flight.pin_parameters(full, {"u": 0.0})


def test_a_sample_interval_that_is_not_positive_is_named():
    """flight_model(dt=0) and (dt=-0.04) ran with status OK (a record with a reversed time axis
    gives a negative dt)."""
    noise = jnp.ones(6)
    for dt in (0.0, -0.04, float("nan")):
        with pytest.raises(ValueError, match="^dt: must be a positive sample interval"):
            flight.flight_model(dt, noise, noise)
    with pytest.raises(ValueError, match="^substeps: must be a positive integer"):
        flight.flight_model(0.04, noise, noise, substeps=0)
