"""Steady-state Kalman machinery and the fixed-interval Wiener smoother (Sun & Cui 2003)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import enable_x64
from scipy.linalg import solve_discrete_are

import jaxest as je
from jaxest.filters.kalman import KalmanFilter
from jaxest.filters.steady_state import SteadyStateKalmanFilter, steady_state_gain
from jaxest.smoothers.steady_state import (
    arma_innovation_model,
    characteristic_polynomial,
    fixed_point_smooth,
    steady_state_smooth,
)
from jaxest.smoothers.wiener import WienerSmoother, lagged_sum, wiener_smooth
from jaxest.systems.wiener_example import ARBITRARY_START, PAPER, PRINTED_ADJ_K, paper_model
from tests.lowering import programs_compiled
from tests.reference import kalman_filter, rts_smoother

wiener_smooth_jit = jax.jit(wiener_smooth, static_argnames=("start", "end_term"))
steady_state_smooth_jit = jax.jit(
    lambda model, ys, prior: steady_state_smooth(model, ys, prior=prior)
)


def simulate(model, T, seed=0):
    n = model.F.shape[0]
    return je.simulate(model, jnp.zeros(n, model.F.dtype), T, jax.random.key(seed)).y


def three_state_model(Phi_diag=(0.95, 0.6, 0.1)):
    """x in R^3, y in R^2, diagonal dynamics mixed by a fixed rotation (distinct real eigenvalues)."""
    rng = np.random.default_rng(4)
    V = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    F = V @ np.diag(Phi_diag) @ V.T
    H = rng.normal(size=(2, 3))
    return je.LinearGaussian(F=jnp.asarray(F), H=jnp.asarray(H), Q=0.3 * jnp.eye(3), R=jnp.eye(2))


def test_paper_numbers_to_printed_decimals():
    with enable_x64(True):
        gain = steady_state_gain(paper_model())
        arma = arma_innovation_model(gain)
        lam = WienerSmoother.from_model(paper_model()).eigenvalues()
        got = {
            "Sigma": gain.Sigma,
            "K": gain.K[:, 0],
            "eigenvalues": lam.real,
            "ar_coeffs": arma.ar[:, 0, 0],
            "ma_coeffs": arma.ma,
            "smoother_transition": gain.smoother_transition,
            "innovation_gain": gain.innovation_gain[:, 0],
        }
        for name, value in got.items():
            np.testing.assert_allclose(
                np.round(np.asarray(value), 4), PAPER[name], atol=1e-12, err_msg=name
            )
        assert np.all(np.asarray(lam.imag) == 0)


def test_printed_adjugate_term_has_flipped_off_diagonal_signs():
    """Eq 28's q^-1 coefficient of adj(I - q^-1 Psi_f) K is reproduced only with the adjugate's
    off-diagonal signs flipped; the true coefficient satisfies A = Psi - H Phi adj K q^-1 (eq 7)."""
    with enable_x64(True):
        gain = steady_state_gain(paper_model())
        arma = arma_innovation_model(gain)
        adj_K = np.einsum("jab,b->ja", arma.adj, gain.K[:, 0])
        np.testing.assert_allclose(np.round(adj_K[0], 4), PRINTED_ADJ_K[0], atol=1e-12)
        np.testing.assert_allclose(adj_K[1], [-0.4496, -0.1387], atol=1e-4)
        flipped = np.asarray(arma.adj[1]) * np.array([[1, -1], [-1, 1]])
        np.testing.assert_allclose(
            np.round(flipped @ gain.K[:, 0], 4), PRINTED_ADJ_K[1], atol=1e-12
        )


def test_characteristic_polynomial_against_numpy():
    with enable_x64(True):
        M = np.random.default_rng(0).normal(size=(4, 4))
        coeffs, adj = characteristic_polynomial(jnp.asarray(M))
        np.testing.assert_allclose(coeffs, np.poly(M), rtol=1e-10, atol=1e-12)
        z = 0.37
        adj_at_z = sum(adj[j] * z**j for j in range(4))
        I_Mz = np.eye(4) - M * z
        np.testing.assert_allclose(adj_at_z, np.linalg.det(I_Mz) * np.linalg.inv(I_Mz), rtol=1e-10)


@pytest.mark.parametrize("make_model", [paper_model, three_state_model], ids=["paper", "3-state"])
def test_arma_innovation_model_lemma2(make_model):
    """A(q^-1) y(s) = Psi(q^-1) eps(s) for every s > n (eq 6), eps from the steady-state filter."""
    with enable_x64(True):
        model = make_model()
        n = model.F.shape[0]
        ys = simulate(model, 60)
        arma = arma_innovation_model(steady_state_gain(model))
        eps = je.run(
            SteadyStateKalmanFilter(), model, ys, prior=je.Gaussian(jnp.ones(n), jnp.eye(n))
        ).innovation
        lhs = lagged_sum(arma.ar, ys)
        rhs = lagged_sum(arma.ma[:, None, None] * jnp.eye(ys.shape[1]), eps)
        np.testing.assert_allclose(lhs[1:], rhs[1:], atol=1e-11)


def numpy_rts(model, ys, m0, P0):
    """Plain NumPy Kalman filter + Rauch-Tung-Striebel smoother (an independent reference)."""
    F, H, Q, R = (np.asarray(a) for a in (model.F, model.H, model.Q, model.R))
    filtered = kalman_filter(
        F, H, Q, R, m0, P0, np.asarray(ys), G=np.asarray(model.process_noise(None, None, 0)[0])
    )
    return rts_smoother(F, *filtered[:4])[0]


@pytest.mark.parametrize("make_model", [paper_model, three_state_model], ids=["paper", "3-state"])
def test_steady_state_smoother_is_rts_started_in_steady_state(make_model):
    """With P(0|-1) = Sigma the Kalman filter never leaves its steady state, so the RTS smoother
    and eq 15 coincide."""
    with enable_x64(True):
        model = make_model()
        n = model.F.shape[0]
        ys = simulate(model, 80, seed=1)
        m0 = jnp.linspace(-1.0, 1.0, n)
        Sigma = steady_state_gain(model).Sigma
        ours = steady_state_smooth_jit(model, ys, je.Gaussian(m0, jnp.eye(n)))
        np.testing.assert_allclose(ours.mean, numpy_rts(model, ys, m0, Sigma), atol=1e-10)


def test_fixed_point_smoother_lemma3_term_by_term():
    """Eq 8 accumulated term by term reaches eq 15's x(t|N) (computed by the backward recursion)."""
    with enable_x64(True):
        model = three_state_model()
        ys = simulate(model, 50, seed=2)
        ss = steady_state_smooth_jit(model, ys, je.Gaussian(jnp.zeros(3), jnp.eye(3)))
        gain = jax.jit(steady_state_gain)(model)
        for t in (0, 17, 48, 49):
            path = jax.jit(fixed_point_smooth)(gain, ss.filtered_mean[t], ss.innovation[t + 1 :])
            np.testing.assert_allclose(path[-1], ss.mean[t], atol=1e-12)
            np.testing.assert_allclose(path[0], ss.filtered_mean[t], atol=0)


def test_steady_state_filter_matches_kalman_filter_from_sigma():
    with enable_x64(True):
        model = paper_model()
        ys = simulate(model, 40)
        Sigma = steady_state_gain(model).Sigma
        prior = je.Gaussian(jnp.array([0.5, -0.5]), Sigma)
        ours = je.run(SteadyStateKalmanFilter(), model, ys, prior=prior)
        ref = je.run(KalmanFilter(), model, ys, prior=prior)
        for field in (
            "mean",
            "cov",
            "predicted_mean",
            "predicted_cov",
            "innovation",
            "loglik_terms",
        ):
            np.testing.assert_allclose(
                getattr(ours, field), getattr(ref, field), atol=1e-10, err_msg=field
            )
        assert np.all(np.asarray(ours.status) == 0)


def test_steady_state_gain_names_F_and_H_and_is_never_silently_wrong():
    """An undetectable (F, H) raises naming F and H; under jit its Sigma is NaN, its status
    NOT_STABILISING (the filter's and the steady-state smoother's status then say NONFINITE).
    Unobservable modes outside the unit circle need no detectability: F = 2, H = 1, Q = 0 gives
    Sigma = 3, where the Kalman filter converges."""
    with enable_x64(True):
        undetectable = je.LinearGaussian(
            F=jnp.diag(jnp.array([2.0, 0.5])), H=jnp.array([[0.0, 1.0]]), Q=jnp.eye(2), R=jnp.eye(1)
        )
        with pytest.raises(ValueError, match=r"^\(F, H\): not detectable: the mode 2 of F"):
            steady_state_gain(undetectable)
        gain = jax.jit(steady_state_gain)(undetectable)
        assert not np.any(np.isfinite(gain.Sigma))
        # and the gain says why (it used to hold the NaN alone)
        assert int(gain.status) & je.RiccatiStatus.NOT_STABILISING and not bool(gain.ok)
        ys = jnp.zeros((5, 1))
        filtered = jax.jit(
            lambda model: je.run(
                SteadyStateKalmanFilter(), model, ys, prior=je.Gaussian(jnp.zeros(2), jnp.eye(2))
            )
        )(undetectable)
        assert np.all(np.asarray(filtered.status) & je.Status.NONFINITE)
        smoothed = steady_state_smooth_jit(undetectable, ys, je.Gaussian(jnp.zeros(2), jnp.eye(2)))
        assert np.all(np.asarray(smoothed.status) & je.Status.NONFINITE)  # it says so too
        # and both say why (they said NONFINITE alone, the gain's reason lost)
        for result in (filtered, smoothed):
            assert result.flags is je.SteadyStateStatus
            assert np.all(np.asarray(result.status) & je.SteadyStateStatus.NO_STEADY_STATE)
            assert "NO_STEADY_STATE" in result.flags.describe(result.any_status)
        scalar = je.LinearGaussian(
            F=jnp.array([[2.0]]), H=jnp.array([[1.0]]), Q=jnp.zeros((1, 1)), R=jnp.eye(1)
        )
        for gain in (steady_state_gain(scalar), jax.jit(steady_state_gain)(scalar)):
            np.testing.assert_allclose(gain.Sigma, [[3.0]], rtol=1e-14)
            assert bool(gain.ok)
        # the Kalman filter from any prior converges to it: P(t|t-1) = 4 P / (1 + P) -> 3
        P = 10.0
        for _ in range(60):
            P = 4 * P / (1 + P)
        np.testing.assert_allclose(P, 3.0, rtol=1e-12)


def test_from_model_outside_jit_compiles_its_arithmetic_as_a_few_programs():
    """After the eager argument checks, the noise covariance, the Riccati solution, the gain and
    the ARMA model are a program each (op by op outside ``jit``, ``from_model`` of the paper's
    model compiled 90 programs)."""
    model = je.LinearGaussian(  # a 2-state / 1-output model no other test here compiles for
        F=jnp.array([[0.9, 0.1], [0.0, 0.5]]), H=jnp.array([[1.0, 0.0]]), Q=0.3 * jnp.eye(2),
        R=jnp.eye(1),
    )  # fmt: skip
    assert programs_compiled(WienerSmoother.from_model, model) <= 8
    Sigma = WienerSmoother.from_model(model).gain.Sigma
    F, H, Q, R = (np.asarray(a) for a in (model.F, model.H, model.Q, model.R))
    np.testing.assert_allclose(Sigma, solve_discrete_are(F.T, H.T, Q, R), rtol=1e-10)


def test_smooth_requires_the_final_innovations():
    """WienerSmoother.smooth has no silent default: the end term or an explicit None."""
    with enable_x64(True):
        model = paper_model()
        ys = simulate(model, 101, seed=1)
        smoother = WienerSmoother.from_model(model)
        optimal, final = smoother.optimal_start(ys, jnp.zeros(2))
        with pytest.raises(TypeError, match="final_innovations"):
            smoother.smooth(ys, optimal)
        reference = steady_state_smooth_jit(model, ys, je.Gaussian(jnp.zeros(2), jnp.eye(2))).mean
        assert np.max(np.abs(smoother.smooth(ys, optimal, final) - reference)) < 1e-8
        printed = smoother.smooth(ys, optimal, None)
        assert np.max(np.abs(printed - reference)) > 1e-2


@pytest.mark.parametrize("make_model", [paper_model, three_state_model], ids=["paper", "3-state"])
def test_wiener_with_optimal_start_equals_eq15_over_the_whole_interval(make_model):
    with enable_x64(True):
        model = make_model()
        n = model.F.shape[0]
        ys = simulate(model, 301, seed=3)
        prior = je.Gaussian(jnp.zeros(n), jnp.eye(n))
        reference = steady_state_smooth_jit(model, ys, prior).mean
        exact = wiener_smooth_jit(model, ys, prior=prior, start="optimal")
        assert np.max(np.abs(exact - reference)) < 1e-8
        # The theorem as printed (no end term) is off near t = N only, like |lambda_max|^(N - t).
        printed = wiener_smooth_jit(model, ys, prior=prior, start="optimal", end_term=False)
        error = np.max(np.abs(printed - reference), axis=1)
        assert error[-1] > 1e-2
        assert np.max(error[:100]) < 1e-6


def test_eq13_start_decays_like_the_far_eigenvalue_and_arbitrary_like_the_near_one():
    with enable_x64(True):
        model = paper_model()
        ys = simulate(model, 301, seed=5)
        smoother = WienerSmoother.from_model(model)
        lam = np.asarray(smoother.eigenvalues().real)
        optimal, final = smoother.optimal_start(ys, jnp.zeros(2))
        reference = smoother.smooth(ys, optimal, final)
        arbitrary = jnp.asarray(ARBITRARY_START)
        chosen = smoother.eq13_initial_values(arbitrary, optimal)
        np.testing.assert_allclose(chosen[0], arbitrary[0])
        np.testing.assert_allclose(
            chosen[1], optimal[1] + lam[1] * (arbitrary[0] - optimal[0]), rtol=1e-12
        )
        delta13 = np.asarray(smoother.smooth(ys, chosen, final) - reference)
        np.testing.assert_allclose(delta13[1:8] / delta13[:7], lam[1], rtol=1e-6)
        delta = np.asarray(smoother.smooth(ys, arbitrary, final) - reference)
        np.testing.assert_allclose(delta[61:100] / delta[60:99], lam[0], rtol=1e-6)


def vandermonde_eq23(lam_far, k, delta_free):
    """Eqs 22-23 literally: alpha^(j) = V^-1 [lambda^(n_d-k+j)] and delta(n_d-k+j) = sum alpha delta(l)."""
    nf = len(lam_far)
    V = np.vander(lam_far, nf, increasing=True)
    rows = []
    for j in range(k):
        alpha = np.linalg.solve(V, lam_far ** (nf + j))
        rows.append(alpha @ delta_free)
    return np.array(rows)


@pytest.mark.parametrize("radius", [0.55, 0.3], ids=["one-near", "two-near"])
def test_eq13_matches_the_vandermonde_formula(radius):
    with enable_x64(True):
        model = three_state_model()
        smoother = WienerSmoother.from_model(model)
        lam = np.asarray(smoother.eigenvalues().real)
        far = lam[np.abs(lam) <= radius]
        k = 3 - len(far)
        rng = np.random.default_rng(0)
        optimal, arbitrary = rng.normal(size=(3, 3)), rng.normal(size=(3, 3))
        chosen = np.asarray(
            smoother.eq13_initial_values(jnp.asarray(arbitrary), jnp.asarray(optimal), radius)
        )
        free = arbitrary[: 3 - k] - optimal[: 3 - k]
        np.testing.assert_allclose(chosen[: 3 - k], arbitrary[: 3 - k])
        np.testing.assert_allclose(
            chosen[3 - k :] - optimal[3 - k :], vandermonde_eq23(far, k, free), rtol=1e-9
        )


def oscillator_model():
    """A lightly damped oscillator plus a fast state: Psi_f has a complex pair near the unit circle."""
    c, s = np.cos(0.3), np.sin(0.3)
    F = np.zeros((3, 3))
    F[:2, :2] = 0.995 * np.array([[c, -s], [s, c]])
    F[2, 2] = 0.2
    F[2, 0] = 0.5
    H = np.array([[0.0, 0.0, 1.0]])
    return je.LinearGaussian(F=jnp.asarray(F), H=jnp.asarray(H), Q=0.01 * jnp.eye(3), R=jnp.eye(1))


def test_eq13_cancels_a_complex_near_pair():
    with enable_x64(True):
        model = oscillator_model()
        smoother = WienerSmoother.from_model(model)
        lam = np.asarray(smoother.eigenvalues())
        assert abs(lam[0].imag) > 0.05 and abs(lam[0]) > 0.5 and abs(lam[2]) < 0.5  # the setting
        ys = simulate(model, 200, seed=6)
        optimal, final = smoother.optimal_start(ys, jnp.zeros(3))
        reference = smoother.smooth(ys, optimal, final)
        arbitrary = jnp.full((3, 3), 5.0)
        delta = np.asarray(
            smoother.smooth(ys, smoother.eq13_initial_values(arbitrary, optimal), final) - reference
        )
        np.testing.assert_allclose(delta[1:6] / delta[:5], lam[2].real, rtol=1e-6)


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_jit_vmap_grad(dtype):
    with enable_x64(dtype == "float64"):
        model = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), paper_model())
        keys = jax.random.split(jax.random.key(0), 3)
        ys = jax.vmap(lambda k: je.simulate(model, jnp.zeros(2, dtype), 120, k).y)(keys)
        prior = je.Gaussian(jnp.zeros(2, dtype), jnp.eye(2, dtype=dtype))
        run = jax.jit(
            jax.vmap(
                lambda y: wiener_smooth(
                    model, y, prior=prior, initial_values=jnp.ones((2, 2), dtype), start="eq13"
                )
            )
        )
        xs = run(ys)
        assert xs.dtype == jnp.dtype(dtype) and xs.shape == (3, 120, 2)
        with enable_x64(True):
            ref = wiener_smooth(
                paper_model(),
                jnp.asarray(ys[1], jnp.float64),
                prior=je.Gaussian(jnp.zeros(2), jnp.eye(2)),
                initial_values=jnp.ones((2, 2)),
                start="eq13",
            )
        np.testing.assert_allclose(xs[1], ref, atol=1e-4 if dtype == "float32" else 1e-10)

        def loss(r):
            noisy = je.LinearGaussian(F=model.F, H=model.H, Q=model.Q, R=r * model.R, G=model.G)
            return jnp.sum(wiener_smooth(noisy, ys[0], prior=prior, start="optimal") ** 2)

        g = jax.jit(jax.grad(loss))(jnp.asarray(1.3, dtype))
        assert g.dtype == jnp.dtype(dtype) and np.isfinite(g)
        if dtype == "float64":
            fd = (loss(1.3 + 1e-6) - loss(1.3 - 1e-6)) / 2e-6
            np.testing.assert_allclose(g, fd, rtol=1e-6)


def clustered_model(n, eigenvalue, dtype=jnp.float64):
    """n states near ``eigenvalue`` (weakly coupled), one measurement: Psi_f's eigenvalues cluster
    there too, which is where the ARMA recursion amplifies rounding."""
    rng = np.random.default_rng(3)
    F = eigenvalue * np.eye(n) + 0.001 * np.triu(rng.normal(size=(n, n)), 1)
    arrays = (F, rng.normal(size=(1, n)), 1e-4 * np.eye(n), np.eye(1))
    return je.LinearGaussian(*(jnp.asarray(a, dtype) for a in arrays))


@pytest.mark.parametrize("n, eigenvalue", [(3, 0.99), (4, 0.999)])
def test_rounding_error_estimate_bounds_the_error(n, eigenvalue):
    with enable_x64():
        model = clustered_model(n, eigenvalue)
        ys = simulate(model, 3000)
        smoother = WienerSmoother.from_model(model)
        optimal, final = smoother.optimal_start(ys, jnp.zeros(n))
        exact = steady_state_smooth(model, ys, prior=je.Gaussian(jnp.zeros(n), jnp.eye(n))).mean
        error = float(jnp.max(jnp.abs(smoother.smooth(ys, optimal, final) - exact)))
        estimate = float(smoother.rounding_error(3000))
        assert error / float(jnp.max(jnp.abs(exact))) <= estimate < 1e-3


@pytest.mark.parametrize("n, eigenvalue, dtype", [(6, 0.999, "float64"), (3, 0.99, "float32")])
def test_smooth_raises_where_rounding_would_leave_no_accurate_digits(n, eigenvalue, dtype):
    # float64, n = 6: the recursion returned values 680 times the signal's size (finite, no
    # warning); float32 at n = 3 gave 1.2 % errors
    with enable_x64(dtype == "float64"):
        model = clustered_model(n, eigenvalue, jnp.dtype(dtype))
        ys = simulate(model, 3000)
        prior = je.Gaussian(jnp.zeros(n, model.F.dtype), jnp.eye(n, dtype=model.F.dtype))
        assert WienerSmoother.from_model(model).rounding_error(3000) > 1e-3
        for smooth in (wiener_smooth, jax.jit(wiener_smooth)):
            with pytest.raises(Exception, match="rounding in the ARMA recursion"):
                jax.block_until_ready(smooth(model, ys, prior=prior))


def far_from_normal_model(rng, n, eigenvalues, closeness=(3, 5), dtype=jnp.float64):
    """F = V diag(eigenvalues) V^-1 with two eigenvectors 10^-c apart, c uniform in
    ``closeness`` (for (3, 5), V of condition 1e4-1e6), one measurement."""
    V = rng.normal(size=(n, n))
    V[:, 1] = V[:, 0] + 10.0 ** -rng.uniform(*closeness) * V[:, 1]
    F = V @ np.diag(eigenvalues) @ np.linalg.inv(V)
    arrays = (F, rng.normal(size=(1, n)), 0.1 * np.eye(n), np.eye(1))
    return je.LinearGaussian(*(jnp.asarray(a, dtype) for a in arrays))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_rounding_error_estimate_counts_the_coefficients_error(seed):
    """Faddeev-LeVerrier loses digits where Psi_f is far from normal; with eps alone in the
    estimate it was 2 to 5.7e6 times below the error (a user's sweep of such models). The
    Cayley-Hamilton residual of the coefficients now enters it, and it bounds the error against
    the steady-state smoother, the same estimate computed stably."""
    rng = np.random.default_rng(seed)
    n = 5
    model = far_from_normal_model(rng, n, np.sort(rng.uniform(0.6, 0.97, n)))
    with enable_x64():
        ys = jnp.asarray(rng.normal(size=(300, 1)))
        prior = je.Gaussian(jnp.zeros(n), jnp.eye(n))
        exact = np.asarray(steady_state_smooth(model, ys, prior=prior).mean)
        error = np.max(np.abs(np.asarray(wiener_smooth(model, ys, prior=prior)) - exact))
        estimate = float(WienerSmoother.from_model(model).rounding_error(300))
        assert error / np.max(np.abs(exact)) <= estimate


def test_float32_smooth_raises_where_the_coefficients_lost_their_digits():
    """A float32 model far from normal whose Wiener smoother was 4.5 % off the float64
    steady-state smoother while the estimate, 7e-5 with eps alone, passed under the
    tolerance (the coefficients had lost their digits, not the recursion). It raises now."""
    n, rng = 5, np.random.default_rng(5)
    model = far_from_normal_model(rng, n, np.sort(rng.uniform(0.5, 0.9, n)), closeness=(1, 3))
    with enable_x64():
        ys = jnp.asarray(3 * rng.normal(size=(300, 1)))
        prior = je.Gaussian(jnp.zeros(n), jnp.eye(n))
        single = je.astype((model, ys, prior), jnp.float32)
        assert float(WienerSmoother.from_model(single[0]).rounding_error(300)) > 1e-3
        with pytest.raises(Exception, match="rounding in the ARMA recursion"):
            jax.block_until_ready(wiener_smooth(single[0], single[1], prior=single[2]))


def test_bad_arguments_name_the_argument():
    model = paper_model()
    ys = jnp.zeros((20, 1))
    prior = je.Gaussian(jnp.zeros(2), jnp.eye(2))
    with pytest.raises(ValueError, match="^start:"):
        wiener_smooth(model, ys, prior=prior, start="best")
    with pytest.raises(ValueError, match="^initial_values:"):
        wiener_smooth(model, ys, prior=prior, initial_values=jnp.zeros((3, 2)), start="eq13")
    with pytest.raises(ValueError, match="^prior:"):
        wiener_smooth(model, ys, start="optimal")
    with pytest.raises(ValueError, match="^ys:"):
        wiener_smooth(model, jnp.zeros((20, 2)), prior=prior)
    # a missing or infinite sample made every start's output NaN without a word
    initial = jnp.zeros((2, 2))
    for bad, message in ((jnp.nan, "^ys: has missing"), (jnp.inf, "^ys: contains")):
        for options in (dict(prior=prior), dict(initial_values=initial, start="arbitrary",
                                                end_term=False)):  # fmt: skip
            with pytest.raises(ValueError, match=message):
                wiener_smooth(model, ys.at[3, 0].set(bad), **options)
    with_input = je.LinearGaussian(
        F=model.F, H=model.H, Q=model.Q, R=model.R, G=model.G, B=jnp.ones((2, 1))
    )
    with pytest.raises(ValueError, match="^model.B:"):
        steady_state_gain(with_input)
    # these ran to an all-NaN result, or failed inside the trace with a TypeError
    eq13 = dict(initial_values=initial, start="eq13")
    cases = [
        (dict(prior=je.Gaussian(jnp.array([jnp.nan, 0.0]), jnp.eye(2))), "^prior.mean: contains"),
        (dict(initial_values=initial + jnp.nan, start="arbitrary"), "^initial_values: contains"),
        (dict(initial_values=[[0.0, 0.0], [0.0, 0.0]], start="arbitrary"), "^initial_values: expected an array"),
        (dict(initial_values=jnp.zeros((2, 2), int), start="arbitrary"), "^initial_values: must be real"),
        (dict(prior=je.Gaussian(jnp.zeros(2, jnp.float32), jnp.eye(2, dtype=jnp.float32))), "^prior: is float32"),
        (dict(prior=prior, radius=float("nan"), **eq13), "^radius: must be a number in"),
    ]  # fmt: skip
    for options, message in cases:
        with pytest.raises(ValueError, match=message):
            wiener_smooth(model, ys, **options)
    with pytest.raises(ValueError, match="^ys: need more than 3 samples, got 2"):
        wiener_smooth(model, ys[:2], prior=prior, **eq13)
    other = steady_state_gain(
        je.LinearGaussian(0.5 * jnp.eye(3), jnp.ones((1, 3)), jnp.eye(3), jnp.eye(1))
    )
    with pytest.raises(ValueError, match="^gain: is for 3 states and 1 measurements"):
        steady_state_smooth(model, ys, prior=prior, gain=other)


@pytest.mark.slow
def test_study_quick_writes_the_summary(tmp_path):
    import json

    from jaxest.studies import load

    with enable_x64(True):
        load("wiener").run(tmp_path, runs=8, seed=0, quick=True, options={})
    summary = json.loads((tmp_path / "wiener" / "summary.json").read_text())
    for key in (
        "Sigma",
        "K",
        "eigenvalues",
        "ar_coeffs",
        "ma_coeffs",
        "x1_chosen",
        "settling_steps",
        "mc_mse",
    ):
        assert key in summary, key
    assert all(summary["matches_paper_to_4_decimals"].values())
    assert summary["max_abs_wiener_optimal_minus_eq15"] < 1e-8
    steps = summary["settling_steps"]
    assert steps["optimal"] == 0 < steps["eq13"] < 10 < steps["arbitrary"]
    assert (
        abs(summary["decay_rate"]["eq13"] - 0.1043) < 1e-3
        and abs(summary["decay_rate"]["arbitrary"] - 0.9226) < 1e-3
    )
    assert set(summary["mc_mse"]) >= {
        "rts",
        "steady_state",
        "wiener_optimal",
        "wiener_eq13",
        "wiener_arbitrary",
    }
    assert (tmp_path / "wiener" / "delta.png").exists() and (
        tmp_path / "wiener" / "tables.md"
    ).exists()


def test_eq13_with_a_repeated_far_eigenvalue():
    """Psi_f with a Jordan block at 0.2 (far) and 0.9 (near): the chosen delta continues
    (1 - 0.2 q^-1)^2 delta(t) = 0, the t lambda^t mode included."""
    from jaxest.filters.steady_state import SteadyStateGain

    with enable_x64(True):
        Phi = jnp.array([[0.2, 1.0, 0.0], [0.0, 0.2, 0.0], [0.0, 0.0, 0.9]])
        gain = SteadyStateGain(
            Phi, jnp.zeros((1, 3)), jnp.eye(3), jnp.zeros((3, 1)), jnp.eye(1), jnp.zeros((), int)
        )  # Psi_f = Phi
        smoother = WienerSmoother(paper_model(), gain, arma_innovation_model(gain))
        rng = np.random.default_rng(1)
        optimal, arbitrary = rng.normal(size=(3, 3)), rng.normal(size=(3, 3))
        delta = (
            np.asarray(smoother.eq13_initial_values(jnp.asarray(arbitrary), jnp.asarray(optimal)))
            - optimal
        )
        np.testing.assert_allclose(delta[:2], arbitrary[:2] - optimal[:2])
        np.testing.assert_allclose(delta[2], 0.4 * delta[1] - 0.04 * delta[0], rtol=1e-6)
