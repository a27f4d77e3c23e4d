"""Matrix products in the working precision by default (``jaxest.linalg``'s module docstring).

JAX's default precision for float32 products is TF32 on recent NVIDIA GPUs. Every estimator entry
point traces its products at "highest" unless the caller chose a precision. The checks read the
lowered program, so they run on any platform: with no precision chosen every product is HIGHEST
(while a plain product outside is DEFAULT, so the check can fail), and a caller's TF32 reaches
jaxest's products.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxest as je
from jaxest.filters import KalmanFilter, ParallelKalmanFilter, SquareRootKF
from tests.lowering import dot_precisions
from tests.reference import random_system

#: 10 states: a 10 x 10 x 10 product is above linalg.SMALL_MATMUL, so real dot products are traced
N, M, T = 10, 3, 4


def _problem():
    F, H, Q, R = (
        jnp.asarray(a, jnp.float32) for a in random_system(np.random.default_rng(0), N, M)
    )
    prior = je.Gaussian(jnp.zeros(N, jnp.float32), jnp.eye(N, dtype=jnp.float32))
    return je.LinearGaussian(F, H, Q, R), prior


@functools.cache
def _entry_points():
    model, prior = _problem()
    loglik = lambda est, mdl, ys: je.run(est, mdl, ys, prior=prior).loglik  # noqa: E731
    scaled = lambda q: je.LinearGaussian(model.F, model.H, q * model.Q, model.R)  # noqa: E731
    return {
        "run KalmanFilter": lambda ys: loglik(KalmanFilter(), model, ys),
        "run SquareRootKF": lambda ys: loglik(SquareRootKF(), model, ys),
        "run ParallelKalmanFilter": lambda ys: loglik(ParallelKalmanFilter(), model, ys),
        "grad through run": lambda ys: jax.grad(lambda q: loglik(KalmanFilter(), scaled(q), ys))(
            jnp.float32(1.0)
        ),
        "rts_smooth": lambda ys: (
            je.rts_smooth(model, je.run(KalmanFilter(), model, ys, prior=prior)).mean
        ),
        "fit_em": lambda ys: je.fit_em(model, ys, prior=prior, num_iters=1).model.F,
        "solve_filter_dare and its gradient": lambda ys: jax.grad(
            lambda Q: je.solve_filter_dare(model.F, model.H, Q, model.R).X[0, 0]
        )(model.Q + ys[0, 0]),
        "simulate": lambda ys: je.simulate(model, prior.mean, T, jax.random.key(0)).states,
    }


@pytest.mark.parametrize("name", list(_entry_points()))
def test_products_are_full_precision_unless_the_caller_chose(name):
    fn = _entry_points()[name]
    ys = jnp.ones((T, M), jnp.float32)
    with jax.default_matmul_precision(None):  # nothing chosen (dynamax's import sets float32)
        precisions = dot_precisions(fn, ys)
        assert precisions and set(precisions) == {"HIGHEST"}
        assert dot_precisions(lambda P: P @ P, jnp.eye(N, dtype=jnp.float32)) == ["DEFAULT"]
    # the caller's choice is kept ("in", not "==": JAX's own linear solves' derivatives ask for
    # HIGHEST whatever the setting)
    with jax.default_matmul_precision("tensorfloat32"):
        assert "HIGH" in dot_precisions(fn, ys)
