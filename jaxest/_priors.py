"""Priors on the state at the first measurement time."""

from __future__ import annotations

import equinox as eqx
from jaxtyping import Array, Float


class Gaussian(eqx.Module):
    """A Gaussian prior N(mean, cov) on the state at the first measurement."""

    mean: Float[Array, " n"]
    cov: Float[Array, "n n"]
