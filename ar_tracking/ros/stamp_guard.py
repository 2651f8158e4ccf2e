"""Stamp checks every node applies to its inputs (DESIGN sec. 7, CONVENTIONS habit 9/14).

Zero stamps are dropped; a stamp older than the previous one is dropped, unless it is older by
more than ``reset_after_s`` (a bag that loops, a clock that restarts): then the stream is
declared new, the node resets its state, and processing goes on.
"""
from __future__ import annotations

import enum


class StampVerdict(enum.Enum):
    OK = 'ok'
    ZERO = 'zero stamp'
    OLDER = 'stamp older than the previous message'
    DUPLICATE = 'same stamp as the previous message'
    RESET = 'clock jumped back; state reset'


class StampGuard:
    """Tracks the last stamp of one input stream (integer nanoseconds)."""

    def __init__(self, reset_after_s: float = 1.0, allow_duplicates: bool = False) -> None:
        self.reset_after_ns = int(reset_after_s * 1e9)
        self.allow_duplicates = allow_duplicates
        self.last_ns: int | None = None

    def check(self, stamp_ns: int) -> StampVerdict:
        if stamp_ns <= 0:
            return StampVerdict.ZERO
        last = self.last_ns
        if last is not None:
            if stamp_ns == last and not self.allow_duplicates:
                return StampVerdict.DUPLICATE
            if stamp_ns < last:
                if last - stamp_ns > self.reset_after_ns:
                    self.last_ns = stamp_ns
                    return StampVerdict.RESET
                return StampVerdict.OLDER
        self.last_ns = stamp_ns
        return StampVerdict.OK

    def reset(self) -> None:
        self.last_ns = None
