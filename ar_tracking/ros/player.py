"""Plays a bag schedule into a node's publishers, on a background thread paced by wall time."""
from __future__ import annotations

import threading
import time
from typing import Any, Callable

from rclpy.serialization import deserialize_message

from ..io.bags import BagError, BagReader
from ..io.replay import ReplayOptions, ScheduledMessage, schedule
from .conversions import message_class


#: How often a bag player publishes /clock, in bag time: 100 Hz, as ``ros2 bag play --clock 100``.
#: (Before every message it was ~420 Hz on a phone bag - IMU, field, camera, truth - and every
#: node with ``use_sim_time`` took each one: a third of imu_magnetometer's CPU live.)
CLOCK_PERIOD_S = 0.01


class ClockTicker:
    """When a bag player publishes /clock: before the first message, then before each message at
    least ``period_ns`` of bag time after the last tick, and whenever the time goes back (a loop);
    ``period_ns`` 0: before every message. The clock so lags the message being published by less
    than the period - nodes here stamp their outputs from their inputs' headers, and sim-time
    timers and throttled logs need no finer clock."""

    def __init__(self, period_ns: int = int(CLOCK_PERIOD_S * 1e9)) -> None:
        self.period_ns = max(0, int(period_ns))
        self._last_ns: int | None = None

    def due(self, t_ns: int) -> bool:
        """Whether /clock should be published (with ``t_ns``) before the message at ``t_ns``."""
        last = self._last_ns
        if last is not None and 0 <= t_ns - last < self.period_ns:
            return False
        self._last_ns = t_ns
        return True


class BagPlayer:
    """Reads a bag on a thread and hands each due message to ``on_message``.

    ``on_message(scheduled, msg_class)`` publishes; ``on_done(error_or_None)`` is called once at
    the end (an unreadable bag ends the playback with one error line, never a traceback).
    """

    def __init__(
        self,
        path: str,
        options: ReplayOptions,
        on_message: Callable[[ScheduledMessage], None],
        on_done: Callable[[str | None], None],
    ) -> None:
        self.path = path
        self.options = options
        self.on_message = on_message
        self.on_done = on_done
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name='bag_player', daemon=True)
        self.published = 0

    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout_s: float = 2.0) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout_s)

    @property
    def running(self) -> bool:
        return self._thread.is_alive()

    @property
    def stopped(self) -> bool:
        """stop() was called (Ctrl-C, node shutdown)."""
        return self._stop.is_set()

    def wait_stop(self, timeout_s: float) -> bool:
        """Wait up to timeout_s for stop(); True if it came."""
        return self._stop.wait(timeout_s)

    def _run(self) -> None:
        error: str | None = None
        try:
            with BagReader(self.path) as bag:
                start = time.monotonic()
                for item in schedule(bag, self.options):
                    if self._stop.is_set():
                        break
                    delay = start + item.due_s - time.monotonic()
                    if delay > 0 and self._stop.wait(delay):
                        break
                    self.on_message(item)
                    self.published += 1
        except BagError as exc:
            error = str(exc)
        except Exception as exc:  # a publisher torn down during shutdown, etc.
            if not self._stop.is_set():
                error = f'{type(exc).__name__}: {exc}'
        self.on_done(error)


def decode(raw: bytes, msgtype: str) -> Any:
    """rclpy message from CDR bytes of a bag."""
    return deserialize_message(raw, message_class(msgtype))
