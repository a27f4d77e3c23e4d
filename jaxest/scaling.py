"""A model run on its state in other units, x = s * x~ (s > 0 per state), for filters in float32
on states whose sizes span many decades (docs/robustness.md, "The 23-state flight model in
float32").

A covariance whose variances span 10^11 (metres of altitude beside milliradians of gyro bias) has
directions that a float32 factorisation, which resolves about 1 / eps = 8.4e6, loses to
rounding; in units of the prior's standard deviations the same posterior is far better
conditioned. The estimate is the same in exact arithmetic: every Gaussian filter, smoother and
simulation is equivariant under this change of variables, and the likelihood p(y) and the
innovations do not change.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxest._priors import Gaussian
from jaxest.models import AbstractGaussianModel


class ScaledState(AbstractGaussianModel):
    """``model`` on the state x~ = x / s, with S = diag(s), s > 0:

    f~(x~, u, k) = f(s x~, u, k) / s,  F~ = S^-1 F S,  G~ = S^-1 G,
    h~(x~, u, k) = h(s x~, u, k),  H~ = H S,  Q and R unchanged.

    Its means and covariances are those of x / s; map them back with :meth:`state_mean` and
    :meth:`state_cov`, and give a prior in the new units with :meth:`scale_prior` (or build both
    with :func:`scale_state`). The Jacobians are the model's own (analytic where it gives them),
    rescaled. A gradient reaches the model's parameters as through the model itself. A wrapped
    :class:`~jaxest.LinearGaussian` is not one itself: what needs one (the Kalman filter's
    closed-form gradient, the parallel and steady-state filters, :func:`~jaxest.fit_em`) takes
    the model, or a LinearGaussian with S^-1 F S, H S, S^-1 G and S^-1 B built from it.
    """

    model: AbstractGaussianModel
    scale: Float[Array, " n"]  #: s, the size of one unit of x~ in the units of x, per state

    def __check_init__(self):
        if not isinstance(self.model, AbstractGaussianModel):
            raise ValueError(
                f"model: expected a Gaussian model (a subclass of jaxest.AbstractGaussianModel), "
                f"got {type(self.model).__name__}"
            )
        if jnp.ndim(self.scale) != 1:
            raise ValueError(f"scale: expected a vector (n,), got shape {jnp.shape(self.scale)}")
        if not isinstance(self.scale, jax.core.Tracer):
            scale = np.asarray(self.scale)
            if not np.all(np.isfinite(scale) & (scale > 0)):
                raise ValueError(f"scale: every entry must be positive and finite, got {scale}")

    @property
    def noise_on_input(self) -> bool:
        """The model's: whether its process noise enters through the input."""
        return getattr(self.model, "noise_on_input", False)

    def f(self, x, u=None, k=0):
        return self.model.f(self.scale * x, u, k) / self.scale

    def h(self, x, u=None, k=0):
        return self.model.h(self.scale * x, u, k)

    def process_noise(self, x, u, k):
        G, Q = self.model.process_noise(self.scale * x, u, k)
        return G / self.scale[:, None], Q

    def measurement_cov(self, k):
        return self.model.measurement_cov(k)

    def transition_jacobian(self, x, u, k):
        mean, F = self.model.transition_jacobian(self.scale * x, u, k)
        return mean / self.scale, F * self.scale / self.scale[:, None]

    def observation_jacobian(self, x, u, k):
        mean, H = self.model.observation_jacobian(self.scale * x, u, k)
        return mean, H * self.scale

    def sample_transition(self, x, u, k, w):
        return self.model.sample_transition(self.scale * x, u, k, w) / self.scale

    def sample_observation(self, x, u, k, v):
        return self.model.sample_observation(self.scale * x, u, k, v)

    def scale_prior(self, prior: Gaussian) -> Gaussian:
        """``prior`` on x, as a prior on x~ = x / s."""
        return Gaussian(prior.mean / self.scale, prior.cov / jnp.outer(self.scale, self.scale))

    def state_mean(self, mean: Float[Array, "*batch n"]) -> Float[Array, "*batch n"]:
        """Means of x~ (any leading axes: steps, runs) in the units of x: s x~."""
        return mean * self.scale

    def state_cov(self, cov: Float[Array, "*batch n n"]) -> Float[Array, "*batch n n"]:
        """Covariances of x~ (any leading axes) in the units of x: S P~ S, entry by entry, so
        nothing is factorised again in the working dtype."""
        return cov * self.scale[:, None] * self.scale


def scale_state(
    model: AbstractGaussianModel, prior: Gaussian, scale: Float[Array, " n"] | None = None
) -> tuple[ScaledState, Gaussian]:
    """``model`` and ``prior`` on the state in units of ``scale`` (:class:`ScaledState`); by
    default the prior's standard deviations, sqrt(diag(prior.cov)), so that the prior's
    covariance has a unit diagonal.

    Example, a float32 filter on a state of very different sizes (docs/robustness.md)::

        scaled_model, scaled_prior = je.scale_state(model, prior)
        result = je.run(je.ImprovedSVDKF(), scaled_model, ys, prior=scaled_prior)
        mean, cov = scaled_model.state_mean(result.mean), scaled_model.state_cov(result.cov)
    """
    if not isinstance(prior, Gaussian):
        raise ValueError(f"prior: expected a jaxest.Gaussian, got {type(prior).__name__}")
    if scale is None:
        variances = jnp.diagonal(prior.cov)
        if not isinstance(variances, jax.core.Tracer) and not np.all(np.asarray(variances) > 0):
            raise ValueError(
                f"prior: its variances {np.asarray(variances)} are not all positive, so they "
                f"give no scale to every state; give scale"
            )
        scale = jnp.sqrt(variances)
    if jnp.shape(scale) != jnp.shape(prior.mean):
        raise ValueError(
            f"scale: has shape {jnp.shape(scale)}, the prior's mean {jnp.shape(prior.mean)}"
        )
    scaled = ScaledState(model, jnp.asarray(scale, jnp.result_type(prior.mean)))
    return scaled, scaled.scale_prior(prior)


__all__ = ["ScaledState", "scale_state"]
