"""The hybrid filter helpers (Langlotz 2011 sec. 5): so(3) maps, pairing by stamp, gyro backup."""
from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from ar_tracking.core.hybrid_orientation import GyroBackup, RotationBuffer, StreamLag
from ar_tracking.core.rotations import heading_tilt_error_deg, rot_z, so3_exp, so3_log

R0_ENU_CAM = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # level, looking north
R_IMU_CAM = np.diag([1.0, -1.0, -1.0])


def camera(heading_rad: float, pitch_rad: float = 0.0) -> np.ndarray:
    """R_enu_cam of a camera turned clockwise (seen from above) by heading and tilted up."""
    tilt = Rotation.from_rotvec([pitch_rad, 0.0, 0.0]).as_matrix()  # about camera x (right)
    return rot_z(-heading_rad) @ R0_ENU_CAM @ tilt.T


def heading_error_deg(R_est: np.ndarray, R_true: np.ndarray) -> float:
    return float(heading_tilt_error_deg(R_est, R_true)[1])


def test_exp_log_round_trip_and_match_scipy():
    rng = np.random.default_rng(0)
    vectors = list(rng.normal(0, 1, (50, 3))) + [np.zeros(3), np.array([1e-9, 0, 0]),
                                                  np.array([0.0, math.pi - 1e-6, 0.0])]
    for v in vectors:
        if np.linalg.norm(v) > math.pi:
            v = v / np.linalg.norm(v) * (np.linalg.norm(v) % math.pi)
        R = so3_exp(v)
        np.testing.assert_allclose(R, Rotation.from_rotvec(v).as_matrix(), atol=1e-9)
        np.testing.assert_allclose(so3_exp(so3_log(R)), R, atol=1e-8)


def sweep(n: int, rate_hz: float = 100.0, seed: int = 0):
    """A camera sweeping back and forth over +-120 deg with small pitch, plus R_pano_enu."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate_hz
    heading = np.radians(120.0) * np.sin(2 * math.pi * t / 12.0) + 1.0
    pitch = np.radians(10.0) * np.sin(2 * math.pi * t / 7.0)
    R_true = np.array([camera(h, p) for h, p in zip(heading, pitch)])
    R_pano_enu = R_true[0].T
    R_pano_cam = np.array([R_pano_enu @ R for R in R_true])
    return t, R_true, R_pano_cam, rng


def run_filter(f, t, R_pano_cam, R_sensor, sigma):
    cov = np.diag([sigma**2, sigma**2, sigma**2])
    results = [f.update(int(tk * 1e9) + 1, V, S, cov) for tk, V, S in zip(t, R_pano_cam, R_sensor)]
    return results


def test_rotation_buffer_interpolates_by_stamp_and_not_across_gaps():
    buf = RotationBuffer(max_gap_ns=100)
    buf.add(0, np.eye(3))
    buf.add(100, rot_z(0.2))
    buf.add(50, rot_z(5.0))  # older than the newest: ignored
    np.testing.assert_allclose(buf.at(25), rot_z(0.05), atol=1e-12)
    buf.add(500, rot_z(0.4))
    assert buf.at(300) is None  # across a gap longer than max_gap_ns
    assert buf.at(600) is None and buf.at(-1) is None


def test_gyro_backup_learns_the_bias_from_vision_and_integrates():
    bias = np.array([0.01, -0.015, 0.012])  # rad/s, imu frame
    w_cam = np.array([0.0, 0.5, 0.0])  # turning about the camera's y axis
    gb = GyroBackup(R_IMU_CAM)
    R = np.eye(3)
    for k in range(1001):  # 10 s at 100 Hz, visual at every third sample
        t = k * 10_000_000 + 1
        gb.add_gyro(t, R_IMU_CAM @ w_cam + bias + np.random.default_rng(k).normal(0, 0.002, 3))
        R = so3_exp(w_cam * 0.01 * k)
        if k % 3 == 0:
            gb.add_visual(t, R)
    np.testing.assert_allclose(gb.bias, bias, atol=0.003)
    gb.anchor(1001 * 10_000_000 + 1, R, np.eye(3) * 1e-6)
    for k in range(1001, 1101):  # 1 s of backup
        gb.add_gyro(k * 10_000_000 + 1, R_IMU_CAM @ w_cam + bias)
    R_true = so3_exp(w_cam * 0.01 * 1100)
    err_deg = np.degrees(np.linalg.norm(so3_log(gb.R_enu_cam.T @ R_true)))
    assert err_deg < 0.3
    assert gb.cov[0, 0] > 1e-6  # the covariance grew


def _backup_through_a_loss(tilt_tau_s: float) -> tuple[float, float, float]:
    """20 s of gyro backup (no vision after the anchor) while the user sweeps +-60 deg with a
    swaying pitch; the gyro has a 0.5 % scale error and a bias the vision did not remove (it
    drifted since), the accelerometer the hand's acceleration as noise. Returns the heading
    and tilt RMS errors over the last 10 s (deg) and the tilt's final 1-sigma (deg) as stated."""
    from ar_tracking.core.hybrid_orientation import GyroBackupConfig

    rng = np.random.default_rng(3)
    t = np.arange(0.0, 20.0, 0.01)
    heading = np.radians(60.0) * np.sin(2 * math.pi * t / 10.0)
    pitch = np.radians(15.0) * np.sin(2 * math.pi * t / 4.0)
    R_true = np.array([camera(h, p) for h, p in zip(heading, pitch)])
    scale = np.diag([1.005, 0.995, 1.005])
    bias = np.array([0.004, -0.003, 0.003])  # rad/s
    gb = GyroBackup(R_IMU_CAM, GyroBackupConfig(tilt_tau_s=tilt_tau_s))
    gb.add_gyro(0, np.zeros(3))
    gb.anchor(0, R_true[0], np.eye(3) * 1e-6)
    errors = []
    for k in range(1, len(t)):
        w_imu = R_IMU_CAM @ so3_log(R_true[k - 1].T @ R_true[k]) / 0.01
        accel = R_IMU_CAM @ R_true[k].T @ np.array([0.0, 0.0, 9.81]) + rng.normal(0.0, 0.5, 3)
        gb.add_gyro(k * 10_000_000, scale @ w_imu + bias, accel)
        if k >= 1000 and k % 10 == 0:
            errors.append(heading_tilt_error_deg(gb.R_enu_cam, R_true[k])[1:])
    heading_err, tilt_err = np.sqrt(np.mean(np.square(errors), axis=0))
    return float(heading_err), float(tilt_err), math.degrees(math.sqrt(gb.cov[0, 0]))


def test_the_accelerometer_holds_the_backups_tilt_through_a_long_loss():
    """A bias the vision no longer removes (and the gyro's scale error) tilts a gyro-only
    backup by degrees over a long loss; pulled by the accelerometer the tilt stays within a
    few tenths, the heading (the gyro's) is not made worse, and the stated tilt sigma stays
    bounded instead of growing with the square of the time lost."""
    heading_gyro, tilt_gyro, sigma_gyro = _backup_through_a_loss(0.0)
    heading_acc, tilt_acc, sigma_acc = _backup_through_a_loss(3.0)
    assert tilt_gyro > 2.0
    assert tilt_acc < 0.25 * tilt_gyro and tilt_acc < 1.0  # what is left: the bias times tau
    assert heading_acc < heading_gyro + 0.1
    assert sigma_acc < 0.6 * sigma_gyro


def test_stream_lag_is_the_median_lag_of_recent_arrivals_never_below_zero():
    lag = StreamLag(window=5)
    assert not lag.known and lag.ns == 0
    for lead, t in ((1300, 1000), (1600, 1310), (1900, 1600), (9000, 1900), (2200, 1910)):
        lag.add(lead, t)  # one slow frame (7100) does not move the median
    assert lag.known and lag.ns == 300
    lag.clear()
    lag.add(1000, 1200)  # the trailing stream ahead: no lag
    assert lag.known and lag.ns == 0


def test_a_late_frame_anchors_the_backup_through_the_gyro_since_its_stamp():
    """The gyro is 0.3 s ahead of a frame (camera latency) while the phone turns with a changing
    rate: the anchor is carried to the gyro's time by the gyro's own rotation since the frame,
    not by the last rate held for 0.3 s."""
    gb = GyroBackup(R_IMU_CAM)

    def heading(t_s: float) -> float:
        return 0.6 * math.sin(2.0 * t_s)  # rate 1.2 cos(2t) rad/s

    for k in range(131):  # 1.3 s at 100 Hz
        t_s = k * 0.01
        w_cam = np.array([0.0, 1.2 * math.cos(2.0 * t_s), 0.0])  # about camera y: heading, clockwise
        gb.add_gyro(k * 10_000_000, R_IMU_CAM @ w_cam)
    gb.anchor(1_000_000_000, camera(heading(1.0)), np.eye(3) * 1e-6)  # the frame of t = 1 s
    assert heading_error_deg(gb.R_enu_cam, camera(heading(1.3))) < 0.05
