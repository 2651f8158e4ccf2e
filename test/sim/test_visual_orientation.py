"""The synthetic visual tracker: relative to the first frame, small noise and drift, lost stretches."""
from __future__ import annotations

import numpy as np
import pytest

from ar_tracking.core.rotations import angle_of, matrix_to_quat_xyzw, rot_z
from ar_tracking.io.bags import BagReader, BagWriter, msg_class, ns_to_stamp
from ar_tracking.sim.visual_orientation import VisualErrorModel, add_visual_orientation, synthesize_visual

R0 = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def camera_info(t_ns: int):
    CI = msg_class('sensor_msgs/msg/CameraInfo')
    Header = msg_class('std_msgs/msg/Header')
    ROI = msg_class('sensor_msgs/msg/RegionOfInterest')
    return CI(header=Header(stamp=ns_to_stamp(int(t_ns)), frame_id='camera_optical'), height=240, width=320,
              distortion_model='', d=np.zeros(0), k=np.zeros(9), r=np.zeros(9), p=np.zeros(12),
              binning_x=0, binning_y=0,
              roi=ROI(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))


def truth(n=3000, rate=100.0):
    t_ns = (np.arange(n) * (1e9 / rate)).astype(np.int64) + 1_000
    R = np.array([rot_z(-0.5 * np.sin(k / rate)) @ R0 for k in range(n)])
    return t_ns, R


def test_relative_to_first_frame_with_small_errors_and_lost_frames():
    t_ns, R = truth()
    cam = (np.arange(900) * 1_000_000_000 // 30).astype(np.int64) + 1_000
    stamps, R_pc = synthesize_visual(t_ns, R, cam, seed=4, model=VisualErrorModel(lost_per_min=6.0))
    assert 0 < len(stamps) < len(cam)  # some frames lost
    assert set(stamps.tolist()) <= set(cam.tolist())
    np.testing.assert_allclose(R_pc[0], np.eye(3))
    idx = np.searchsorted(cam, stamps)
    R_true_rel = R[0].T @ R[np.searchsorted(t_ns, cam[idx])]
    err_deg = np.degrees(angle_of(np.swapaxes(R_true_rel, 1, 2) @ R_pc))
    assert err_deg.max() < 1.0 and err_deg[1:].mean() > 0.01  # noisy, drifting, but small
    again = synthesize_visual(t_ns, R, cam, seed=4, model=VisualErrorModel(lost_per_min=6.0))
    np.testing.assert_array_equal(again[0], stamps)
    np.testing.assert_array_equal(again[1], R_pc)


def test_bag_gets_panorama_orientation_and_keeps_every_topic(tmp_path):
    t_ns, R = truth(300)
    src = tmp_path / 'in.mcap'
    TS = msg_class('geometry_msgs/msg/TransformStamped')
    Header = msg_class('std_msgs/msg/Header')
    Tf = msg_class('geometry_msgs/msg/Transform')
    V3 = msg_class('geometry_msgs/msg/Vector3')
    Q = msg_class('geometry_msgs/msg/Quaternion')
    with BagWriter(src) as bag:
        for k, (t, Rk) in enumerate(zip(t_ns, R, strict=True)):
            q = matrix_to_quat_xyzw(Rk)
            bag.write('/ground_truth/orientation', int(t), TS(
                header=Header(stamp=ns_to_stamp(int(t)), frame_id='enu'), child_frame_id='camera_optical',
                transform=Tf(translation=V3(x=0.0, y=0.0, z=0.0), rotation=Q(x=q[0], y=q[1], z=q[2], w=q[3]))))
            if k % 3 == 0:
                bag.write('/camera/camera_info', int(t), camera_info(int(t)))
    (tmp_path / 'in.params.yaml').write_text('imu_magnetometer:\n  ros__parameters: {}\n')
    out = add_visual_orientation(src, tmp_path / 'out.mcap', seed=1)
    with BagReader(out) as bag:
        assert set(bag.topics) == {'/ground_truth/orientation', '/camera/camera_info', '/panorama/orientation'}
        vis = bag.read_all('/panorama/orientation')
        assert 50 < len(vis) <= 100
        assert vis[0][1].header.frame_id == 'panorama' and vis[0][1].child_frame_id == 'camera_optical'
        assert bag.message_count(['/ground_truth/orientation']) == 300
    assert (tmp_path / 'out.params.yaml').exists()


def test_bag_without_truth_is_refused(tmp_path):
    from ar_tracking.io.bags import BagError

    src = tmp_path / 'empty.mcap'
    with BagWriter(src) as bag:
        bag.write('/camera/camera_info', 1000, camera_info(1000))
    with pytest.raises(BagError):
        add_visual_orientation(src, tmp_path / 'out.mcap')
