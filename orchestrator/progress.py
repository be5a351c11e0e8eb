"""A one-line progress display: rewritten in place on a terminal, one line a second in a log."""

from __future__ import annotations

import sys
import time
from typing import TextIO


class Progress:
    """Shows ``label | key value | ...``; call :meth:`update` as often as you like."""

    def __init__(self, stream: TextIO | None = None, interval: float = 1.0, enabled: bool = True) -> None:
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty()
        self.interval = 0.1 if self.tty else interval
        self.enabled = enabled
        self._last = 0.0
        self._width = 0

    def update(self, text: str, force: bool = False) -> None:
        """Show ``text`` (rate-limited unless ``force``)."""
        if not self.enabled:
            return
        now = time.monotonic()
        if not force and now - self._last < self.interval:
            return
        self._last = now
        if self.tty:
            pad = max(0, self._width - len(text))
            self.stream.write("\r" + text + " " * pad)
            self._width = len(text)
        else:
            self.stream.write(text + "\n")
        self.stream.flush()

    def message(self, text: str) -> None:
        """A line that stays (ends the in-place line first)."""
        if not self.enabled:
            return
        if self.tty and self._width:
            self.stream.write("\n")
            self._width = 0
        self.stream.write(text + "\n")
        self.stream.flush()

    def done(self) -> None:
        """End the in-place line."""
        if self.enabled and self.tty and self._width:
            self.stream.write("\n")
            self.stream.flush()
            self._width = 0


def bar(done: int, total: int, unit: str = "episodes", width: int = 24) -> str:
    """A text progress bar: ``[#####-------] 5/12 episodes``."""
    n = int(round(width * done / max(1, total)))
    return "[" + "#" * n + "-" * (width - n) + f"] {done}/{total} {unit}"
