"""``jaxest.report``: ``timed`` compiles once, then times runs of the compiled program;
``best_of`` keeps the fastest of its calls; ``emit_json`` records the XLA flags the numbers were measured under."""

import json
import math
import time

import jax
import jax.numpy as jnp
import pytest

from jaxest.report import best_of, emit_json, markdown_table, timed


def counting_sleeper(calls: list):
    """A program whose every run sleeps 20 ms and appends to ``calls`` (a host callback)."""

    def sleep(x):
        calls.append(1)
        time.sleep(0.02)
        return x

    return lambda x: jax.pure_callback(sleep, jax.ShapeDtypeStruct(x.shape, x.dtype), x) + 1.0


@pytest.mark.parametrize("repeats, runs", [(0, 1), (1, 2), (3, 4)])
def test_runs_once_to_warm_up_then_repeats(repeats, runs):
    """``repeats=0`` times the warm-up run itself: the program runs once; otherwise once more
    per repeat. The time is a run's (no upper bound: a loaded machine may be slow), and the
    output the warm-up run's."""
    calls = []
    compile_s, run_s, output = timed(counting_sleeper(calls), (jnp.zeros(3),), repeats)
    assert len(calls) == runs
    assert math.isfinite(run_s) and run_s >= 0.02  # one run's time: at least its sleep
    assert compile_s >= 0.0
    assert jnp.array_equal(output, jnp.ones(3))


def test_best_of_keeps_the_fastest_call_and_the_last_result():
    """Calls that sleep 0.3, 0.02 and 0.3 s: the time is the fastest's (the first's or the
    mean's would be 0.3 or over 0.2), the result the last call's, and nothing runs beyond."""
    sleeps, results = iter([0.3, 0.02, 0.3]), []

    def call():
        time.sleep(next(sleeps))
        results.append(len(results))
        return jnp.asarray(results[-1])

    last, seconds = best_of(call, 3)
    assert results == [0, 1, 2] and int(last) == 2
    assert 0.02 <= seconds < 0.2


def test_benchmark_output_records_the_xla_flags(monkeypatch, tmp_path, capsys):
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_use_fusion_emitters=false")
    text = emit_json({"ratio": math.inf}, tmp_path / "out.json")
    assert json.loads(text) == {"ratio": None, "xla_flags": "--xla_cpu_use_fusion_emitters=false"}
    assert json.loads((tmp_path / "out.json").read_text()) == json.loads(text)
    assert json.loads(capsys.readouterr().out) == json.loads(text)
    monkeypatch.delenv("XLA_FLAGS")
    assert json.loads(emit_json({}))["xla_flags"] == ""
    assert json.loads(emit_json([1.0])) == [1.0]  # only a dict has a place for it


def test_markdown_table_refuses_a_row_of_another_width():
    """A row with fewer cells than headers was written under the wrong columns, silently."""
    assert markdown_table(["a", "b"], [[1, 0.5]]) == "| a | b |\n|---|---|\n| 1 | 0.5 |\n"
    with pytest.raises(ValueError, match=r"^rows\[1\]: has 1 cells for 2 headers"):
        markdown_table(["a", "b"], [[1, 2], [3]])
