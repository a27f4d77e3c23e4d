"""jaxest.xla_flags: which flags reach XLA_FLAGS, and that XLA takes them."""

import os
import subprocess
import sys

import jaxlib
import pytest

from jaxest import xla_flags


def test_adds_the_flags_but_keeps_a_choice_already_made(monkeypatch):
    monkeypatch.setattr(jaxlib, "__version__", "0.10.2")
    monkeypatch.setenv("XLA_FLAGS", "--xla_backend_optimization_level=2 --xla_dump_to=/tmp/x")
    both = xla_flags.FASTER_COMPILATION + xla_flags.UNOPTIMISED_MACHINE_CODE
    assert xla_flags.add(both) == xla_flags.FASTER_COMPILATION
    assert os.environ["XLA_FLAGS"].split() == [
        "--xla_backend_optimization_level=2",
        "--xla_dump_to=/tmp/x",
        *xla_flags.FASTER_COMPILATION,
    ]
    assert xla_flags.add(both) == ()  # a second call adds nothing twice


def test_adds_to_the_environment_of_a_process_to_be_started(monkeypatch):
    monkeypatch.setattr(jaxlib, "__version__", "0.10.2")
    monkeypatch.setenv("XLA_FLAGS", "--xla_dump_to=/tmp/x")
    child = {"XLA_FLAGS": "--xla_cpu_parallel_codegen_split_count=4"}
    both = xla_flags.FASTER_COMPILATION + xla_flags.SERIAL_CODEGEN
    assert xla_flags.add(both, child) == xla_flags.FASTER_COMPILATION
    assert child["XLA_FLAGS"].split() == [
        "--xla_cpu_parallel_codegen_split_count=4",
        *xla_flags.FASTER_COMPILATION,
    ]
    assert os.environ["XLA_FLAGS"] == "--xla_dump_to=/tmp/x"  # this process's: unchanged
    empty = {}
    assert xla_flags.add(xla_flags.SERIAL_CODEGEN, empty) == xla_flags.SERIAL_CODEGEN
    assert empty == {"XLA_FLAGS": xla_flags.SERIAL_CODEGEN[0]}


def test_adds_nothing_on_a_jaxlib_it_was_not_measured_on(monkeypatch):
    monkeypatch.setattr(jaxlib, "__version__", "0.11.2")
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    assert xla_flags.add(xla_flags.FASTER_COMPILATION) == ()
    assert "XLA_FLAGS" not in os.environ


@pytest.mark.parametrize("flag", ["xla_cpu_use_fusion_emitters=false", "--xla_dump_to"])
def test_a_malformed_flag_names_the_argument(flag):
    with pytest.raises(ValueError, match="^flags:"):
        xla_flags.add((flag,))


_COMPILED_TEXT = """
import sys
from jaxest import xla_flags
import jax, jax.numpy as jnp
if sys.argv[1] == "add":
    xla_flags.add(xla_flags.FASTER_COMPILATION)
f = lambda x: jnp.tanh(x[:, None] * x[None, :]).sum(0) + jnp.exp(x).cumsum()
print(jax.jit(f).lower(jnp.ones(8)).compile().as_text())
"""


@pytest.mark.skipif(
    not jaxlib.__version__.startswith(xla_flags.MEASURED_JAXLIB), reason="flags not measured here"
)
def test_flags_added_before_the_first_computation_reach_xla():
    """The compiled program differs from the default one, so XLA read the flag."""
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    texts = [
        subprocess.run(
            [sys.executable, "-c", _COMPILED_TEXT, mode],
            env=env,
            capture_output=True,
            text=True,
            check=True,
        ).stdout
        for mode in ("default", "add")
    ]
    assert texts[0] != texts[1]
