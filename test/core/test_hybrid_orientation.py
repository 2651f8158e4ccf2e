"""The hybrid filter core (Langlotz 2011 sec. 5): so(3) maps, eq. 2/6, gates, weighting, backup."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ar_tracking.core.hybrid_orientation import (
    GyroBackup,
    HybridFilterParams,
    PanoramaWorldFilter,
    RotationBuffer,
)
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


def test_measurement_is_the_left_error_with_identity_jacobian():
    """Eq. 5-6: if R_PN = exp(m) R_hat, the measurement log(R_DP^-1 R_DN R_hat^-1) is m."""
    rng = np.random.default_rng(1)
    R_hat = so3_exp(rng.normal(0, 1, 3))
    for _ in range(10):
        m = rng.normal(0, 0.01, 3)
        R_pe_true = so3_exp(m) @ R_hat
        R_pano_cam = so3_exp(rng.normal(0, 1, 3))
        R_enu_cam = R_pe_true.T @ R_pano_cam  # eq. 1
        z = so3_log((R_pano_cam @ R_enu_cam.T) @ R_hat.T)
        np.testing.assert_allclose(z, m, atol=1e-12)


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


def test_filter_converges_to_true_panorama_frame_from_noisy_compass():
    t, R_true, R_pano_cam, rng = sweep(3000)
    noise = rng.normal(0, 0.03, (len(t), 3))
    R_sensor = np.array([so3_exp(e) @ R for e, R in zip(noise, R_true)])
    f = PanoramaWorldFilter()
    run_filter(f, t, R_pano_cam, R_sensor, 0.03)
    R_global = f.global_orientation(R_pano_cam[-1])
    assert abs(heading_error_deg(R_global, R_true[-1])) < 0.3
    assert heading_tilt_error_deg(R_global, R_true[-1])[0] < 0.5
    # The covariance shrank from the seed's and stays symmetric positive definite.
    assert f.heading_sigma_rad() < 0.01
    assert np.all(np.linalg.eigvalsh(f.P) > 0)


def disturbed_run(params: HybridFilterParams, seed: int = 2) -> float:
    """Heading error (deg) of R_PN after a 6-deg compass turn lasting 4 s of a 30 s sweep."""
    t, R_true, R_pano_cam, rng = sweep(3000, seed=seed)
    defl = np.radians(6.0) * np.clip(np.minimum(t - 15.0, 19.0 - t) / 0.5, 0, 1)
    noise = rng.normal(0, 0.01, (len(t), 3))
    R_sensor = np.array([rot_z(d) @ so3_exp(e) @ R for d, e, R in zip(defl, noise, R_true)])
    f = PanoramaWorldFilter(params)
    cov = np.eye(3) * 0.02**2
    worst = 0.0
    for k, (tk, V, S) in enumerate(zip(t, R_pano_cam, R_sensor)):
        f.update(int(tk * 1e9) + 1, V, S, cov)
        if 1500 <= k <= 2200:  # during the disturbance and just after
            worst = max(worst, abs(heading_error_deg(f.global_orientation(V), R_true[k])))
    return worst


def test_heading_gate_rejects_a_turned_field_that_keeps_magnitude_and_dip():
    gated = disturbed_run(HybridFilterParams())
    ungated = disturbed_run(HybridFilterParams(gate_chi2=0.0, heading_gate_rad=0.0))
    assert gated < 0.6, gated
    assert ungated > 2.0 * gated and ungated > 1.0, (gated, ungated)


def test_sensor_reporting_a_disturbed_field_is_rejected():
    f = PanoramaWorldFilter()
    V = np.eye(3)
    f.update(1, V, camera(0.0), np.eye(3) * 1e-4)
    R_before = f.R_hat.copy()
    big = np.diag([1e-4, 1e-4, 0.3**2])  # heading sigma 0.3 rad > max_sensor_heading_sigma_rad
    r = f.update(10_000_001, V, rot_z(0.2) @ camera(0.0), big)
    assert not r.accepted and 'disturbed' in r.reason
    np.testing.assert_allclose(f.R_hat, R_before)


def test_direction_weighting_limits_the_pull_of_a_long_stay():
    """A compass bias that exists in one direction only: staying there 60 s pulls less."""
    rng = np.random.default_rng(3)
    n_sweep, n_stay = 2000, 6000
    t = np.arange(n_sweep + n_stay) / 100.0
    heading = np.concatenate([np.linspace(0, 2 * math.pi, n_sweep, endpoint=False), np.full(n_stay, 0.3)])
    R_true = np.array([camera(h) for h in heading])
    bias = np.where(np.abs((heading - 0.3 + math.pi) % (2 * math.pi) - math.pi) < 0.2, np.radians(3.0), 0.0)
    noise = rng.normal(0, 0.01, (len(t), 3))
    R_sensor = np.array([rot_z(b) @ so3_exp(e) @ R for b, e, R in zip(bias, noise, R_true)])
    R_pano_cam = np.array([R_true[0].T @ R for R in R_true])
    errors = {}
    for bins in (12, 0):
        params = HybridFilterParams(direction_bins=bins, heading_gate_rad=0.0, gate_chi2=0.0, direction_ref_count=20.0)
        f = PanoramaWorldFilter(params)
        run_filter(f, t, R_pano_cam, R_sensor, 0.02)
        errors[bins] = abs(heading_error_deg(f.global_orientation(R_pano_cam[-1]), R_true[-1]))
    assert errors[12] < 0.7 * errors[0], errors


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


def test_reset_gives_a_clean_filter():
    f = PanoramaWorldFilter()
    f.update(1, np.eye(3), camera(0.1), None)
    assert f.initialized
    f.reset()
    assert not f.initialized and f.updates == 0 and f.t_ns is None
