"""Stop on Ctrl-C / SIGTERM between two units of work, for the graph runner and every node's main.

Raising KeyboardInterrupt from a signal handler lands wherever the main thread happens to be:
inside the bag writer's bookkeeping (a corrupt bag) or inside rclpy's take of a message
(pybind11 turns it into a RuntimeError traceback and the node exits 1). A flag that the loops
check cannot. Imports nothing of rclpy, so that a node does not pull in the runner's modules.
"""
from __future__ import annotations

import signal
import threading
from typing import Any


class StopOnSignal:
    """Within the block, Ctrl-C (SIGINT) and SIGTERM ask the run to stop between two messages.

    Raising KeyboardInterrupt from the handler could land inside the bag writer's bookkeeping
    and leave a corrupt bag; a flag checked by the playback loops cannot. A second signal
    raises KeyboardInterrupt at once (for a run stuck somewhere else).
    """

    def __init__(self) -> None:
        self.requested = threading.Event()
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> 'StopOnSignal':
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous[sig] = signal.signal(sig, self._handler)
        return self

    def _handler(self, signum: int, frame: Any) -> None:
        if self.requested.is_set():
            raise KeyboardInterrupt
        self.requested.set()

    def __exit__(self, *exc: object) -> None:
        for sig, previous in self._previous.items():
            signal.signal(sig, previous)
