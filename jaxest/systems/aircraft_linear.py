"""Linear aircraft models of Lungu, Lungu & Grigorie's adaptive-observer paper (eqs 33, 35).

Both are continuous time, x' = A x + B u. The paper names the states and the controls but not the
measured outputs nor how the unknown parameters enter; :func:`aircraft_observer_model` makes these
choices and documents them.

- Charlie, longitudinal motion (eq 33), states [V_hat, alpha, pitch angle, omega_y_hat], control
  the elevator deflection. Non-dimensional: the time is t_hat = t / tau_a with tau_a = 2.1 s
  (eq 34), so every time in this model is in units of tau_a.
- Boeing 747, lateral motion at Mach 0.8, 40,000 ft (eq 35), states [beta, r (yaw rate), p (roll
  rate), phi (roll angle)], controls [rudder, aileron], time in seconds. The OCR scan prints
  A[2, 0] = 0.305 (sign and decimal point lost: it makes the airframe unstable) and an aileron
  column [0, 0.123, 1.063, 0]; the published values (docs/papers/adaptive.md) are A[2, 0] = -3.05 and
  [0, 0.0077, 0.143, 0]. The published values are the default; ``printed=True`` gives the scan's.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "CHARLIE_TIME_UNIT_S", "CHARLIE_THETA", "B747_THETA", "charlie", "b747", "CHARLIE_OUTPUTS",
    "B747_OUTPUTS", "output_matrix", "aircraft",
]  # fmt: skip

#: tau_a of eq 34, seconds per unit of the Charlie model's non-dimensional time
CHARLIE_TIME_UNIT_S = 2.1

#: the parameter value the paper simulates for Charlie: theta = 2
CHARLIE_THETA = (2.0,)
#: the parameter values the paper simulates for the Boeing 747: theta = [0.9, 3]
B747_THETA = (0.9, 3.0)


def charlie() -> tuple[np.ndarray, np.ndarray]:
    """(A, B) of the Charlie longitudinal model, eq 33 as printed."""
    A = np.array(
        [
            [-0.026, 0.025, -0.1, 0.0],
            [-0.36, -3.0, 0.0, 1.0],
            [0.0, 0.0, 0.0, 1.0],
            [0.4212, -38.49, 0.0, -3.67],
        ]
    )
    B = np.array([[0.0], [0.0], [0.0], [1.0]])
    return A, B


def b747(printed: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(A, B) of the Boeing 747 lateral model, eq 35: published values, or the scan's."""
    a31, aileron = (
        (0.305, [0.0, 0.123, 1.063, 0.0]) if printed else (-3.05, [0.0, 0.0077, 0.143, 0.0])
    )
    A = np.array(
        [
            [-0.0558, -0.9968, 0.0802, 0.0415],
            [0.598, -0.115, -0.0318, 0.0],
            [a31, 0.388, -0.465, 0.0],
            [0.0, 0.0805, 1.0, 0.0],
        ]
    )
    B = np.column_stack([[0.0073, -0.475, 0.153, 0.0], aileron])
    return A, B


#: Charlie's measured outputs (rows of the identity): airspeed, pitch angle and pitch rate (not
#: the angle of attack); (A, C) is observable
CHARLIE_OUTPUTS = (0, 2, 3)
#: the 747's measured outputs (rows of the identity): yaw rate, roll rate and roll angle (not
#: the sideslip); (A, C) is observable
B747_OUTPUTS = (1, 2, 3)


def output_matrix(n: int, rows) -> np.ndarray:
    """C selecting the states ``rows`` of an ``n``-state model."""
    return np.eye(n)[list(rows)]


def aircraft(name: str, printed: bool = False) -> dict:
    """Everything the study needs about aircraft ``name`` ("charlie" or "b747").

    Returns a dict with ``A``, ``B``, ``C``, ``theta`` (the paper's true values), ``state_names``,
    ``input_names`` and ``time_unit``. ``printed`` selects the scan's 747 values.
    """
    if name == "charlie":
        A, B = charlie()
        return {
            "A": A,
            "B": B,
            "C": output_matrix(4, CHARLIE_OUTPUTS),
            "theta": np.array(CHARLIE_THETA),
            "state_names": ["V_hat", "alpha", "pitch", "omega_y_hat"],
            "input_names": ["elevator"],
            "time_unit": f"tau_a = {CHARLIE_TIME_UNIT_S} s (non-dimensional time, eq 34)",
        }
    if name == "b747":
        A, B = b747(printed)
        return {
            "A": A,
            "B": B,
            "C": output_matrix(4, B747_OUTPUTS),
            "theta": np.array(B747_THETA),
            "state_names": ["beta", "r", "p", "phi"],
            "input_names": ["rudder", "aileron"],
            "time_unit": "s",
        }
    raise ValueError(f"name: unknown aircraft {name!r}; choose 'charlie' or 'b747'")
