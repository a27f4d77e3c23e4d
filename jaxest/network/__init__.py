"""Network-structured optimal filter for continuous-time large-scale systems (Zhang & Dai).

- :mod:`~jaxest.network.structure`: the coupled system (eqs 1-3), the communication structure C(t)
  and the existence test of lemma 1;
- :mod:`~jaxest.network.design`: lemma 2 by SVD, the covariance ODEs 28-31 and the gains of step 4;
- :mod:`~jaxest.network.filter`: the filter of eq 9 on sampled data, on one device or sharded.
"""

from jaxest.network.design import (
    NetworkDesign,
    NetworkDesignStatus,
    SteadyState,
    centralized_steady_state,
    design,
    steady_state,
)
from jaxest.network.filter import NetworkFilter, NetworkResult, run_sharded
from jaxest.network.structure import (
    CommunicationStructure,
    LargeScaleSystem,
    check_existence,
    simulate_network,
)

__all__ = [
    "CommunicationStructure",
    "LargeScaleSystem",
    "NetworkDesign",
    "NetworkDesignStatus",
    "NetworkFilter",
    "NetworkResult",
    "SteadyState",
    "centralized_steady_state",
    "check_existence",
    "design",
    "run_sharded",
    "simulate_network",
    "steady_state",
]
