"""State-space models as equinox Modules (pytrees: they ``vmap``, ``jit`` and differentiate).

Discrete time, k = 0, 1, ..., T-1::

    x_{k+1} = f(x_k, u_k, k) + G_k w_k      (or f(x_k, u_k + w_k, k): noise on the measured input)
    y_k     = h(x_k, u_k, k) + v_k,          w_k ~ N(0, Q_k),  v_k ~ N(0, R_k)

The protocol estimators read a model through (never through its attributes) is
:class:`AbstractGaussianModel`: a deterministic part, ``f`` and ``h``, apart from the noise
description, ``process_noise`` (G, Q) and ``measurement_cov`` (R). From those four methods it
derives what the filters ask at a linearisation point ``x`` --

- ``transition(x, u, k) -> (f(x, u, k), F, G, Q)``  with F = df/dx (by ``jax.linearize``);
- ``observation(x, u, k) -> (h(x, u, k), H, R)``    with H = dh/dx;

-- and the samplers :func:`simulate` uses. A user's own model subclasses it and writes the four
methods; :class:`LinearGaussian` and :class:`NonlinearGaussian` are the built-in ones.
"""

from __future__ import annotations

import abc
import inspect
import operator
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from jaxest._priors import Gaussian
from jaxest._status import StatusOverSteps, finite_status
from jaxest.linalg import (
    after,
    factor_psd_or_nan,
    mv,
    symmetrize,
    working_precision_by_default,
)


def at_time(matrix: Array, k, ndim: int = 2) -> Array:
    """``matrix[k]`` if it carries a leading time axis (ndim + 1 dims), else ``matrix``."""
    return matrix[k] if matrix.ndim == ndim + 1 else matrix


def noise_cov(cov: Array, k) -> Array:
    """The covariance ``cov`` (at step ``k`` if it carries a time axis), as its symmetric part.
    A covariance is symmetric; the argument checks refuse one that is not, but under ``jit``
    its values are not known, and the filters read a non-symmetric one differently (those that
    factor it took its lower triangle, the Kalman filter the symmetric part of S), each with
    status OK. For a symmetric ``cov`` this is ``cov`` itself, to the bit; a non-square one is
    returned as it is, for the argument checks to name."""
    cov = at_time(cov, k)
    square = cov.ndim >= 2 and cov.shape[-1] == cov.shape[-2]
    return symmetrize(cov) if square else cov


def jacobian_by_linearize(fn: Callable, x) -> tuple[Array, Array]:
    """``fn(x)`` and its Jacobian, from one ``jax.linearize`` (the primal is computed once)."""
    value, jvp = jax.linearize(fn, x)
    eye = jnp.eye(x.shape[0], dtype=x.dtype)
    return value, jax.vmap(jvp, out_axes=-1)(eye)


class AbstractGaussianModel(eqx.Module):
    """A model with Gaussian noise, read by every Gaussian filter through these methods.

    Subclasses implement :meth:`f`, :meth:`h`, :meth:`process_noise` and
    :meth:`measurement_cov`; Jacobians come from ``jax.linearize`` unless a subclass overrides
    :meth:`transition_jacobian` / :meth:`observation_jacobian`. ``u`` is ``None`` without inputs.
    """

    @abc.abstractmethod
    def f(self, x, u=None, k=0):
        """The deterministic transition f(x_k, u_k, k)."""

    @abc.abstractmethod
    def h(self, x, u=None, k=0):
        """The deterministic measurement h(x_k, u_k, k)."""

    @abc.abstractmethod
    def process_noise(self, x, u, k) -> tuple[Array, Array]:
        """(G, Q): the noise gain at (x, u) and the covariance of w_k."""

    @abc.abstractmethod
    def measurement_cov(self, k) -> Array:
        """R_k, the covariance of v_k."""

    def transition_jacobian(self, x, u, k) -> tuple[Array, Array]:
        """f(x, u, k) and F = df/dx."""
        return jacobian_by_linearize(lambda z: self.f(z, u, k), x)

    def observation_jacobian(self, x, u, k) -> tuple[Array, Array]:
        """h(x, u, k) and H = dh/dx."""
        return jacobian_by_linearize(lambda z: self.h(z, u, k), x)

    def transition(self, x, u, k):
        """(f(x, u, k), F, G, Q): what a filter's time update needs."""
        mean, F = self.transition_jacobian(x, u, k)
        G, Q = self.process_noise(x, u, k)
        return mean, F, G, Q

    def observation(self, x, u, k):
        """(h(x, u, k), H, R): what a filter's measurement update needs."""
        mean, H = self.observation_jacobian(x, u, k)
        return mean, H, self.measurement_cov(k)

    def sample_transition(self, x, u, k, w):
        """x_{k+1} for the process-noise draw w ~ N(0, Q_k)."""
        G, _ = self.process_noise(x, u, k)
        return self.f(x, u, k) + G @ w

    def sample_observation(self, x, u, k, v):
        """y_k for the measurement-noise draw v ~ N(0, R_k)."""
        return self.h(x, u, k) + v


class LinearGaussian(AbstractGaussianModel):
    """x_{k+1} = F x_k + B u_k + G w_k,  y_k = H x_k + D u_k + v_k.

    Any matrix may carry a leading time axis (shape (T, ...)) for a time-varying model. ``G``
    defaults to the identity (then Q is n x n); ``B``, ``D`` default to no input. The filters
    read Q and R as their symmetric parts (:func:`noise_cov`).
    """

    F: Float[Array, "*T n n"]
    H: Float[Array, "*T m n"]
    Q: Float[Array, "*T q q"]
    R: Float[Array, "*T m m"]
    G: Float[Array, "*T n q"] | None = None
    B: Float[Array, "*T n p"] | None = None
    D: Float[Array, "*T m p"] | None = None

    def f(self, x, u=None, k=0):
        mean = mv(at_time(self.F, k), x)
        if self.B is not None and u is not None:
            mean = mean + mv(at_time(self.B, k), u)
        return mean

    def h(self, x, u=None, k=0):
        mean = mv(at_time(self.H, k), x)
        if self.D is not None and u is not None:
            mean = mean + mv(at_time(self.D, k), u)
        return mean

    def process_noise(self, x, u, k):
        n = self.F.shape[-1]
        G = jnp.eye(n, dtype=self.F.dtype) if self.G is None else at_time(self.G, k)
        return G, noise_cov(self.Q, k)

    def measurement_cov(self, k):
        return noise_cov(self.R, k)

    def transition_jacobian(self, x, u, k):
        return self.f(x, u, k), at_time(self.F, k)

    def observation_jacobian(self, x, u, k):
        return self.h(x, u, k), at_time(self.H, k)


def call_with_optional(fn: Callable, x, u, k):
    """``fn(x)``, ``fn(x, u)`` or ``fn(x, u, k)``, whichever ``fn`` takes."""
    try:
        params = inspect.signature(fn).parameters.values()
    except (TypeError, ValueError):  # builtins without a signature: give everything
        return fn(x, u, k)
    if any(p.kind is p.VAR_POSITIONAL for p in params):
        return fn(x, u, k)
    positional = [p for p in params if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
    return fn(*(x, u, k)[: max(1, min(3, len(positional)))])


class NonlinearGaussian(AbstractGaussianModel):
    """x_{k+1} = f(x_k, u_k) + G(x_k, u_k) w_k,  y_k = h(x_k, u_k) + v_k.

    ``f`` and ``h`` are written in ``jax.numpy`` and take ``(x)``, ``(x, u)`` or ``(x, u, k)``
    (``u`` is ``None`` without inputs). Their Jacobians come from ``jax.linearize`` unless
    ``jac_f`` / ``jac_h`` (same arguments) are given. Make ``f``/``h`` equinox Modules to let
    gradients reach their parameters.

    Process noise enters in one of three ways:

    - ``noise_gain=None``: additive, G = I (Q is n x n);
    - ``noise_gain=callable``: G(x, u) (Q is q x q);
    - ``noise_on_input=True``: the measured input is noisy, x_{k+1} = f(x_k, u_k + w_k), so
      G = df/du at (x, u) and Q is the covariance of the input noise (eq 27 of the SVD-EKF paper).

    ``Q`` and ``R`` may carry a leading time axis; the filters read them as their symmetric
    parts (:func:`noise_cov`).
    """

    transition_fn: Callable
    observation_fn: Callable
    Q: Float[Array, "*T q q"]
    R: Float[Array, "*T m m"]
    noise_gain: Callable | None = None
    noise_on_input: bool = eqx.field(static=True, default=False)
    jac_f: Callable | None = None
    jac_h: Callable | None = None

    def __init__(self, f, h, Q, R, noise_gain=None, noise_on_input=False, jac_f=None, jac_h=None):
        self.transition_fn, self.observation_fn, self.Q, self.R = f, h, Q, R
        self.noise_gain, self.noise_on_input = noise_gain, noise_on_input
        self.jac_f, self.jac_h = jac_f, jac_h

    def __check_init__(self):
        if self.noise_on_input and self.noise_gain is not None:
            raise ValueError("noise_gain: give either noise_gain or noise_on_input=True, not both")

    def f(self, x, u=None, k=0):
        return call_with_optional(self.transition_fn, x, u, k)

    def h(self, x, u=None, k=0):
        return call_with_optional(self.observation_fn, x, u, k)

    def process_noise(self, x, u, k):
        Q = noise_cov(self.Q, k)
        if self.noise_on_input:
            G = jax.jacfwd(lambda v: self.f(x, v, k))(u)
        elif self.noise_gain is not None:
            G = call_with_optional(self.noise_gain, x, u, k)
        else:
            G = jnp.eye(x.shape[0], dtype=jnp.result_type(x, Q))
        return G, Q

    def measurement_cov(self, k):
        return noise_cov(self.R, k)

    def transition_jacobian(self, x, u, k):
        if self.jac_f is None:
            return super().transition_jacobian(x, u, k)
        return self.f(x, u, k), call_with_optional(self.jac_f, x, u, k)

    def observation_jacobian(self, x, u, k):
        if self.jac_h is None:
            return super().observation_jacobian(x, u, k)
        return self.h(x, u, k), call_with_optional(self.jac_h, x, u, k)

    def sample_transition(self, x, u, k, w):
        if self.noise_on_input:
            return self.f(x, u + w, k)
        return super().sample_transition(x, u, k, w)


class Simulation(StatusOverSteps):
    """Output of :func:`simulate`: true states x_0..x_{T-1}, measurements y_0..y_{T-1}, and each
    step's :class:`~jaxest.Status` bits: ``NONFINITE`` where the state or the measurement drawn
    is NaN or infinite. Under ``jit`` the argument checks cannot see a covariance's values, and
    an indefinite one gives NaN draws; a filter would then read a NaN measurement as a missing
    one, without a word."""

    states: Float[Array, "T n"]
    observations: Float[Array, "T m"]
    status: Int[Array, " T"]

    @property
    def y(self):
        return self.observations


def gaussian_noise(key, cov):
    """Default noise sampler: one draw of N(0, cov) for a positive semidefinite cov,
    :func:`psd_root` (cov) z."""
    z = jax.random.normal(key, cov.shape[:1], dtype=cov.dtype)
    return psd_root(cov) @ z


def psd_root(cov):
    """S with S S^T = cov for a positive semidefinite cov: chol(cov), or, where cov is singular
    and has no Cholesky factor (a noise that drives some states only, Q = 0), U diag(D) from
    its symmetric eigendecomposition; the Cholesky factor alone gave NaN draws. An indefinite
    cov gives NaN (:func:`~jaxest.linalg.factor_psd_or_nan`)."""
    chol = jnp.linalg.cholesky(cov)

    def semidefinite_root():
        # after the Cholesky factor: two batched LAPACK calls at once can deadlock jaxlib 0.10
        U, D = factor_psd_or_nan(after(cov, chol))
        return U * D

    return jax.lax.cond(jnp.all(jnp.isfinite(chol)), lambda: chol, semidefinite_root)


def check_inputs_used(model, inputs):
    """Raise ``ValueError`` where ``inputs`` are given to a linear model without B and D, which
    would ignore them (a user who forgot B would get estimates without the inputs' effect), or
    where B (n x p) or D (m x p) does not fit the state, the measurements or the inputs' width
    p: the products would broadcast a size 1 (B of one column took the sum of two inputs)."""
    linear = isinstance(model, LinearGaussian)
    if inputs is not None and linear and model.B is None and model.D is None:
        raise ValueError(
            "inputs: the model has no input matrices (model.B and model.D are None), so the "
            "inputs would be ignored; give LinearGaussian(..., B=...) or drop inputs"
        )
    if inputs is None and linear and (model.B is not None or model.D is not None):
        raise ValueError(
            "inputs: the model has input matrices (model.B or model.D) but no inputs were given, "
            "so they would be ignored; pass inputs (zeros for none) or build the model without them"
        )
    if linear and inputs is not None and len(np.shape(inputs)) != 2:
        raise ValueError(
            f"inputs: a linear model's inputs are a (T, p) array (B u_k), got shape "
            f"{jax.tree.map(np.shape, inputs)}"
        )
    if not linear or inputs is None:
        return
    for name, rows in (("B", "F"), ("D", "H")):
        matrix = getattr(model, name)
        expected = (jnp.shape(getattr(model, rows))[-2], jnp.shape(inputs)[-1])
        if matrix is not None and jnp.shape(matrix)[-2:] != expected:
            raise ValueError(
                f"model.{name}: expected trailing shape {expected} (rows of model.{rows}, the "
                f"inputs' width), got {jnp.shape(matrix)}"
            )


def check_time_axis(name: str, matrix, first: int, count: int, ndim: int = 2) -> None:
    """Raise ``ValueError`` where ``matrix``, if it carries a leading time axis (ndim + 1 dims,
    read by :func:`at_time`), does not cover the steps ``first`` .. ``first + count - 1`` that a
    run or a simulation reads: JAX clamps an index past the end, so those steps would silently
    reuse the last matrix."""
    if matrix is None or callable(matrix) or jnp.ndim(matrix) != ndim + 1:
        return
    if jnp.shape(matrix)[0] >= first + count:
        return
    steps = (
        f"the {count} measurements"
        if first == 0
        else f"steps {first}..{first + count - 1} (k0 = {first}, {count} measurements)"
    )
    raise ValueError(f"{name}: time-varying with {jnp.shape(matrix)[0]} steps, fewer than {steps}")


def check_time_axes(model, first: int, count: int) -> None:
    """:func:`check_time_axis` for the matrices of a built-in model."""
    if isinstance(model, LinearGaussian):
        names = ("F", "H", "Q", "R", "G", "B", "D")
    elif isinstance(model, NonlinearGaussian):
        names = ("Q", "R")
    else:
        return
    for name in names:
        check_time_axis(f"model.{name}", getattr(model, name), first, count)


@working_precision_by_default
def simulate(
    model: AbstractGaussianModel,
    x0,
    num_steps: int,
    key,
    *,
    inputs=None,
    process_noise: Callable = gaussian_noise,
    measurement_noise: Callable = gaussian_noise,
) -> Simulation:
    """Draw a true trajectory and its measurements from ``model``.

    ``x0`` is the initial state, or a :class:`~jaxest.Gaussian` to draw it from. The noise
    samplers take ``(key, cov)`` and return one draw (default: Gaussian); pass, e.g., a uniform
    sampler for bounded noise. ``inputs`` has a leading time axis of length ``num_steps``.

    Compiled as one program (``equinox.filter_jit``; ``num_steps``, the samplers and the model's
    functions are static), so a second call with arrays of the same shapes does not compile.
    Covariances whose values are known are checked here (``ValueError``); under ``jit`` a bad
    one shows in :attr:`Simulation.status` instead.
    """
    from jaxest._checks import (  # _checks imports this
        check_inputs,
        check_key,
        check_matrix,
        check_model_shapes,
        first_input,
        model_shapes,
    )

    try:
        steps = operator.index(num_steps)  # a Python, NumPy or concrete JAX integer
    except TypeError:
        raise ValueError(
            f"num_steps: expected an integer known before tracing (it sets the number of "
            f"steps), got {num_steps!r}"
        ) from None
    if steps < 0:
        raise ValueError(f"num_steps: must not be negative, got {steps}")
    check_key("key", key)  # JAX's own errors for an int seed or a batch of keys named none
    if not isinstance(x0, Gaussian):
        try:  # an initial state given as a list or a number, too
            x0 = jnp.asarray(x0)
        except (TypeError, ValueError) as err:
            raise ValueError(
                f"x0: expected an initial state (an array) or a jaxest.Gaussian, got "
                f"{type(x0).__name__}"
            ) from err
    start = x0.mean if isinstance(x0, Gaussian) else x0
    check_matrix("x0", start, ndim=1)  # finite
    if isinstance(model, LinearGaussian):
        check_matrix("model.F", model.F, square=True)
    if inputs is not None:
        check_inputs(inputs, steps, f"num_steps is {steps}")
    check_inputs_used(model, inputs)
    check_time_axes(model, 0, steps)
    if isinstance(model, LinearGaussian):
        n = model.F.shape[-1]
        if start.shape != (n,):
            raise ValueError(f"x0: expected shape ({n},) for the model's state, got {start.shape}")
        check_matrix("model.H", model.H, (None, n))
        if model.G is not None:
            check_matrix("model.G", model.G, (n, None))
        m, q = model.H.shape[-2], n if model.G is None else model.G.shape[-1]
        check_matrix("model.Q", model.Q, (q, q), psd=True)
        check_matrix("model.R", model.R, (m, m), psd=True)
    else:  # what its functions return (an f(x) of another size was broadcast into the state)
        if isinstance(model, NonlinearGaussian):
            check_matrix("model.Q", model.Q, psd=True)
            check_matrix("model.R", model.R, psd=True)
        u0 = None if inputs is None else jax.tree.map(first_input, inputs)
        check_model_shapes(model, model_shapes(model, start, u0, "x0"), start.shape[-1], "x0")
    if isinstance(x0, Gaussian):
        check_matrix("x0.cov", x0.cov, psd=True)
    return _simulate(model, x0, steps, key, inputs, process_noise, measurement_noise)


@eqx.filter_jit
def _simulate(model, x0, num_steps: int, key, inputs, process_noise, measurement_noise):
    key0, key = jax.random.split(key)
    if isinstance(x0, Gaussian):
        x0 = x0.mean + gaussian_noise(key0, x0.cov)
    keys = jax.random.split(key, (num_steps, 2))

    def body(x, args):
        k, (kw, kv), u = args
        v = measurement_noise(kv, model.measurement_cov(k))
        y = model.sample_observation(x, u, k, v)
        _, Q = model.process_noise(x, u, k)
        x_next = model.sample_transition(x, u, k, process_noise(kw, Q))
        return x_next, (x, y, finite_status(x, y))

    _, (states, ys, status) = jax.lax.scan(body, x0, (jnp.arange(num_steps), keys, inputs))
    return Simulation(states, ys, status)
