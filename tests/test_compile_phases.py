"""benchmarks/compile_phases.py: its equation count and its split of a first call."""

import jax
import jax.numpy as jnp
from jax import lax

from tests import benchmark_scripts

benchmark_scripts.load("speed")  # compile_phases imports it by name, as when run as a script
compile_phases = benchmark_scripts.load("compile_phases")


def doubled_plus_one(x):
    return lax.scan(lambda c, _: (2.0 * c + 1.0, None), x, None, length=3)[0]


def test_equations_count_the_ones_inside_a_scan_and_a_jit():
    # the scan equation and its body's multiply and add
    assert compile_phases.equations(jax.make_jaxpr(doubled_plus_one)(1.0).jaxpr) == 3
    # a jit equation, then the scan's three inside it, then a sine
    nested = lambda x: jnp.sin(jax.jit(doubled_plus_one)(x))
    assert compile_phases.equations(jax.make_jaxpr(nested)(1.0).jaxpr) == 5


def test_phases_time_each_step_of_a_cold_first_call():
    result = compile_phases.phases(doubled_plus_one, (jnp.ones(4),), None, repeats=2)
    assert result["equations"] == 3
    assert all(result[key] > 0 for key in ("trace_s", "lower_s", "compile_s"))
