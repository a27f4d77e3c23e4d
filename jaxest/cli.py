"""Command line: ``python -m jaxest reproduce {all,STUDY...} --out DIR [--jobs N]``."""

from __future__ import annotations

import argparse
import functools
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from jaxest import compile_cache, studies, xla_flags
from jaxest.report import write_json


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="jaxest", description="jaxest: differentiable estimation in JAX"
    )
    sub = parser.add_subparsers(dest="command", required=True)
    rep = sub.add_parser(
        "reproduce",
        help="run the papers' studies",
        description="Run the papers' studies; each writes figures (PNG) and tables (Markdown + JSON).",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="studies:\n"
        + "\n".join(f"  {name:10s} {_describe(name)}" for name in studies.STUDIES),
    )
    rep.add_argument(
        "study", nargs="+", choices=["all", *studies.STUDIES], help="study name(s) or 'all'"
    )
    rep.add_argument(
        "--out", type=Path, default=Path("results"), help="output directory (default: results)"
    )
    rep.add_argument(
        "--runs",
        type=_at_least_one,
        default=None,
        help="Monte Carlo runs (default: each study's own)",
    )
    rep.add_argument("--seed", type=int, default=0, help="PRNG seed (default: 0)")
    rep.add_argument("--quick", action="store_true", help="small, fast versions of every study")
    rep.add_argument(
        "--data", type=Path, default=None, help="flight data directory (svd-ekf study)"
    )
    rep.add_argument(
        "--b747-printed",
        action="store_true",
        help="adaptive study: the Boeing 747 matrices as printed in the scan, not the published ones",
    )
    rep.add_argument(
        "--jobs",
        type=_at_least_one,
        default=1,
        help="studies run at once, each in its own process (default: 1); the studies whose "
        "tables report wall times run alone after the others",
    )
    # a worker of --jobs: write this study's index entry to FILE, leave announcements to the parent
    rep.add_argument("--worker", type=Path, default=None, help=argparse.SUPPRESS)
    return parser


def _at_least_one(text: str) -> int:
    """An option's whole number of at least 1 (argparse names the option and exits with 2, as
    for its own errors: ``--jobs 0`` exited with 1 and no usage line)."""
    try:
        number = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if number < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {number}")
    return number


def _describe(name: str) -> str:
    try:
        return studies.load(name).DESCRIPTION
    except ImportError as err:  # a study whose optional pieces are missing still lists
        return f"(unavailable: {err})"


def _read_index(path: Path) -> dict[str, dict]:
    """The entries of an output folder's ``index.json``; {} where it is missing or unreadable."""
    try:
        index = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return index if isinstance(index, dict) else {}


def _seconds_by_study(index: dict[str, dict], quick: bool, jobs: int) -> dict[str, float]:
    """Each study's wall time in the last run into this folder (its ``index``), where it ran in
    the same mode (``--quick`` or not, the same ``--jobs``)."""
    return {
        name: entry["seconds"]
        for name, entry in index.items()
        if isinstance(entry, dict)
        and entry.get("quick") == quick
        and entry.get("jobs", 1) == jobs
        and "seconds" in entry
    }


@functools.cache
def _timed(name: str) -> bool:
    """Whether the study's tables report wall times (its module's ``TIMED``): with ``--jobs`` it
    runs with no other study beside it, so that nothing else competes for the processor."""
    return getattr(studies.load(name), "TIMED", False)


def _start_order(names: list[str], seconds: dict[str, float]) -> list[str]:
    """The order ``--jobs`` starts the studies in: the untimed ones first, longest first, then
    the timed ones. Longest by the last run's times where it timed every untimed study, else by
    :data:`jaxest.studies.TYPICAL_SECONDS` (a fresh clone's first run): as listed, the five
    studies beside svd-ekf ran after one another past its end (603 against 492 s)."""
    untimed = [name for name in names if not _timed(name)]
    if not all(name in seconds for name in untimed):
        seconds = studies.TYPICAL_SECONDS
    untimed.sort(key=lambda name: -seconds[name])
    return untimed + [name for name in names if _timed(name)]


def _seconds_to_go(
    running: dict[str, float], queued: list[str], seconds: dict[str, float], jobs: int
) -> float | None:
    """Seconds until the last study is done if each takes as long as in the last run
    (``seconds``), or None where one has no time there. ``running``: study -> seconds it has
    run; ``queued``: the studies still to start, in their order. Up to ``jobs`` untimed studies
    run at once, each starting in the first free slot; the timed ones run alone, after them."""
    if any(name not in seconds for name in [*running, *queued]):
        return None
    left = {name: max(seconds[name] - ran, 0.0) for name, ran in running.items()}
    slots = sorted(t for name, t in left.items() if not _timed(name))
    slots += [0.0] * (jobs - len(slots))
    alone = sum(t for name, t in left.items() if _timed(name))
    for name in queued:
        if _timed(name):
            alone += seconds[name]
        else:
            slots[slots.index(min(slots))] += seconds[name]
    return max(slots) + alone


def _to_go(seconds_left: float | None) -> str:
    if seconds_left is None:
        return ""
    return f" (about {seconds_left:.0f} s to go, by the last run's times)"


def _run_here(names: list[str], args, seconds: dict[str, float]) -> dict[str, dict]:
    """Run the studies one after the other in this process; their index entries."""
    # Before the first computation, which is when XLA reads its flags: the studies compile about
    # as much as they run, and this flag halves compiling without slowing what runs
    # (jaxest.xla_flags has the measurements).
    xla_flags.add(xla_flags.FASTER_COMPILATION)
    import jax

    jax.config.update("jax_enable_x64", True)  # studies run in float64 unless they say otherwise
    compile_cache.enable()  # where JAXEST_COMPILATION_CACHE=1 asks for it
    index = {}
    for i, name in enumerate(names):
        start = time.perf_counter()
        if args.worker is None:
            to_go = _to_go(_seconds_to_go({}, names[i:], seconds, jobs=1))
            print(f"== [{i + 1}/{len(names)}] {name}: {_describe(name)}{to_go}", file=sys.stderr)
        studies.load(name).run(
            args.out,
            runs=args.runs,
            seed=args.seed,
            quick=args.quick,
            options={"data": args.data, "printed_747": args.b747_printed},
        )
        # Release the study's compiled programs: each holds mapped code pages, and one process
        # running every study reached the kernel's 65530-mapping limit in the eighth
        # ("LLVM ERROR: Unable to allocate section memory", 36 min in).
        jax.clear_caches()
        index[name] = {
            "seconds": round(time.perf_counter() - start, 2),
            "dir": str(args.out / name),
            "quick": args.quick,
            "jobs": args.jobs,
            "xla_flags": xla_flags.current(),
        }
        if args.worker is None:
            print(f"== {name}: done in {index[name]['seconds']} s -> {args.out / name}",
                  file=sys.stderr)  # fmt: skip
    return index


def _worker_command(name: str, args, entry_file: Path) -> list[str]:
    """The command that runs study ``name`` in a process of its own, with the options given."""
    command = [sys.executable, "-m", "jaxest", "reproduce", name, "--out", str(args.out),
               "--seed", str(args.seed), "--jobs", str(args.jobs), "--worker", str(entry_file)]  # fmt: skip
    if args.runs is not None:
        command += ["--runs", str(args.runs)]
    if args.quick:
        command.append("--quick")
    if args.data is not None:
        command += ["--data", str(args.data)]
    if args.b747_printed:
        command.append("--b747-printed")
    return command


def _worker_environment(name: str) -> dict[str, str]:
    """The environment of the worker running study ``name``: this process's, and for a study
    that runs beside another (not :func:`_timed`) XLA's machine code compiled in one piece
    (:data:`jaxest.xla_flags.SERIAL_CODEGEN`). With both cores busy, splitting it for XLA's
    thread pool only adds work: the six untimed studies with ``--jobs 2`` took 37-58 s less CPU
    and 15-21 s less wall time (4-6 %, 3-4 %), with the same results (docs/performance.md).
    A timed study whose module sets ``RUNS_ACROSS_CORES`` runs alone with one CPU device per
    core (:func:`jaxest.xla_flags.cpu_devices`), over which it shards its runs."""
    environment = dict(os.environ)
    if not _timed(name):
        xla_flags.add(xla_flags.SERIAL_CODEGEN, environment)
    elif getattr(studies.load(name), "RUNS_ACROSS_CORES", False):
        xla_flags.add(xla_flags.cpu_devices(), environment)
    return environment


def _entry_file(out: Path, name: str) -> Path:
    """Where the worker running study ``name`` writes its index entry for the parent."""
    return out / f".index-{name}.json"


def _run_in_processes(
    names: list[str], args, seconds: dict[str, float]
) -> tuple[dict[str, dict], list[str]]:
    """Run the studies ``args.jobs`` at a time, each in a process of its own, the timed ones
    alone after the others; relays each process's progress lines, labelled with its study.
    After a study fails no other starts. Returns the finished studies' index entries and the
    failed studies."""
    queued = _start_order(names, seconds)
    running: dict[str, tuple[subprocess.Popen, float, threading.Thread]] = {}
    index: dict[str, dict] = {}
    failed: list[str] = []
    lock = threading.Lock()

    def say(text: str) -> None:
        with lock:
            print(text, file=sys.stderr, flush=True)

    def relay(name: str, stream) -> None:
        for line in stream:
            line = line.rstrip("\n")
            say(line if line.startswith(f"[{name}]") else f"[{name}] {line}")

    def may_start(name: str) -> bool:
        if _timed(name):
            return not running
        return len(running) < args.jobs and not any(_timed(other) for other in running)

    def ran_for() -> dict[str, float]:
        now = time.perf_counter()
        return {other: now - started for other, (_, started, _) in running.items()}

    try:
        while queued or running:
            while queued and not failed and may_start(queued[0]):
                name = queued.pop(0)
                process = subprocess.Popen(
                    _worker_command(name, args, _entry_file(args.out, name)),
                    stderr=subprocess.PIPE,
                    text=True,
                    env=_worker_environment(name),
                )
                thread = threading.Thread(target=relay, args=(name, process.stderr), daemon=True)
                thread.start()
                beside = f"; beside {', '.join(running)}" if running else ""
                running[name] = (process, time.perf_counter(), thread)
                to_go = _to_go(_seconds_to_go(ran_for(), queued, seconds, args.jobs))
                say(f"== [{len(names) - len(queued)}/{len(names)}] {name}: {_describe(name)}"
                    f"{beside}{to_go}")  # fmt: skip
            if not running:
                break
            time.sleep(0.2)
            for name, (process, _, thread) in list(running.items()):
                if process.poll() is None:
                    continue
                thread.join()
                del running[name]
                if process.returncode != 0:
                    failed.append(name)
                    say(f"== {name}: failed (exit code {process.returncode}); its output is above")
                    continue
                entry_file = _entry_file(args.out, name)
                index[name] = json.loads(entry_file.read_text())[name]
                entry_file.unlink()
                left = _seconds_to_go(ran_for(), queued, seconds, args.jobs)
                to_go = _to_go(left) if queued or running else ""
                say(f"== {name}: done in {index[name]['seconds']} s -> {args.out / name}{to_go}")
    finally:
        for process, *_ in running.values():  # interrupted: stop the studies still running
            process.terminate()
            process.wait()
    return index, failed


def _check_data(directory: Path, names) -> None:
    """``--data`` a directory holding the records the chosen studies read (the svd-ekf study's):
    a missing file was found after the study's simulated part, with a traceback."""
    from jaxest.systems import flight_data

    try:
        flight_data.find_data_dir(directory)
    except ValueError as error:  # "data: ... is not a directory ..."
        raise SystemExit(f"--{error}") from None
    if "svd-ekf" in names:
        wanted = [*flight_data.ATTAS_FILES.values(), flight_data.HFB320_FILE]
        missing = [name for name in wanted if not (directory / name).is_file()]
        if missing:
            raise SystemExit(
                f"--data: {directory} lacks {', '.join(missing)} (the svd-ekf study's records). "
                f"{flight_data.DOWNLOAD_HINT}"
            )


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    names = list(dict.fromkeys(studies.STUDIES if "all" in args.study else args.study))  # once each
    # an option for a study not chosen was ignored without a word (a --jobs worker gets every
    # option the parent was given, whatever its study)
    for option, given, study in (("--b747-printed", args.b747_printed, "adaptive"),
                                 ("--data", args.data is not None, "svd-ekf")):  # fmt: skip
        if given and study not in names and args.worker is None:
            parser.error(f"{option}: only the {study} study reads it, and it is not chosen")
    if args.out.exists() and not args.out.is_dir():  # mkdir said "File exists"
        raise SystemExit(f"--out: {args.out} is a file, not a directory")
    try:
        args.out.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise SystemExit(f"--out: cannot create {args.out} ({error.strerror})") from None
    try:  # a directory that exists but cannot be written failed inside the first study
        tempfile.TemporaryFile(dir=args.out).close()
    except OSError as error:
        raise SystemExit(f"--out: cannot write in {args.out} ({error.strerror})") from None
    if args.data is not None:
        _check_data(args.data, names)
    if args.worker is not None:  # one study for a parent that keeps the index
        write_json(args.worker, _run_here(names, args, {}))
        return 0
    index_path = args.out / "index.json"
    earlier = _read_index(index_path)
    seconds = _seconds_by_study(earlier, args.quick, args.jobs)
    if args.jobs > 1:
        index, failed = _run_in_processes(names, args, seconds)
    else:
        index, failed = _run_here(names, args, seconds), []
    # the folder's studies: this run's, and those of earlier runs that this one did not redo
    kept = {name: entry for name, entry in earlier.items() if name not in failed}
    write_json(index_path, {**kept, **index})
    if failed:
        raise SystemExit(f"reproduce: {', '.join(failed)} failed; see the output above")
    return 0
