"""The benchmark's plumbing on a short bag (speeds are reported, never asserted)."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

pytest.importorskip('rclpy')

from ar_tracking.eval.bench import run_bench  # noqa: E402


def test_bench_reports_the_design_names(tmp_path):
    # the live pass as the graph is deployed: every node its own process (the threads pass is
    # the same code with the runner's default executor, which test_runner covers)
    results = run_bench(tmp_path, duration_s=2.0, areas=['graph'], live_executors=('processes',))
    graph = results['graph']
    for key in ('realtime_factor', 'transport_floor_factor', 'wall_s', 'input_messages'):
        assert key in graph
    assert graph['realtime_factor'] > 0 and graph['transport_floor_factor'] > 0
    # a 2 s bag: 'auto' keeps the nodes in the runner's process (processes pay off from 30 s)
    assert graph['executor'] == 'events' and graph['one_process']['realtime_factor'] > 0 and graph['start_s'] > 0
    # 2 s of IMU + magnetometer at 100 Hz, and camera images + camera_info at 30 Hz
    assert graph['input_messages'] == 400 + 120
    node = graph['nodes']['imu_magnetometer']
    assert node['n'] == 400 and 0 < node['p50_ms'] <= node['p95_ms']
    assert graph['nodes']['panorama_mapper']['n'] == 120
    assert graph['lost_deliveries'] == 0 and graph['dropped_deliveries'] == 0  # lockstep loses nothing
    # the one-process wall split: the nodes' callbacks and the rest add up to it
    one = graph['one_process']
    assert 0 < graph['node_callbacks_s'] and 0 < one['node_callbacks_s'] < one['wall_s']
    assert one['node_callbacks_s'] + one['wall_minus_callbacks_s'] == pytest.approx(one['wall_s'], abs=2e-3)
    live = graph['live']  # the realtime pass at 1x: counts per node and the latency keys
    assert live['executor'] == 'processes' and 'live_threads' not in graph
    assert live['failed_nodes'] == {} and set(live['dropped']) == set(graph['nodes'])
    assert live['inputs']['imu_magnetometer']['/imu/data_raw']['published'] == 200
    assert live['latency_n'] > 0 and 'latency_ms_p95' in live
    json.dumps(results)  # JSON-able


def test_bench_unknown_area_is_a_usage_error(tmp_path):
    proc = subprocess.run([sys.executable, '-m', 'ar_tracking.cli', 'bench', '--areas', 'teleportation',
                           '--workdir', str(tmp_path)], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and 'teleportation' in proc.stderr and 'Traceback' not in proc.stderr


def test_quiet_bench_prints_its_json_and_no_node_logs(tmp_path):
    """-q: the nodes the bench runs in this process log nothing (their info lines were printed)."""
    proc = subprocess.run([sys.executable, '-m', 'ar_tracking.cli', 'bench', '--areas', 'graph', '--duration', '1',
                           '--workdir', str(tmp_path), '-q'], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert 'graph' in json.loads(proc.stdout)
    assert '[INFO]' not in proc.stderr and '[WARN]' not in proc.stderr, proc.stderr[-2000:]


def test_the_photo_worlds_bench_runs_each_world_present_and_says_when_none_is(tmp_path, monkeypatch):
    import ar_tracking.eval as evaluation
    import ar_tracking.eval.bench_hybrid as bench_hybrid
    from ar_tracking.eval.bench import bench_photo_worlds

    monkeypatch.setattr(evaluation, 'SHARED_DATA', tmp_path / 'data')
    assert 'pano_grail' in bench_photo_worlds(tmp_path)['skipped']
    (tmp_path / 'data' / 'pano_parrington').mkdir(parents=True)
    calls = []
    monkeypatch.setattr(bench_hybrid, 'bench_seeds',
                        lambda workdir, seeds, world_photos: calls.append((workdir, list(seeds), world_photos)) or {})
    assert list(bench_photo_worlds(tmp_path / 'w', seeds=range(7, 9))) == ['pano_parrington']
    assert calls == [(tmp_path / 'w' / 'pano_parrington', [7, 8], tmp_path / 'data' / 'pano_parrington')]
