"""A small progress display for long studies (stderr; a bar on a terminal, lines otherwise)."""

from __future__ import annotations

import sys
import time


class Progress:
    """``with Progress("smf-fdi", total=3) as p: ...; p.advance("L=0 done")``."""

    def __init__(self, label: str, total: int, stream=None):
        self.label, self.total, self.done = label, max(int(total), 1), 0
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

    def _show(self, message):
        elapsed = time.perf_counter() - self.start
        width = 24
        filled = int(width * self.done / self.total)
        bar = "#" * filled + "-" * (width - filled)
        text = f"[{self.label}] [{bar}] {self.done}/{self.total} {elapsed:6.1f}s {message}"
        if self.tty:
            self.stream.write("\r" + text[:120].ljust(120))
        else:
            self.stream.write(text + "\n")
        self.stream.flush()
