"""jaxest.gc_thresholds: the collector settings for processes that trace and compile a lot."""

import gc

from jaxest import gc_thresholds


def test_collect_rarely_sets_the_thresholds_and_returns_the_earlier_ones():
    suite_thresholds = gc.get_threshold()
    try:
        gc.set_threshold(700, 10, 10)
        assert gc_thresholds.collect_rarely() == (700, 10, 10)
        assert gc.get_threshold() == gc_thresholds.FOR_TRACING
        # fewer young collections than the default, and full ones still happen
        assert gc_thresholds.FOR_TRACING[0] > 700 and gc_thresholds.FOR_TRACING[2] > 0
    finally:
        gc.set_threshold(*suite_thresholds)
