"""Mapping runs while the tracker waits for a frame (Klein & Murray 2009 sec. 3).

PTAM on the iPhone has one core; it works because "bundle adjustment only runs while the tracking
thread is waiting for a new frame" (sec. 3, thread priorities). In Python the two threads share
one interpreter lock, and gtsam's optimiser holds it for a whole Levenberg-Marquardt iteration, so
mapping work that overlaps a frame stalls the tracker (and plain Python work time-slices with it
every ``sys.getswitchinterval()``). :class:`FrameGate` restores the paper's behaviour
cooperatively: the tracker reports the start and the end of every frame, and the mapping thread
calls :meth:`FrameGate.checkpoint` before each step of its work (one bundle-adjustment iteration,
one keyframe insertion step, ...). A checkpoint returns at once unless a frame is being tracked
or the step's expected cost does not fit before the next frame is due (the frame period is
learnt from the frame starts); otherwise the mapping thread sleeps (without the interpreter lock)
until the tracker is between frames again.

Progress is guaranteed: a step waits for at most one frame (when frames come back to back there
is no idle time at all; mapping then gets one step per frame) and at most ``max_wait_s``; while
someone waits for the mapper (:meth:`opened`, e.g. lockstep runs calling
``SlamSystem.wait_for_mapping`` after each frame) the gate does not hold the mapper at all, so
those runs stay deterministic. Only the thread bound with :meth:`bind` is ever held; calls from
any other thread (``process_queue`` in the caller, ``initialise_map`` from the tracker) pass.
"""
from __future__ import annotations

import threading
import time
from contextlib import contextmanager
from typing import Any, Iterator


class FrameGate:
    """Frame start/end signals from the tracker; step checkpoints for the mapping thread."""

    def __init__(self, max_wait_s: float = 0.5, margin_s: float = 0.002,
                 default_cost_s: float = 0.005) -> None:
        self.max_wait_s = float(max_wait_s)
        self.margin_s = float(margin_s)
        self.default_cost_s = float(default_cost_s)
        self.enabled = True
        self._cond = threading.Condition()
        self._thread: threading.Thread | None = None
        self._tracking = False
        self._frames_done = 0
        self._last_start: float | None = None
        self._period: float | None = None
        self._open = 0
        self._released = False
        #: Expected cost (s) of the step after a checkpoint of each label (rises at once, decays).
        self._cost: dict[str, float] = {}
        self._step_label: str | None = None
        self._step_t0 = 0.0
        self.stats: dict[str, Any] = {'checkpoints': 0, 'held': 0, 'held_s': 0.0,
                                      'steps_in_frame': 0, 'max_step_ms': {}}

    # ---- tracker side ------------------------------------------------------------------------
    def frame_started(self) -> None:
        now = time.perf_counter()
        with self._cond:
            if self._last_start is not None:
                dt = now - self._last_start
                if 0.0 < dt < 1.0:
                    # Frame period: a running estimate that follows a slower rate at once.
                    self._period = dt if self._period is None else max(min(dt, 1.5 * self._period),
                                                                       0.9 * self._period + 0.1 * dt)
            self._last_start = now
            self._tracking = True

    def frame_finished(self) -> None:
        with self._cond:
            self._tracking = False
            self._frames_done += 1
            self._cond.notify_all()

    @property
    def tracking(self) -> bool:
        """True while the tracker works on a frame."""
        return self._tracking

    # ---- waiting for the mapper -----------------------------------------------------------------
    @contextmanager
    def opened(self) -> Iterator[None]:
        """The gate holds nothing inside this block (someone waits for the mapper)."""
        with self._cond:
            self._open += 1
            self._cond.notify_all()
        try:
            yield
        finally:
            with self._cond:
                self._open -= 1

    def release(self) -> None:
        """Opens the gate for good (the mapper is stopping)."""
        with self._cond:
            self._released = True
            self._cond.notify_all()

    # ---- mapper side ---------------------------------------------------------------------------
    def bind(self, thread: threading.Thread | None = None) -> None:
        """The thread whose checkpoints may block (default: the calling thread)."""
        self._thread = thread or threading.current_thread()
        self._released = False

    def idle(self) -> None:
        """Ends the current step without starting another (the mapper has no work)."""
        self._end_step(time.perf_counter())
        self._step_label = None

    def checkpoint(self, label: str) -> float:
        """Called by the mapping thread before a step ``label``; returns the seconds it was held."""
        if threading.current_thread() is not self._thread:
            return 0.0  # the caller's own thread (process_queue, initialise_map): never held
        now = time.perf_counter()
        self._end_step(now)
        held = 0.0
        if self.enabled:
            held = self._wait(self._cost.get(label, self.default_cost_s), now)
        self._step_label = label
        self._step_t0 = time.perf_counter()
        if self._tracking:
            self.stats['steps_in_frame'] += 1
        return held

    def _end_step(self, now: float) -> None:
        lab = self._step_label
        if lab is None:
            return
        d = now - self._step_t0
        self._cost[lab] = max(d, 0.8 * self._cost.get(lab, d))
        mx = self.stats['max_step_ms']
        mx[lab] = max(mx.get(lab, 0.0), d * 1e3)

    def _fits(self, cost: float, now: float) -> tuple[bool, float]:
        """(does a step of ``cost`` s end before the next frame is due, seconds until that changes)."""
        if self._last_start is None or self._period is None:
            return True, 0.0
        due = self._last_start + self._period
        if now + cost + self.margin_s <= due:
            return True, 0.0
        overdue = due + 0.5 * self._period  # frames stopped coming regularly: do not wait on them
        if now >= overdue:
            return True, 0.0
        return False, overdue - now

    def _wait(self, cost: float, t0: float) -> float:
        self.stats['checkpoints'] += 1
        with self._cond:
            seen = self._frames_done
            held = False
            while True:
                now = time.perf_counter()
                if self._open or self._released or now - t0 >= self.max_wait_s:
                    break
                if self._frames_done > seen:
                    break  # a whole frame went by while this step waited: its turn now
                timeout = self.max_wait_s - (now - t0)
                if not self._tracking:
                    ok, until = self._fits(cost, now)
                    if ok:
                        break
                    timeout = min(timeout, until)
                held = True
                self._cond.wait(max(timeout, 1e-4))
        waited = time.perf_counter() - t0
        if held:
            self.stats['held'] += 1
            self.stats['held_s'] += waited
        return waited


__all__ = ['FrameGate']
