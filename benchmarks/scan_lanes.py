"""The lane width of the parallel scans: filter + smoother run time against T / C.

:func:`jaxest.scan.associative_scan` combines C = T / CHUNKS elements per step (module docstring
of :mod:`jaxest.scan`, which gives the values measured on a CPU and a GPU): wide steps leave lanes
unused, narrow ones take more steps, each with a fixed cost. For each n, T and dtype and
each value of ``--chunks``, this times the parallel filter + smoother in square-root and standard
form (:func:`jaxest.studies.parallel.timing`, best of ``--repeats`` runs after compiling) and
reports as ``best`` the value whose run time over the fastest value's, averaged over the
configurations and both forms, is smallest, beside the default. ``--lax`` adds
``lax.associative_scan`` (the same tree, one compiled combination per level) at the smallest T.
Run it on a new platform to set :data:`jaxest.scan.CHUNKS`; the JSON names the device and is
rewritten after each configuration, so a run cut short keeps what it measured.

    python benchmarks/scan_lanes.py --json lanes.json
    python benchmarks/scan_lanes.py --states 20 --lengths 100000 --chunks 4 16 64 --lax
"""

from __future__ import annotations

import argparse
import contextlib
from pathlib import Path
from unittest import mock

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxest._estimator  # noqa: E402
import jaxest.scan  # noqa: E402
import jaxest.smoothers.parallel  # noqa: E402
from jaxest.progress import Progress  # noqa: E402
from jaxest.report import device_name, emit_json, write_json  # noqa: E402
from jaxest.studies.parallel import timing  # noqa: E402

PARALLEL = ("parallel_sqrt", "parallel_standard")


def lax_associative_scan() -> contextlib.ExitStack:
    """The parallel filter and smoother on ``lax.associative_scan`` while inside."""
    stack = contextlib.ExitStack()
    for module in (jaxest._estimator, jaxest.smoothers.parallel):
        stack.enter_context(mock.patch.object(module, "associative_scan", jax.lax.associative_scan))
    return stack


def best_chunks(rows: list[dict]) -> tuple[int, dict]:
    """The ``chunks`` value with the least mean run time over the fastest value's at the same n,
    T, dtype and method, and that mean for every value."""
    swept = [r for r in rows if r["chunks"] is not None]
    key = lambda r: (r["n"], r["T"], r["dtype"], r["method"])  # noqa: E731
    fastest = {}
    for r in swept:
        fastest[key(r)] = min(fastest.get(key(r), np.inf), r["run_s"])
    ratios = {}
    for r in swept:
        ratios.setdefault(r["chunks"], []).append(r["run_s"] / fastest[key(r)])
    means = {c: float(np.mean(v)) for c, v in ratios.items()}
    return min(means, key=means.get), means


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", default=None, help="write the results here (default: stdout)")
    parser.add_argument("--states", type=int, nargs="+", default=[4, 20])
    parser.add_argument("--lengths", type=int, nargs="+", default=[10_000, 100_000])
    parser.add_argument("--dtypes", nargs="+", default=["float32"])
    parser.add_argument("--chunks", type=int, nargs="+", default=[4, 16, 64, 256])
    parser.add_argument("--repeats", type=int, default=5, help="timed runs after compiling")
    parser.add_argument("--lax", action="store_true", help="add lax.associative_scan")
    args = parser.parse_args(argv)
    configs = [(n, T, d) for n in args.states for T in args.lengths for d in args.dtypes]
    with_lax = [c for c in configs if args.lax and c[1] == min(args.lengths)]
    rows = []

    def report():
        best, means = best_chunks(rows) if rows else (None, {})
        return {"device": device_name(), "default_chunks": jaxest.scan.CHUNKS,
                "best_chunks": best, "mean_over_fastest": means, "rows": rows}  # fmt: skip

    total = len(configs) * len(args.chunks) + len(with_lax)
    with Progress("scan-lanes", total=total) as progress:
        for n, T, dtype in configs:
            for value in args.chunks:
                with mock.patch.object(jaxest.scan, "CHUNKS", value):
                    C = jaxest.scan.lanes(T)
                    for r in timing(n, T, jnp.dtype(dtype), args.repeats, PARALLEL):
                        rows.append({**r, "chunks": value, "lanes": C})
                progress.advance(f"n={n} T={T} {dtype} T/C={value}")
            if (n, T, dtype) in with_lax:
                with lax_associative_scan():
                    for r in timing(n, T, jnp.dtype(dtype), args.repeats, PARALLEL):
                        rows.append({**r, "chunks": None, "lanes": None})
                progress.advance(f"n={n} T={T} {dtype} lax.associative_scan")
            if args.json:
                write_json(Path(args.json), report())
    for r in rows:
        scan = "lax" if r["chunks"] is None else f"T/C={r['chunks']} (C={r['lanes']})"
        print(f"n={r['n']} T={r['T']} {r['dtype']} {r['method']} {scan}: compile "
              f"{r['compile_s']:.1f} s, run {1e3 * r['run_s']:.3f} ms, "
              f"rel loglik diff {r['loglik_rel_diff']}")  # fmt: skip
    emit_json(report(), args.json)


if __name__ == "__main__":
    main()
