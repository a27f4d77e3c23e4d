"""The set-membership filter's guarantee on random nonlinear systems, checked by simulation.

Each system has n in {2, 3} states and m in {1, 2, 3} measurements:
x_{k+1} = A x + a * g(x) + w and y = C x + c * g'(x) + v. Here A is random and stable, and
C is random. Each g_i is a random one of seventeen terms of one other state: smooth (sin,
tanh, 0.3 v^2, cos v - 1, 0.1 v^3, atan, exp(-v^2), sqrt(1 + v^2) - 1, and
logsumexp([v, -v]), which JAX writes with a ``stop_gradient``), a bearing atan2(v,
-1 + 0.3 cos v) with its branch cut at v = 0, a step (v > 0.3), a kink written as the
largest entry of an array, max([v, -v / 2]) (``jnp.max``, whose derivative JAX divides by the
number of tied entries), the smaller of v and 0.2 - v written as ``jnp.sort``'s first entry,
a running maximum (``lax.cummax`` of [0.1 v, v], a kink at 0), a branch
(``lax.cond(v > 0.3, sin, v / 2)``, a jump at 0.3), a quantiser (floor(4 v) / 4, a step at
every quarter) or an angle wrapped into [-pi, pi) (``jnp.mod(4 v + pi, 2 pi) - pi``, a jump
at every odd multiple of pi / 4). The noise is uniform in its
box, and half of the runs draw it at the box's corners. The filter runs with the automatic
remainder bounds (:func:`jaxest.setmembership.interval.remainder_bound`), its runs under one
``jit(vmap)``.

Per system, over every run and step:
- ``bounded``: sets that are not UNBOUNDED;
- ``outside``: bounded sets that do not contain the simulated state. The guarantee says 0.
- ``empty``: steps flagged EMPTY_SET. No sensor is faulty, so every one is a false alarm.
- ``nonfinite``: steps flagged NONFINITE (a remainder bound is NaN: a jump in the box).

    python benchmarks/smf_guarantee.py [--seed 0] [--systems 8] [--runs 100] [--steps 60]
        [--json out.json]
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

import jaxest as je  # noqa: E402
from jaxest.report import emit_json  # noqa: E402
from jaxest.setmembership import (  # noqa: E402
    BoundedNoiseModel,
    Ellipsoid,
    SetMembershipFilter,
    SetStatus,
)

#: the nonlinear terms, by name: smooth ones, a bearing across its branch cut, a step, kinks, a
#: branch, a quantiser, an angle wrap
TERMS = {
    "sin": jnp.sin,
    "tanh": jnp.tanh,
    "square": lambda v: 0.3 * v**2,
    "cos": lambda v: jnp.cos(v) - 1,
    "cube": lambda v: 0.1 * v**3,
    "atan": jnp.arctan,
    "gauss": lambda v: jnp.exp(-(v**2)),
    "hyperbola": lambda v: jnp.sqrt(1 + v**2) - 1,
    "bearing": lambda v: jnp.arctan2(v, -1.0 + 0.3 * jnp.cos(v)),
    "step": lambda v: (v > 0.3).astype(v.dtype),
    "vee": lambda v: jnp.max(jnp.stack([v, -0.5 * v])),
    "branch": lambda v: jax.lax.cond(v > 0.3, jnp.sin, lambda u: 0.5 * u, v),
    "quantised": lambda v: 0.25 * jnp.floor(4 * v),
    "logsumexp": lambda v: jax.nn.logsumexp(jnp.stack([v, -v])) - jnp.log(2.0),
    "sorted": lambda v: jnp.sort(jnp.stack([v, 0.2 - v]))[0],
    "running_max": lambda v: jax.lax.cummax(jnp.stack([0.1 * v, v]))[-1],
    "wrapped": lambda v: jnp.mod(4 * v + jnp.pi, 2 * jnp.pi) - jnp.pi,
}


def random_system(rng):
    """(model, prior, description) of one random system."""
    n, m = int(rng.integers(2, 4)), int(rng.integers(1, 4))
    A = np.eye(n) + 0.1 * rng.normal(size=(n, n))
    A *= 0.95 / max(1.0, np.max(np.abs(np.linalg.eigvals(A))))
    C = rng.normal(size=(m, n))
    names = list(TERMS)
    f_terms = [names[i] for i in rng.integers(len(names), size=n)]
    h_terms = [names[i] for i in rng.integers(len(names), size=m)]

    def with_terms(M, terms, gains):
        M, gains = jnp.asarray(M), jnp.asarray(gains)

        def fn(x):
            g = [TERMS[name](x[(row + 1) % x.shape[0]]) for row, name in enumerate(terms)]
            return M @ x + gains * jnp.stack(g)

        return fn

    f = with_terms(A, f_terms, 0.05 * rng.normal(size=n))
    h = with_terms(C, h_terms, 0.3 * rng.normal(size=m))
    process_bound = 10 ** rng.uniform(-3, -1.5, size=n)
    measurement_bound = 10 ** rng.uniform(-2.5, -1, size=m)
    model = BoundedNoiseModel(f, h, jnp.asarray(process_bound), jnp.asarray(measurement_bound))
    prior = Ellipsoid(jnp.asarray(0.5 * rng.normal(size=n)), 0.05 * jnp.eye(n))
    return model, prior, {"n": n, "m": m, "f_terms": f_terms, "h_terms": h_terms}


def simulate(model, prior, steps, key):
    """States and measurements of one run: x_0 uniform in the prior, the noise uniform in its
    boxes, or at their corners (half the runs)."""
    n, m = model.state_dim, model.obs_dim
    start, k_w, k_v, k_corner = jax.random.split(key, 4)
    direction = jax.random.normal(start, (n,))
    radius = jax.random.uniform(jax.random.fold_in(start, 1)) ** (1 / n)
    unit_ball = radius * direction / jnp.linalg.norm(direction)
    x0 = prior.center + jnp.linalg.cholesky(prior.shape) @ unit_ball
    at_corners = jax.random.bernoulli(k_corner)

    def draw(key, bound, shape):
        corner = jax.random.rademacher(key, shape, bound.dtype) * bound
        inside = jax.random.uniform(jax.random.fold_in(key, 1), shape, minval=-bound, maxval=bound)
        return jnp.where(at_corners, corner, inside)

    ws = draw(k_w, model.process_bound, (steps, n))
    vs = draw(k_v, model.measurement_bound, (steps, m))

    def step(x, noise):
        w, v = noise
        return model.transition(x) + w, (x, model.observation(x) + v)

    _, (states, ys) = jax.lax.scan(step, x0, (ws, vs))
    return states, ys


def check(model, prior, runs: int, steps: int, key) -> dict:
    """The counts of the module docstring for ``runs`` runs of ``steps`` steps."""
    keys = jax.random.split(key, runs)
    states, ys = jax.vmap(lambda k: simulate(model, prior, steps, k))(keys)
    filtered = jax.jit(jax.vmap(lambda y: je.run(SetMembershipFilter(), model, y, prior=prior)))
    result = filtered(ys)
    inside = np.asarray(jax.vmap(lambda r, x: r.contains(x))(result, states))
    bounded = ~np.asarray(result.unbounded)
    status = np.asarray(result.status)
    return {
        "bounded": int(bounded.sum()),
        "outside": int((bounded & ~inside).sum()),
        "empty": int(((status & SetStatus.EMPTY_SET) != 0).sum()),
        "nonfinite": int(((status & SetStatus.NONFINITE) != 0).sum()),
    }


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--systems", type=int, default=8)
    parser.add_argument("--runs", type=int, default=100)
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--json", help="write the results here as well as to stdout")
    args = parser.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    rows = []
    for index in range(args.systems):
        model, prior, described = random_system(rng)
        key = jax.random.key(1000 * args.seed + index)
        rows.append(described | check(model, prior, args.runs, args.steps, key))
        jax.clear_caches()
    counts = ("bounded", "outside", "empty", "nonfinite")
    totals = {name: sum(row[name] for row in rows) for name in counts}
    emit_json(
        {"seed": args.seed, "runs": args.runs, "steps": args.steps, "systems": rows,
         "totals": totals},
        args.json,
    )  # fmt: skip


if __name__ == "__main__":
    main()
