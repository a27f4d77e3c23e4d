"""Observers: Zhang's adaptive observer for MIMO LTV systems (continuous and discrete forms)."""

from jaxest.observers.adaptive import (
    AdaptiveObserver,
    AdaptiveResult,
    ClosedLoopRun,
    ContinuousLTV,
    DiscreteAdaptiveObserver,
    DiscreteLTV,
    InputEffectiveness,
    ObserverPrior,
    simulate_closed_loop,
)

__all__ = [
    "AdaptiveObserver",
    "AdaptiveResult",
    "ClosedLoopRun",
    "ContinuousLTV",
    "DiscreteAdaptiveObserver",
    "DiscreteLTV",
    "InputEffectiveness",
    "ObserverPrior",
    "simulate_closed_loop",
]
