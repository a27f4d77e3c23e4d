"""Loader for the real flight-test data of Jategaonkar's *Flight Vehicle System Identification*.

The files (``flt_data.zip`` of the book's supplementary material) are not part of jaxest and may not
be copied into it: give their directory (or set ``JAXEST_FLIGHT_DATA``), or keep them at
``../shared/data/flight`` beside the repository (the default). Channel order and units follow the book's ``README.txt``:

- ATTAS (DLR's VFW-614), ``fAttas*``: 25 Hz, 45 channels (48 in the ``_pqrDot`` files), accelerations
  at the CG in m/s^2, rates in deg/s, angles in deg, true airspeed in m/s, pressure altitude in ft;
- HFB-320, ``hfb320_1_10.asc``: 10 Hz, 20 channels in SI units (rad), no altitude channel.

Every record is returned in the units of :mod:`jaxest.systems.flight`: inputs
[a_x, a_y, a_z (m/s^2), p, q, r (rad/s)] and outputs [V (m/s), beta, alpha, theta, phi (rad),
h (m)], NaN for a channel the file lacks (the filters treat NaN as missing).

Sensor time delays (time skew): the flow vanes of the ATTAS lag the inertial sensors by about a tenth
of a second, a usual finding of flight-path reconstruction. :func:`advance_channels` undoes such
delays so that the model, which evaluates every output at the inputs' sample time, fits the data.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxest.systems.flight import DEG

__all__ = [
    "FOOT", "DATA_ENV", "DEFAULT_DATA_DIR", "DOWNLOAD_HINT", "ATTAS_FILES", "HFB320_FILE", "FlightData",
    "find_data_dir", "load_attas", "attas_record", "load_hfb320", "advance_channels",
]  # fmt: skip

#: metres per foot (the files give altitude in feet)
FOOT = 0.3048

#: environment variable naming the data directory (used when no directory is given)
DATA_ENV = "JAXEST_FLIGHT_DATA"
#: where the files are looked for otherwise: ../shared/data/flight beside the repository
DEFAULT_DATA_DIR = Path(__file__).resolve().parents[3] / "shared" / "data" / "flight"

#: where the files come from, appended to the errors for a missing directory or file
DOWNLOAD_HINT = (
    "The flight data are the files of flt_data.zip, the supplementary material of R. V. Jategaonkar, "
    "'Flight Vehicle System Identification - A Time Domain Methodology' (AIAA, Progress in "
    "Astronautics and Aeronautics; 2nd ed. 2015, doi:10.2514/4.102790), downloadable from the "
    "book's page on AIAA's Aerospace Research Central (arc.aiaa.org, 'Supplemental Material'). "
    "Unpack it and pass its flt_data directory with --data DIR."
)

#: ATTAS maneuvers analysed by the study and their files
ATTAS_FILES = {
    "elevator": "fAttasElv1_pqrDot.asc",
    "aileron": "fAttasAil1_pqrDot.asc",
    "rudder": "fAttasRud1_pqrDot.asc",
}
#: the HFB-320 record's file
HFB320_FILE = "hfb320_1_10.asc"

# 0-based columns (README.txt numbers minus one) and the factor to SI units
_ATTAS_INPUTS = [(1, 1.0), (2, 1.0), (3, 1.0), (6, DEG), (7, DEG), (8, DEG)]
_ATTAS_OUTPUTS = [(14, 1.0), (13, DEG), (12, DEG), (10, DEG), (9, DEG), (15, FOOT)]
_HFB_INPUTS = [(9, 1.0), (11, 1.0), (10, 1.0), (12, 1.0), (7, 1.0), (13, 1.0)]
_HFB_OUTPUTS = [(4, 1.0), (16, 1.0), (5, 1.0), (6, 1.0), (17, 1.0), (None, 1.0)]


@dataclass(frozen=True)
class FlightData:
    """One recorded maneuver in SI units (see the module docstring)."""

    name: str
    t: np.ndarray
    inputs: np.ndarray
    outputs: np.ndarray

    @property
    def dt(self) -> float:
        return float(np.median(np.diff(self.t)))

    @property
    def rate_hz(self) -> float:
        return 1.0 / self.dt


def find_data_dir(path: str | Path | None = None) -> Path | None:
    """The flight-data directory: ``path`` if given (it must exist), else ``$JAXEST_FLIGHT_DATA``,
    else the default one if it exists, else ``None``."""
    if path is None and os.environ.get(DATA_ENV):
        path = os.environ[DATA_ENV]
    if path is not None:
        path = Path(path)
        if not path.is_dir():
            raise ValueError(f"data: {path} is not a directory. {DOWNLOAD_HINT}")
        return path
    return DEFAULT_DATA_DIR if DEFAULT_DATA_DIR.is_dir() else None


def _required_dir(data_dir) -> Path:
    directory = find_data_dir(data_dir)
    if directory is None:
        raise ValueError(
            f"data: no directory given and none at {DEFAULT_DATA_DIR}. {DOWNLOAD_HINT}"
        )
    return directory


def _read(path: Path, columns: int) -> np.ndarray:
    if not path.is_file():
        raise ValueError(f"data: {path} not found. {DOWNLOAD_HINT}")
    table = np.loadtxt(path)
    if table.ndim != 2 or table.shape[1] < columns:
        raise ValueError(
            f"data: {path} has shape {table.shape}, expected at least {columns} columns"
        )
    return table


def _channels(table, spec):
    cols = [
        np.full(table.shape[0], np.nan) if col is None else table[:, col] * scale
        for col, scale in spec
    ]
    return np.stack(cols, axis=1)


def load_attas(maneuver: str, data_dir: str | Path | None = None) -> FlightData:
    """An ATTAS maneuver (``elevator``, ``aileron`` or ``rudder``, or a file name) at 25 Hz."""
    name = ATTAS_FILES.get(maneuver, maneuver)
    return attas_record(_read(_required_dir(data_dir) / name, 45), f"ATTAS {maneuver}")


def attas_record(table, name: str) -> FlightData:
    """Rows of an ATTAS table (the 45 channels of ``README.txt`` as columns, read from any of the
    ``fAttas*`` files) as a record, time counted from its first row."""
    table = np.asarray(table, np.float64)
    if table.ndim != 2 or table.shape[0] < 2 or table.shape[1] < 45:
        raise ValueError(f"table: expected at least 2 rows of 45 ATTAS channels, got {table.shape}")
    return FlightData(
        name=name,
        t=table[:, 0] - table[0, 0],
        inputs=_channels(table, _ATTAS_INPUTS),
        outputs=_channels(table, _ATTAS_OUTPUTS),
    )


def load_hfb320(data_dir: str | Path | None = None) -> FlightData:
    """The HFB-320 elevator 3-2-1-1 + pulse record at 10 Hz (no altitude: h is NaN)."""
    table = _read(_required_dir(data_dir) / HFB320_FILE, 20)
    return FlightData(
        name="HFB-320 elevator",
        t=table[:, 0] - table[0, 0],
        inputs=_channels(table, _HFB_INPUTS),
        outputs=_channels(table, _HFB_OUTPUTS),
    )


def advance_channels(outputs, dt: float, delays, max_delays) -> jax.Array:
    """``outputs`` (T x m) with channel j read ``delays[j]`` seconds later: sample k becomes the
    channel's value at t_k + delays[j], interpolated linearly between samples. This undoes a sensor
    that lags the others by ``delays[j]``; it is differentiable in ``delays`` and ``vmap``s over them.

    The last ceil(max_delays[j] / dt) samples of channel j are marked missing (NaN) whatever its
    delay, so that runs with any delays up to ``max_delays`` (numbers, not traced) filter the same
    measurements and their log-likelihoods can be compared.
    """
    outputs = jnp.asarray(outputs)
    max_delays = np.asarray(max_delays, dtype=float)
    if max_delays.shape != (outputs.shape[1],) or np.any(max_delays < 0):
        raise ValueError(
            f"max_delays: expected {outputs.shape[1]} non-negative numbers, got {max_delays}"
        )
    steps = outputs.shape[0]
    index = jnp.arange(steps, dtype=outputs.dtype)
    shifted = jax.vmap(
        lambda y, d: jnp.interp(index + d / dt, index, y), in_axes=(1, 0), out_axes=1
    )
    advanced = shifted(outputs, jnp.asarray(delays, outputs.dtype))
    tail = np.ceil(max_delays / dt - 1e-9).astype(int)
    kept = np.arange(steps)[:, None] < steps - tail[None, :]
    return jnp.where(kept, advanced, jnp.nan)
