"""What every ar_tracking node shares: parameters with descriptors, guarded callbacks, timing.

A node subclasses :class:`TrackingNode` and uses

* ``self.param(name, default, description, ...)`` to declare a parameter with a description and
  a range (CONVENTIONS habit 7) and read its value;
* ``self.subscribe(...)`` / ``self.advertise(...)`` instead of create_subscription /
  create_publisher. Subscriptions are wrapped so that a callback that raises logs one throttled
  line and the message is skipped (DESIGN sec. 7: a message it cannot use never crashes the
  graph), their processing time is recorded (for ``ar-tracking bench``), and the lockstep runner
  can count deliveries and publications (:class:`LockstepHooks`). Publications are also
  counted per topic (``publish_counts``) and callbacks per topic (``callback_stats``), from
  which the realtime runner tells what each node received from what was published to it.
"""
from __future__ import annotations

import sys
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)

from ..blas import limit_blas_threads
from .params import is_number_list
from .signals import StopOnSignal

#: Sensor subscriptions: best effort, keep last 5 (a reliable publisher still reaches them).
SENSOR_QOS = qos_profile_sensor_data
#: A camera a node tracks every frame of (panorama_mapper): best effort like SENSOR_QOS, keep
#: last 10 (a third of a second at 30 Hz), so that a run of frames costlier than the frame
#: interval (a lost camera relocalising, ~36 ms a frame here) is caught up by the frames after
#: it (~8 ms) instead of dropped.
CAMERA_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT, history=HistoryPolicy.KEEP_LAST)
#: High-rate sensor streams a filter needs every sample of (IMU and field at 100-400 Hz, the
#: visual orientation per frame): best effort like SENSOR_QOS - a driver's sensor-data
#: publisher matches - but keep last 200, so that a stall of the node's process of up to half a
#: second at 400 Hz (2 s at 100 Hz) loses nothing (depth 5 lost samples under load: 50 ms).
STREAM_QOS = QoSProfile(depth=200, reliability=ReliabilityPolicy.BEST_EFFORT, history=HistoryPolicy.KEEP_LAST)
#: The same depth, reliable: for streams the graph's own nodes publish (reliably) between
#: processes, where best effort lost a few samples to a starved reader (3 of 3,600 visual
#: orientations with SLAM on the same 2 cores); a best-effort publisher would not match it.
RELIABLE_STREAM_QOS = QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
#: Estimates and products: reliable, keep last 10.
RELIABLE_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
#: Subscriptions that must see every message (the runner's recorder): reliable, keep all.
RECORDER_QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_ALL)
#: The recorder's reader for a topic published best effort (the only reader that matches it).
RECORDER_BEST_EFFORT_QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.BEST_EFFORT, history=HistoryPolicy.KEEP_ALL)
#: Latched products (maps, static data): reliable + transient local, depth 1.
LATCHED_QOS = QoSProfile(
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
    history=HistoryPolicy.KEEP_LAST,
)


@dataclass
class LockstepHooks:
    """Callbacks the lockstep runner installs to account for every message.

    ``published(topic)`` after each publish (the runner then knows, per subscription of the
    topic, how many messages wait in its history and which one a full KEEP_LAST history just
    dropped); ``taken(subscription)`` when a callback starts (the message has left the history);
    ``delivered(subscription)`` when it has finished (whatever it published is counted by then).
    """

    delivered: Callable[[Any], None]
    published: Callable[[str], None]
    taken: Callable[[Any], None] | None = None


class _CountingPublisher:
    """A publisher proxy that reports each publish to the lockstep hooks (if any)."""

    def __init__(self, node: 'TrackingNode', publisher: Any) -> None:
        self._node = node
        self._publisher = publisher
        #: rclpy's ``topic_name`` asks the rcl handle on every read (~5 us); it never changes
        self._topic = publisher.topic_name

    def publish(self, msg: Any) -> None:
        tap = self._node.publish_tap
        if tap is None:
            self._publisher.publish(msg)
        else:  # lockstep over node processes: the runner carries it (ros/parallel_lockstep.py)
            tap(self._topic, msg)
        self._node.publish_counts[self._topic] += 1
        hooks = self._node.lockstep_hooks
        if hooks is not None:
            hooks.published(self._topic)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._publisher, name)


@dataclass
class CallbackStats:
    """Processing time of each callback call, in milliseconds (bench: p50 / p95)."""

    durations_ms: list[float] = field(default_factory=list)
    failures: int = 0


class TrackingNode(Node):
    """Base class of the ar_tracking nodes (see module docstring)."""

    #: Topics the node subscribes to -> message type (relative names, for the runner).
    INPUTS: dict[str, str] = {}
    #: Topics the node publishes -> message type (relative names, for the runner and recorder).
    OUTPUTS: dict[str, str] = {}
    #: (topic, message or CDR bytes) -> None: takes every publication instead of DDS (set in a
    #: node process of a lockstep run, ros/parallel_lockstep.py; None: publish as usual)
    publish_tap: Callable[[str, Any], None] | None = None

    def __init__(self, node_name: str, **kwargs: Any) -> None:
        kwargs.setdefault('automatically_declare_parameters_from_overrides', False)
        super().__init__(node_name, **kwargs)
        limit_blas_threads()
        self.lockstep_hooks: LockstepHooks | None = None
        self.callback_stats: dict[str, CallbackStats] = defaultdict(CallbackStats)
        #: fully qualified topic -> messages this node published on it (the realtime runner's
        #: live accounting: published to a subscription vs processed by its callback). Each
        #: node publishes from its own thread only, so a plain counter is enough.
        self.publish_counts: dict[str, int] = defaultdict(int)
        #: messages that did not read as their subscription's type (never reached a callback)
        self.unreadable = 0
        self._validators: dict[str, Callable[[Any], str | None]] = {}
        self._live: dict[str, Callable[[Any], None]] = {}
        #: Set by a node that has finished its job (a replay at the end of its bag): the node
        #: script then exits with this code.
        self.exit_code: int | None = None
        self._warned_at: dict[tuple[Any, int], float] = {}
        self._warned_skipped: dict[tuple[Any, int], int] = {}
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._after_set_parameters)

    # -- parameters ------------------------------------------------------------------------

    def param(
        self,
        name: str,
        default: Any,
        description: str,
        *,
        min_value: float | None = None,
        max_value: float | None = None,
        read_only: bool = True,
        validate: Callable[[Any], str | None] | None = None,
        live: Callable[[Any], None] | None = None,
    ) -> Any:
        """Declare a parameter with a description (and a range for numbers); return its value.

        Every parameter either applies live or is read-only (a ``set_parameters`` that returned
        success while nothing changed would mislead): with ``live`` the parameter can be set at
        run time and ``live(value)`` reconfigures the node after each accepted change; without
        it the parameter is declared read_only and a change is refused with that reason.
        ``read_only`` is kept for callers that say so explicitly; it cannot make a parameter
        without ``live`` writable.

        ``validate`` returns None for an acceptable value or the reason it is rejected; it runs
        for the initial value and for every later change (a rejected change leaves the state).
        """
        descriptor = ParameterDescriptor(description=description, read_only=live is None)
        if min_value is not None or max_value is not None:
            lo = -1e300 if min_value is None else min_value
            hi = 1e300 if max_value is None else max_value
            if isinstance(default, bool):
                pass
            elif isinstance(default, int):
                descriptor.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=0)]
            else:
                descriptor.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi), step=0.0)]
        self._coerce_override(name, default)
        value = self.declare_parameter(name, default, descriptor).value
        if validate is not None:
            reason = validate(value)
            if reason is not None:
                raise ValueError(f'parameter {name}: {reason}')
            self._validators[name] = validate
        if live is not None:
            self._live[name] = live
        return value

    def unknown_parameters(self) -> list[str]:
        """Overrides (params file, ``-p``) that name no declared parameter: rclpy ignores them."""
        return sorted(n for n in self._parameter_overrides if not self.has_parameter(n))

    def _coerce_override(self, name: str, default: Any) -> None:
        """Accept 1 for 1.0 (and [0, 0, 0] for a float array) in params files."""
        override = self._parameter_overrides.get(name)
        if override is None:
            return
        value = override.value
        if isinstance(default, float) and isinstance(value, int) and not isinstance(value, bool):
            self._parameter_overrides[name] = Parameter(name, value=float(value))
        elif isinstance(default, list) and default and isinstance(default[0], float) and is_number_list(value):
            self._parameter_overrides[name] = Parameter(name, value=[float(v) for v in value])

    def _on_set_parameters(self, params: Sequence[Parameter]) -> SetParametersResult:
        for p in params:
            check = self._validators.get(p.name)
            if check is not None:
                reason = check(p.value)
                if reason is not None:
                    return SetParametersResult(successful=False, reason=f'{p.name}: {reason}')
        return SetParametersResult(successful=True)

    def _after_set_parameters(self, params: Sequence[Parameter]) -> None:
        """Apply accepted changes of live parameters (validated by :meth:`_on_set_parameters`)."""
        for p in params:
            apply = self._live.get(p.name)
            if apply is None:
                continue
            try:
                apply(p.value)
            except Exception as exc:  # a live change must not end the node
                self.get_logger().error(f'parameter {p.name}: cannot apply {p.value!r} ({type(exc).__name__}: {exc})')
                continue
            self.get_logger().info(f'parameter {p.name} set to {p.value!r}')

    # -- topics ----------------------------------------------------------------------------

    def subscribe(
        self,
        msg_type: Any,
        topic: str,
        callback: Callable[[Any], None],
        qos: QoSProfile = SENSOR_QOS,
        *,
        raw: bool = False,
        view: Callable[[bytes], Any] | None = None,
    ) -> Any:
        """create_subscription with a guarded, timed callback (see module docstring).

        ``view``: a reader of the message's CDR bytes (:mod:`ar_tracking.ros.cdr_views`); the
        subscription is then raw and the callback gets the view (with the message's field
        names and values) instead of the message rclpy would build, at a fraction of the cost
        of rclpy's deserialisation. Bytes that do not read as the type are dropped before the
        callback, as rclpy drops a message it cannot deserialise: never delivered (the lockstep
        runner's step times out on them and books them lost), one throttled error line."""
        stats = self.callback_stats[topic]
        logger = self.get_logger()
        decode = None
        if view is not None:
            from .cdr_views import viewer

            decode = viewer(msg_type, view)
            raw = True

        def guarded(msg: Any) -> None:
            if decode is not None:
                try:
                    msg = decode(msg)
                except Exception as exc:  # not the declared type: dropped, as rclpy would
                    self.unreadable += 1
                    logger.error(f'{topic}: message does not read as {msg_type.__name__} '
                                 f'({type(exc).__name__}: {exc}), dropped', throttle_duration_sec=5.0)
                    return
            hooks = self.lockstep_hooks
            if hooks is not None and hooks.taken is not None:
                hooks.taken(subscription)
            start = time.perf_counter()
            try:
                callback(msg)
            except Exception as exc:  # never let one bad message end the graph
                stats.failures += 1
                logger.error(
                    f'{topic}: message skipped, {type(exc).__name__}: {exc}',
                    throttle_duration_sec=5.0,
                )
            finally:
                stats.durations_ms.append((time.perf_counter() - start) * 1e3)
                if hooks is not None:
                    hooks.delivered(subscription)

        subscription = self.create_subscription(msg_type, topic, guarded, qos, raw=raw)
        return subscription

    def advertise(self, msg_type: Any, topic: str, qos: QoSProfile = RELIABLE_QOS) -> _CountingPublisher:
        """create_publisher, counted for the lockstep runner."""
        return _CountingPublisher(self, self.create_publisher(msg_type, topic, qos))

    # -- logging ---------------------------------------------------------------------------

    def warn_throttled(self, text: str, period_s: float = 5.0) -> None:
        """One warning line, at most once per period for the same call site.

        rclpy's own throttling keys on the line that calls the logger, which would be this
        method for every warning of the node (one kind of bad input would silence all others);
        so the throttle here keys on the caller of warn_throttled.
        """
        caller = sys._getframe(1)
        key = (caller.f_code, caller.f_lineno)
        now = time.monotonic()
        last = self._warned_at.get(key)
        if last is not None and now - last < period_s:
            self._warned_skipped[key] = self._warned_skipped.get(key, 0) + 1
            return
        self._warned_at[key] = now
        skipped = self._warned_skipped.pop(key, 0)
        # the count of the lines the throttle held back, so a recurring problem shows its size
        self.get_logger().warning(text + (f' ({skipped} more like this in the last {now - last:.1f} s)'
                                          if skipped and last is not None else ''))


def _params_files(args: Sequence[str]) -> list[str]:
    """The ``--params-file`` paths of a ``--ros-args`` command line."""
    files: list[str] = []
    in_ros = False
    it = iter(args)
    for a in it:
        if a == '--ros-args':
            in_ros = True
        elif a == '--':
            in_ros = False
        elif in_ros and a == '--params-file':
            files.append(next(it, ''))
    return files


#: The node modules' directory, ar_tracking/nodes beside this package (listed, never imported).
_NODES_DIR = Path(__file__).resolve().parent.parent / 'nodes'


def _known_node_names() -> list[str]:
    """The node module names (the modules of ar_tracking/nodes), for the misspelt-section hint
    of :func:`params_file_warnings`. Listed from the files, so that the ros layer does not
    import the nodes package above it."""
    import pkgutil

    return [m.name for m in pkgutil.iter_modules([str(_NODES_DIR)])]


def params_file_warnings(node: Node, files: Sequence[str]) -> list[str]:
    """What a params file says that this node ignores: unknown parameters in a section for
    this node, and sections named like one of the package's nodes but misspelt."""
    import difflib

    from .params import ParamsError, load_params_file

    known = set(_known_node_names()) | {node.get_name()}
    fqn = node.get_fully_qualified_name().lstrip('/')
    warnings: list[str] = []
    for path in files:
        try:
            sections = load_params_file(path)
        except ParamsError:
            continue  # reported before rclpy.init
        for section, values in sections.items():
            if '*' in section:
                continue  # wildcards (/**) apply to every node: nothing to check
            if section == fqn:
                declared = {n for n in values if node.has_parameter(n)}
                unknown = sorted(set(values) - declared)
                if unknown:
                    warnings.append(f'{path}: {section}: unknown parameter(s) {", ".join(unknown)} (ignored)')
                continue
            base = section.rsplit('/', 1)[-1]
            if base not in known:
                close = difflib.get_close_matches(base, sorted(known), n=1, cutoff=0.75)
                if close:
                    warnings.append(f'{path}: section {section!r} names no node; did you mean {close[0]!r}? (ignored)')
    return warnings


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def node_executor(context: Any) -> Any:
    """The executor one node spins on: rclpy's EventsExecutor (``rclpy.experimental``, Jazzy
    on), else the SingleThreadedExecutor.

    The SingleThreadedExecutor rebuilds its wait set (every subscription, publisher event and
    parameter service of the node) for each callback it runs: at IMU rates that was most of a
    node process's CPU (graph bench, one process per node: imu_magnetometer 21 s of CPU for
    60 s of a 100 Hz IMU and magnetometer, its AHRS ~0.5 s of it). The EventsExecutor queues
    the middleware's events in C++ and runs the callbacks in arrival order, as the other
    does for one node."""
    try:
        from rclpy.experimental import EventsExecutor
    except ImportError:  # an rclpy before Jazzy
        from rclpy.executors import SingleThreadedExecutor

        return SingleThreadedExecutor(context=context)
    return EventsExecutor(context=context)


def run_node(node_factory: Callable[[], Node], args: Sequence[str] | None = None) -> int:
    """main() body of every node executable (CONVENTIONS habit 12).

    A bad parameter or params file ends in one line on stderr and exit code 2 (never a
    traceback); unknown parameters and misspelt node sections of a params file are warned
    about; Ctrl-C (or SIGTERM) stops the node's threads before the context goes away, so it
    exits 0 without a KeyboardInterrupt traceback or "publisher's context is invalid".
    """
    import rclpy
    from rclpy.exceptions import NameValidationException, ParameterException
    from rclpy.executors import ExternalShutdownException
    from rclpy.signals import SignalHandlerOptions

    from .params import ParamsError, load_params_file

    argv = list(sys.argv if args is None else args)
    for path in _params_files(argv):
        try:
            load_params_file(path)
        except ParamsError as exc:
            print(f'error: {exc}', file=sys.stderr)
            return 2

    node = None
    code = 0
    # Ctrl-C / SIGTERM: the spin loop below stops within 0.2 s. The handlers stay installed for
    # the process's end (close and destroy_node below).
    stop = StopOnSignal()
    try:
        stop.__enter__()
        try:
            # rclpy's own SIGINT handler shuts the context down at once, under the feet of
            # threads still publishing; here Ctrl-C sets the stop flag (a second one interrupts).
            rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
        except Exception as exc:  # RCLError: unparsable --ros-args
            print(f'error: {_first_line(exc)}', file=sys.stderr)
            return 2
        try:
            node = node_factory()
        except (ValueError, TypeError, ParameterException, NameValidationException) as exc:
            print(f'error: {_first_line(exc)}', file=sys.stderr)
            return 2
        for text in params_file_warnings(node, _params_files(argv)):
            node.get_logger().warning(text)
        # Short waits, so that a signal is handled within 0.2 s (nothing wakes a wait up
        # without rclpy's signal handler).
        executor = node_executor(node.context)
        executor.add_node(node)
        while not stop.requested.is_set() and node.context.ok() and getattr(node, 'exit_code', None) is None:
            executor.spin_once(timeout_sec=0.2)
        code = getattr(node, 'exit_code', None) or 0
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        try:
            if node is not None:
                close = getattr(node, 'close', None)
                if callable(close):
                    close()
                node.destroy_node()
        except KeyboardInterrupt:
            pass
        rclpy.try_shutdown()
    return code
