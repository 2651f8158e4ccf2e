"""robot_arcs scenario (Caarls 2009 Fig. 9a): motion, sensors, delayed camera, determinism; the
hard profile's real-camera effects."""
from __future__ import annotations

import math

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from ar_tracking.io.bags import BagReader, stamp_to_ns
from ar_tracking.sim import robot_arcs as ra
from ar_tracking.sim import robot_arcs_real as rr
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
    a = make_bag('robot_arcs', tmp_path / 'a.mcap', seed=2, duration_s=1.5, profile='kind')
    b = make_bag('robot_arcs', tmp_path / 'b.mcap', seed=2, duration_s=1.5, profile='kind')
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


def test_hard_profile_motion_pans_and_lever_arm_physics():
    sched = ra.ArcSchedule.make(12.0)
    t = np.arange(0, 12.0, 0.001)
    tr = rr.truth_at(sched, t)
    rate = np.abs(tr.omega_world[:, 2])
    assert 150 < np.degrees(rate.max()) < 175                     # quick pans ~155 deg/s (+ the arc's own turn)
    # The IMU point's acceleration is the second derivative of its position (lever arm included).
    p_imu = tr.cam.position + np.einsum('nij,j->ni', tr.cam.R_enu_cam, -rr.R_IMU_CAM.T @ rr.T_IMU_CAM)
    a_num = np.gradient(np.gradient(p_imu, t, axis=0), t, axis=0)
    err = np.linalg.norm(a_num - tr.imu_accel, axis=1)[10:-10]
    assert np.percentile(err, 99.5) < 0.05        # (a pan starts with a step in angular acceleration)
    assert np.abs(tr.imu_accel - tr.cam.accel).max() > 1.0       # the pans swing the IMU around
    _, accel = rr.simulate_imu(tr, ra.make_imu_errors(1), 1)
    still = (tr.cam.speed_m_s == 0) & (rate == 0)
    assert abs(np.linalg.norm(accel[still], axis=1).mean() - 9.80665) < 0.1


def test_hard_profile_bag_distortion_gamma_mount_and_truth_corners(tmp_path):
    a = make_bag('robot_arcs', tmp_path / 'h.mcap', seed=3, duration_s=1.0)
    side = yaml.safe_load((tmp_path / 'h.params.yaml').read_text())
    vi = side['visual_inertial_filter']['ros__parameters']
    assert 'imu_to_camera_xyzw' not in vi and 'camera_in_imu_m' not in vi   # the mount is on /tf_static only
    assert side['marker_tracker']['ros__parameters']['marker_print_contrast'] == ra.WHITE / ra.BLACK
    with BagReader(a) as bag:
        tf = next(bag.deserialize(m) for m in bag.messages(['/tf_static'])).transforms[0]
        infos = [(m.log_time_ns, bag.deserialize(m)) for m in bag.messages(['/camera/camera_info'])]
        imgs = [(m.log_time_ns, bag.deserialize(m)) for m in bag.messages(['/camera/image_raw'])]
        corners = [bag.deserialize(m) for m in bag.messages([rr.TOPIC_CORNERS])]
    q = tf.transform.rotation
    assert np.allclose(Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix(), rr.R_IMU_CAM, atol=1e-9)
    assert np.allclose([tf.transform.translation.x, tf.transform.translation.y, tf.transform.translation.z], rr.T_IMU_CAM)
    assert len(imgs) == rr.CAMERA_RATE_HZ and len(infos) == len(imgs) and len(corners) == len(imgs)
    assert np.allclose(infos[0][1].d, rr.DISTORTION)
    for (li, info), (lm, img) in zip(infos, imgs):
        assert stamp_to_ns(info.header.stamp) == stamp_to_ns(img.header.stamp)
        assert li - lm == rr.CAMERA_INFO_LAG_NS                         # camera_info comes just after its image
        assert lm - stamp_to_ns(img.header.stamp) == ra.PROCESSING_DELAY_NS
    assert sorted(m.id for m in corners[0].markers) == [0, 1, 2, 3]
    assert any(m.ns == 'occluded' for c in corners for m in c.markers)   # the pole covers a marker
    # The white quiet zone is brighter than a linear rendering gives: the display gamma.
    img = np.frombuffer(bytes(imgs[0][1].data), np.uint8).reshape(480, 640)
    assert img.max() > 235
