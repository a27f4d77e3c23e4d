"""Design of the network-structured optimal filter (lemma 2, lemma 3, theorem).

For each node i, with E_i the couplings it does not hear (eq 16), unbiasedness needs
(C_i - G_i H_i2) E_i = 0 (eqs 13, 17). Lemma 2, computed by one SVD H_i2 E_i = U S V^T instead of
the permutations of eqs 20-22: every solution is

    G_i = B_i + G~_i phi_i,   B_i = C_i E_i (H_i2 E_i)^+,
    rows of phi_i = a basis of the left null space of H_i2 E_i

(eq 18). ``phi_i`` is kept as a q x q matrix whose rows outside the null space are zero, so shapes
do not depend on ranks. The error e = x - x^ of all nodes obeys e' = Phi e + F w - G v exactly
(eq 37) with Phi_ii = Gamma_i = A_i - G_i H_i1 + (C_i - G_i H_i2) L_ii (self-coupling included,
docs/papers/network.md), Phi_ij = B_ij = (C_i - G_i H_i2) L_ij for j in C_i and 0 otherwise, so the joint
covariance obeys

    P' = Phi P + P Phi^T + F Q F^T + G R G^T,   P(0) = blkdiag(Sigma_i(0))         (eqs 28-31)

whose diagonal blocks are eq 28 and off-diagonal blocks eq 30. Step 4 of the theorem sets the
derivative of tr(S_i P_i') with respect to G~_i to zero:

    G~_i = [P_i H_i1^T + sum_{j in C_i or j = i} P_ij L_ij^T H_i2^T - B_i R_i]
           phi_i^T (phi_i R_i phi_i^T)^{-1}

(the printed '+ B_i' lost '- B_i R_i'). The gain is instantaneous (greedy); it does not depend on
S_i.
"""

from __future__ import annotations

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from jaxest._checks import check_matrix, check_positive_int, is_concrete
from jaxest._status import Status, StatusOfOne, finite_status, status_where
from jaxest.linalg import symmetrize, working_precision_by_default
from jaxest.network.structure import (
    CommunicationStructure,
    LargeScaleSystem,
    block_diag,
    check_existence,
    piece_index,
    unheard_couplings,
)
from jaxest.riccati import solve_filter_care


class GainConstraint(eqx.Module):
    """Lemma 2 for every node: G_i = particular_i + G~_i phi_i solves (C_i - G_i H_i2) E_i = 0."""

    particular: Float[Array, "N n q"]  #: B_i = C_i E_i (H_i2 E_i)^+ (eq 21)
    phi: Float[Array, "N q q"]  #: rows spanning the left null space of H_i2 E_i, other rows zero
    null_mask: Float[Array, "N q"]  #: 1 on the rows of phi that are in the null space
    residual: Float[Array, " N"]  #: ||(C_i - B_i H_i2) E_i|| / ||C_i E_i||: 0 iff eq 15 holds


def gain_constraint(system: LargeScaleSystem, structure: CommunicationStructure) -> GainConstraint:
    """Lemma 2 by SVD for a constant system and structure (works under jit/vmap/grad)."""
    E = unheard_couplings(system, structure)  # (N, h, Nn)
    M = system.H2 @ E  # (N, q, Nn)
    q, width = M.shape[-2:]
    if width < q:  # pad so that the thin SVD still returns a complete U (q x q)
        M = jnp.concatenate([M, jnp.zeros((*M.shape[:-1], q - width), M.dtype)], axis=-1)
        E = jnp.concatenate([E, jnp.zeros((*E.shape[:-1], q - width), E.dtype)], axis=-1)
    pinv, phi, null_mask = pseudo_inverse_and_left_null_rows(M)
    CE = system.C @ E
    particular = CE @ pinv
    # a diagnostic, not differentiated (the norm's derivative is NaN where eq 15 holds exactly)
    CE, gap = jax.lax.stop_gradient((CE, CE - particular @ M))
    scale = jnp.maximum(jnp.linalg.norm(CE, axis=(-2, -1)), jnp.finfo(M.dtype).tiny)
    residual = jnp.linalg.norm(gap, axis=(-2, -1)) / scale
    return GainConstraint(particular, phi, null_mask, residual)


@jax.custom_jvp
def pseudo_inverse_and_left_null_rows(M):
    """For M (..., q, w), w >= q, by its SVD: the pseudo-inverse M^+ (..., w, q), a q x q matrix
    phi whose rows are an orthonormal basis of the left null space of M (its other rows zero),
    and the mask of those rows. The rank counts singular values above max(q, w) eps s_max.

    Derivative at constant rank (the SVD's own is NaN at the zero or repeated singular values
    a rank-deficient M has, so the designed gains' gradient was NaN wherever the constraint
    bites): d M^+ = -M^+ dM M^+ + M^+ M^+T dM^T (I - M M^+) + (I - M^+ M) dM^T M^+T M^+
    (Golub & Pereyra 1973), and d phi = phi dP for the projector P = I - M M^+ =
    phi^T phi, dP = -(P dM M^+ + (P dM M^+)^T): the basis turns only as its span does, and
    every use of phi (G = B + G~ phi with G~ optimal) depends on the span alone."""
    U, s, Vt = jnp.linalg.svd(M, full_matrices=False)  # U (..., q, q), s (..., q)
    eps = jnp.finfo(M.dtype).eps
    in_range = s > max(M.shape[-2:]) * eps * s[..., :1]
    s_inv = jnp.where(in_range, 1.0 / jnp.where(in_range, s, 1.0), 0.0)
    pinv = jnp.einsum("...ku,...u,...qu->...kq", Vt.mT, s_inv, U)
    null_mask = (~in_range).astype(M.dtype)
    return pinv, null_mask[..., :, None] * U.mT, null_mask


@pseudo_inverse_and_left_null_rows.defjvp
def _pseudo_inverse_and_left_null_rows_jvp(primals, tangents):
    (M,), (dM,) = primals, tangents
    pinv, phi, null_mask = pseudo_inverse_and_left_null_rows(M)
    left_null = phi.mT @ phi  # I - M M^+
    right_null = jnp.eye(M.shape[-1], dtype=M.dtype) - pinv @ M  # I - M^+ M
    d_pinv = (
        -pinv @ dM @ pinv + pinv @ pinv.mT @ dM.mT @ left_null + right_null @ dM.mT @ pinv.mT @ pinv
    )
    moved = left_null @ dM @ pinv
    d_phi = -phi @ (moved + moved.mT)
    return (pinv, phi, null_mask), (d_pinv, d_phi, jnp.zeros_like(null_mask))


def closed_loop_blocks(system: LargeScaleSystem, structure: CommunicationStructure):
    """(Abar, Hbar): blocks (N, N, n, n) and (N, N, q, n) of what node i uses of node j:
    Abar_ij = [i = j] A_i + C_i L_ij, Hbar_ij = [i = j] H_i1 + H_i2 L_ij for j in C_i or j = i,
    zero otherwise. Phi_ij = Abar_ij - G_i Hbar_ij (eqs 11, 12, 36)."""
    N = system.num_nodes
    eye = jnp.eye(N, dtype=system.A.dtype)
    used = (structure.hears | jnp.eye(N, dtype=bool)).astype(system.A.dtype)
    L = system.L * used[:, :, None, None]
    Abar = eye[:, :, None, None] * system.A[:, None] + jnp.einsum("iac,ijcb->ijab", system.C, L)
    Hbar = eye[:, :, None, None] * system.H1[:, None] + jnp.einsum("iac,ijcb->ijab", system.H2, L)
    return Abar, Hbar


def to_blocks(P: Float[Array, "Nn Nn"], N: int) -> Float[Array, "N N n n"]:
    """The N x N blocks P_ij of a joint matrix, as an (N, N, n, n) array."""
    n = P.shape[-1] // N
    return jnp.transpose(P.reshape(N, n, N, n), (0, 2, 1, 3))


def from_blocks(X: Float[Array, "N N a b"]) -> Array:
    """Inverse of :func:`to_blocks`: assemble blocks X[i, j] into one matrix."""
    N, _, a, b = X.shape
    return jnp.transpose(X, (0, 2, 1, 3)).reshape(N * a, N * b)


def measurement_cross_covariance(P, Hbar):
    """K_i = E[e_i (y_i - y^_i)^T] = P_i H_i1^T + sum_{j in C_i or j = i} P_ij L_ij^T H_i2^T."""
    return jnp.einsum("ijab,ijcb->iac", to_blocks(P, Hbar.shape[0]), Hbar)


def optimal_gain(system, constraint: GainConstraint, Hbar, P) -> Float[Array, "N n q"]:
    """Step 4 of the theorem (corrected, docs/papers/network.md) followed by eq 18: the gains G_i (N, n, q)."""
    K = measurement_cross_covariance(P, Hbar)
    B, phi = constraint.particular, constraint.phi
    free = (K - B @ system.R) @ jnp.swapaxes(phi, -1, -2)
    # phi R phi^T is zero outside the null rows; adding the identity there makes it invertible
    # without changing G~ phi (those rows of phi are zero).
    gram = phi @ system.R @ jnp.swapaxes(phi, -1, -2) + jax.vmap(jnp.diag)(
        1.0 - constraint.null_mask
    )
    free = jnp.swapaxes(jnp.linalg.solve(gram, jnp.swapaxes(free, -1, -2)), -1, -2)
    return B + free @ phi


def closed_loop_matrix(Abar, Hbar, G) -> Float[Array, "Nn Nn"]:
    """Phi of e' = Phi e + F w - G v (eq 37): Phi_ij = Abar_ij - G_i Hbar_ij."""
    return from_blocks(Abar - jnp.einsum("iaq,ijqb->ijab", G, Hbar))


def noise_rate(system, G) -> Float[Array, "Nn Nn"]:
    """blkdiag(F_i Q_i F_i^T + G_i R_i G_i^T), the noise term of P'."""
    FQF = jnp.einsum("iap,ipq,ibq->iab", system.F, system.Q, system.F)
    GRG = jnp.einsum("iaq,iqr,ibr->iab", G, system.R, G)
    return block_diag(FQF + GRG)


def covariance_rate(system, Abar, Hbar, G, P) -> Float[Array, "Nn Nn"]:
    """P' = Phi P + P Phi^T + F Q F^T + G R G^T (eqs 28 and 30 are its blocks)."""
    PhiP = closed_loop_matrix(Abar, Hbar, G) @ P
    return PhiP + PhiP.T + noise_rate(system, G)


def node_costs(P, S) -> Float[Array, " N"]:
    """J_i = tr(S_i P_i) (eq 43) for every node."""
    return jnp.einsum(
        "iab,iba->i", S, jnp.diagonal(to_blocks(P, S.shape[0]), axis1=0, axis2=1).transpose(2, 0, 1)
    )


class _Pieces(eqx.Module):
    """What the covariance ODE needs on each constant piece of a piecewise-constant design."""

    starts: tuple[float, ...] = eqx.field(static=True)
    system: LargeScaleSystem
    constraint: GainConstraint
    Abar: Array
    Hbar: Array

    def at(self, t):
        k = piece_index(self.starts, t)
        pick = lambda x: x[k]
        return jax.tree.map(pick, (self.system, self.constraint, self.Abar, self.Hbar))


def _pieces(system: LargeScaleSystem, structure: CommunicationStructure) -> _Pieces:
    starts = tuple(sorted(set(system.switch_times) | set(structure.switch_times)))
    systems, constraints, Abars, Hbars = [], [], [], []
    for t in starts:
        sys_t, struct_t = system.at(t), structure.at(t)
        systems.append(sys_t)
        constraints.append(gain_constraint(sys_t, struct_t))
        Abar, Hbar = closed_loop_blocks(sys_t, struct_t)
        Abars.append(Abar)
        Hbars.append(Hbar)
    stack = lambda items: jax.tree.map(lambda *x: jnp.stack(x), *items)
    return _Pieces(starts, stack(systems), stack(constraints), jnp.stack(Abars), jnp.stack(Hbars))


def _vector_field(t, P, pieces: _Pieces):
    """Right-hand side of eqs 28-31 with the gains of step 4 (``args`` of diffrax = pieces)."""
    sys, cons, Abar, Hbar = pieces.at(t)
    G = optimal_gain(sys, cons, Hbar, P)
    return symmetrize(covariance_rate(sys, Abar, Hbar, G, P))


def _design_field(t, P, args):
    return _vector_field(t, P, args[0])


def _save_gains_and_costs(t, P, args):
    pieces, S = args
    sys, cons, _, Hbar = pieces.at(t)
    return optimal_gain(sys, cons, Hbar, P), node_costs(P, S), P


def _tolerances(dtype):
    return (1e-10, 1e-12) if jnp.finfo(dtype).bits == 64 else (1e-5, 1e-7)


#: the flags of a design (:func:`design`, :func:`steady_state`): the core's, NO_FILTER,
#: NOT_SETTLED and SOLVER_FAILED
NetworkDesignStatus = Status.extend(
    "NetworkDesignStatus",
    NO_FILTER=(
        4,
        "a node admits no filter of the communication structure (lemma 1, eq 15): it neither "
        "hears a node it is coupled to nor measures that coupling, and the gains and costs "
        "are not those of a filter; call design outside jit to have the node named",
    ),
    NOT_SETTLED=(
        8,
        "steady_state: P' of eqs 28-31 had not fallen to the steady-state tolerance by "
        "t = horizon, so the gains and costs are those at settle_time, not a steady state's: "
        "either there is no steady state (a mode of the error dynamics, eq 37, with "
        "Re lambda >= 0 that no node measures makes the covariance grow without bound; "
        "centralized_steady_state names such a mode of the whole system) or the horizon is "
        "shorter than the slowest mode needs; raise horizon",
    ),
    SOLVER_FAILED=(
        16,
        "the ODE solver of eqs 28-31 (diffrax) stopped before the end of the interval: "
        "max_steps was reached, the step size collapsed or the covariance overflowed; what "
        "comes after is not the ODE's solution; raise max_steps, or see NOT_SETTLED for a "
        "covariance that grows without bound",
    ),
)


def solver_status(sol) -> Int[Array, ""]:
    """SOLVER_FAILED where diffrax stopped short (``throw=False``: its failures are data, and
    under ``vmap`` one member's does not stop the batch), a terminating event (the steady
    state's) being no failure."""
    stopped = (sol.result != diffrax.RESULTS.successful) & (
        sol.result != diffrax.RESULTS.event_occurred
    )
    return status_where(stopped, NetworkDesignStatus.SOLVER_FAILED)


def design_status(pieces, *arrays) -> Int[Array, ""]:
    """NONFINITE where ``arrays`` are, NO_FILTER where lemma 2's constraint residual of a node
    on some piece exceeds sqrt(eps) (it is rounding, about eps, where lemma 1 holds, and of
    order one where it fails): what :func:`check_existence` says eagerly, under ``jit``."""
    residual = pieces.constraint.residual  # (pieces, N)
    no_filter = jnp.any(residual > jnp.sqrt(jnp.finfo(residual.dtype).eps))
    return finite_status(*arrays) | status_where(no_filter, NetworkDesignStatus.NO_FILTER)


class NetworkDesign(StatusOfOne):
    """The designed filter on a time grid: ``ts`` (K,), gains G_i(t_k) (K, N, n, q), node costs
    tr(S_i P_i(t_k)) (K, N), the joint error covariance at the last time (Nn, Nn) and the
    status (:data:`NetworkDesignStatus`)."""

    ts: Float[Array, " K"]
    gains: Float[Array, "K N n q"]
    costs: Float[Array, "K N"]
    final_cov: Float[Array, "Nn Nn"]
    status: Int[Array, ""]

    flags = NetworkDesignStatus

    @property
    def J(self) -> Float[Array, " K"]:
        """J(t_k) = sum_i tr(S_i P_i(t_k)) (eq 43)."""
        return jnp.sum(self.costs, axis=-1)


def _initial_cov(system, cov0):
    if cov0 is None:
        return jnp.zeros((system.num_nodes * system.state_dim,) * 2, system.A.dtype)
    return block_diag(cov0)


def _weights(system, S):
    if S is None:
        return jnp.broadcast_to(
            jnp.eye(system.state_dim, dtype=system.A.dtype), system.A.shape[-3:]
        )
    return S


def check_design_arguments(system: LargeScaleSystem, cov0, S, max_steps) -> None:
    """What :func:`design` and :func:`steady_state` share: ``cov0`` and ``S`` (where given) N
    symmetric positive semidefinite n x n blocks (a non-symmetric or indefinite cov0 gave other
    costs silently, an indefinite S a negative J, a NaN cov0 an error from inside diffrax, and a
    joint (Nn, Nn) one an unpacking error), ``max_steps`` a positive integer."""
    blocks = (system.num_nodes, system.state_dim, system.state_dim)
    for name, value in (("cov0", cov0), ("S", S)):
        if value is not None:
            if np.ndim(value) != 3:
                got = np.shape(value)
                raise ValueError(f"{name}: expected a block per node, shape {blocks}; got {got}")
            check_matrix(name, value, blocks, psd=True, ndim=3)
    check_positive_int("max_steps", max_steps)


@working_precision_by_default
def design(
    system: LargeScaleSystem,
    structure: CommunicationStructure,
    cov0: Float[Array, "N n n"],
    ts: Float[Array, " K"],
    S: Float[Array, "N n n"] | None = None,
    max_steps: int = 100_000,
) -> NetworkDesign:
    """Integrate eqs 28-31 with the gains of step 4 (diffrax Tsit5, adaptive) from t = ts[0]
    with P(0) = blkdiag(cov0) (eqs 29, 31); return gains and costs at ``ts``.

    Raises ``ValueError`` naming the node if the structure admits no filter (lemma 1), and
    naming ``cov0`` or ``S`` unless each is N positive semidefinite n x n blocks
    (:func:`check_design_arguments`). Where the solver stops short (``max_steps``) the status
    carries SOLVER_FAILED, and the times it did not reach hold inf (NONFINITE).
    """
    check_design_arguments(system, cov0, S, max_steps)
    if np.ndim(ts) != 1 or np.size(ts) == 0:
        raise ValueError(f"ts: expected a vector of times, got shape {np.shape(ts)}")
    if is_concrete(ts) and np.any(np.diff(np.asarray(ts)) < 0):  # an error from inside diffrax
        raise ValueError("ts: must be increasing (the times the design is saved at)")
    check_existence(system, structure)
    return _design(
        system, structure, cov0, jnp.asarray(ts, system.A.dtype), _weights(system, S), max_steps
    )


@eqx.filter_jit
def _design(system, structure, cov0, ts, S, max_steps):
    pieces = _pieces(system, structure)
    rtol, atol = _tolerances(system.A.dtype)
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(_design_field),
        diffrax.Tsit5(),
        t0=ts[0],
        t1=ts[-1],
        dt0=None,
        y0=_initial_cov(system, cov0),
        saveat=diffrax.SaveAt(ts=ts, fn=_save_gains_and_costs),
        args=(pieces, S),
        stepsize_controller=diffrax.PIDController(
            rtol=rtol, atol=atol, jump_ts=list(pieces.starts[1:]) or None
        ),
        max_steps=max_steps,
        throw=False,
    )
    gains, costs, covs = sol.ys
    status = design_status(pieces, gains, costs) | solver_status(sol)
    return NetworkDesign(ts, gains, costs, covs[-1], status)


class SteadyState(StatusOfOne):
    """Steady state of eqs 28-31 for a constant system: joint covariance P, gains G_i, node costs
    tr(S_i P_i), the time it took to settle, the norm of P' there and the status
    (:data:`NetworkDesignStatus`; NOT_SETTLED: P' had not vanished by the horizon, and these are
    the values at ``settle_time``, not a steady state's)."""

    cov: Float[Array, "Nn Nn"]
    gains: Float[Array, "N n q"]
    costs: Float[Array, " N"]
    settle_time: Float[Array, ""]
    rate_norm: Float[Array, ""]
    status: Int[Array, ""]

    flags = NetworkDesignStatus

    @property
    def J(self) -> Float[Array, ""]:
        """J = sum_i tr(S_i P_i) (eq 43), per member of a ``vmap``-ed batch (it summed the
        whole batch's costs)."""
        return jnp.sum(self.costs, axis=-1)


@working_precision_by_default
def steady_state(
    system: LargeScaleSystem,
    structure: CommunicationStructure,
    cov0: Float[Array, "N n n"] | None = None,
    S: Float[Array, "N n n"] | None = None,
    horizon: float = 1e4,
    max_steps: int = 100_000,
) -> SteadyState:
    """Integrate eqs 28-31 with the gains of step 4 from P(0) = blkdiag(cov0) (zero if None;
    eqs 29, 31) until P' vanishes (diffrax steady-state event: |P'| < 1e-11 + 1e-9 |P|, RMS
    norms, in float64; 1e-6 + 1e-4 |P| in float32), at most up to t = ``horizon``, as
    docs/papers/network.md recommends over a fixed-point Lyapunov iteration.

    Raises ``ValueError`` naming the node if the structure admits no filter (lemma 1), naming
    ``cov0`` or ``S`` as :func:`design` does (:func:`check_design_arguments`), and ``horizon``
    unless it is a positive finite scalar. The status carries NOT_SETTLED where P' had not
    vanished by the horizon: there is no steady state (a mode of the error dynamics e' = Phi e
    (eq 37) with Re lambda >= 0 that no node measures: P grows without bound) or the horizon is
    too short; with SOLVER_FAILED where diffrax stopped short (``max_steps``, an overflowing P).
    The gains and costs are then those at ``settle_time``, not a steady state's.
    """
    if len(system.switch_times) > 1 or len(structure.switch_times) > 1:
        raise ValueError("system: steady_state needs a constant system and structure; use design()")
    check_design_arguments(system, cov0, S, max_steps)
    if np.ndim(horizon) != 0:
        raise ValueError(f"horizon: expected a scalar time, got shape {np.shape(horizon)}")
    if is_concrete(horizon) and not (np.isfinite(horizon) and horizon > 0):
        raise ValueError(f"horizon: must be positive and finite, got {horizon}")
    check_existence(system, structure)
    return _steady_state(system, structure, cov0, _weights(system, S), horizon, max_steps)


def _rms_norm(x) -> Float[Array, ""]:
    """sqrt(mean(x^2)), diffrax's norm for the steady-state event, without overflow: a P growing
    without bound (no steady state) squared to inf near |P| = 1e154, and |P'| < inf settled it.
    The scale max|x| is kept between the smallest normal number and its inverse: XLA divides by
    multiplying with the reciprocal, which flushed to zero above 2^1022 (a norm of 0). inf or
    NaN where x holds one, so that such a P never settles."""
    tiny = jnp.finfo(x.dtype).tiny
    scale = jnp.clip(jnp.max(jnp.abs(x)), tiny, 1 / tiny)
    return scale * jnp.sqrt(jnp.mean((x / scale) ** 2))


@eqx.filter_jit
def _steady_state(system, structure, cov0, S, horizon, max_steps):
    pieces = _pieces(system, structure)
    rtol, atol = _tolerances(system.A.dtype)
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(_vector_field),
        diffrax.Tsit5(),
        t0=0.0,
        t1=horizon,
        dt0=None,
        y0=_initial_cov(system, cov0),
        saveat=diffrax.SaveAt(t1=True),
        args=pieces,
        stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol),
        event=diffrax.Event(
            diffrax.steady_state_event(rtol=10 * rtol, atol=10 * atol, norm=_rms_norm)
        ),
        max_steps=max_steps,
        throw=False,
    )
    P = sol.ys[-1]
    sys, cons, _, Hbar = pieces.at(sol.ts[-1])
    gains, costs = optimal_gain(sys, cons, Hbar, P), node_costs(P, S)
    rate_norm = jnp.linalg.norm(_vector_field(sol.ts[-1], P, pieces))
    settled = sol.result == diffrax.RESULTS.event_occurred  # not: the horizon, or a failure
    status = (
        design_status(pieces, gains, costs)
        | solver_status(sol)
        | status_where(~settled, NetworkDesignStatus.NOT_SETTLED)
    )
    return SteadyState(P, gains, costs, sol.ts[-1], rate_norm, status)


@eqx.filter_jit
def instantaneous_cost(system, structure, P, free, S, node):
    """tr(S_i [P']_ii) as a function of node i's free gain part G~_i (n, q) (lemma 4, eq 44), at
    the joint covariance P, the other nodes keeping their optimal gains. ``node`` may be an int or
    an integer array (traced: one compilation serves every node). Used to check step 4: its
    gradient vanishes at the designed gain."""
    constraint = gain_constraint(system, structure)
    Abar, Hbar = closed_loop_blocks(system, structure)
    G = optimal_gain(system, constraint, Hbar, P)
    G = G.at[node].set(constraint.particular[node] + free @ constraint.phi[node])
    dP = covariance_rate(system, Abar, Hbar, G, P)
    return node_costs(dP, S)[node]


@eqx.filter_jit
def optimal_free_gain(system, structure, P, node):
    """The free part G~_i of step 4 at P (zero columns outside the null space of phi_i); ``node``
    an int or an integer array."""
    constraint = gain_constraint(system, structure)
    _, Hbar = closed_loop_blocks(system, structure)
    G = optimal_gain(system, constraint, Hbar, P)[node]
    # phi_i has orthonormal rows on the null space: G~_i = (G_i - B_i) phi_i^T
    return (G - constraint.particular[node]) @ constraint.phi[node].T


@working_precision_by_default
def centralized_steady_state(system: LargeScaleSystem):
    """Steady-state Kalman-Bucy covariance of the whole system (the lower bound on every structure):
    the filter CARE A P + P A^T - P H^T R^{-1} H P + F Q F^T = 0 through ``jaxest.riccati``."""
    A, H, W, R = system.centralized()
    return solve_filter_care(A, H, W, R).X
