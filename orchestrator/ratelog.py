"""Problems that can repeat every frame (malformed bus messages) counted per kind and logged once per kind."""

from __future__ import annotations

import logging
from collections import Counter


class OncePerKind:
    """Count problems by kind; log the first of each kind in one line (no traceback), count the rest.

    A peer sending a malformed message 30 times a second gives one log line, not a flood.
    """

    def __init__(self, logger: logging.Logger, what: str) -> None:
        self.logger = logger
        self.what = what
        self.counts: Counter[str] = Counter()

    def report(self, kind: str, detail: str) -> None:
        """Count one problem of ``kind``; the first of a kind is logged as a warning."""
        self.counts[kind] += 1
        if self.counts[kind] == 1:
            self.logger.warning("%s (%s): %s; further ones of this kind are counted, not logged",
                                self.what, kind, detail)

    @property
    def total(self) -> int:
        """Problems counted over all kinds."""
        return sum(self.counts.values())
