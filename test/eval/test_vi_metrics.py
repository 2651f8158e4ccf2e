"""End to end on short robot_arcs bags: both nodes in the lockstep runner, then evaluate_vi; the
hard profile's IMU mount from /tf_static against the same mount from parameters."""
from __future__ import annotations

from pathlib import Path

import pytest
import yaml

pytest.importorskip('rclpy')

from ar_tracking.eval.evaluate import evaluate_all  # noqa: E402
from ar_tracking.eval.vi_metrics import evaluate_markers, evaluate_vi  # noqa: E402
from ar_tracking.nodes.marker_tracker import MarkerTrackerNode  # noqa: E402
from ar_tracking.nodes.visual_inertial_filter import VisualInertialFilterNode  # noqa: E402
from ar_tracking.ros.runner import GraphRunner  # noqa: E402
from ar_tracking.io.bags import BagReader, BagWriter  # noqa: E402
from ar_tracking.sim import robot_arcs_real as rr  # noqa: E402
from ar_tracking.sim.bagmaker import make_bag  # noqa: E402

GRAPH = {'marker_tracker': MarkerTrackerNode, 'visual_inertial_filter': VisualInertialFilterNode}


@pytest.fixture(scope='module')
def runs(tmp_path_factory) -> tuple[Path, Path, Path]:
    d = tmp_path_factory.mktemp('vi')
    bag = make_bag('robot_arcs', d / 'arcs.mcap', seed=5, duration_s=9.0, profile='kind')
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


@pytest.fixture(scope='module')
def mount_runs(tmp_path_factory) -> tuple[dict, dict, Path]:
    """The same hard bag twice: the mount only on /tf_static (the sidecar has no mount), and
    without /tf_static with the mount in the parameters (a copy of the first without its
    /tf_static: what rr.write_bag(mount_on_tf_static=False) writes, see the test below, without
    rendering the frames a second time)."""
    d = tmp_path_factory.mktemp('vi_mount')
    seed, duration = 7, 5.0
    tf_bag = make_bag('robot_arcs', d / 'tf.mcap', seed=seed, duration_s=duration)
    side = yaml.safe_load((d / 'tf.params.yaml').read_text())
    assert 'imu_to_camera_xyzw' not in side['visual_inertial_filter']['ros__parameters']
    par_bag = d / 'par.mcap'
    with BagReader(tf_bag) as r, BagWriter(par_bag) as w:
        assert '/tf_static' in r.topics
        for m in r.messages([t for t in r.topics if t != '/tf_static']):
            w.write(m.topic, m.log_time_ns, m.rawdata, m.msgtype)
    side['visual_inertial_filter']['ros__parameters'].update(rr.mount_params())
    (d / 'par.params.yaml').write_text(yaml.safe_dump(side))
    out = {}
    for name, bag, params in (('tf', tf_bag, d / 'tf.params.yaml'), ('par', par_bag, d / 'par.params.yaml')):
        res = GraphRunner(bag, d / f'{name}.out.mcap', params_files=[params], graph=GRAPH).run()
        assert res.lost_deliveries == 0
        out[name] = evaluate_vi(d / f'{name}.out.mcap')
    return out['tf'], out['par'], d / 'tf.out.mcap'


def _bag_messages(path: Path) -> list[tuple[str, int, bytes]]:
    with BagReader(path) as bag:
        return [(m.topic, m.log_time_ns, m.rawdata) for m in bag.messages()]


def test_a_bag_without_the_mount_on_tf_static_is_the_same_bag_without_tf_static(tmp_path):
    """rr.write_bag(mount_on_tf_static=False) leaves out /tf_static and nothing else (the
    mount_runs fixture strips /tf_static from the 5 s bag instead of rendering it twice)."""
    bags = {}
    for flag in (True, False):
        bags[flag] = tmp_path / f'{flag}.mcap'
        with BagWriter(bags[flag]) as bag:
            rr.write_bag(bag, 7, 0.15, 'raw', mount_on_tf_static=flag)
    with_tf, without = _bag_messages(bags[True]), _bag_messages(bags[False])
    assert [m for m in with_tf if m[0] != '/tf_static'] == without
    assert len(with_tf) == len(without) + 1 and any(m[0] == '/camera/image_raw' for m in without)


def test_mount_from_tf_static_equals_mount_from_parameters(mount_runs):
    tf, par, _ = mount_runs
    assert tf is not None and par is not None and tf['n'] > 300
    for key in ('position_rmse_cm', 'orientation_rmse_deg'):
        assert tf[key] == pytest.approx(par[key], rel=0.10), key
    # and the figures are those of a working filter (a mount ignored gives ~1 m, ~9 deg)
    assert tf['position_rmse_cm'] < 1.5 and tf['orientation_rmse_deg'] < 0.2
    assert tf['position_rmse_cm'] < tf['camera_only']['position_rmse_cm']


def test_evaluate_scores_markers_camera_only_and_the_corners(mount_runs):
    tf, _, out = mount_runs
    m = evaluate_markers(out)
    assert m is not None
    pose = m['pose']
    # Camera only at capture stamps; the first image is not lost (its camera_info comes just after it).
    assert pose['n'] >= 0.85 * 5.0 * 20 and 0.85 <= pose['coverage'] <= 1.0
    assert pose['position_rmse_cm'] < 1.5 and pose['orientation_rmse_deg'] < 0.3
    assert pose['position_rmse_cm'] > tf['position_rmse_cm']            # the IMU helps
    assert 0.05 < pose['nees_position_median'] < 6.0                    # an honest covariance
    assert abs(m['corner_bias_px']) < 0.05 and m['corner_rmse_px'] < 0.2   # gamma undone
    assert m['corners_markers'] > 100
    assert 'markers' in evaluate_all(out, reference=False)
