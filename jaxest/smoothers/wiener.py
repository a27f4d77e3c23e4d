"""The fixed-interval Wiener smoother in ARMA form (Sun & Cui, 2003, theorem, eqs 10-13).

Given y(0), ..., y(N), the smoother obeys the ARMA recursion (eq 10)

    Psi(q^-1) x(t|N) = adj(I - q^-1 Psi_f) K y(t) + sum_{i=1}^{N-t} K_i A(q^-1) y(t+i) + e_N(t)

(eqs 11-12 with K_i of eq 9), run forward for t = n..N from n initial values
x(0|N), ..., x(n-1|N) (n = deg Psi = the state dimension; a singular Psi_f just gives trailing
zero coefficients). The sum is the backward recursion of
:func:`~jaxest.smoothers.steady_state.backward_gain_sum` applied to A(q^-1) y, so the whole
smoother costs O(N n^2) time and O(N n) memory.

The end term e_N(t) is not in the paper. Its proof (eq 16) moves Psi(q^-1) through
L_{N,t}(q^-1), whose number of terms N - t changes with t; doing the shift exactly leaves

    e_N(t) = Sigma M^{N-t} v_N,  v_N = sum_{r=0}^{n-1} sum_{j=r+1}^{n} psi_j M^{j-r} H^T Q_eps^-1 eps(N-r)

with M = (I - K H)^T Phi^T, which needs the last n innovations. It decays like |lambda_max|^{N-t}:
negligible far from the end, of the size of the signal near it. :meth:`WienerSmoother.smooth`
adds it from ``final_innovations`` (then eq 10 reproduces eq 15 exactly); the argument is required,
and only an explicit ``None`` runs the theorem as printed. It enters as the terminal value of the backward recursion.

With the optimal initial values (the steady-state smoother of eq 15 at t < n) the smoother equals
eq 15; any other start adds delta(t) with Psi(q^-1) delta(t) = 0 (eq 17), a mix of lambda_i^t over
the eigenvalues of Psi_f (eq 19). :meth:`WienerSmoother.eq13_initial_values` picks the last k
initial values so that the k eigenvalues near the unit circle drop out of delta (eq 13).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxest._checks import (
    check_complete,
    check_flag,
    check_gaussian_prior,
    check_matrix,
    check_measurements,
    check_precision,
)
from jaxest._priors import Gaussian
from jaxest.filters.steady_state import SteadyStateGain, steady_state_gain
from jaxest.linalg import working_precision_by_default
from jaxest.models import LinearGaussian
from jaxest.smoothers.steady_state import (
    ArmaInnovationModel,
    SteadyStateSmootherResult,
    arma_innovation_model,
    backward_gain_sum,
    steady_state_smooth,
)


def lagged_sum(
    coeffs: Float[Array, "d a b"], signal: Float[Array, "T b"]
) -> Float[Array, "T-d+1 a"]:
    """sum_{j=0}^{d-1} coeffs[j] signal(t - j) for t = d-1, ..., T-1 (a matrix polynomial in q^-1
    applied where all its lags exist)."""
    d, T = coeffs.shape[0], signal.shape[0]
    return sum(signal[d - 1 - j : T - j] @ coeffs[j].T for j in range(d))


#: :meth:`WienerSmoother.smooth` raises where :meth:`WienerSmoother.rounding_error` exceeds this
ROUNDING_TOLERANCE = 1e-3
_INACCURATE = (
    "WienerSmoother.smooth: rounding in the ARMA recursion (eq 10) would leave x(t|N) with an "
    f"estimated relative error above {ROUNDING_TOLERANCE:g} (or NaN: the steady-state gain has "
    "no accurate solution). It happens where Psi_f's eigenvalues cluster near the unit circle; "
    "jaxest.steady_state_smooth computes the same estimate stably "
    "(WienerSmoother.rounding_error gives the estimate)."
)


class WienerSmoother(eqx.Module):
    """The fixed-interval Wiener smoother of a time-invariant linear model (build it with
    :meth:`from_model`; it is a pytree, so it ``vmap``s and differentiates)."""

    model: LinearGaussian
    gain: SteadyStateGain
    arma: ArmaInnovationModel

    @classmethod
    def from_model(cls, model: LinearGaussian) -> WienerSmoother:
        """Lemmas 1-2: the steady-state gain and the ARMA innovation model of ``model``."""
        gain = steady_state_gain(model)
        return cls(model, gain, arma_innovation_model(gain))

    @property
    def order(self) -> int:
        """n_d = n, the number of initial values the recursion needs."""
        return self.arma.ma.shape[0] - 1

    def eigenvalues(self) -> Array:
        """The eigenvalues lambda_i of Psi_f (the roots of z^n Psi(1/z)), by decreasing modulus."""
        lam = jnp.linalg.eigvals(self.gain.Psi_f)
        return lam[jnp.argsort(-jnp.abs(lam))]

    def end_term(self, final_innovations: Float[Array, "n m"]) -> Float[Array, " n"]:
        """v_N of the module docstring from eps(N-n+1), ..., eps(N) (oldest first)."""
        n, psi = self.order, self.arma.ma
        M, Hq = self.gain.smoother_transition, self.gain.innovation_gain
        powers = [M @ Hq]  # M^p H^T Q_eps^-1, p = 1..n
        for _ in range(n - 1):
            powers.append(M @ powers[-1])
        v = jnp.zeros(n, final_innovations.dtype)
        for r in range(n):
            coeff = sum(psi[p + r] * powers[p - 1] for p in range(1, n - r + 1))
            v = v + coeff @ final_innovations[n - 1 - r]
        return v

    @eqx.filter_jit
    def smooth(
        self,
        ys: Float[Array, "T m"],
        initial_values: Float[Array, "n n"],
        final_innovations: Float[Array, "n m"] | None,
    ) -> Float[Array, "T n"]:
        """Eq 10: x(t|N) for t = 0..N (T = N + 1 samples), started from
        ``initial_values`` = x(0|N), ..., x(n-1|N).

        ``final_innovations`` is required: the steady-state filter's eps(N-n+1..N) (the second
        value of :meth:`optimal_start`) include the end term, and the result is exact; ``None``
        asks for the theorem as printed, which is off near t = N by the end term (of the size of
        the signal there).

        Raises (``eqx.error_if``, under ``jit`` too) where :meth:`rounding_error` exceeds
        ``ROUNDING_TOLERANCE`` or is NaN: the recursion would return finite numbers without
        accurate digits."""
        n, psi = self.order, self.arma.ma
        if ys.shape[0] <= n + 1:
            raise ValueError(f"ys: need more than {n + 1} samples, got {ys.shape[0]}")
        filtered_part = lagged_sum(jnp.einsum("jab,bm->jam", self.arma.adj, self.gain.K), ys)[1:]
        arma_output = lagged_sum(self.arma.ar, ys)  # A(q^-1) y(s), s = n..N
        end = None if final_innovations is None else self.end_term(final_innovations)
        forcing = filtered_part + backward_gain_sum(self.gain, arma_output, end)  # eqs 11-12

        def body(past, b):  # past[j] = x(t-1-j|N)
            x = b - psi[1:] @ past
            return jnp.concatenate([x[None], past[:-1]]), x

        _, xs = jax.lax.scan(body, initial_values[::-1], forcing)
        xs = jnp.concatenate([initial_values, xs])
        return eqx.error_if(
            xs, ~(self.rounding_error(ys.shape[0]) <= ROUNDING_TOLERANCE), _INACCURATE
        )

    def rounding_error(self, num_samples: int) -> Float[Array, ""]:
        """An estimate of the relative error rounding leaves in x(t|N) over ``num_samples``
        samples: e ||h||_1 ||psi||_1, h the impulse response of 1 / Psi(q^-1) over the record.
        Eq 10 runs x(t|N) = b(t) - sum_j psi_j x(t-j|N), so each step's relative error e (of
        order e ||psi||_1 |x|) reaches every later x through h. With the eigenvalues of
        Psi_f clustered near the unit circle h grows like t^(n-1) lambda^t first: n = 6 at
        0.999 gives ||h||_1 ~ 1e16 over 3000 samples and no correct digit in float64, while the
        steady-state smoother, the same estimate, stays exact (docs/papers/wiener.md,
        "Rounding in the ARMA recursion"). NaN where the gain is (no accurate Riccati solution).

        e is eps, or the error of the coefficients psi and adj(I - Psi_f q^-1) where that is
        larger: Faddeev-LeVerrier (:func:`characteristic_polynomial`) loses digits where Psi_f is
        far from normal, and its Cayley-Hamilton residual, |Psi_f B_{n-1} + psi_n I| relative
        to |Psi_f B_{n-1}| + n |psi_n| (zero in exact arithmetic), measures how many. With eps
        alone the estimate was 2 to 5.7e6 times below the error for F with eigenvectors of
        condition 1e4-3e6, and a float32 result 0.8 % off passed under the tolerance."""
        n, psi, adj = self.order, self.arma.ma, self.arma.adj

        def impulse(past, _):  # past[j] = h(t-1-j)
            h = -psi[1:] @ past
            return jnp.concatenate([h[None], past[:-1]]), h

        unit = jnp.zeros(n, psi.dtype).at[0].set(1.0)  # h(0) = 1
        _, h = jax.lax.scan(impulse, unit, None, length=num_samples - 1)
        h_norm = 1 + jnp.sum(jnp.abs(h))
        last = self.gain.Psi_f @ adj[-1]  # Psi_f B_{n-1} = -psi_n I in exact arithmetic
        residual = jnp.sum(jnp.abs(last + psi[-1] * jnp.eye(n, dtype=psi.dtype)))
        coefficient_error = residual / (jnp.sum(jnp.abs(last)) + n * jnp.abs(psi[-1]))
        relative = jnp.maximum(jnp.finfo(psi.dtype).eps, coefficient_error)
        return relative * h_norm * jnp.sum(jnp.abs(psi))

    @eqx.filter_jit
    def optimal_start(
        self, ys: Float[Array, "T m"], prior_mean: Float[Array, " n"]
    ) -> tuple[Float[Array, "n n"], Float[Array, "n m"]]:
        """The optimal initial values x^o(0|N), ..., x^o(n-1|N) (eqs 8-9 / 15) and the final
        innovations eps(N-n+1), ..., eps(N) of the end term, from one pass of the steady-state
        smoother with the filter started at x(0|-1) = ``prior_mean``."""
        prior = Gaussian(prior_mean, self.gain.Sigma)
        return self.start_from(steady_state_smooth(self.model, ys, prior=prior, gain=self.gain))

    def start_from(
        self, steady: SteadyStateSmootherResult
    ) -> tuple[Float[Array, "n n"], Float[Array, "n m"]]:
        """:meth:`optimal_start` read off a steady-state smoother result already at hand."""
        return steady.mean[: self.order], steady.innovation[-self.order :]

    @eqx.filter_jit
    def eq13_initial_values(
        self, arbitrary: Float[Array, "n n"], optimal: Float[Array, "n n"], radius: float = 0.5
    ) -> Float[Array, "n n"]:
        """Eq 13: keep the first n - k of the ``arbitrary`` initial values and set the last k so
        that the k eigenvalues of Psi_f with |lambda| > ``radius`` (near the unit circle) vanish
        from delta(t) = x(t|N) - x^o(t|N).

        delta then has to lie in the span of lambda_i^t over the n - k far eigenvalues, i.e.
        solve Psi_far(q^-1) delta(t) = 0 with Psi_far(z) = prod_far (1 - lambda_i z); the last k
        initial deltas are that recursion continued from the first n - k. For distinct real
        eigenvalues this is the Vandermonde solution of eqs 21-23; it equally covers repeated
        far eigenvalues (then t lambda^t terms stay, as they must) and complex pairs (a pair is
        near or far together, so Psi_far is real). All traced: ``radius`` may change under jit.
        """
        n = self.order
        lam = jnp.linalg.eigvals(self.gain.Psi_f)
        far = jnp.abs(lam) <= radius
        psi_far = jnp.ones((1,), lam.dtype)
        for root in jnp.where(far, lam, 0.0):  # near roots contribute the factor 1
            psi_far = jnp.convolve(psi_far, jnp.stack([jnp.ones_like(root), -root]))
        psi_far = psi_far.real.astype(arbitrary.dtype)
        free = jnp.sum(far)  # n - k
        deltas = []
        for t in range(n):
            continued = -sum(
                (psi_far[l] * deltas[t - l] for l in range(1, t + 1)), jnp.zeros(n, arbitrary.dtype)
            )
            deltas.append(jnp.where(t < free, arbitrary[t] - optimal[t], continued))
        return optimal + jnp.stack(deltas)


@working_precision_by_default
def wiener_smooth(
    model: LinearGaussian,
    ys: Float[Array, "T m"],
    *,
    prior: Gaussian | None = None,
    initial_values: Float[Array, "n n"] | None = None,
    start: str = "optimal",
    radius: float = 0.5,
    end_term: bool = True,
) -> Float[Array, "T n"]:
    """x(t|N), t = 0..N, by the fixed-interval Wiener smoother (eq 10), started

    - ``start="arbitrary"``: from ``initial_values`` as given;
    - ``start="optimal"``: from the optimal values (eq 15 with the filter started at
      x(0|-1) = ``prior.mean``), so it equals the steady-state smoother;
    - ``start="eq13"``: from ``initial_values`` with the last k replaced by eq 13.

    ``end_term=False`` runs the theorem as printed (see the module docstring). Everything but
    ``start="arbitrary", end_term=False`` needs ``prior`` (one steady-state smoother pass, which
    uses ``prior.mean`` only: see :func:`~jaxest.steady_state_smooth`).
    """
    if start not in ("arbitrary", "optimal", "eq13"):
        raise ValueError(f"start: expected 'arbitrary', 'optimal' or 'eq13', got {start!r}")
    check_flag("end_term", end_term)
    smoother = WienerSmoother.from_model(model)
    n, m = smoother.order, model.H.shape[0]
    if jnp.ndim(ys) != 2 or jnp.shape(ys)[1] != m:
        raise ValueError(f"ys: expected shape (T, {m}), got {jnp.shape(ys)}")
    check_measurements(ys)  # before optimal_start's jit, inside which the values are unknown
    check_complete(ys, "the Wiener smoother's lagged sums (eq 10) need every sample")
    if jnp.shape(ys)[0] <= n + 1:  # before optimal_start, which failed inside its trace
        raise ValueError(f"ys: need more than {n + 1} samples, got {jnp.shape(ys)[0]}")
    if start != "optimal":
        if initial_values is None or np.shape(initial_values) != (n, n):
            raise ValueError(
                f"initial_values: start={start!r} needs an ({n}, {n}) array x(0|N)..x({n - 1}|N)"
            )
        check_matrix("initial_values", initial_values, (n, n))  # an array, finite
        check_precision(model, ys, initial_values, name="initial_values")
    if start == "eq13" and not (isinstance(radius, int | float) and 0 < radius < 1):
        raise ValueError(f"radius: must be a number in (0, 1), got {radius!r}")
    if start == "arbitrary" and not end_term:
        return smoother.smooth(ys, initial_values, None)
    if prior is None:
        raise ValueError(f"prior: start={start!r} needs a Gaussian prior on x(0)")
    check_gaussian_prior(prior, n)
    check_precision(model, ys, prior)
    optimal, final_innovations = smoother.optimal_start(ys, prior.mean)
    x0 = {"arbitrary": initial_values, "optimal": optimal}.get(start)
    if start == "eq13":
        x0 = smoother.eq13_initial_values(initial_values, optimal, radius)
    return smoother.smooth(ys, x0, final_innovations if end_term else None)


__all__ = ["WienerSmoother", "lagged_sum", "wiener_smooth"]
