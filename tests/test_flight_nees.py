"""The model variants of ``benchmarks/flight_nees.py`` (issue 16): rows of f and h replaced by their
first-order expansion about a reference state carried in the input, checked against Jacobians
computed here with ``jax.jacfwd``."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxest.studies import svd_ekf
from jaxest.systems import flight_sim as sim
from jaxest.systems.flight import N_STATE
from tests import benchmark_scripts

flight_nees = benchmark_scripts.load("flight_nees")


@pytest.fixture(scope="module")
def setting():
    model = svd_ekf.model_for(10, jnp.float64)
    truth = sim.true_flight("aileron", 10, 2.0)
    batch = svd_ekf.simulated_batch(truth, 1, jax.random.key(3), jnp.float64)
    ys, inputs, mean0, states = (a[0] for a in batch)
    k = 7
    ref = states[k]
    x = mean0 + 0.3 * jnp.sqrt(jnp.diagonal(svd_ekf.prior_cov(jnp.float64)))
    return model, inputs[k], ref, x


def test_linearised_rows_are_the_first_order_expansion_and_the_rest_is_exact(setting):
    model, u, ref, x = setting
    h = model.observation_fn

    @jax.jit  # one program, where op-by-op evaluation compiles each operation
    def evaluate(x, u, ref):
        u_ref = jnp.concatenate([u, ref])
        expansion = h(ref, u) + jax.jacfwd(lambda z: h(z, u))(ref) @ (x - ref)
        all_rows = flight_nees.AboutReference(h)(x, u_ref)
        return expansion, all_rows, flight_nees.AboutReference(h, (1,))(x, u_ref), h(x, u)

    expansion, all_rows, beta_only, exact = evaluate(x, u, ref)
    np.testing.assert_allclose(all_rows, expansion, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(beta_only[1], expansion[1], rtol=1e-12, atol=1e-12)
    keep = np.array([0, 2, 3, 4, 5])
    np.testing.assert_allclose(beta_only[keep], exact[keep], rtol=1e-12, atol=1e-12)
    assert not np.allclose(beta_only[1], exact[1])  # x is far enough from ref to tell them apart


def test_variants_linearise_f_with_G_at_the_reference(setting):
    model, u, ref, x = setting
    linear = flight_nees.variant(model, True, None)
    exact = flight_nees.variant(model, False, ())
    f, h, G = model.transition_fn, model.observation_fn, model.noise_gain

    @jax.jit  # one program, where op-by-op evaluation compiles each operation
    def evaluate(x, u, ref):
        u_ref = jnp.concatenate([u, ref])
        expansion = f(ref, u) + jax.jacfwd(lambda z: f(z, u))(ref) @ (x - ref)
        return [
            (linear.f(x, u_ref), expansion),
            (exact.f(x, u_ref), f(x, u)),
            (exact.h(x, u_ref), h(x, u)),
            (linear.noise_gain(x, u_ref), G(ref, u)),
            (exact.noise_gain(x, u_ref), G(x, u)),
        ]

    pairs = evaluate(x, u, ref)
    for (got, want), rtol, atol in zip(
        pairs, [1e-12] + [1e-14] * 4, [1e-12] + [0] * 4, strict=True
    ):
        np.testing.assert_allclose(got, want, rtol=rtol, atol=atol)
    assert ref.shape == (N_STATE,)  # the inputs augmented with the reference state
