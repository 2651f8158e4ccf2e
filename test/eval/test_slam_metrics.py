"""slam measures (evo ATE/RPE after Sim(3) alignment, tracked ratio, map sizes) and the figure."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ar_tracking.eval.slam_figures import slam_figure
from ar_tracking.eval.slam_metrics import evaluate_slam, slam_metrics, slam_metrics_from_arrays
from ar_tracking.io.bags import BagWriter, msg_class, ns_to_stamp
from ar_tracking.sim.handheld_desk import trajectory

T0 = 1_700_000_000_000_000_000
SIGMA = 0.002  # m, per axis, in truth units


def _truth(seconds: float = 20.0):
    t_ns = np.arange(0, int(seconds * 1e9), 10_000_000, dtype=np.int64)
    R, p = trajectory(1, seconds, t_ns * 1e-9)
    return T0 + t_ns, p, Rotation.from_matrix(R).as_quat()


def _estimate(t_gt, p_gt, q_gt, keep=None, seed=0):
    """Camera frames at 20 Hz; the map frame is the world scaled by 0.3, turned, shifted, noisy."""
    rng = np.random.default_rng(seed)
    idx = np.arange(0, len(t_gt), 5)
    if keep is not None:
        idx = idx[keep]
    R_mw = Rotation.from_euler('xyz', [100, -20, 35], degrees=True)
    p = 0.3 * R_mw.apply(p_gt[idx] + rng.normal(0, SIGMA, (len(idx), 3))) + [1.0, -2.0, 0.5]
    q = (R_mw * Rotation.from_quat(q_gt[idx])).as_quat()
    return t_gt[idx], p, q


def test_scaled_rotated_shifted_estimate_has_ate_at_noise_level():
    t_gt, p_gt, q_gt = _truth()
    t_e, p_e, q_e = _estimate(t_gt, p_gt, q_gt)
    m = slam_metrics_from_arrays(t_e, p_e, q_e, t_gt, p_gt, q_gt, n_frames=len(t_e))
    noise_rms = SIGMA * np.sqrt(3)
    assert 0.6 * noise_rms < m['ate_rmse_m'] < 1.3 * noise_rms
    assert m['scale'] == pytest.approx(1 / 0.3, rel=0.01)
    assert m['rpe_delta_frames'] == 20 and m['rpe_rmse'] < 3 * noise_rms
    assert m['ate_rot_rmse_deg'] < 0.5  # the alignment rotation comes from the noisy positions
    assert m['tracked_ratio'] == 1.0 and m['n_associated'] == len(t_e) == 400
    path = np.sum(np.linalg.norm(np.diff(p_gt[(t_gt >= t_e[0]) & (t_gt <= t_e[-1])], axis=0), axis=1))
    assert m['path_length_m'] == pytest.approx(path, rel=1e-6)
    assert m['ate_ratio'] == pytest.approx(m['ate_rmse_m'] / m['path_length_m'], rel=1e-3)


def test_wrong_estimate_has_large_ate():
    t_gt, p_gt, q_gt = _truth()
    t_e, _, q_e = _estimate(t_gt, p_gt, q_gt)
    R_other, p_other = trajectory(6, 20.0, (t_e - T0) * 1e-9)
    p_wrong = p_other[::-1] * 0.3  # another motion, backwards
    m = slam_metrics_from_arrays(t_e, p_wrong, q_e, t_gt, p_gt, q_gt, n_frames=len(t_e))
    assert m['ate_rmse_m'] > 0.03 and m['ate_ratio'] > 0.005


def test_tracked_ratio_counts_frames_with_a_pose_and_ignores_bad_ones():
    t_gt, p_gt, q_gt = _truth(10.0)
    keep = np.r_[np.arange(0, 60), np.arange(110, 200)]  # lost for 2.5 s
    t_e, p_e, q_e = _estimate(t_gt, p_gt, q_gt, keep)
    p_e[5] = np.nan  # a broken message is not a tracked frame
    m = slam_metrics_from_arrays(t_e, p_e, q_e, t_gt, p_gt, q_gt, n_frames=200)
    assert m['tracked_frames'] == 149 and m['tracked_ratio'] == pytest.approx(149 / 200)
    assert m['ate_rmse_m'] < 0.01
    none = slam_metrics_from_arrays([], np.zeros((0, 3)), np.zeros((0, 4)), t_gt, p_gt, q_gt, n_frames=200)
    assert none['tracked_ratio'] == 0.0 and none['ate_rmse_m'] is None and none['rpe_rmse'] is None


def _header(ns, frame):
    return msg_class('std_msgs/msg/Header')(stamp=ns_to_stamp(int(ns)), frame_id=frame)


def _pose_stamped(ns, frame, p, q):
    G = msg_class('geometry_msgs/msg/Point')
    Q = msg_class('geometry_msgs/msg/Quaternion')
    return msg_class('geometry_msgs/msg/PoseStamped')(header=_header(ns, frame), pose=msg_class('geometry_msgs/msg/Pose')(
        position=G(x=float(p[0]), y=float(p[1]), z=float(p[2])),
        orientation=Q(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))))


def _write_bag(path, with_slam=True):
    t_gt, p_gt, q_gt = _truth(6.0)
    keep = np.arange(10, 120)
    t_e, p_e, q_e = _estimate(t_gt, p_gt, q_gt, keep)
    Image = msg_class('sensor_msgs/msg/Image')
    PointCloud2 = msg_class('sensor_msgs/msg/PointCloud2')
    PointField = msg_class('sensor_msgs/msg/PointField')
    PoseArray = msg_class('geometry_msgs/msg/PoseArray')
    events = [(int(t), 0, i) for i, t in enumerate(t_gt)] + [(int(t), 1, i) for i, t in enumerate(t_gt[::5])]
    if with_slam:
        events += [(int(t), 2, i) for i, t in enumerate(t_e)] + [(int(t_e[20]), 3, 3), (int(t_e[90]), 3, 7)]
    with BagWriter(path, storage='mcap') as bag:
        for ns, kind, i in sorted(events):
            if kind == 0:
                bag.write('/ground_truth/pose', ns, _pose_stamped(ns, 'world', p_gt[i], q_gt[i]))
            elif kind == 1:
                bag.write('/camera/image_raw', ns, Image(header=_header(ns, 'camera_optical'), height=4, width=4,
                                                         encoding='mono8', is_bigendian=0, step=4,
                                                         data=np.zeros(16, np.uint8)))
            elif kind == 2:
                bag.write('/slam/pose', ns, _pose_stamped(ns, 'slam_map', p_e[i], q_e[i]))
            else:
                n_pts = 10 * i
                bag.write('/slam/keyframes', ns, PoseArray(header=_header(ns, 'slam_map'), poses=[
                    _pose_stamped(ns, 'slam_map', p_e[0], q_e[0]).pose] * i))
                bag.write('/slam/map_points', ns, PointCloud2(
                    header=_header(ns, 'slam_map'), height=1, width=n_pts,
                    fields=[PointField(name=c, offset=4 * k, datatype=7, count=1) for k, c in enumerate('xyz')],
                    is_bigendian=False, point_step=12, row_step=12 * n_pts,
                    data=np.zeros(12 * n_pts, np.uint8), is_dense=True))
    return len(keep), len(t_gt[::5])


def test_bag_metrics_and_figure(tmp_path):
    bag = tmp_path / 'out.mcap'
    n_tracked, n_frames = _write_bag(bag)
    m = slam_metrics(bag)
    assert m['frames'] == n_frames == 120 and m['tracked_frames'] == n_tracked
    assert m['tracked_ratio'] == pytest.approx(n_tracked / n_frames)
    assert m['keyframes'] == 7 and m['points'] == 70
    assert m['ate_rmse_m'] < 0.01 and m['path_length_m'] > 0.1
    assert evaluate_slam(bag) == m
    png = slam_figure(bag, tmp_path / 'fig.png')
    assert png is not None and png.stat().st_size > 10_000
    t_gt, p_gt, q_gt = _truth(6.0)
    t_e, p_e, q_e = _estimate(t_gt, p_gt, q_gt)
    arrays = dict(stamps_ns_est=t_e, p_est=p_e, quat_xyzw_est=q_e, stamps_ns_gt=t_gt, p_gt=p_gt,
                  quat_xyzw_gt=q_gt, n_frames=len(t_e))
    assert slam_figure(arrays, tmp_path / 'arr.png').is_file()


def test_bag_without_slam_output(tmp_path):
    bag = tmp_path / 'plain.mcap'
    _write_bag(bag, with_slam=False)
    assert evaluate_slam(bag) is None
    m = slam_metrics(bag)
    assert m['frames'] == 120 and m['tracked_ratio'] == 0.0 and m['ate_rmse_m'] is None
    assert slam_figure(bag, tmp_path / 'none.png') is None
