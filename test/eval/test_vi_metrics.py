"""End to end on a short robot_arcs bag: both nodes in the lockstep runner, then evaluate_vi."""
from __future__ import annotations

from pathlib import Path

import pytest

pytest.importorskip('rclpy')

from ar_tracking.eval.vi_metrics import evaluate_vi  # noqa: E402
from ar_tracking.nodes.marker_tracker import MarkerTrackerNode  # noqa: E402
from ar_tracking.nodes.visual_inertial_filter import VisualInertialFilterNode  # noqa: E402
from ar_tracking.ros.runner import GraphRunner  # noqa: E402
from ar_tracking.sim.bagmaker import make_bag  # noqa: E402

GRAPH = {'marker_tracker': MarkerTrackerNode, 'visual_inertial_filter': VisualInertialFilterNode}


@pytest.fixture(scope='module')
def runs(tmp_path_factory) -> tuple[Path, Path, Path]:
    d = tmp_path_factory.mktemp('vi')
    bag = make_bag('robot_arcs', d / 'arcs.mcap', seed=5, duration_s=9.0)
    outs = []
    for name in ('a', 'b'):
        out = d / f'{name}.out.mcap'
        res = GraphRunner(bag, out, params_files=[d / 'arcs.params.yaml'], graph=GRAPH).run()
        assert res.nodes == ['marker_tracker', 'visual_inertial_filter'] and res.lost_deliveries == 0
        outs.append(out)
    return bag, outs[0], outs[1]


def test_lockstep_runs_are_identical(runs):
    _, a, b = runs
    assert a.read_bytes() == b.read_bytes()


def test_filter_beats_the_held_camera_and_rollback_beats_on_arrival(runs):
    _, out, _ = runs
    m = evaluate_vi(out)
    assert m is not None and m['n'] > 500
    assert m['position_rmse_cm'] * 3 <= m['camera_only']['position_rmse_cm']
    assert m['offline_rollback']['position_rmse_cm'] < m['no_rollback']['position_rmse_cm']
    assert m['orientation_rmse_deg'] < 0.5
    assert m['position_rmse_cm'] < 1.0
    assert '32' in m['by_speed_cm_s']


def test_no_odometry_gives_none(runs):
    bag, _, _ = runs
    assert evaluate_vi(bag) is None
