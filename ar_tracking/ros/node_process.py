"""One graph node in a process of its own: ``ar-tracking run --rate R --executor processes``.

The deployment shape of a ROS graph (``ros2 launch`` starts every node as its own process):
no node shares an interpreter, so a heavy one (SLAM) cannot hold the GIL while the IMU path
waits, and on a machine with several cores the nodes run in parallel. The runner keeps the
player (feeder) and the recorder in its own process and talks to each node process over a pipe:

1. the child starts rclpy on the runner's domain, builds the node (parameters as in-process),
   hands it the bag's static transforms, and reports its subscriptions and publishers;
2. the runner answers with how many subscribers each of the child's output topics and how many
   publishers each of its input topics will have; the child spins until both sides have
   matched them (so that no first message is lost to discovery) and reports ready;
3. after the playback and the drain, the runner asks for the child's counts (callbacks per
   input topic with their durations, messages published per topic) - the live report's
   figures - and the child shuts down cleanly. With the request come the numbers of messages
   published on its inputs, so that it waits for those still in transit.

:class:`NodeProcess` is the runner-side handle; it has the attributes the live report reads
from in-process nodes (``callback_stats``, ``publish_counts``, ``get_name``), filled at the end.
"""
from __future__ import annotations

import logging
import multiprocessing
import os
import signal
import time
from dataclasses import dataclass, field
from typing import Any

from .graph_plan import load_node_class
from .run_state import DRAIN_QUIET_S, history_depth
from ..errors import ArTrackingError

logger = logging.getLogger(__name__)

#: How long a child may take to import, build its node and match its subscribers, s.
START_TIMEOUT_S = 60.0
#: How long a child waits for its subscriptions to match their topics' publishers, s (a
#: publisher with a QoS the subscription cannot match never does: the run then goes on).
READER_MATCH_TIMEOUT_S = 10.0
#: How long a child may take to report its counts and exit, s.
STOP_TIMEOUT_S = 10.0


class NodeProcessError(ArTrackingError):
    """A node process did not start, died, or did not report."""


@dataclass
class _Durations:
    """The counterpart of node_base.CallbackStats the live report reads."""

    durations_ms: list[float] = field(default_factory=list)


def _parent_log_level() -> int | None:
    """The default rcutils log level of this process (``ar-tracking -q`` raises it to ERROR),
    for the node processes to take over; None without rclpy."""
    try:
        import rclpy.logging

        return int(rclpy.logging.get_logger_effective_level(''))
    except Exception:  # noqa: BLE001 - no rclpy or no logging: the child keeps its default
        return None


def _child_main(name: str, spec: Any, params: dict[str, Any], domain_id: int, transforms: list[Any],
                conn: Any, stop: Any, log_level: int | None = None, lockstep: bool = False) -> None:
    """Entry point of the child process (forked from the forkserver or spawned: nothing of the parent's DDS state is inherited,
    so the parent's log level comes as ``log_level``). ``lockstep``: the runner carries the
    node's messages over the pipe (:mod:`~ar_tracking.ros.lockstep_child`), not DDS."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C goes to the runner, which stops us
    if lockstep:  # nothing goes over DDS: no discovery traffic with anyone
        os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'OFF'
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    import rclpy
    import rclpy.logging

    if log_level is not None:
        rclpy.logging.set_logger_level('', log_level)
    from rclpy.qos import ReliabilityPolicy

    from .node_base import TrackingNode, node_executor
    from .params import to_overrides

    context = rclpy.Context()
    node = None
    outbox: list[tuple[str, bytes]] = []
    try:
        rclpy.init(context=context, domain_id=domain_id)
        cls = load_node_class(spec)
        if lockstep:
            from .lockstep_child import publication_tap

            TrackingNode.publish_tap = staticmethod(publication_tap(outbox, cls.OUTPUTS))
        node = cls(context=context, parameter_overrides=to_overrides(params))
        node.lockstep_hooks = None
        if transforms and callable(getattr(node, 'on_static_transforms', None)):
            node.on_static_transforms(transforms)
        conn.send(('created', [s.topic_name for s in node.subscriptions], [p.topic_name for p in node.publishers],
                   [p.topic_name for p in node.publishers if p.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT],
                   {s.topic_name: history_depth(s.qos_profile) for s in node.subscriptions}))
        if lockstep:
            from .lockstep_child import serve_steps

            conn.send(('ready', list(outbox)))
            outbox.clear()
            serve_steps(node, conn, outbox)
        else:
            _serve_live(node, node_executor(context), conn, stop)
        conn.send(('counts', {t: list(s.durations_ms) for t, s in node.callback_stats.items()},
                   dict(node.publish_counts), time.process_time()))
    except BaseException as exc:  # reported to the runner, which ends the run with the node's name
        try:
            conn.send(('error', f'{type(exc).__name__}: {exc}'))
        except (OSError, ValueError):
            pass
        raise SystemExit(1) from None
    finally:
        if node is not None:
            close = getattr(node, 'close', None)
            if callable(close):
                close()
            node.destroy_node()
        rclpy.try_shutdown(context=context)


def _serve_live(node: Any, executor: Any, conn: Any, stop: Any) -> None:
    """Realtime: match the runner's counts of subscribers and publishers (at most
    START_TIMEOUT_S; the readers' side READER_MATCH_TIMEOUT_S), report ready, spin until asked
    to stop, then take what is still queued or in flight."""
    executor.add_node(node)
    expected, publishers = conn.recv()
    deadline = time.monotonic() + START_TIMEOUT_S
    pubs = [p for p in node.publishers if expected.get(p.topic_name, 0) > 0]
    subs = [s for s in node.subscriptions if publishers.get(s.topic_name, 0) > 0]
    subs_deadline = time.monotonic() + READER_MATCH_TIMEOUT_S
    while time.monotonic() < deadline and not stop.is_set():
        # Matched on both sides: a best-effort reader drops what a writer it has not yet
        # discovered sends, even when that writer already counts it as matched.
        if (all(p.get_subscription_count() >= expected[p.topic_name] for p in pubs)
                and (time.monotonic() > subs_deadline
                     or all(s.get_publisher_count() >= publishers[s.topic_name] for s in subs))):
            break
        executor.spin_once(timeout_sec=0.02)
    conn.send(('ready', None))
    while not stop.is_set():
        executor.spin_once(timeout_sec=0.05)
    _take_the_rest(node, executor, conn.recv()[1] if conn.poll() else {})


def _take_the_rest(node: Any, executor: Any, expected: dict[str, int]) -> None:
    """Once asked to stop: take the inputs still queued or in flight, as the in-process drain
    would. ``expected`` (fully qualified topic -> messages its publishers sent, from the runner;
    empty when unknown): done as soon as every input has had that many callbacks; while one is
    short, until nothing moved for ``DRAIN_QUIET_S`` (a message still in transit between
    processes, or a node that dropped some); without counts, until nothing moved for 0.2 s."""
    quiet_s = 0.2
    done, quiet_since = -1, time.monotonic()
    while True:
        counts = {'/' + t.lstrip('/'): len(st.durations_ms) for t, st in node.callback_stats.items()}
        if sum(counts.values()) != done:
            done, quiet_since = sum(counts.values()), time.monotonic()
        if expected:
            if all(counts.get(t, 0) >= n for t, n in expected.items()):
                return
            quiet_s = DRAIN_QUIET_S
        if time.monotonic() - quiet_since > quiet_s:
            return
        executor.spin_once(timeout_sec=0.05)


#: What the forkserver imports once, so that each node process forked from it starts with
#: them loaded (~1.2 s of CPU per process otherwise: rclpy, numpy, OpenCV, scipy's rotations).
FORKSERVER_PRELOAD = ['rclpy', 'rclpy.serialization', 'numpy', 'cv2', 'scipy.spatial.transform',
                      'ar_tracking.ros.node_base', 'ar_tracking.ros.lockstep_child', 'ar_tracking.ros.conversions']


def _process_context() -> Any:
    """How node processes start: forked from a server process that has the heavy modules
    imported and no DDS state (a fork of the runner itself would copy its DDS participant and
    threads), where the platform has one; else spawned."""
    if os.environ.get('AR_TRACKING_NODE_START') == 'spawn' or 'forkserver' not in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context('spawn')
    ctx = multiprocessing.get_context('forkserver')
    ctx.set_forkserver_preload(FORKSERVER_PRELOAD)
    return ctx


class NodeProcess:
    """Runner-side handle of one node running in a child process (module docstring)."""

    def __init__(self, name: str, spec: Any, params: dict[str, Any], domain_id: int,
                 transforms: list[Any] | None = None, lockstep: bool = False) -> None:
        self.name = name
        #: the runner carries this node's messages over the pipe (parallel_lockstep)
        self.lockstep = lockstep
        self.node_class = load_node_class(spec)
        mp = _process_context()
        self._stop = mp.Event()
        self._conn, child_conn = mp.Pipe()
        self.process = mp.Process(
            target=_child_main, name=f'ar_tracking_{name}', daemon=True,
            args=(name, spec, params, domain_id, list(transforms or []), child_conn, self._stop, _parent_log_level(),
                  lockstep))
        self.subscription_topics: list[str] = []
        #: subscribed topic -> its KEEP_LAST depth (None: KEEP_ALL)
        self.subscription_depths: dict[str, int | None] = {}
        self.publisher_topics: list[str] = []
        #: Output topics the child's node publishes best effort (a reliable reader never matches).
        self.best_effort_topics: list[str] = []
        self._created = False
        self.callback_stats: dict[str, _Durations] = {}
        self.publish_counts: dict[str, int] = {}
        self.failure: str | None = None
        #: CPU seconds of the child process (all its threads), from its counts report
        self.cpu_s: float | None = None
        self._counted = False

    def get_name(self) -> str:
        return self.name

    def start(self) -> None:
        self.process.start()

    def _receive(self, kind: str, timeout_s: float) -> tuple[Any, ...]:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self._conn.poll(0.05):
                try:
                    msg = self._conn.recv()
                except EOFError:
                    break
                if msg[0] == 'error':
                    self.failure = msg[1]
                    raise NodeProcessError(f'{self.name}: {msg[1]}')
                if msg[0] == kind:
                    return tuple(msg[1:])
            elif not self.process.is_alive():
                break
        code = self.process.exitcode
        self.failure = self.failure or (f'exited with code {code}' if code is not None else f'no {kind} report')
        raise NodeProcessError(f'{self.name}: {self.failure}')

    def wait_created(self) -> None:
        """Block until the child has built its node (its topics are then known); once."""
        if self._created:
            return
        (self.subscription_topics, self.publisher_topics, self.best_effort_topics,
         self.subscription_depths) = self._receive('created', START_TIMEOUT_S)
        self._created = True

    def expect(self, subscribers: dict[str, int], publishers: dict[str, int]) -> None:
        """Tell the child how many subscribers each of its output topics and how many
        publishers each of its input topics will have (it waits until it has matched them)."""
        self._conn.send(({t: subscribers.get(t, 0) for t in self.publisher_topics},
                         {t: publishers.get(t, 0) for t in self.subscription_topics}))

    def wait_ready(self) -> tuple[Any, ...]:
        """Block until the child is ready; in lockstep, its report holds what the node
        published before its first input."""
        return self._receive('ready', START_TIMEOUT_S)

    # Lockstep over the pipe (parallel_lockstep).
    @property
    def connection(self) -> Any:
        return self._conn

    def send_steps(self, chunk: list[tuple[int, list[tuple[str, bytes]]]]) -> None:
        """Send the child the inputs of some steps, (seq, [(topic, raw), ...]) in step order."""
        self._conn.send(('steps', chunk))

    def receive_outputs(self) -> list[tuple[int, list[tuple[str, bytes]], list[str]]]:
        """One report of the child: per step of a chunk sent, (seq, what it published, the
        topics of inputs it could not read); NodeProcessError if it failed or is gone."""
        try:
            msg = self._conn.recv()
        except (EOFError, OSError):
            self.failure = self.failure or f'exited with code {self.process.exitcode}'
            raise NodeProcessError(f'{self.name}: {self.failure}') from None
        if msg[0] == 'error':
            self.failure = msg[1]
            raise NodeProcessError(f'{self.name}: {msg[1]}')
        return msg[1]

    def died(self) -> str | None:
        """Why the child is gone while it should run (None while it runs)."""
        if self.process.is_alive():
            return None
        if self._conn.poll():
            try:
                msg = self._conn.recv()
            except EOFError:
                msg = None
            if msg and msg[0] == 'error':
                self.failure = msg[1]
        self.failure = self.failure or f'exited with code {self.process.exitcode}'
        return self.failure

    def reported(self) -> bool:
        """Whether the child has sent its counts (or failed); takes them without waiting."""
        while not self._counted and self.failure is None and self._conn.poll():
            try:
                msg = self._conn.recv()
            except EOFError:
                break
            if msg[0] == 'counts':
                self._take_counts(*msg[1:])
            elif msg[0] == 'error':
                self.failure = msg[1]
        return self._counted or self.failure is not None

    def _take_counts(self, durations: dict[str, list[float]], published: dict[str, int],
                     cpu_s: float | None = None) -> None:
        self.callback_stats = {t: _Durations(list(d)) for t, d in durations.items()}
        self.publish_counts = dict(published)
        self.cpu_s = cpu_s
        self._counted = True

    def request_stop(self, expected: dict[str, int] | None = None) -> None:
        """Tell the child to take what is queued, report and exit (returns at once);
        ``expected``: how many messages were published on each of its input topics."""
        if expected is not None:
            try:
                self._conn.send(('expected', dict(expected)))
            except OSError:  # the child is gone: stop() reports how
                pass
        self._stop.set()

    def stop(self) -> None:
        """Stop the child, collect its counts and let it exit (killed if it does not)."""
        if self.process.pid is None:
            return
        if self.lockstep and not self._stop.is_set():
            try:
                self._conn.send(('stop',))
            except OSError:  # the child is gone: reported below
                pass
        self._stop.set()
        if not self.reported() and self.process.is_alive():
            try:
                report = self._receive('counts', STOP_TIMEOUT_S)
            except NodeProcessError as exc:
                logger.warning('%s', exc)
            else:
                self._take_counts(*report)
        self.process.join(STOP_TIMEOUT_S)
        if self.process.is_alive():
            self.process.kill()
            self.process.join(2.0)

    # The in-process node interface the runner's teardown calls.
    def close(self) -> None:
        self.stop()

    def destroy_node(self) -> None:
        pass
