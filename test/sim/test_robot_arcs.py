"""robot_arcs scenario (Caarls 2009 Fig. 9a): motion, sensors, delayed camera, determinism."""
from __future__ import annotations

import math

import numpy as np
import yaml

from ar_tracking.io.bags import BagReader, stamp_to_ns
from ar_tracking.sim import robot_arcs as ra
from ar_tracking.sim.bagmaker import SCENARIOS, START_NS, make_bag


def test_half_circles_speeds_and_imu_physics():
    sched = ra.ArcSchedule.make(60.0)
    t = np.arange(0, 60.0, 0.001)
    tr = ra.truth_at(sched, t)
    r = np.linalg.norm(tr.position[:, :2], axis=1)
    assert np.allclose(r, ra.RADIUS_M)
    assert np.all(tr.position[:, 1] >= -1e-9)
    assert abs(tr.speed_m_s.max() - 2.24) < 1e-6
    for v in ra.ARC_SPEEDS_M_S:  # each half circle cruises at its speed for a while
        assert np.isclose(tr.speed_m_s, v, atol=1e-9).sum() > 200
    # velocity and acceleration are the derivatives of position
    v_num = np.gradient(tr.position, t, axis=0)
    assert np.abs(v_num - tr.velocity)[5:-5].max() < 0.01
    gyro, accel = ra.simulate_imu(tr, ra.make_imu_errors(1), 1)
    at_rest = tr.speed_m_s == 0
    assert abs(np.linalg.norm(accel[at_rest], axis=1).mean() - 9.80665) < 0.05


def test_bag_layout_delay_and_determinism(tmp_path):
    assert 'robot_arcs' in SCENARIOS
    a = make_bag('robot_arcs', tmp_path / 'a.mcap', seed=2, duration_s=1.5)
    b = make_bag('robot_arcs', tmp_path / 'b.mcap', seed=2, duration_s=1.5)
    assert a.read_bytes() == b.read_bytes()
    side = yaml.safe_load((tmp_path / 'a.params.yaml').read_text())
    assert 'marker_map' in side['marker_tracker']['ros__parameters']
    assert side['visual_inertial_filter']['ros__parameters']['imu_to_camera_xyzw'] == [1.0, 0.0, 0.0, 0.0]
    assert (tmp_path / 'a.markers.yaml').is_file()
    with BagReader(a) as bag:
        topics = bag.topics
        for t in ('/camera/image_raw', '/camera/camera_info', '/imu/data_raw', '/ground_truth/pose',
                  '/ground_truth/orientation', '/tf_static'):
            assert t in topics
        imgs = [(m.log_time_ns, bag.deserialize(m)) for m in bag.messages(['/camera/image_raw'])]
        imus = [bag.deserialize(m) for m in bag.messages(['/imu/data_raw'])]
    assert len(imgs) == math.ceil(1.5 * 15) and len(imus) == 150
    for log, msg in imgs:
        assert log - stamp_to_ns(msg.header.stamp) == ra.PROCESSING_DELAY_NS
        assert msg.encoding == 'mono8' and msg.width == 640
    assert stamp_to_ns(imgs[0][1].header.stamp) == START_NS
