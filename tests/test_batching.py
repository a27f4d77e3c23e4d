"""``vmap_minor`` against ``jax.vmap``: the estimators (forward and gradient, float32 and float64),
each primitive rule on its own, the primitives that fall back, ``in_axes`` and bad input."""

import jax
import jax.numpy as jnp
import jaxlib
import numpy as np
import pytest
from jax import lax

import jaxest as je
from jaxest import xla_flags
from jaxest.batching import vmap_minor, vmap_minor_fallbacks
from jaxest.systems import duffing
from tests.registry import GAUSSIAN_FILTER_IDS, GAUSSIAN_FILTERS

RUNS, STEPS = 5, 12


def linear_case(dtype):
    """A 3-state / 2-sensor model whose Q is scaled per run, and each run's measurements."""
    rng = np.random.default_rng(0)
    F = 0.9 * np.linalg.qr(rng.normal(size=(3, 3)))[0]
    H = rng.normal(size=(2, 3))
    model = je.LinearGaussian(*(jnp.asarray(a, dtype) for a in (F, H, np.eye(3), 0.5 * np.eye(2))))
    prior = je.Gaussian(jnp.zeros(3, dtype), jnp.eye(3, dtype=dtype))
    ys = jnp.asarray(rng.normal(size=(RUNS, STEPS, 2)), dtype)
    ys = ys.at[0, 3, 1].set(jnp.nan)  # a missing entry in one run
    scales = jnp.asarray(np.linspace(0.5, 2.0, RUNS), dtype)
    return model, prior, ys, scales


def close(a, b, dtype):
    tolerance = 1e-10 if dtype == jnp.float64 else 2e-4
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=tolerance, atol=tolerance)


@pytest.mark.parametrize(
    ("estimator", "dtype"),
    [(je.KalmanFilter(), jnp.float32), (je.UKF(), jnp.float64), (je.UKF(), jnp.float32)],
    ids=["KalmanFilter-float32", "UKF-float64", "UKF-float32"],
)
def test_gaussian_filters_match_vmap(estimator, dtype):
    """The Kalman filter in float32 and the UKF (the registry's filters in float64: below)."""
    model, prior, ys, scales = linear_case(dtype)

    def one_run(scale, y):
        result = je.run(estimator, scaled_Q(model, scale), y, prior=prior)
        return result.loglik, result.mean, result.cov, result.status

    close(vmap_minor(one_run)(scales, ys), jax.vmap(one_run)(scales, ys), dtype)


@pytest.mark.parametrize("filter_type", GAUSSIAN_FILTERS, ids=GAUSSIAN_FILTER_IDS)
def test_every_gaussian_filter_matches_vmap(filter_type):
    model, prior, ys, scales = linear_case(jnp.float64)

    def one_run(scale, y):
        result = je.run(filter_type(), scaled_Q(model, scale), y, prior=prior)
        return result.loglik, result.mean, result.cov, result.status

    close(vmap_minor(one_run)(scales, ys), jax.vmap(one_run)(scales, ys), jnp.float64)


def scaled_Q(model, scale):
    """``model`` with its Q scaled by ``scale``."""
    return je.LinearGaussian(model.F, model.H, scale * model.Q, model.R)


def kalman_loglik(model, prior):
    """(Q scale, one run's measurements) -> the Kalman filter's log-likelihood."""
    return lambda scale, y: je.run(je.KalmanFilter(), scaled_Q(model, scale), y, prior=prior).loglik


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_value_and_grad_inside_matches_vmap(dtype):
    """Differentiated inside: the Kalman filter's closed-form gradient rule already applied."""
    model, prior, ys, scales = linear_case(dtype)
    loglik = kalman_loglik(model, prior)
    value_and_grad = jax.value_and_grad(loglik)
    close(vmap_minor(value_and_grad)(scales, ys), jax.vmap(value_and_grad)(scales, ys), dtype)


def test_a_gradient_taken_outside_keeps_the_custom_rules():
    """Taken outside, a function with custom derivative rules runs under jax.vmap: evaluating
    the rules by their primal code made the SVD filters' gradients NaN (the SVD's derivative,
    which their rules replace), relu's derivative at 0 one half and a custom_vjp's its primal's.
    Under jax.vmap and jax.jacfwd too."""
    model, prior, ys, scales = linear_case(jnp.float64)
    for estimator in (je.KalmanFilter(), je.SVDEKF()):
        loglik = lambda s, y, e=estimator: je.run(e, scaled_Q(model, s), y, prior=prior).loglik
        total = lambda batched, f=loglik: lambda s: jnp.sum(batched(f)(s, ys))
        expected = jax.grad(total(jax.vmap))(scales)
        assert np.all(np.isfinite(expected))
        close(jax.grad(total(vmap_minor))(scales), expected, jnp.float64)
        close(jax.jacfwd(total(vmap_minor))(scales), expected, jnp.float64)

    @jax.custom_vjp
    def hundredfold(x):
        return jnp.sin(x)

    hundredfold.defvjp(lambda x: (jnp.sin(x), None), lambda _, g: (100 * g,))
    for f in (jax.nn.relu, hundredfold):
        total = lambda batched, f=f: lambda x: jnp.sum(batched(f)(x))
        x = jnp.zeros(3)
        expected = jax.grad(total(jax.vmap))(x)
        close(jax.grad(total(vmap_minor))(x), expected, jnp.float64)
        batch = jax.vmap(jax.grad(total(vmap_minor)))(jnp.zeros((2, 3)))  # under jax.vmap
        close(batch, jnp.stack([expected] * 2), jnp.float64)


def test_contractions_keep_preferred_element_type_and_weak_types():
    """A dot_general with preferred_element_type multiplied in the inputs' dtype: int8 100 x 100
    summed over 4 gave 64 (overflowed) for 40 000. A weakly typed float batch times a float16
    array came out float64 where jax.vmap gives float16."""
    a = jnp.full((3, 4, 4), 100, jnp.int8)
    dot = lambda x: jnp.dot(x, x, preferred_element_type=jnp.int32)
    np.testing.assert_array_equal(vmap_minor(dot)(a), jax.vmap(dot)(a))
    assert int(vmap_minor(dot)(a)[0, 0, 0]) == 40_000
    weak = jnp.broadcast_to(jnp.asarray(1.5), (3,))  # a Python float's weak type
    half = lambda x: x * jnp.ones(2, jnp.float16)
    assert vmap_minor(half)(weak).dtype == jax.vmap(half)(weak).dtype == jnp.float16


def test_nonlinear_filter_under_jit_and_vmap():
    """The Duffing EKF inside a caller's jit, and vmap_minor itself under jax.vmap."""
    model, prior = duffing.model(), duffing.prior()
    gaussian = je.NonlinearGaussian(model.f, model.h, 1e-5 * jnp.eye(2), 1e-4 * jnp.eye(2))
    ys = jax.random.normal(jax.random.PRNGKey(1), (2, RUNS, STEPS, 2)) * 0.01
    first = je.Gaussian(prior.center, 0.01 * jnp.eye(2))

    def one_run(y):
        result = je.run(je.EKF(), gaussian, y, prior=first)
        return result.loglik, result.mean

    expected = jax.vmap(jax.vmap(one_run))(ys)
    close(jax.jit(vmap_minor(one_run))(ys[0]), jax.tree.map(lambda a: a[0], expected), jnp.float64)
    close(jax.vmap(vmap_minor(one_run))(ys), expected, jnp.float64)


def test_particle_filter_with_keys_matches_vmap():
    model, prior, ys, _ = linear_case(jnp.float64)
    ys = jnp.nan_to_num(ys)
    keys = jax.random.split(jax.random.PRNGKey(0), RUNS)
    one_run = lambda key, y: je.run(je.ParticleFilter(16), model, y, prior=prior, key=key).loglik
    close(vmap_minor(one_run)(keys, ys), jax.vmap(one_run)(keys, ys), jnp.float64)


def test_kalman_filter_runs_batch_minor_throughout():
    """Every primitive of the Kalman filter and its gradient has a batch-minor rule, and the
    covariances the program carries have the runs last."""
    model, prior, ys, scales = linear_case(jnp.float64)
    loglik = kalman_loglik(model, prior)
    assert vmap_minor_fallbacks(loglik, scales, ys) == {}
    assert vmap_minor_fallbacks(jax.value_and_grad(loglik), scales, ys) == {}
    program = jax.jit(vmap_minor(loglik)).lower(scales, ys).as_text()
    assert f"3x3x{RUNS}xf64" in program and f"{RUNS}x3x3xf64" not in program


def test_a_large_product_is_a_batched_dot():
    """Past ``SMALL_MATMUL`` multiply-adds a product falls back to XLA's dot (8 x 8 x 8 = 512
    is the last one written as a multiply and a sum)."""
    for n, expected in ((8, {}), (9, {"dot_general": 1})):
        a = jax.random.normal(jax.random.PRNGKey(n), (RUNS, n, n))
        square = lambda a: a @ a
        assert vmap_minor_fallbacks(square, a) == expected
        close(vmap_minor(square)(a), jax.vmap(square)(a), jnp.float64)


def test_a_primitive_without_rule_falls_back_and_is_reported():
    matrices = jax.random.normal(jax.random.PRNGKey(2), (RUNS, 3, 3))
    smallest_eigenvalue = lambda a: jnp.linalg.eigvalsh(a @ a.T)[0] + jnp.sum(a)
    assert "eigh" in vmap_minor_fallbacks(smallest_eigenvalue, matrices)
    close(
        vmap_minor(smallest_eigenvalue)(matrices),
        jax.vmap(smallest_eigenvalue)(matrices),
        jnp.float64,
    )


def structural(a, b, i):
    """A function that reaches each structural rule: broadcasts, reshapes, slices (static and
    dynamic), concatenation, stacking, padding, gathers, transposes, reductions and contractions
    in several arrangements."""
    m = a.reshape(2, 6)[:, 1:5].T  # (4, 2)
    v = jnp.concatenate([a[0], b])  # (3 + 2,)
    stacked = jnp.stack([a[0], a[1]])
    padded = jnp.pad(b, (1, 2))
    picked = jnp.diagonal(a[:3, :3])
    window = lax.dynamic_slice(v, (i,), (2,))
    updated = lax.dynamic_update_slice(a, jnp.ones((1, 3), a.dtype) * b[0], (i, jnp.int32(0)))
    contractions = (
        jnp.einsum("ij,jk->ik", a, a.T),  # matrix product
        a @ v[:3],  # matrix-vector
        v @ v,  # vector dot
        jnp.einsum("bij,bjk->bik", a.reshape(2, 2, 3), a.reshape(2, 3, 2)),  # with batch dims
    )
    reductions = (jnp.max(m, axis=0), jnp.cumsum(v), jnp.argmax(v), jnp.flip(v), jnp.prod(b))
    return m, v, stacked, padded, picked, window, updated, contractions, reductions


@pytest.mark.parametrize("in_axes", [0, (0, 0, None), (0, None, None)])
def test_structural_rules_match_vmap(in_axes):
    a = jax.random.normal(jax.random.PRNGKey(3), (RUNS, 4, 3))
    b = jax.random.normal(jax.random.PRNGKey(4), (RUNS, 2))
    i = jnp.ones(RUNS, jnp.int32)
    args = tuple(
        x if axis == 0 else x[0] for x, axis in zip((a, b, i), _axes(in_axes), strict=True)
    )
    expected = jax.vmap(structural, in_axes=in_axes)(*args)
    close(vmap_minor(structural, in_axes=in_axes)(*args), expected, jnp.float64)
    # an index per run makes the dynamic slice and update a gather and a scatter
    per_run_index = {"dynamic_slice": 1, "dynamic_update_slice": 1}
    expected_fallbacks = per_run_index if _axes(in_axes)[2] == 0 else {}
    assert vmap_minor_fallbacks(structural, *args, in_axes=in_axes) == expected_fallbacks


def _axes(in_axes):
    return (in_axes,) * 3 if not isinstance(in_axes, tuple) else in_axes


def branches(x, shared_index):
    per_run = lax.cond(x[0] > 0, lambda z: z * 2.0, lambda z: -z, x)
    shared = lax.switch(shared_index, [jnp.sin, jnp.cos, lambda z: z**2], x)
    constant_branch = lax.cond(shared_index > 0, lambda z: z, lambda z: jnp.zeros_like(z), x)
    return per_run, shared, constant_branch


def test_cond_with_batched_and_shared_index_matches_vmap():
    x = jax.random.normal(jax.random.PRNGKey(5), (RUNS, 3))
    assert vmap_minor_fallbacks(branches, x, jnp.asarray(1), in_axes=(0, None)) == {}
    for index in (0, 1, 2):
        args = (x, jnp.asarray(index))
        close(
            vmap_minor(branches, in_axes=(0, None))(*args),
            jax.vmap(branches, in_axes=(0, None))(*args),
            jnp.float64,
        )


def counted_scan(x):
    """A carry that starts shared and becomes batched, a counter that stays shared (and
    indexes the xs), and stacked outputs of both kinds."""

    def step(carry, t):
        total, count = carry
        total = total + x[count % 3] * t
        return (total, count + 1), (total, count)

    return lax.scan(step, (jnp.zeros(()), 0), jnp.arange(4.0))


def test_scan_carries_match_vmap():
    x = jax.random.normal(jax.random.PRNGKey(6), (RUNS, 3))
    close(vmap_minor(counted_scan)(x), jax.vmap(counted_scan)(x), jnp.float64)
    assert vmap_minor_fallbacks(counted_scan, x) == {}  # the counter's index stays shared


def test_pytree_arguments_and_shared_outputs():
    model, prior, ys, scales = linear_case(jnp.float64)
    one_run = lambda model, y: (
        je.run(je.KalmanFilter(), model, y, prior=prior).loglik,
        jnp.ones(2),
    )
    batched_models = jax.vmap(lambda s: scaled_Q(model, s))(scales)
    minor = vmap_minor(one_run)(batched_models, ys)
    close(minor, jax.vmap(one_run)(batched_models, ys), jnp.float64)
    assert minor[1].shape == (RUNS, 2)


@pytest.mark.parametrize(
    ("in_axes", "args", "message"),
    [
        (1, (jnp.ones((3, 2)),), "in_axes: each entry must be 0 or None"),
        ((0, 0), (jnp.ones(3),), "in_axes: 2 entries for 1 arguments"),
        (None, (jnp.ones(3),), "no argument is batched"),
        (0, (jnp.ones(3), jnp.ones(4)), "disagree on the batch size"),
        (0, (jnp.ones(()),), "a batched argument is a scalar"),
        (0, ("text",), "argument 0: a leaf of type str is not an array"),
        (({"a": 0},), ({"b": jnp.ones(3)},), "in_axes: entry 0 is not a pytree prefix"),
    ],
)
def test_bad_arguments_raise_before_tracing(in_axes, args, message):
    with pytest.raises(ValueError, match=message):
        vmap_minor(lambda *a: a, in_axes=in_axes)(*args)


def test_compile_options_only_on_the_measured_jaxlib(monkeypatch):
    assert xla_flags.compile_options(xla_flags.NO_YNN_FUSION) == xla_flags.NO_YNN_FUSION
    monkeypatch.setattr(jaxlib, "__version__", "0.11.0")
    assert xla_flags.compile_options(xla_flags.NO_YNN_FUSION) is None


def test_gradient_sums_per_run_and_shared_cotangents():
    """``add_any`` (autodiff's sum of cotangents) of a per-run cotangent and a shared one (the
    ones of ``jnp.sum(x)``), which takes no size-1 broadcasting."""
    grad = jax.grad(lambda x, w: jnp.sum(w * x * x) + jnp.sum(x))
    x = jax.random.normal(jax.random.PRNGKey(7), (RUNS, 3))
    w = jnp.arange(1.0, 4.0)
    expected = jax.vmap(grad, in_axes=(0, None))(x, w)
    close(vmap_minor(grad, in_axes=(0, None))(x, w), expected, jnp.float64)
    assert vmap_minor_fallbacks(grad, x, w, in_axes=(0, None)) == {}
