"""Plays a bag schedule into a node's publishers, on a background thread paced by wall time."""
from __future__ import annotations

import threading
import time
from typing import Any, Callable

from rclpy.serialization import deserialize_message

from ..io.bags import BagError, BagReader
from ..io.replay import ReplayOptions, ScheduledMessage, schedule
from .conversions import message_class


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
