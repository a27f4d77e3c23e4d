"""Zhang's adaptive observer: convergence, integration accuracy against scipy, the discrete form
against a plain NumPy recursion, persistent-excitation monitoring and jit/vmap/grad."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate
import scipy.linalg
from jax import enable_x64

import jaxest as je
from jaxest import run
from jaxest.observers import (
    AdaptiveObserver,
    ContinuousLTV,
    DiscreteAdaptiveObserver,
    DiscreteLTV,
    InputEffectiveness,
    ObserverPrior,
    ObserverStatus as Status,
    simulate_closed_loop,
)
from jaxest.systems.aircraft_linear import aircraft, b747
from tests import reference

DT = 0.01


def charlie_setup(dtype=jnp.float64, M=30.0, window=200, threshold=1e-6):
    ac = aircraft("charlie")
    A, B, C = (jnp.asarray(ac[k], dtype) for k in ("A", "B", "C"))
    n, m = 4, 3
    model = ContinuousLTV(A, jnp.zeros_like(B), C, InputEffectiveness(B))
    # independent gains from scipy: LQR state feedback and the steady-state filter Riccati P
    Pc = scipy.linalg.solve_continuous_are(ac["A"], ac["B"], np.eye(n), np.eye(1))
    Kbar = jnp.asarray(ac["B"].T @ Pc, dtype)
    Pf = jnp.asarray(
        scipy.linalg.solve_continuous_are(ac["A"].T, ac["C"].T, np.eye(n), np.eye(m)), dtype
    )
    obs = AdaptiveObserver(
        M=M * jnp.eye(1, dtype=dtype),
        Sigma=jnp.eye(m, dtype=dtype),
        Q=jnp.eye(n, dtype=dtype),
        R=jnp.eye(m, dtype=dtype),
        dt=DT,
        excitation_window=window,
        excitation_threshold=threshold,
    )
    prior = ObserverPrior(jnp.zeros(n, dtype), jnp.ones(1, dtype), Pf)
    return model, obs, prior, Kbar, jnp.asarray(ac["theta"], dtype)


def multisine(T, amplitude=1.0, dtype=jnp.float64):
    t = np.arange(T) * DT
    return jnp.asarray(
        amplitude * (np.sin(0.5 * t) + np.sin(1.3 * t + 1) + np.sin(2.9 * t + 2))[:, None], dtype
    )


X0 = (0.1, 0.05, 0.0, 0.0)


def test_noise_free_convergence_charlie():
    with enable_x64():
        model, obs, prior, Kbar, theta = charlie_setup()
        sim = eqx.filter_jit(simulate_closed_loop)(
            obs, model, theta, jnp.asarray(X0), prior, Kbar, multisine(8000)
        )
        est = sim.estimate
        theta_err = jnp.abs(est.theta[-1] - theta) / jnp.abs(theta)
        x_err = jnp.linalg.norm(est.x[-1] - sim.states[-1])
        assert float(theta_err[0]) < 1e-6
        assert float(x_err) < 1e-6
        assert float(jnp.abs(est.theta[0, 0] - theta[0])) > 0.5  # it started far away
        assert bool(jnp.all(est.status == Status.OK))


def test_closed_loop_equals_open_loop_run():
    with enable_x64():
        model, obs, prior, Kbar, theta = charlie_setup()
        key = jax.random.PRNGKey(1)
        sim = simulate_closed_loop(
            obs, model, theta, jnp.asarray(X0), prior, Kbar, multisine(300), key, 0.01
        )
        again = run(obs, model, sim.observations, inputs=sim.inputs, prior=prior)
        np.testing.assert_allclose(again.theta, sim.estimate.theta, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(again.x, sim.estimate.x, rtol=1e-12, atol=1e-14)


def _ltv_model():
    A0 = np.array([[0.0, 1.0], [-2.0, -0.5]])

    def A(t):
        return jnp.asarray(A0) + 0.3 * jnp.sin(t) * jnp.array([[0.0, 0.0], [1.0, 0.0]])

    C = lambda t: jnp.array([[1.0, 0.2 * jnp.cos(t)]])
    B = jnp.array([[0.0], [1.0]])
    psi = lambda t, u, y: jnp.array([[0.0, 0.0], [u[0], y[0] * jnp.cos(t)]])
    return ContinuousLTV(A, B, C, psi), A0


def test_step_integrates_the_sampled_observer_like_scipy():
    """One step of RK4 substeps matches solve_ivp on the same ODE written out in NumPy."""
    with enable_x64():
        model, A0 = _ltv_model()
        M, Sigma, Q, R = np.diag([2.0, 0.5]), np.array([[1.5]]), np.eye(2), np.array([[0.3]])
        obs = AdaptiveObserver(
            M=jnp.asarray(M),
            Sigma=jnp.asarray(Sigma),
            Q=jnp.asarray(Q),
            R=jnp.asarray(R),
            dt=0.05,
            substeps=8,
        )
        prior = ObserverPrior(
            jnp.array([0.3, -0.1]), jnp.array([0.5, -0.2]), jnp.array([[1.0, 0.1], [0.1, 0.5]])
        )
        state = obs.init(model, prior)
        # take a few steps so that Gamma is non-zero, then compare one step
        for k in range(3):
            state, _ = obs.step(model, state, k, jnp.array([0.2 * k + 0.1]), jnp.array([1.0 - k]))
        y, u = np.array([0.7]), np.array([0.4])
        t0 = float(obs.time(3))
        new, _ = obs.step(model, state, 3, jnp.asarray(y), jnp.asarray(u))

        def A(t):
            return A0 + 0.3 * np.sin(t) * np.array([[0.0, 0.0], [1.0, 0.0]])

        def C(t):
            return np.array([[1.0, 0.2 * np.cos(t)]])

        e = y - C(t0) @ np.asarray(state.x)

        def f(t, z):
            x, th, G, P = z[:2], z[2:4], z[4:8].reshape(2, 2), z[8:].reshape(2, 2)
            Ct = C(t)
            psi = np.array([[0.0, 0.0], [u[0], y[0] * np.cos(t)]])
            K = P @ Ct.T @ np.linalg.inv(R)
            g = M @ G.T @ Ct.T @ Sigma @ e
            dx = A(t) @ x + np.array([0.0, u[0]]) + psi @ th + K @ e + G @ g
            dG = (A(t) - K @ Ct) @ G + psi
            dP = A(t) @ P + P @ A(t).T - P @ Ct.T @ np.linalg.inv(R) @ Ct @ P + Q
            return np.concatenate([dx, g, dG.ravel(), dP.ravel()])

        z0 = np.concatenate(
            [
                np.asarray(state.x),
                np.asarray(state.theta),
                np.asarray(state.Gamma).ravel(),
                np.asarray(state.P).ravel(),
            ]
        )
        ref = scipy.integrate.solve_ivp(f, (t0, t0 + 0.05), z0, rtol=1e-12, atol=1e-14).y[:, -1]
        np.testing.assert_allclose(new.x, ref[:2], rtol=1e-9, atol=1e-11)
        np.testing.assert_allclose(new.theta, ref[2:4], rtol=1e-9, atol=1e-11)
        np.testing.assert_allclose(new.Gamma, ref[4:8].reshape(2, 2), rtol=1e-9, atol=1e-11)
        np.testing.assert_allclose(new.P, ref[8:].reshape(2, 2), rtol=1e-9, atol=1e-11)


def test_sampled_observer_tends_to_continuous_eq17():
    """With a small dt the sampled observer follows eq 17 driven by continuous y (scipy)."""
    with enable_x64():
        A = np.array([[0.0, 1.0], [-2.0, -0.7]])
        Bp = np.array([[0.0], [1.0]])
        C = np.array([[1.0, 0.0]])
        K = np.array([[1.0], [1.0]])
        M, theta = 5.0, 1.7
        u = lambda t: np.sin(t) + np.sin(2.3 * t)

        def f(t, z):  # truth x, observer x_hat, theta_hat, Gamma
            x, xh, th, G = z[:2], z[2:4], z[4], z[5:7]
            e = C @ x - C @ xh
            psi = Bp[:, 0] * u(t)
            adapt = M * (C @ G) * e
            dxh = A @ xh + psi * th + K[:, 0] * e + G * adapt
            return np.concatenate([A @ x + psi * theta, dxh, adapt, (A - K @ C) @ G + psi])

        T = 20.0
        ts = np.arange(0, 2001) * 0.01
        ref = scipy.integrate.solve_ivp(
            f, (0, T), np.array([0.5, 0, 0, 0, 0, 0, 0.0]), t_eval=ts, rtol=1e-10, atol=1e-12
        )
        errors = []
        for dt in (0.01, 0.001):
            steps = int(round(T / dt)) + 1
            t = np.arange(steps) * dt
            model = ContinuousLTV(
                jnp.asarray(A),
                jnp.zeros((2, 1)),
                jnp.asarray(C),
                InputEffectiveness(jnp.asarray(Bp)),
            )
            us = jnp.asarray(u(t)[:, None])
            xs = scipy.integrate.solve_ivp(
                lambda s, x: A @ x + Bp[:, 0] * u(s) * theta,
                (0, T),
                [0.5, 0],
                t_eval=t,
                rtol=1e-10,
                atol=1e-12,
            ).y.T
            obs = AdaptiveObserver(
                M=jnp.array([[M]]), Sigma=jnp.eye(1), K=jnp.asarray(K), dt=dt, substeps=2
            )
            # u varies within a sample here (continuous truth above); the observer holds u_k
            res = run(
                obs,
                model,
                jnp.asarray(xs @ C.T),
                inputs=us,
                prior=ObserverPrior(jnp.zeros(2), jnp.zeros(1)),
            )
            stride = int(round(0.01 / dt))
            errors.append(np.max(np.abs(np.asarray(res.theta[::stride, 0]) - ref.y[4])))
        coarse, fine = errors
        assert fine < 0.02
        assert fine < coarse / 5  # first order in dt


def test_excitation_lost_without_reference():
    with enable_x64():
        # the closed loop's phugoid (-0.06 +- 0.17j) lets the transient's excitation die slowly
        model, obs, prior, Kbar, theta = charlie_setup(window=300, threshold=1e-4)
        T = 3000
        quiet = simulate_closed_loop(
            obs, model, theta, jnp.asarray(X0), prior, Kbar, jnp.zeros((T, 1))
        )
        excited = simulate_closed_loop(
            obs, model, theta, jnp.asarray(X0), prior, Kbar, multisine(T)
        )
        lost = (quiet.estimate.status & Status.NOT_EXCITED) != 0
        assert not bool(jnp.any(lost[:300]))  # window not yet full
        assert bool(jnp.all(lost[-300:]))  # the transient died out: excitation lost
        assert not bool(jnp.any((excited.estimate.status & Status.NOT_EXCITED) != 0))
        # eq 16 window Gramian against a trapezoid rule on the sampled Gamma (NumPy)
        C, G = np.asarray(model.C), np.asarray(excited.estimate.Gamma)
        integrand = np.einsum("tnp,mn,mq,tqr->tpr", G, C, C, G)
        k = T - 1
        trap = DT * (integrand[k - 300 : k + 1].sum(0) - 0.5 * (integrand[k - 300] + integrand[k]))
        np.testing.assert_allclose(
            float(excited.estimate.excitation[k]), np.linalg.eigvalsh(trap)[0], rtol=1e-3
        )


def phi_per_step(model, inputs):
    """``model.phi(k, u_k, None)`` for every step k, stacked, as NumPy: one compiled program
    (called step by step outside ``jit`` it dispatched each operation anew, 3.8 s for 8 000 steps)."""
    steps = jnp.arange(len(inputs))
    return np.asarray(jax.jit(jax.vmap(lambda k, u: model.phi(k, u, None)))(steps, inputs))


def numpy_discrete_observer(
    F, B, H, Phi, Q, R, lam, x, P, theta, Sp, ys, us, window=200, anti_windup=True
):
    """docs/papers/adaptive.md in its own ordering (predict with (u_{k-1}, Phi_{k-1}), then
    update), in covariance form S_theta. With ``anti_windup`` the forgetting of
    DiscreteAdaptiveObserver's docstring: lambda_k = max(lambda, 1 - mu_k) (mu_k the smallest
    generalised eigenvalue of (W_k / N, S_theta^-1)) and the prior term, applied as
    S_bar = (lambda_k S_theta^-1 + (1 - lambda_k) S_0^-1)^-1 before the measurement update;
    without, the paper's recursion. NaN entries of y_k are not measured: their rows are deleted
    from H, R and y_k. Returns x, theta and the window Gramians W_k (sums of Omega^T S^-1 Omega
    over the last ``window`` steps)."""
    n, p = F.shape[0], theta.shape[0]
    Ups, Sp0 = np.zeros((n, p)), Sp
    xs, thetas, grams = [], [], []
    increments = np.zeros((len(ys), p, p))
    for k, y in enumerate(ys):
        if k == 0:  # the prior is on x_0: no prediction before the first measurement
            x_pred, P_pred, Ups_pred = x, P, Ups
        else:
            u, Ph = us[k - 1], Phi[k - 1]
            x_pred = F @ x + B @ u + Ph @ theta
            P_pred = F @ P @ F.T + Q
            Ups_pred = F @ Ups + Ph
        seen = ~np.isnan(y)  # a missing entry's row is deleted (the observer masks it)
        Hs, y = H[seen], y[seen]
        S = Hs @ P_pred @ Hs.T + R[np.ix_(seen, seen)]
        K = P_pred @ Hs.T @ np.linalg.inv(S)
        P = (np.eye(n) - K @ Hs) @ P_pred
        Ups = (np.eye(n) - K @ Hs) @ Ups_pred
        Om = Hs @ Ups_pred
        increments[k] = Om.T @ np.linalg.solve(S, Om)
        W = increments[max(0, k + 1 - window) : k + 1].sum(axis=0)
        grams.append(W)
        e = y - Hs @ x_pred
        if anti_windup:
            mu = scipy.linalg.eigh(W / window, np.linalg.inv(Sp), eigvals_only=True)[0]
            lam_k = max(lam, 1 - mu)
            Sp = np.linalg.inv(lam_k * np.linalg.inv(Sp) + (1 - lam_k) * np.linalg.inv(Sp0))
            Lam = np.linalg.inv(S + Om @ Sp @ Om.T)
            Gam = Sp @ Om.T @ Lam
            Sp = Sp - Sp @ Om.T @ Lam @ Om @ Sp
        else:
            Lam = np.linalg.inv(lam * S + Om @ Sp @ Om.T)
            Gam = Sp @ Om.T @ Lam
            Sp = (Sp - Sp @ Om.T @ Lam @ Om @ Sp) / lam
        theta_new = theta + Gam @ e
        x = x_pred + K @ e + Ups @ (theta_new - theta)
        theta = theta_new
        xs.append(x)
        thetas.append(theta)
    return np.array(xs), np.array(thetas), np.array(grams)


def test_discrete_form_matches_numpy_and_converges():
    with enable_x64():
        model, obs, prior, Kbar, theta = charlie_setup()
        sim = simulate_closed_loop(obs, model, theta, jnp.asarray(X0), prior, Kbar, multisine(3000))
        dmodel = model.discretize(DT)
        dobs = DiscreteAdaptiveObserver(Q=1e-4 * jnp.eye(4), R=1e-2 * jnp.eye(3), forgetting=0.99)
        dprior = ObserverPrior(jnp.zeros(4), jnp.ones(1), jnp.eye(4), 10.0 * jnp.eye(1))
        res = run(dobs, dmodel, sim.observations, inputs=sim.inputs, prior=dprior)
        Phi = phi_per_step(dmodel, sim.inputs[:400])
        xs, thetas, grams = numpy_discrete_observer(
            np.asarray(dmodel.F),
            np.asarray(dmodel.B),
            np.asarray(dmodel.H),
            Phi,
            1e-4 * np.eye(4),
            1e-2 * np.eye(3),
            0.99,
            np.zeros(4),
            np.eye(4),
            np.ones(1),
            10.0 * np.eye(1),
            np.asarray(sim.observations[:400]),
            np.asarray(sim.inputs[:400]),
        )
        np.testing.assert_allclose(res.theta[:400], thetas, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(res.x[:400], xs, rtol=1e-9, atol=1e-12)
        # the monitor: smallest eigenvalue of the window Gramian in units of the prior's information
        np.testing.assert_allclose(res.excitation[:400], 10.0 * grams[:, 0, 0], rtol=1e-9)
        assert not np.any(np.asarray(res.status) & Status.NOT_EXCITED)
        # the sampled truth is exactly the discretised model: noise-free, the estimates converge
        # geometrically (the bounded forgetting slows the paper's rate; with lambda = 1 the error
        # would still be 3e-3 at the end)
        error = np.abs(np.asarray(res.theta[:, 0]) - 2.0)
        assert error[-1] < 1e-7 and error[-1] < 1e-3 * error[1000]
        assert float(jnp.linalg.norm(res.x[-1] - sim.states[-1])) < error[-1]  # x follows theta


class StackedRegressor(eqx.Module):
    """Phi_k read from an array stacked over time (arrays, so new draws reuse the program)."""

    Phi: jax.Array

    def __call__(self, k, u, y):
        return self.Phi[k]


def augmented_kalman_filter(F, B, H, Phi, Q, R, x0, P0, theta0, S0, ys, us):
    """The filtered x and theta of the textbook Kalman filter (:func:`tests.reference.
    kalman_filter`) on z = (x, theta, 1), theta constant and the last entry carrying the input:
    z_{k+1} = [[F, Phi_k, B u_k], [0, I, 0], [0, 0, 1]] z_k + (w_k, 0, 0), y_k = [H, 0, 0] z_k
    + v_k."""
    n, p = F.shape[0], Phi.shape[-1]
    F_aug = np.stack([
        np.block([[F, Phi_k, (B @ u)[:, None]],
                  [np.zeros((p, n)), np.eye(p), np.zeros((p, 1))],
                  [np.zeros((1, n + p)), np.ones((1, 1))]])
        for Phi_k, u in zip(Phi, us, strict=True)
    ])  # fmt: skip
    H_aug = np.hstack([H, np.zeros((H.shape[0], p + 1))])
    Q_aug = scipy.linalg.block_diag(Q, np.zeros((p + 1, p + 1)))
    prior_mean = np.concatenate([x0, theta0, [1.0]])
    prior_cov = scipy.linalg.block_diag(P0, S0, [[0.0]])
    means = reference.kalman_filter(F_aug, H_aug, Q_aug, R, prior_mean, prior_cov, ys)[0]
    return means[:, :n], means[:, n : n + p]


def test_discrete_form_without_forgetting_is_the_augmented_kalman_filter():
    """With forgetting 1 the discrete observer is the Kalman filter on (x, theta), theta constant
    (its docstring says why): random systems, a time-varying regressor and missing entries,
    against a NumPy augmented filter, with no argument in common but the data."""
    rng = np.random.default_rng(3)
    n, m, p, inputs, T = 3, 2, 2, 2, 40
    observer = DiscreteAdaptiveObserver(
        Q=jnp.eye(n), R=jnp.eye(m), forgetting=1.0, excitation_window=5, excitation_threshold=0.0
    )
    for _ in range(3):  # one program: the draws differ in values only
        F = 0.9 * rng.standard_normal((n, n)) / np.sqrt(n)
        B, H = rng.standard_normal((n, inputs)), rng.standard_normal((m, n))
        Phi = rng.standard_normal((T, n, p))
        A, C = rng.standard_normal((n, n)), rng.standard_normal((m, m))
        Q, R = 0.01 * A @ A.T + 1e-3 * np.eye(n), 0.1 * C @ C.T + 0.05 * np.eye(m)
        x0, P0 = rng.standard_normal(n), rng.uniform(0.1, 2) * np.eye(n)
        theta0, S0 = rng.standard_normal(p), rng.uniform(0.1, 5) * np.eye(p)
        ys, us = rng.standard_normal((T, m)), rng.standard_normal((T, inputs))
        ys[rng.random(ys.shape) < 0.1] = np.nan
        ys[5] = np.nan
        xs, thetas = augmented_kalman_filter(F, B, H, Phi, Q, R, x0, P0, theta0, S0, ys, us)
        model = DiscreteLTV(*map(jnp.asarray, (F, B, H)), StackedRegressor(jnp.asarray(Phi)))
        prior = ObserverPrior(*map(jnp.asarray, (x0, theta0, P0, S0)))
        tuned = eqx.tree_at(lambda o: (o.Q, o.R), observer, (jnp.asarray(Q), jnp.asarray(R)))
        result = run(tuned, model, jnp.asarray(ys), inputs=jnp.asarray(us), prior=prior)
        assert np.all(np.asarray(result.status) == Status.OK)
        np.testing.assert_allclose(result.x, xs, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(result.theta, thetas, rtol=1e-10, atol=1e-12)


def test_missing_measurements_are_not_measured():
    """NaN in y (the protocol's missing data) drops those rows: the discrete form equals a NumPy
    recursion that deletes them, and noise-free both forms still converge, the continuous one
    more slowly than without gaps (before, one NaN made every later estimate NaN)."""
    with enable_x64():
        model, obs, prior, Kbar, theta = charlie_setup()
        sim = simulate_closed_loop(obs, model, theta, jnp.asarray(X0), prior, Kbar, multisine(8000))
        rng = np.random.default_rng(0)
        ys = np.asarray(sim.observations).copy()
        ys[rng.random(ys.shape[0]) < 0.05] = np.nan  # whole samples
        ys[rng.random(ys.shape) < 0.05] = np.nan  # single channels
        ys[0] = np.nan
        missing = np.isnan(ys)
        dmodel = model.discretize(DT)
        dobs = DiscreteAdaptiveObserver(Q=1e-4 * jnp.eye(4), R=1e-2 * jnp.eye(3), forgetting=0.99)
        dprior = ObserverPrior(jnp.zeros(4), jnp.ones(1), jnp.eye(4), 10.0 * jnp.eye(1))
        res = run(dobs, dmodel, jnp.asarray(ys), inputs=sim.inputs, prior=dprior)
        Phi = phi_per_step(dmodel, sim.inputs[:400])
        xs, thetas, _ = numpy_discrete_observer(
            *(np.asarray(a) for a in (dmodel.F, dmodel.B, dmodel.H)), Phi, 1e-4 * np.eye(4),
            1e-2 * np.eye(3), 0.99, np.zeros(4), np.eye(4), np.ones(1), 10.0 * np.eye(1),
            ys[:400], np.asarray(sim.inputs[:400]),
        )  # fmt: skip
        np.testing.assert_allclose(res.theta[:400], thetas, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(res.x[:400], xs, rtol=1e-9, atol=1e-12)
        for result in (res, run(obs, model, jnp.asarray(ys), inputs=sim.inputs, prior=prior)):
            assert np.all(np.asarray(result.status) == Status.OK)
            assert np.all(np.asarray(result.innovation)[missing] == 0.0)
            error = np.abs(np.asarray(result.theta[:, 0]) - float(theta[0]))
            assert error[-1] < 1e-5 * abs(float(theta[0])) and error[-1] < 1e-2 * error[4000]


def test_a_channel_missing_throughout_equals_the_model_without_it():
    """y's second channel NaN at every step: the continuous observer, with the Riccati gain and
    with a fixed one, runs as on the model that lacks that row of C, with R and Sigma restricted
    to the measured channels (non-diagonal, so that a product left unmasked would show)."""
    with enable_x64():
        model, obs, prior, Kbar, theta = charlie_setup()
        sim = simulate_closed_loop(obs, model, theta, jnp.asarray(X0), prior, Kbar, multisine(1500))
        ys = np.asarray(sim.observations).copy()
        ys[:, 1] = np.nan
        kept = np.array([0, 2])
        R = jnp.array([[1.0, 0.3, 0.1], [0.3, 2.0, 0.2], [0.1, 0.2, 1.5]])
        Sigma = jnp.array([[2.0, 0.5, -0.3], [0.5, 1.0, 0.4], [-0.3, 0.4, 1.0]])
        K = 0.5 * model.C.T  # A - K C is stable for the Charlie model at both sizes
        reduced = ContinuousLTV(model.A, model.B, model.C[kept], model.psi)
        riccati = eqx.tree_at(lambda o: (o.R, o.Sigma), obs, (R, Sigma))
        fixed = AdaptiveObserver(M=obs.M, Sigma=Sigma, K=K, dt=DT)
        for full, part in (
            (riccati, eqx.tree_at(lambda o: (o.R, o.Sigma), obs, (R[kept][:, kept], Sigma[kept][:, kept]))),
            (fixed, AdaptiveObserver(M=obs.M, Sigma=Sigma[kept][:, kept], K=K[:, kept], dt=DT)),
        ):  # fmt: skip
            with_gap = run(full, model, jnp.asarray(ys), inputs=sim.inputs, prior=prior)
            without = run(part, reduced, jnp.asarray(ys[:, kept]), inputs=sim.inputs, prior=prior)
            for field in ("x", "theta", "Gamma", "excitation"):
                np.testing.assert_allclose(
                    getattr(with_gap, field), getattr(without, field), rtol=1e-9, atol=1e-12
                )
            assert np.all(np.asarray(with_gap.status) == np.asarray(without.status))


def windup_reproduction():
    """Issue 18's reproduction: the input off from 30 s to 70 s, forgetting 0.99."""
    A = jnp.array([[-1.0, 1.0], [0.0, -2.0]])
    B = jnp.array([[0.0], [1.0]])
    C = jnp.array([[1.0, 0.0]])
    dm = ContinuousLTV(A, jnp.zeros_like(B), C, InputEffectiveness(B)).discretize(0.01)
    T, theta = 8000, jnp.array([2.0])
    t = np.arange(T) * 0.01
    u = (np.sin(1.3 * t) + np.sin(3.1 * t))[:, None]
    u[3000:7000] = 0.0
    u = jnp.asarray(u)

    def step(x, ku):
        return dm.F @ x + dm.B @ ku[1] + dm.phi(ku[0], ku[1], None) @ theta, C @ x

    ys = jax.lax.scan(step, jnp.zeros(2), (jnp.arange(T), u))[1]
    ys = ys + 0.01 * jax.random.normal(jax.random.PRNGKey(0), (T, 1))
    prior = ObserverPrior(jnp.zeros(2), jnp.ones(1), jnp.eye(2), jnp.eye(1))
    return dm, ys, u, prior


def test_forgetting_does_not_wind_up_and_the_unexcited_interval_is_flagged():
    with enable_x64():
        dm, ys, u, prior = windup_reproduction()
        obs = DiscreteAdaptiveObserver(Q=1e-6 * jnp.eye(2), R=1e-4 * jnp.eye(1), forgetting=0.99)
        res = run(obs, dm, ys, inputs=u, prior=prior)
        error = np.abs(np.asarray(res.theta[:, 0]) - 2.0)
        assert error[7000:7500].max() < 0.05 * 2.0  # 70-75 s, after the input returns
        assert error[7000:].max() < 0.05 * 2.0 and error[1000:3000].max() < 0.05 * 2.0
        lost = (np.asarray(res.status) & Status.NOT_EXCITED) != 0
        assert lost[3500:7000].all()  # from 5 s after the input stops to its return
        assert not lost[200:3000].any() and not lost[7100:].any()  # excited once the window fills
        assert np.all((np.asarray(res.status) & ~Status.NOT_EXCITED) == 0)
        # the same run by the NumPy recursion, and the paper's forgetting, which winds up
        Phi = phi_per_step(dm, u)
        args = [np.asarray(v) for v in (dm.F, dm.B, dm.H)] + [Phi, 1e-6 * np.eye(2)]
        args += [1e-4 * np.eye(1), 0.99, np.zeros(2), np.eye(2), np.ones(1), np.eye(1)]
        _, thetas, _ = numpy_discrete_observer(*args, np.asarray(ys), np.asarray(u))
        np.testing.assert_allclose(res.theta, thetas, rtol=1e-7)
        _, wound, _ = numpy_discrete_observer(
            *args, np.asarray(ys), np.asarray(u), anti_windup=False
        )
        assert np.abs(wound[7000:7500, 0] - 2.0).max() > 100


def test_discrete_model_takes_matrices_stacked_over_time():
    """Stacked F_k, B_k, H_k give the callables' results; a time-varying A(t) is sampled."""
    with enable_x64():
        model, A0 = _ltv_model()
        dt, T = 0.05, 60
        sampled = model.discretize(dt, steps=T)
        assert sampled.F.shape == (T, 2, 2) and sampled.B.shape == (T, 2, 1)
        # one sample interval against scipy's integrator (u, psi held at t_k)
        rng = np.random.default_rng(0)
        theta = np.array([0.7, -0.4])
        for k in (0, 17, 59):
            x, u, y = rng.normal(size=2), rng.normal(size=1), rng.normal(size=1)
            F, B, _ = sampled.matrices(k)
            x_next = F @ x + B @ u + sampled.phi(k, jnp.asarray(u), jnp.asarray(y)) @ theta
            t0 = k * dt
            forcing = np.asarray(model.B @ u + model.psi(t0, u, y) @ theta)
            sol = scipy.integrate.solve_ivp(
                lambda t, z: np.asarray(model.A(t)) @ z + forcing,
                (t0, t0 + dt),
                x,
                rtol=1e-12,
                atol=1e-14,
            )
            np.testing.assert_allclose(x_next, sol.y[:, -1], rtol=1e-9, atol=1e-12)
            np.testing.assert_allclose(sampled.matrices(k)[2], model.C(t0), rtol=1e-15)
        # the observer reads stacked matrices as it reads callables of k
        as_callables = DiscreteLTV(
            lambda k: sampled.F[k], lambda k: sampled.B[k], sampled.H, sampled.phi
        )
        ys = jnp.asarray(rng.normal(size=(T, 1)))
        us = jnp.asarray(rng.normal(size=(T, 1)))
        obs = DiscreteAdaptiveObserver(Q=1e-3 * jnp.eye(2), R=1e-2 * jnp.eye(1), forgetting=0.98)
        prior = ObserverPrior(jnp.zeros(2), jnp.zeros(2), jnp.eye(2), jnp.eye(2))
        stacked = run(obs, sampled, ys, inputs=us, prior=prior)
        called = run(obs, as_callables, ys, inputs=us, prior=prior)
        np.testing.assert_allclose(stacked.theta, called.theta, rtol=1e-12, atol=1e-14)
        with pytest.raises(ValueError, match="^steps:"):
            model.discretize(dt)
        # past the stacked steps F[k] would be F[T-1] (clamped indexing): the run says so
        longer = lambda a: jnp.concatenate([a, a[:5]])
        with pytest.raises(ValueError, match=r"^model.F: time-varying with 60 steps"):
            run(obs, sampled, longer(ys), inputs=longer(us), prior=prior)


def _loss(obs, model, prior, Kbar, theta, r):
    sim = simulate_closed_loop(obs, model, theta, jnp.asarray(X0, r.dtype), prior, Kbar, r)
    return jnp.mean((sim.estimate.theta - theta) ** 2)


def _discrete_loss(obs, model, prior, ys, us):
    return jnp.mean((run(obs, model, ys, inputs=us, prior=prior).theta - 2.0) ** 2)


@pytest.mark.parametrize("x64", [False, True])
def test_jit_vmap_grad(x64):
    """One unbatched jit compile and one jit(vmap(value_and_grad)) compile per observer."""
    with enable_x64(x64):
        dtype = jnp.float64 if x64 else jnp.float32
        model, obs, prior, Kbar, theta = charlie_setup(dtype, M=5.0)
        r = multisine(100, dtype=dtype)
        amps = jnp.asarray([0.5, 1.0, 2.0], dtype)
        loss = eqx.filter_jit(_loss)
        batched = eqx.filter_jit(
            jax.vmap(
                lambda o, a: eqx.filter_value_and_grad(_loss)(o, model, prior, Kbar, theta, a * r),
                in_axes=(None, 0),
            )
        )
        values, grads = batched(obs, amps)
        looped = jnp.stack([loss(obs, model, prior, Kbar, theta, a * r) for a in amps])
        assert values.dtype == dtype and bool(jnp.all(jnp.isfinite(values)))
        np.testing.assert_allclose(values, looped, rtol=1e-4 if not x64 else 1e-12)
        for g in (grads.M, grads.Sigma, grads.Q, grads.R):
            assert bool(jnp.all(jnp.isfinite(g))) and bool(jnp.any(g != 0))
        if x64:  # central finite differences in M, Sigma[0, 0] and Q[3, 3] (second amplitude)
            h = 1e-4
            for get, direction in (
                (lambda o: o.M, jnp.ones((1, 1))),
                (lambda o: o.Sigma, jnp.zeros((3, 3)).at[0, 0].set(1.0)),
                (lambda o: o.Q, jnp.zeros((4, 4)).at[3, 3].set(1.0)),
            ):
                plus = eqx.tree_at(get, obs, get(obs) + h * direction)
                minus = eqx.tree_at(get, obs, get(obs) - h * direction)
                fd = (
                    loss(plus, model, prior, Kbar, theta, r)
                    - loss(minus, model, prior, Kbar, theta, r)
                ) / (2 * h)
                np.testing.assert_allclose(jnp.sum(get(grads)[1] * direction), fd, rtol=1e-5)
        # the discrete form on recorded data: vmap over measurement noise, grad to Q and R
        dmodel = model.discretize(DT)
        sim = simulate_closed_loop(obs, model, theta, jnp.asarray(X0, dtype), prior, Kbar, r)
        dobs = DiscreteAdaptiveObserver(
            Q=1e-4 * jnp.eye(4, dtype=dtype), R=1e-2 * jnp.eye(3, dtype=dtype)
        )
        dprior = ObserverPrior(
            jnp.zeros(4, dtype),
            jnp.ones(1, dtype),
            jnp.eye(4, dtype=dtype),
            jnp.eye(1, dtype=dtype),
        )
        noise = 1e-3 * jax.random.normal(jax.random.PRNGKey(0), (3, *sim.observations.shape), dtype)
        dloss = eqx.filter_jit(_discrete_loss)
        dvalues, dgrads = eqx.filter_jit(
            jax.vmap(
                lambda v: eqx.filter_value_and_grad(_discrete_loss)(
                    dobs, dmodel, dprior, sim.observations + v, sim.inputs
                )
            )
        )(noise)
        dlooped = jnp.stack(
            [dloss(dobs, dmodel, dprior, sim.observations + v, sim.inputs) for v in noise]
        )
        np.testing.assert_allclose(dvalues, dlooped, rtol=1e-4 if not x64 else 1e-12)
        assert bool(jnp.all(jnp.isfinite(dgrads.Q))) and bool(jnp.all(jnp.isfinite(dgrads.R)))
        if x64:
            h = 1e-7
            plus = eqx.tree_at(lambda o: o.R, dobs, dobs.R * (1 + h))
            minus = eqx.tree_at(lambda o: o.R, dobs, dobs.R * (1 - h))
            fd = (
                dloss(plus, dmodel, dprior, sim.observations + noise[0], sim.inputs)
                - dloss(minus, dmodel, dprior, sim.observations + noise[0], sim.inputs)
            ) / (2 * h)
            np.testing.assert_allclose(jnp.sum(dgrads.R[0] * dobs.R), fd, rtol=1e-5)


def test_bad_arguments_raise():
    """Settings of the wrong kind are named when the observer is made: a float substeps failed
    in fori_loop with a TypeError, an infinite dt and a NaN t0 ran on, NaN from the first step."""
    model, obs, prior, _, _ = charlie_setup(jnp.float32)
    with pytest.raises(ValueError, match="M"):
        AdaptiveObserver(M=-jnp.eye(1), Sigma=jnp.eye(3), Q=jnp.eye(4), R=jnp.eye(3))
    with pytest.raises(ValueError, match="K"):
        AdaptiveObserver(M=jnp.eye(1), Sigma=jnp.eye(3))
    with pytest.raises(ValueError, match="Sigma"):
        AdaptiveObserver(M=jnp.eye(1), Sigma=jnp.eye(2), Q=jnp.eye(4), R=jnp.eye(3)).init(
            model, prior
        )
    with pytest.raises(ValueError, match=r"^prior.theta: expected shape \(1,\), one entry per "):
        obs.init(model, ObserverPrior(prior.x, jnp.ones(2), prior.P))
    tuning = dict(M=jnp.eye(1), Sigma=jnp.eye(3), Q=jnp.eye(4), R=jnp.eye(3))
    for message, settings in (
        ("^substeps: must be a positive integer, got 2.5", dict(substeps=2.5)),
        ("^substeps: must be a positive integer, got 0", dict(substeps=0)),
        ("^dt: must be a positive number, got inf", dict(dt=np.inf)),
        ("^dt: must be a positive number, got -0.01", dict(dt=-0.01)),
        ("^t0: must be a finite number, got nan", dict(t0=np.nan)),
    ):
        with pytest.raises(ValueError, match=message):
            AdaptiveObserver(**tuning, **settings)


def test_a_fixed_gain_the_observer_cannot_converge_with_is_named():
    """A fixed K with A - K C unstable, or a Runge-Kutta step unstable for it: the estimate
    diverged with status OK until it overflowed (K = [-3, 0]^T: an error above 1 from step 68,
    NONFINITE at step 354; K = [600, 0]^T at dt = 0.01 in one substep: from step 2, NONFINITE at
    step 19). RK4 is stable on the negative real axis down to -2.785: 600 dt / 3 = 2 is the
    fewest substeps. Both are named before tracing, by run and in a closure, and an adequate
    gain runs."""
    A, C = jnp.asarray([[0.0, 1.0], [-2.0, -0.5]]), jnp.asarray([[1.0, 0.0]])
    B = jnp.asarray([[0.0], [1.0]])
    model = ContinuousLTV(A, B, C, InputEffectiveness(B))
    prior = ObserverPrior(jnp.zeros(2), jnp.ones(1))
    ys, us = jnp.zeros((5, 1)), jnp.zeros((5, 1))
    observer = lambda K, substeps=1: AdaptiveObserver(
        M=jnp.eye(1), Sigma=jnp.eye(1), K=jnp.asarray(K), dt=0.01, substeps=substeps
    )
    unstable, stiff = observer([[-3.0], [0.0]]), observer([[600.0], [0.0]])
    for obs, match in ((unstable, r"^K: A - K C must be stable.* up to 2.28"),
                       (stiff, r"^substeps: .* take substeps >= 3 ")):  # fmt: skip
        with pytest.raises(ValueError, match=match):
            run(obs, model, ys, prior=prior, inputs=us)
        with pytest.raises(ValueError, match=match):
            jax.jit(lambda: obs.init(model, prior))()
    for obs in (observer([[600.0], [0.0]], substeps=3), observer([[3.0], [2.0]])):
        assert int(run(obs, model, ys, prior=prior, inputs=us).any_status) == 0


def test_aircraft_models():
    A_pub, B_pub = b747()
    A_pr, B_pr = b747(printed=True)
    assert np.max(np.linalg.eigvals(A_pub).real) < 0  # published: stable (slow spiral -0.007)
    assert np.max(np.linalg.eigvals(A_pr).real) > 0.04  # the scan's A[2, 0] = 0.305: divergent
    assert B_pr[2, 1] == 1.063 and B_pub[2, 1] == 0.143
    for name in ("charlie", "b747"):
        ac = aircraft(name)
        obsv = np.vstack([ac["C"] @ np.linalg.matrix_power(ac["A"], k) for k in range(4)])
        assert np.linalg.matrix_rank(obsv) == 4
    with pytest.raises(ValueError, match="name"):
        aircraft("concorde")


def test_smallest_eigenvalue_closed_forms():
    from jaxest.observers.excitation import smallest_eigenvalue

    rng = np.random.default_rng(0)
    for p in (1, 2, 3):
        X = rng.normal(size=(p, p))
        W = X @ X.T
        np.testing.assert_allclose(
            smallest_eigenvalue(jnp.asarray(W)), np.linalg.eigvalsh(W)[0], rtol=1e-5, atol=1e-6
        )


def test_run_names_bad_arguments_before_tracing():
    """The observers' arguments were checked only inside the trace: ys one column too wide ran
    on, broadcast; an indefinite P ran with status OK; a missing input, a list A, a C of the
    wrong width, a psi that is not a function or the other observer's model raised TypeErrors
    and AttributeErrors from inside; inputs one step short, JAX's error about scan's axes; a phi
    of the wrong shape and a NaN or integer prior.x or prior.theta, below."""
    A, C = jnp.asarray([[0.0, 1.0], [-2.0, -0.5]]), jnp.asarray([[1.0, 0.0]])
    B = jnp.asarray([[0.0], [1.0]])
    model = ContinuousLTV(A, B, C, InputEffectiveness(B))
    obs = AdaptiveObserver(M=jnp.eye(1), Sigma=jnp.eye(1), Q=jnp.eye(2), R=jnp.eye(1), dt=0.01)
    prior = ObserverPrior(jnp.zeros(2), jnp.ones(1), jnp.eye(2))
    discrete = model.discretize(0.01)
    matrices = (discrete.F, discrete.B, discrete.H)
    dobs = DiscreteAdaptiveObserver(1e-4 * jnp.eye(2), jnp.eye(1))
    dprior = ObserverPrior(jnp.zeros(2), jnp.ones(1), jnp.eye(2), jnp.eye(1))
    ys, us = jnp.zeros((5, 1)), jnp.ones((5, 1))
    cases = [
        (r"^ys: expected 1 column\(s\) \(model.C has 1 rows\), got 2", obs, model, jnp.zeros((5, 2)), us, prior),
        ("^ys: contains", obs, model, ys.at[2].set(jnp.inf), us, prior),
        ("^prior.P: must be positive definite", obs, model, ys, us, ObserverPrior(prior.x, prior.theta, -jnp.eye(2))),
        ("^prior.theta_cov: must be positive definite", dobs, discrete, ys, us, ObserverPrior(prior.x, prior.theta, jnp.eye(2), -jnp.eye(1))),
        (r"^inputs: the observer holds u_k .* shape \(T, 1\)", obs, model, ys, None, prior),
        ("^inputs: has 4 time steps but the measurements have 5", obs, model, ys, us[:4], prior),
        (r"^inputs: expected 1 column\(s\)", dobs, discrete, ys, jnp.ones((5, 2)), dprior),
        ("^model.A: expected an array, got list", obs, ContinuousLTV(A.tolist(), B, C, model.psi), ys, us, prior),
        (r"^model: its A \(2, 2\), B \(2, 1\) and C \(1, 3\) do not fit", obs, ContinuousLTV(A, B, jnp.ones((1, 3)), model.psi), ys, us, prior),
        ("^model.psi: expected a function, got int", obs, ContinuousLTV(A, B, C, 3), ys, us, prior),
        ("^model: expected a ContinuousLTV, got DiscreteLTV", obs, discrete, ys, us, prior),
        ("^model: expected a DiscreteLTV, got ContinuousLTV", dobs, model, ys, us, dprior),
        # named only by the protocol check before, as a state that changed dtype after one step
        ("^prior: is float32, narrower than", dobs, discrete, ys, us, je.astype(dprior, jnp.float32)),
        # phi of the wrong height: a TypeError from the trace; of another width than prior.theta:
        # blamed on the estimator (its step changed state.Ups_pred)
        (r"^model.phi: expected an \(n, p\) = \(2, p\) matrix, got \(3, 1\)", dobs, DiscreteLTV(*matrices, lambda k, u, y: jnp.ones((3, 1))), ys, us, dprior),
        (r"^model.phi: expected an \(n, p\) = \(2, p\) matrix, got \(2,\)", dobs, DiscreteLTV(*matrices, lambda k, u, y: jnp.ones(2)), ys, us, dprior),
        (r"^prior.theta: expected shape \(3,\), one entry per column of model.phi \(2, 3\), got \(1,\)", dobs, DiscreteLTV(*matrices, lambda k, u, y: jnp.ones((2, 3))), ys, us, dprior),
        # NaN in the prior's vectors ran with status NONFINITE (a Gaussian's mean is refused)
        ("^prior.x: contains NaN", obs, model, ys, us, ObserverPrior(prior.x.at[0].set(jnp.nan), prior.theta, prior.P)),
        ("^prior.theta: contains NaN", dobs, discrete, ys, us, eqx.tree_at(lambda p: p.theta, dprior, jnp.full(1, jnp.nan))),
        ("^prior.x: must be real floating point, got int32", dobs, discrete, ys, us, eqx.tree_at(lambda p: p.x, dprior, jnp.zeros(2, jnp.int32))),
        (r"^prior.theta: expected a vector, got shape \(1, 1\)", obs, model, ys, us, ObserverPrior(prior.x, jnp.ones((1, 1)), prior.P)),
    ]  # fmt: skip
    for message, observer, model_, ys_, us_, prior_ in cases:
        with pytest.raises(ValueError, match=message):
            run(observer, model_, ys_, inputs=us_, prior=prior_)
    assert int(run(dobs, discrete, ys, inputs=us, prior=dprior).any_status) == 0
