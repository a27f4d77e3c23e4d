import jax
import pytest

from jaxest import compile_cache, gc_thresholds, xla_flags

# The suite compiles far more than it runs: XLA flags that compile faster (jaxest.xla_flags has
# the measurements), added before the first computation; subprocesses inherit them.
xla_flags.add(
    xla_flags.FASTER_COMPILATION + xla_flags.UNOPTIMISED_MACHINE_CODE + xla_flags.SERIAL_CODEGEN
)

# Tests work in float64 unless they cast to float32 themselves; jaxest never flips this on import.
jax.config.update("jax_enable_x64", True)


# JAX's persistent compilation cache only where JAXEST_COMPILATION_CACHE=1 asks for it
# (jaxest.compile_cache says why it is off by default); subprocesses inherit it.
compile_cache.enable()

# Python's cyclic garbage collector, run 30-40 times less often: at its default thresholds it took
# 23-31 s of each worker's CPU (jaxest.gc_thresholds has the measurements).
gc_thresholds.collect_rarely()


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drop every compiled program after each test module. A pytest-xdist worker otherwise keeps
    all it compiled: in a fresh-clone run its memory grew steadily to 5.6 and 6.4 GB, and the
    last two of the jaxlib aborts below came late (after 77 % and 89 % of the tests), each
    while compiling in a worker that had run hundreds of tests. Whether that accumulation
    causes them is not known; releasing it costs a few recompilations of shared programs."""
    yield
    jax.clear_caches()


#: how often each test's worker process crashed (pytest-xdist)
_crashes: dict[str, int] = {}


def pytest_handlecrashitem(crashitem, report, sched):
    """Run a test whose pytest-xdist worker crashed once more, in a fresh worker; a second crash
    fails it. jaxlib 0.10 crashes a process now and then inside XLA: in four full runs of the
    suite on 2-core CPUs (CI and clean clones), one worker each died in a different test (a segmentation fault in
    ``executable.serialize()``, an abort or a segmentation fault in ``backend_compile_and_load``), and each
    of those tests passes when run again. Only a dead worker is retried; a failing assertion is not."""
    _crashes[crashitem] = _crashes.get(crashitem, 0) + 1
    if _crashes[crashitem] == 1:
        sched.mark_test_pending(crashitem)
        report.outcome = "rerun"
