"""Smoothers: RTS for any Gaussian filter result."""

from jaxest.smoothers.rts import SmootherResult, rts_smooth

__all__ = ["SmootherResult", "rts_smooth"]
