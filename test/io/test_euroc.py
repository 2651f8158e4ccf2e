"""EuRoC folder -> bag: a synthetic folder (always) and the shared V1_01 micro excerpt (when present)."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ar_tracking.io.bags import BagReader, stamp_to_ns
from ar_tracking.io.euroc import EurocError, euroc_to_bag
from conftest import SHARED_DATA

MICRO = SHARED_DATA / 'euroc_v1_01_micro'
T0 = 1_403_715_273_262_142_976
CAM_YAML = """%YAML:1.0
sensor_type: camera
T_BS:
  cols: 4
  rows: 4
  data: [0.0, -1.0, 0.0, 0.1,
         1.0, 0.0, 0.0, 0.0,
         0.0, 0.0, 1.0, 0.0,
         0.0, 0.0, 0.0, 1.0]
rate_hz: 20
resolution: [16, 12]
camera_model: pinhole
intrinsics: [20.0, 21.0, 7.5, 5.5]
distortion_model: radial-tangential
distortion_coefficients: [-0.28, 0.07, 0.0002, 0.00002]
"""
IMU_YAML = """%YAML:1.0
T_BS:
  cols: 4
  rows: 4
  data: [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]
rate_hz: 200
gyroscope_noise_density: 1.6968e-04
accelerometer_noise_density: 2.0000e-3
"""


def _folder(root: Path, gt_rows: list[str] | None = None, body_gt: bool = False) -> Path:
    cam = root / 'mav0' / 'cam0'
    (cam / 'data').mkdir(parents=True)
    (cam / 'sensor.yaml').write_text(CAM_YAML)
    lines = ['#timestamp [ns],filename']
    for k in range(3):
        t = T0 + k * 50_000_000
        cv2.imwrite(str(cam / 'data' / f'{t}.png'), np.full((12, 16), 40 * k + 10, np.uint8))
        lines.append(f'{t},{t}.png')
    (cam / 'data.csv').write_text('\n'.join(lines) + '\n')
    imu = root / 'mav0' / 'imu0'
    imu.mkdir()
    (imu / 'sensor.yaml').write_text(IMU_YAML)
    rows = ['#timestamp [ns],w_x,w_y,w_z,a_x,a_y,a_z']
    rows += [f'{T0 + k * 5_000_000},0.01,-0.02,0.03,9.8,0.1,{-0.2 + k * 0.01}' for k in range(25)]
    (imu / 'data.csv').write_text('\n'.join(rows) + '\n')
    if gt_rows is not None:
        target = root / 'mav0' / 'state_groundtruth_estimate0' / 'data.csv' if body_gt else root / 'gt.csv'
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_text('#timestamp, p_x, p_y, p_z, q_w, q_x, q_y, q_z\n' + '\n'.join(gt_rows) + '\n')
    return root


def _gt_rows(R_list, p_list):
    rows = []
    for k, (R, p) in enumerate(zip(R_list, p_list)):
        x, y, z, w = Rotation.from_matrix(R).as_quat()
        rows.append(f'{T0 + k * 50_000_000}.0000000000,{p[0]},{p[1]},{p[2]},{w},{x},{y},{z}')
    return rows


def _read(bag_path):
    with BagReader(bag_path) as bag:
        topics = bag.topics
        out = {t: [bag.deserialize(m) for m in bag.messages([t])] for t in topics}
    return out


def test_synthetic_folder_to_bag(tmp_path):
    R_true = [Rotation.from_euler('z', 10 * k, degrees=True).as_matrix() for k in range(3)]
    p_true = [np.array([1.0 + k, 2.0, 3.0]) for k in range(3)]
    # the file stores R_cam_world (inverted), as ORB-SLAM's V101_GT.txt does
    folder = _folder(tmp_path / 'seq', _gt_rows([R.T for R in R_true], p_true))
    out = euroc_to_bag(folder, tmp_path / 'seq_bag', folder / 'gt.csv', invert_gt_quaternion=True)
    assert out.name == 'seq_bag.mcap' and out.is_file()
    msgs = _read(out)
    assert len(msgs['/camera/image_raw']) == len(msgs['/camera/camera_info']) == 3
    assert len(msgs['/imu/data_raw']) == 25 and len(msgs['/ground_truth/pose']) == 3
    img = msgs['/camera/image_raw'][1]
    assert img.encoding == 'mono8' and (img.width, img.height) == (16, 12)
    assert stamp_to_ns(img.header.stamp) == T0 + 50_000_000 and np.all(img.data == 50)
    info = msgs['/camera/camera_info'][0]
    assert info.distortion_model == 'plumb_bob' and np.allclose(info.d, [-0.28, 0.07, 0.0002, 0.00002, 0.0])
    assert np.allclose(info.k, [20.0, 0, 7.5, 0, 21.0, 5.5, 0, 0, 1])
    imu = msgs['/imu/data_raw'][3]
    assert imu.linear_acceleration.x == pytest.approx(9.8) and imu.angular_velocity.z == pytest.approx(0.03)
    assert imu.angular_velocity_covariance[0] == pytest.approx(1.6968e-04 ** 2 * 200)
    for k, m in enumerate(msgs['/ground_truth/pose']):
        q = m.pose.orientation
        assert np.allclose(Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix(), R_true[k], atol=1e-9)
        assert m.header.frame_id == 'world' and m.pose.position.x == pytest.approx(p_true[k][0])
    tf = msgs['/tf_static'][0].transforms[0]
    assert (tf.header.frame_id, tf.child_frame_id) == ('imu', 'camera_optical')
    assert tf.transform.translation.x == pytest.approx(0.1)
    with pytest.raises(EurocError, match='already exists'):
        euroc_to_bag(folder, out)


def test_body_ground_truth_is_moved_to_the_camera(tmp_path):
    R_wb = Rotation.from_euler('xyz', [5, -10, 30], degrees=True).as_matrix()
    folder = _folder(tmp_path / 'seq', _gt_rows([R_wb] * 3, [np.zeros(3)] * 3), body_gt=True)
    out = euroc_to_bag(folder / 'mav0', tmp_path / 'b.mcap')  # mav0 itself works too
    m = _read(out)['/ground_truth/pose'][0]
    T_bc = np.array([[0, -1, 0, 0.1], [1, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    q = m.pose.orientation
    assert np.allclose(Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix(), R_wb @ T_bc[:3, :3], atol=1e-9)
    assert np.allclose([m.pose.position.x, m.pose.position.y, m.pose.position.z], R_wb @ T_bc[:3, 3])


@pytest.mark.parametrize('damage, message', [
    (lambda f: (f / 'mav0' / 'cam0' / 'data.csv').write_text('#t,f\n123,a.png\nxyz,b.png\n'), r'data.csv:3: bad timestamp'),
    (lambda f: (f / 'mav0' / 'cam0' / 'data' / f'{T0}.png').unlink(), r'1 of 3 listed images are missing'),
    (lambda f: (f / 'mav0' / 'cam0' / 'sensor.yaml').write_text('resolution: [16, 12]\n'), r'needs resolution'),
    (lambda f: (f / 'mav0' / 'imu0' / 'data.csv').write_text(f'{T0},1,2,nan,4,5,6\n'), r'data.csv:1: NaN'),
    (lambda f: (f / 'gt.csv').write_text(f'{T0},0,0,0,2,0,0,0\n'), r'gt.csv:1: quaternion of norm 2.000'),
])
def test_bad_input_is_one_line_error(tmp_path, damage, message):
    folder = _folder(tmp_path / 'seq', _gt_rows([np.eye(3)], [np.zeros(3)]))
    damage(folder)
    with pytest.raises(EurocError, match=message) as info:
        euroc_to_bag(folder, tmp_path / 'x.mcap', folder / 'gt.csv')
    assert '\n' not in str(info.value)
    with pytest.raises(EurocError, match='no such folder'):
        euroc_to_bag(tmp_path / 'absent', tmp_path / 'y.mcap')


def test_euroc_v1_01_micro(tmp_path):
    if not (MICRO / 'mav0' / 'cam0' / 'data.csv').is_file():
        pytest.skip(f'{MICRO} not present')
    out = euroc_to_bag(MICRO, tmp_path / 'v101.mcap', MICRO / 'groundtruth_cam0' / 'V101_GT.txt',
                       invert_gt_quaternion=True)
    with BagReader(out) as bag:
        assert bag.message_count(['/camera/image_raw']) == 95
        assert bag.message_count(['/imu/data_raw']) == 29120
        assert bag.message_count(['/ground_truth/pose']) == 2871
        info = bag.deserialize(next(iter(bag.messages(['/camera/camera_info']))))
        first = bag.deserialize(next(iter(bag.messages(['/camera/image_raw']))))
        tf = bag.deserialize(next(iter(bag.messages(['/tf_static'])))).transforms[0].transform.rotation
        gt, acc = [], []
        end = T0 + 4_750_000_000
        for m in bag.messages(['/ground_truth/pose', '/imu/data_raw']):
            if m.log_time_ns > end:
                break
            msg = bag.deserialize(m)
            if m.topic == '/imu/data_raw':
                a = msg.linear_acceleration
                acc.append([a.x, a.y, a.z])
            else:
                gt.append(msg.pose.orientation)
    assert (info.width, info.height) == (752, 480) and info.k[0] == pytest.approx(458.654)
    png = cv2.imread(str(MICRO / 'mav0' / 'cam0' / 'data' / f'{stamp_to_ns(first.header.stamp)}.png'), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(np.asarray(first.data).reshape(480, 752), png)
    # standing still before take-off: the accelerometer, turned into the world with the
    # (inverted) ground-truth camera orientation and the camera -> IMU extrinsics, points up
    R_imu_cam = Rotation.from_quat([tf.x, tf.y, tf.z, tf.w]).as_matrix()
    R_w_cam = Rotation.from_quat([[q.x, q.y, q.z, q.w] for q in gt]).as_matrix()
    up = np.einsum('nij,j->ni', R_w_cam @ R_imu_cam.T, np.mean(acc, axis=0))
    ang = np.degrees(np.arccos(up[:, 2] / np.linalg.norm(up, axis=1)))
    assert len(gt) >= 70 and ang.max() < 5.0  # 88 deg without the inversion
