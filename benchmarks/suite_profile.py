"""Where the test suite's time goes: for every test, the seconds JAX spent tracing programs to
jaxprs, lowering them to MLIR and XLA spent compiling them (the compile events JAX records through
``jax.monitoring``), and the rest of the test's wall time (running the programs, Python, waiting
for subprocesses, whose own compiling is not seen). Issue 17 bounds `make test` in wall time; this
says what that time is made of.

A pytest plugin and a summary. Record (each pytest-xdist worker appends to ``DIR/<worker>.jsonl``,
so give each run an empty directory, and give it with ``=``: as a separate argument pytest takes
it for a path to test and roots the run elsewhere), then summarise:

    PYTHONPATH=benchmarks python -m pytest -n 2 -p suite_profile --suite-profile=DIR
    python benchmarks/suite_profile.py DIR [--top 15] [--json out.json]

The summary splits the suite by the ``slow`` marker too (:data:`MARKER`): what ``make test-fast``
runs and what only ``make test`` adds.

A test's time counts from its setup to its teardown, so a module-scoped fixture's cost lands on
the first test that uses it. XLA programs that compile in under :data:`SMALL_PROGRAM_S` are
counted apart: they are mostly single operations run outside ``jit`` (one program per operation,
shape and dtype), where the rest are the jitted estimators the tests exercise.

Each record also splits the test's phases by program name (:func:`program_name`: ``_run`` for
``jax.jit`` of jaxest's driver, ``add`` for an addition outside ``jit``), and the summary lists
the costliest names over the suite: which functions' programs the time goes to, and in how many
tests.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import time
from pathlib import Path

import pytest

#: the compile phases JAX records, by the last part of their event name
PHASES = {
    "/jax/core/compile/jaxpr_trace_duration": "trace",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
    "/jax/core/compile/backend_compile_duration": "compile",
}
#: XLA programs compiled faster than this (seconds) are counted as small
SMALL_PROGRAM_S = 0.05
#: the marker of the tests ``make test-fast`` leaves out (pyproject.toml)
MARKER = "slow"


def program_name(fun_name: str) -> str:
    """The name of the function a program was made from, the same for its three phases: JAX
    names the tracing by the function (``loss``) and the lowering and compiling by the program
    (``jit(loss)``)."""
    if fun_name.startswith("jit(") and fun_name.endswith(")"):
        return fun_name[len("jit(") : -1]
    return fun_name


class _Recorder:
    """The current test's seconds and counts per phase, in all and per program name, fed by
    ``jax.monitoring``."""

    def __init__(self, path: Path):
        self.path = path
        self.start = time.perf_counter()
        self.seconds = collections.Counter()
        self.counts = collections.Counter()
        self.programs = collections.defaultdict(collections.Counter)

    def __call__(self, event: str, seconds: float, **kwargs) -> None:
        phase = PHASES.get(event)
        if phase is None:
            return
        self.seconds[phase] += seconds
        self.counts[phase] += 1
        if phase == "compile" and seconds < SMALL_PROGRAM_S:
            self.seconds["compile_small"] += seconds
            self.counts["compile_small"] += 1
        program = self.programs[program_name(kwargs.get("fun_name", "?"))]
        program[phase] += seconds
        if phase == "compile":
            program["compiled"] += 1

    def begin(self) -> None:
        self.start = time.perf_counter()
        self.seconds.clear()
        self.counts.clear()
        self.programs.clear()

    def end(self, test_id: str, markers: list[str]) -> None:
        record = {
            "test": test_id,
            "markers": markers,
            "wall": time.perf_counter() - self.start,
            "seconds": dict(self.seconds),
            "counts": dict(self.counts),
            "programs": {name: dict(split) for name, split in self.programs.items()},
            "xla_flags": os.environ.get("XLA_FLAGS", ""),
        }
        with self.path.open("a") as stream:
            stream.write(json.dumps(record) + "\n")


_recorder: _Recorder | None = None


def pytest_addoption(parser):
    parser.addoption(
        "--suite-profile",
        metavar="DIR",
        help="write each test's tracing, lowering and compiling seconds to DIR/<worker>.jsonl",
    )


def pytest_configure(config):
    global _recorder
    directory = config.getoption("--suite-profile")
    if not directory:
        return
    import jax

    Path(directory).mkdir(parents=True, exist_ok=True)
    worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
    _recorder = _Recorder(Path(directory) / f"{worker}.jsonl")
    jax.monitoring.register_event_duration_secs_listener(_recorder)


def pytest_unconfigure(config):
    global _recorder
    if _recorder is not None:
        import jax

        jax.monitoring.unregister_event_duration_listener(_recorder)
        _recorder = None


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    """Around a test's setup, call and teardown, in the process that runs it (a pytest-xdist
    controller receives its workers' reports, but runs no test)."""
    if _recorder is not None:
        _recorder.begin()
    yield
    if _recorder is not None:
        _recorder.end(item.nodeid, sorted({marker.name for marker in item.iter_markers()}))


def read_records(directory: Path) -> list[dict]:
    """Every test's record in the ``*.jsonl`` files of ``directory``."""
    records = [
        json.loads(line)
        for path in sorted(directory.glob("*.jsonl"))
        for line in path.read_text().splitlines()
    ]
    if not records:
        raise ValueError(f"directory: no test records (*.jsonl) in {directory}")
    return records


def _split(records: list[dict]) -> dict:
    """Summed wall seconds and their split into the phases, the small programs' compiling and
    the rest, with the number of programs traced, lowered and compiled."""
    seconds, counts = collections.Counter(), collections.Counter()
    wall = 0.0
    for record in records:
        wall += record["wall"]
        seconds.update(record["seconds"])
        counts.update(record["counts"])
    phases = {phase: seconds[phase] for phase in ("trace", "lower", "compile")}
    return {
        "tests": len(records),
        "wall_s": wall,
        **{f"{phase}_s": value for phase, value in phases.items()},
        "compile_small_s": seconds["compile_small"],
        "other_s": wall - sum(phases.values()),
        "programs_compiled": counts["compile"],
        "small_programs_compiled": counts["compile_small"],
    }


def _by_program(records: list[dict]) -> list[dict]:
    """Each program name's seconds per phase summed over the tests, the programs compiled under
    it and the tests that made them, the costliest first."""
    seconds = collections.defaultdict(collections.Counter)
    tests = collections.Counter()
    for record in records:
        for name, split in record["programs"].items():
            seconds[name].update(split)
            tests[name] += 1
    rows = [
        {
            "program": name,
            "tests": tests[name],
            "compiled": split["compiled"],
            **{f"{phase}_s": split[phase] for phase in ("trace", "lower", "compile")},
            "total_s": split["trace"] + split["lower"] + split["compile"],
        }
        for name, split in seconds.items()
    ]
    return sorted(rows, key=lambda row: -row["total_s"])


def summarise(records: list[dict], top: int) -> dict:
    """The whole suite's split (:func:`_split`), and the same for the tests marked
    :data:`MARKER` and the others, and for the ``top`` slowest test files and tests; the
    ``top`` costliest program names (:func:`_by_program`); ``suite_xla_flags``: the
    ``XLA_FLAGS`` the suite ran with (``"xla_flags"``, added by
    :func:`~jaxest.report.emit_json`, are the summarising process's)."""
    by_file = collections.defaultdict(list)
    for record in records:
        by_file[record["test"].split("::")[0]].append(record)
    files = [{"file": name, **_split(file_records)} for name, file_records in by_file.items()]
    slowest = sorted(records, key=lambda r: -r["wall"])[:top]
    return {
        "suite_xla_flags": sorted({r["xla_flags"] for r in records}),
        "suite": _split(records),
        "by_marker": {
            MARKER: _split([r for r in records if MARKER in r["markers"]]),
            f"not {MARKER}": _split([r for r in records if MARKER not in r["markers"]]),
        },
        "files": sorted(files, key=lambda f: -f["wall_s"])[:top],
        "tests": [{"test": r["test"], **_split([r])} for r in slowest],
        "programs": _by_program(records)[:top],
    }


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("directory", type=Path, help="the --suite-profile directory of a run")
    parser.add_argument(
        "--top", type=int, default=15, help="files, tests and program names listed (default 15)"
    )
    parser.add_argument("--json", help="write the summary here as well as to stdout")
    args = parser.parse_args(argv)
    from jaxest.report import emit_json

    emit_json(summarise(read_records(args.directory), args.top), args.json)


if __name__ == "__main__":
    main()
