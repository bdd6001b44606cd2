"""Logging that cannot flood: a message key logs at most once per period."""

from __future__ import annotations

import logging
import time
from typing import Any


class RateLimitedLogger:
    """Wraps a logger; each ``key`` logs at most once per ``period_s``, with a count of
    the occurrences it held back."""

    def __init__(self, logger: logging.Logger, period_s: float = 5.0) -> None:
        self.logger = logger
        self.period_s = period_s
        self._last: dict[str, float] = {}
        self._held: dict[str, int] = {}

    def log(self, level: int, key: str, msg: str, *args: Any) -> None:
        now = time.monotonic()
        last = self._last.get(key)
        if last is not None and now - last < self.period_s:
            self._held[key] = self._held.get(key, 0) + 1
            return
        held = self._held.pop(key, 0)
        self._last[key] = now
        if held:
            msg = f"{msg} (and {held} more in {self.period_s:g} s)"
        self.logger.log(level, msg, *args)

    def info(self, key: str, msg: str, *args: Any) -> None:
        self.log(logging.INFO, key, msg, *args)

    def warning(self, key: str, msg: str, *args: Any) -> None:
        self.log(logging.WARNING, key, msg, *args)
