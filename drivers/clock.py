"""Clocks: real time for the demo and hardware, simulated time for deterministic tests.

Every timed loop calls ``clock.sleep_until(t)``: the real clock sleeps, the simulated clock
jumps, so the same code runs in both and a simulated run is as fast as the CPU allows.
"""

from __future__ import annotations

import threading
import time
from typing import Protocol


class Clock(Protocol):
    """Monotonic seconds."""

    def now(self) -> float:
        """Current time, s."""

    def sleep_until(self, t: float) -> None:
        """Return when ``now() >= t``."""


class RealClock:
    """Wall-clock monotonic time (``time.monotonic``)."""

    def now(self) -> float:
        """Current monotonic time, s."""
        return time.monotonic()

    def sleep_until(self, t: float) -> None:
        """Sleep until ``t`` (returns at once when it is past)."""
        dt = t - time.monotonic()
        if dt > 0:
            time.sleep(dt)


class SimClock:
    """Simulated time starting at ``start``; ``sleep_until`` advances it instantly (never backwards)."""

    def __init__(self, start: float = 0.0) -> None:
        self._t = float(start)
        self._lock = threading.Lock()

    def now(self) -> float:
        """Current simulated time, s."""
        return self._t

    def sleep_until(self, t: float) -> None:
        """Advance simulated time to ``t`` if it is later."""
        with self._lock:
            if t > self._t:
                self._t = float(t)
