"""jaxest: differentiable state estimation in JAX.

Every filter, smoother and observer is an equinox Module with a pure ``init``/``step`` pair that
``jit``s, ``vmap``s and differentiates; see :mod:`jaxest.run` for the protocol.
"""

from jaxest.models import LinearGaussian, NonlinearGaussian, Simulation, simulate
from jaxest.run import FilterResult, Gaussian, Status, filter, run

__all__ = [
    "FilterResult",
    "Gaussian",
    "LinearGaussian",
    "NonlinearGaussian",
    "Simulation",
    "Status",
    "filter",
    "run",
    "simulate",
]
