"""Error-state filters and roll-back (Caarls 2009 Fig. 7-8) on seeded synthetic data."""
from __future__ import annotations

import numpy as np

from ar_tracking.core.vio.eskf import (FilterNoise, OrientationState, PositionState, matrix_to_quat,
                                       predict_orientation, predict_position, quat_exp, quat_log,
                                       quat_mul, quat_to_matrix, update_orientation)
from ar_tracking.core.vio.rollback import FusionConfig, PoseMeasurement, RollbackFusion, Verdict
from ar_tracking.sim import robot_arcs as ra

T0 = 1_700_000_000_000_000_000


def test_quaternion_helpers_round_trip():
    rng = np.random.default_rng(0)
    for _ in range(20):
        v = rng.normal(size=3)
        q = quat_exp(v)
        assert np.allclose(np.linalg.norm(q), 1)
        R = quat_to_matrix(q)
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-12)
        q2 = matrix_to_quat(R)
        assert np.allclose(quat_to_matrix(q2), R, atol=1e-12)
        if np.linalg.norm(v) < np.pi:
            assert np.allclose(quat_log(q), v, atol=1e-9)


def test_orientation_covariance_propagation_matches_numeric_jacobian():
    """Phi of Fig. 7 (error in the body frame) against finite differences of the process model."""
    rng = np.random.default_rng(1)
    q0 = quat_exp(rng.normal(size=3))
    b0 = np.array([0.01, -0.02, 0.005])
    gyro = np.array([0.5, -0.3, 1.2])
    dt = 0.01

    def f(x):
        s = OrientationState(quat_mul(q0, quat_exp(x[:3])), b0 + x[3:], np.zeros((6, 6)))
        predict_orientation(s, gyro, dt, FilterNoise())
        return s

    nominal = f(np.zeros(6))
    Phi = np.zeros((6, 6))
    for i in range(6):
        e = np.zeros(6)
        e[i] = 1e-6
        s = f(e)
        Phi[:3, i] = quat_log(quat_mul(quat_conj := np.array([nominal.quat_wxyz[0], *-nominal.quat_wxyz[1:]]), s.quat_wxyz)) / 1e-6
        Phi[3:, i] = (s.gyro_bias - nominal.gyro_bias) / 1e-6
    P0 = np.diag([1e-4, 2e-4, 3e-4, 1e-6, 2e-6, 3e-6])
    s = OrientationState(q0, b0, P0.copy())
    noiseless = FilterNoise(gyro_noise_rad_s=1e-12, angular_rate_change_rad_s=0, gyro_bias_walk_rad_s=0)
    predict_orientation(s, gyro, dt, noiseless)
    expected = Phi @ P0 @ Phi.T
    assert np.abs(s.P - expected).max() < 1e-3 * np.abs(expected).max()
    del quat_conj


def test_position_prediction_is_exact_for_constant_acceleration():
    s = PositionState(np.zeros(3), np.array([1.0, 0, 0]), np.zeros(3), np.eye(9) * 1e-4)
    R = np.eye(3)
    a = np.array([0.5, -0.2, 0.0])
    f = a + np.array([0, 0, 9.80665])
    for _ in range(100):
        predict_position(s, R, f, 0.01, FilterNoise())
    assert np.allclose(s.v, [1.5, -0.2, 0.0], atol=1e-12)
    assert np.allclose(s.p, [1.0 + 0.25, -0.1, 0.0], atol=1e-12)
    assert np.allclose(s.P, s.P.T) and np.all(np.linalg.eigvalsh(s.P) > 0)


def test_orientation_update_transfers_error_and_gates():
    s = OrientationState(np.array([1.0, 0, 0, 0]), np.zeros(3), np.diag([1e-2] * 3 + [1e-4] * 3))
    meas = quat_exp(np.array([0.05, 0, 0]))
    r = update_orientation(s, meas, np.eye(3) * 1e-2)
    assert r.accepted
    assert np.isclose(quat_log(s.quat_wxyz)[0], 0.025, atol=1e-3)  # half way for equal variances
    s2 = OrientationState(np.array([1.0, 0, 0, 0]), np.zeros(3), np.eye(6) * 1e-6)
    r2 = update_orientation(s2, quat_exp(np.array([0.5, 0, 0])), np.eye(3) * 1e-6)
    assert not r2.accepted and np.allclose(s2.quat_wxyz, [1, 0, 0, 0])


def _arcs(duration_s: float, seed: int = 3):
    sched = ra.ArcSchedule.make(duration_s)
    t = T0 + np.arange(0, int(duration_s * 1e9), 10_000_000, dtype=np.int64)
    truth = ra.truth_at(sched, (t - T0) * 1e-9)
    gyro, accel = ra.simulate_imu(truth, ra.make_imu_errors(seed), seed)
    rng = np.random.default_rng(seed)
    cams = []
    for k in range(0, len(t), 7):  # ~14 Hz camera
        p = truth.position[k] + rng.normal(0, 0.002, 3)
        cams.append((int(t[k]), truth.R_enu_cam[k], p))
    return t, truth, gyro, accel, cams


def _run(t, gyro, accel, cams, delay_ns, rollback=True):
    f = RollbackFusion(FusionConfig(R_imu_cam=ra.R_IMU_CAM, rollback=rollback))
    arrivals = sorted((c[0] + delay_ns, c) for c in cams)
    ai, out = 0, []
    for i, ti in enumerate(t):
        while ai < len(arrivals) and arrivals[ai][0] <= ti:
            tc, R, p = arrivals[ai][1]
            f.add_pose(PoseMeasurement(tc, R, p))
            ai += 1
        f.add_imu(int(ti), gyro[i], accel[i])
        s = f.state
        out.append(None if s is None else f.camera_pose(s)[1])
    return f, out


def _rmse(out, truth, start=100):
    e = [np.linalg.norm(p - truth.position[i]) for i, p in enumerate(out) if p is not None and i >= start]
    return float(np.sqrt(np.mean(np.square(e))))


def test_rollback_of_late_poses_equals_poses_on_time():
    """Fig. 8: rolled back and replayed, an 80 ms late pose gives the same states as on time."""
    t, truth, gyro, accel, cams = _arcs(8.0)
    _, on_time = _run(t, gyro, accel, cams, 0)
    fl, late = _run(t, gyro, accel, cams, 80_000_000)
    assert fl.rollbacks > 50
    # The late run's buffered states (after all roll-backs) coincide with the on-time run.
    t_index = {int(ti): i for i, ti in enumerate(t)}
    captures = {c[0] for c in cams}  # there the on-time output already includes the pose
    diffs = []
    for ev in fl._events:
        i = t_index.get(ev.t_ns)
        if ev.meas is None and i is not None and ev.t_ns not in captures and ev.state is not None and ev.t_ns < t[-1] - 100_000_000:
            diffs.append(np.linalg.norm(fl.camera_pose(ev.state)[1] - on_time[i]))
    assert len(diffs) > 50
    assert max(diffs) < 1e-9
    assert _rmse(late, truth) < 0.01


def test_rollback_beats_applying_on_arrival_and_is_deterministic():
    t, truth, gyro, accel, cams = _arcs(12.0)
    _, rb = _run(t, gyro, accel, cams, 80_000_000, True)
    _, rb2 = _run(t, gyro, accel, cams, 80_000_000, True)
    _, arrival = _run(t, gyro, accel, cams, 80_000_000, False)
    assert _rmse(rb, truth) < 0.5 * _rmse(arrival, truth)
    assert all((a is None and b is None) or np.array_equal(a, b) for a, b in zip(rb, rb2))


def test_bad_input_verdicts_and_no_nan():
    t, truth, gyro, accel, cams = _arcs(4.0)
    f = RollbackFusion(FusionConfig(R_imu_cam=ra.R_IMU_CAM, max_consecutive_rejections=3))
    assert f.add_pose(PoseMeasurement(int(t[0]), truth.R_enu_cam[0], truth.position[0])) is Verdict.PENDING
    for i in range(150):
        f.add_imu(int(t[i]), gyro[i], accel[i])
        if i % 7 == 0 and i > 8:
            f.add_pose(PoseMeasurement(int(t[i - 8]), truth.R_enu_cam[i - 8], truth.position[i - 8]))
    assert f.state is not None
    assert f.add_imu(int(t[150]), np.array([np.nan, 0, 0]), accel[150]) is Verdict.INVALID
    assert f.add_imu(int(t[149]), gyro[149], accel[149]) is Verdict.STAMP_BACK
    assert f.add_pose(PoseMeasurement(int(t[0]) - 10**9, truth.R_enu_cam[0], truth.position[0])) is Verdict.TOO_OLD
    bad_R = truth.R_enu_cam[140] * 2
    assert f.add_pose(PoseMeasurement(int(t[140]), bad_R, truth.position[140])) is Verdict.INVALID
    assert f.add_pose(PoseMeasurement(int(t[141]), truth.R_enu_cam[141], truth.position[141] + [0.5, 0, 0])) is Verdict.OUTLIER
    p_before = f.state.pos.p.copy()
    # An IMU gap: bridged and reported, the state stays finite.
    assert f.add_imu(int(t[160]), gyro[160], accel[160]) is Verdict.GAP
    assert f.state is not None and f.state.is_finite()
    assert np.linalg.norm(f.state.pos.p - p_before) < 0.2
    # A long gap loses the track; the next pose re-initialises it.
    assert f.add_imu(int(t[260]), gyro[260], accel[260]) is Verdict.RESET_GAP
    assert f.state is None
    f.add_imu(int(t[261]), gyro[261], accel[261])
    assert f.add_pose(PoseMeasurement(int(t[261]), truth.R_enu_cam[261], truth.position[261])) is Verdict.INITIALISED
    # Poses that keep jumping: rejected, then the filter re-initialises from the camera.
    verdicts = []
    for k in range(262, 266):
        f.add_imu(int(t[k]), gyro[k], accel[k])
        verdicts.append(f.add_pose(PoseMeasurement(int(t[k]), truth.R_enu_cam[k], truth.position[k] + [1.0, 0, 0])))
    assert verdicts[:2] == [Verdict.OUTLIER, Verdict.OUTLIER] and Verdict.REINITIALISED in verdicts
    assert f.state.is_finite()
