"""The graph runner behind ``ar-tracking run``: every node that can run on a bag, one output bag.

Two clocks (DESIGN sec. 4):

* **lockstep** (default): all nodes in one process on a private rclpy Context. The runner
  publishes one input message, then spins until every subscription that should receive it -
  and, recursively, every message the nodes publish in response - has been delivered and
  processed. Only then does the next input go out. A burst larger than a subscription's
  KEEP_LAST depth is booked at publish time as superseded (depth 1: the node wants the latest
  value only) or dropped (a deeper queue overflowed), never waited for, and reported in the
  run result by node and topic (:class:`_DeliveryLedger`). Outputs are written with the log time of the
  input that caused them, in a fixed order, so two runs give byte-identical output bags.
* **realtime** (``rate > 0``): the bag is played at ``rate`` times its speed with ``/clock``;
  nodes use sim time and whatever they cannot keep up with is dropped, like on a device. Each
  node spins on its own thread (its own SingleThreadedExecutor), so a slow node (SLAM, the
  panorama) cannot stall the IMU path, and the player thread publishes on schedule whatever
  the nodes do. The run counts, per node, the inputs published to it against those its
  callbacks processed (:attr:`RunResult.live_dropped`), measures the end-to-end latency of
  ``orientation/global`` (input stamp published -> output received by the recorder), and
  reports a node whose thread died (then the run stops and ``ar-tracking run`` exits 1).

Inputs the evaluation needs (ground truth, static transforms, the non-image sensor topics) are
copied into the output bag; images only on request. The output bag is closed cleanly on every
exit path, Ctrl-C included, with everything processed so far. A kill that no handler sees
(SIGKILL, out of memory) leaves an MCAP without its summary: the writer flushes a chunk every
``flush_every_s`` of bag time, and :class:`~ar_tracking.io.bags.BagReader` recovers what reached
the file.
"""
from __future__ import annotations

import importlib
import itertools
import logging
import math
import os
import signal
import threading
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable

from ..io.bags import TF_STATIC_TOPIC, BagReader, BagWriter, static_transforms
from .params import params_for_node, to_overrides

logger = logging.getLogger(__name__)

#: The processing nodes the runner can start: name -> "module:Class". Replay nodes are not
#: listed: in the runner, the runner itself plays the bag.
GRAPH_NODES: dict[str, str] = {
    'imu_magnetometer': 'ar_tracking.nodes.imu_magnetometer:ImuMagnetometerNode',
    'panorama_mapper': 'ar_tracking.nodes.panorama_mapper:PanoramaMapperNode',
    'hybrid_orientation_filter': 'ar_tracking.nodes.hybrid_orientation_filter:HybridOrientationFilterNode',
    'annotation_matcher': 'ar_tracking.nodes.annotation_matcher:AnnotationMatcherNode',
    'ar_view': 'ar_tracking.nodes.ar_view:ArViewNode',
    'marker_tracker': 'ar_tracking.nodes.marker_tracker:MarkerTrackerNode',
    'visual_inertial_filter': 'ar_tracking.nodes.visual_inertial_filter:VisualInertialFilterNode',
    'keyframe_slam_mapper': 'ar_tracking.nodes.keyframe_slam_mapper:KeyframeSlamMapperNode',
}

#: Named graphs for ``ar-tracking run --graph``: which nodes each starts (those whose inputs
#: the bag has). ``auto`` (the default) is every node, with the rule of :func:`choose_nodes`.
NAMED_GRAPHS: dict[str, list[str]] = {
    'orientation': ['imu_magnetometer', 'panorama_mapper', 'hybrid_orientation_filter'],
    'annotations': ['imu_magnetometer', 'panorama_mapper', 'hybrid_orientation_filter',
                    'annotation_matcher', 'ar_view'],
    'slam': ['keyframe_slam_mapper'],
    'markers': ['marker_tracker', 'visual_inertial_filter'],
    'all': list(GRAPH_NODES),
}
GRAPH_CHOICES = ('auto', *NAMED_GRAPHS)

#: The topic by which the automatic choice recognises a phone orientation recording (see
#: :func:`choose_nodes`).
ROTATION_IN_PLACE_TOPIC = '/imu/mag'

#: Name of the MCAP metadata record in which an output bag says where it came from.
RUN_METADATA = 'ar_tracking.run'

#: Topics copied from the input bag to the output by default (prefix match).
COPY_PREFIXES = ('/ground_truth/', '/tf_static', '/tf', '/gps/', '/imu/')
IMAGE_TYPES = ('sensor_msgs/msg/Image', 'sensor_msgs/msg/CompressedImage')
#: Realtime: the output whose end-to-end latency the run measures (input stamp -> received).
LATENCY_TOPIC = '/orientation/global'
#: Realtime without a camera: the inputs whose stamps the latency is measured from.
SENSOR_STAMP_TYPES = ('sensor_msgs/msg/Imu', 'sensor_msgs/msg/MagneticField')


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


#: ``--executor``: auto (events in lockstep, one thread per node with --rate), threads (one
#: SingleThreadedExecutor per node on its own thread; realtime only, lockstep uses single),
#: single, events, multi (one MultiThreadedExecutor, a callback group per node).
EXECUTOR_CHOICES = ('auto', 'threads', 'processes', 'single', 'events', 'multi')


class RunError(Exception):
    """The graph cannot run on this bag: one line for the user."""


def check_rate(rate: float, *, lockstep: bool) -> float:
    """The playback rate as a float, or :class:`RunError` with one line saying why not.

    ``run`` takes a finite rate >= 0 (0 = lockstep); ``replay`` (``lockstep=False``) a finite
    rate > 0. ``inf`` would publish the whole bag at once and lose most outputs, ``nan``
    compares false with everything and would slip through any range check after it.
    """
    try:
        value = float(rate)
    except (TypeError, ValueError):
        raise RunError(f'--rate must be a number, not {rate!r}') from None
    if not math.isfinite(value):
        raise RunError(f'--rate must be a finite number, not {value!r}')
    if lockstep and value < 0:
        raise RunError(f'--rate must be >= 0 (0 = lockstep), not {value:g}')
    if not lockstep and value <= 0:
        raise RunError(f'--rate must be > 0, not {value:g}')
    return value


@dataclass
class RunResult:
    """What one run did: counts, time, and every message a subscription did not get.

    Lockstep accounting (see :class:`_DeliveryLedger`): ``superseded`` counts the messages that
    a KEEP_LAST depth-1 subscription (a node that wants only the latest value, e.g. a map or
    the current labels) replaced by a newer one; ``dropped`` the messages a deeper queue
    overflowed with (a burst larger than the node's depth: the node may have needed them);
    ``lost`` the deliveries that did not happen within the step timeout (a bug or a message
    that does not deserialise). Each maps node name -> topic -> count.
    """

    out_path: Path
    input_messages: int = 0
    output_messages: int = 0
    wall_s: float = 0.0
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
        dropped per node, published/processed per node and topic, latency p50/p95 in ms."""
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
        }


class _SubscriptionAccount:
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


class _DeliveryLedger:
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
        self.by_topic: dict[str, list[_SubscriptionAccount]] = defaultdict(list)
        self.by_sub: dict[int, _SubscriptionAccount] = {}
        #: subscriptions of node processes (realtime only: not accounted, only waited for)
        self.external: dict[str, int] = defaultdict(int)
        self.outstanding = 0
        #: deliveries of messages the ledger had booked as replaced (0 when DDS keeps depth
        #: exactly as modelled; tests check it)
        self.corrections = 0

    def add(self, node: str, subscription: Any) -> None:
        from rclpy.qos import HistoryPolicy

        qos = subscription.qos_profile
        depth = None if qos.history == HistoryPolicy.KEEP_ALL else max(1, int(qos.depth))
        account = _SubscriptionAccount(node, subscription.topic_name, depth)
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
                    kind = result.superseded if a.depth == 1 else result.dropped
                    kind.setdefault(a.node, {})[a.topic] = kind.get(a.node, {}).get(a.topic, 0) + a.superseded
                if a.lost:
                    result.lost.setdefault(a.node, {})[a.topic] = result.lost.get(a.node, {}).get(a.topic, 0) + a.lost


def load_node_class(spec: Any) -> Any:
    """A node class from a "module:Class" spec (classes pass through)."""
    if not isinstance(spec, str):
        return spec
    module, _, cls = spec.partition(':')
    return getattr(importlib.import_module(module), cls)


def plan_nodes(
    bag_topics: Iterable[str],
    only: Iterable[str] | None = None,
    graph: dict[str, Any] | None = None,
    params: Callable[[str], dict[str, Any]] | None = None,
) -> tuple[list[str], dict[str, str]]:
    """Which nodes can run: those whose inputs are in the bag or produced by a node that runs,
    and whose REQUIRED_PARAMS (e.g. marker_tracker's marker map) are set in their parameters.

    ``graph`` maps node names to classes or "module:Class" specs (default: GRAPH_NODES);
    ``params(name)`` gives a node's merged parameters. Returns (node names in start order,
    reasons for the ones left out).
    """
    graph = GRAPH_NODES if graph is None else graph
    available = {t.lstrip('/') for t in bag_topics}
    wanted = list(only) if only else list(graph)
    unknown = [n for n in wanted if n not in graph]
    if unknown:
        raise RunError(f'unknown node(s) {", ".join(unknown)}; known: {", ".join(graph)}')
    reasons: dict[str, str] = {}
    for name in list(wanted):
        required = getattr(load_node_class(graph[name]), 'REQUIRED_PARAMS', [])
        given = params(name) if params is not None else {}
        missing = [r if isinstance(r, str) else ' or '.join(r) for r in required
                   if not any(given.get(k) for k in ((r,) if isinstance(r, str) else r))]
        if missing:
            reasons[name] = f'needs the parameter {", ".join(missing)}'
            wanted.remove(name)
    started: list[str] = []
    pending = list(wanted)
    progress = True
    while progress:
        progress = False
        for name in list(pending):
            cls = load_node_class(graph[name])
            needed = cls.REQUIRED_INPUTS if hasattr(cls, 'REQUIRED_INPUTS') else list(cls.INPUTS)
            if all(_satisfied(t, available) for t in needed):
                started.append(name)
                available.update(cls.OUTPUTS)
                pending.remove(name)
                progress = True
    for name in pending:
        cls = load_node_class(graph[name])
        needed = cls.REQUIRED_INPUTS if hasattr(cls, 'REQUIRED_INPUTS') else list(cls.INPUTS)
        missing = [t if isinstance(t, str) else ' or '.join(t) for t in needed if not _satisfied(t, available)]
        reasons[name] = f'needs {", ".join(missing)}'
    return started, reasons


def choose_nodes(
    bag_topics: Iterable[str],
    nodes: Iterable[str] | None = None,
    named_graph: str | None = None,
    graph: dict[str, Any] | None = None,
) -> tuple[list[str], dict[str, str]]:
    """The nodes a run asks for, before :func:`plan_nodes` checks their inputs.

    ``nodes`` (``--nodes``) wins, then a named graph (``--graph``, :data:`NAMED_GRAPHS`).
    Automatic (``auto`` or None) is every node of ``graph`` except one rule: keyframe_slam_mapper
    is not started on a bag with a magnetometer (``/imu/mag``). Such a bag is the outdoor
    phone setting of Langlotz et al. 2011: the user turns the camera in place, and monocular
    SLAM needs a sideways baseline to initialise; on a pure rotation it never does, prints
    "move the camera sideways" and costs most of the graph's time. Returns (names asked for,
    reason per node left out by the rule).
    """
    graph = GRAPH_NODES if graph is None else graph
    if nodes:
        return list(nodes), {}
    if named_graph not in (None, 'auto'):
        if named_graph not in NAMED_GRAPHS:
            raise RunError(f'unknown graph {named_graph!r}; known: {", ".join(GRAPH_CHOICES)}')
        return [n for n in NAMED_GRAPHS[named_graph] if n in graph], {}
    topics = {'/' + t.lstrip('/') for t in bag_topics}
    ruled_out: dict[str, str] = {}
    if 'keyframe_slam_mapper' in graph and ROTATION_IN_PLACE_TOPIC in topics:
        ruled_out['keyframe_slam_mapper'] = (
            f'the bag has {ROTATION_IN_PLACE_TOPIC}: a phone orientation recording whose camera '
            'mostly rotates in place, where monocular SLAM cannot initialise '
            '(start it with --graph slam or all, or --nodes keyframe_slam_mapper)'
        )
    return [n for n in graph if n not in ruled_out], ruled_out


_runs_in_process = itertools.count()


def _satisfied(requirement: str | tuple[str, ...], available: set[str]) -> bool:
    """A required input is a topic, or a tuple of alternatives of which one must be there
    (e.g. ('camera/image_raw', 'camera/image_raw/compressed'))."""
    if isinstance(requirement, str):
        return requirement in available
    return any(t in available for t in requirement)


def _init_private_context(rclpy: Any, context: Any, lockstep: bool) -> int:
    """Initialise the runner's context so that no other process can join its graph.

    Lockstep graphs live in one process: DDS discovery is switched off for them
    (ROS_AUTOMATIC_DISCOVERY_RANGE=OFF still connects the nodes of one process), so two runs on
    one machine can never hear each other whatever their domain. Realtime graphs stay on
    localhost discovery (nodes may run as separate processes) on their own domain id.
    """
    key = 'ROS_AUTOMATIC_DISCOVERY_RANGE'
    previous = os.environ.get(key)
    os.environ[key] = 'OFF' if lockstep else (previous or 'LOCALHOST')
    domain_id = _domain_id()
    try:
        rclpy.init(context=context, domain_id=domain_id)
    finally:
        if previous is None:
            del os.environ[key]
        else:
            os.environ[key] = previous
    return domain_id


def _node_class(node: Any) -> Any:
    """The node class of an in-process node or of a node process's handle."""
    return getattr(node, 'node_class', None) or type(node)


def _domain_id() -> int:
    """A DDS domain for the private graph, so that two runs on one machine (or two runs one
    after the other in one process, while DDS still tears down the first) never hear each other.
    """
    env = os.environ.get('AR_TRACKING_DOMAIN_ID')
    if env:
        return int(env)
    return 101 + (os.getpid() * 7 + next(_runs_in_process)) % 100


class _Recorder:
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


class GraphRunner:
    """Runs the node graph on one bag and records the outputs (see the module docstring)."""

    def __init__(
        self,
        bag: str | Path,
        out: str | Path,
        *,
        params_files: list[str | Path] | None = None,
        nodes: list[str] | None = None,
        rate: float = 0.0,
        storage: str | None = None,
        copy_images: bool = False,
        executor: str = 'auto',
        progress: Callable[[int, int], None] | None = None,
        step_timeout_s: float = 10.0,
        max_messages: int | None = None,
        graph: dict[str, Any] | None = None,
        flush_every_s: float = 0.5,
        named_graph: str | None = None,
        output_taps: list[Callable[[str, str], Callable[[bytes], None]]] | None = None,
    ) -> None:
        self.bag_path = Path(bag)
        #: The output MCAP closes a chunk every this much bag time (what a kill can lose).
        self.flush_every_s = flush_every_s
        self.out_path = Path(out)
        self.params_files = list(params_files or [])
        self.only_nodes = nodes
        #: ``--graph``: a name of NAMED_GRAPHS, or None/'auto' for the automatic choice
        self.named_graph = named_graph
        #: factories (topic, msgtype) -> callback that also get every recorded output as raw
        #: CDR (the Foxglove live view: ros/foxglove.py)
        self.output_taps = list(output_taps or [])
        self.rate = rate
        self.storage = storage
        self.copy_images = copy_images
        self.executor_kind = executor
        self.progress = progress
        self.step_timeout_s = step_timeout_s
        self.max_messages = max_messages
        self.graph = GRAPH_NODES if graph is None else graph
        self._ledger = _DeliveryLedger()
        self._stop = threading.Event()
        self._consecutive_losses: dict[str, int] = {}
        #: realtime: input header stamp (ns) -> perf_counter when the player published it
        self._published_wall: dict[int, float] = {}

    # -- setup ------------------------------------------------------------------------------

    def run(self) -> RunResult:
        import rclpy
        from rclpy.context import Context

        self.rate = check_rate(self.rate, lockstep=True)
        if self.executor_kind not in EXECUTOR_CHOICES:
            raise RunError(f'unknown executor {self.executor_kind!r}; known: {", ".join(EXECUTOR_CHOICES)}')
        if self.executor_kind in ('multi', 'processes') and self.rate == 0:
            raise RunError(f'--executor {self.executor_kind} is for realtime runs (--rate R); '
                           'lockstep spins one node at a time')
        reader = BagReader(self.bag_path)
        reader.open()
        try:
            return self._run_with(reader, rclpy, Context())
        finally:
            reader.close()

    def _run_with(self, reader: BagReader, rclpy: Any, context: Any) -> RunResult:
        from .node_base import LockstepHooks, RECORDER_QOS, RELIABLE_QOS, TrackingNode
        from .conversions import message_class

        bag_types = reader.topics
        node_params = {name: params_for_node(name, self.params_files) for name in self.graph}
        wanted, ruled_out = choose_nodes(bag_types, self.only_nodes, self.named_graph, self.graph)
        names, skipped = (plan_nodes(bag_types, wanted, self.graph, node_params.__getitem__)
                          if wanted else ([], {}))
        # Asked for by name and not startable: a warning. Left out by the automatic choice (the
        # bag lacks its inputs, or the rule): information.
        explicit = bool(self.only_nodes) or self.named_graph not in (None, 'auto')
        for name, why in skipped.items():
            logger.log(logging.WARNING if explicit else logging.INFO, '%s not started: %s', name, why)
        for name, why in ruled_out.items():
            logger.info('%s not started: %s', name, why)
        if not names:
            raise RunError(
                f'{self.bag_path}: no node can run on this bag '
                f'(topics: {", ".join(sorted(bag_types)) or "none"})'
            )
        domain_id = _init_private_context(rclpy, context, lockstep=self.rate == 0)
        nodes: list[Any] = []
        writer = None
        executor = None
        node_executors: dict[str, Any] = {}
        result = RunResult(self.out_path, bag_duration_s=reader.duration_s, nodes=names,
                           not_started={**skipped, **ruled_out})
        ledger = self._ledger = _DeliveryLedger()
        hooks = LockstepHooks(ledger.delivered, ledger.published, ledger.taken)
        realtime = self.rate > 0
        in_processes = realtime and self.executor_kind == 'processes'
        try:
            transforms = static_transforms(reader) if in_processes and TF_STATIC_TOPIC in reader.topics else []
            for name in names:
                params = dict(node_params[name])
                if realtime:
                    params['use_sim_time'] = True
                if in_processes:
                    from .node_process import NodeProcess

                    handle = NodeProcess(name, self.graph[name], params, domain_id, transforms)
                    handle.start()
                    nodes.append(handle)
                    continue
                cls = load_node_class(self.graph[name])
                try:
                    node = cls(context=context, parameter_overrides=to_overrides(params))
                except Exception as exc:  # a rejected parameter, a bad params file value
                    raise RunError(f'{name}: cannot start ({exc})') from exc
                node.lockstep_hooks = None if realtime else hooks
                nodes.append(node)
            if not in_processes:
                self._hand_static_transforms(reader, nodes)

            consumed = {t for n in nodes for t in _node_class(n).INPUTS}
            feeder = TrackingNode('graph_feeder', context=context)
            feeder.lockstep_hooks = None if realtime else hooks
            nodes.append(feeder)
            feed_pubs: dict[str, Any] = {}
            produced = {t for n in nodes[:-1] for t in _node_class(n).OUTPUTS}
            for topic, msgtype in bag_types.items():
                if topic.lstrip('/') in produced:
                    logger.warning('%s is in the bag and produced by a node: the node wins', topic)
                    continue
                if topic.lstrip('/') in consumed:
                    feed_pubs[topic] = feeder.advertise(message_class(msgtype), topic, RELIABLE_QOS)
            clock_pub = None
            if realtime:
                from rosgraph_msgs.msg import Clock

                clock_pub = feeder.advertise(Clock, '/clock', RELIABLE_QOS)

            output_types: dict[str, str] = {}
            for n in nodes[:-1]:
                for topic, msgtype in _node_class(n).OUTPUTS.items():
                    output_types['/' + topic.lstrip('/')] = msgtype
            recorder_node = TrackingNode('graph_recorder', context=context)
            recorder_node.lockstep_hooks = None if realtime else hooks
            nodes.append(recorder_node)

            copy_topics = {
                t for t, ty in bag_types.items()
                if (t.startswith(COPY_PREFIXES) or t.lstrip('/') in consumed)
                and (self.copy_images or ty not in IMAGE_TYPES)
                and t not in output_types
            }
            writer = BagWriter(self.out_path, storage=self.storage, overwrite=True,  # type: ignore[arg-type]
                               flush_every_s=self.flush_every_s)
            writer.open()
            writer.add_metadata(RUN_METADATA, {
                'source_bag': str(self.bag_path.resolve()), 'nodes': ','.join(names),
                'clock': 'realtime' if realtime else 'lockstep',
            })
            recorder = _Recorder(writer, output_types)
            clock_ns = [reader.start_ns]

            published_wall = self._published_wall = {}

            def make_cb(topic: str) -> Callable[[bytes], None]:
                if realtime:
                    measure = topic == LATENCY_TOPIC
                    latencies = result.live_latency_ms

                    def record_now(raw: bytes) -> None:
                        if measure:  # before the writer lock: receipt, not recording, time
                            received = time.perf_counter()
                            sent = published_wall.get(header_stamp_ns(raw))  # type: ignore[arg-type]
                            if sent is not None:
                                latencies.append((received - sent) * 1e3)
                        with recorder.lock:
                            writer.write(topic, clock_ns[0], raw, msgtype=output_types[topic])
                            recorder.count += 1
                    return record_now
                return lambda raw: recorder.add(topic, raw)

            # The recorder keeps every message: KEEP_ALL, so that no burst of a node is lost.
            for topic, msgtype in sorted(output_types.items()):
                recorder_node.subscribe(message_class(msgtype), topic, self._tapped(make_cb(topic), topic, msgtype),
                                        RECORDER_QOS, raw=True)

            for n in nodes:
                for sub in getattr(n, 'subscriptions', ()):
                    ledger.add(n.get_name(), sub)
            executor = self._make_executor(rclpy, context, realtime)
            if in_processes:
                self._connect_node_processes(nodes, ledger)
            # Realtime with per-node threads: each processing node gets its own executor; the
            # feeder and the recorder stay on the main executor.
            if realtime and self._live_kind() == 'threads':
                from rclpy.executors import SingleThreadedExecutor

                for n in nodes[:-2]:
                    node_executors[n.get_name()] = own = SingleThreadedExecutor(context=context)
                    own.add_node(n)
            for n in nodes:
                if n.get_name() not in node_executors and not hasattr(n, 'node_class'):
                    executor.add_node(n)
            self._wait_for_discovery(executor, nodes)

            total = reader.message_count(set(feed_pubs) | copy_topics)
            if self.max_messages is not None:
                total = min(total, self.max_messages)
            start = time.perf_counter()
            try:
                with _StopOnSignal() as stop:
                    self._stop = stop.requested
                    if realtime:
                        stamp_topics = self._latency_stamp_topics(feed_pubs, bag_types)
                        self._play_realtime(reader, executor, node_executors, nodes, feed_pubs, stamp_topics,
                                            clock_pub, copy_topics, writer, recorder, clock_ns, result, total)
                    else:
                        self._play_lockstep(reader, executor, feed_pubs, copy_topics, writer, recorder, result, total)
                result.interrupted = stop.requested.is_set()
            except KeyboardInterrupt:
                result.interrupted = True
            if result.interrupted:
                logger.warning('interrupted: closing %s with what was processed', self.out_path)
            result.wall_s = time.perf_counter() - start
            if in_processes:
                self._stop_node_processes(nodes, executor, recorder)
            result.output_messages = recorder.count
            if realtime:
                self._live_report(nodes, result)
            else:
                ledger.report(result)
                self._log_drops(result)
                if ledger.corrections:
                    logger.debug('delivery ledger: %d messages booked as replaced were delivered', ledger.corrections)
            for n in nodes[:-2]:
                result.timings_ms[n.get_name()] = {
                    t: list(s.durations_ms) for t, s in n.callback_stats.items()
                }
        finally:
            for own in node_executors.values():
                own.shutdown(timeout_sec=2.0)
            if executor is not None:
                executor.shutdown(timeout_sec=2.0)
            if writer is not None:
                writer.close()
            for n in nodes:
                close = getattr(n, 'close', None)
                if callable(close):
                    close()
                n.destroy_node()
            rclpy.try_shutdown(context=context)
        return result

    def _tapped(self, record: Callable[[bytes], None], topic: str, msgtype: str) -> Callable[[bytes], None]:
        """``record`` followed by the output taps of this topic; a failing tap is logged once
        and left out, never ends the run."""
        taps = [factory(topic, msgtype) for factory in self.output_taps]
        if not taps:
            return record

        def record_and_tap(raw: bytes) -> None:
            record(raw)
            for tap in list(taps):
                try:
                    tap(raw)
                except Exception as exc:  # noqa: BLE001 - a viewer must not end the run
                    logger.warning('%s: output tap failed (%s); left out', topic, exc)
                    taps.remove(tap)
        return record_and_tap

    @staticmethod
    def _hand_static_transforms(reader: BagReader, nodes: list[Any]) -> None:
        """Give the bag's /tf_static to every node with an ``on_static_transforms`` method.

        The pip-only ROS has no tf2_msgs, so no node can subscribe to /tf_static; the runner
        reads it with rosbags (io.bags.static_transforms) and calls the method with the list of
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

    def _make_executor(self, rclpy: Any, context: Any, realtime: bool) -> Any:
        from rclpy.executors import SingleThreadedExecutor

        # 'auto': the EventsExecutor in lockstep. The SingleThreadedExecutor rebuilds its wait
        # set (every subscription, publisher event and parameter service of every node) for
        # each callback: on the sample bag's orientation graph that was half of the profiled
        # time (cProfile: 16 of 32 s in _wait_for_ready_callbacks), the EventsExecutor spends
        # ~1.5 s outside the nodes' callbacks; outputs are byte-identical. Realtime runs keep
        # the SingleThreadedExecutor (the player thread publishes concurrently; a
        # MultiThreadedExecutor's per-callback overhead drops messages at IMU rates). With
        # 'auto' or 'threads' in realtime this executor carries only the feeder and the
        # recorder; each processing node has its own (see _live_kind).
        kind = self.executor_kind
        if kind not in EXECUTOR_CHOICES:
            raise RunError(f'unknown executor {kind!r}; known: {", ".join(EXECUTOR_CHOICES)}')
        if kind == 'auto':
            kind = 'single' if realtime else 'events'
        if kind in ('multi', 'processes') and not realtime:
            raise RunError(f'--executor {kind} is for realtime runs (--rate R); lockstep spins one node at a time')
        if kind == 'processes':
            kind = 'single'  # the feeder and the recorder; each node has its own process
        if kind == 'multi':
            from rclpy.executors import MultiThreadedExecutor

            # every rclpy Node has its own MutuallyExclusiveCallbackGroup as default group: a
            # node's callbacks never overlap, different nodes run in parallel
            return MultiThreadedExecutor(num_threads=max(2, len(self.graph) + 1), context=context)
        if kind == 'events':
            from rclpy.experimental import EventsExecutor

            return EventsExecutor(context=context)
        return SingleThreadedExecutor(context=context)

    def _live_kind(self) -> str:
        """Realtime executor layout: 'threads' (each node on its own thread and
        SingleThreadedExecutor; the default) or 'shared' (every node on one executor of the
        kind asked for: single, events or multi)."""
        return 'threads' if self.executor_kind in ('auto', 'threads') else 'shared'

    @staticmethod
    def _connect_node_processes(nodes: list[Any], ledger: '_DeliveryLedger') -> None:
        """Wait for every node process to build its node, tell each how many subscribers its
        outputs have (other node processes and this process's recorder), wait until they have
        matched, and book the node processes' subscriptions for the feeder's discovery wait."""
        from .node_process import NodeProcessError

        handles = [n for n in nodes if hasattr(n, 'node_class')]
        try:
            for h in handles:
                h.wait_created()
            subscribers: dict[str, int] = defaultdict(int)
            for h in handles:
                for topic in h.subscription_topics:
                    subscribers[topic] += 1
            for topic in ledger.by_topic:
                subscribers[topic] += ledger.subscribers(topic)
            for h in handles:
                h.expect(subscribers)
            for h in handles:
                h.wait_ready()
        except NodeProcessError as exc:
            raise RunError(f'cannot start {exc}') from exc
        for h in handles:
            for topic in h.subscription_topics:
                ledger.external[topic] += 1

    def _stop_node_processes(self, nodes: list[Any], executor: Any, recorder: _Recorder) -> None:
        """Stop the node processes upstream first: a node is asked to stop (it takes what is
        still queued for it, reports its counts and exits) once every node it subscribes to has
        reported, so that a backlog an upstream node is still working off reaches its
        downstream nodes (a node in a cycle, or left when the time is up, is stopped with the
        rest). What they publish meanwhile is recorded until the recorder is quiet."""
        handles = [n for n in nodes if hasattr(n, 'node_class')]
        deadline = time.monotonic() + self.DRAIN_MAX_S
        # upstream[i]: the node processes whose outputs node i subscribes to
        upstream = [{j for j, g in enumerate(handles) if g is not h and set(h.subscription_topics) & set(g.publisher_topics)}
                    for h in handles]
        remaining = set(range(len(handles)))
        while remaining:
            ready = {i for i in remaining if not upstream[i] & remaining}
            if not ready or time.monotonic() >= deadline:
                ready = set(remaining)
            layer = [handles[i] for i in sorted(ready)]
            for h in layer:
                h.request_stop()
            while time.monotonic() < deadline and not all(h.reported() or not h.process.is_alive() for h in layer):
                executor.spin_once(timeout_sec=0.02)
            remaining -= ready
        last, quiet_since = recorder.count, time.monotonic()
        while time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
            if recorder.count != last:
                last, quiet_since = recorder.count, time.monotonic()
            elif time.monotonic() - quiet_since > self.DRAIN_QUIET_S and not any(h.process.is_alive() and
                                                                                  not h.reported() for h in handles):
                break
        for h in handles:
            h.stop()

    def _wait_for_discovery(self, executor: Any, nodes: list[Any], timeout_s: float = 15.0) -> None:
        """Spin until every publisher sees the subscriptions of its topic in this graph."""
        deadline = time.monotonic() + timeout_s
        subscribers = self._ledger.subscribers
        pubs = [p for n in nodes for p in getattr(n, 'publishers', ()) if subscribers(p.topic_name)]
        handles = [n for n in nodes if hasattr(n, 'node_class')]
        while time.monotonic() < deadline:
            for h in handles:
                why = h.died()
                if why is not None:
                    raise RunError(f'{h.name} died while starting: {why}')
            if all(p.get_subscription_count() >= subscribers(p.topic_name) for p in pubs):
                # Every reader matched; let the writers' side settle too.
                executor.spin_once(timeout_sec=0.01)
                return
            executor.spin_once(timeout_sec=0.02)
        missing = [p.topic_name for p in pubs if p.get_subscription_count() < subscribers(p.topic_name)]
        raise RunError(f'nodes did not connect within {timeout_s:g} s on {", ".join(missing)}')

    # -- lockstep --------------------------------------------------------------------------

    def _play_lockstep(
        self,
        reader: BagReader,
        executor: Any,
        feed_pubs: dict[str, Any],
        copy_topics: set[str],
        writer: BagWriter,
        recorder: _Recorder,
        result: RunResult,
        total: int,
    ) -> None:
        done = 0
        for msg in reader.messages(set(feed_pubs) | copy_topics):
            if self._stop.is_set():
                break
            if self.max_messages is not None and done >= self.max_messages:
                break
            if msg.topic in copy_topics:
                writer.write(msg.topic, msg.log_time_ns, msg.rawdata, msgtype=msg.msgtype)
            pub = feed_pubs.get(msg.topic)
            if pub is not None:
                pub.publish(msg.rawdata)
                result.input_messages += 1
                self._settle(executor, result, msg.topic)
                recorder.flush(msg.log_time_ns)
            done += 1
            if self.progress is not None:
                self.progress(done, total)

    #: After this many inputs in a row whose deliveries were lost, the run stops: the graph
    #: is not receiving what the runner publishes (e.g. messages that do not deserialise).
    MAX_CONSECUTIVE_LOSSES = 20

    def _settle(self, executor: Any, result: RunResult, topic: str = '') -> None:
        """Spin until every delivery the ledger expects happened (or give up after the step
        timeout). Messages a full KEEP_LAST history replaced are not expected (the ledger
        counts them at publish time), so a timeout means a delivery that DDS really lost.

        The first loss waits the full step timeout; while losses continue, later steps wait
        only a tenth of it, and a long run of them ends the run with a RunError.
        """
        ledger = self._ledger
        if ledger.settled:
            self._consecutive_losses[topic] = 0
            return
        losses = self._consecutive_losses.get(topic, 0)
        timeout = self.step_timeout_s if losses == 0 else self.step_timeout_s / 10
        deadline = None
        while not ledger.settled:
            executor.spin_once(timeout_sec=0.05)
            if ledger.settled:
                break
            now = time.monotonic()
            if deadline is None:
                deadline = now + timeout
            elif now > deadline:
                lost = ledger.give_up()
                result.lost_deliveries += lost
                self._consecutive_losses[topic] = losses + 1
                logger.warning('%s: %d message deliveries did not happen within %.2f s', topic, lost, timeout)
                if losses + 1 >= self.MAX_CONSECUTIVE_LOSSES:
                    raise RunError(
                        f'the nodes received none of the last {losses + 1} messages on {topic}; '
                        'stopping (are they of the declared type?)'
                    )
                return
        self._consecutive_losses[topic] = 0

    @staticmethod
    def _log_drops(result: RunResult) -> None:
        """One line per node and topic whose queue a burst overflowed (INFO for depth-1
        latest-value subscriptions, WARNING for the others: the node may have needed them)."""
        for node, topics in sorted(result.superseded.items()):
            for topic, n in sorted(topics.items()):
                logger.info('%s: %d messages on %s superseded by newer ones (depth 1: latest value only)',
                            node, n, topic)
        for node, topics in sorted(result.dropped.items()):
            for topic, n in sorted(topics.items()):
                logger.warning('%s: %d messages on %s dropped: a burst overflowed its queue', node, n, topic)

    # -- realtime --------------------------------------------------------------------------

    @staticmethod
    def _latency_stamp_topics(feed_pubs: dict[str, Any], bag_types: dict[str, str]) -> set[str]:
        """The fed topics whose publication times the latency is measured from: the camera
        images (orientation/global carries the image stamp), or without a camera the IMU and
        field samples (the hybrid filter then answers each sample with its stamp)."""
        images = {t for t in feed_pubs if bag_types.get(t) in IMAGE_TYPES}
        return images or {t for t in feed_pubs if bag_types.get(t) in SENSOR_STAMP_TYPES}

    #: Realtime: after the last input, spin until the nodes have processed nothing more for
    #: this long (their queues are empty), at most DRAIN_MAX_S.
    DRAIN_QUIET_S = 0.5
    DRAIN_MAX_S = 10.0

    def _play_realtime(
        self,
        reader: BagReader,
        executor: Any,
        node_executors: dict[str, Any],
        nodes: list[Any],
        feed_pubs: dict[str, Any],
        stamp_topics: set[str],
        clock_pub: Any,
        copy_topics: set[str],
        writer: BagWriter,
        recorder: _Recorder,
        clock_ns: list[int],
        result: RunResult,
        total: int,
    ) -> None:
        """Play the bag from a player thread at ``rate`` while the nodes spin on theirs.

        The player never waits for a node: it sleeps to each message's due time and publishes
        (DDS queues it in each subscription's history; a full history drops its oldest). Each
        node in ``node_executors`` spins on its own thread; the rest (feeder, recorder, or every
        node with a shared executor) on this one. A node thread that dies is booked in
        ``result.failed_nodes`` and ends the playback.
        """
        from rosgraph_msgs.msg import Clock

        from .conversions import to_stamp

        clock = Clock()
        finished = threading.Event()
        stop_nodes = threading.Event()
        errors: list[BaseException] = []
        published_wall = self._published_wall
        late_ms: list[float] = []

        def play() -> None:
            done = 0
            try:
                start_wall = time.monotonic()
                for msg in reader.messages(set(feed_pubs) | copy_topics):
                    if finished.is_set() or (self.max_messages is not None and done >= self.max_messages):
                        break
                    due = start_wall + (msg.log_time_ns - reader.start_ns) * 1e-9 / self.rate
                    delay = due - time.monotonic()
                    if delay > 0 and finished.wait(delay):
                        break
                    late_ms.append(max(0.0, -delay) * 1e3)
                    clock_ns[0] = msg.log_time_ns
                    clock_pub.publish(to_stamp(msg.log_time_ns, clock.clock) and clock)
                    if msg.topic in copy_topics:
                        with recorder.lock:
                            writer.write(msg.topic, msg.log_time_ns, msg.rawdata, msgtype=msg.msgtype)
                    pub = feed_pubs.get(msg.topic)
                    if pub is not None:
                        stamp = header_stamp_ns(msg.rawdata) if msg.topic in stamp_topics else None
                        if stamp is not None:
                            # the first input of a stamp starts its clock (setdefault keeps it)
                            published_wall.setdefault(stamp, time.perf_counter())
                        pub.publish(msg.rawdata)
                        result.input_messages += 1
                    done += 1
                    if self.progress is not None:
                        self.progress(done, total)
            except BaseException as exc:  # reported in the main thread
                errors.append(exc)
            finally:
                finished.set()

        def spin_node(name: str, own: Any) -> None:
            try:
                while not stop_nodes.is_set():
                    own.spin_once(timeout_sec=0.05)
            except BaseException as exc:  # the node is gone: report it, stop the run
                result.failed_nodes[name] = f'{type(exc).__name__}: {exc}'
                logger.error('%s died: %s: %s', name, type(exc).__name__, exc)
                finished.set()

        node_threads = [threading.Thread(target=spin_node, args=(name, own), name=f'node_{name}', daemon=True)
                        for name, own in node_executors.items()]
        for t in node_threads:
            t.start()
        thread = threading.Thread(target=play, name='graph_player', daemon=True)
        thread.start()

        def processed() -> int:
            return recorder.count + sum(len(st.durations_ms) for n in nodes for st in n.callback_stats.values())

        def spin_main() -> None:
            try:
                executor.spin_once(timeout_sec=0.05)
            except BaseException as exc:  # a shared executor: the failing node is not known
                result.failed_nodes.setdefault('executor', f'{type(exc).__name__}: {exc}')
                logger.error('the executor died: %s: %s', type(exc).__name__, exc)
                finished.set()

        handles = [n for n in nodes if hasattr(n, 'node_class')]

        def check_processes() -> None:
            for h in handles:
                why = h.died()
                if why is not None and h.name not in result.failed_nodes:
                    result.failed_nodes[h.name] = why
                    logger.error('%s died: %s', h.name, why)
                    finished.set()

        try:
            while not finished.is_set():
                if self._stop.is_set():
                    finished.set()
                    break
                spin_main()
                check_processes()
            # Drain: let the nodes empty their queues (until nothing moves for DRAIN_QUIET_S).
            if not result.failed_nodes and not self._stop.is_set():
                drain_until = time.monotonic() + self.DRAIN_MAX_S
                last, quiet_since = processed(), time.monotonic()
                while time.monotonic() < drain_until and not result.failed_nodes:
                    spin_main()
                    now_done = processed()
                    if now_done != last:
                        last, quiet_since = now_done, time.monotonic()
                    elif time.monotonic() - quiet_since > self.DRAIN_QUIET_S:
                        break
        finally:
            finished.set()
            thread.join(2.0)
            stop_nodes.set()
            for t in node_threads:
                t.join(5.0)
        if late_ms:
            late_ms.sort()
            result.live_player_late_ms_p95 = late_ms[min(len(late_ms) - 1, int(0.95 * len(late_ms)))]
        if errors:
            raise errors[0]

    @staticmethod
    def _live_report(nodes: list[Any], result: RunResult) -> None:
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
        for node, missed in sorted(result.live_dropped.items()):
            if missed:
                detail = ', '.join(f'{done} of {pub} on {t}' for t, (pub, done) in sorted(result.live_inputs[node].items())
                                   if pub > done)
                logger.warning('%s: %d inputs dropped (processed %s): it did not keep up', node, missed, detail)


class _StopOnSignal:
    """Within the block, Ctrl-C (SIGINT) and SIGTERM ask the run to stop between two messages.

    Raising KeyboardInterrupt from the handler could land inside the bag writer's bookkeeping
    and leave a corrupt bag; a flag checked by the playback loops cannot. A second signal
    raises KeyboardInterrupt at once (for a run stuck somewhere else).
    """

    def __init__(self) -> None:
        self.requested = threading.Event()
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> '_StopOnSignal':
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


def transport_probe_graph() -> dict[str, Any]:
    """A graph of one node that subscribes to every input of the real graph and does nothing:
    running it measures the floor that rclpy transport alone sets (``transport_floor_factor``)."""
    from .conversions import message_class
    from .node_base import SENSOR_QOS, TrackingNode

    inputs: dict[str, str] = {}
    for spec in GRAPH_NODES.values():
        inputs.update(load_node_class(spec).INPUTS)

    class TransportProbe(TrackingNode):
        INPUTS = inputs
        OUTPUTS: dict[str, str] = {}
        REQUIRED_INPUTS: list[str] = []

        def __init__(self, **kwargs: Any) -> None:
            super().__init__('transport_probe', **kwargs)
            for topic, msgtype in self.INPUTS.items():
                self.subscribe(message_class(msgtype), topic, lambda msg: None, SENSOR_QOS, raw=True)

    return {'transport_probe': TransportProbe}
