"""Pairing two sensor streams by stamp, whatever order their messages arrive in.

Each sample of the primary stream (e.g. the IMU) is paired with the sample of the secondary
stream (e.g. the magnetometer) whose stamp is nearest, if it is within ``max_gap_ns``. A primary
sample is decided as soon as a secondary sample at or after its stamp has arrived (the nearest
one can no longer change), or when the primary stream has moved on by more than ``max_gap_ns``
(then only earlier secondaries can pair with it). The result is the same for any interleaving
of the two streams, which is what makes lockstep and live runs agree (CONVENTIONS habit 14).
"""
from __future__ import annotations

from bisect import bisect_left
from collections import deque
from typing import Generic, TypeVar

P = TypeVar('P')
S = TypeVar('S')


class NearestStampPairer(Generic[P, S]):
    """See the module docstring. Stamps are integer nanoseconds, increasing per stream."""

    def __init__(self, max_gap_ns: int, max_pending: int = 256) -> None:
        self.max_gap_ns = int(max_gap_ns)
        self.max_pending = max_pending
        self._pending: deque[tuple[int, P]] = deque()
        self._secondary_t: list[int] = []
        self._secondary_v: list[S] = []
        self._newest_primary = -1

    def reset(self) -> None:
        self._pending.clear()
        self._secondary_t.clear()
        self._secondary_v.clear()
        self._newest_primary = -1

    def add_primary(self, t_ns: int, value: P) -> list[tuple[int, P, S | None]]:
        """Queue a primary sample; returns the (stamp, primary, secondary-or-None) now decided."""
        self._pending.append((t_ns, value))
        self._newest_primary = max(self._newest_primary, t_ns)
        return self._resolve()

    def add_secondary(self, t_ns: int, value: S) -> list[tuple[int, P, S | None]]:
        """Store a secondary sample (older than the last one: ignored); returns decided pairs."""
        if self._secondary_t and t_ns < self._secondary_t[-1]:
            return []
        self._secondary_t.append(t_ns)
        self._secondary_v.append(value)
        return self._resolve()

    def _resolve(self) -> list[tuple[int, P, S | None]]:
        decided: list[tuple[int, P, S | None]] = []
        while self._pending:
            t, value = self._pending[0]
            i = bisect_left(self._secondary_t, t)  # first secondary at or after t
            has_after = i < len(self._secondary_t)
            overdue = self._newest_primary - t > self.max_gap_ns or len(self._pending) > self.max_pending
            if not (has_after or overdue):
                break
            best: S | None = None
            best_gap = self.max_gap_ns + 1
            for j in (i - 1, i):
                if 0 <= j < len(self._secondary_t):
                    gap = abs(self._secondary_t[j] - t)
                    if gap < best_gap:
                        best, best_gap = self._secondary_v[j], gap
            decided.append((t, value, best if best_gap <= self.max_gap_ns else None))
            self._pending.popleft()
        self._trim()
        return decided

    def _trim(self) -> None:
        """Keep only the secondaries that can still pair: from the last one before the oldest
        pending (or newest) primary stamp onwards."""
        anchor = self._pending[0][0] if self._pending else self._newest_primary
        i = bisect_left(self._secondary_t, anchor) - 1
        if i > 0:
            del self._secondary_t[:i]
            del self._secondary_v[:i]
