"""The joint 15-state error filter (:mod:`ar_tracking.core.vio.joint`) and the sampling error of
the IMU input (:func:`ar_tracking.core.vio.eskf.sampling_error_cov`), on synthetic data."""
from __future__ import annotations

import numpy as np

from ar_tracking.core.vio.eskf import (FilterNoise, OrientationState, PositionState, predict_position,
                                       quat_exp, quat_log, quat_mul, quat_to_matrix, matrix_to_quat,
                                       sampling_error_cov, update_orientation, update_position)
from ar_tracking.core.vio.joint import pose_observation, predict_joint, skew, update_joint

R_IC = quat_to_matrix(quat_exp(np.array([1.5, -0.2, 0.3])))
T_IC = np.array([0.03, -0.05, 0.02])


def _states(rng: np.random.Generator) -> tuple[OrientationState, PositionState]:
    ori = OrientationState(quat_exp(rng.normal(size=3)), rng.normal(scale=0.01, size=3), np.eye(6) * 1e-4)
    pos = PositionState(rng.normal(size=3), rng.normal(size=3), rng.normal(scale=0.05, size=3), np.eye(9) * 1e-4)
    return ori, pos


def test_pose_observation_jacobian_matches_finite_differences():
    """H of the camera pose (lever arm and mount included) against perturbing the true states."""
    rng = np.random.default_rng(3)
    ori, pos = _states(rng)
    R_cam = ori.R @ R_IC
    p_cam = pos.p + ori.R @ T_IC
    z0, H = pose_observation(ori, pos, R_IC, T_IC, R_cam, p_cam)
    assert np.allclose(z0, 0, atol=1e-12)
    eps = 1e-6
    for i in range(15):
        dx = np.zeros(15)
        dx[i] = eps
        # the measurement of a true state = estimate (+) dx; the innovation is then H dx
        o2 = OrientationState(quat_mul(ori.quat_wxyz, quat_exp(dx[:3])), ori.gyro_bias + dx[3:6], ori.P)
        p2 = PositionState(pos.p + dx[6:9], pos.v + dx[9:12], pos.accel_bias + dx[12:], pos.P)
        z, _ = pose_observation(ori, pos, R_IC, T_IC, o2.R @ R_IC, p2.p + o2.R @ T_IC)
        assert np.allclose(z / eps, H[:, i], atol=1e-5), i


def test_joint_transition_matches_finite_differences_of_the_process_model():
    """Phi of the joint time update: an orientation error tilts the specific force into the
    velocity and position (the coupling the separate filters lack), besides the blocks of Fig. 7."""
    rng = np.random.default_rng(4)
    ori, pos = _states(rng)
    gyro, accel, dt = np.array([0.4, -1.1, 2.0]), np.array([0.3, 9.9, -0.8]), 0.01
    noise = FilterNoise()

    def step(dx):
        o = OrientationState(quat_mul(ori.quat_wxyz, quat_exp(dx[:3])), ori.gyro_bias + dx[3:6], np.zeros((6, 6)))
        p = PositionState(pos.p + dx[6:9], pos.v + dx[9:12], pos.accel_bias + dx[12:], np.zeros((9, 9)))
        predict_joint(o, p, np.zeros((6, 9)), gyro, accel, dt, noise)
        return o, p

    o0, p0 = step(np.zeros(15))
    eps = 1e-6
    Phi = np.zeros((15, 15))
    for i in range(15):
        dx = np.zeros(15)
        dx[i] = eps
        o, p = step(dx)
        Phi[:3, i] = quat_log(quat_mul(np.array([o0.quat_wxyz[0], *-o0.quat_wxyz[1:]]), o.quat_wxyz)) / eps
        Phi[3:6, i] = (o.gyro_bias - o0.gyro_bias) / eps
        Phi[6:9, i] = (p.p - p0.p) / eps
        Phi[9:12, i] = (p.v - p0.v) / eps
        Phi[12:, i] = (p.accel_bias - p0.accel_bias) / eps
    # propagate a covariance with only orientation uncertainty: the filter's P must equal Phi P Phi^T + Q
    o, p = OrientationState(ori.quat_wxyz.copy(), ori.gyro_bias.copy(), np.diag([1e-4] * 3 + [0.0] * 3)), pos.copy()
    p.P = np.zeros((9, 9))
    cross = predict_joint(o, p, np.zeros((6, 9)), gyro, accel, dt, noise)[0]
    P0 = np.zeros((15, 15))
    P0[:3, :3] = np.eye(3) * 1e-4
    expected = Phi @ P0 @ Phi.T
    assert np.abs(Phi[9:12, :3]).max() > 0.05        # the tilt coupling is there
    assert np.allclose(cross, expected[:6, 6:], atol=2e-9)
    assert np.allclose(p.P[3:6, 3:6] - expected[9:12, 9:12], p.P[3:6, 3:6] - expected[9:12, 9:12].T)
    assert np.all(np.diag(p.P)[3:6] >= np.diag(expected)[9:12] - 1e-12)


def test_joint_update_uses_the_pose_cross_covariance():
    """A pose whose position error is its orientation error times the distance to the markers
    (the rotation-translation ambiguity): with the orientation known well from the gyro, the
    joint update removes most of the position error, the separate ones do not."""
    rng = np.random.default_rng(5)
    distance = 3.0
    sig_rot = np.radians(0.1)
    n = 300
    err_joint, err_sep = [], []
    for _ in range(n):
        ori = OrientationState(quat_exp(rng.normal(size=3)), np.zeros(3), np.diag([np.radians(0.02) ** 2] * 3 + [1e-6] * 3))
        pos = PositionState(np.zeros(3), np.zeros(3), np.zeros(3), np.diag([0.01 ** 2] * 3 + [0.1 ** 2] * 3 + [0.01] * 3))
        truth_R, truth_p = ori.R.copy(), pos.p.copy()
        # true states = estimate here; the camera pose error: a turn dtheta (world) about a
        # vertical axis and the matching sideways position error, dp = distance * (z x dtheta)
        dth = np.array([0.0, 0.0, rng.normal(scale=sig_rot)])
        dp = distance * np.cross([1.0, 0.0, 0.0], dth) + rng.normal(scale=2e-4, size=3)
        J = distance * skew(np.array([1.0, 0.0, 0.0]))
        C = np.zeros((6, 6))
        C[3:, 3:] = np.diag([sig_rot ** 2] * 3)
        C[:3, :3] = J @ C[3:, 3:] @ J.T + np.eye(3) * 4e-8
        C[:3, 3:] = J @ C[3:, 3:]
        C[3:, :3] = C[:3, 3:].T
        R_m = quat_to_matrix(quat_exp(dth)) @ truth_R @ R_IC
        p_m = truth_p + truth_R @ T_IC + dp
        o1, p1 = ori.copy(), pos.copy()
        res, _ = update_joint(o1, p1, np.zeros((6, 9)), R_IC, T_IC, R_m, p_m, C, gate=None)
        assert res.accepted
        err_joint.append(np.linalg.norm(p1.p - truth_p))
        o2, p2 = ori.copy(), pos.copy()
        R_w_imu = R_m @ R_IC.T
        update_orientation(o2, matrix_to_quat(R_w_imu), R_w_imu.T @ C[3:, 3:] @ R_w_imu, gate=None)
        update_position(p2, p_m - R_w_imu @ T_IC, C[:3, :3], gate=None)
        err_sep.append(np.linalg.norm(p2.p - truth_p))
    rms_j, rms_s = np.sqrt(np.mean(np.square(err_joint))), np.sqrt(np.mean(np.square(err_sep)))
    assert rms_j < 0.5 * rms_s, (rms_j, rms_s)


def test_sampling_error_covariance_is_the_trapezoid_error_of_a_step():
    """An input that steps by delta at a uniformly random instant inside one IMU interval: the
    trapezoid's velocity error has exactly the covariance sampling_error_cov(delta) dt^2."""
    rng = np.random.default_rng(6)
    delta, dt = np.array([4.0, -1.0, 0.5]), 0.01
    errs = []
    for u in rng.uniform(size=4000):
        s = PositionState(np.zeros(3), np.zeros(3), np.zeros(3), np.zeros((9, 9)))
        a0 = np.array([0.0, 0.0, 9.80665])
        predict_position(s, np.eye(3), a0 + 0.5 * delta, dt, FilterNoise())   # trapezoid of the two samples
        true_v = delta * (1.0 - u) * dt                                          # the step at u * dt
        errs.append(s.v - true_v)
    errs = np.array(errs)
    C = np.cov(errs.T) / dt ** 2
    assert np.allclose(C, sampling_error_cov(delta), rtol=0.1, atol=1e-3)
    # and the filter's velocity covariance grows by it
    s = PositionState(np.zeros(3), np.zeros(3), np.zeros(3), np.zeros((9, 9)))
    predict_position(s, np.eye(3), np.array([0, 0, 9.80665]), dt, FilterNoise(0, 0, 0, 1e-9, 0, 0), accel_step_cov=sampling_error_cov(delta))
    assert np.allclose(s.P[3:6, 3:6], sampling_error_cov(delta) * dt ** 2, rtol=1e-3)


def test_camera_covariance_is_the_observation_jacobian_times_p():
    """The published camera pose covariance of the joint filter: position uncertainty grows with
    orientation uncertainty through the lever arm, and the two blocks correlate."""
    from ar_tracking.core.vio.rollback import FusionConfig, FusionState, RollbackFusion

    rng = np.random.default_rng(9)
    ori, pos = _states(rng)
    ori.P = np.diag([1e-4] * 3 + [1e-6] * 3)
    pos.P = np.diag([1e-6] * 3 + [1e-4] * 3 + [1e-4] * 3)
    f = RollbackFusion(FusionConfig(R_imu_cam=R_IC, t_imu_cam=T_IC))
    st = FusionState(0, ori, pos, np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3))
    C = f.camera_covariance(st)
    _, H = pose_observation(ori, pos, R_IC, T_IC, ori.R @ R_IC, pos.p + ori.R @ T_IC)
    P = np.zeros((15, 15))
    P[:6, :6], P[6:, 6:] = ori.P, pos.P
    assert np.allclose(C, H @ P @ H.T)
    assert np.trace(C[:3, :3]) > np.trace(pos.P[:3, :3]) * 1.05
    assert np.abs(C[:3, 3:]).max() > 0
    assert np.all(np.linalg.eigvalsh(C) > 0)
