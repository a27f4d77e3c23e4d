"""Large-scale system and communication structure (section 2 of Zhang & Dai), lemma 1.

N coupled continuous-time subsystems, i = 0..N-1 (eqs 1-3)::

    x_i' = A_i x_i + C_i z_i + F_i w_i,     z_i = sum_j L_ij x_j,
    y_i  = H_i1 x_i + H_i2 z_i + v_i,       E[w_i w_i^T] = Q_i delta, E[v_i v_i^T] = R_i delta.

All subsystems share the sizes n (state), h (coupling), q (measurement), p (process noise); pad with
zero rows/columns where a subsystem is smaller. Every matrix is stacked over nodes, and may carry
one more leading axis, one entry per piece of a piecewise-constant time variation that starts at
``switch_times[k]`` (``switch_times[0] == 0``). The communication structure C(t) of the paper is
``hears[i, j]`` = node i receives node j's estimate (j in C_i), piecewise constant the same way.
Both are equinox Modules, so they ``vmap`` (e.g. over coupling strengths) and ``jit``.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from jaxest._checks import check_matrix, is_concrete
from jaxest.linalg import working_precision_by_default
from jaxest.models import psd_root


def piece_index(switch_times: tuple[float, ...], t) -> Array:
    """Index of the piece of a piecewise-constant schedule that holds at time ``t``."""
    starts = jnp.asarray(switch_times)
    return jnp.clip(jnp.searchsorted(starts, t, side="right") - 1, 0, len(switch_times) - 1)


def pick_piece(value: Array, ndim: int, index) -> Array:
    return value[index] if value.ndim == ndim + 1 else value


def _check_switch_times(switch_times):
    times = np.asarray(switch_times, dtype=float)
    if times.ndim != 1 or times.size == 0 or times[0] != 0.0 or np.any(np.diff(times) <= 0):
        raise ValueError(
            f"switch_times: expected increasing times starting at 0, got {switch_times}"
        )


class LargeScaleSystem(eqx.Module):
    """The coupled system of eqs 1-3, every matrix stacked over the N nodes.

    Shapes: A (N, n, n), C (N, n, h), F (N, n, p), L (N, N, h, n) with L[i, j] = L_ij,
    H1 (N, q, n), H2 (N, q, h), Q (N, p, p), R (N, q, q); each may have a leading axis of length
    ``len(switch_times)`` for a piecewise-constant time-varying system.
    """

    A: Float[Array, "*K N n n"]
    C: Float[Array, "*K N n h"]
    F: Float[Array, "*K N n p"]
    L: Float[Array, "*K N N h n"]
    H1: Float[Array, "*K N q n"]
    H2: Float[Array, "*K N q h"]
    Q: Float[Array, "*K N p p"]
    R: Float[Array, "*K N q q"]
    switch_times: tuple[float, ...] = eqx.field(static=True, default=(0.0,))

    def __check_init__(self):
        _check_switch_times(self.switch_times)
        N, n = self.A.shape[-3], self.A.shape[-1]
        h, q, p = self.C.shape[-1], self.H1.shape[-2], self.F.shape[-1]
        shapes = {
            "A": (N, n, n),
            "C": (N, n, h),
            "F": (N, n, p),
            "L": (N, N, h, n),
            "H1": (N, q, n),
            "H2": (N, q, h),
            "Q": (N, p, p),
            "R": (N, q, q),
        }
        for name, shape in shapes.items():
            value = getattr(self, name)
            if value.shape[value.ndim - len(shape) :] != shape or value.ndim not in (
                len(shape),
                len(shape) + 1,
            ):
                raise ValueError(
                    f"{name}: expected shape {shape} (or with a time axis), got {value.shape}"
                )
            if value.ndim == len(shape) + 1 and value.shape[0] != len(self.switch_times):
                raise ValueError(
                    f"{name}: time axis of length {value.shape[0]}, "
                    f"but {len(self.switch_times)} switch_times"
                )
        # values are checked when concrete; under jit/vmap check_matrix checks shapes only. A
        # NaN in the others surfaced as an EquinoxRuntimeError from inside the design's ODE
        for name in ("A", "C", "F", "H1", "H2"):
            check_matrix(name, getattr(self, name), ndim=3)  # finite
        check_matrix("L", self.L, ndim=4)
        check_matrix("Q", self.Q, psd=True, ndim=3)
        check_matrix("R", self.R, spd=True, ndim=3)

    @property
    def num_nodes(self) -> int:
        return self.A.shape[-3]

    @property
    def state_dim(self) -> int:
        return self.A.shape[-1]

    @property
    def obs_dim(self) -> int:
        return self.H1.shape[-2]

    def at(self, t) -> LargeScaleSystem:
        """The constant system that holds at time ``t``."""
        k = piece_index(self.switch_times, t)
        ndims = {"A": 3, "C": 3, "F": 3, "L": 4, "H1": 3, "H2": 3, "Q": 3, "R": 3}
        return LargeScaleSystem(**{m: pick_piece(getattr(self, m), d, k) for m, d in ndims.items()})

    def centralized(self):
        """The whole system as one: (A, H, F Q F^T, R) with x = [x_1; ...; x_N] (eq 4).

        A = blkdiag(A_i) + blkdiag(C_i) L, H = blkdiag(H_i1) + blkdiag(H_i2) L (constant system).
        """
        N, n, q = self.num_nodes, self.state_dim, self.obs_dim
        A = block_diag(self.A) + jnp.einsum("iac,ijcb->iajb", self.C, self.L).reshape(N * n, N * n)
        H = block_diag(self.H1) + jnp.einsum("iac,ijcb->iajb", self.H2, self.L).reshape(
            N * q, N * n
        )
        FQF = jnp.einsum("iap,ipq,ibq->iab", self.F, self.Q, self.F)
        return A, H, block_diag(FQF), block_diag(self.R)


def block_diag(blocks: Float[Array, "N a b"]) -> Float[Array, "Na Nb"]:
    """blkdiag(blocks[0], ..., blocks[N-1]) (the paper's eq 8 'Kronecker' sum is this)."""
    N, a, b = blocks.shape
    eye = jnp.eye(N, dtype=blocks.dtype)
    return jnp.einsum("ij,iab->iajb", eye, blocks).reshape(N * a, N * b)


class CommunicationStructure(eqx.Module):
    """C(t): ``hears[i, j]`` is True when node j sends its estimate to node i (j in C_i).

    ``hears`` is (N, N) or (K, N, N) for a structure that switches at ``switch_times``. The diagonal
    is ignored (a node always knows its own estimate).
    """

    hears: Bool[Array, "*K N N"]
    switch_times: tuple[float, ...] = eqx.field(static=True, default=(0.0,))

    def __check_init__(self):
        _check_switch_times(self.switch_times)
        if self.hears.ndim not in (2, 3) or self.hears.shape[-1] != self.hears.shape[-2]:
            raise ValueError(f"hears: expected shape (N, N) or (K, N, N), got {self.hears.shape}")
        if not jnp.issubdtype(self.hears.dtype, jnp.integer) and self.hears.dtype != bool:
            # a float one raised a TypeError from a logical operation in the design
            raise ValueError(f"hears: must be boolean, got {self.hears.dtype}; use hears != 0")
        if self.hears.ndim == 3 and self.hears.shape[0] != len(self.switch_times):
            raise ValueError(
                f"hears: time axis of length {self.hears.shape[0]}, "
                f"but {len(self.switch_times)} switch_times"
            )

    @classmethod
    def from_offsets(cls, N: int, offsets) -> CommunicationStructure:
        """Node i hears node i + d for every d in ``offsets`` that stays inside 0..N-1."""
        index = np.arange(N)
        hears = np.zeros((N, N), dtype=bool)
        for d in offsets:
            hears |= index[None, :] - index[:, None] == d
        return cls(jnp.asarray(hears))

    @classmethod
    def none(cls, N: int) -> CommunicationStructure:
        """Fully decentralized: nobody hears anybody (Sanders et al.)."""
        return cls.from_offsets(N, [])

    @classmethod
    def chain(cls, N: int) -> CommunicationStructure:
        """Each node hears its chain neighbours i - 1 and i + 1."""
        return cls.from_offsets(N, [-1, 1])

    @classmethod
    def full(cls, N: int) -> CommunicationStructure:
        """Every node hears every other node."""
        return cls(jnp.asarray(~np.eye(N, dtype=bool)))

    @property
    def num_nodes(self) -> int:
        return self.hears.shape[-1]

    def at(self, t) -> CommunicationStructure:
        """The structure that holds at time ``t``, diagonal cleared."""
        hears = pick_piece(self.hears, 2, piece_index(self.switch_times, t))
        return CommunicationStructure(hears & ~jnp.eye(self.num_nodes, dtype=bool))

    def links(self) -> int:
        """Number of directed links (j -> i, j != i) of a constant structure."""
        hears = np.asarray(self.hears, dtype=bool) & ~np.eye(self.num_nodes, dtype=bool)
        return int(hears.sum(axis=(-2, -1)).max())


def unheard_couplings(system: LargeScaleSystem, structure: CommunicationStructure) -> Array:
    """E_i of eq 16 for every node, as (N, h, N n): the blocks L_ij of the nodes j != i that i does
    not hear, the other blocks zeroed (zero columns change neither eq 15 nor eq 17)."""
    N, n, h = system.num_nodes, system.state_dim, system.C.shape[-1]
    unheard = ~structure.hears & ~jnp.eye(N, dtype=bool)
    E = system.L * unheard[:, :, None, None].astype(system.L.dtype)
    return jnp.transpose(E, (0, 2, 1, 3)).reshape(N, h, N * n)


def existence_ranks(system: LargeScaleSystem, structure: CommunicationStructure) -> np.ndarray:
    """Lemma 1 (eq 15) for a constant system: (N, 2) integer array of rank(H_i2 E_i) and
    rank([H_i2; C_i] E_i); node i admits a filter of the structure iff the two are equal."""
    E = np.asarray(unheard_couplings(system, structure), dtype=np.float64)
    H2 = np.asarray(system.H2, dtype=np.float64)
    C = np.asarray(system.C, dtype=np.float64)
    ranks = []
    for i in range(system.num_nodes):
        both = np.concatenate([H2[i], C[i]]) @ E[i]
        tol = (
            max(both.shape)
            * np.finfo(np.asarray(system.H2).dtype).eps
            * max(np.abs(both).max(), 1e-300)
        )
        ranks.append(
            [np.linalg.matrix_rank(H2[i] @ E[i], tol=tol), np.linalg.matrix_rank(both, tol=tol)]
        )
    return np.asarray(ranks, dtype=int)


def check_existence(system: LargeScaleSystem, structure: CommunicationStructure) -> None:
    """Raise ``ValueError`` naming the first node for which lemma 1 fails, on every piece of a
    piecewise-constant system/structure. Does nothing where an array it reads is traced (not
    concrete: under ``jax.grad`` with respect to C or H2 it raised a
    ``TracerArrayConversionError``)."""
    if not all(is_concrete(a) for a in (system.L, system.H2, system.C, structure.hears)):
        return
    for t in sorted(set(system.switch_times) | set(structure.switch_times)):
        sys_t, struct_t = system.at(t), structure.at(t)
        ranks = existence_ranks(sys_t, struct_t)
        bad = np.flatnonzero(ranks[:, 0] != ranks[:, 1])
        if bad.size:
            i = int(bad[0])
            hears = np.asarray(struct_t.hears[i])
            L = np.asarray(sys_t.L[i])
            silent = [
                j for j in range(system.num_nodes) if j != i and not hears[j] and np.any(L[j])
            ]
            raise ValueError(
                f"structure: node {i} admits no filter from t = {t} (lemma 1, eq 15: "
                f"rank H_i2 E_i = {ranks[i, 0]} < rank [H_i2; C_i] E_i = {ranks[i, 1]}): "
                f"it neither hears nodes {silent} nor measures the coupling it receives from them"
                + (f"; nodes {bad.tolist()} fail" if bad.size > 1 else "")
            )


def simulate_step(system: LargeScaleSystem, x: Float[Array, "N n"], t, dt: float, key):
    """One Euler-Maruyama step of eqs 1-3 from x(t): returns (x(t + dt), y_k) with the sampled
    measurement y_k = (1/dt) * integral of y over [t, t + dt] = H x(t) + dv / dt, dv ~ N(0, R dt)."""
    N, n = x.shape
    sys = system.at(t)
    kw, kv = jax.random.split(key)
    A, H, _, _ = sys.centralized()
    noise = lambda k, cov: jnp.einsum(
        "iab,ib->ia", jax.vmap(psd_root)(cov), jax.random.normal(k, cov.shape[:2], x.dtype)
    )
    w, v = noise(kw, sys.Q), noise(kv, sys.R)
    y = (H @ x.reshape(-1)).reshape(N, -1) + v / jnp.sqrt(dt)
    drift = (A @ x.reshape(-1)).reshape(N, n)
    return x + dt * drift + jnp.sqrt(dt) * jnp.einsum("iap,ip->ia", sys.F, w), y


def draw_initial_state(mean0: Float[Array, "N n"], cov0: Float[Array, "N n n"], key):
    """x(0) ~ N(mean0, blkdiag(cov0)) (cov0 positive semidefinite: :func:`psd_root`)."""
    normal = jax.random.normal(key, mean0.shape, mean0.dtype)
    return mean0 + jnp.einsum("iab,ib->ia", jax.vmap(psd_root)(cov0), normal)


@working_precision_by_default
def simulate_network(
    system: LargeScaleSystem,
    mean0: Float[Array, "N n"],
    cov0: Float[Array, "N n n"],
    dt: float,
    num_steps: int,
    key,
):
    """Euler-Maruyama draw of eqs 1-3 sampled every ``dt`` (see :func:`simulate_step`).

    Returns ``(states, ys)``: x(t_k) with shape (T, N, n) and the sampled measurements y_k,
    shape (T, N, q). The initial state is drawn from N(mean0, blkdiag(cov0)).
    """
    key0, key = jax.random.split(key)

    def body(x, args):
        k, step_key = args
        x_next, y = simulate_step(system, x, k * dt, dt, step_key)
        return x_next, (x, y)

    keys = jax.random.split(key, num_steps)
    _, (states, ys) = jax.lax.scan(
        body, draw_initial_state(mean0, cov0, key0), (jnp.arange(num_steps), keys)
    )
    return states, ys
