"""The Monte Carlo engine: reproducible from one key whatever the chunking, and identical on one
and on four (forced host) devices."""

import json
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxest as je
from jaxest.filters import SVDEKF
from jaxest.montecarlo import monte_carlo
from tests.processes import cpu_devices_env

STUDY = """
import json, sys
import jax, jax.numpy as jnp
jax.config.update("jax_enable_x64", True)
import jaxest as je
from jaxest.filters import SVDEKF
from jaxest.montecarlo import monte_carlo

model = je.LinearGaussian(jnp.asarray([[1.0, 0.1], [0.0, 0.9]]), jnp.asarray([[1.0, 0.0]]),
                          0.01 * jnp.eye(2), jnp.asarray([[0.2]]))
prior = je.Gaussian(jnp.zeros(2), jnp.eye(2))

def one_run(key):
    sim = je.simulate(model, prior, 50, key)
    res = je.run(SVDEKF(), model, sim.y, prior=prior)
    return {"loglik": res.loglik, "error": jnp.mean((res.mean - sim.states) ** 2)}

out = monte_carlo(one_run, jax.random.PRNGKey(42), 12, chunk_size=4)
jitted = jax.jit(lambda key: monte_carlo(one_run, key, 12, chunk_size=4))(jax.random.PRNGKey(42))
print(json.dumps({"devices": jax.device_count(), "loglik": out["loglik"].tolist(), "error": out["error"].tolist(),
                  "jit_loglik": jitted["loglik"].tolist()}))
"""


def run_study(devices: int) -> dict:
    done = subprocess.run(
        [sys.executable, "-c", STUDY],
        env=cpu_devices_env(devices),
        capture_output=True,
        text=True,
        timeout=600,
        check=True,
    )
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_same_results_on_one_and_four_devices():
    one, four = run_study(1), run_study(4)
    assert one["devices"] == 1 and four["devices"] == 4
    assert one["loglik"] == four["loglik"]
    assert one["error"] == four["error"]
    assert four["jit_loglik"] == four["loglik"]  # the keys sharded inside jit


def test_chunking_does_not_change_which_key_a_run_gets():
    model = je.LinearGaussian(jnp.eye(1) * 0.9, jnp.eye(1), jnp.eye(1) * 0.1, jnp.eye(1))
    prior = je.Gaussian(jnp.zeros(1), jnp.eye(1))
    sim = lambda key: je.simulate(model, prior, 30, key).y
    key = jax.random.PRNGKey(3)
    whole = monte_carlo(sim, key, 10, mesh=None)
    chunked = monte_carlo(sim, key, 10, chunk_size=3, mesh=None)
    np.testing.assert_array_equal(whole, chunked)
    # run 7 is the run of key split(key, 10)[7] (up to the last bit: vmap vs a single call)
    np.testing.assert_allclose(whole[7], sim(jax.random.split(key, 10)[7]), rtol=1e-13, atol=1e-15)
    lls = monte_carlo(
        lambda k: je.run(SVDEKF(), model, sim(k), prior=prior).loglik, key, 10, chunk_size=4
    )
    assert lls.shape == (10,) and np.all(np.isfinite(lls))


def test_runs_inside_jit_vmap_and_grad():
    """A study's mean log-likelihood as a function of log R and the key: jitted with the key
    traced, batched over keys, and differentiated inside jit (against central differences)."""
    model = je.LinearGaussian(jnp.eye(2) * 0.9, jnp.ones((1, 2)), jnp.eye(2), jnp.eye(1))
    prior = je.Gaussian(jnp.zeros(2), jnp.eye(2))

    def loglik(log_r, key):
        ys = je.simulate(model, prior, 20, key).y
        tuned = je.LinearGaussian(model.F, model.H, model.Q, jnp.exp(log_r) * jnp.eye(1))
        return je.run(je.KalmanFilter(), tuned, ys, prior=prior).loglik

    def study(log_r, key):
        return jnp.mean(monte_carlo(lambda k: loglik(log_r, k), key, 7, chunk_size=3))

    key = jax.random.key(0)
    eager = study(0.1, key)
    np.testing.assert_allclose(jax.jit(study)(0.1, key), eager, rtol=1e-13)
    keys = jax.random.split(key, 2)
    np.testing.assert_allclose(
        jax.vmap(study, (None, 0))(0.1, keys), [study(0.1, k) for k in keys], rtol=1e-13
    )
    central = (study(0.1 + 1e-5, key) - study(0.1 - 1e-5, key)) / 2e-5
    np.testing.assert_allclose(jax.jit(jax.grad(study))(0.1, key), central, rtol=1e-7)


def test_minor_batching_gives_the_same_runs():
    """batching="minor" (vmap_minor): the runs of jax.vmap to rounding, whole and chunked,
    called eagerly and inside jit (without its compiler options there)."""
    model = je.LinearGaussian(jnp.eye(3) * 0.9, jnp.ones((2, 3)), jnp.eye(3), jnp.eye(2))
    prior = je.Gaussian(jnp.zeros(3), jnp.eye(3))

    def one_run(key):
        ys = je.simulate(model, prior, 20, key).y
        result = je.run(je.KalmanFilter(), model, ys, prior=prior)
        return result.loglik, result.mean

    key = jax.random.key(4)
    expected = monte_carlo(one_run, key, 6, mesh=None)
    for chunk_size in (None, 4):
        minor = monte_carlo(one_run, key, 6, chunk_size=chunk_size, mesh=None, batching="minor")
        for a, b in zip(minor, expected, strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)
    study = lambda batching: jax.jit(
        lambda k: monte_carlo(one_run, k, 6, mesh=None, batching=batching)
    )
    np.testing.assert_allclose(study("minor")(key)[0], expected[0], rtol=1e-12)
    # the filter's 3 x 3 covariances of the 6 runs, runs first or last
    assert "6x3x3xf64" in study("vmap").lower(key).as_text()
    assert "3x3x6xf64" in study("minor").lower(key).as_text()


def test_rejects_bad_arguments():
    with pytest.raises(ValueError, match="batching"):
        monte_carlo(lambda k: k, jax.random.PRNGKey(0), 3, batching="last")
    with pytest.raises(ValueError, match="num_runs"):
        monte_carlo(lambda k: k, jax.random.PRNGKey(0), 0)
    with pytest.raises(ValueError, match="chunk_size"):
        monte_carlo(lambda k: k, jax.random.PRNGKey(0), 3, chunk_size=0)
    with pytest.raises(ValueError, match="^run_fn: expected a function, got int"):  # a TypeError
        monte_carlo(3, jax.random.PRNGKey(0), 3)
    # JAX's TypeErrors, an AttributeError and a rejected NumPy integer named nothing before
    draw = lambda k: jax.random.normal(k)
    for key, message in [
        (0, "^key: expected a PRNG key .*got 0"),
        (jnp.zeros(2, jnp.int32), r"^key: expected a PRNG key .*int32 array of shape \(2,\)"),
        (jax.random.split(jax.random.key(0)), r"^key: expected one PRNG key, got a batch"),
    ]:
        with pytest.raises(ValueError, match=message):
            monte_carlo(draw, key, 3)
    with pytest.raises(ValueError, match="^mesh: expected a 1-D jax.sharding.Mesh"):
        monte_carlo(draw, jax.random.key(0), 3, mesh="all")
    assert monte_carlo(draw, jax.random.key(0), np.int64(3), chunk_size=np.int64(2)).shape == (3,)


def test_keys_of_any_prng_implementation():
    """A typed rbg key raised a TypeError (its data was rewrapped as the default threefry's).
    rbg's draws under vmap differ from unbatched ones, so chunks of one run match a loop."""
    draw = lambda k: jax.random.normal(k, (2,))
    key = jax.random.key(0, impl="rbg")
    loop = np.stack([draw(k) for k in jax.random.split(key, 3)])
    np.testing.assert_array_equal(monte_carlo(draw, key, 3, chunk_size=1, mesh=None), loop)
