"""Plain NumPy reference implementations the tests compare jaxest against."""

import numpy as np


def kalman_filter(F, H, Q, R, m0, P0, ys, G=None):
    """Textbook covariance Kalman filter; NaN entries of y are skipped by dropping their rows.

    Returns filtered means, covariances, predicted means, covariances and the log-likelihood.
    """
    n = len(m0)
    G = np.eye(n) if G is None else G
    x, P = np.array(m0, float), np.array(P0, float)
    means, covs, pmeans, pcovs, loglik = [], [], [], [], 0.0
    for k, y in enumerate(ys):
        Fk = F[k] if F.ndim == 3 else F
        Hk = H[k] if H.ndim == 3 else H
        pmeans.append(x.copy())
        pcovs.append(P.copy())
        obs = np.isfinite(y)
        if obs.any():
            Ho, Ro = Hk[obs], R[np.ix_(obs, obs)]
            e = y[obs] - Ho @ x
            S = Ho @ P @ Ho.T + Ro
            K = P @ Ho.T @ np.linalg.inv(S)
            x = x + K @ e
            P = P - K @ S @ K.T
            _, logdet = np.linalg.slogdet(S)
            loglik += -0.5 * (obs.sum() * np.log(2 * np.pi) + logdet + e @ np.linalg.solve(S, e))
        means.append(x.copy())
        covs.append(P.copy())
        x = Fk @ x
        P = Fk @ P @ Fk.T + G @ Q @ G.T
    return np.array(means), np.array(covs), np.array(pmeans), np.array(pcovs), loglik


def rts_smoother(F, means, covs, pmeans, pcovs):
    """Textbook RTS smoother over the output of :func:`kalman_filter`."""
    ms, Ps = means.copy(), covs.copy()
    for k in range(len(means) - 2, -1, -1):
        C = covs[k] @ F.T @ np.linalg.inv(pcovs[k + 1])
        ms[k] = means[k] + C @ (ms[k + 1] - pmeans[k + 1])
        Ps[k] = covs[k] + C @ (Ps[k + 1] - pcovs[k + 1]) @ C.T
    return ms, Ps


def random_system(rng, n, m, correlated_R=True, stable=0.95):
    """A random stable linear system with SPD Q and (optionally correlated) R."""
    F = stable * np.linalg.qr(rng.normal(size=(n, n)))[0]
    H = rng.normal(size=(m, n))
    A = rng.normal(size=(n, n))
    Q = A @ A.T / n + 0.1 * np.eye(n)
    B = rng.normal(size=(m, m))
    R = B @ B.T / m + 0.2 * np.eye(m) if correlated_R else np.diag(rng.uniform(0.2, 1.0, m))
    return F, H, Q, R
