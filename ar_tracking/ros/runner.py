"""The graph runner behind ``ar-tracking run``: every node that can run on a bag, one output bag.

Two clocks (DESIGN sec. 4):

* **lockstep** (default): all nodes in one process on a private rclpy Context. The runner
  publishes one input message, then spins until every subscription that should receive it -
  and, recursively, every message the nodes publish in response - has been delivered and
  processed. Only then does the next input go out. A burst larger than a subscription's
  KEEP_LAST depth is booked at publish time as superseded (depth 1: the node wants the latest
  value only) or dropped (a deeper queue overflowed), never waited for, and reported in the
  run result by node and topic (:class:`~ar_tracking.ros.run_state.DeliveryLedger`). Outputs are written with the log time of the
  input that caused them, in a fixed order, so two runs give byte-identical output bags.
* **realtime** (``rate > 0``): the bag is played at ``rate`` times its speed with ``/clock``;
  nodes use sim time and whatever they cannot keep up with is dropped, like on a device. Each
  node runs in a process of its own, as ``ros2 launch`` starts them (or on a thread of its own
  in this process: ``executor='threads'``, and for node classes that are not importable by a
  "module:Class" spec), so a slow node (SLAM, the panorama) cannot stall the IMU path, and the
  player thread publishes on schedule whatever the nodes do. The run counts, per node, the inputs published to it against those its
  callbacks processed (:attr:`RunResult.live_dropped`), measures the end-to-end latency of
  ``orientation/global`` (input stamp published -> output received by the recorder), and
  reports a node whose thread died (then the run stops and ``ar-tracking run`` exits 1).

Inputs the evaluation needs (ground truth, static transforms, the non-image sensor topics) are
copied into the output bag; images only on request. The output bag is closed cleanly on every
exit path, Ctrl-C included, with everything processed so far. A kill that no handler sees
(SIGKILL, out of memory) leaves an MCAP without its summary: the writer flushes a chunk every
``flush_every_s`` of bag time, and :class:`~ar_tracking.io.bags.BagReader` recovers what reached
the file.

The runner is split in four modules: :mod:`~ar_tracking.ros.graph_plan` (which nodes start),
:mod:`~ar_tracking.ros.run_state` (the result, the ledger, the recorder), this one (set-up,
lockstep feeding, teardown) and :mod:`~ar_tracking.ros.live_play` (realtime playback and node
processes). Every public name of the first two is importable from here.
"""
from __future__ import annotations

import itertools
import logging
import os
import threading
import time
from pathlib import Path
from typing import Any, Callable

from ..io.bags import BagReader, BagWriter
from ..io.static_tf import TF_STATIC_TOPIC, static_transforms
from .graph_plan import (EXECUTOR_CHOICES, GRAPH_CHOICES, GRAPH_NODES, NAMED_GRAPHS, ROTATION_IN_PLACE_TOPIC,
                         RunError, check_rate, choose_nodes, load_node_class, plan_nodes, transport_probe_graph)
from .live_play import (IMAGE_TYPES, SENSOR_STAMP_TYPES, RealtimePlayback, best_effort_outputs, connect_node_processes, latency_stamp_topics, live_report,
                        publisher_counts, stop_node_processes)
from .node_process import READER_MATCH_TIMEOUT_S, NodeProcess
from .params import params_for_node, to_overrides
from .run_state import DeliveryLedger, Recorder, RunResult, RunSession, hand_static_transforms, header_stamp_ns, log_drops
from .signals import StopOnSignal

__all__ = [
    'COPY_PREFIXES', 'EXECUTOR_CHOICES', 'GRAPH_CHOICES', 'GRAPH_NODES', 'IMAGE_TYPES', 'LATENCY_TOPIC',
    'NAMED_GRAPHS', 'ROTATION_IN_PLACE_TOPIC', 'RUN_METADATA', 'SENSOR_STAMP_TYPES', 'GraphRunner', 'RunError',
    'RunResult', 'check_rate', 'choose_nodes', 'header_stamp_ns', 'load_node_class', 'plan_nodes',
    'transport_probe_graph',
]

logger = logging.getLogger(__name__)

#: Name of the MCAP metadata record in which an output bag says where it came from.
RUN_METADATA = 'ar_tracking.run'

#: Topics copied from the input bag to the output by default (prefix match).
COPY_PREFIXES = ('/ground_truth/', '/tf_static', '/tf', '/gps/', '/imu/')
#: Lockstep: 'auto' runs the nodes in processes of their own on bags at least this long, s.
PARALLEL_LOCKSTEP_MIN_S = 30.0
#: Realtime: the output whose end-to-end latency the run measures (input stamp -> received).
LATENCY_TOPIC = '/orientation/global'


_runs_in_process = itertools.count()


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
        compression: str = 'lz4',
    ) -> None:
        self.bag_path = Path(bag)
        self.compression = compression  # of the output MCAP's chunks (io.bags.MCAP_COMPRESSIONS)
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
        #: ``executor_kind`` with 'auto' resolved for this run (:meth:`_resolve_executor`)
        self._executor = executor
        self.progress = progress
        self.step_timeout_s = step_timeout_s
        self.max_messages = max_messages
        self.graph = GRAPH_NODES if graph is None else graph
        self._ledger = DeliveryLedger()
        self._stop = threading.Event()
        self._consecutive_losses: dict[str, int] = {}

    # -- setup ------------------------------------------------------------------------------

    def run(self) -> RunResult:
        import rclpy
        from rclpy.context import Context

        self.rate = check_rate(self.rate, lockstep=True)
        if self.executor_kind not in EXECUTOR_CHOICES:
            raise RunError(f'unknown executor {self.executor_kind!r}; known: {", ".join(EXECUTOR_CHOICES)}')
        if self.executor_kind == 'multi' and self.rate == 0:
            raise RunError('--executor multi is for realtime runs (--rate R); lockstep spins one node at a time')
        reader = BagReader(self.bag_path)
        reader.open()
        try:
            return self._run_with(reader, rclpy, Context())
        finally:
            reader.close()

    def _resolve_executor(self, names: list[str], duration_s: float) -> str:
        """The executor layout of this run: ``executor_kind``, where 'auto' is one process per
        node when every node of the graph can start in a process of its own (a "module:Class"
        spec) - in realtime always (the deployment shape; the graph bench's live pass: no input
        dropped, orientation latency p95 ~30 ms, against 36 dropped frames and 108 ms with the
        nodes on threads of one process, which share its interpreter), in lockstep for two nodes
        or more on a bag of PARALLEL_LOCKSTEP_MIN_S or longer (ros/parallel_lockstep.py: the
        nodes work in parallel; starting their processes costs a few seconds) - and otherwise
        one thread per node in realtime, the EventsExecutor in lockstep."""
        if self.executor_kind != 'auto':
            return self.executor_kind
        importable = all(isinstance(self.graph[name], str) for name in names)
        if self.rate > 0:
            return 'processes' if importable else 'threads'
        return 'processes' if importable and len(names) >= 2 and duration_s >= PARALLEL_LOCKSTEP_MIN_S else 'events'

    def _run_with(self, reader: BagReader, rclpy: Any, context: Any) -> RunResult:
        """Set up the graph, feed it the bag, drain it, and tear it down on every exit path."""
        started = time.perf_counter()
        names, not_started, node_params = self._plan(reader.topics)
        self._executor = self._resolve_executor(names, reader.duration_s)
        domain_id = _init_private_context(rclpy, context, lockstep=self.rate == 0)
        result = RunResult(self.out_path, bag_duration_s=reader.duration_s, nodes=names, not_started=not_started,
                           executor=self._executor)
        self._ledger = DeliveryLedger()
        realtime = self.rate > 0
        session = RunSession(reader, result, realtime=realtime, in_processes=self._executor == 'processes')
        session.lockstep_hooks = self._hooks()
        try:
            self._start_nodes(session, names, node_params, context, domain_id)
            self._wire(session, names, context)
            result.start_s = time.perf_counter() - started
            self._feed(session)
            self._finish(session)
        finally:
            self._teardown(session, rclpy, context)
        return result

    def _plan(self, bag_types: dict[str, str]) -> tuple[list[str], dict[str, str], dict[str, dict[str, Any]]]:
        """The nodes to start (in order), why the others are not started, and every node's
        merged parameters; RunError if none can run."""
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
        return names, {**skipped, **ruled_out}, node_params

    def _hooks(self) -> Any:
        """The lockstep hooks every in-process node reports deliveries through (None in realtime):
        built once per run into ``RunSession.lockstep_hooks``."""
        from .node_base import LockstepHooks

        ledger = self._ledger
        return None if self.rate > 0 else LockstepHooks(ledger.delivered, ledger.published, ledger.taken)

    def _start_nodes(self, s: RunSession, names: list[str], node_params: dict[str, dict[str, Any]],
                     context: Any, domain_id: int) -> None:
        """Build the processing nodes (or start their processes) into ``s.nodes``, and hand
        in-process nodes the bag's static transforms."""
        reader = s.reader
        hooks = s.lockstep_hooks
        transforms = static_transforms(reader) if s.in_processes and TF_STATIC_TOPIC in reader.topics else []
        for name in names:
            params = dict(node_params[name])
            if s.realtime:
                params['use_sim_time'] = True
            if s.in_processes:
                handle = NodeProcess(name, self.graph[name], params, domain_id, transforms, lockstep=not s.realtime)
                handle.start()
                s.nodes.append(handle)
                continue
            cls = load_node_class(self.graph[name])
            try:
                node = cls(context=context, parameter_overrides=to_overrides(params))
            except Exception as exc:  # a rejected parameter, a bad params file value
                raise RunError(f'{name}: cannot start ({exc})') from exc
            node.lockstep_hooks = hooks
            s.nodes.append(node)
        if not s.in_processes:
            hand_static_transforms(reader, s.nodes)

    def _wire(self, s: RunSession, names: list[str], context: Any) -> None:
        """The feeder (a publisher per consumed bag topic, /clock in realtime), the recorder
        node and the output bag, the executors, and the wait until everything has matched."""
        from .conversions import message_class
        from .node_base import RELIABLE_QOS, TrackingNode

        bag_types = s.reader.topics
        hooks = s.lockstep_hooks
        parallel = s.in_processes and not s.realtime
        consumed = {t for n in s.nodes for t in _node_class(n).INPUTS}
        produced = {t for n in s.nodes for t in _node_class(n).OUTPUTS}
        output_types: dict[str, str] = {}
        for n in s.nodes:
            for topic, msgtype in _node_class(n).OUTPUTS.items():
                output_types['/' + topic.lstrip('/')] = msgtype
        feeder = TrackingNode('graph_feeder', context=context)
        feeder.lockstep_hooks = hooks
        s.nodes.append(feeder)
        for topic, msgtype in bag_types.items():
            if topic.lstrip('/') in produced:
                logger.warning('%s is in the bag and produced by a node: the node wins', topic)
                continue
            if topic.lstrip('/') in consumed:  # (a lockstep over node processes feeds them over pipes)
                s.feed_pubs[topic] = (None if parallel else feeder.advertise(message_class(msgtype), topic, RELIABLE_QOS))
        if s.realtime:
            from rosgraph_msgs.msg import Clock

            s.clock_pub = feeder.advertise(Clock, '/clock', RELIABLE_QOS)
        recorder_node = TrackingNode('graph_recorder', context=context)
        recorder_node.lockstep_hooks = hooks
        s.nodes.append(recorder_node)
        s.copy_topics = {
            t for t, ty in bag_types.items()
            if (t.startswith(COPY_PREFIXES) or t.lstrip('/') in consumed)
            and (self.copy_images or ty not in IMAGE_TYPES)
            and t not in output_types
        }
        self._open_output(s, names, output_types, None if parallel else recorder_node)
        if parallel:
            self._connect_parallel(s, output_types)
        else:
            self._make_executors(s, context)
            self._wait_for_discovery(s.executor, s.nodes)
        s.total = s.reader.message_count(set(s.feed_pubs) | s.copy_topics)
        if self.max_messages is not None:
            s.total = min(s.total, self.max_messages)

    def _open_output(self, s: RunSession, names: list[str], output_types: dict[str, str], recorder_node: Any) -> None:
        """Open the output bag and subscribe the recorder node (if any) to every node output."""
        from .conversions import message_class
        from .node_base import RECORDER_BEST_EFFORT_QOS, RECORDER_QOS

        writer = s.writer = BagWriter(self.out_path, storage=self.storage, overwrite=True,  # type: ignore[arg-type]
                                      flush_every_s=self.flush_every_s, compression=self.compression)
        writer.open()
        writer.add_metadata(RUN_METADATA, {
            'source_bag': str(self.bag_path.resolve()), 'nodes': ','.join(names),
            'clock': 'realtime' if s.realtime else 'lockstep',
        })
        s.recorder = Recorder(writer, output_types)
        s.clock_ns = [s.reader.start_ns]
        if recorder_node is None:  # lockstep over node processes: outputs come over the pipes
            return
        # The recorder keeps every message (KEEP_ALL) with the reliability its publishers offer
        # (as rosbag2: a reliable reader never matches a best-effort publisher).
        best_effort = best_effort_outputs(s.nodes)
        for topic, msgtype in sorted(output_types.items()):
            qos = RECORDER_BEST_EFFORT_QOS if topic in best_effort else RECORDER_QOS
            recorder_node.subscribe(message_class(msgtype), topic,
                                    self._tapped(self._record_callback(s, topic, output_types), topic, msgtype),
                                    qos, raw=True)

    def _connect_parallel(self, s: RunSession, output_types: dict[str, str]) -> None:
        """Lockstep over node processes: wait for them to start, and the runner's
        :class:`~ar_tracking.ros.parallel_lockstep.ParallelLockstep` that feeds them."""
        from .parallel_lockstep import ParallelLockstep

        recorder = s.recorder
        assert recorder is not None
        # each output as the in-process recorder node takes it (the step's batch, the taps)
        record = {t: self._tapped(self._record_callback(s, t, output_types), t, ty) for t, ty in output_types.items()}

        def take(topic: str, raw: bytes) -> None:
            keep = record.get(topic)  # a topic no node class declares is not recorded, as in one process
            if keep is not None:
                keep(raw)
        s.parallel = ParallelLockstep([n for n in s.nodes if hasattr(n, 'node_class')], recorder, s.result, take)
        s.parallel.connect()

    def _record_callback(self, s: RunSession, topic: str, output_types: dict[str, str]) -> Callable[[bytes], None]:
        """How the recorder takes one output: in lockstep into the step's batch (written in a
        fixed order at the step's end); in realtime written at once with the play clock's log
        time, after the latency of ``LATENCY_TOPIC`` is measured."""
        recorder, writer, clock_ns = s.recorder, s.writer, s.clock_ns
        assert recorder is not None and writer is not None
        if not s.realtime:
            return lambda raw: recorder.add(topic, raw)
        measure = topic == LATENCY_TOPIC
        latencies = s.result.live_latency_ms
        published_wall = s.published_wall

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

    def _make_executors(self, s: RunSession, context: Any) -> None:
        """Book every subscription in the ledger, make the executor(s), connect the node
        processes, and add each in-process node to its executor."""
        ledger = self._ledger
        for n in s.nodes:
            for sub in getattr(n, 'subscriptions', ()):
                ledger.add(n.get_name(), sub)
        s.executor = self._make_executor(context, s.realtime)
        if s.in_processes:
            connect_node_processes(s.nodes, ledger)
        # Realtime with per-node threads: each processing node gets its own executor; the
        # feeder and the recorder stay on the main executor.
        if s.realtime and self._executor == 'threads':
            from .node_base import node_executor

            for n in s.nodes[:-2]:
                s.node_executors[n.get_name()] = own = node_executor(context)
                own.add_node(n)
        for n in s.nodes:
            if n.get_name() not in s.node_executors and not hasattr(n, 'node_class'):
                s.executor.add_node(n)

    def _feed(self, s: RunSession) -> None:
        """Play the bag (lockstep or realtime) until its end, a stop request or Ctrl-C."""
        result = s.result
        start = time.perf_counter()
        try:
            with StopOnSignal() as stop:
                self._stop = stop.requested
                if s.realtime:
                    s.stamp_topics = latency_stamp_topics(s.feed_pubs, s.reader.topics)
                    RealtimePlayback(s, rate=self.rate, max_messages=self.max_messages, progress=self.progress,
                                     stop=self._stop).run()
                elif s.parallel is not None:
                    s.parallel.play(s.reader.messages(set(s.feed_pubs) | s.copy_topics), set(s.feed_pubs),
                                    s.copy_topics, self._stop, self.max_messages, self.progress, s.total)
                else:
                    self._play_lockstep(s)
            result.interrupted = stop.requested.is_set()
        except KeyboardInterrupt:
            result.interrupted = True
        if result.interrupted:
            logger.warning('interrupted: closing %s with what was processed', self.out_path)
        result.wall_s = time.perf_counter() - start

    def _finish(self, s: RunSession) -> None:
        """After the feed: stop the node processes, then the counts into the result."""
        result, ledger = s.result, self._ledger
        assert s.recorder is not None
        if s.in_processes and s.realtime:
            stop_node_processes(s.nodes, s.executor, s.recorder)
        if s.parallel is not None:
            s.parallel.finish()
        result.output_messages = s.recorder.count
        if s.realtime:
            live_report(s.nodes, result)
        else:
            ledger.report(result)
            log_drops(result)
            if ledger.corrections:
                logger.debug('delivery ledger: %d messages booked as replaced were delivered', ledger.corrections)
        for n in s.nodes[:-2]:
            result.timings_ms[n.get_name()] = {
                t: list(st.durations_ms) for t, st in n.callback_stats.items()
            }

    @staticmethod
    def _teardown(s: RunSession, rclpy: Any, context: Any) -> None:
        """Shut the executors down, close the output bag (a valid bag on every exit path),
        close and destroy every node, shut the private context down."""
        for own in s.node_executors.values():
            own.shutdown(timeout_sec=2.0)
        if s.executor is not None:
            s.executor.shutdown(timeout_sec=2.0)
        if s.writer is not None:
            s.writer.close()
        for n in s.nodes:
            close = getattr(n, 'close', None)
            if callable(close):
                close()
            n.destroy_node()
        rclpy.try_shutdown(context=context)

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

    def _make_executor(self, context: Any, realtime: bool) -> Any:
        from rclpy.executors import SingleThreadedExecutor

        from .node_base import node_executor

        # The EventsExecutor (node_base.node_executor) unless asked otherwise: rclpy's
        # SingleThreadedExecutor rebuilds its wait set for each callback (lockstep on the sample
        # bag's orientation graph: 16 of 32 s in _wait_for_ready_callbacks; outputs byte-identical).
        # A MultiThreadedExecutor's per-callback overhead drops messages at IMU rates; 'single'
        # keeps rclpy's default for comparison. (run() has checked the kind against the clock.)
        kind = self._executor
        if kind in ('auto', 'threads', 'processes', 'events'):
            return node_executor(context)  # realtime: the feeder and the recorder (nodes have their own)
        if kind == 'multi':
            from rclpy.executors import MultiThreadedExecutor

            # every rclpy Node has its own MutuallyExclusiveCallbackGroup as default group: a
            # node's callbacks never overlap, different nodes run in parallel
            return MultiThreadedExecutor(num_threads=max(2, len(self.graph) + 1), context=context)
        return SingleThreadedExecutor(context=context)

    def _wait_for_discovery(self, executor: Any, nodes: list[Any], timeout_s: float = 15.0) -> None:
        """Spin until every publisher sees the subscriptions of its topic in this graph and, with
        node processes, this process's subscriptions see their publishers (a best-effort reader
        drops what a writer it has not yet discovered sends; waited for at most
        READER_MATCH_TIMEOUT_S: a QoS that never matches does not hold the run)."""
        deadline = time.monotonic() + timeout_s
        subscribers = self._ledger.subscribers
        pubs = [p for n in nodes for p in getattr(n, 'publishers', ()) if subscribers(p.topic_name)]
        handles = [n for n in nodes if hasattr(n, 'node_class')]
        publishers = publisher_counts(nodes) if handles else {}
        readers = [r for n in nodes if not hasattr(n, 'node_class') for r in getattr(n, 'subscriptions', ())
                   if publishers.get(r.topic_name)]
        readers_deadline = time.monotonic() + READER_MATCH_TIMEOUT_S
        while time.monotonic() < deadline:
            for h in handles:
                why = h.died()
                if why is not None:
                    raise RunError(f'{h.name} died while starting: {why}')
            if (all(p.get_subscription_count() >= subscribers(p.topic_name) for p in pubs)
                    and (time.monotonic() > readers_deadline
                         or all(r.get_publisher_count() >= publishers[r.topic_name] for r in readers))):
                # Every reader matched; let the writers' side settle too.
                executor.spin_once(timeout_sec=0.01)
                return
            executor.spin_once(timeout_sec=0.02)
        missing = [p.topic_name for p in pubs if p.get_subscription_count() < subscribers(p.topic_name)]
        raise RunError(f'nodes did not connect within {timeout_s:g} s on {", ".join(missing)}')

    # -- lockstep --------------------------------------------------------------------------

    def _play_lockstep(self, s: RunSession) -> None:
        """Publish one input, settle the graph, write the step's outputs; then the next."""
        writer, recorder, result = s.writer, s.recorder, s.result
        assert writer is not None and recorder is not None
        done = 0
        for msg in s.reader.messages(set(s.feed_pubs) | s.copy_topics):
            if self._stop.is_set():
                break
            if self.max_messages is not None and done >= self.max_messages:
                break
            if msg.topic in s.copy_topics:
                writer.write(msg.topic, msg.log_time_ns, msg.rawdata, msgtype=msg.msgtype)
            pub = s.feed_pubs.get(msg.topic)
            if pub is not None:
                pub.publish(msg.rawdata)
                result.input_messages += 1
                self._settle(s.executor, result, msg.topic)
                recorder.flush(msg.log_time_ns)
            done += 1
            if self.progress is not None:
                self.progress(done, s.total)

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
