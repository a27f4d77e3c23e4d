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
filter"; docs/papers/adaptive.md) for x_{k+1} = F x_k + B u_k + Phi_k theta, y_k = H x_k.

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

from jaxest._checks import (
    as_array,
    check_callable,
    check_inputs,
    check_matrix,
    check_measurements,
    check_positive_int,
    check_precision,
    check_prior_vector,
    check_sequence,
    is_concrete,
)
from jaxest._estimator import AbstractEstimator, AbstractResult
from jaxest._status import finite_status as check_finite_status
from jaxest.filters.common import masked_measurement
from jaxest.linalg import (
    cho_solve_lower,
    chol_inverse,
    cholesky,
    inv_spd,
    mm,
    mv,
    solve_triangular,
    symmetrize,
    working_precision_by_default,
)
from jaxest.models import at_time, check_time_axis
from jaxest.observers import excitation
from jaxest.observers.excitation import ObserverStatus as Status


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

    def discretize(self, dt: float, steps: int | None = None, substeps: int = 32) -> DiscreteLTV:
        """The zero-order-hold sampling at t_k = k dt (u and psi held over each sample).

        Constant A, B: exact, F = e^{A dt}, B_d = E B, Phi_k = E psi(k dt, u_k, y_k) with
        E = int_0^dt e^{A s} ds. Time-varying A(t) or B(t): over [t_k, t_k + dt],
        F_k = Phi(t_k + dt, t_k) (the transition matrix), B_k = int Phi(t_k + dt, s) B(s) ds and
        E_k = int Phi(t_k + dt, s) ds, from dPhi/ds = A Phi, dB_k/ds = A B_k + B(s),
        dE_k/ds = A E_k + I by Runge-Kutta with ``substeps`` steps, for k < ``steps`` (the
        horizon, needed then) and stacked over time. A callable C(t) is read at t_k.
        """
        H = SampledMatrix(self.C, dt) if callable(self.C) else self.C
        if not (callable(self.A) or callable(self.B)):
            F, E = _exp_and_integral(self.A, dt)
            return DiscreteLTV(F, E @ self.B, H, HeldRegressor(E, self.psi, dt))
        if steps is None or steps < 1:
            raise ValueError(
                "steps: a time-varying A(t) or B(t) is sampled over a horizon; pass "
                f"steps=T (the number of samples), got {steps}"
            )
        F, B, E = jax.vmap(lambda k: self._sample_interval(k * dt, dt, substeps))(jnp.arange(steps))
        return DiscreteLTV(F, B, H, HeldRegressor(E, self.psi, dt))

    def _sample_interval(self, t, dt, substeps):
        """(Phi(t + dt, t), int Phi(t + dt, s) B(s) ds, int Phi(t + dt, s) ds) by Runge-Kutta."""
        A0, B0, _ = self.matrices(t)
        eye = jnp.eye(A0.shape[-1], dtype=A0.dtype)

        def field(s, z):
            transition, input_integral, integral = z
            A, B, _ = self.matrices(s)
            return A @ transition, A @ input_integral + B, A @ integral + eye

        zero = jnp.zeros_like(eye)
        transition, input_integral, integral = _rk4(
            field, (eye, jnp.zeros_like(B0), zero), t, dt, substeps
        )
        return transition, input_integral, integral


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
    """Phi_k = E_k psi(k dt, u_k, y_k): the sampled regressor of :meth:`ContinuousLTV.discretize`
    (``E`` one matrix, or stacked over time)."""

    E: Float[Array, "n n"] | Float[Array, "T n n"]
    psi: Callable
    dt: float = eqx.field(static=True)

    def __call__(self, k, u, y):
        return at_time(self.E, k) @ self.psi(k * self.dt, u, y)


class SampledMatrix(eqx.Module):
    """M_k = matrix(k dt): a matrix function of time read at the sample times."""

    matrix: Callable
    dt: float = eqx.field(static=True)

    def __call__(self, k):
        return self.matrix(k * self.dt)


class DiscreteLTV(eqx.Module):
    """x_{k+1} = F x_k + B u_k + Phi(k, u_k, y_k) theta,  y_k = H x_k.

    ``F``, ``B``, ``H`` are matrices, matrices stacked over time (a leading axis T, read at k as
    :class:`~jaxest.LinearGaussian` does) or callables of k.
    """

    F: Float[Array, "n n"] | Float[Array, "T n n"] | Callable
    B: Float[Array, "n l"] | Float[Array, "T n l"] | Callable
    H: Float[Array, "m n"] | Float[Array, "T m n"] | Callable
    phi: Callable

    def matrices(self, k):
        """(F_k, B_k, H_k)."""
        return tuple(
            matrix(k) if callable(matrix) else at_time(matrix, k)
            for matrix in (self.F, self.B, self.H)
        )


class ObserverPrior(eqx.Module):
    """Initial estimates: ``x`` (n), ``theta`` (p), Riccati ``P`` (n x n, eq 32; not used with a
    fixed gain) and, for the discrete form, the parameter covariance ``theta_cov`` (p x p)."""

    x: Float[Array, " n"]
    theta: Float[Array, " p"]
    P: Float[Array, "n n"] | None = None
    theta_cov: Float[Array, "p p"] | None = None


class AdaptiveOutput(eqx.Module):
    """One sample's estimates (the fields of :class:`AdaptiveResult`, unstacked)."""

    x: Float[Array, " n"] | None
    theta: Float[Array, " p"] | None
    Gamma: Float[Array, "n p"] | None
    innovation: Float[Array, " m"] | None
    excitation: Float[Array, ""] | None
    status: Int[Array, ""] | None


class AdaptiveResult(AbstractResult):
    """Estimates at the sample times: ``x`` x_hat(t_k), ``theta`` theta_hat(t_k), ``Gamma``
    Gamma(t_k), ``innovation`` y_k - C x_hat, ``excitation`` the smallest eigenvalue of the eq 16
    Gramian over the window ending at t_k (for the discrete form: of its counterpart, see
    :class:`DiscreteAdaptiveObserver`), ``status`` bits
    (:class:`~jaxest.observers.ObserverStatus`)."""

    flags = Status

    final_state: object
    x: Float[Array, "T n"] | None = None
    theta: Float[Array, "T p"] | None = None
    Gamma: Float[Array, "T n p"] | None = None
    innovation: Float[Array, "T m"] | None = None
    excitation: Float[Array, " T"] | None = None
    status: Int[Array, " T"] | None = None
    any_status: Int[Array, ""] | None = None
    saved: object = None


def adaptive_result(outputs: AdaptiveOutput, final_state) -> AdaptiveResult:
    """The stacked outputs and the final state as an :class:`AdaptiveResult`."""
    return AdaptiveResult(
        final_state=final_state,
        x=outputs.x,
        theta=outputs.theta,
        Gamma=outputs.Gamma,
        innovation=outputs.innovation,
        excitation=outputs.excitation,
        status=outputs.status,
    )


def _rk4(field, z, t, h, substeps: int):
    """Classical Runge-Kutta for z' = field(s, z) over [t, t + h] in ``substeps`` steps: a fixed
    step of the observer's discretisation, as in :func:`jaxest.systems.flight.integrate_interval`
    (which says why not diffrax)."""
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


def _check_run_arguments(model, model_type: type, ys, inputs, prior, t0, tuning: dict) -> None:
    """What :func:`jaxest.run` gives an observer, before it traces anything: a model of
    ``model_type`` whose matrices (arrays or callables) fit one another at the first sample
    ``t0`` and whose regressor is a function, ``ys`` (T, m) without +-inf, ``inputs`` (T, l),
    held over each sample, and an :class:`ObserverPrior` as wide as the model, the data and the
    observer's ``tuning`` matrices (by name). They failed inside the trace with TypeErrors and
    AttributeErrors, or (ys of another width) ran on, broadcast."""
    if not isinstance(model, model_type):
        raise ValueError(f"model: expected a {model_type.__name__}, got {type(model).__name__}")
    state, output, regressor = (
        ("A", "C", "psi") if model_type is ContinuousLTV else ("F", "H", "phi")
    )
    for name in (state, "B", output):
        if not callable(getattr(model, name)):
            as_array(f"model.{name}", getattr(model, name))
    check_callable(f"model.{regressor}", getattr(model, regressor))
    S, B, C = jax.eval_shape(model.matrices, t0)
    n = S.shape[-1]
    matrices = len(S.shape) == len(B.shape) == len(C.shape) == 2
    if not (matrices and S.shape == (n, n) and B.shape[0] == n and C.shape[1] == n):
        raise ValueError(
            f"model: its {state} {S.shape}, B {B.shape} and {output} {C.shape} do not fit one "
            f"state (expected (n, n), (n, l) and (m, n))"
        )
    check_measurements(ys)
    m = C.shape[0]
    check_sequence("ys", ys, dim=m, dim_source=f" (model.{output} has {m} rows)")
    if inputs is None:
        raise ValueError(
            f"inputs: the observer holds u_k over each sample (model.B is {B.shape}); pass "
            f"inputs of shape (T, {B.shape[1]})"
        )
    T = np.shape(ys)[0]
    check_inputs(inputs, T, f"the measurements have {T}")
    check_sequence("inputs", inputs, dim=B.shape[1], dim_source=f" (model.B has {B.shape[1]})")
    _check_prior_type(prior)
    for field in ("x", "theta"):  # their sizes are init's to check (it evaluates the model)
        check_prior_vector(prior, field)
    tuning = {name: value for name, value in tuning.items() if value is not None}
    check_precision(model, ys, prior, inputs=inputs, **tuning)


def _check_prior_type(prior) -> None:
    if not isinstance(prior, ObserverPrior):
        raise ValueError(
            f"prior: expected ObserverPrior(x, theta, ...), got {type(prior).__name__}"
        )


def _check_number(name: str, value, sign: str = "") -> None:
    """``value`` is a finite real number, Python's or NumPy's (not a bool), and ``sign``
    ("positive", "non-negative") where given: a static setting such as a time or a threshold."""
    number = isinstance(value, int | float | np.integer | np.floating)
    finite = number and not isinstance(value, bool | np.bool_) and bool(np.isfinite(value))
    signed = {"": True, "positive": finite and value > 0, "non-negative": finite and value >= 0}
    if not (finite and signed[sign]):
        raise ValueError(f"{name}: must be a {sign or 'finite'} number, got {value!r}")


def _check_excitation(window, threshold) -> None:
    """The excitation monitor's window (steps) and threshold (0 never flags)."""
    check_positive_int("excitation_window", window)
    _check_number("excitation_threshold", threshold, "non-negative")


def rk4_growth(z):
    """|R(z)| for the classical Runge-Kutta method, R(z) = 1 + z + z^2/2 + z^3/6 + z^4/24: the
    factor by which one step of length h multiplies a mode e^{lambda t}, z = h lambda."""
    return np.abs(1 + z + z**2 / 2 + z**3 / 6 + z**4 / 24)


def _check_fixed_gain(K, model, dt: float, substeps: int) -> None:
    """A fixed gain K must make A - K C stable (Hurwitz; the state error and Gamma of eqs 12 and
    17 evolve by it), and the Runge-Kutta step h = dt / substeps must be stable for it (|R(h
    lambda)| <= 1 for every eigenvalue lambda: :func:`rk4_growth`). Otherwise the estimate
    diverged with status OK until it overflowed (K = [-3, 0]^T on a damped oscillator: an error
    above 1 from step 68, NONFINITE at step 354). Checked for a time-invariant model and a gain
    whose values are known."""
    if K is None or callable(model.A) or callable(model.C):
        return
    if not all(is_concrete(a) for a in (K, model.A, model.C)):
        return
    A, C, K = (np.asarray(a, np.float64) for a in (model.A, model.C, K))
    if A.ndim != 2 or K.shape != (A.shape[0], C.shape[0]):
        return  # a misshapen one: init names it (_check_dimensions)
    eigenvalues = np.linalg.eigvals(A - K @ C)
    if np.max(eigenvalues.real) >= 0:
        raise ValueError(
            f"K: A - K C must be stable for the observer to converge; its eigenvalues "
            f"{np.round(eigenvalues, 4)} have real parts up to {np.max(eigenvalues.real):.3g}"
        )
    stable = lambda count: np.max(rk4_growth(dt / count * eigenvalues)) <= 1
    if stable(substeps):
        return
    enough = substeps
    while not stable(enough):  # stable for small enough steps: Re lambda < 0
        enough *= 2
    low = enough // 2  # unstable
    while enough - low > 1:
        middle = (low + enough) // 2
        low, enough = (low, middle) if stable(middle) else (middle, enough)
    raise ValueError(
        f"substeps: a Runge-Kutta step of dt / substeps = {dt / substeps:.3g} is unstable for "
        f"A - K C (eigenvalues {np.round(eigenvalues, 4)}: one step multiplies a mode by up to "
        f"{np.max(rk4_growth(dt / substeps * eigenvalues)):.3g}); take substeps >= {enough} "
        f"or a smaller dt"
    )


def _check_regressor(model, t, n: int, l: int, m: int, prior) -> int:
    """p, the columns of the model's regressor (:attr:`ContinuousLTV.psi` at time ``t``,
    :attr:`DiscreteLTV.phi` at step ``t``), evaluated abstractly with u of size ``l`` and y of
    size ``m``: an (n, p) matrix, and ``prior.theta`` of size p. A regressor of the wrong height
    failed inside the trace (a TypeError about adding shapes), one of another width was blamed
    on the estimator (its step changed the state's shape)."""
    name = "psi" if isinstance(model, ContinuousLTV) else "phi"
    dtype = jnp.result_type(prior.x)
    value = jax.eval_shape(getattr(model, name), t, jnp.zeros(l, dtype), jnp.zeros(m, dtype))
    shape = getattr(value, "shape", None)
    if shape is None or len(shape) != 2 or shape[0] != n:
        got = type(value).__name__ if shape is None else shape
        raise ValueError(f"model.{name}: expected an (n, p) = ({n}, p) matrix, got {got}")
    p = shape[1]
    if np.shape(prior.theta) != (p,):
        raise ValueError(
            f"prior.theta: expected shape ({p},), one entry per column of model.{name} "
            f"{shape}, got {np.shape(prior.theta)}"
        )
    return p


def _check_shapes(shapes: dict) -> None:
    """Each ``name: (value, shape)`` has that shape."""
    for name, (value, want) in shapes.items():
        if np.shape(value) != want:
            raise ValueError(f"{name}: expected shape {want}, got {np.shape(value)}")


def _check_dimensions(M, Sigma, Q, R, K, prior, n, m, p):
    shapes = {"prior.x": (prior.x, (n,)), "M": (M, (p, p)), "Sigma": (Sigma, (m, m))}
    if K is not None:
        shapes["K"] = (K, (n, m))
    else:
        shapes |= {"Q": (Q, (n, n)), "R": (R, (m, m))}
    _check_shapes(shapes)


class AdaptiveState(eqx.Module):
    x: Float[Array, " n"]
    theta: Float[Array, " p"]
    Gamma: Float[Array, "n p"]
    P: Float[Array, "n n"] | None
    window: excitation.ExcitationWindow


class AdaptiveObserver(AbstractEstimator):
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
    t0: float = eqx.field(static=True, default=0.0)

    def __check_init__(self):
        _check_tuning(self.M, self.Sigma, self.Q, self.R, self.K)
        _check_excitation(self.excitation_window, self.excitation_threshold)
        _check_number("dt", self.dt, "positive")
        check_positive_int("substeps", self.substeps)  # a float failed in fori_loop
        _check_number("t0", self.t0)

    def time(self, k):
        """t_k = t0 + k dt."""
        return self.t0 + k * self.dt

    def check(self, model, ys, inputs, prior) -> None:
        """The arguments (:func:`_check_run_arguments`) and the fixed gain's stability
        (:func:`_check_fixed_gain`), before :func:`jaxest.run` traces the model and the gain."""
        tuning = {"M": self.M, "Sigma": self.Sigma, "Q": self.Q, "R": self.R, "K": self.K}
        _check_run_arguments(model, ContinuousLTV, ys, inputs, prior, self.t0, tuning)
        if prior.P is not None and self.K is None:
            check_matrix("prior.P", prior.P, spd=True)
        _check_fixed_gain(self.K, model, self.dt, self.substeps)

    def init(self, model: ContinuousLTV, prior: ObserverPrior) -> AdaptiveState:
        t0 = self.t0
        _check_prior_type(prior)
        A, B, C = model.matrices(t0)
        n, m = A.shape[-1], C.shape[-2]
        dtype = jnp.result_type(prior.x)
        p = _check_regressor(model, t0, n, B.shape[-1], m, prior)
        _check_dimensions(self.M, self.Sigma, self.Q, self.R, self.K, prior, n, m, p)
        _check_fixed_gain(self.K, model, self.dt, self.substeps)  # where known here (a closure)
        P = None
        if self.K is None:
            if prior.P is None:
                raise ValueError("prior.P: the Riccati gain (Q, R given) needs an initial P")
            check_matrix("prior.P", prior.P, (n, n), spd=True)
            P = jnp.asarray(prior.P, dtype)
        return AdaptiveState(
            x=jnp.asarray(prior.x, dtype),
            theta=jnp.asarray(prior.theta, dtype),
            Gamma=jnp.zeros((n, p), dtype),
            P=P,
            window=excitation.empty_window(self.excitation_window, p, dtype),
        )

    def step(self, model: ContinuousLTV, state: AdaptiveState, k, y, u, key=None):
        """Estimates at t_k, then integrate eqs 12, 17, 32 over [t_k, t_k + dt]."""
        t = self.time(k)
        _, _, C_k = model.matrices(t)
        # NaN entries of y_k are not measured: over [t_k, t_k + dt] their rows of C drop out of
        # eqs 12, 16, 17 and 32 and their innovations are 0 (R^-1 is that of the measured ones)
        observed = ~jnp.isnan(y)
        e = jnp.where(observed, y - C_k @ state.x, 0.0)
        mask = observed.astype(e.dtype)[:, None]
        level = excitation.excitation_level(state.window)
        status = check_finite_status(state.x, state.theta) | excitation.excitation_status(
            state.window, level, self.excitation_threshold
        )
        output = AdaptiveOutput(state.x, state.theta, state.Gamma, e, level, status)
        # one inverse per sample, not one solve per Runge-Kutta stage (R is small, SPD). The
        # products below are jaxest.linalg's: with a per-run C (the mask) and R^-1, ``@`` under
        # vmap is a batched dot per product, and 12 runs of the 747 study (80 000 steps) took
        # 21 s instead of 5 s
        R_inv = None
        if self.K is None:
            R_inv = inv_spd(masked_measurement(y, C_k @ state.x, C_k, self.R).R)
        Sigma_e = mv(self.Sigma, e)  # constant over the step

        def field(s, z):
            x, theta, Gamma, P, _ = z
            A, B, C = model.matrices(s)
            C = mask * C
            psi = model.psi(s, u, y)
            if P is None:
                K = self.K
            else:
                PCt = mm(P, C.T)
                K = mm(PCt, R_inv)  # eq 31, K = P C^T R^-1
            CG = mm(C, Gamma)
            adapt = mv(self.M, mv(CG.T, Sigma_e))  # M Gamma^T C^T Sigma e
            dx = mv(A, x) + mv(B, u) + mv(psi, theta) + mv(K, e) + mv(Gamma, adapt)
            dGamma = mm(A - mm(K, C), Gamma) + psi
            dP = None
            if P is not None:
                dP = mm(A, P) + mm(P, A.T) - mm(K, PCt.T) + self.Q
            return dx, adapt, dGamma, dP, mm(CG.T, mm(self.Sigma, CG))

        p = state.theta.shape[0]
        z0 = (state.x, state.theta, state.Gamma, state.P, jnp.zeros((p, p), state.x.dtype))
        x, theta, Gamma, P, increment = _rk4(field, z0, t, self.dt, self.substeps)
        new = AdaptiveState(
            x=x,
            theta=theta,
            Gamma=Gamma,
            P=None if P is None else symmetrize(P),
            window=excitation.push(state.window, symmetrize(increment)),
        )
        return new, output

    def result(self, outputs: AdaptiveOutput, final_state) -> AdaptiveResult:
        return adaptive_result(outputs, final_state)


class DiscreteState(eqx.Module):
    x_pred: Float[Array, " n"]
    P_pred: Float[Array, "n n"]
    theta: Float[Array, " p"]
    Ups_pred: Float[Array, "n p"]
    theta_info: Float[Array, "p p"]  #: J, the information about theta (S_theta^-1)
    prior_factor: Float[Array, "p p"]  #: L0 with L0 L0^T = prior.theta_cov
    window: excitation.ExcitationWindow


class DiscreteAdaptiveObserver(AbstractEstimator):
    """The discrete-time adaptive observer (adaptive Kalman filter; docs/papers/adaptive.md,
    discrete adaptive Kalman form), with an excitation monitor and forgetting without windup.

    Kalman part with weights ``Q``, ``R``; the parameter part is recursive least squares on the
    regressor Omega_k = H Upsilon_k, kept in information form J = S_theta^-1::

        P- = F P F^T + Q,  S_k = H P- H^T + R,  K_k = P- H^T S_k^{-1},  P = (I - K_k H) P-
        Upsilon_k = (I - K_k H)(F Upsilon_{k-1} + Phi_{k-1})
        Omega_k = H (F Upsilon_{k-1} + Phi_{k-1}),  M_k = Omega_k^T S_k^{-1} Omega_k
        J_k = lambda_k J_{k-1} + (1 - lambda_k) J_0 + M_k,  J_0 = prior.theta_cov^-1
        Gain_k = J_k^{-1} Omega_k^T S_k^{-1}
        e_k = y_k - H (F x + B u + Phi theta),  theta_k = theta_{k-1} + Gain_k e_k
        x_k = F x + B u + Phi theta_{k-1} + K_k e_k + Upsilon_k (theta_k - theta_{k-1})

    With lambda_k = lambda and no J_0 term this is the paper's recursion (S_theta <- (S_theta -
    S_theta Omega^T Lambda Omega S_theta) / lambda); M_k is the information y_k carries about
    theta. With ``forgetting = 1`` it is the Kalman filter on the augmented state (x, theta),
    theta constant (docs/papers/adaptive.md, "Discrete adaptive Kalman form").

    **Excitation monitor** (the discrete counterpart of eq 16): W_k, the sum of M_j over the last
    ``excitation_window`` steps (j <= k), is the information the window's measurements carry
    about theta. ``excitation`` is the smallest eigenvalue of L0^T W_k L0 (L0 L0^T =
    prior.theta_cov): the window's information in units of the prior's. Below
    ``excitation_threshold`` (once the window is full) the status carries ``NOT_EXCITED``: the
    window told less about theta than the prior did.

    **Forgetting without windup.** Exponential forgetting, J_k = lambda J_{k-1} + M_k, removes
    (1 - lambda) J per step whether or not data arrive: without excitation S_theta grows like
    lambda^-k (covariance windup: lambda = 0.99 for 40 s at dt = 0.01 gives S_theta ~ 1e17 and,
    when the input returns, a one-sample fit of noise). Here the forgetting is bounded by the
    information that arrives: lambda_k = max(lambda, 1 - mu_k), with mu_k the smallest
    eigenvalue of L_J^-1 (W_k / N) L_J^-T (J_{k-1} = L_J L_J^T, N = ``excitation_window``), the
    window's average information per step relative to J, so (1 - lambda_k) J never exceeds
    W_k / N in the least-informed direction. Under steady excitation W_k / N = (1 - lambda) J
    and lambda_k = lambda (plain exponential forgetting); as the excitation fades, lambda_k -> 1
    and what was learnt is kept, so the estimate holds its accuracy through an unexcited
    interval instead of relaxing; the price is slower tracking after the excitation weakens
    for good. The term (1 - lambda_k) J_0 (stabilised forgetting, Kulhavy & Zarrop 1993) keeps
    J >= J_0: S_theta never exceeds ``prior.theta_cov``. Chosen over a trace bound on S_theta
    (a tuning constant that ignores direction) and directional forgetting (which forgets along
    any regressor direction however weak, so a fading scalar regressor still winds up, and needs
    a dead zone). lambda_k is treated as a constant by gradients.

    Following the jaxest convention the step updates with y_k then predicts to k + 1 with u_k,
    so the state carries F x + B u + Phi theta, P- and F Upsilon + Phi. ``prior`` is on x_0
    (``prior.P`` its covariance, ``prior.theta_cov`` the initial S_theta).
    """

    Q: Float[Array, "n n"]
    R: Float[Array, "m m"]
    forgetting: float = eqx.field(static=True, default=1.0)
    excitation_window: int = eqx.field(static=True, default=200)
    excitation_threshold: float = eqx.field(static=True, default=1.0)

    def __check_init__(self):
        check_matrix("Q", self.Q, square=True, psd=True)
        check_matrix("R", self.R, spd=True)
        if not 0 < self.forgetting <= 1:
            raise ValueError(f"forgetting: must be in (0, 1], got {self.forgetting}")
        _check_excitation(self.excitation_window, self.excitation_threshold)

    def check(self, model, ys, inputs, prior) -> None:
        """The arguments (:func:`_check_run_arguments`) and the prior's covariances, before
        :func:`jaxest.run` traces anything (``init`` checks their shapes)."""
        _check_run_arguments(model, DiscreteLTV, ys, inputs, prior, 0, {"Q": self.Q, "R": self.R})
        for name in ("P", "theta_cov"):
            if getattr(prior, name) is not None:
                check_matrix(f"prior.{name}", getattr(prior, name), spd=True)

    def check_steps(self, model, first: int, count: int) -> None:
        if isinstance(model, DiscreteLTV):
            for name in ("F", "B", "H"):
                check_time_axis(f"model.{name}", getattr(model, name), first, count)
            if isinstance(model.phi, HeldRegressor):
                check_time_axis("model.phi.E", model.phi.E, first, count)

    def init(self, model: DiscreteLTV, prior: ObserverPrior) -> DiscreteState:
        if not isinstance(prior, ObserverPrior) or prior.P is None or prior.theta_cov is None:
            raise ValueError("prior: expected ObserverPrior(x, theta, P, theta_cov)")
        F, B, H = model.matrices(0)
        n, m = F.shape[-1], H.shape[-2]
        p = _check_regressor(model, 0, n, B.shape[-1], m, prior)
        check_matrix("prior.P", prior.P, (n, n), spd=True)
        check_matrix("prior.theta_cov", prior.theta_cov, (p, p), spd=True)
        _check_shapes({"Q": (self.Q, (n, n)), "R": (self.R, (m, m)), "prior.x": (prior.x, (n,))})
        dtype = jnp.result_type(prior.x)
        prior_factor = cholesky(jnp.asarray(prior.theta_cov, dtype))
        return DiscreteState(
            x_pred=jnp.asarray(prior.x, dtype),
            P_pred=jnp.asarray(prior.P, dtype),
            theta=jnp.asarray(prior.theta, dtype),
            Ups_pred=jnp.zeros((n, p), dtype),
            theta_info=chol_inverse(prior_factor),
            prior_factor=prior_factor,
            window=excitation.empty_window(self.excitation_window, p, dtype),
        )

    def forgetting_factor(self, info, gramian, window_length: int):
        """lambda_k = max(lambda, 1 - mu_k): mu_k is the window's average information per step
        relative to J (smallest eigenvalue of L_J^-1 W L_J^-T / N, J = L_J L_J^T, W the window's
        ``gramian`` over N = ``window_length`` steps), so the information forgotten per step,
        (1 - lambda_k) J, never exceeds what arrives on average. Treated as a constant by
        gradients."""
        if self.forgetting == 1:
            return 1.0
        L = cholesky(info)
        rate = gramian / window_length
        whitened = solve_triangular(L, solve_triangular(L, rate, lower=True).T, lower=True)
        mu = excitation.smallest_eigenvalue(jax.lax.stop_gradient(symmetrize(whitened)))
        return jnp.maximum(self.forgetting, 1 - mu)

    def step(self, model: DiscreteLTV, state: DiscreteState, k, y, u, key=None):
        F, B, H = model.matrices(k)
        n = F.shape[-1]
        # NaN entries of y_k are not measured: their rows of H drop out, their innovations are 0
        measured = masked_measurement(y, mv(H, state.x_pred), H, self.R)
        H, e = measured.H, measured.innovation
        HP = mm(H, state.P_pred)
        S_factor = cholesky(mm(HP, H.T) + measured.R)
        K = cho_solve_lower(S_factor, HP).T
        I_KH = jnp.eye(n, dtype=F.dtype) - mm(K, H)
        P = symmetrize(mm(I_KH, state.P_pred))
        Omega = mm(H, state.Ups_pred)
        S_inv_Omega = cho_solve_lower(S_factor, Omega)
        increment = symmetrize(mm(Omega.T, S_inv_Omega))  # the information y_k carries about theta
        window = excitation.push(state.window, increment)
        L0 = state.prior_factor
        gramian = excitation.gramian(window)
        level = excitation.smallest_eigenvalue(jax.lax.stop_gradient(L0.T @ gramian @ L0))
        not_excited = excitation.excitation_status(window, level, self.excitation_threshold)
        info = state.theta_info + increment
        if self.forgetting != 1:  # bounded forgetting towards the prior information J_0
            lam = self.forgetting_factor(state.theta_info, gramian, window.increments.shape[0])
            info = lam * state.theta_info + (1 - lam) * chol_inverse(L0) + increment
        info = symmetrize(info)
        gain = cho_solve_lower(cholesky(info), S_inv_Omega.T)  # J^-1 Omega^T S^-1
        theta = state.theta + mv(gain, e)
        Ups = mm(I_KH, state.Ups_pred)
        x = state.x_pred + mv(K, e) + mv(Ups, theta - state.theta)
        status = check_finite_status(x, theta, P, info) | not_excited
        Phi = model.phi(k, u, y)
        new = DiscreteState(
            x_pred=mv(F, x) + mv(B, u) + mv(Phi, theta),
            P_pred=symmetrize(mm(mm(F, P), F.T) + self.Q),
            theta=theta,
            Ups_pred=mm(F, Ups) + Phi,
            theta_info=info,
            prior_factor=state.prior_factor,
            window=window,
        )
        return new, AdaptiveOutput(x, theta, Ups, e, level, status)

    def result(self, outputs: AdaptiveOutput, final_state) -> AdaptiveResult:
        return adaptive_result(outputs, final_state)


class ClosedLoopRun(eqx.Module):
    """Truth (``states``, ``observations`` as measured, ``inputs`` applied) and the estimates."""

    states: Float[Array, "T n"]
    observations: Float[Array, "T m"]
    inputs: Float[Array, "T l"]
    estimate: AdaptiveResult


@working_precision_by_default
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
    ``step`` is the one :func:`jaxest.run` drives, so re-running it open loop on
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
        k, r, v = args
        t = observer.time(k)
        _, _, C = model.matrices(t)
        y_true = C @ x
        y = y_true + v
        u = -feedback_gain @ obs.x + r
        x_next = propagate(x, u, y_true, theta, t)
        obs, out = observer.step(model, obs, k, y, u)
        return (x_next, obs), (x, y, u, out)

    steps = jnp.arange(T)
    (_, final), (xs, ys, us, outs) = jax.lax.scan(
        body, (jnp.asarray(x0, dtype), state), (steps, reference, noise)
    )
    return ClosedLoopRun(xs, ys, us, observer.result(outs, final))
