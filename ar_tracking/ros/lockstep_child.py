"""The node process's side of the lockstep over node processes (:mod:`.parallel_lockstep`).

In a node process of a lockstep run nothing goes over DDS: the runner sends batches of steps
over the process's pipe, :func:`serve_steps` runs the node's subscription callbacks on them in
the order sent, and the node's publications - taken by :func:`publication_tap` instead of being
handed to DDS - go back to the runner per step.
"""
from __future__ import annotations

import queue
import threading
import time
from collections import defaultdict
from typing import Any, Callable

#: A node process sends the outputs of the steps it has done once it has worked this long
#: since it last sent, s (else at the end of the runner's batch): a node downstream of a slow
#: one (the hybrid behind the mapper) gets each step's outputs as they are done, while a fast
#: node's outputs still go back a batch at a time.
SEND_AFTER_S = 0.002


def serve_steps(node: Any, conn: Any, outbox: list[tuple[str, bytes]]) -> None:
    """In the node's process: run its subscriptions' callbacks on the batches the runner sends,
    in the order sent, and send back what the node published (``outbox``, filled by the node's
    ``publish_tap``) for each step. Returns when the runner sends ``('stop',)``.

    A pipe reader thread takes the runner's messages as they come, so that the runner never
    waits on a node busy with a step while it sends it the next ones. Outputs go back at the
    end of each batch, or as soon as ``SEND_AFTER_S`` of work has passed since the last send."""
    from rclpy.serialization import deserialize_message

    subscriptions: dict[str, list[Any]] = defaultdict(list)
    for sub in node.subscriptions:
        subscriptions[sub.topic_name].append(sub)
    inbox: queue.SimpleQueue[Any] = queue.SimpleQueue()
    threading.Thread(target=_read_pipe, args=(conn, inbox), daemon=True, name='lockstep_pipe').start()
    while True:
        item = inbox.get()
        if item[0] != 'steps':
            return
        results = []
        sent = time.perf_counter()
        for seq, batch in item[1]:
            unread: list[str] = []
            for topic, raw in batch:
                for sub in subscriptions.get(topic, ()):
                    if sub.raw:
                        msg: Any = raw
                    else:
                        try:
                            msg = deserialize_message(raw, sub.msg_type)
                        except Exception:  # noqa: BLE001 - not the declared type: dropped, as rclpy would
                            unread.append(topic)
                            continue
                    before = getattr(node, 'unreadable', 0)
                    sub.callback(msg)  # the node's guarded callback: a failure is logged, not raised
                    if getattr(node, 'unreadable', 0) != before:  # a view that could not read it
                        unread.append(topic)
            results.append((seq, list(outbox), unread))
            outbox.clear()
            if time.perf_counter() - sent > SEND_AFTER_S:  # a slow node's outputs go out at once
                conn.send(('outs', results))
                results, sent = [], time.perf_counter()
        if results:
            conn.send(('outs', results))


def _read_pipe(conn: Any, inbox: queue.SimpleQueue[Any]) -> None:
    """Move the runner's messages into ``inbox`` until ``stop`` (or the pipe closes)."""
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            inbox.put(('stop',))
            return
        inbox.put(msg)
        if msg[0] != 'steps':
            return


def publication_tap(outbox: list[tuple[str, bytes]], msgtypes: dict[str, str]) -> Callable[[str, Any], None]:
    """A ``TrackingNode.publish_tap`` that keeps each publication's CDR bytes in ``outbox``
    instead of handing it to DDS. ``msgtypes``: the node's output topics -> message types.

    rclpy's ``serialize_message`` leaves the CDR alignment padding uninitialised (a string's
    padding held heap bytes that changed from run to run), where DDS writes zeros; so a message
    object is serialised by rclpy, read back and written again by rosbags, whose padding is zero:
    the bytes DDS would carry (0.4 ms for a 2 MB panorama image)."""
    from rclpy.serialization import serialize_message

    from ..io.bags import TYPESTORE

    types = {'/' + t.lstrip('/'): ty for t, ty in msgtypes.items()}

    def tap(topic: str, msg: Any) -> None:
        if isinstance(msg, (bytes, bytearray, memoryview)):
            raw = bytes(msg)
        else:
            raw = serialize_message(msg)
            msgtype = types.get(topic)
            if msgtype is not None:
                raw = bytes(TYPESTORE.serialize_cdr(TYPESTORE.deserialize_cdr(raw, msgtype), msgtype))
        outbox.append((topic, raw))
    return tap
