"""Realtime playback of the graph runner (``ar-tracking run --rate R``) and its node processes.

Split out of :mod:`ar_tracking.ros.runner` (see its module docstring for the two clocks): the
player thread that publishes the bag on schedule, the per-node spin threads, the drain after
the last input, the live report (inputs published against processed, per node), and the
start-up and upstream-first stop of node processes (``--executor processes``).
"""
from __future__ import annotations

import logging
import threading
import time
from collections import defaultdict
from typing import Any, Callable

from .conversions import to_stamp
from .player import ClockTicker
from .node_process import NodeProcessError
from .graph_plan import RunError
from .run_state import DRAIN_MAX_S, DRAIN_QUIET_S, DeliveryLedger, Recorder, RunResult, RunSession, header_stamp_ns

# The runner's logger: users (and tests) filter the runner's messages by this name.
logger = logging.getLogger('ar_tracking.ros.runner')

IMAGE_TYPES = ('sensor_msgs/msg/Image', 'sensor_msgs/msg/CompressedImage')
#: Realtime without a camera: the inputs whose stamps the latency is measured from.
SENSOR_STAMP_TYPES = ('sensor_msgs/msg/Imu', 'sensor_msgs/msg/MagneticField')


def latency_stamp_topics(feed_pubs: dict[str, Any], bag_types: dict[str, str]) -> set[str]:
    """The fed topics whose publication times the latency is measured from: the camera
    images (orientation/global carries the image stamp), or without a camera the IMU and
    field samples (the hybrid filter then answers each sample with its stamp)."""
    images = {t for t in feed_pubs if bag_types.get(t) in IMAGE_TYPES}
    return images or {t for t in feed_pubs if bag_types.get(t) in SENSOR_STAMP_TYPES}


def _handles(nodes: list[Any]) -> list[Any]:
    """The node-process handles among the nodes (they carry the ``node_class`` attribute)."""
    return [n for n in nodes if hasattr(n, 'node_class')]


class RealtimePlayback:
    """Play the bag from a player thread at ``rate`` while the nodes spin on theirs.

    The player never waits for a node: it sleeps to each message's due time and publishes
    (DDS queues it in each subscription's history; a full history drops its oldest). Each
    node in ``session.node_executors`` spins on its own thread; the rest (feeder, recorder, or
    every node with a shared executor) on the calling thread. A node thread that dies is
    booked in ``result.failed_nodes`` and ends the playback.
    """

    def __init__(self, session: RunSession, *, rate: float, max_messages: int | None,
                 progress: Callable[[int, int], None] | None, stop: threading.Event) -> None:
        from rosgraph_msgs.msg import Clock

        self.s = session
        self.rate = rate
        self.max_messages = max_messages
        self.progress = progress
        #: the run's stop request (a signal): ends the playback without a drain
        self.stop = stop
        self.clock = Clock()
        self.clock_ticker = ClockTicker()
        self.finished = threading.Event()
        self.stop_nodes = threading.Event()
        self.errors: list[BaseException] = []
        self.late_ms: list[float] = []
        self.handles = _handles(session.nodes)

    # -- threads ----------------------------------------------------------------------------

    def _publish(self, msg: Any) -> None:
        """Publish one bag message: /clock when due, the copy to the output bag, the feed."""
        s = self.s
        s.clock_ns[0] = msg.log_time_ns  # the recorder's log time: every message
        if self.clock_ticker.due(msg.log_time_ns):  # /clock at most every CLOCK_PERIOD_S of bag time
            s.clock_pub.publish(to_stamp(msg.log_time_ns, self.clock.clock) and self.clock)
        if msg.topic in s.copy_topics:
            assert s.recorder is not None and s.writer is not None
            with s.recorder.lock:
                s.writer.write(msg.topic, msg.log_time_ns, msg.rawdata, msgtype=msg.msgtype)
        pub = s.feed_pubs.get(msg.topic)
        if pub is not None:
            stamp = header_stamp_ns(msg.rawdata) if msg.topic in s.stamp_topics else None
            if stamp is not None:
                # the first input of a stamp starts its clock (setdefault keeps it)
                self.s.published_wall.setdefault(stamp, time.perf_counter())
            pub.publish(msg.rawdata)
            s.result.input_messages += 1

    def _play(self) -> None:
        """The player thread: each message at its due time, whatever the nodes do."""
        reader = self.s.reader
        done = 0
        try:
            start_wall = time.monotonic()
            for msg in reader.messages(set(self.s.feed_pubs) | self.s.copy_topics):
                if self.finished.is_set() or (self.max_messages is not None and done >= self.max_messages):
                    break
                due = start_wall + (msg.log_time_ns - reader.start_ns) * 1e-9 / self.rate
                delay = due - time.monotonic()
                if delay > 0 and self.finished.wait(delay):
                    break
                self.late_ms.append(max(0.0, -delay) * 1e3)
                self._publish(msg)
                done += 1
                if self.progress is not None:
                    self.progress(done, self.s.total)
        except BaseException as exc:  # reported in the main thread
            self.errors.append(exc)
        finally:
            self.finished.set()

    def _spin_node(self, name: str, own: Any) -> None:
        """A node thread: spin the node's own executor until the run stops."""
        try:
            while not self.stop_nodes.is_set():
                own.spin_once(timeout_sec=0.05)
        except BaseException as exc:  # the node is gone: report it, stop the run
            self.s.result.failed_nodes[name] = f'{type(exc).__name__}: {exc}'
            logger.error('%s died: %s: %s', name, type(exc).__name__, exc)
            self.finished.set()
        finally:
            self.s.result.live_cpu_s[name] = time.thread_time()

    # -- the calling thread -----------------------------------------------------------------

    def _processed(self) -> int:
        assert self.s.recorder is not None
        return self.s.recorder.count + sum(len(st.durations_ms) for n in self.s.nodes for st in n.callback_stats.values())

    def _spin_main(self) -> None:
        try:
            self.s.executor.spin_once(timeout_sec=0.05)
        except BaseException as exc:  # a shared executor: the failing node is not known
            self.s.result.failed_nodes.setdefault('executor', f'{type(exc).__name__}: {exc}')
            logger.error('the executor died: %s: %s', type(exc).__name__, exc)
            self.finished.set()

    def _check_processes(self) -> None:
        failed = self.s.result.failed_nodes
        for h in self.handles:
            why = h.died()
            if why is not None and h.name not in failed:
                failed[h.name] = why
                logger.error('%s died: %s', h.name, why)
                self.finished.set()

    def _drain(self) -> None:
        """Let the nodes empty their queues (until nothing moves for DRAIN_QUIET_S)."""
        result = self.s.result
        drain_until = time.monotonic() + DRAIN_MAX_S
        last, quiet_since = self._processed(), time.monotonic()
        while time.monotonic() < drain_until and not result.failed_nodes:
            self._spin_main()
            now_done = self._processed()
            if now_done != last:
                last, quiet_since = now_done, time.monotonic()
            elif time.monotonic() - quiet_since > DRAIN_QUIET_S:
                break

    def run(self) -> None:
        """Play, spin until the player is done (or a node died, or a stop was asked for),
        drain, join the threads; the player's p95 lateness into the result."""
        node_threads = [threading.Thread(target=self._spin_node, args=(name, own), name=f'node_{name}', daemon=True)
                        for name, own in self.s.node_executors.items()]
        for t in node_threads:
            t.start()
        thread = threading.Thread(target=self._play, name='graph_player', daemon=True)
        thread.start()
        try:
            while not self.finished.is_set():
                if self.stop.is_set():
                    self.finished.set()
                    break
                self._spin_main()
                self._check_processes()
            if not self.s.result.failed_nodes and not self.stop.is_set():
                self._drain()
        finally:
            self.finished.set()
            thread.join(2.0)
            self.stop_nodes.set()
            for t in node_threads:
                t.join(5.0)
        late_ms = self.late_ms
        if late_ms:
            late_ms.sort()
            self.s.result.live_player_late_ms_p95 = late_ms[min(len(late_ms) - 1, int(0.95 * len(late_ms)))]
        if self.errors:
            raise self.errors[0]


def live_report(nodes: list[Any], result: RunResult) -> None:
    """Per processing node and input topic: messages published on the topic (by the player
    and every node) against those the node's callback processed (``callback_stats``), into
    ``result.live_inputs``; one warning line per node that missed inputs."""
    published: dict[str, int] = defaultdict(int)
    for n in nodes[:-1]:  # the processing nodes and the feeder (the recorder publishes nothing)
        for topic, count in getattr(n, 'publish_counts', {}).items():
            published[topic] += count
    for n in nodes[:-2]:
        inputs = {}
        for topic, stats in n.callback_stats.items():
            fq = '/' + topic.lstrip('/')
            inputs[fq] = (published.get(fq, 0), len(stats.durations_ms))
        result.live_inputs[n.get_name()] = inputs
        cpu_s = getattr(n, 'cpu_s', None)  # a node process's own report
        if cpu_s is not None:
            result.live_cpu_s[n.get_name()] = cpu_s
    for node, missed in sorted(result.live_dropped.items()):
        if missed:
            detail = ', '.join(f'{done} of {pub} on {t}' for t, (pub, done) in sorted(result.live_inputs[node].items())
                               if pub > done)
            logger.warning('%s: %d inputs dropped (processed %s): it did not keep up', node, missed, detail)


# -- node processes (--executor processes) ---------------------------------------------------

def best_effort_outputs(nodes: list[Any]) -> set[str]:
    """Topics some node of the graph publishes best effort: an in-process node's publishers
    say it themselves; a node process has told it when it was created (waited for here)."""
    from rclpy.qos import ReliabilityPolicy

    topics: set[str] = set()
    for n in nodes:
        if hasattr(n, 'node_class'):  # a node process
            n.wait_created()
            topics.update(n.best_effort_topics)
        else:
            topics.update(p.topic_name for p in getattr(n, 'publishers', ())
                          if p.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT)
    return topics


def publisher_counts(nodes: list[Any]) -> dict[str, int]:
    """Publishers per topic in the graph: the node processes' (as they reported them) and the
    in-process nodes' (the feeder, the recorder, threads)."""
    counts: dict[str, int] = defaultdict(int)
    for n in nodes:
        topics = n.publisher_topics if hasattr(n, 'node_class') else [p.topic_name for p in getattr(n, 'publishers', ())]
        for topic in topics:
            counts[topic] += 1
    return counts


def connect_node_processes(nodes: list[Any], ledger: DeliveryLedger) -> None:
    """Wait for every node process to build its node, tell each how many subscribers its
    outputs have (other node processes and this process's recorder), wait until they have
    matched, and book the node processes' subscriptions for the feeder's discovery wait."""
    handles = _handles(nodes)
    try:
        for h in handles:
            h.wait_created()
        subscribers: dict[str, int] = defaultdict(int)
        for h in handles:
            for topic in h.subscription_topics:
                subscribers[topic] += 1
        for topic in ledger.by_topic:
            subscribers[topic] += ledger.subscribers(topic)
        publishers = publisher_counts(nodes)
        for h in handles:
            h.expect(subscribers, publishers)
        for h in handles:
            h.wait_ready()
    except NodeProcessError as exc:
        raise RunError(f'cannot start {exc}') from exc
    for h in handles:
        for topic in h.subscription_topics:
            ledger.external[topic] += 1


def stop_node_processes(nodes: list[Any], executor: Any, recorder: Recorder,
                        drain_quiet_s: float = DRAIN_QUIET_S, drain_max_s: float = DRAIN_MAX_S) -> None:
    """Stop the node processes upstream first: a node is asked to stop (it takes what is
    still queued for it, reports its counts and exits) once every node it subscribes to has
    reported, so that a backlog an upstream node is still working off reaches its
    downstream nodes (a node in a cycle, or left when the time is up, is stopped with the
    rest). With the request a node gets the number of messages published on each of its inputs
    (the feeder's and the reported nodes'), so that it also waits for those still in transit
    between processes. What they publish meanwhile is recorded until the recorder is quiet."""
    handles = _handles(nodes)
    deadline = time.monotonic() + drain_max_s
    # upstream[i]: the node processes whose outputs node i subscribes to
    upstream = [{j for j, g in enumerate(handles) if g is not h and set(h.subscription_topics) & set(g.publisher_topics)}
                for h in handles]
    remaining = set(range(len(handles)))
    while remaining:
        ready = {i for i in remaining if not upstream[i] & remaining}
        counted = bool(ready) and time.monotonic() < deadline  # every upstream node has reported
        if not counted:
            ready = set(remaining)
        layer = [handles[i] for i in sorted(ready)]
        published: dict[str, int] = defaultdict(int)  # by the feeder and the nodes that reported
        for n in nodes:
            for topic, count in getattr(n, 'publish_counts', {}).items():
                published[topic] += count
        for h in layer:  # with the counts it waits for what is still in transit to it
            h.request_stop({t: published[t] for t in h.subscription_topics if t in published} if counted else None)
        while time.monotonic() < deadline and not all(h.reported() or not h.process.is_alive() for h in layer):
            executor.spin_once(timeout_sec=0.02)
        remaining -= ready
    last, quiet_since = recorder.count, time.monotonic()
    while time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
        if recorder.count != last:
            last, quiet_since = recorder.count, time.monotonic()
        elif time.monotonic() - quiet_since > drain_quiet_s and not any(h.process.is_alive() and
                                                                         not h.reported() for h in handles):
            break
    for h in handles:
        h.stop()
