"""Study and benchmark outputs: JSON summaries, Markdown tables, and timing of compiled calls."""

from __future__ import annotations

import json
import math
import os
import platform
import time
from pathlib import Path

import jax
import numpy as np

from jaxest import xla_flags


def to_jsonable(value):
    """Convert arrays/NumPy scalars to plain Python; non-finite floats become ``None`` (null)."""
    if isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [to_jsonable(v) for v in value]
    if hasattr(value, "shape") or isinstance(value, np.generic):
        return to_jsonable(np.asarray(value).tolist())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def write_json(path: Path, data) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(to_jsonable(data), indent=2))


def markdown_table(headers: list[str], rows: list[list], floatfmt: str = ".4g") -> str:
    """A GitHub-flavoured Markdown table (``ValueError`` for a row of another width than
    ``headers``: it was written under the wrong columns)."""
    for index, row in enumerate(rows):
        if len(row) != len(headers):
            raise ValueError(
                f"rows[{index}]: has {len(row)} cells for {len(headers)} headers {headers}"
            )

    def cell(v):
        if isinstance(v, float | np.floating):
            return format(float(v), floatfmt)
        return str(v)

    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def emit_json(data, path=None) -> str:
    """Print ``data`` as JSON (non-finite numbers as null) and write it to ``path`` if given:
    the output of every benchmark script. A dict gains ``"xla_flags"``, the process's
    ``XLA_FLAGS``: compile times (and some run times) depend on them (:mod:`jaxest.xla_flags`)."""
    if isinstance(data, dict):
        data = {**data, "xla_flags": xla_flags.current()}
    text = json.dumps(to_jsonable(data), indent=1)
    if path:
        Path(path).write_text(text)
    print(text)
    return text


def timed_call(call) -> tuple[object, float]:
    """``call()``'s result, waited for (JAX dispatches asynchronously), and the seconds it took."""
    start = time.perf_counter()
    result = jax.block_until_ready(call())
    return result, time.perf_counter() - start


def best_of(call, repeats: int) -> tuple[object, float]:
    """The last result of ``repeats`` calls of ``call()`` (each waited for, :func:`timed_call`)
    and the fastest call's seconds, the benchmarks' measure of a time: the other calls only add
    the machine's noise. Call it once before, to compile it."""
    runs = [timed_call(call) for _ in range(repeats)]
    return runs[-1][0], min(seconds for _, seconds in runs)


def timed(fn, args, repeats: int = 5, compiler_options=None) -> tuple[float, float, object]:
    """(compile seconds, best run seconds, output) of ``jax.jit(fn)(*args)``: compiled ahead of
    time (with ``compiler_options``), run once to warm up (its output is returned), then the
    fastest of ``repeats`` runs (the benchmarks' per-step times). ``repeats=0``: the warm-up
    run's time, for runs too long to repeat."""
    compiled, compile_s = timed_call(lambda: jax.jit(fn).lower(*args).compile(compiler_options))
    output, warm_up_s = timed_call(lambda: compiled(*args))
    best_s = best_of(lambda: compiled(*args), repeats)[1] if repeats else warm_up_s
    return compile_s, best_s, output


def device_name() -> str:
    """The first device, e.g. ``gpu: NVIDIA H100`` or ``cpu: x86_64, 2 cores``."""
    device = jax.devices()[0]
    if device.platform == "cpu":
        return f"cpu: {platform.machine()}, {os.cpu_count()} cores"
    return f"{device.platform}: {device.device_kind}"
