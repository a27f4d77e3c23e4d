"""The information-form filters (EKF, InformationFilter, SVDEKF) where R is far below H P H^T:
right, or flagged INFORMATION_INCONSISTENT, never wrong with status OK (docs/robustness.md)."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxest as je
from tests.reference import kalman_filter

INFORMATION_FORM = [je.EKF, je.InformationFilter, je.SVDEKF]
IDS = [f.__name__ for f in INFORMATION_FORM]
#: measurement noise variances, from ordinary to 10^10 below the predicted position variance
R_SWEEP = (1e-2, 1e-4, 1e-6, 1e-8, 3e-9, 1e-9, 5e-10, 1e-10, 1e-12)
STEPS = 20
FLAG = je.InformationStatus.INFORMATION_INCONSISTENT


@functools.cache
def precise_position_sensor():
    """A constant-velocity model (F = [[1, 0.1], [0, 1]], Q = 0.01 I, P0 = I) with a position
    sensor of variance R for each R of :data:`R_SWEEP` (a missing measurement at steps 5 and
    13), its measurements, and the NumPy Kalman filter's filtered means, their standard
    deviations and its log-likelihood."""
    rng = np.random.default_rng(0)
    F, H, Q = np.array([[1.0, 0.1], [0.0, 1.0]]), np.array([[1.0, 0.0]]), 0.01 * np.eye(2)
    ys, means, stds, logliks = [], [], [], []
    for R in R_SWEEP:
        x, y = np.array([3.0, 1.0]), []
        for _ in range(STEPS):
            y.append(H @ x + np.sqrt(R) * rng.normal(size=1))
            x = F @ x + rng.multivariate_normal(np.zeros(2), Q)
        y = np.array(y)
        y[[5, 13]] = np.nan
        mean, cov, _, _, loglik = kalman_filter(F, H, Q, R * np.eye(1), np.zeros(2), np.eye(2), y)
        ys.append(y), means.append(mean), logliks.append(loglik)
        stds.append(np.sqrt(np.diagonal(cov, axis1=1, axis2=2)))
    return (F, H, Q), np.array(ys), (np.array(means), np.array(stds), np.array(logliks))


@functools.cache
def sweep(Filter, dtype):
    """Filtered means, log-likelihood and the OR of the steps' status of ``Filter`` over
    :data:`R_SWEEP`, in ``dtype``: one ``vmap`` over the noise levels."""
    (F, H, Q), ys, _ = precise_position_sensor()
    c = lambda a: jnp.asarray(a, dtype)

    @jax.jit
    @jax.vmap
    def run(R, y):
        model = je.LinearGaussian(c(F), c(H), c(Q), R * jnp.eye(1, dtype=dtype))
        result = je.run(Filter(), model, y, prior=je.Gaussian(c(np.zeros(2)), c(np.eye(2))))
        return result.mean, result.loglik, result.any_status

    return jax.tree.map(np.asarray, run(c(R_SWEEP), c(ys)))


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64], ids=["float32", "float64"])
@pytest.mark.parametrize("Filter", INFORMATION_FORM, ids=IDS)
def test_right_or_flagged_never_wrong_with_status_ok(Filter, dtype):
    """Status OK means the filtered means lie within one standard deviation of the float64
    NumPy Kalman filter's (the flag allows half of one per step) and the log-likelihood within
    one nat of its; every R where that fails is flagged. Before the flag (and the likelihood from
    S), all with status OK in float32: the SVD-EKF's means 18 and 7e9 standard deviations off
    (R = 1e-10, 1e-12), the EKF's log-likelihood off by 6 to 7e4 nats from R = 1e-8 down, the
    information filter's by 9 at R = 1e-8."""
    _, _, (ref_means, ref_stds, ref_logliks) = precise_position_sensor()
    means, logliks, status = sweep(Filter, dtype)
    known = je.Status.NONFINITE | je.Status.NOT_POSITIVE_DEFINITE | FLAG
    assert not np.any(status & ~np.int32(known))
    for i, R in enumerate(R_SWEEP):
        if status[i] != je.Status.OK:
            continue
        error = np.max(np.abs(means[i] - ref_means[i]) / ref_stds[i])
        assert error < 1, (R, error)
        assert abs(logliks[i] - ref_logliks[i]) < 1, (R, logliks[i], ref_logliks[i])


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64], ids=["float32", "float64"])
@pytest.mark.parametrize("Filter", INFORMATION_FORM, ids=IDS)
def test_ordinary_noise_is_not_flagged(Filter, dtype):
    """R from 1e-2 to 1e-8 against a predicted position variance near 0.01-1: no flag in either
    dtype (float32 loses digits there, but less than a tenth of a standard deviation)."""
    assert np.all(sweep(Filter, dtype)[2][:4] == je.Status.OK)


def test_flags_where_the_information_form_goes_wrong():
    """In float32 the SVD-EKF strays by 20 standard deviations at R = 1e-10 (flagged by its
    correction), the information filter's predicted information matrix by 62 % at R = 3e-9
    while its numbers stay finite (flagged by the time update's check), and the EKF's
    likelihood, now from S, is right where the determinant lemma's cancelled."""
    assert sweep(je.SVDEKF, jnp.float32)[2][R_SWEEP.index(1e-10)] == FLAG
    assert sweep(je.InformationFilter, jnp.float32)[2][R_SWEEP.index(3e-9)] == FLAG
    _, _, (_, _, ref_logliks) = precise_position_sensor()
    np.testing.assert_allclose(sweep(je.EKF, jnp.float32)[1], ref_logliks, atol=1e-3)


def test_the_flag_is_named_and_explained():
    """The results carry :data:`InformationStatus`: ``describe`` and ``throw=True`` name the
    flag and say what to do."""
    (F, H, Q), ys, _ = precise_position_sensor()
    c = lambda a: jnp.asarray(a, jnp.float32)
    model = je.LinearGaussian(c(F), c(H), c(Q), c(1e-10 * np.eye(1)))
    prior = je.Gaussian(c(np.zeros(2)), c(np.eye(2)))
    y = c(ys[R_SWEEP.index(1e-10)])
    result = je.run(je.SVDEKF(), model, y, prior=prior)
    assert result.flags is je.InformationStatus
    assert "INFORMATION_INCONSISTENT" in result.flags.describe(result.any_status)
    with pytest.raises(Exception, match="covariance-form filter"):
        je.run(je.SVDEKF(), model, y, prior=prior, throw=True)


def test_the_ekf_flags_an_update_its_inverse_got_wrong():
    """The EKF inverts P(k|k-1) for eq 9. With a prior of variances 100 and 0.01 and a sum of
    the two measured to 1e-3 (float32), the inverse loses the measured direction: the means
    are off by 4e-3 of their size, and the flag says so."""
    rng = np.random.default_rng(1)
    F, H, Q = np.eye(3), np.array([[1.0, 1.0, 0.0]]), 1e-6 * np.eye(3)
    P0, R, ys = np.diag([100.0, 0.01, 1.0]), 1e-6 * np.eye(1), rng.normal(size=(10, 1))
    ref_means = kalman_filter(F, H, Q, R, np.zeros(3), P0, ys)[0]
    c = lambda a: jnp.asarray(a, jnp.float32)
    result = je.run(
        je.EKF(), je.LinearGaussian(c(F), c(H), c(Q), c(R)), c(ys),
        prior=je.Gaussian(c(np.zeros(3)), c(P0)),
    )  # fmt: skip
    error = np.max(np.abs(np.asarray(result.mean) - ref_means)) / np.max(np.abs(ref_means))
    assert error > 1e-3
    assert result.any_status == FLAG
