"""``ar-tracking bench``: speed of the graph and of the cores on this machine, as one JSON object.

Names follow DESIGN.md sec. 8 (``{area: {measure: value}}``). Speed is measured here, never in
the tests. rclpy is imported only inside the functions that run the graph, so the module stays
importable without ROS.
"""
from __future__ import annotations

import logging
import os
import platform
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from .bench_bag import benchmark_bag

logger = logging.getLogger(__name__)

AREAS = ('graph', 'orientation', 'orientation_seeds', 'orientation_photo_worlds', 'panorama', 'markers_vi',
         'annotations', 'slam', 'store', 'foxglove')
#: The real photo turns of ../shared/data that ``orientation_photo_worlds`` cuts camera frames from.
PHOTO_WORLDS = ('pano_grail', 'pano_parrington')


def percentiles_ms(values: list[float]) -> dict[str, float]:
    if not values:
        return {'p50_ms': float('nan'), 'p95_ms': float('nan'), 'n': 0}
    arr = np.asarray(values)
    return {'p50_ms': round(float(np.percentile(arr, 50)), 4),
            'p95_ms': round(float(np.percentile(arr, 95)), 4), 'n': int(arr.size)}


#: The graph area's realtime passes: every node its own process (``graph.live``), then in one
#: process on threads (``graph.live_threads``).
LIVE_EXECUTORS = ('processes', 'threads')


def bench_graph(workdir: Path, duration_s: float, live_rate: float = 1.0,
                live_executors: tuple[str, ...] = LIVE_EXECUTORS) -> dict[str, Any]:
    """realtime_factor of the lockstep graph (as ``run`` chooses its executor, and with every
    node in one process: ``one_process``), the transport floor, per-node processing times;
    and with ``live_rate`` > 0 a realtime pass at that rate per executor in ``live_executors``
    (inputs dropped per node, ``orientation/global`` latency p50/p95 in ms). The first is
    ``live`` (DESIGN names ``graph.live.dropped`` and ``graph.live.latency_ms_p95``): every node
    its own process, as a device runs the graph (``ar-tracking run --executor processes``, like
    ``ros2 launch``); the others ``live_<executor>`` (threads: every node in this process on its
    own thread, sharing the interpreter). Each pass takes the bag's duration / live_rate."""
    from ..ros.runner import GraphRunner, transport_probe_graph

    bag = benchmark_bag(workdir, duration_s)
    params = [p for p in [bag.with_name(bag.stem + '.params.yaml')] if p.exists()]
    full = GraphRunner(bag, workdir / 'graph.out.mcap', params_files=params).run()
    # the same graph with every node in the runner's process (the lockstep before session 26;
    # the run above itself when 'auto' chose that, on a short bag)
    one = full if full.executor == 'events' else GraphRunner(
        bag, workdir / 'graph.one_process.out.mcap', params_files=params, executor='events').run()
    floor = GraphRunner(bag, workdir / 'transport.out.mcap', graph=transport_probe_graph()).run()
    nodes = {node: percentiles_ms([v for values in topics.values() for v in values])
             for node, topics in full.timings_ms.items()}
    callbacks_s, one_callbacks_s = _callbacks_s(full), _callbacks_s(one)
    return {
        'bag': str(bag),
        'bag_duration_s': round(full.bag_duration_s, 3),
        'input_messages': full.input_messages,
        'wall_s': round(full.wall_s, 3),
        'realtime_factor': round(full.realtime_factor, 3),
        # 'auto': on this bag every node in a process of its own (ros/parallel_lockstep.py)
        'executor': full.executor,
        'start_s': round(full.start_s, 3),
        'cpu_s': {node: round(cpu, 3) for node, cpu in sorted(full.live_cpu_s.items())},
        # where the one-process wall goes: the nodes' callbacks, and the rest (runner,
        # transport, recording) - against the transport floor's wall
        'one_process': {'realtime_factor': round(one.realtime_factor, 3), 'wall_s': round(one.wall_s, 3),
                        'start_s': round(one.start_s, 3), 'lost_deliveries': one.lost_deliveries,
                        'node_callbacks_s': round(one_callbacks_s, 3),
                        'wall_minus_callbacks_s': round(one.wall_s - one_callbacks_s, 3)},
        'transport_floor_factor': round(floor.realtime_factor, 3),
        'transport_wall_s': round(floor.wall_s, 3),
        # the nodes' own work: their callbacks, summed over the nodes (in processes of their
        # own they overlap: the wall can be shorter than this)
        'node_callbacks_s': round(callbacks_s, 3),
        # lockstep accounting: timeouts, queue overflows, depth-1 replacements (node -> topic)
        'lost_deliveries': full.lost_deliveries,
        'dropped_deliveries': full.dropped_deliveries,
        'superseded_deliveries': full.superseded_deliveries,
        'dropped': full.dropped,
        'nodes': nodes,
        **{('live' if k == 0 else f'live_{executor}'): _live_pass(bag, params, workdir, live_rate, executor)
           for k, executor in enumerate(live_executors) if live_rate > 0},
    }


def _callbacks_s(result: Any) -> float:
    """The nodes' callback time of a run, summed over nodes and topics, s."""
    return sum(v for topics in result.timings_ms.values() for values in topics.values() for v in values) * 1e-3


def bench_photo_worlds(workdir: Path, seeds: range = range(301, 306)) -> dict[str, Any]:
    """The fresh-seed figures of :func:`.bench_hybrid.bench_seeds` with the camera frames cut
    from each real photo turn of ../shared/data that is present (make-bag ``--world-photos``: an
    office, a lawn with trees) instead of the simulator's drawn street: {world: bench_seeds
    result}, or {'skipped': why} when none is here."""
    from . import SHARED_DATA
    from .bench_hybrid import bench_seeds

    present = [name for name in PHOTO_WORLDS if (SHARED_DATA / name).is_dir()]
    if not present:
        return {'skipped': f'no photo turn ({", ".join(PHOTO_WORLDS)}) in {SHARED_DATA}'}
    return {name: bench_seeds(workdir / name, seeds=seeds, world_photos=SHARED_DATA / name) for name in present}


def _live_pass(bag: Path, params: list[Path], workdir: Path, rate: float, executor: str) -> dict[str, Any]:
    """The graph at ``rate`` x bag speed with the runner's ``executor`` (processes or threads)."""
    from ..ros.runner import GraphRunner

    live = GraphRunner(bag, workdir / f'graph.live_{executor}.out.mcap', params_files=params, rate=rate,
                       executor=executor).run()
    return {'rate': rate, 'executor': executor, 'wall_s': round(live.wall_s, 3), 'failed_nodes': live.failed_nodes,
            **live.live_summary()}


def _rate(fn: Callable[[int], None], n: int) -> float:
    start = time.perf_counter()
    fn(n)
    return n / (time.perf_counter() - start)


def machine() -> dict[str, Any]:
    return {'python': platform.python_version(), 'cpus': os.cpu_count(), 'machine': platform.machine()}


def run_bench(workdir: Path, duration_s: float = 60.0, areas: list[str] | None = None,
              live_executors: tuple[str, ...] = LIVE_EXECUTORS) -> dict[str, Any]:
    """All benchmark areas (or the chosen ones) as one nested dict (``live_executors``: the
    graph area's realtime passes, see :func:`bench_graph`)."""
    workdir.mkdir(parents=True, exist_ok=True)
    chosen = list(areas or AREAS)
    unknown = [a for a in chosen if a not in AREAS]
    if unknown:
        raise ValueError(f'unknown bench area(s) {", ".join(unknown)}; known: {", ".join(AREAS)}')
    results: dict[str, Any] = {'machine': machine()}
    if 'orientation' in chosen:
        from .bench_hybrid import bench_hybrid

        results['orientation'] = bench_hybrid(workdir, duration_s=duration_s)
    if 'orientation_seeds' in chosen:
        from .bench_hybrid import bench_seeds

        # 10 fresh 40 s rotation_sweep seeds through the graph, evaluated (~15 min).
        results['orientation_seeds'] = bench_seeds(workdir / 'seeds')
    if 'orientation_photo_worlds' in chosen:
        # the first 5 of those seeds in each real photo world (~8 min per world)
        results['orientation_photo_worlds'] = bench_photo_worlds(workdir / 'photo_worlds')
    if 'graph' in chosen:
        results['graph'] = bench_graph(workdir, duration_s, live_executors=live_executors)
    if 'panorama' in chosen:
        from .bench_panorama import bench_panorama

        results['panorama'] = bench_panorama(workdir / 'panorama')
    if 'markers_vi' in chosen:
        from .bench_markers_vi import bench_markers_vi

        results.update(bench_markers_vi(workdir / 'markers_vi'))  # areas 'markers' and 'vi'
    if 'annotations' in chosen:
        from .bench_annotations import bench_annotations

        results['annotations'] = bench_annotations()  # incl. the Fig. 7 table over 26 spots (~17 min)
    if 'slam' in chosen:
        from .bench_slam import bench_slam

        results['slam'] = bench_slam()
    if 'store' in chosen:
        from .bench_store import bench_store

        # near() on 100,000 annotations (SQLite, PostGIS), 8 writers + 8 readers for 30 s (~2 min)
        results['store'] = bench_store(workdir / 'store')
    if 'foxglove' in chosen:
        from .bench_foxglove import bench_foxglove

        results['foxglove'] = bench_foxglove(workdir, duration_s=min(duration_s, 20.0))
    return results
