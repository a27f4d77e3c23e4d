"""Every benchmark script loads and parses its options: most are run by hand, not by a test,
and a renamed function in jaxest (``parallel.grid_points``) breaks them unseen."""

import os
import sys

import pytest

from tests import benchmark_scripts

#: the scripts; ``_name.py`` is a module the scripts share
SCRIPTS = sorted(
    path.stem for path in benchmark_scripts.BENCHMARKS.glob("*.py") if not path.stem.startswith("_")
)


@pytest.mark.parametrize("name", SCRIPTS)
def test_script_loads_and_prints_its_help(name, monkeypatch, capsys):
    # scripts may set XLA_FLAGS for what they start (profile_step): restored after the test
    monkeypatch.setenv("XLA_FLAGS", os.environ.get("XLA_FLAGS", ""))
    monkeypatch.syspath_prepend(benchmark_scripts.BENCHMARKS)  # as run: siblings import by name
    module = benchmark_scripts.load(name)
    monkeypatch.setattr(sys, "argv", [f"{name}.py", "--help"])
    with pytest.raises(SystemExit) as exit_:
        module.main()
    assert exit_.value.code == 0
    assert capsys.readouterr().out.startswith("usage:")


def test_profiles_count_each_run_of_an_operation_and_leave_control_flow_out(monkeypatch):
    # the trace also has the runtime's spans and an event per loop, whose length depends on how
    # XLA runs the loop (here the whole of it): the shares' denominator leaves both out
    import jax
    import jax.numpy as jnp

    monkeypatch.setenv("XLA_FLAGS", os.environ.get("XLA_FLAGS", ""))
    xla_trace = benchmark_scripts.load("_xla_trace")

    def twenty_factorisations(A):
        step = lambda i, A: jnp.linalg.cholesky(A) * 2 + jnp.eye(3) * (1 + jnp.sin(1.0 * i))
        return jax.lax.fori_loop(0, 20, step, A)

    A = jnp.broadcast_to(2 * jnp.eye(3), (50, 3, 3))
    compiled = jax.jit(twenty_factorisations).lower(A).compile()
    jax.block_until_ready(compiled(A))
    total, calls, runs_as = xla_trace.traced_operations(lambda: compiled(A), compiled.as_text())
    (factorisation,) = [name for name, kind in runs_as.items() if kind.endswith("potrf_ffi")]
    assert "while" in runs_as.values()
    assert calls[factorisation] == 20
    assert "while" not in {runs_as[name] for name in total}
    assert all(name in runs_as for name in total)  # no runtime span
