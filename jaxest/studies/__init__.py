"""The papers' studies, one module each, run by ``python -m jaxest reproduce NAME``.

Each module defines ``DESCRIPTION`` (one line) and
``run(out: pathlib.Path, *, runs: int | None, seed: int, quick: bool, options: dict) -> dict``,
which writes its figures (PNG) and tables (Markdown + JSON) under ``out / NAME`` and returns the
summary it wrote. ``runs=None`` means the study's default number of Monte Carlo runs. A study
whose tables report wall times sets ``TIMED = True``: ``reproduce --jobs N`` runs it with no other
study beside it.
"""

from __future__ import annotations

import importlib

#: study name -> module (imported only when the study runs)
STUDIES: dict[str, str] = {
    "filters": "jaxest.studies.filters",
    "svd-ekf": "jaxest.studies.svd_ekf",
    "wiener": "jaxest.studies.wiener",
    "smf-fdi": "jaxest.studies.smf_fdi",
    "network": "jaxest.studies.network",
    "adaptive": "jaxest.studies.adaptive",
    "parallel": "jaxest.studies.parallel",
    "sigma-point": "jaxest.studies.sigma_point",
}

#: each study's wall time (s) at full size in a fresh-clone ``make reproduce`` (two at a time,
#: 2-core CPU, 0443cdd, 2026-11-29; docs/performance.md): ``reproduce --jobs`` starts the longest
#: first by these where no earlier run into the output folder timed every study
TYPICAL_SECONDS: dict[str, float] = {
    "filters": 54,
    "svd-ekf": 454,
    "wiener": 8,
    "smf-fdi": 25,
    "network": 103,
    "adaptive": 94,
    "parallel": 152,
    "sigma-point": 212,
}


def load(name: str):
    """The module of study ``name``."""
    if name not in STUDIES:
        raise ValueError(f"study: unknown study {name!r}; choose from {', '.join(STUDIES)}")
    return importlib.import_module(STUDIES[name])
