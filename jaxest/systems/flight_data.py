"""Loader for the real flight-test data of Jategaonkar's *Flight Vehicle System Identification*.

The files (``flt_data.zip`` of the book's supplementary material) are not part of jaxest and may not
be copied into it: give their directory (or set ``JAXEST_FLIGHT_DATA``), or keep them at
``../shared/data/flight`` beside the repository (the default). Channel order and units follow the book's ``README.txt``:

- ATTAS (DLR's VFW-614), ``fAttas*``: 25 Hz, 45 channels (48 in the ``_pqrDot`` files), accelerations
  at the CG in m/s^2, rates in deg/s, angles in deg, true airspeed in m/s, pressure altitude in ft;
- HFB-320, ``hfb320_1_10.asc``: 10 Hz, 20 channels in SI units (rad), no altitude channel.

The README's ft for the pressure altitude (HQNH, column 16) does not hold for every file: the
quasi-steady stall records ``fAttas_qst01/02.asc`` give it in metres (their ``_withHeader``
copy says M, and the static pressure, column 33, in Pa, puts them at 5 300 m, not 1 600). So the
unit is told by the static pressure: whichever of ft and m puts HQNH near the ISA pressure
altitude of PSTAT (:func:`infer_altitude_unit`), unless given (``altitude_unit=``). The copies
with a text header (``*_withHeader.asc``) are refused: they do not keep the README's units
(``fAttas_qst01_withHeader.asc`` gives the rates and attitude angles in rad under DEG
headings), and the same data come without one.

Every file is checked as it loads (a ``ValueError`` naming it): the column count of its aircraft
(a file of the other one, a dropped column), and a time column that is finite, increasing and
uniformly sampled (the filters take one ``dt``; a gap of missing samples is not interpolated).

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

from jaxest._checks import is_concrete
from jaxest.systems.flight import DEG

__all__ = [
    "FOOT", "ALTITUDE_UNITS", "DATA_ENV", "DEFAULT_DATA_DIR", "DOWNLOAD_HINT", "ATTAS_FILES",
    "HFB320_FILE", "FlightData", "find_data_dir", "load_attas", "attas_record", "infer_altitude_unit",
    "load_hfb320", "advance_channels",
]  # fmt: skip

#: metres per foot (the README gives the ATTAS altitude in feet)
FOOT = 0.3048
#: the units an ATTAS file may give its pressure altitude (HQNH) in, and metres per unit
ALTITUDE_UNITS = {"ft": FOOT, "m": 1.0}

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

# 0-based columns (README.txt numbers minus one) and the factor to SI units; the altitude's
# factor is the file's unit's (ALTITUDE_UNITS)
_ATTAS_INPUTS = [(1, 1.0), (2, 1.0), (3, 1.0), (6, DEG), (7, DEG), (8, DEG)]
_ATTAS_OUTPUTS = [(14, 1.0), (13, DEG), (12, DEG), (10, DEG), (9, DEG)]
_ATTAS_ALTITUDE = 15
_ATTAS_STATIC_PRESSURE = 32
#: column counts of the ATTAS files (45, 48 with the _pqrDot files' three) and the HFB-320 file
_ATTAS_WIDTHS = (45, 48)
_HFB_WIDTHS = (20,)
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


def _read(path: Path, widths: tuple[int, ...]) -> np.ndarray:
    """The file's table; a ``ValueError`` naming the file where it is not a headerless table of
    ``widths`` columns sampled uniformly in time."""
    if not path.is_file():
        raise ValueError(f"data: {path} not found. {DOWNLOAD_HINT}")
    if path.suffix.lower() == ".mat":
        raise ValueError(
            f"data: {path} is a MATLAB file; jaxest reads the book's text (.asc) files, which "
            f"hold the same channels"
        )
    lines = path.read_text(encoding="latin-1").splitlines()
    first = next((i for i, line in enumerate(lines) if _numeric(line)), len(lines))
    if first == len(lines):
        raise ValueError(f"data: {path} has no row of numbers")
    if first > 0:
        raise ValueError(
            f"data: {path} has a text header; jaxest reads the files without one, in the units "
            f"of README.txt (the _withHeader copies do not keep them: fAttas_qst01_withHeader.asc "
            f"gives the rates and attitude angles in rad under a DEG header)"
        )
    try:
        table = np.loadtxt(path, encoding="latin-1", ndmin=2)
    except ValueError as error:
        raise ValueError(f"data: {path} is not a table of numbers: {error}") from None
    if table.shape[1] not in widths:
        raise ValueError(
            f"data: {path} has {table.shape[0]} rows of {table.shape[1]} columns, expected "
            f"{' or '.join(map(str, widths))} columns (is it a file of the other aircraft?)"
        )
    if table.shape[0] < 2:  # no sampling interval; was reported as a column count
        raise ValueError(f"data: {path} has 1 row, and a record needs at least 2 (a time step)")
    _check_time(table[:, 0], path)
    return table


def _numeric(line: str) -> bool:
    try:
        return bool([float(field) for field in line.split()])
    except ValueError:
        return False


def _check_time(t, path) -> None:
    """Time (the first column) finite, increasing and sampled at one interval, to 1 %."""
    steps = np.diff(t)
    if not np.all(np.isfinite(t)):
        row = _first(~np.isfinite(t))
        raise ValueError(f"data: {path}: time (column 1) is not finite at row {row}")
    dt = np.median(steps)
    if not dt > 0:
        raise ValueError(f"data: {path}: time (column 1) does not increase (median step {dt})")
    uneven = ~(np.abs(steps - dt) <= 0.01 * dt)
    if np.any(uneven):
        row = _first(uneven)
        raise ValueError(
            f"data: {path}: time (column 1) goes from {t[row]} to {t[row + 1]} at row {row + 1}, "
            f"where the record steps by {dt:.6g}; the filters need one sample interval"
        )


def _first(mask) -> int:
    return int(np.flatnonzero(mask)[0])


def _channels(table, spec):
    cols = [
        np.full(table.shape[0], np.nan) if col is None else table[:, col] * scale
        for col, scale in spec
    ]
    return np.stack(cols, axis=1)


def load_attas(
    maneuver: str, data_dir: str | Path | None = None, altitude_unit: str | None = None
) -> FlightData:
    """An ATTAS maneuver (``elevator``, ``aileron`` or ``rudder``, or a file name) at 25 Hz, its
    altitude in ``altitude_unit`` (``"ft"`` or ``"m"``; by default :func:`infer_altitude_unit`'s)."""
    name = ATTAS_FILES.get(maneuver, maneuver)
    table = _read(_required_dir(data_dir) / name, _ATTAS_WIDTHS)
    return attas_record(table, f"ATTAS {maneuver}", altitude_unit)


def attas_record(table, name: str, altitude_unit: str | None = None) -> FlightData:
    """Rows of an ATTAS table (the 45 channels of ``README.txt`` as columns, read from any of the
    ``fAttas*`` files) as a record, time counted from its first row; the pressure altitude
    (column 16) in ``altitude_unit``, by default :func:`infer_altitude_unit`'s."""
    table = np.asarray(table, np.float64)
    if table.ndim != 2 or table.shape[0] < 2 or table.shape[1] < 45:
        raise ValueError(f"table: expected at least 2 rows of 45 ATTAS channels, got {table.shape}")
    if altitude_unit is None:
        altitude_unit = infer_altitude_unit(table)
    if altitude_unit not in ALTITUDE_UNITS:
        raise ValueError(f"altitude_unit: expected 'ft' or 'm', got {altitude_unit!r}")
    altitude = (_ATTAS_ALTITUDE, ALTITUDE_UNITS[altitude_unit])
    return FlightData(
        name=name,
        t=table[:, 0] - table[0, 0],
        inputs=_channels(table, _ATTAS_INPUTS),
        outputs=_channels(table, [*_ATTAS_OUTPUTS, altitude]),
    )


def infer_altitude_unit(table) -> str:
    """The unit (``"ft"`` or ``"m"``) of an ATTAS table's pressure altitude HQNH (column 16):
    the one that puts its median within 300 m + 10 % of the ISA pressure altitude of the static
    pressure PSTAT (column 33, read as hPa below 2 000, else Pa), h = 44 330.8 m (1 - (p /
    1013.25 hPa)^0.190263). The margin covers QNH's offset from the standard atmosphere (about
    8 m per hPa) and the two sensors' errors; a ``ValueError`` where both units or neither fit
    (near the ground feet and metres differ by less than that)."""
    table = np.asarray(table, np.float64)
    pressure = np.nanmedian(table[:, _ATTAS_STATIC_PRESSURE])
    pressure_pa = pressure * 100.0 if pressure < 2000.0 else pressure
    isa = 44330.8 * (1.0 - (pressure_pa / 101325.0) ** 0.190263)
    recorded = np.nanmedian(table[:, _ATTAS_ALTITUDE])
    fits = [
        unit
        for unit, metres in ALTITUDE_UNITS.items()
        if abs(recorded * metres - isa) <= 300.0 + 0.1 * abs(isa)
    ]
    if len(fits) != 1:
        raise ValueError(
            f"altitude_unit: cannot tell whether the pressure altitude (column 16, median "
            f"{recorded:.6g}) is in ft or m from the static pressure (column 33, median "
            f"{pressure:.6g}: {isa:.0f} m); give altitude_unit='ft' or 'm'"
        )
    return fits[0]


def load_hfb320(data_dir: str | Path | None = None) -> FlightData:
    """The HFB-320 elevator 3-2-1-1 + pulse record at 10 Hz (no altitude: h is NaN)."""
    table = _read(_required_dir(data_dir) / HFB320_FILE, _HFB_WIDTHS)
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

    The delays must lie in [0, max_delays] (checked where they are not traced). The last
    ceil(max_delays[j] / dt) samples of channel j are marked missing (NaN) whatever its
    delay, so that runs with any delays up to ``max_delays`` (numbers, not traced) filter the same
    measurements and their log-likelihoods can be compared.
    """
    outputs = jnp.asarray(outputs)
    max_delays = np.asarray(max_delays, dtype=float)
    if max_delays.shape != (outputs.shape[1],) or np.any(max_delays < 0):
        raise ValueError(
            f"max_delays: expected {outputs.shape[1]} non-negative numbers, got {max_delays}"
        )
    if is_concrete(delays):
        given, rounding = np.asarray(delays, np.float64), 1e-6 * dt  # 5 * 0.04 > 0.2, float32 0.2
        beyond = ~((-rounding <= given) & (given <= max_delays + rounding))
        if np.any(beyond):
            raise ValueError(
                f"delays: must lie in [0, max_delays]; got {given} against "
                f"{max_delays} (beyond the limit the samples past the record are not marked "
                f"missing but repeated)"
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
