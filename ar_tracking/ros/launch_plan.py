"""What the launch files start, as plain data (launch/launch_ros are not on the pip-only path,
so the decisions live here, where a test can check them; launch/*.py only turn them into
launch_ros Node actions).

Each node gets its packaged config/<node>.yaml, then the user's params file (or, when none is
given, the device calibration that ``ar-tracking make-bag`` writes next to the bag:
``<bag>.params.yaml``) read for that node, then ``use_sim_time``. A params file that cannot be
read is a :class:`~ar_tracking.ros.params.ParamsError` (one line) at launch. With a namespace, the bag's clock is that
namespace's own (``/<ns>/clock``: bag_replay ``clock_topic: clock`` and every node remaps
``/clock`` to it), so two robots replayed side by side each have a monotonic clock.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .params import params_for_node

#: The graphs the launch files start (after bag_replay).
GRAPHS = {
    'orientation': ['imu_magnetometer', 'panorama_mapper', 'hybrid_orientation_filter'],
    'slam': ['keyframe_slam_mapper'],
}


@dataclass
class NodeSpec:
    """One launch_ros Node: executable (= node name), namespace, parameter files/dicts, remaps."""

    executable: str
    namespace: str = ''
    parameters: list[Any] = field(default_factory=list)
    remappings: list[tuple[str, str]] = field(default_factory=list)


def _truthy(value: str | bool) -> bool:
    return value if isinstance(value, bool) else str(value).strip().lower() in ('1', 'true', 'yes', 'on')


def sidecar_params(bag: str) -> str:
    """``<bag>.params.yaml`` beside a bag file or directory when it exists, else ''."""
    if not bag:
        return ''
    p = Path(bag)
    candidate = p.with_name(p.stem + '.params.yaml') if p.suffix else p.with_name(p.name + '.params.yaml')
    return str(candidate) if candidate.is_file() else ''


def plan(graph: str, bag: str, config_dir: str, namespace: str = '', params: str = '',
         use_sim_time: str | bool = True, rate: str | float = 1.0, loop: str | bool = False,
         own_clock: str = 'auto') -> list[NodeSpec]:
    """The nodes of one launch: bag_replay, then the graph's nodes.

    ``own_clock``: 'auto' (a per-namespace clock when a namespace is given), 'true' or 'false'.
    """
    if graph not in GRAPHS:
        raise ValueError(f'unknown graph {graph!r} (one of {", ".join(GRAPHS)})')
    ns = namespace.strip().strip('/')
    per_ns_clock = bool(ns) if own_clock == 'auto' else _truthy(own_clock)
    user_params = params or sidecar_params(bag)
    remaps = [('/clock', 'clock')] if per_ns_clock else []
    sim = {'use_sim_time': _truthy(use_sim_time)}
    replay = NodeSpec('bag_replay', ns, [
        str(Path(config_dir) / 'bag_replay.yaml'),
        {'bag_path': bag, 'rate': float(rate), 'loop': _truthy(loop),
         'clock_topic': 'clock' if per_ns_clock else '/clock'},
    ])
    specs = [replay]
    for name in GRAPHS[graph]:
        files: list[Any] = [str(Path(config_dir) / f'{name}.yaml')]
        if user_params:
            # As a dict of this node's values (/**, <node>, /<ns>/<node> sections): a file's
            # plain `<node>:` section would not reach the node once it is namespaced.
            files.append(params_for_node(name, [user_params], use_packaged=False, namespace=ns))
        specs.append(NodeSpec(name, ns, files + [sim], list(remaps)))
    return specs
