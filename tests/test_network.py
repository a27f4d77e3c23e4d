"""Network-structured filter: lemma 1/2, covariance ODEs 28-31, step-4 gains, eq 9 filter.

Independent references: a KKT solve of the constrained gain problem (no SVD), the block equations
28 and 30 written out per block in NumPy and integrated with scipy, scipy's CARE for uncoupled
nodes, an explicit Gamma_i / B_ij form of eq 9, and Monte Carlo runs.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate
import scipy.linalg
from jax import enable_x64

from jaxest import Gaussian, Status, raise_if_failed, run
from jaxest.network import (
    CommunicationStructure,
    LargeScaleSystem,
    NetworkDesignStatus,
    NetworkFilter,
    check_existence,
    design,
    simulate_network,
    steady_state,
)
from jaxest.network.design import (
    closed_loop_blocks,
    gain_constraint,
    instantaneous_cost,
    optimal_free_gain,
    optimal_gain,
    pseudo_inverse_and_left_null_rows,
    unheard_couplings,
)
from jaxest.systems.chain import initial_prior, mass_chain

DT, STEPS = 2e-3, 5000  # the one sample grid of the chain tests (one compilation of design)


@pytest.fixture(scope="module")
def chain3():
    """Three masses, chain communication, designed on the sample grid (float64)."""
    with enable_x64():
        system = mass_chain(3)
        mean0, cov0 = initial_prior(3)
        structure = CommunicationStructure.chain(3)
        des = design(system, structure, cov0, jnp.arange(STEPS) * DT)
        return system, structure, mean0, cov0, des


def random_system(rng, N=3, n=2, h=2, q=3, p=2, dtype=np.float64, H2_rank=None):
    """A random coupled system; H_i2 has rank ``H2_rank`` (default full) so the constraint bites."""

    def spd(k):
        X = rng.normal(size=(N, k, k))
        return X @ np.swapaxes(X, -1, -2) / k + 0.5 * np.eye(k)

    H2 = rng.normal(size=(N, q, h))
    if H2_rank is not None:
        H2 = H2[:, :, :H2_rank] @ rng.normal(size=(N, H2_rank, h))
    return LargeScaleSystem(
        A=jnp.asarray(rng.normal(size=(N, n, n)) - 2 * np.eye(n), dtype),
        C=jnp.asarray(rng.normal(size=(N, n, h)), dtype),
        F=jnp.asarray(rng.normal(size=(N, n, p)), dtype),
        L=jnp.asarray(0.5 * rng.normal(size=(N, N, h, n)), dtype),
        H1=jnp.asarray(rng.normal(size=(N, q, n)), dtype),
        H2=jnp.asarray(H2, dtype),
        Q=jnp.asarray(spd(p), dtype),
        R=jnp.asarray(spd(q), dtype),
    )


def kkt_gain(C, H2, E, R, K, S):
    """argmin_G tr(S (G R G^T - G K^T - K G^T)) s.t. G H2 E = C E, by a KKT system (no SVD)."""
    n, q = K.shape
    M = H2 @ E
    # column-major vec: vec(G M) = (M^T kron I_n) vec(G)
    Aeq = np.kron(M.T, np.eye(n))
    Hq = 2 * np.kron(R, S)
    kkt = np.block([[Hq, Aeq.T], [Aeq, np.zeros((Aeq.shape[0],) * 2)]])
    rhs = np.concatenate([2 * (S @ K).reshape(-1, order="F"), (C @ E).reshape(-1, order="F")])
    sol = np.linalg.lstsq(kkt, rhs, rcond=None)[0]
    return sol[: n * q].reshape(n, q, order="F")


def blocks_reference(system, hears_fn, t_span, P0, t_eval):
    """Eqs 28 and 30 block by block (sums over l in C_i, self-coupling in Gamma_i), gains by KKT,
    integrated with scipy. ``hears_fn(t)`` gives the structure at t."""
    A, C, F, L, H1, H2, Q, R = (
        np.asarray(getattr(system, m)) for m in ("A", "C", "F", "L", "H1", "H2", "Q", "R")
    )
    N, n = A.shape[0], A.shape[-1]

    def gains(P, hears):
        G = []
        for i in range(N):
            unheard = [j for j in range(N) if j != i and not hears[i, j]]
            E = (
                np.concatenate([L[i, j] for j in unheard], axis=1)
                if unheard
                else np.zeros((L.shape[2], 1))
            )
            used = [i] + [j for j in range(N) if hears[i, j] and j != i]
            K = P[i, i] @ H1[i].T + sum(P[i, j] @ L[i, j].T @ H2[i].T for j in used)
            G.append(kkt_gain(C[i], H2[i], E, R[i], K, np.eye(n)))
        return G

    def rate(t, vecP):
        hears = hears_fn(t)
        P = vecP.reshape(N, n, N, n).transpose(0, 2, 1, 3)
        G = gains(P, hears)
        Gam = [A[i] - G[i] @ H1[i] + (C[i] - G[i] @ H2[i]) @ L[i, i] for i in range(N)]
        B = {
            (i, j): (C[i] - G[i] @ H2[i]) @ L[i, j]
            for i in range(N)
            for j in range(N)
            if hears[i, j] and j != i
        }
        dP = np.zeros_like(P)
        for i in range(N):
            for j in range(N):
                d = Gam[i] @ P[i, j] + P[i, j] @ Gam[j].T  # eq 30
                d += sum(B[i, l] @ P[l, j] for l in range(N) if (i, l) in B)
                d += sum(P[i, l] @ B[j, l].T for l in range(N) if (j, l) in B)
                if i == j:  # eq 28
                    d += F[i] @ Q[i] @ F[i].T + G[i] @ R[i] @ G[i].T
                dP[i, j] = d
        return dP.transpose(0, 2, 1, 3).reshape(-1)

    sol = scipy.integrate.solve_ivp(
        rate, t_span, P0.reshape(-1), t_eval=t_eval, rtol=1e-10, atol=1e-12, method="DOP853"
    )
    return sol.y.T.reshape(len(t_eval), N * n, N * n)


@pytest.mark.parametrize("seed", [0, 1])
def test_lemma2_gain_solves_constraint_and_matches_kkt(seed):
    with enable_x64():
        rng = np.random.default_rng(seed)
        system = random_system(rng, N=4, h=2, q=3, H2_rank=None)
        hears = rng.random((4, 4)) < 0.4
        structure = CommunicationStructure(jnp.asarray(hears))
        cons = gain_constraint(system, structure.at(0.0))
        E = np.asarray(unheard_couplings(system, structure.at(0.0)))
        X = rng.normal(size=(8, 8))
        P = jnp.asarray(X @ X.T + np.eye(8))
        _, Hbar = closed_loop_blocks(system, structure.at(0.0))
        G = np.asarray(optimal_gain(system, cons, Hbar, P))
        K = np.asarray(
            jnp.einsum("ijab,ijcb->iac", P.reshape(4, 2, 4, 2).transpose(0, 2, 1, 3), Hbar)
        )
        for i in range(4):
            C, H2 = np.asarray(system.C[i]), np.asarray(system.H2[i])
            # eq 17 for the optimal gain and for an arbitrary free part
            assert np.allclose((C - G[i] @ H2) @ E[i], 0, atol=1e-12)
            G_any = np.asarray(cons.particular[i] + rng.normal(size=(2, 3)) @ cons.phi[i])
            assert np.allclose((C - G_any @ H2) @ E[i], 0, atol=1e-12)
            # step 4 against the KKT solution, with a non-identity S (S drops out)
            S = np.diag(rng.uniform(0.5, 2.0, size=2))
            G_ref = kkt_gain(C, H2, E[i], np.asarray(system.R[i]), K[i], S)
            np.testing.assert_allclose(G[i], G_ref, rtol=1e-9, atol=1e-10)
        assert np.all(np.asarray(cons.residual) < 1e-12)


def test_existence_error_names_the_node():
    with enable_x64():
        no_sensors = mass_chain(4, force_sensors=False)
        _, cov0 = initial_prior(4)
        with pytest.raises(ValueError, match=r"node 0 admits no filter.*hears nodes \[1, 2\]"):
            steady_state(no_sensors, CommunicationStructure.none(4), cov0)
        # hearing only the neighbours leaves the springs to i +- 2 unmeasured and unheard
        with pytest.raises(ValueError, match=r"node 0 .*hears nodes \[2\]"):
            design(no_sensors, CommunicationStructure.chain(4), cov0, jnp.linspace(0, 1, 3))
        # full communication needs no coupling sensor (eq 13 is empty), and with the force
        # sensors every structure is feasible
        check_existence(no_sensors, CommunicationStructure.full(4))
        for name in ("none", "chain", "full"):
            check_existence(mass_chain(4), getattr(CommunicationStructure, name)(4))
        # under jit nothing can raise: the status says it (the costs were finite, status-less)
        no_filter = int(NetworkDesignStatus.NO_FILTER)
        ts, none = jnp.linspace(0, 1, 3), CommunicationStructure.none(4)
        assert jax.jit(steady_state)(no_sensors, none, cov0).status == no_filter
        assert jax.jit(design)(no_sensors, none, cov0, ts).status == no_filter
        assert jax.jit(design)(mass_chain(4), none, cov0, ts).status == 0


def test_design_names_a_bad_cov0_or_S_and_differentiates_in_L_C_and_H2():
    """A non-symmetric or indefinite cov0 gave other costs silently, a joint (Nn, Nn) cov0 an
    unpacking error; the gradient in C or H2 raised a TracerArrayConversionError from the
    existence check, which read them as NumPy arrays (now skipped where they are traced), and
    in L, C or H2 it was NaN wherever H_i2 E_i is rank-deficient, as here (the SVD's derivative
    at a zero singular value; now lemma 2's own, :func:`pseudo_inverse_and_left_null_rows`)."""
    with enable_x64():
        system = random_system(np.random.default_rng(3))  # node 0 does not hear node 2
        structure, ts = CommunicationStructure.chain(3), jnp.linspace(0.0, 0.5, 3)
        eye = jnp.stack([jnp.eye(2)] * 3)
        for cov0, match in (
            (eye.at[0, 0, 1].set(0.5), "cov0: must be symmetric"),
            (eye.at[1].set(jnp.diag(jnp.asarray([1.0, -1.0]))), "cov0: must be positive semi"),
            (jnp.eye(6), r"cov0: expected a block per node, shape \(3, 2, 2\)"),
        ):
            with pytest.raises(ValueError, match=f"^{match}"):
                design(system, structure, cov0, ts)
        with pytest.raises(ValueError, match="^S: expected a block per node"):
            design(system, structure, eye, ts, S=jnp.eye(2))
        with pytest.raises(ValueError, match="^ts: must be increasing"):  # an error in diffrax
            design(system, structure, eye, ts[::-1])
        # a NaN in the system surfaced as an EquinoxRuntimeError from inside the design's ODE,
        # a float hears as a TypeError from a logical operation
        matrices = {name: getattr(system, name) for name in ("A", "C", "F", "L", "H1", "H2")}
        for name, value in matrices.items():
            with pytest.raises(ValueError, match=f"^{name}: contains NaN"):
                nan = {**matrices, name: value.at[0].set(jnp.nan)}
                LargeScaleSystem(**nan, Q=system.Q, R=system.R)
        with pytest.raises(ValueError, match="^hears: must be boolean, got float"):
            CommunicationStructure(structure.hears.astype(float))

        def cost(scales):  # of L, C and H2: one gradient program for the three
            where = lambda s: (s.L, s.C, s.H2)
            scaled = [a * b for a, b in zip(scales, where(system), strict=True)]
            return design(eqx.tree_at(where, system, scaled), structure, eye, ts).J[-1]

        gradient, h = jax.grad(cost)(jnp.ones(3)), 1e-6
        for i in range(3):
            central = (cost(jnp.ones(3).at[i].add(h)) - cost(jnp.ones(3).at[i].add(-h))) / (2 * h)
            np.testing.assert_allclose(gradient[i], central, rtol=1e-6)


@pytest.mark.parametrize("shape, rank", [((3, 4), 2), ((3, 5), 0), ((2, 6), 1)])
def test_pseudo_inverse_and_null_space_derivatives_at_constant_rank(shape, rank):
    """Against central differences along a curve of constant rank, (I + t X) M (I + t Y), whose
    tangent is dM = X M + M Y (along M + t dM the rank grows: a rank-0 M stays 0 either way)."""
    rng = np.random.default_rng(rank)
    with enable_x64():
        q, w = shape
        M = jnp.asarray(rng.normal(size=(q, rank)) @ rng.normal(size=(rank, w)))
        X, Y = jnp.asarray(rng.normal(size=(q, q))), jnp.asarray(rng.normal(size=(w, w)))
        curve = lambda t: (jnp.eye(q) + t * X) @ M @ (jnp.eye(w) + t * Y)  # rank kept
        dM = X @ M + M @ Y
        projector = lambda phi: phi.T @ phi
        outputs = lambda t: (lambda p, phi, _: (p, projector(phi)))(
            *pseudo_inverse_and_left_null_rows(curve(t))
        )
        _, (d_pinv, d_phi, d_mask) = jax.jvp(pseudo_inverse_and_left_null_rows, (M,), (dM,))
        _, phi, _ = pseudo_inverse_and_left_null_rows(M)
        h = 1e-6
        plus, minus = outputs(h), outputs(-h)
        np.testing.assert_allclose(d_pinv, (plus[0] - minus[0]) / (2 * h), atol=1e-7)
        np.testing.assert_allclose(
            d_phi.T @ phi + phi.T @ d_phi, (plus[1] - minus[1]) / (2 * h), atol=1e-7
        )
        assert not np.any(d_mask)


def test_simulation_draws_a_singular_noise_or_prior():
    """LargeScaleSystem takes a positive semidefinite Q (a node padded to a common size, a
    noise-free node), but the simulation factored Q and cov0 by Cholesky: NaN draws. Positive
    definite ones draw as before."""
    with enable_x64():
        system = random_system(np.random.default_rng(0), N=2)
        mean0, eye, key = jnp.zeros((2, 2)), jnp.stack([jnp.eye(2)] * 2), jax.random.key(0)
        states, ys = simulate_network(system, mean0, eye, 0.01, 5, key)
        normal = jax.random.normal(jax.random.split(key)[0], (2, 2), jnp.float64)
        np.testing.assert_array_equal(states[0], normal)  # chol(I) z: the draw it always was
        singular = jnp.diag(jnp.asarray([1.0, 0.0]))
        for Q, cov0 in ((system.Q.at[1].set(singular), eye), (system.Q, eye.at[0].set(singular))):
            states, ys = simulate_network(eqx.tree_at(lambda s: s.Q, system, Q), mean0, cov0,
                                          0.01, 5, key)  # fmt: skip
            assert np.all(np.isfinite(states)) and np.all(np.isfinite(ys))
        assert states[0, 0, 1] == 0  # a known component stays at its mean


@pytest.mark.parametrize("switching", [False, True])
def test_design_matches_block_equations_28_30(switching):
    with enable_x64():
        rng = np.random.default_rng(3)
        system = random_system(rng, N=3, h=2, q=3, H2_rank=None)
        sparse = rng.random((3, 3)) < 0.5
        if switching:  # C(t) changes at t = 0.4: a time-varying structure
            structure = CommunicationStructure(
                jnp.asarray(np.stack([sparse, ~sparse])), switch_times=(0.0, 0.4)
            )
            hears_fn = lambda t: (sparse if t < 0.4 else ~sparse) & ~np.eye(3, dtype=bool)
        else:
            structure = CommunicationStructure(jnp.asarray(sparse))
            hears_fn = lambda t: sparse & ~np.eye(3, dtype=bool)
        cov0 = np.stack([np.eye(2) * (i + 1) for i in range(3)])
        ts = np.linspace(0.0, 1.0, 6)
        des = design(system, structure, jnp.asarray(cov0), jnp.asarray(ts))
        P0 = scipy.linalg.block_diag(*cov0)
        if switching:  # integrate the reference piecewise across the switch
            a = blocks_reference(system, hears_fn, (0.0, 0.4), P0, [0.0, 0.2, 0.4])
            b = blocks_reference(system, hears_fn, (0.4, 1.0), a[-1], [0.4, 0.6, 0.8, 1.0])
            ref = np.concatenate([a, b[1:]])
        else:
            ref = blocks_reference(system, hears_fn, (0.0, 1.0), P0, ts)
        costs = np.einsum("kiaia->ki", ref.reshape(6, 3, 2, 3, 2))
        np.testing.assert_allclose(np.asarray(des.costs), costs, rtol=1e-7)
        np.testing.assert_allclose(np.asarray(des.final_cov), ref[-1], rtol=1e-7, atol=1e-9)


def test_uncoupled_nodes_are_kalman_bucy_filters():
    """L = 0: eq 28 is each node's Riccati equation, its steady state the CARE solution."""
    with enable_x64():
        rng = np.random.default_rng(5)
        system = random_system(rng, N=3)
        system = LargeScaleSystem(
            system.A, system.C, system.F, 0 * system.L, system.H1, system.H2, system.Q, system.R
        )
        ss = steady_state(system, CommunicationStructure.none(3))
        for i in range(3):
            A, H, F = (np.asarray(getattr(system, m)[i]) for m in ("A", "H1", "F"))
            W = F @ np.asarray(system.Q[i]) @ F.T
            P = scipy.linalg.solve_continuous_are(A.T, H.T, W, np.asarray(system.R[i]))
            np.testing.assert_allclose(
                np.asarray(ss.cov)[2 * i : 2 * i + 2, 2 * i : 2 * i + 2], P, rtol=1e-7
            )
        off = np.asarray(ss.cov).copy()
        for i in range(3):
            off[2 * i : 2 * i + 2, 2 * i : 2 * i + 2] = 0
        assert np.abs(off).max() < 1e-10
        assert bool(ss.ok) and ss.flags is NetworkDesignStatus  # as every result with a status
        raise_if_failed(ss)
        with pytest.raises(Exception, match="NO_FILTER"):
            raise_if_failed(eqx.tree_at(lambda s: s.status, ss, NetworkDesignStatus.NO_FILTER))


def scalar_nodes(a, h):
    """Uncoupled scalar nodes x_i' = a_i x_i + w_i, y_i = h_i x_i + v_i, Q_i = R_i = 1: eq 28 is
    node i's Riccati equation P' = 2 a_i P - h_i^2 P^2 + 1, solved in closed form below."""
    N, col = len(a), lambda v: jnp.asarray(v, jnp.float64)[:, None, None]
    ones = jnp.ones((N, 1, 1))
    return LargeScaleSystem(
        A=col(a), C=0 * ones, F=ones, L=jnp.zeros((N, N, 1, 1)), H1=col(h), H2=0 * ones,
        Q=ones, R=ones,
    )  # fmt: skip


def test_steady_state_flags_a_covariance_that_has_not_settled():
    """An unstable node that measures nothing (P' = 0.4 P + 1: no steady state) was reported
    with status OK: J = 1.2e9 at horizon 50, an EquinoxRuntimeError from diffrax (max_steps) at
    the default horizon (under vmap it stopped the whole batch), and with a second node J =
    1.4e154 (diffrax's RMS norm of P overflowed to inf, and |P'| < inf fired the steady-state
    event); a stable node cut short by the horizon likewise; a design past max_steps raised.
    SteadyState.J summed the costs of a whole vmap-ed batch."""
    with enable_x64():
        none1, none2 = CommunicationStructure.none(1), CommunicationStructure.none(2)
        NOT_SETTLED, FAILED = NetworkDesignStatus.NOT_SETTLED, NetworkDesignStatus.SOLVER_FAILED
        # a = -1, h = 1: P' = -(P - p1)(P - p2), p1 = sqrt(2) - 1 the steady state, p2 = -1 -
        # sqrt(2); from P(0) = 0, P(t) = p1 p2 (1 - e^{-kt}) / (p2 - p1 e^{-kt}), k = p1 - p2
        p1, p2 = np.sqrt(2) - 1, -np.sqrt(2) - 1
        decay = np.exp(-(p1 - p2) * 0.1)
        ss = steady_state(scalar_nodes([-1.0], [1.0]), none1)
        assert ss.status == 0 and float(ss.settle_time) < 20
        np.testing.assert_allclose(ss.J, p1, rtol=1e-8)
        short = steady_state(scalar_nodes([-1.0], [1.0]), none1, horizon=0.1)
        assert short.status == NOT_SETTLED and float(short.settle_time) == 0.1
        np.testing.assert_allclose(short.J, p1 * p2 * (1 - decay) / (p2 - p1 * decay), rtol=1e-8)
        # a = 0.2, h = 0: P(t) = (e^{0.4 t} - 1) / 0.4 grows without bound
        unstable = scalar_nodes([0.2], [0.0])
        grown = steady_state(unstable, none1, horizon=50.0)
        assert grown.status == NOT_SETTLED and float(grown.settle_time) == 50.0
        np.testing.assert_allclose(grown.J, np.expm1(20.0) / 0.4, rtol=1e-8)
        # at the default horizon P overflows near t = 1770 and the solver stops (max_steps)
        assert steady_state(unstable, none1).status == NOT_SETTLED | FAILED
        both = jax.jit(steady_state)(scalar_nodes([-1.0, 0.2], [1.0, 0.0]), none2)
        assert both.status & NOT_SETTLED
        np.testing.assert_allclose(both.costs[0], p1, rtol=1e-8)  # the stable node settled
        # vmap: one member's failure is its own status, not an exception for the batch
        batch = jax.vmap(lambda s: steady_state(s, none1, horizon=50.0))(
            jax.vmap(lambda a, h: scalar_nodes(a[None], h[None]))(
                jnp.asarray([-1.0, 0.2]), jnp.asarray([1.0, 0.0])
            )
        )
        np.testing.assert_array_equal(batch.status, [0, NOT_SETTLED])
        np.testing.assert_allclose(batch.J, [p1, np.expm1(20.0) / 0.4], rtol=1e-8)
        # grad through the event-terminated solve: dP/da = 1 + a / sqrt(a^2 + 1)
        slope = jax.grad(lambda a: steady_state(scalar_nodes(a[None], [1.0]), none1).J)(-1.0)
        np.testing.assert_allclose(slope, 1 - 1 / np.sqrt(2), rtol=1e-6)
        cut = design(scalar_nodes([-1.0], [1.0]), none1, jnp.ones((1, 1, 1)), ts=jnp.arange(3.0),
                     max_steps=3)  # fmt: skip
        assert cut.status & FAILED and cut.costs[0, 0] == 1.0  # P(0) = cov0, then inf


def test_steady_state_checks_its_arguments_as_design_does():
    """steady_state skipped design's checks: S = -I gave J = -0.414 with status OK, horizon = -1
    gave J = -1.69 (integrated backwards) with status OK, a NaN or indefinite cov0 an
    EquinoxRuntimeError from inside diffrax, a cov0 or S of the wrong shape an unpacking or
    einsum error naming no argument."""
    with enable_x64():
        system, none, one = (
            scalar_nodes([-1.0], [1.0]),
            CommunicationStructure.none(1),
            jnp.ones((1, 1, 1)),
        )
        for kwargs, match in (
            ({"S": -one}, r"S: must be positive semidefinite"),
            ({"S": jnp.ones((1, 1))}, r"S: expected a block per node, shape \(1, 1, 1\)"),
            ({"cov0": jnp.ones((1, 1))}, r"cov0: expected a block per node, shape \(1, 1, 1\)"),
            ({"cov0": -5 * one}, r"cov0: must be positive semidefinite"),
            ({"cov0": jnp.nan * one}, r"cov0: contains NaN"),
            ({"horizon": -1.0}, r"horizon: must be positive and finite"),
            ({"horizon": np.inf}, r"horizon: must be positive and finite"),
            ({"horizon": jnp.ones(2)}, r"horizon: expected a scalar time"),
            ({"max_steps": 0}, r"max_steps: must be a positive integer"),
        ):
            with pytest.raises(ValueError, match=f"^{match}"):
                steady_state(system, none, **kwargs)
        with pytest.raises(ValueError, match="^max_steps: must be a positive integer"):
            design(system, none, one, jnp.arange(3.0), max_steps=2.5)
        # traced, a NaN cov0 cannot be read: it is flagged, not raised from inside diffrax
        assert jax.jit(steady_state)(system, none, jnp.nan * one).status & Status.NONFINITE


@eqx.filter_jit
def _cost_and_grad(system, structure, P, free, S, node):
    return jax.value_and_grad(instantaneous_cost, argnums=3)(system, structure, P, free, S, node)


@pytest.mark.parametrize("name", ["none", "chain", "full"])
def test_step4_gradient_vanishes_at_designed_gain(name):
    """Autodiff check of step 4: d tr(S_i P_i') / d G~_i = 0 at the designed gain (to 1e-8 rel.),
    at an arbitrary joint covariance P (off-diagonal blocks non-zero) and a non-identity S_i."""
    with enable_x64():
        N = 3
        system = mass_chain(N)
        structure = getattr(CommunicationStructure, name)(N).at(0.0)
        X = np.random.default_rng(7).normal(size=(2 * N, 2 * N))
        P = jnp.asarray(0.1 * X @ X.T / N + 0.01 * np.eye(2 * N))
        S = jnp.asarray(np.stack([np.diag([1.0 + i, 0.5]) for i in range(N)]))
        for i in range(N):
            free = optimal_free_gain(system, structure, P, i)
            grad_zero = _cost_and_grad(system, structure, P, jnp.zeros_like(free), S, i)[1]
            assert float(jnp.linalg.norm(grad_zero)) > 1e-3
            cost, grad = _cost_and_grad(system, structure, P, free, S, i)
            rel = float(jnp.linalg.norm(grad) / jnp.linalg.norm(grad_zero))
            assert rel < 1e-8, (i, rel)
            # and it is a minimum: moving the free gain raises the cost
            moved = _cost_and_grad(system, structure, P, free + 1e-2 * (free != 0), S, i)[0]
            assert float(moved) > float(cost)


def explicit_eq9_step(system, hears, G, xhat, y, dt):
    """Eq 9 with Gamma_i and B_ij formed explicitly (eqs 11-12 + self-coupling), plain NumPy."""
    A, C, L, H1, H2 = (np.asarray(getattr(system, m)) for m in ("A", "C", "L", "H1", "H2"))
    new = np.empty_like(xhat)
    for i in range(len(xhat)):
        Gam = A[i] - G[i] @ H1[i] + (C[i] - G[i] @ H2[i]) @ L[i, i]
        rate = Gam @ xhat[i] + G[i] @ y[i]
        for j in range(len(xhat)):
            if hears[i, j] and j != i:
                rate += (C[i] - G[i] @ H2[i]) @ L[i, j] @ xhat[j]
        new[i] = xhat[i] + dt * rate
    return new


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_filter_step_against_explicit_form_and_transforms(chain3, dtype):
    """The scan step is eq 9 (explicit Gamma_i, B_ij in NumPy); jit, vmap and grad, f32 and f64."""
    T = 40
    with enable_x64(dtype == "float64"):
        dt_ = jnp.dtype(dtype)
        system64, structure, mean0, cov0, des = chain3
        system, mean0, cov0 = mass_chain(3, dtype=dt_), mean0.astype(dt_), cov0.astype(dt_)
        filt = NetworkFilter(structure, des.gains[:T].astype(dt_), DT)
        _, ys = jax.jit(simulate_network, static_argnums=(3, 4))(
            system, mean0, cov0, DT, T, jax.random.key(0)
        )
        prior = Gaussian(mean0, cov0)
        res = jax.jit(lambda ys: run(filt, system, ys, prior=prior))(ys)
        assert res.mean.dtype == dt_ and np.all(np.asarray(res.status) == 0)
        with pytest.raises(ValueError, match="^gains: time-varying with 40 steps"):
            run(filt, system, jnp.concatenate([ys, ys[:3]]), prior=prior)  # gains[39] reused
        with pytest.raises(ValueError, match="^ys: has missing"):  # was NaN estimates from there
            run(filt, system, ys.at[3, 0, 0].set(jnp.nan), prior=prior)
        x = np.asarray(mean0, np.float64)
        hears, gains = np.asarray(structure.hears), np.asarray(des.gains, np.float64)
        tol = 1e-12 if dtype == "float64" else 2e-5
        for k in range(T):
            np.testing.assert_allclose(np.asarray(res.mean[k]), x, rtol=tol, atol=tol)
            y = np.asarray(ys[k], np.float64)
            x = explicit_eq9_step(system64, hears, gains[k], x, y, DT)
        # vmap over systems (the model is a pytree) and measurements equals a loop
        systems = jax.jit(jax.vmap(lambda k: mass_chain(3, k_near=k, dtype=dt_)))(
            jnp.asarray([0.3, 0.6], dt_)
        )
        batched = jax.vmap(lambda s, y: run(filt, s, y, prior=prior).mean)(
            systems, jnp.stack([ys, 2 * ys])
        )
        second = run(filt, mass_chain(3, k_near=0.6, dtype=dt_), 2 * ys, prior=prior).mean
        np.testing.assert_allclose(np.asarray(batched[1]), np.asarray(second), rtol=tol, atol=tol)

        # grad through the filter w.r.t. the model (mass 0's stiffness) vs finite differences
        @jax.jit
        def loss(a):
            others = (getattr(system, m) for m in ("C", "F", "L", "H1", "H2", "Q", "R"))
            sys = LargeScaleSystem(system.A.at[0, 1, 0].set(a), *others)
            return jnp.sum(run(filt, sys, ys, prior=prior).final_mean ** 2)

        a0 = system.A[0, 1, 0]
        g = float(jax.grad(loss)(a0))
        if dtype == "float64":
            fd = (loss(a0 + 1e-6) - loss(a0 - 1e-6)) / 2e-6
            np.testing.assert_allclose(g, float(fd), rtol=1e-6)
        assert np.isfinite(g) and g != 0.0


def test_filter_names_the_argument_that_does_not_fit(chain3):
    """Measurements of the wrong width broadcast through eq 9 with status OK, and gains, a
    structure or a prior of the wrong size or precision (an integer mean, float32 against
    float64 gains or measurements) failed inside the trace without naming themselves."""
    system, structure, mean0, cov0, des = chain3
    _, ys = simulate_network(system, mean0, cov0, DT, 20, jax.random.key(0))
    prior = Gaussian(mean0, cov0)
    gains = des.gains[0]
    cases = [
        (NetworkFilter(structure, gains, DT), ys[..., :1], prior, r"^ys: expected shape \(T, 3, 5\)"),
        (NetworkFilter(structure, gains[..., :2], DT), ys, prior, r"^gains: expected shape \(3, 2, 5\)"),
        (NetworkFilter(CommunicationStructure.chain(2), gains, DT), ys, prior, r"^structure: has 2"),
        (NetworkFilter(structure, gains, DT), ys, Gaussian(mean0[:, :1], cov0), r"^prior.mean:"),
        (NetworkFilter(structure, gains, -DT), ys, prior, r"^dt: must be positive"),
        (NetworkFilter(structure, gains, DT), ys, Gaussian(mean0.astype(int), cov0), "^prior.mean: must be real"),
        (NetworkFilter(structure, gains, DT), ys, Gaussian(mean0.astype(jnp.float32), cov0),
         r"^prior.mean: is float32, narrower .*gains float64"),
    ]  # fmt: skip
    for filt, measurements, start, message in cases:
        with pytest.raises(ValueError, match=message):
            run(filt, system, measurements, prior=start)


def test_monte_carlo_matches_designed_cost(chain3):
    """Empirical error covariance of the sampled filter matches the designed P (eqs 28-31).

    The Euler discretisation biases the empirical J by about 1.7 dt relative (0.35 % here, well
    under the Monte Carlo standard error)."""
    with enable_x64():
        system, structure, mean0, cov0, des = chain3
        filt = NetworkFilter(structure, des.gains, DT)
        prior = Gaussian(mean0, cov0)

        def errors(key):
            xs, ys = simulate_network(system, mean0, cov0, DT, STEPS, key)
            e = xs - run(filt, system, ys, prior=prior).mean
            return jnp.einsum("tia,tia->t", e, e)

        runs = 64
        sq = np.asarray(jax.jit(jax.vmap(errors))(jax.random.split(jax.random.key(1), runs)))
        window = slice(STEPS // 2, STEPS)  # steady state: t in [5, 10]
        per_run = sq[:, window].mean(axis=1)
        se = per_run.std(ddof=1) / np.sqrt(runs)
        J = float(np.mean(des.J[window]))
        assert abs(per_run.mean() - J) < 4 * se, (per_run.mean(), J, se)
        assert se < 0.05 * J  # the check has teeth: a missing factor 1/2 would be far outside
        # the transient too: at t = 0.2 the error has not settled yet
        k = 100
        assert abs(sq[:, k].mean() - float(des.J[k])) < 4 * sq[:, k].std(ddof=1) / np.sqrt(runs)
