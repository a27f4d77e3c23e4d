"""Command line: ``python -m jaxest reproduce {all,STUDY...} --out DIR``."""

from __future__ import annotations

import argparse
import json
import sys
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
        "--runs", type=int, default=None, help="Monte Carlo runs (default: each study's own)"
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
    return parser


def _describe(name: str) -> str:
    try:
        return studies.load(name).DESCRIPTION
    except ImportError as err:  # a study whose optional pieces are missing still lists
        return f"(unavailable: {err})"


def _seconds_by_study(index_path: Path, quick: bool) -> dict[str, float]:
    """Each study's wall time in the last run into this folder (``index.json``), where it ran in
    the same mode (``--quick`` or not); {} without a readable index."""
    try:
        index = json.loads(index_path.read_text())
    except (OSError, ValueError):
        return {}
    return {
        name: entry["seconds"]
        for name, entry in index.items()
        if isinstance(entry, dict) and entry.get("quick") == quick and "seconds" in entry
    }


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    # Before the first computation, which is when XLA reads its flags: the studies compile about
    # as much as they run, and this flag halves compiling without slowing what runs
    # (jaxest.xla_flags has the measurements).
    xla_flags.add(xla_flags.FASTER_COMPILATION)
    import jax

    jax.config.update("jax_enable_x64", True)  # studies run in float64 unless they say otherwise
    compile_cache.enable()  # where JAXEST_COMPILATION_CACHE=1 asks for it
    names = list(studies.STUDIES) if "all" in args.study else args.study
    if args.runs is not None and args.runs < 1:
        raise SystemExit("--runs: must be at least 1")
    args.out.mkdir(parents=True, exist_ok=True)
    last_run = _seconds_by_study(args.out / "index.json", args.quick)
    index = {}
    for i, name in enumerate(names):
        start = time.perf_counter()
        to_go = [last_run.get(n) for n in names[i:]]
        estimate = (
            f" (about {sum(to_go):.0f} s to go, by the last run's times)"
            if None not in to_go
            else ""
        )
        print(f"== [{i + 1}/{len(names)}] {name}: {_describe(name)}{estimate}", file=sys.stderr)
        module = studies.load(name)
        module.run(
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
            "xla_flags": xla_flags.current(),
        }
        print(
            f"== {name}: done in {index[name]['seconds']} s -> {args.out / name}", file=sys.stderr
        )
    write_json(args.out / "index.json", index)
    return 0
