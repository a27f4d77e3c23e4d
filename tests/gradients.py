"""Shared gradient checks for the nonlinear filters' tests."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import jaxest as je


def loglik_of_R_scale(filt, model, prior, ys):
    """scale -> log p(y) of ``filt`` with R replaced by scale * R."""

    def loss(scale):
        scaled = eqx.tree_at(lambda m: m.R, model, scale * model.R)
        return je.run(filt, scaled, ys, prior=prior).loglik

    return loss


def check_grad_float64_and_float32(filt, problem, h=1e-5):
    """d loglik / d (R scale) equals the central finite difference in float64 (rtol 1e-6); in
    float32 the jitted, vmapped value and gradient follow the float64 ones. ``problem(dtype)``
    returns (model, prior, ys)."""
    value_and_grad = jax.jit(jax.value_and_grad(loglik_of_R_scale(filt, *problem(jnp.float64))))
    fd = (value_and_grad(1.0 + h)[0] - value_and_grad(1.0 - h)[0]) / (2 * h)
    np.testing.assert_allclose(value_and_grad(1.0)[1], fd, rtol=1e-6)

    loss32 = loglik_of_R_scale(filt, *problem(jnp.float32))
    scales = jnp.array([0.5, 1.0, 2.0], jnp.float32)
    values, grads = jax.jit(jax.vmap(jax.value_and_grad(loss32)))(scales)
    assert values.dtype == grads.dtype == jnp.float32
    for scale, value, grad in zip(scales, values, grads, strict=True):
        value64, grad64 = value_and_grad(float(scale))
        np.testing.assert_allclose(value, value64, rtol=1e-4)
        np.testing.assert_allclose(grad, grad64, rtol=1e-2, atol=1e-2)
