"""Speed of Zhang's adaptive observer: simulated seconds per wall-clock second, one run and under
``vmap`` over many scenarios, by ``jax.vmap`` and by ``jaxest.vmap_minor`` (recorded closed-loop
data, the observer alone, float64).

    PYTHONPATH=. python benchmarks/adaptive.py [--batch 1000] [--seconds 20] [--json PATH]
"""

from __future__ import annotations

import argparse
import platform

import equinox as eqx
import jax
import jax.numpy as jnp

from jaxest.report import best_of, timed_call


def _timed(fn, *args, repeats: int = 3) -> float:
    timed_call(lambda: fn(*args))  # compile
    return best_of(lambda: fn(*args), repeats)[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--batch", type=int, default=1000, help="scenarios under vmap (default 1000)"
    )
    parser.add_argument("--seconds", type=float, default=20.0, help="simulated time per run")
    parser.add_argument("--json", default=None, help="also write the JSON here")
    args = parser.parse_args()
    jax.config.update("jax_enable_x64", True)

    from jaxest import run, vmap_minor
    from jaxest.observers.adaptive import DiscreteAdaptiveObserver, ObserverPrior
    from jaxest.report import device_name, emit_json
    from jaxest.studies.adaptive import (
        DT,
        fly,
        hand_observer,
        make_plant,
        prior_for,
        random_scenarios,
    )

    results = {"device": device_name(), "machine": platform.machine(), "dt": DT}
    for name in ("charlie", "b747"):
        plant = make_plant(name)
        observer = hand_observer(plant)
        prior = prior_for(observer, plant)
        scenarios = random_scenarios(name, plant, jax.random.PRNGKey(0), args.batch)
        data = eqx.filter_jit(jax.vmap(lambda s: fly(observer, plant, name, s, args.seconds)))(
            scenarios
        )
        ys, us = data.observations, data.inputs
        steps = ys.shape[1]

        dmodel = plant.model.discretize(DT)
        n, m, p = plant.model.A.shape[0], plant.model.C.shape[0], plant.theta.shape[0]
        dobs = DiscreteAdaptiveObserver(Q=1e-4 * jnp.eye(n), R=1e-2 * jnp.eye(m), forgetting=0.99)
        dprior = ObserverPrior(jnp.zeros(n), jnp.ones(p), jnp.eye(n), jnp.eye(p))

        def one_run(y, u):
            return run(observer, plant.model, y, inputs=u, prior=prior).theta

        def one_discrete_run(y, u):
            return run(dobs, dmodel, y, inputs=u, prior=dprior).theta

        # one run; the runs under jax.vmap; the runs on the minor axis of every array
        continuous, batched, minor = (
            eqx.filter_jit(one_run), eqx.filter_jit(jax.vmap(one_run)), vmap_minor(one_run)
        )  # fmt: skip
        discrete, dbatched, dminor = (
            eqx.filter_jit(one_discrete_run),
            eqx.filter_jit(jax.vmap(one_discrete_run)),
            vmap_minor(one_discrete_run),
        )

        single = _timed(continuous, ys[0], us[0])
        many = _timed(batched, ys, us, repeats=1)
        many_minor = _timed(minor, ys, us, repeats=1)
        dsingle = _timed(discrete, ys[0], us[0])
        dmany = _timed(dbatched, ys, us, repeats=1)
        dmany_minor = _timed(dminor, ys, us, repeats=1)
        simulated = steps * DT
        results[name] = {
            "steps": steps,
            "substeps": observer.substeps,
            "continuous_single_sim_s_per_wall_s": simulated / single,
            "continuous_vmap_sim_s_per_wall_s": args.batch * simulated / many,
            "continuous_vmap_minor_sim_s_per_wall_s": args.batch * simulated / many_minor,
            "continuous_vmap_batch": args.batch,
            "discrete_single_sim_s_per_wall_s": simulated / dsingle,
            "discrete_vmap_sim_s_per_wall_s": args.batch * simulated / dmany,
            "discrete_vmap_minor_sim_s_per_wall_s": args.batch * simulated / dmany_minor,
        }
    emit_json(results, args.json)


if __name__ == "__main__":
    main()
