"""The network-structured filter (eq 9) on sampled data, on one device or one node per device.

Node i runs x^_i' = Gamma_i x^_i + sum_{j in C_i} B_ij x^_j + G_i y_i (eq 9, with eqs 11-12 and
the self-coupling of docs/papers/network.md), written in the equivalent innovation form

    x^_i' = A_i x^_i + C_i z^_i + G_i (y_i - H_i1 x^_i - H_i2 z^_i),
    z^_i  = L_ii x^_i + sum_{j in C_i} L_ij x^_j,

so a node needs only its own model rows, its measurements and the estimates it hears. On sampled
data (y_k = mean of y over [t_k, t_k + dt], see :func:`jaxest.network.simulate_network`) one step
is an Euler step of length dt with the neighbours' estimates exchanged once per step; the error of
the discretisation is O(dt) (the study computes it exactly).
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, PartitionSpec
from jaxtyping import Array, Float, Int

from jaxest._checks import check_complete, check_precision
from jaxest._estimator import AbstractEstimator, AbstractResult
from jaxest._priors import Gaussian
from jaxest._status import finite_status
from jaxest.linalg import working_precision_by_default
from jaxest.models import at_time, check_time_axis
from jaxest.network.structure import (
    CommunicationStructure,
    LargeScaleSystem,
    pick_piece,
    piece_index,
)


def node_rate(A, C, H1, H2, G, mean, coupling, y) -> Array:
    """x^_i' for a batch of nodes (leading axis): A x^ + C z^ + G (y - H1 x^ - H2 z^) (eq 9)."""
    innovation = y - jnp.einsum("iqn,in->iq", H1, mean) - jnp.einsum("iqh,ih->iq", H2, coupling)
    return (
        jnp.einsum("iab,ib->ia", A, mean)
        + jnp.einsum("iah,ih->ia", C, coupling)
        + jnp.einsum("iaq,iq->ia", G, innovation)
    )


class NetworkState(eqx.Module):
    mean: Float[Array, "N n"]  #: x^_i(t_k) of every node


class NetworkOutput(eqx.Module):
    mean: Float[Array, "N n"] | None  #: x^_i(t_k), before the step's measurements
    status: Int[Array, ""] | None


class NetworkResult(AbstractResult):
    """``mean[k, i]`` = x^_i(t_k), the estimate from the measurements before t_k; ``final_mean``
    is x^(t_T); ``status`` holds :class:`jaxest.Status` bits per step."""

    final_state: NetworkState
    mean: Float[Array, "T N n"] | None = None
    status: Int[Array, " T"] | None = None
    any_status: Int[Array, ""] | None = None
    saved: object = None

    @property
    def final_mean(self) -> Float[Array, "N n"]:
        return self.final_state.mean


class NetworkFilter(AbstractEstimator):
    """Eq 9 with designed gains: ``gains`` (N, n, q) constant, or (T, N, n, q) with gains[k] used
    on [t_k, t_k + dt] (e.g. :attr:`NetworkDesign.gains` on the sample grid).

    No missing (NaN) measurements: the gains are designed for every node measuring at every
    sample. ``run`` refuses NaN in concrete ``ys`` (``ValueError``); inside ``jit`` a NaN entry
    makes the estimate NaN from there on (``status``: NONFINITE)."""

    structure: CommunicationStructure
    gains: Float[Array, "*T N n q"]
    dt: float = eqx.field(static=True)
    t0: float = eqx.field(static=True, default=0.0)

    def gain(self, k):
        return at_time(self.gains, k, ndim=3)

    def init(self, model: LargeScaleSystem, prior: Gaussian) -> NetworkState:
        """x^_i(t0) = m_i(0) (eq 10); ``prior.mean`` has shape (N, n)."""
        return NetworkState(jnp.asarray(prior.mean))

    def check(self, model, ys, inputs, prior) -> None:
        if not isinstance(model, LargeScaleSystem):
            raise ValueError(f"model: expected a LargeScaleSystem, got {type(model).__name__}")
        if not isinstance(prior, Gaussian):
            raise ValueError(f"prior: expected jaxest.Gaussian(mean, cov), got {type(prior)}")
        N, n, q = model.num_nodes, model.state_dim, model.obs_dim
        if np.shape(prior.mean) != (N, n):
            raise ValueError(f"prior.mean: expected shape ({N}, {n}), got {np.shape(prior.mean)}")
        if np.ndim(ys) != 3 or np.shape(ys)[1:] != (N, q):
            raise ValueError(f"ys: expected shape (T, {N}, {q}), got {np.shape(ys)}")
        if self.structure.num_nodes != N:
            raise ValueError(f"structure: has {self.structure.num_nodes} nodes, the model {N}")
        if np.shape(self.gains)[-3:] != (N, n, q) or np.ndim(self.gains) not in (3, 4):
            raise ValueError(
                f"gains: expected shape ({N}, {n}, {q}) or (T, {N}, {n}, {q}), got "
                f"{np.shape(self.gains)}"
            )
        if not self.dt > 0:
            raise ValueError(f"dt: must be positive (the sample interval), got {self.dt}")
        check_complete(ys, "the gains are designed for every node measuring at every sample")
        check_precision(model, ys, prior.mean, name="prior.mean", gains=self.gains)

    def check_steps(self, model, first: int, count: int) -> None:
        check_time_axis("gains", self.gains, first, count, ndim=3)

    def step(self, model: LargeScaleSystem, state: NetworkState, k, y_k, u_k=None, key=None):
        t = self.t0 + k * self.dt
        sys = model.at(t)
        hears = self.structure.at(t).hears
        used = (hears | jnp.eye(hears.shape[-1], dtype=bool)).astype(state.mean.dtype)
        coupling = jnp.einsum("ij,ijhn,jn->ih", used, sys.L, state.mean)
        rate = node_rate(sys.A, sys.C, sys.H1, sys.H2, self.gain(k), state.mean, coupling, y_k)
        mean = state.mean + self.dt * rate
        return NetworkState(mean), NetworkOutput(state.mean, finite_status(mean))

    def result(self, outputs: NetworkOutput, final_state: NetworkState) -> NetworkResult:
        return NetworkResult(final_state=final_state, mean=outputs.mean, status=outputs.status)


def _node_spec(ndim: int, node_axis_from_end: int) -> PartitionSpec:
    axes = [None] * ndim
    axes[ndim - node_axis_from_end] = "node"
    return PartitionSpec(*axes)


def heard_offsets(structure: CommunicationStructure) -> list[int]:
    """The offsets d (mod N) such that some node i hears node i + d, over every piece."""
    hears = np.asarray(structure.hears, dtype=bool).reshape(
        -1, structure.num_nodes, structure.num_nodes
    )
    N = structure.num_nodes
    pairs = np.argwhere(hears & ~np.eye(N, dtype=bool))
    return sorted({int((j - i) % N) for _, i, j in pairs})


@working_precision_by_default
def run_sharded(
    filt: NetworkFilter,
    system: LargeScaleSystem,
    ys: Float[Array, "T N q"],
    prior: Gaussian,
    devices=None,
) -> NetworkResult:
    """Run ``filt`` with one node per device (``shard_map`` over a mesh axis "node").

    Each device holds its node's model rows, gains, measurements and estimate; the estimates a
    node hears arrive by ``ppermute``, one collective per offset d in :func:`heard_offsets` (so a
    chain structure exchanges with the two neighbouring devices only). Gives the same estimates
    as :func:`jaxest.run` on one device (up to rounding). The structure must be concrete.
    """
    filt.check(system, ys, None, prior)
    filt.check_steps(system, 0, np.shape(ys)[0])
    N = system.num_nodes
    devices = list(jax.devices()[:N]) if devices is None else list(devices)
    if len(devices) != N:
        raise ValueError(f"devices: need one device per node ({N}), got {len(devices)}")
    mesh = Mesh(np.asarray(devices), ("node",))
    offsets = heard_offsets(filt.structure)
    dt, t0 = filt.dt, filt.t0
    sys_times, struct_times = system.switch_times, filt.structure.switch_times

    def node_program(A, C, L, H1, H2, hears, gains, ys, mean0):
        i = jax.lax.axis_index("node")

        def body(carry, y):
            k, mean = carry  # mean (1, n): this node's estimate
            t = t0 + k * dt
            p = piece_index(sys_times, t)
            A_k, C_k, H1_k, H2_k = (pick_piece(M, 3, p) for M in (A, C, H1, H2))
            L_k = pick_piece(L, 4, p)[0]  # (N, h, n): this node's couplings L_ij
            hears_k = pick_piece(hears, 2, piece_index(struct_times, t))[0]
            coupling = L_k[i] @ mean[0]
            for d in offsets:  # receive x^_{i+d} from the device at offset d
                other = jax.lax.ppermute(mean, "node", perm=[(j, (j - d) % N) for j in range(N)])
                j = (i + d) % N
                coupling = coupling + hears_k[j].astype(mean.dtype) * (L_k[j] @ other[0])
            rate = node_rate(
                A_k, C_k, H1_k, H2_k, at_time(gains, k, ndim=3), mean, coupling[None], y
            )
            new = mean + dt * rate
            return (k + 1, new), (mean, finite_status(new)[None])

        (_, final), (means, status) = jax.lax.scan(body, (jnp.zeros((), jnp.int32), mean0), ys)
        return means, status, final

    args = (
        system.A,
        system.C,
        system.L,
        system.H1,
        system.H2,
        filt.structure.hears,
        filt.gains,
        ys,
        prior.mean,
    )
    from_end = (3, 3, 4, 3, 3, 2, 3, 2, 2)
    in_specs = tuple(_node_spec(jnp.ndim(a), e) for a, e in zip(args, from_end, strict=True))
    sharded = jax.shard_map(
        node_program,
        mesh=mesh,
        in_specs=in_specs,
        out_specs=(PartitionSpec(None, "node"), PartitionSpec(None, "node"), PartitionSpec("node")),
    )
    means, status, final = jax.jit(sharded)(*args)
    status = functools.reduce(jnp.bitwise_or, [status[:, i] for i in range(N)])  # flags of any node
    any_status = jax.lax.reduce(status, jnp.int32(0), jax.lax.bitwise_or, (0,))
    return NetworkResult(
        final_state=NetworkState(final), mean=means, status=status, any_status=any_status
    )
