"""The IMU interval model (:mod:`ar_tracking.core.vio.sampling`): a step of the angular
acceleration located from the gyro, the specific-force step it causes placed there."""
from __future__ import annotations

import numpy as np

from ar_tracking.core.vio.rollback import FusionConfig, PoseMeasurement, RollbackFusion
from ar_tracking.core.vio.sampling import interval_model
from ar_tracking.sim import robot_arcs as ra
from ar_tracking.sim import robot_arcs_real as rr

T0 = 1_700_000_000_000_000_000


def test_kink_time_and_mean_force_of_an_alpha_step():
    """Rate w(t) = w0 + alpha (t - t_s)+ (a kink at t_s) and force a = a0 + (alpha x r) [t > t_s]:
    the model finds t_s from four gyro samples and gives the force's true mean over the
    interval and over a part of it (a camera pose splits intervals), where the trapezoid is off
    by up to half the step."""
    rng = np.random.default_rng(7)
    dt = 0.01
    alpha = np.array([0.0, 0.0, 70.0])
    r = np.array([0.05, -0.03, 0.02])
    step = np.cross(alpha, r)
    a_base = np.array([0.1, 9.8, -0.2])
    for t_s in rng.uniform(0.0005, 0.0095, 10):
        t = np.array([-dt, 0.0, dt, 2 * dt])          # samples k-2 .. k+1; the interval is [0, dt]
        w = np.array([np.array([0.1, 0.0, 0.3]) + alpha * max(ti - t_s, 0.0) for ti in t])
        a = np.array([a_base + (step if ti > t_s else 0.0) for ti in t])
        m = interval_model(dt, tuple(w), tuple(a), gyro_noise_rad_s=0.005)
        assert m.tau is not None and abs(m.tau - t_s) < 1e-6
        true_mean = a_base + step * (dt - t_s) / dt
        _, a_mean = m.means(0.0, dt)
        assert np.allclose(a_mean, true_mean, atol=1e-9)
        _, a_part = m.means(0.0, 0.5 * dt)
        assert np.allclose(a_part, a_base + step * max(0.5 * dt - t_s, 0.0) / (0.5 * dt), atol=1e-9)
        trapezoid = 0.5 * (a[1] + a[2])
        assert np.linalg.norm(trapezoid - true_mean) > 0.05 * np.linalg.norm(step) or abs(t_s - dt / 2) < 0.0006


def test_no_kink_within_the_gyro_noise_keeps_the_trapezoid():
    rng = np.random.default_rng(8)
    dt, noise = 0.01, 0.005
    w = tuple(np.array([0.2, 0.1, 0.4]) + 0.5 * k * dt + rng.normal(scale=noise, size=3) for k in range(4))
    a = tuple(np.array([0.0, 9.8, 0.0]) + rng.normal(scale=0.01, size=3) for _ in range(4))
    m = interval_model(dt, w, a, gyro_noise_rad_s=noise)
    assert m.tau is None
    _, a_mean = m.means(0.0, dt)
    assert np.allclose(a_mean, 0.5 * (a[1] + a[2]))


def test_rollback_integrates_a_quick_pan_start_without_the_sampling_drift():
    """The noise-free IMU of robot_arcs' hard profile (a 155 deg/s pan, IMU at a 6 cm lever arm)
    integrated through the filter for 0.5 s from the true state with no camera in between: the
    trapezoid drifts by centimetres' fractions, the interval model by a small part of that."""
    sched = ra.ArcSchedule.make(4.0)
    t_s = np.arange(1.00, 2.101, 0.01)
    tr = rr.truth_at(sched, t_s)
    R_imu_enu = np.swapaxes(tr.R_enu_imu, 1, 2)
    gyro = np.einsum('nij,nj->ni', R_imu_enu, tr.omega_world)
    accel = np.einsum('nij,nj->ni', R_imu_enu, tr.imu_accel + np.array([0, 0, ra.GRAVITY_M_S2]))
    t_ns = T0 + np.round(t_s * 1e9).astype(np.int64)
    drift = {}
    for model in (False, True):
        cfg = FusionConfig(R_imu_cam=rr.R_IMU_CAM, t_imu_cam=rr.T_IMU_CAM, sampling_model=model, gate_chi2=0.0)
        f = RollbackFusion(cfg)
        for k in range(len(t_s)):
            f.add_imu(int(t_ns[k]), gyro[k], accel[k])
            # exact poses every 50 ms until the pan starts (1.7 s), then the IMU alone
            if t_s[k] < 1.6 and k % 5 == 0:
                f.add_pose(PoseMeasurement(int(t_ns[k]), tr.cam.R_enu_cam[k], tr.cam.position[k], np.eye(6) * 1e-12))
        _, p = f.camera_pose(f.state)
        drift[model] = float(np.linalg.norm(p - tr.cam.position[-1]))
    assert drift[False] > 0.003, drift
    assert drift[True] < 0.25 * drift[False], drift
