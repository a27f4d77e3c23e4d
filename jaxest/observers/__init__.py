"""Observers: Zhang's adaptive observer for MIMO LTV systems (continuous and discrete forms)."""

from jaxest.observers.adaptive import (
    AdaptiveObserver,
    AdaptiveOutput,
    AdaptiveResult,
    ClosedLoopRun,
    ContinuousLTV,
    DiscreteAdaptiveObserver,
    DiscreteLTV,
    InputEffectiveness,
    ObserverPrior,
    simulate_closed_loop,
)
from jaxest.observers.excitation import ObserverStatus

__all__ = [
    "AdaptiveObserver",
    "AdaptiveOutput",
    "ObserverStatus",
    "AdaptiveResult",
    "ClosedLoopRun",
    "ContinuousLTV",
    "DiscreteAdaptiveObserver",
    "DiscreteLTV",
    "InputEffectiveness",
    "ObserverPrior",
    "simulate_closed_loop",
]
