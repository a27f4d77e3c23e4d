"""The example of §4 of the fixed-interval Wiener smoother paper (Sun & Cui, 2003), eq 25.

x(t+1) = Phi x(t) + Gamma w(t), y(t) = H x(t) + v(t), Q = R = 1, x(0) = 0, N = 300, with

    Phi = [[0.2, 0.1], [0, 1]],  Gamma = [1, 1]^T,  H = [1, 0].

``PAPER`` holds the printed numbers (docs/papers/wiener.md confirms them; the adjugate term of eq 28 is the
exception, see ``PRINTED_ADJ_K``).
"""

from __future__ import annotations

import jax.numpy as jnp

from jaxest.models import LinearGaussian

__all__ = ["N", "ARBITRARY_START", "PAPER", "PRINTED_ADJ_K", "paper_model"]

N = 300  #: the fixed interval [0, N]
ARBITRARY_START = ((10.0, 20.0), (10.0, 20.0))  #: the paper's x(0|300) = x(1|300) = [10, 20]

#: The numbers printed in §4 (eqs 26-28 and the text), to their printed decimals.
PAPER = {
    "Sigma": [[1.0788, 1.4418], [1.4418, 4.0309]],
    "K": [0.5190, 0.6936],
    "eigenvalues": [0.9226, 0.1043],
    "ar_coeffs": [1.0, -1.2, 0.2],
    "ma_coeffs": [1.0, -1.0269, 0.0962],
    "smoother_transition": [[0.0269, -0.6936], [0.1, 1.0]],  # (I - K H)^T Phi^T
    "innovation_gain": [0.4810, 0.0],  # H^T / Q_eps
}

#: Eq 28 prints adj(I - q^-1 Psi_f) K = [0.5190 - 0.5163 q^-1, 0.6936 + 0.0053 q^-1]^T. The q^-1
#: coefficients are what one gets with the signs of the adjugate's off-diagonal entries flipped;
#: the true ones are [-0.4496, -0.1387] (only they make A(q^-1) = 1 - 1.2 q^-1 + 0.2 q^-2 of eq 26).
PRINTED_ADJ_K = [[0.5190, 0.6936], [-0.5163, 0.0053]]


def paper_model(dtype=None) -> LinearGaussian:
    """The model of eq 25 (float64 when x64 is on, unless ``dtype`` says otherwise)."""
    a = lambda v: jnp.asarray(v, dtype)
    return LinearGaussian(
        F=a([[0.2, 0.1], [0.0, 1.0]]),
        H=a([[1.0, 0.0]]),
        Q=a([[1.0]]),
        R=a([[1.0]]),
        G=a([[1.0], [1.0]]),
    )
