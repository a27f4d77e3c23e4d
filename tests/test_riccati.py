"""Riccati solvers against scipy and exact rational arithmetic, under jit/vmap/grad, gradients
against finite differences, and the status of problems without a stabilising solution."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg as sl
from jax import enable_x64

from jaxest.riccati import (
    RiccatiStatus,
    _balancing,
    lqr_gain,
    solve_care,
    solve_dare,
    solve_filter_care,
    solve_filter_dare,
)
from tests.exact_riccati import exact_care, exact_dare
from tests.lowering import programs_compiled


def random_problem(seed, n, m):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, n)) / np.sqrt(n) * 1.3  # some modes unstable
    B = rng.normal(size=(n, m))
    C = rng.normal(size=(n, n))
    Q = C @ C.T / n
    R = np.eye(m) + 0.2 * np.ones((m, m))
    return A, B, Q, R


SIZES = [(1, 1), (3, 2), (8, 3)]


@pytest.mark.parametrize("n,m", SIZES)
def test_dare_matches_scipy(n, m):
    with enable_x64(True):
        A, B, Q, R = random_problem(n + m, n, m)
        solution = solve_dare(A, B, Q, R)
        X = np.asarray(solution.X)
        ref = sl.solve_discrete_are(A, B, Q, R)
        assert int(solution.status) == RiccatiStatus.OK
        np.testing.assert_allclose(X, ref, rtol=1e-9, atol=1e-9 * np.abs(ref).max())
        residual = A.T @ X @ A - A.T @ X @ B @ np.linalg.solve(R + B.T @ X @ B, B.T @ X @ A) + Q - X
        assert np.abs(residual).max() < 1e-9 * np.abs(X).max()


def test_a_first_call_outside_jit_compiles_the_solver_as_one_program():
    """The solvers check their arguments eagerly and run the rest as one program; op by op
    outside ``jit``, a first 4-state ``solve_dare`` compiled 65 programs (1.3 s)."""
    A, B, Q, R = random_problem(5, 5, 4)  # a size no other test here solves
    for solve, arguments in ((solve_dare, (A, B)), (solve_filter_care, (A.T, B.T))):
        assert programs_compiled(solve, *arguments, Q, R) <= 3
        assert int(solve(*arguments, Q, R).status) == RiccatiStatus.OK


@pytest.mark.parametrize("n,m", SIZES)
def test_care_matches_scipy(n, m):
    with enable_x64(True):
        A, B, Q, R = random_problem(n + m, n, m)
        solution = solve_care(A, B, Q, R)
        X = np.asarray(solution.X)
        ref = sl.solve_continuous_are(A, B, Q, R)
        assert int(solution.status) == RiccatiStatus.OK
        np.testing.assert_allclose(X, ref, rtol=1e-9, atol=1e-9 * np.abs(ref).max())
        K = np.asarray(lqr_gain(A, B, Q, R))
        np.testing.assert_allclose(K, np.linalg.solve(R, B.T @ ref), rtol=1e-8, atol=1e-9)
        assert np.linalg.eigvals(A - B @ K).real.max() < 0  # stabilising


def test_float32_stays_float32_and_is_accurate():
    A, B, Q, R = random_problem(3, 3, 1)
    A32, B32, Q32, R32 = (np.float32(v) for v in (A, B, Q, R))
    for solve, ref in ((solve_dare, sl.solve_discrete_are), (solve_care, sl.solve_continuous_are)):
        solution = solve(A32, B32, Q32, R32)
        X = solution.X
        assert X.dtype == jnp.float32 and int(solution.status) == RiccatiStatus.OK
        np.testing.assert_allclose(X, ref(A, B, Q, R), rtol=2e-4, atol=2e-4)


def test_paper_filter_riccati_eq5():
    """The Wiener paper's example (docs/papers/wiener.md): Sigma from the filter form of eq 5."""
    with enable_x64(True):
        Phi = np.array([[0.2, 0.1], [0.0, 1.0]])
        Gamma = np.array([[1.0], [1.0]])
        H = np.array([[1.0, 0.0]])
        Sigma = solve_dare(Phi.T, H.T, Gamma @ Gamma.T, np.eye(1)).X
        np.testing.assert_allclose(Sigma, [[1.078811, 1.441808], [1.441808, 4.030933]], atol=5e-7)
        np.testing.assert_array_equal(
            solve_filter_dare(Phi, H, Gamma @ Gamma.T, np.eye(1)).X, Sigma
        )


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_jit_and_vmap(dtype):
    with enable_x64(dtype == "float64"):
        problems = [random_problem(s, 3, 2) for s in range(4)]
        A, B, Q, R = (jnp.asarray(np.stack(p), dtype) for p in zip(*problems, strict=True))
        for solve, ref in (
            (solve_dare, sl.solve_discrete_are),
            (solve_care, sl.solve_continuous_are),
        ):
            solution = jax.jit(jax.vmap(solve))(A, B, Q, R)
            X = solution.X
            assert X.dtype == jnp.dtype(dtype)
            np.testing.assert_array_equal(solution.status, 0)
            tol = 1e-9 if dtype == "float64" else 1e-3
            for i, p in enumerate(problems):
                np.testing.assert_allclose(X[i], ref(*p), rtol=tol, atol=tol)


def _loss(solve, weights):
    return jax.jit(lambda A, B, Q, R: jnp.sum(weights * solve(A, B, Q, R).X))


def states_in_units(scales, discrete):
    """A well-conditioned 3-state problem (Q = I, R = 1) with its states rescaled by ``scales``
    (x -> S x, as a position in km beside a rate in mm/s)."""
    A = np.array([[-0.4, 1.0, 0.0], [-1.0, -0.3, 0.5], [0.2, 0.0, -0.8]])
    A = np.eye(3) + 0.5 * A if discrete else A
    S, S_inv = np.diag(scales), np.diag(1 / np.asarray(scales))
    return S @ A @ S_inv, S @ np.array([[0.0], [1.0], [0.3]]), S_inv @ S_inv, np.eye(1)


@pytest.mark.parametrize("units", [False, True], ids=["random", "units-1e6-apart"])
@pytest.mark.parametrize("solve", [solve_dare, solve_care], ids=["dare", "care"])
def test_gradient_matches_finite_differences(solve, units):
    """Through the implicit derivative, and through the balancing, which moves the states of
    the second problem by up to 2^10 (each argument perturbed relative to its entries); in
    reverse mode and in forward mode (``jax.jvp`` raised a TypeError on the custom_vjp)."""
    with enable_x64(True):
        if units:
            A, B, Q, R = states_in_units((1e3, 1.0, 1e-3), solve is solve_dare)
        else:
            A, B, Q, R = random_problem(5, 3, 2)
        weights = np.random.default_rng(9).normal(size=(3, 3))
        loss = _loss(solve, weights)
        grads = jax.jit(jax.grad(loss, argnums=(0, 1, 2, 3)))(A, B, Q, R)
        forward = jax.jit(lambda args, tangents: jax.jvp(loss, args, tangents)[1])
        args = [A, B, Q, R]
        rng = np.random.default_rng(1)
        for i in range(4):
            direction = rng.normal(size=args[i].shape) * (np.abs(args[i]) if units else 1)
            if i >= 2:  # Q and R are symmetric: perturb symmetrically
                direction = direction + direction.T
            h = 1e-6
            plus = [a + h * direction if j == i else a for j, a in enumerate(args)]
            minus = [a - h * direction if j == i else a for j, a in enumerate(args)]
            fd = (loss(*plus) - loss(*minus)) / (2 * h)
            np.testing.assert_allclose(np.sum(grads[i] * direction), fd, rtol=1e-6, atol=1e-8)
            tangents = [direction if j == i else np.zeros_like(a) for j, a in enumerate(args)]
            np.testing.assert_allclose(forward(args, tangents), fd, rtol=1e-6, atol=1e-8)


def test_steady_state_filter_differentiates_in_forward_mode():
    """Its gain comes from solve_filter_dare: jacfwd (and optimistix's least-squares solvers,
    which linearise) raised a TypeError where the solver had only a reverse-mode rule."""
    import jaxest as je

    with enable_x64(True):
        F, H = jnp.asarray([[1.0, 0.1], [0.0, 1.0]]), jnp.asarray([[1.0, 0.0]])
        Q, R = jnp.asarray([[1e-4, 1e-3], [1e-3, 2e-2]]), jnp.asarray([[0.25]])
        prior = je.Gaussian(jnp.zeros(2), jnp.eye(2))
        ys = je.simulate(je.LinearGaussian(F, H, Q, R), prior, 50, jax.random.key(0)).y
        loglik = lambda r: (
            je.run(
                je.SteadyStateKalmanFilter(), je.LinearGaussian(F, H, Q, r * R), ys, prior=prior
            ).loglik
        )
        h = 1e-6
        central = (loglik(1 + h) - loglik(1 - h)) / (2 * h)
        np.testing.assert_allclose(jax.jit(jax.jacfwd(loglik))(1.0), central, rtol=1e-7)
        np.testing.assert_allclose(jax.jit(jax.grad(loglik))(1.0), central, rtol=1e-7)


def test_gradient_under_vmap_float32():
    A, B, Q, R = (np.float32(v) for v in random_problem(7, 2, 1))
    weights = np.ones((2, 2), np.float32)
    g = jax.vmap(jax.grad(_loss(solve_dare, weights)), in_axes=(0, None, None, None))(
        np.stack([A, 0.9 * A]), B, Q, R
    )
    assert g.dtype == jnp.float32 and np.all(np.isfinite(g))
    with enable_x64(True):
        g64 = jax.grad(_loss(solve_dare, weights))(A.astype(np.float64), B, Q, R)
    np.testing.assert_allclose(g[0], g64, rtol=1e-3, atol=1e-3)


@pytest.mark.parametrize("solve", [solve_dare, solve_care], ids=["dare", "care"])
def test_a_member_masked_out_by_its_status_leaves_the_gradient_finite(solve):
    """A batch member with no stabilising solution, masked out by its own status
    (``where(s.ok, s.X, 0)``), has a zero cotangent; the DARE's adjoint Stein solve turned it
    into NaN through the unstable A_c, and the whole batch's gradient was NaN (the CARE's
    Lyapunov solve kept this one finite, and is guarded alike). The gradient is the good
    members' alone, which central differences confirm."""
    B, R = jnp.asarray([[0.0], [1.0]]), jnp.eye(1)
    unstable = 2.0 if solve is solve_dare else 0.5  # a mode B does not reach
    As = jnp.asarray([[[1.2, 0.3], [0.1, 0.4]], np.diag([unstable, -0.5]), [[0.5, 1.0], [-1, 0.2]]])

    def masked(Q, As):
        solutions = jax.vmap(lambda A: solve(A, B, Q, R))(As)
        ok = solutions.ok[:, None, None]
        return jnp.sum(jnp.where(ok, solutions.X, 0.0)), solutions.ok

    with enable_x64(True):
        (_, ok), gradient = jax.jit(jax.value_and_grad(masked, has_aux=True))(jnp.eye(2), As)
        assert ok.tolist() == [True, False, True]
        good = jax.grad(lambda Q: masked(Q, As[ok])[0])(jnp.eye(2))
        np.testing.assert_allclose(gradient, good, rtol=1e-12)
        step = 1e-6
        for i, j in ((0, 0), (0, 1), (1, 1)):
            E = jnp.zeros((2, 2)).at[i, j].set(step).at[j, i].set(step)
            central = (masked(jnp.eye(2) + E, As)[0] - masked(jnp.eye(2) - E, As)[0]) / (2 * step)
            directional = gradient[i, j] + gradient[j, i] if i != j else gradient[i, i]
            np.testing.assert_allclose(directional, central, rtol=1e-6)


def test_lqr_gain_gradient_through_the_gain():
    with enable_x64(True):
        A, B, Q, R = random_problem(2, 3, 1)
        f = jax.jit(lambda A: jnp.sum(lqr_gain(A, B, Q, R) ** 2))
        g = jax.grad(f)(A)
        d = np.random.default_rng(3).normal(size=A.shape)
        fd = (f(A + 1e-6 * d) - f(A - 1e-6 * d)) / 2e-6
        np.testing.assert_allclose(np.sum(g * d), fd, rtol=1e-6)


def issue_problem(small_eigenvalue):
    """The ill-conditioned R of the issue: R = U diag(1, small) U^T, U a rotation by 0.5 rad."""
    A = np.array([[1.1, 0.3], [0.0, 0.8]])
    B = np.array([[1.0, 0.0], [0.5, 1.0]])
    c, s = np.cos(0.5), np.sin(0.5)
    U = np.array([[c, -s], [s, c]])
    return A, B, np.eye(2), U @ np.diag([1.0, small_eigenvalue]) @ U.T


@pytest.mark.parametrize("small_eigenvalue", [1e-10, 1e-12], ids=["cond1e10", "cond1e12"])
@pytest.mark.parametrize(
    "solve,scipy_solve,exact",
    [
        (solve_dare, sl.solve_discrete_are, exact_dare),
        (solve_care, sl.solve_continuous_are, exact_care),
    ],
    ids=["dare", "care"],
)
def test_ill_conditioned_R_against_exact_arithmetic(solve, scipy_solve, exact, small_eigenvalue):
    """cond(R) = 1e10 and 1e12: within 10x scipy's error of the exact solution of the stated
    floats (forming B R^-1 B^T cost 2e-9 (DARE) and 6e-8 (CARE) at 1e10)."""
    with enable_x64(True):
        problem = issue_problem(small_eigenvalue)
        reference = scipy_solve(*problem)
        X_exact, residual = exact(*problem, reference)
        assert residual < 1e-90
        solution = solve(*problem)
        assert int(solution.status) == RiccatiStatus.OK
        scipy_error = np.abs(reference - X_exact).max()
        floor = np.finfo(np.float64).eps * np.abs(X_exact).max()
        assert np.abs(np.asarray(solution.X) - X_exact).max() <= 10 * max(scipy_error, floor)


ROTATION = np.array([[np.cos(0.5), -np.sin(0.5)], [np.sin(0.5), np.cos(0.5)]])


def float32_data_and_reference(scipy_solve, problem):
    """``problem`` rounded to float32, and scipy's float64 solution of those rounded data."""
    data = [np.float32(v) for v in problem]
    with enable_x64(True):
        return data, scipy_solve(*(np.float64(v) for v in data))


@pytest.mark.parametrize(
    "solve,filter_solve,scipy_solve,problem,flagged",
    [
        # a nearly singular R not aligned with the axes: rounding it through its Cholesky factor
        # moves the solution, which the CARE's residual, evaluated through the same factor,
        # cannot see
        (solve_care, solve_filter_care, sl.solve_continuous_are,
         ([[2.4]], [[-1.6, -0.8]], [[0.03]], ROTATION @ np.diag([1.0, 1e-6]) @ ROTATION.T), True),
        # the same R where the DARE's solution is small: its closed-loop residual's term K^T R K
        # is evaluated with rounding errors far above what X's accuracy allows
        (solve_dare, solve_filter_dare, sl.solve_discrete_are,
         ([[0.4, 0.3], [0.0, 2.7]], [[-1.0, -0.4], [0.1, -1.3]], 1e-7 * np.eye(2),
          ROTATION @ np.diag([1.0, 1e-6]) @ ROTATION.T), True),
        # a diagonal R with scales 1e6 apart is solved to working accuracy
        (solve_care, solve_filter_care, sl.solve_continuous_are,
         ([[2.4]], [[-1.6, -0.8]], [[0.03]], np.diag([1e-3, 1e3])), False),
    ],
    ids=["care-rotated-R", "dare-rotated-R", "care-diagonal-R"],
)  # fmt: skip
def test_float32_says_inaccurate_where_rounding_R_moves_the_solution(
    solve, filter_solve, scipy_solve, problem, flagged
):
    """Float32 solutions off by more than sqrt(eps) (against float64 on the same float32 data)
    said OK before: their residuals' own rounding hid it. The status now says INACCURATE."""
    data, reference = float32_data_and_reference(scipy_solve, problem)
    with enable_x64(True):
        assert int(solve(*(np.float64(v) for v in data)).status) == RiccatiStatus.OK
    solution = solve(*data)
    error = np.abs(np.asarray(solution.X, np.float64) - reference).max() / np.abs(reference).max()
    assert (error > np.sqrt(np.finfo(np.float32).eps)) == flagged
    assert bool(int(solution.status) & RiccatiStatus.INACCURATE) == flagged
    # the filter form is the same equation
    filter_status = int(filter_solve(data[0].T, data[1].T, *data[2:]).status)
    assert bool(filter_status & RiccatiStatus.INACCURATE) == flagged


@pytest.mark.parametrize("scales", [(1e3, 1.0, 1e-3), (1e3, 1e-3, 1.0)], ids=["a", "b"])
@pytest.mark.parametrize(
    "solve,scipy_solve",
    [(solve_care, sl.solve_continuous_are), (solve_dare, sl.solve_discrete_are)],
    ids=["care", "dare"],
)
def test_float32_solves_states_in_very_different_units(solve, scipy_solve, scales):
    """:func:`states_in_units`: float32 said NOT_STABILISING or INACCURATE for all four, and one
    DARE answer was off by 4e7 relative. Balancing the Hamiltonian first (powers of two, exact)
    solves them to float32's accuracy."""
    problem = states_in_units(scales, discrete=solve is solve_dare)
    data, reference = float32_data_and_reference(scipy_solve, problem)
    solution = solve(*data)
    assert int(solution.status) == RiccatiStatus.OK
    error = np.linalg.norm(np.asarray(solution.X, np.float64) - reference)
    assert error / np.linalg.norm(reference) < 1e-6


def test_balancing_scales_are_powers_of_two_that_shrink_the_hamiltonian():
    """The balancing's scales d are exact powers of two (so scaling back loses nothing; under
    ``jit(vmap(...))``, where ``jnp.exp2`` is not exact), and diag(D, D^-1) H diag(D^-1, D) has
    a much smaller off-diagonal 1-norm than H, for the states of the test above in units up to
    1e6 apart."""
    problems = []
    for scales in [(1e3, 1.0, 1e-3), (1e3, 1e-3, 1.0), (1e-2, 1.0, 1e2), (0.3, 7.0, 1e-3)]:
        A, B, Q, _ = states_in_units(scales, discrete=False)
        problems.append((A, B @ B.T, Q))  # G = B R^-1 B^T with R = 1
    stacked = [np.stack(arrays) for arrays in zip(*problems, strict=True)]

    def off_diagonal_norm(A, G, Q):
        H = np.block([[A, -G], [-Q, -A.T]])
        return np.abs(H).sum() - np.abs(np.diag(H)).sum()

    for dtype in (np.float32, np.float64):
        with enable_x64(dtype == np.float64):
            scales = jax.jit(jax.vmap(_balancing))(*(jnp.asarray(v, dtype) for v in stacked))
        assert scales.dtype == dtype
        for (A, G, Q), d in zip(problems, np.asarray(scales, np.float64), strict=True):
            assert np.all(d == 2.0 ** np.round(np.log2(d)))
            balanced = off_diagonal_norm(A * d / d[:, None], G / d / d[:, None], Q * d * d[:, None])
            assert balanced < 1e-2 * off_diagonal_norm(A, G, Q)


@pytest.mark.parametrize("dtype,seed", [(np.float64, 98), (np.float32, 81)])
def test_no_process_noise_on_a_stable_system_has_covariance_zero(dtype, seed):
    """Q = 0 and a stable F: the steady-state covariance is 0. Newton's iterates shrank towards
    it by a few eps a step without ever settling relative to themselves, and the status said
    INACCURATE (these draws were found by a sweep); an iterate that collapses to rounding noise
    of the last is now taken for 0."""
    rng = np.random.default_rng(seed)
    F = rng.normal(size=(5, 5)) / np.sqrt(5) * 1.5
    assert np.abs(np.linalg.eigvals(F)).max() < 1
    H = rng.normal(size=(1, 5))
    with enable_x64(dtype == np.float64):
        solution = solve_filter_dare(*(dtype(v) for v in (F, H, np.zeros((5, 5)), np.eye(1))))
    assert int(solution.status) == RiccatiStatus.OK
    assert np.all(np.asarray(solution.X) == 0)


def test_status_fields_against_numpy():
    """The residual is at rounding level and the margin is -log of the closed loop's spectral
    radius (DARE) or -max Re lambda / |A_c| (CARE), both computed here from eigvals."""
    with enable_x64(True):
        A, B, Q, R = random_problem(4, 3, 2)
        d, c = solve_dare(A, B, Q, R), solve_care(A, B, Q, R)
        assert float(d.residual) < 1e-14 and float(c.residual) < 1e-14
        Ad = A - B @ np.asarray(d.K)
        np.testing.assert_allclose(
            d.margin, -np.log(np.abs(np.linalg.eigvals(Ad)).max()), rtol=1e-6
        )
        Ac = A - B @ np.asarray(c.K)
        abscissa = np.linalg.eigvals(Ac).real.max() / np.abs(Ac).max()
        np.testing.assert_allclose(c.margin, -abscissa, rtol=1e-6)


def test_filter_forms_are_the_transposed_control_forms():
    with enable_x64(True):
        A, B, Q, R = random_problem(6, 3, 2)
        F, H = A.T, B.T
        dare, care = solve_filter_dare(F, H, Q, R), solve_filter_care(F, H, Q, R)
        Sigma = sl.solve_discrete_are(F.T, H.T, Q, R)
        np.testing.assert_allclose(dare.X, Sigma, rtol=1e-10, atol=1e-12)
        predictor = F @ Sigma @ H.T @ np.linalg.inv(H @ Sigma @ H.T + R)
        np.testing.assert_allclose(dare.K, predictor, rtol=1e-9, atol=1e-12)
        Sigma = sl.solve_continuous_are(F.T, H.T, Q, R)
        np.testing.assert_allclose(care.X, Sigma, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(care.K, Sigma @ H.T @ np.linalg.inv(R), rtol=1e-9, atol=1e-12)


#: (solver, A, B, Q, R, the eager error) of problems without a stabilising solution
NO_STABILISING_SOLUTION = {
    "dare-unstabilisable-1.2": (
        solve_dare, np.diag([1.2, 0.5]), np.array([[0.0], [1.0]]), np.eye(2),
        "not stabilisable: the mode 1.2 of A",
    ),
    "dare-undetectable-1.0": (
        solve_dare, np.diag([1.0, 0.5]), np.array([[1.0], [1.0]]), np.diag([0.0, 1.0]),
        "no stabilising solution: the mode 1 of A",
    ),
    "dare-undetectable-rotation": (  # modes 0.6 +- 0.8j on the unit circle, Q = 0
        solve_dare, np.array([[0.6, 0.8], [-0.8, 0.6]]), np.array([[1.0], [0.3]]),
        np.zeros((2, 2)), "no stabilising solution: the mode 0.6",
    ),
    "care-unstabilisable-0.3": (
        solve_care, np.diag([0.3, -1.0]), np.array([[0.0], [1.0]]), np.eye(2),
        "not stabilisable: the mode 0.3 of A",
    ),
    "care-undetectable-i": (
        solve_care, np.array([[0.0, 1.0], [-1.0, 0.0]]), np.array([[0.0], [1.0]]),
        np.zeros((2, 2)), "no stabilising solution: the mode 0[+-]1j of A",
    ),
    "care-undetectable-0": (
        solve_care, np.diag([0.0, -1.0]), np.array([[1.0], [1.0]]), np.diag([0.0, 1.0]),
        "no stabilising solution: the mode 0 of A",
    ),
}  # fmt: skip


@pytest.mark.parametrize("dtype", ["float32", "float64"])
@pytest.mark.parametrize("case", list(NO_STABILISING_SOLUTION))
def test_no_stabilising_solution_raises_eagerly_and_flags_under_jit(case, dtype):
    solve, A, B, Q, match = NO_STABILISING_SOLUTION[case]
    with enable_x64(dtype == "float64"):
        with pytest.raises(ValueError, match=match):
            solve(A, B, Q, np.eye(1))
        args = [jnp.asarray(v, dtype) for v in (A, B, Q, np.eye(1))]
        solution = jax.jit(solve)(*args)
        assert int(solution.status) & RiccatiStatus.NOT_STABILISING
        assert not bool(solution.ok)
        if solve is solve_care:  # the bare gain is NaN rather than wrong
            assert not bool(jnp.any(jnp.isfinite(jax.jit(lqr_gain)(*args))))


def test_stabilising_solution_without_detectability():
    """Unobservable modes outside the stability region need no detectability: the stabilising
    solution exists (as scipy finds), eagerly and under jit."""
    with enable_x64(True):
        A, B, Q = np.diag([1.2, 0.5]), np.array([[1.0], [1.0]]), np.diag([0.0, 1.0])
        for solution in (solve_dare(A, B, Q, np.eye(1)), jax.jit(solve_dare)(A, B, Q, np.eye(1))):
            assert int(solution.status) == RiccatiStatus.OK
            np.testing.assert_allclose(
                solution.X, sl.solve_discrete_are(A, B, Q, np.eye(1)), rtol=1e-12
            )
            assert np.abs(np.linalg.eigvals(A - B @ np.asarray(solution.K))).max() < 1
        # the filter form F = 2, H = 1, Q = 0: Sigma = 3 (F - K H = 0.5), not the fixed point 0
        for solve in (solve_filter_dare, jax.jit(solve_filter_dare)):
            solution = solve(np.array([[2.0]]), np.array([[1.0]]), np.zeros((1, 1)), np.eye(1))
            np.testing.assert_allclose(solution.X, [[3.0]], rtol=1e-14)
            np.testing.assert_allclose(solution.K, [[1.5]], rtol=1e-14)
            assert int(solution.status) == RiccatiStatus.OK


def test_filter_form_names_F_and_H():
    F, H = np.diag([2.0, 0.5]), np.array([[0.0, 1.0]])
    with pytest.raises(ValueError, match=r"^\(F, H\): not detectable: the mode 2 of F"):
        solve_filter_dare(F, H, np.eye(2), np.eye(1))
    with pytest.raises(ValueError, match=r"^\(F, H\): not detectable: the mode 2 of F"):
        solve_filter_care(F, H, np.eye(2), np.eye(1))
    with pytest.raises(ValueError, match=r"^\(F, Q\): no stabilising solution: the mode 1 of F"):
        solve_filter_dare(np.diag([1.0, 0.5]), np.ones((1, 2)), np.diag([0.0, 1.0]), np.eye(1))
    with pytest.raises(ValueError, match=r"^H: expected 2 columns to match F \(2 x 2\)"):
        solve_filter_dare(F, np.ones((1, 3)), np.eye(2), np.eye(1))
    with pytest.raises(ValueError, match="^F: must be square"):
        solve_filter_care(np.ones((2, 3)), np.ones((1, 3)), np.eye(2), np.eye(1))


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_a_large_q_does_not_make_a_controllable_pair_uncontrollable(dtype):
    """The eager PBH check measured controllability against |Q| too: Q = 1e12 (float64) or 1e6
    (float32) made (A, B) = (2, 1) "not stabilisable", a ValueError for a problem scipy solves."""
    f = lambda v: jnp.asarray([[v]], dtype)
    for q in (1e6, 1e12, 1e18):
        for solve, scipy_solve, a in ((solve_dare, sl.solve_discrete_are, 2.0),
                                      (solve_care, sl.solve_continuous_are, 1.0)):  # fmt: skip
            solution = solve(f(a), f(1.0), f(q), f(1.0))
            expected = scipy_solve(*(np.asarray([[v]]) for v in (a, 1.0, q, 1.0)))
            assert int(solution.status) == 0
            np.testing.assert_allclose(solution.X, expected, rtol=100 * jnp.finfo(dtype).eps)


def _in_units(A, B, Q, R, states, inputs):
    """The problem (A, B, Q, R) with state i in units scaled by ``states[i]`` and input j by
    ``inputs[j]``, and how to map its X back: the same problem, whose X is D^-1 X D^-1."""
    d, e = np.asarray(states, float), np.asarray(inputs, float)
    scaled = (A * d[:, None] / d, B * d[:, None] / e, Q / d[:, None] / d, R / e[:, None] / e)
    return scaled, lambda X: np.asarray(X) * d[:, None] * d


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_the_eager_check_does_not_depend_on_units(dtype):
    """Units change no answer, but the eager PBH check measured rank against absolute
    tolerances, so a solvable problem in other units raised "not stabilisable" or "no
    stabilising solution": a double integrator in mm and km/s, an input or a measurement
    scaled by 1e-10 (its R by 1e-20), a tracker with a small process noise, random states
    scaled by up to 10^+-4 (14 of 40 in a sweep of DARE problems). Each is solved eagerly as under jit, and
    its X mapped back agrees with the problem in the original units."""
    tolerance = {"float32": 1e-4, "float64": 1e-8}[dtype]
    integrator = (np.array([[0.0, 1.0], [0.0, 0.0]]), np.array([[0.0], [1.0]]), np.diag([1.0, 0.0]))
    rng = np.random.default_rng(21)
    random = [(rng.normal(size=(3, 3)), rng.normal(size=(3, 1)), np.eye(3)) for _ in range(4)]
    cases = [
        (solve_care, sl.solve_continuous_are, integrator, [1e3, 1e-3], [1e4]),
        (solve_dare, sl.solve_discrete_are, (np.diag([1.2, 0.7]) + np.triu(np.ones((2, 2)), 1) * 0.3,
                                             np.ones((2, 1)), np.eye(2)), [1.0, 1.0], [1e10]),
        *[(solve_dare, sl.solve_discrete_are, problem, 10.0 ** rng.uniform(-4, 4, 3), [1.0])
          for problem in random],
        *[(solve_care, sl.solve_continuous_are, problem, 10.0 ** rng.uniform(-4, 4, 3), [1.0])
          for problem in random],
    ]  # fmt: skip
    with enable_x64(dtype == "float64"):
        for solve, scipy_solve, (A, B, Q), states, inputs in cases:
            reference = scipy_solve(A, B, Q, np.eye(1))
            scaled, back = _in_units(A, B, Q, np.eye(1), states, inputs)
            solution = solve(*(jnp.asarray(v, dtype) for v in scaled))
            error = np.linalg.norm(back(np.asarray(solution.X, np.float64)) - reference)
            assert int(solution.status) == RiccatiStatus.OK
            assert error <= tolerance * np.linalg.norm(reference)
        # the filter forms: a measurement in other units (Sigma is that of H = R = 1), and a
        # small process noise
        F, H = np.array([[1.0, 1.0], [0.0, 1.0]]), np.array([[1.0, 0.0]])
        q = {"float32": 1e-5, "float64": 1e-12}[dtype]
        for scale, Q in ((1e-10, np.eye(2)), (1.0, np.diag([0.0, q]))):
            reference = sl.solve_discrete_are(F.T, H.T, Q, np.eye(1))
            data = (F, scale * H, Q, np.array([[scale**2]]))
            solution = solve_filter_dare(*(jnp.asarray(v, dtype) for v in data))
            assert int(solution.status) == RiccatiStatus.OK
            np.testing.assert_allclose(solution.X, reference, rtol=tolerance, atol=0)
        # and still refused where units cannot help: a mode of 2 that B does not reach
        A, B = np.diag([2.0, 0.5]), np.array([[0.0], [1e-4]])
        with pytest.raises(ValueError, match="not stabilisable: the mode 2 of A"):
            solve_dare(*_in_units(A, B, np.eye(2), np.eye(1), [1e4, 1e-4], [1e-8])[0])


def test_gradient_in_R_outside_jit_keeps_the_eager_check():
    """Differentiating in R alone, outside jit, leaves F, H and Q concrete, so the eager check
    runs with R traced: it read R for its balancing and raised a TracerArrayConversionError
    (notebook 03's d MSE / d r). Central differences confirm the gradient."""
    F, H, Q = np.array([[0.2, 0.1], [0.0, 1.0]]), np.array([[1.0, 0.0]]), np.ones((2, 2))
    with enable_x64(True):
        total = lambda r: jnp.sum(solve_filter_dare(F, H, Q, r * jnp.eye(1)).X)
        gradient = float(jax.grad(total)(1.0))
        central = (float(total(1.0 + 1e-6)) - float(total(1.0 - 1e-6))) / 2e-6
        np.testing.assert_allclose(gradient, central, rtol=1e-6)


def test_float32_certifies_a_solution_whose_frobenius_norm_overflows():
    """A float32 DARE whose balanced X reaches 7.6e21: jnp.linalg.norm squares the entries and
    overflowed, so the status check's scale was infinite, the relative residual exactly 0 and
    the INACCURATE test compared inf with inf (found by a random search; X was right)."""
    A = [
        [0.17377452552318573, 0.00022909084509592503, -807.7630615234375],
        [309.0133056640625, -0.02422318607568741, -4915501.0],
        [-1.318207409894967e-06, -3.791335956293551e-08, -0.6813963651657104],
    ]
    B = [[0.80052250623703], [-7.798365550115705e-05], [8998.1875]]
    Q = [
        [2.370443820953369, -2859.72216796875, 1.3726601537200622e-05],
        [-2859.72216796875, 19723352.0, -0.06218867376446724],
        [1.3726601537200622e-05, -0.06218867376446724, 1.958860806894336e-08],
    ]
    R = [[0.14833049476146698]]  # fmt: skip
    single = solve_dare(*(jnp.asarray(v, jnp.float32) for v in (A, B, Q, R)))
    with enable_x64(True):
        double = solve_dare(*(jnp.asarray(np.float32(v), jnp.float64) for v in (A, B, Q, R)))
        assert int(double.status) == 0
        X = np.asarray(double.X)
    assert int(single.status) == 0
    assert 0 < float(single.residual) < np.sqrt(np.finfo(np.float32).eps)
    np.testing.assert_allclose(single.X, X, rtol=1e-4, atol=1e-4 * np.abs(X).max())


def test_stable_modes_need_neither_control_nor_observation():
    with enable_x64(True):
        A, B, Q, R = np.diag([0.5, -0.3]), np.zeros((2, 1)), np.zeros((2, 2)), np.eye(1)
        np.testing.assert_array_equal(solve_dare(A, B, Q, R).X, np.zeros((2, 2)))
        Q = np.eye(2)  # then X = sum_k A^k Q A^k = diag(1 / (1 - a^2))
        np.testing.assert_allclose(
            solve_dare(A, B, Q, R).X, np.diag([1 / 0.75, 1 / 0.91]), rtol=1e-12
        )


@pytest.mark.parametrize(
    "args,name",
    [
        ((np.eye(2), np.ones((3, 1)), np.eye(2), np.eye(1)), "B"),  # A is 2 x 2: B has 3 rows
        ((np.ones((2, 3)), np.ones((2, 1)), np.eye(2), np.eye(1)), "A"),
        ((np.eye(2), np.ones((2, 1)), np.eye(2), -np.eye(1)), "R"),
        ((np.eye(2), np.ones((2, 1)), np.array([[1.0, 2.0], [0.0, 1.0]]), np.eye(1)), "Q"),
        ((np.eye(2), np.ones(2), np.eye(2), np.eye(1)), "B"),
        # these raised an SVD LinAlgError (NaN), gave a status (inf), a TypeError from the
        # solver's loop (complex) and a NumPy reduction error (no states)
        ((np.eye(2), np.array([[np.nan], [1.0]]), np.eye(2), np.eye(1)), "B"),
        ((np.eye(2), np.array([[np.inf], [1.0]]), np.eye(2), np.eye(1)), "B"),
        ((np.eye(2) + 0j, np.ones((2, 1)), np.eye(2), np.eye(1)), "A"),
        ((np.zeros((0, 0)), np.zeros((0, 1)), np.zeros((0, 0)), np.eye(1)), "A"),
        ((np.eye(2), np.zeros((2, 0)), np.eye(2), np.zeros((0, 0))), "B"),  # a reduction error
    ],
)
def test_bad_arguments_name_the_argument(args, name):
    with pytest.raises(ValueError, match=f"^{name}:"):
        solve_dare(*args)
