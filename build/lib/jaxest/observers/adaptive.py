"""Zhang's adaptive observer for MIMO linear time-varying systems (Zhang 2002; Lungu, Lungu &
Grigorie, "Aircrafts state estimation by using an adaptive observer for MIMO LTV systems").

The system (eq 1), with theta in R^p unknown and constant::

    x' = A(t) x + B(t) u + psi(t) theta,      y = C(t) x.

The observer (eqs 12, 17, 31-32), with tuning matrices M (p x p) and Sigma (m x m), both SPD::

    Gamma'     = (A - K C) Gamma + psi                                            (12)
    x_hat'     = A x_hat + B u + psi theta_hat + [K + Gamma M Gamma^T C^T Sigma] (y - C x_hat)
    theta_hat' = M Gamma^T C^T Sigma (y - C x_hat)                                (17)
    K = P C^T R^{-1},   P' = A P + P A^T - P C^T R^{-1} C P + Q                   (31-32)

or a fixed gain K (pole placement). :class:`AdaptiveObserver` is the sampled-data form: y is
measured at t_k = t_0 + k dt; the input u_k and the innovation e_k = y_k - C(t_k) x_hat(t_k) are
held over [t_k, t_{k+1}], and eqs 12, 17, 32 (and the excitation integral of eq 16) are
integrated over the interval by classical Runge-Kutta with ``substeps`` steps. Holding the
innovation keeps the truth a fixed point of the sampled observer (noise-free, x_hat = x and
theta_hat = theta stay so exactly); as dt -> 0 the scheme tends to eq 17 driven by continuous y.

:class:`DiscreteAdaptiveObserver` is the discrete-time form (Zhang 2018, "adaptive Kalman
filter"; NOTES.md section 5) for x_{k+1} = F x_k + B u_k + Phi_k theta, y_k = H x_k.

M, Sigma, Q and R are array fields of the observer: gradients flow to them (``eqx.filter_grad``
over the observer); :func:`jaxest.tune.fit` tunes them (see :mod:`jaxest.studies.adaptive`).
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from jaxest.checks import check_matrix
from jaxest.linalg import symmetrize
from jaxest.observers import excitation
from jaxest.run import Status, check_finite_status


def _value(matrix, t):
    return matrix(t) if callable(matrix) else matrix


class ContinuousLTV(eqx.Module):
    """x' = A(t) x + B(t) u + psi(t, u, y) theta,  y = C(t) x  (eq 1).

    ``A``, ``B``, ``C`` are arrays (time-invariant) or callables ``t -> array``. ``psi`` is a
    callable ``(t, u, y) -> (n, p)`` built from measured signals (u, y): the observer passes the
    held input and the measured sample.
    """

    A: Float[Array, "n n"] | Callable
    B: Float[Array, "n l"] | Callable
    C: Float[Array, "m n"] | Callable
    psi: Callable

    def matrices(self, t):
        """(A(t), B(t), C(t))."""
        return _value(self.A, t), _value(self.B, t), _value(self.C, t)

    def derivative(self, t, x, u, psi_theta):
        """A(t) x + B(t) u + psi theta (``psi_theta`` given)."""
        A, B, _ = self.matrices(t)
        return A @ x + B @ u + psi_theta

    def propagator(self, dt: float, substeps: int = 32) -> Callable:
        """``(x, u, y, theta, t) -> x(t + dt)``: the true state one sample later, u held.

        Exact when A and B are arrays (e^{A dt} x + E (B u + psi(t, u, y) theta), with
        E = int_0^dt e^{A s} ds, from one matrix exponential made here); otherwise Runge-Kutta
        with ``substeps`` steps and psi(s, u, y) along the interval.
        """
        if callable(self.A) or callable(self.B):

            def rk4_step(x, u, y, theta, t):
                field = lambda s, z: self.derivative(s, z, u, self.psi(s, u, y) @ theta)
                return _rk4(field, x, t, dt, substeps)

            return rk4_step
        F, E = _exp_and_integral(self.A, dt)
        return lambda x, u, y, theta, t: F @ x + E @ (self.B @ u + self.psi(t, u, y) @ theta)

    def discretize(self, dt: float) -> DiscreteLTV:
        """The exact zero-order-hold sampling (time-invariant A, B; psi constant over a sample).

        F = e^{A dt}, B_d = E B, Phi_k = E psi(k dt, u_k, y_k) with E = int_0^dt e^{A s} ds.
        """
        if callable(self.A) or callable(self.B):
            raise ValueError("model: discretize needs constant arrays A and B")
        F, E = _exp_and_integral(self.A, dt)
        return DiscreteLTV(F, E @ self.B, self.C, HeldRegressor(E, self.psi, dt))


def _exp_and_integral(A, dt):
    """(e^{A dt}, int_0^dt e^{A s} ds) from one exponential of [[A, I], [0, 0]] dt (Van Loan)."""
    n = A.shape[0]
    block = jnp.zeros((2 * n, 2 * n), A.dtype)
    block = block.at[:n, :n].set(A).at[:n, n:].set(jnp.eye(n, dtype=A.dtype))
    expm = jax.scipy.linalg.expm(block * dt)
    return expm[:n, :n], expm[:n, n:]


class InputEffectiveness(eqx.Module):
    """psi(t, u, y) = B_psi diag(u): theta_i scales the effectiveness of input i."""

    B_psi: Float[Array, "n l"]

    def __call__(self, t, u, y):
        return self.B_psi * u[None, :]


class HeldRegressor(eqx.Module):
    """Phi_k = E psi(k dt, u_k, y_k): the sampled regressor of :meth:`ContinuousLTV.discretize`."""

    E: Float[Array, "n n"]
    psi: Callable
    dt: float = eqx.field(static=True)

    def __call__(self, k, u, y):
        return self.E @ self.psi(k * self.dt, u, y)


class DiscreteLTV(eqx.Module):
    """x_{k+1} = F x_k + B u_k + Phi(k, u_k, y_k) theta,  y_k = H x_k (arrays or callables of k)."""

    F: Float[Array, "n n"] | Callable
    B: Float[Array, "n l"] | Callable
    H: Float[Array, "m n"] | Callable
    phi: Callable

    def matrices(self, k):
        """(F_k, B_k, H_k)."""
        return _value(self.F, k), _value(self.B, k), _value(self.H, k)


class ObserverPrior(eqx.Module):
    """Initial estimates: ``x`` (n), ``theta`` (p), Riccati ``P`` (n x n, eq 32; not used with a
    fixed gain) and, for the discrete form, the parameter covariance ``theta_cov`` (p x p)."""

    x: Float[Array, " n"]
    theta: Float[Array, " p"]
    P: Float[Array, "n n"] | None = None
    theta_cov: Float[Array, "p p"] | None = None


class AdaptiveResult(eqx.Module):
    """Estimates at the sample times: ``x`` x_hat(t_k), ``theta`` theta_hat(t_k), ``Gamma``
    Gamma(t_k), ``innovation`` y_k - C x_hat, ``excitation`` the smallest eigenvalue of the eq 16
    Gramian over the window ending at t_k (NaN for the discrete form), ``status`` bits."""

    x: Float[Array, "T n"]
    theta: Float[Array, "T p"]
    Gamma: Float[Array, "T n p"]
    innovation: Float[Array, "T m"]
    excitation: Float[Array, " T"]
    status: Int[Array, " T"]

    @property
    def ok(self) -> jax.Array:
        """True where every step finished with status OK."""
        return jnp.all(self.status == Status.OK, axis=-1)


def _rk4(field, z, t, h, substeps: int):
    """Classical Runge-Kutta for z' = field(s, z) over [t, t + h] in ``substeps`` steps."""
    d = h / substeps

    def axpy(a, x, y):
        return jax.tree_util.tree_map(lambda xi, yi: yi + a * xi, x, y)

    def body(i, z):
        s = t + i * d
        k1 = field(s, z)
        k2 = field(s + d / 2, axpy(d / 2, k1, z))
        k3 = field(s + d / 2, axpy(d / 2, k2, z))
        k4 = field(s + d, axpy(d, k3, z))
        incr = jax.tree_util.tree_map(
            lambda a, b, c, e: (a + 2 * b + 2 * c + e) / 6, k1, k2, k3, k4
        )
        return axpy(d, incr, z)

    return jax.lax.fori_loop(0, substeps, body, z)


def _check_tuning(M, Sigma, Q, R, K):
    check_matrix("M", M, spd=True, ndim=2)
    check_matrix("Sigma", Sigma, spd=True, ndim=2)
    if (K is None) == (Q is None or R is None):
        raise ValueError("K: give either a fixed gain K or both Riccati weights Q and R")
    if K is None:
        check_matrix("Q", Q, spd=True, ndim=2)
        check_matrix("R", R, spd=True, ndim=2)


def _check_dimensions(M, Sigma, Q, R, K, prior, n, m, p):
    shapes = {"prior.x": (prior.x, (n,)), "prior.theta": (prior.theta, (p,)), "M": (M, (p, p))}
    shapes["Sigma"] = (Sigma, (m, m))
    if K is not None:
        shapes["K"] = (K, (n, m))
    else:
        shapes |= {"Q": (Q, (n, n)), "R": (R, (m, m))}
    for name, (value, want) in shapes.items():
        if np.shape(value) != want:
            raise ValueError(f"{name}: expected shape {want}, got {np.shape(value)}")


class AdaptiveState(eqx.Module):
    t: Float[Array, ""]
    x: Float[Array, " n"]
    theta: Float[Array, " p"]
    Gamma: Float[Array, "n p"]
    P: Float[Array, "n n"] | None
    window: excitation.ExcitationWindow


class AdaptiveObserver(eqx.Module):
    """Zhang's continuous-time adaptive observer, sampled every ``dt`` (eqs 12, 17, 31-32, 16).

    Give ``Q`` and ``R`` for the Riccati gain K = P C^T R^{-1} (P integrated by eq 32 from
    ``prior.P``), or a fixed gain ``K`` with A - K C stable. ``excitation_window`` (in samples)
    and ``excitation_threshold`` (delta of eq 16) set the persistent-excitation monitor.
    """

    M: Float[Array, "p p"]
    Sigma: Float[Array, "m m"]
    Q: Float[Array, "n n"] | None = None
    R: Float[Array, "m m"] | None = None
    K: Float[Array, "n m"] | None = None
    dt: float = eqx.field(static=True, default=0.01)
    substeps: int = eqx.field(static=True, default=4)
    excitation_window: int = eqx.field(static=True, default=200)
    excitation_threshold: float = eqx.field(static=True, default=1e-6)

    def __check_init__(self):
        _check_tuning(self.M, self.Sigma, self.Q, self.R, self.K)
        if not self.dt > 0 or self.substeps < 1:
            raise ValueError(
                f"dt: must be positive with substeps >= 1, got {self.dt}, {self.substeps}"
            )

    def init(self, model: ContinuousLTV, prior: ObserverPrior, t0: float = 0.0) -> AdaptiveState:
        if not isinstance(prior, ObserverPrior):
            raise ValueError(
                f"prior: expected ObserverPrior(x, theta, ...), got {type(prior).__name__}"
            )
        A, B, C = model.matrices(t0)
        n, m = A.shape[-1], C.shape[-2]
        dtype = jnp.result_type(prior.x)
        psi = jax.eval_shape(model.psi, t0, jnp.zeros(B.shape[-1], dtype), jnp.zeros(m, dtype))
        if len(psi.shape) != 2 or psi.shape[0] != n:
            raise ValueError(f"model.psi: expected an (n, p) = ({n}, p) matrix, got {psi.shape}")
        p = psi.shape[1]
        _check_dimensions(self.M, self.Sigma, self.Q, self.R, self.K, prior, n, m, p)
        P = None
        if self.K is None:
            if prior.P is None:
                raise ValueError("prior.P: the Riccati gain (Q, R given) needs an initial P")
            check_matrix("prior.P", prior.P, (n, n), spd=True)
            P = jnp.asarray(prior.P, dtype)
        return AdaptiveState(
            t=jnp.asarray(t0, dtype),
            x=jnp.asarray(prior.x, dtype),
            theta=jnp.asarray(prior.theta, dtype),
            Gamma=jnp.zeros((n, p), dtype),
            P=P,
            window=excitation.empty_window(self.excitation_window, p, dtype),
        )

    def gain(self, P, C, R_inv):
        """K(t): fixed, or P C^T R^{-1} (eq 31)."""
        if self.K is not None:
            return self.K
        return P @ C.T @ R_inv

    def step(self, model: ContinuousLTV, state: AdaptiveState, y, u):
        """Estimates at t_k, then integrate eqs 12, 17, 32 over [t_k, t_k + dt]."""
        _, _, C_k = model.matrices(state.t)
        e = y - C_k @ state.x
        level = excitation.excitation_level(state.window)
        status = check_finite_status(state.x, state.theta) | excitation.excitation_status(
            state.window, level, self.excitation_threshold
        )
        output = AdaptiveResult(state.x, state.theta, state.Gamma, e, level, status)
        # one inverse per sample, not one solve per Runge-Kutta stage (R is small, SPD)
        R_inv = None if self.K is not None else jnp.linalg.inv(self.R)

        def field(s, z):
            x, theta, Gamma, P, _ = z
            A, B, C = model.matrices(s)
            psi = model.psi(s, u, y)
            K = self.gain(P, C, R_inv)
            CG = C @ Gamma
            adapt = self.M @ (CG.T @ (self.Sigma @ e))  # M Gamma^T C^T Sigma e
            dx = A @ x + B @ u + psi @ theta + K @ e + Gamma @ adapt
            dGamma = (A - K @ C) @ Gamma + psi
            dP = None
            if P is not None:
                PCt = P @ C.T
                dP = A @ P + P @ A.T - PCt @ R_inv @ PCt.T + self.Q
            return dx, adapt, dGamma, dP, CG.T @ self.Sigma @ CG

        p = state.theta.shape[0]
        z0 = (state.x, state.theta, state.Gamma, state.P, jnp.zeros((p, p), state.x.dtype))
        x, theta, Gamma, P, increment = _rk4(field, z0, state.t, self.dt, self.substeps)
        new = AdaptiveState(
            t=state.t + self.dt,
            x=x,
            theta=theta,
            Gamma=Gamma,
            P=None if P is None else symmetrize(P),
            window=excitation.push(state.window, symmetrize(increment)),
        )
        return new, output

    def result(self, outputs: AdaptiveResult, final_state) -> AdaptiveResult:
        return outputs


class DiscreteState(eqx.Module):
    k: Int[Array, ""]
    x_pred: Float[Array, " n"]
    P_pred: Float[Array, "n n"]
    theta: Float[Array, " p"]
    Ups_pred: Float[Array, "n p"]
    theta_cov: Float[Array, "p p"]


class DiscreteAdaptiveObserver(eqx.Module):
    """The discrete-time adaptive observer (adaptive Kalman filter; NOTES.md section 5).

    Kalman part with weights ``Q``, ``R``; the parameter part is recursive least squares with
    forgetting factor ``forgetting`` (lambda in (0, 1]) on the regressor Omega_k = H Upsilon_k::

        P- = F P F^T + Q,  S_k = H P- H^T + R,  K_k = P- H^T S_k^{-1},  P = (I - K_k H) P-
        Upsilon_k = (I - K_k H)(F Upsilon_{k-1} + Phi_{k-1})
        Omega_k = H (F Upsilon_{k-1} + Phi_{k-1})
        Lambda_k = (lambda S_k + Omega_k S_theta Omega_k^T)^{-1}
        Gain_k = S_theta Omega_k^T Lambda_k
        S_theta <- (S_theta - S_theta Omega_k^T Lambda_k Omega_k S_theta) / lambda
        e_k = y_k - H (F x + B u + Phi theta),  theta_k = theta_{k-1} + Gain_k e_k
        x_k = F x + B u + Phi theta_{k-1} + K_k e_k + Upsilon_k (theta_k - theta_{k-1})

    Following the jaxest convention the step updates with y_k then predicts to k + 1 with u_k,
    so the state carries F x + B u + Phi theta, P- and F Upsilon + Phi. ``prior`` is on x_0
    (``prior.P`` its covariance, ``prior.theta_cov`` the initial S_theta).
    """

    Q: Float[Array, "n n"]
    R: Float[Array, "m m"]
    forgetting: float = eqx.field(static=True, default=1.0)

    def __check_init__(self):
        check_matrix("Q", self.Q, square=True, psd=True)
        check_matrix("R", self.R, spd=True)
        if not 0 < self.forgetting <= 1:
            raise ValueError(f"forgetting: must be in (0, 1], got {self.forgetting}")

    def init(self, model: DiscreteLTV, prior: ObserverPrior) -> DiscreteState:
        if not isinstance(prior, ObserverPrior) or prior.P is None or prior.theta_cov is None:
            raise ValueError("prior: expected ObserverPrior(x, theta, P, theta_cov)")
        F, _, H = model.matrices(0)
        n, m, p = F.shape[-1], H.shape[-2], np.shape(prior.theta)[0]
        check_matrix("prior.P", prior.P, (n, n), spd=True)
        check_matrix("prior.theta_cov", prior.theta_cov, (p, p), spd=True)
        for name, value, want in (
            ("Q", self.Q, (n, n)),
            ("R", self.R, (m, m)),
            ("prior.x", prior.x, (n,)),
        ):
            if np.shape(value) != want:
                raise ValueError(f"{name}: expected shape {want}, got {np.shape(value)}")
        dtype = jnp.result_type(prior.x)
        return DiscreteState(
            k=jnp.zeros((), jnp.int32),
            x_pred=jnp.asarray(prior.x, dtype),
            P_pred=jnp.asarray(prior.P, dtype),
            theta=jnp.asarray(prior.theta, dtype),
            Ups_pred=jnp.zeros((n, p), dtype),
            theta_cov=jnp.asarray(prior.theta_cov, dtype),
        )

    def step(self, model: DiscreteLTV, state: DiscreteState, y, u):
        F, B, H = model.matrices(state.k)
        n = F.shape[-1]
        S = H @ state.P_pred @ H.T + self.R
        K = jnp.linalg.solve(S, H @ state.P_pred).T
        I_KH = jnp.eye(n, dtype=F.dtype) - K @ H
        P = symmetrize(I_KH @ state.P_pred)
        Omega = H @ state.Ups_pred
        St = state.theta_cov
        inner = self.forgetting * S + Omega @ St @ Omega.T
        gain = jnp.linalg.solve(inner, Omega @ St).T  # S_theta Omega^T Lambda
        theta_cov = symmetrize((St - gain @ Omega @ St) / self.forgetting)
        e = y - H @ state.x_pred
        theta = state.theta + gain @ e
        Ups = I_KH @ state.Ups_pred
        x = state.x_pred + K @ e + Ups @ (theta - state.theta)
        Phi = model.phi(state.k, u, y)
        status = check_finite_status(x, theta, P, theta_cov)
        nan = jnp.full((), jnp.nan, x.dtype)
        new = DiscreteState(
            k=state.k + 1,
            x_pred=F @ x + B @ u + Phi @ theta,
            P_pred=symmetrize(F @ P @ F.T + self.Q),
            theta=theta,
            Ups_pred=F @ Ups + Phi,
            theta_cov=theta_cov,
        )
        return new, AdaptiveResult(x, theta, Ups, e, nan, status)

    def result(self, outputs: AdaptiveResult, final_state) -> AdaptiveResult:
        return outputs


class ClosedLoopRun(eqx.Module):
    """Truth (``states``, ``observations`` as measured, ``inputs`` applied) and the estimates."""

    states: Float[Array, "T n"]
    observations: Float[Array, "T m"]
    inputs: Float[Array, "T l"]
    estimate: AdaptiveResult


def simulate_closed_loop(
    observer: AdaptiveObserver,
    model: ContinuousLTV,
    theta,
    x0,
    prior: ObserverPrior,
    feedback_gain,
    reference,
    key=None,
    noise_std=0.0,
) -> ClosedLoopRun:
    """Fly ``model`` with true parameters ``theta`` from ``x0`` under u_k = -K_bar x_hat(t_k) + r_k.

    ``reference`` (T x l) is the added excitation r_k; u_k is held over each sample interval and
    the truth is propagated exactly (:meth:`ContinuousLTV.propagator`). y_k = C x(t_k) + v_k with
    v_k ~ N(0, diag(noise_std^2)) when ``key`` is given. The observer sees only (y_k, u_k); its
    ``step`` is the one :func:`jaxest.run.run` drives, so re-running it open loop on
    (``observations``, ``inputs``) gives the same estimates.
    """
    state = observer.init(model, prior)
    T, m = reference.shape[0], model.matrices(0.0)[2].shape[0]
    dtype = state.x.dtype
    propagate = model.propagator(observer.dt)
    noise = jnp.zeros((T, m), dtype)
    if key is not None:
        noise = jnp.asarray(noise_std, dtype) * jax.random.normal(key, (T, m), dtype)

    def body(carry, args):
        x, obs = carry
        r, v = args
        _, _, C = model.matrices(obs.t)
        y_true = C @ x
        y = y_true + v
        u = -feedback_gain @ obs.x + r
        x_next = propagate(x, u, y_true, theta, obs.t)
        obs, out = observer.step(model, obs, y, u)
        return (x_next, obs), (x, y, u, out)

    _, (xs, ys, us, outs) = jax.lax.scan(body, (jnp.asarray(x0, dtype), state), (reference, noise))
    return ClosedLoopRun(xs, ys, us, outs)
