"""The network filter with one node per device (shard_map + ppermute) on 4 forced CPU devices.

Runs in a subprocess because the device count is fixed when JAX starts.
"""

import subprocess
import sys
import textwrap

from tests.processes import ROOT, cpu_devices_env

SCRIPT = textwrap.dedent(
    """
    import jax, jax.numpy as jnp, numpy as np
    jax.config.update("jax_enable_x64", True)
    from jaxest.network import CommunicationStructure, NetworkFilter, design, run_sharded, simulate_network
    from jaxest.network.filter import heard_offsets
    from jaxest import Gaussian, run
    from jaxest.systems.chain import initial_prior, mass_chain

    assert jax.device_count() == 4
    N, T, dt = 4, 200, 0.01
    system = mass_chain(N)
    mean0, cov0 = initial_prior(N)
    mean0 = mean0 + jnp.arange(2 * N, dtype=mean0.dtype).reshape(N, 2) / 10
    left_then_full = CommunicationStructure(
        jnp.stack([CommunicationStructure.from_offsets(N, [-1]).hears,
                   CommunicationStructure.full(N).hears]), switch_times=(0.0, 1.0))
    structures = {
        "chain": CommunicationStructure.chain(N),
        "left_then_full": left_then_full,
    }
    assert heard_offsets(structures["chain"]) == [1, 3]  # i + 1 and i - 1 (mod 4) only
    _, ys = simulate_network(system, mean0, cov0, dt, T, jax.random.key(0))
    for name, structure in structures.items():
        des = design(system, structure, cov0, jnp.arange(T) * dt)
        filt = NetworkFilter(structure, des.gains, dt)
        single = run(filt, system, ys, prior=Gaussian(mean0, cov0))
        sharded = run_sharded(filt, system, ys, Gaussian(mean0, cov0))
        assert sharded.mean.sharding.device_set == set(jax.devices()), name
        np.testing.assert_allclose(np.asarray(sharded.mean), np.asarray(single.mean), rtol=1e-12, atol=1e-13)
        np.testing.assert_allclose(np.asarray(sharded.final_mean), np.asarray(single.final_mean), rtol=1e-12, atol=1e-13)
        assert np.all(np.asarray(sharded.status) == 0) and sharded.status.shape == (T,)
        # estimates differ between structures: the communication is really used
        print(name, float(jnp.abs(sharded.final_mean).sum()))
    try:  # a gain schedule shorter than ys: gains[k] past its end would be the last one
        run_sharded(filt, system, jnp.concatenate([ys, ys[:2]]), Gaussian(mean0, cov0))
    except ValueError as error:
        assert str(error).startswith("gains: time-varying"), error
    else:
        raise AssertionError("run_sharded ran past the gain schedule")
    print("SHARDED-OK")
    """
)


def test_sharded_run_matches_single_device():
    proc = subprocess.run(
        [sys.executable, "-c", SCRIPT],
        env=cpu_devices_env(4),
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "SHARDED-OK" in proc.stdout
    finals = [float(line.split()[1]) for line in proc.stdout.splitlines() if len(line.split()) == 2]
    assert len(set(finals)) == 2, proc.stdout
