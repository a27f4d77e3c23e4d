"""A small progress display for long studies (stderr; a bar on a terminal, lines otherwise).

Written here rather than taken from tqdm or rich: a study advances a few dozen times, each step
seconds to minutes, and needs a bar, the elapsed time and an estimate of what remains, which is
less code than adapting a dependency's defaults (per-iteration rates, refresh threads) to it.
"""

from __future__ import annotations

import sys
import time


class Progress:
    """``with Progress("smf-fdi", total=3) as p: ...; p.advance("L=0 done")``.

    ``weights``: each step's expected cost, in order (``total`` defaults to their number), for
    a study whose steps differ in cost: the bar and the estimate of what remains then count
    cost done, not steps done. Equal by default."""

    def __init__(self, label: str, total: int | None = None, stream=None, weights=None):
        if total is None and weights is None:
            raise ValueError("total: give the number of steps, or their weights")
        total = len(weights) if total is None else total
        self.label, self.total, self.done = label, max(int(total), 1), 0
        self.weights = [1.0] * self.total if weights is None else [float(w) for w in weights]
        if len(self.weights) != self.total or not all(w > 0 for w in self.weights):
            raise ValueError(f"weights: {self.total} positive costs expected, got {weights!r}")
        self.stream = stream or sys.stderr
        self.start = time.perf_counter()
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()

    def __enter__(self):
        self._show("starting")
        return self

    def __exit__(self, *exc):
        if self.tty:
            self.stream.write("\n")
        self.stream.flush()
        return False

    def advance(self, message: str = "", steps: int = 1):
        self.done = min(self.done + steps, self.total)
        self._show(message)

    def fraction(self) -> float:
        """The share of the expected cost done."""
        return sum(self.weights[: self.done]) / sum(self.weights)

    def remaining(self, elapsed: float) -> float | None:
        """Seconds left if the steps still to come cost, per unit of weight, what the finished
        ones did (None before the first step): a guide, since the weights are estimates."""
        if self.done == 0:
            return None
        return elapsed * (1 - self.fraction()) / self.fraction()

    def _show(self, message):
        elapsed = time.perf_counter() - self.start
        width = 24
        filled = int(width * self.fraction())
        bar = "#" * filled + "-" * (width - filled)
        left = self.remaining(elapsed)
        estimate = "" if left is None or self.done == self.total else f" ~{left:.0f}s left"
        text = (
            f"[{self.label}] [{bar}] {self.done}/{self.total} {elapsed:6.1f}s{estimate} {message}"
        )
        if self.tty:
            self.stream.write("\r" + text[:120].ljust(120))
        else:
            self.stream.write(text + "\n")
        self.stream.flush()
