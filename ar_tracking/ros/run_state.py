"""The state of one graph run: its result, the lockstep delivery ledger, the output recorder.

Split out of :mod:`ar_tracking.ros.runner` (which re-exports the public names): the runner's
set-up, lockstep feeding, realtime playback (:mod:`ar_tracking.ros.live_play`) and teardown
share one :class:`RunSession`, and each part reads and books what it needs there.
"""
from __future__ import annotations

import logging
import math
import threading
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..io.bags import BagReader, BagWriter
from ..io.static_tf import TF_STATIC_TOPIC, static_transforms

logger = logging.getLogger('ar_tracking.ros.runner')  # what it logs is the runner's

#: Realtime: after the last input, spin until the nodes have processed nothing more for
#: this long (their queues are empty), at most DRAIN_MAX_S.
DRAIN_QUIET_S = 0.5
DRAIN_MAX_S = 10.0


def header_stamp_ns(raw: bytes) -> int | None:
    """The header stamp (ns) of a serialised message that starts with std_msgs/Header, read
    from its CDR bytes without deserialising (4-byte encapsulation, then int32 sec and uint32
    nanosec); None if too short."""
    if len(raw) < 12:
        return None
    order = 'little' if raw[1] & 1 else 'big'
    sec = int.from_bytes(raw[4:8], order, signed=True)
    nsec = int.from_bytes(raw[8:12], order)
    return sec * 1_000_000_000 + nsec



@dataclass
class RunResult:
    """What one run did: counts, time, and every message a subscription did not get.

    Lockstep accounting (see :class:`DeliveryLedger`): ``superseded`` counts the messages that
    a KEEP_LAST depth-1 subscription (a node that wants only the latest value, e.g. a map or
    the current labels) replaced by a newer one; ``dropped`` the messages a deeper queue
    overflowed with (a burst larger than the node's depth: the node may have needed them);
    ``lost`` the deliveries that did not happen within the step timeout (a bug or a message
    that does not deserialise). Each maps node name -> topic -> count.
    """

    out_path: Path
    input_messages: int = 0
    output_messages: int = 0
    #: the playback's wall time (what ``realtime_factor`` divides by), s
    wall_s: float = 0.0
    #: from the run's start to the playback's: starting the nodes (their processes) and matching, s
    start_s: float = 0.0
    #: which executor layout ran the nodes (``--executor`` with 'auto' resolved)
    executor: str = ''
    bag_duration_s: float = 0.0
    interrupted: bool = False
    lost_deliveries: int = 0
    nodes: list[str] = field(default_factory=list)
    #: node name -> input topic -> processing times in ms
    timings_ms: dict[str, dict[str, list[float]]] = field(default_factory=dict)
    #: node name -> why it was not started (missing inputs or parameters, the automatic rule)
    not_started: dict[str, str] = field(default_factory=dict)
    superseded: dict[str, dict[str, int]] = field(default_factory=dict)
    dropped: dict[str, dict[str, int]] = field(default_factory=dict)
    lost: dict[str, dict[str, int]] = field(default_factory=dict)
    #: realtime only: node -> input topic -> (messages published on it, messages the node's
    #: callback processed); the difference is what the node never saw (a full queue, a
    #: best-effort loss) - see :attr:`live_dropped`
    live_inputs: dict[str, dict[str, tuple[int, int]]] = field(default_factory=dict)
    #: realtime only: end-to-end latency of each ``orientation/global`` message received by the
    #: recorder, ms: wall time of receipt minus wall time at which the runner published the
    #: input (a camera image if the graph is fed any, else any input) with the same stamp
    live_latency_ms: list[float] = field(default_factory=list)
    #: realtime only: how late the player published inputs against the bag schedule, ms (p95);
    #: large values mean the player itself was starved, not the nodes
    live_player_late_ms_p95: float = 0.0
    #: CPU seconds of each node process (``--executor processes``, lockstep too: all its
    #: threads, DDS's included) or of the thread that spun it (threads); where the live time goes
    live_cpu_s: dict[str, float] = field(default_factory=dict)
    #: node name -> why it stopped working (its thread died); the run ends non-zero
    failed_nodes: dict[str, str] = field(default_factory=dict)

    @property
    def realtime_factor(self) -> float:
        return self.bag_duration_s / self.wall_s if self.wall_s > 0 else float('inf')

    @property
    def superseded_deliveries(self) -> int:
        return sum(n for topics in self.superseded.values() for n in topics.values())

    @property
    def dropped_deliveries(self) -> int:
        return sum(n for topics in self.dropped.values() for n in topics.values())

    @property
    def live_dropped(self) -> dict[str, int]:
        """Realtime: node -> inputs published to it that its callbacks never processed."""
        return {node: sum(max(0, pub - done) for pub, done in topics.values())
                for node, topics in self.live_inputs.items()}

    def live_latency_percentile(self, q: float) -> float | None:
        """Percentile ``q`` (0-100) of :attr:`live_latency_ms`, ms; None without samples."""
        if not self.live_latency_ms:
            return None
        ordered = sorted(self.live_latency_ms)
        # linear interpolation between closest ranks (numpy's default)
        pos = (len(ordered) - 1) * q / 100.0
        lo = int(math.floor(pos))
        hi = min(lo + 1, len(ordered) - 1)
        return ordered[lo] + (ordered[hi] - ordered[lo]) * (pos - lo)

    def live_summary(self) -> dict[str, Any]:
        """The realtime figures as one JSON-ready dict (``live`` of the CLI summary and bench):
        dropped per node, published/processed per node and topic, latency p50/p95 in ms, CPU
        seconds per node."""
        p50 = self.live_latency_percentile(50)
        p95 = self.live_latency_percentile(95)
        return {
            'dropped': self.live_dropped,
            'inputs': {node: {t: {'published': pub, 'processed': done} for t, (pub, done) in sorted(topics.items())}
                       for node, topics in sorted(self.live_inputs.items())},
            'latency_ms_p50': None if p50 is None else round(p50, 3),
            'latency_ms_p95': None if p95 is None else round(p95, 3),
            'latency_n': len(self.live_latency_ms),
            'player_late_ms_p95': round(self.live_player_late_ms_p95, 3),
            'cpu_s': {node: round(cpu, 3) for node, cpu in sorted(self.live_cpu_s.items())},
        }


class SubscriptionAccount:
    """One subscription's side of the ledger."""

    __slots__ = ('node', 'topic', 'depth', 'queued', 'in_flight', 'superseded', 'lost')

    def __init__(self, node: str, topic: str, depth: int | None) -> None:
        self.node = node
        self.topic = topic
        #: KEEP_LAST depth; None for KEEP_ALL (never drops)
        self.depth = depth
        self.queued = 0
        self.in_flight = 0
        self.superseded = 0
        self.lost = 0


class DeliveryLedger:
    """Exact lockstep accounting of deliveries, per subscription.

    All nodes share one process and DDS delivers a publish into each matching reader's history
    at once, so at publish time the runner knows for each subscription of the topic how many
    messages wait in its history; if that history is KEEP_LAST and already full, the oldest
    waiting message is replaced - it is counted as superseded, not waited for. A step is
    settled when no subscription has a message waiting or a callback running.

    Should DDS keep a message the ledger counted as replaced (it never has in our tests), the
    delivery cancels that count; should it lose one the ledger expects, the runner's step
    timeout still ends the wait and reports it as lost.
    """

    def __init__(self) -> None:
        self.by_topic: dict[str, list[SubscriptionAccount]] = defaultdict(list)
        self.by_sub: dict[int, SubscriptionAccount] = {}
        #: subscriptions of node processes (realtime only: not accounted, only waited for)
        self.external: dict[str, int] = defaultdict(int)
        self.outstanding = 0
        #: deliveries of messages the ledger had booked as replaced (0 when DDS keeps depth
        #: exactly as modelled; tests check it)
        self.corrections = 0

    def add(self, node: str, subscription: Any) -> None:
        account = SubscriptionAccount(node, subscription.topic_name, history_depth(subscription.qos_profile))
        self.by_topic[subscription.topic_name].append(account)
        self.by_sub[id(subscription)] = account

    def subscribers(self, topic: str) -> int:
        return len(self.by_topic.get(topic, ())) + self.external.get(topic, 0)

    def published(self, topic: str) -> None:
        for a in self.by_topic.get(topic, ()):
            if a.depth is not None and a.queued >= a.depth:
                a.superseded += 1  # the history drops its oldest waiting message for this one
            else:
                a.queued += 1
                self.outstanding += 1

    def taken(self, subscription: Any) -> None:
        a = self.by_sub.get(id(subscription))
        if a is None:
            return
        if a.queued > 0:
            a.queued -= 1
            self.outstanding -= 1
        elif a.superseded > 0:
            a.superseded -= 1  # DDS kept one the ledger thought replaced
            self.corrections += 1
        a.in_flight += 1
        self.outstanding += 1

    def delivered(self, subscription: Any) -> None:
        a = self.by_sub.get(id(subscription))
        if a is None or a.in_flight == 0:
            return
        a.in_flight -= 1
        self.outstanding -= 1

    @property
    def settled(self) -> bool:
        return self.outstanding <= 0

    def give_up(self) -> int:
        """Book every waiting message as lost (after a step timeout); returns how many."""
        lost = 0
        for accounts in self.by_topic.values():
            for a in accounts:
                waiting = a.queued + a.in_flight
                a.lost += waiting
                lost += waiting
                a.queued = a.in_flight = 0
        self.outstanding = 0
        return lost

    def report(self, result: RunResult) -> None:
        """Superseded (depth-1 subscriptions: latest value only), dropped (deeper queues that a
        burst overflowed) and lost deliveries into the run result, by node and topic."""
        for accounts in self.by_topic.values():
            for a in accounts:
                if a.superseded:
                    book(result.superseded if a.depth == 1 else result.dropped, a.node, a.topic, a.superseded)
                if a.lost:
                    book(result.lost, a.node, a.topic, a.lost)


def history_depth(qos: Any) -> int | None:
    """A subscription's KEEP_LAST depth (None: KEEP_ALL): how many messages its history holds."""
    from rclpy.qos import HistoryPolicy

    return None if qos.history == HistoryPolicy.KEEP_ALL else max(1, int(qos.depth))


def book(table: dict[str, dict[str, int]], node: str, topic: str, n: int) -> None:
    """Add ``n`` to a node -> topic -> count table of the run result (superseded, dropped, lost)."""
    counts = table.setdefault(node, {})
    counts[topic] = counts.get(topic, 0) + n


class Recorder:
    """Collects node outputs during one lockstep step, then writes them in a fixed order."""

    def __init__(self, writer: BagWriter, topic_types: dict[str, str]) -> None:
        self.writer = writer
        self.topic_types = topic_types
        self.order = {t: i for i, t in enumerate(sorted(topic_types))}
        self.pending: list[tuple[int, int, str, bytes]] = []
        self.count = 0
        self.lock = threading.Lock()

    def add(self, topic: str, raw: bytes) -> None:
        with self.lock:
            self.pending.append((self.order.get(topic, 1 << 30), len(self.pending), topic, raw))

    def flush(self, log_time_ns: int) -> None:
        with self.lock:
            items, self.pending = sorted(self.pending), []
        for _, _, topic, raw in items:
            self.writer.write(topic, log_time_ns, raw, msgtype=self.topic_types[topic])
            self.count += 1


@dataclass
class RunSession:
    """Everything one run builds, so that set-up, feeding, draining and teardown are separate
    steps: the teardown closes whatever the set-up got to (a failing start included)."""

    reader: BagReader
    result: RunResult
    realtime: bool
    in_processes: bool
    #: processing nodes (or node-process handles), then the feeder, then the recorder node
    nodes: list[Any] = field(default_factory=list)
    executor: Any = None
    #: realtime with per-node threads: node name -> its own executor
    node_executors: dict[str, Any] = field(default_factory=dict)
    writer: BagWriter | None = None
    recorder: Recorder | None = None
    #: fed input topic -> the feeder's publisher
    feed_pubs: dict[str, Any] = field(default_factory=dict)
    clock_pub: Any = None
    #: input topics copied to the output bag
    copy_topics: set[str] = field(default_factory=set)
    #: realtime: the log time of the last played message (the log time outputs get)
    clock_ns: list[int] = field(default_factory=list)
    #: realtime: the fed topics whose publication times the latency is measured from
    stamp_topics: set[str] = field(default_factory=set)
    #: messages the run will read (progress total)
    total: int = 0
    #: realtime: input header stamp (ns) -> perf_counter when the player published it (the
    #: start of the end-to-end latency of the recorded ``orientation/global`` with that stamp)
    published_wall: dict[int, float] = field(default_factory=dict)
    #: lockstep: the one LockstepHooks (ros.node_base) every in-process node, the feeder and the
    #: recorder report through; None in realtime (each node counts only its own messages)
    lockstep_hooks: Any = None
    #: lockstep over node processes: the ParallelLockstep that feeds them (ros.parallel_lockstep)
    parallel: Any = None


def hand_static_transforms(reader: BagReader, nodes: list[Any]) -> None:
    """Give the bag's /tf_static to every node with an ``on_static_transforms`` method.

    The pip-only ROS has no tf2_msgs, so no node can subscribe to /tf_static; the runner
    reads it with rosbags (io.static_tf.static_transforms) and calls the method with the list of
    StaticTransform (parent, child, rotation, translation) before the first message. A
    node that fails on them keeps running without (one warning).
    """
    if TF_STATIC_TOPIC not in reader.topics:
        return
    receivers = [n for n in nodes if callable(getattr(n, 'on_static_transforms', None))]
    if not receivers:
        return
    transforms = static_transforms(reader)
    if not transforms:
        return
    for node in receivers:
        try:
            node.on_static_transforms(transforms)
        except Exception as exc:  # a node's bug must not end the run
            logger.warning('%s: cannot use /tf_static (%s: %s)', node.get_name(), type(exc).__name__, exc)
        else:
            logger.info('%s: %d static transforms from the bag\'s /tf_static', node.get_name(), len(transforms))


def log_drops(result: RunResult) -> None:
    """One line per node and topic whose queue a burst overflowed (INFO for depth-1
    latest-value subscriptions, WARNING for the others: the node may have needed them)."""
    for node, topics in sorted(result.superseded.items()):
        for topic, n in sorted(topics.items()):
            logger.info('%s: %d messages on %s superseded by newer ones (depth 1: latest value only)',
                        node, n, topic)
    for node, topics in sorted(result.dropped.items()):
        for topic, n in sorted(topics.items()):
            logger.warning('%s: %d messages on %s dropped: a burst overflowed its queue', node, n, topic)
