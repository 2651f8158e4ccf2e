"""Which nodes a graph run starts: the node registry, the named graphs and the planning rules.

Split out of :mod:`ar_tracking.ros.runner` (which re-exports every name here) so that the node
processes (:mod:`ar_tracking.ros.node_process`) can load node classes without importing the
runner. Nothing here starts rclpy: choosing and planning work on topic names and classes only.
"""
from __future__ import annotations

import importlib
import math
from typing import Any, Callable, Iterable

from ..errors import ArTrackingError

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

#: ``--executor``: auto (events in lockstep; with --rate one process per node, or one thread per
#: node for node classes given as classes, not "module:Class" specs), threads (one
#: EventsExecutor per node on its own thread; realtime only), processes (one process per node;
#: realtime only), single (rclpy's SingleThreadedExecutor for every node), events, multi (one
#: MultiThreadedExecutor, a callback group per node).
EXECUTOR_CHOICES = ('auto', 'threads', 'processes', 'single', 'events', 'multi')


class RunError(ArTrackingError):
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



def _satisfied(requirement: str | tuple[str, ...], available: set[str]) -> bool:
    """A required input is a topic, or a tuple of alternatives of which one must be there
    (e.g. ('camera/image_raw', 'camera/image_raw/compressed'))."""
    if isinstance(requirement, str):
        return requirement in available
    return any(t in available for t in requirement)


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
