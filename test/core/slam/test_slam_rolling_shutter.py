"""Rolling-shutter correction (Klein & Murray 2009 sec. 6) on a seeded synthetic rolling-shutter
sequence: the sensor reads rows over 60 ms while each keyframe's camera moves."""
from __future__ import annotations

import cv2
import numpy as np

from ar_tracking.core.slam.bundle_adjustment import bundle_adjust
from ar_tracking.core.slam.camera import Camera
from ar_tracking.core.slam.rolling_shutter import correct_keyframe, estimate_camera_velocity
from ar_tracking.core.slam.slam_map import Keyframe, Measurement
from ar_tracking.sim.ba_problem import look_at

CAM = Camera(fx=500.0, fy=500.0, cx=319.5, cy=239.5, width=640, height=480, readout_s=0.06)
FRAME_DT = 1.0 / 15.0


def _pose_at(R0, t0, xi, dt):
    """T(dt) = exp(xi dt) T0 (xi = (v, omega) in the camera frame, first order in v)."""
    dR, _ = cv2.Rodrigues(np.asarray(xi[3:], float) * dt)
    return dR @ R0, dR @ t0 + np.asarray(xi[:3], float) * dt


def _project(R, t, X):
    return CAM.project((R @ X + t)[None])[0][0]


def _rs_observation(R0, t0, xi, X):
    """Where a rolling-shutter camera sees X: the row's capture time depends on the row."""
    uv = _project(R0, t0, X)
    for _ in range(8):
        R, t = _pose_at(R0, t0, xi, float(CAM.row_time_offset_s(uv[1])))
        uv = _project(R, t, X)
    return uv


def _scene(seed, n_kf=8, n_pts=150, vel_noise=5.0, px_noise=0.3):
    rng = np.random.default_rng(seed)
    pts = {i: rng.uniform(-1.0, 1.0, 3) for i in range(n_pts)}
    kfs, true_poses, xis = [], {}, {}
    for k, a in enumerate(np.linspace(-0.5, 0.5, n_kf)):
        R, t = look_at(np.array([4 * np.sin(a), 0.3 * np.cos(3 * a), -4 * np.cos(a)]),
                       rng.normal(0, 0.1, 3))
        true_poses[k] = (R, t)
        xi = np.concatenate([rng.normal(0, 0.4, 3), rng.normal(0, 0.6, 3)])
        xis[k] = xi
        kf = Keyframe(id=k, stamp_ns=k, R_c_w=R.copy(), t_c_w=t.copy(), pyramid=[], fixed=k == 0)
        for pid, X in pts.items():
            uv_c = _project(R, t, X)
            if not CAM.in_image(uv_c, border=10)[0] or (R @ X + t)[2] <= 0:
                continue
            uv = _rs_observation(R, t, xi, X) + rng.normal(0, px_noise, 2)
            kf.measurements[pid] = Measurement(k, pid, uv, 0)
            # Image velocity from the neighbouring frames (central difference, noisy).
            up = _rs_observation(*_pose_at(R, t, xi, FRAME_DT), xi, X)
            um = _rs_observation(*_pose_at(R, t, xi, -FRAME_DT), xi, X)
            kf.image_velocities[pid] = (up - um) / (2 * FRAME_DT) + rng.normal(0, vel_noise, 2)
        kfs.append(kf)
    return kfs, pts, true_poses, xis


def test_velocity_estimate_recovers_camera_motion():
    kfs, pts, _, xis = _scene(0, n_kf=3)
    for kf in kfs:
        ids = list(kf.image_velocities)
        xi = estimate_camera_velocity(kf.R_c_w, kf.t_c_w, np.array([pts[p] for p in ids]),
                                      np.array([kf.image_velocities[p] for p in ids]), CAM)
        assert xi is not None
        assert np.linalg.norm(xi[3:] - xis[kf.id][3:]) < 0.1 * np.linalg.norm(xis[kf.id][3:]) + 0.02
        assert np.linalg.norm(xi[:3] - xis[kf.id][:3]) < 0.25 * np.linalg.norm(xis[kf.id][:3]) + 0.05
    # Too few points: no estimate.
    assert estimate_camera_velocity(np.eye(3), np.zeros(3), np.array([[0, 0, 3.0]]),
                                    np.zeros((1, 2)), CAM) is None


def test_correction_moves_measurements_to_the_centre_row_time():
    kfs, pts, true_poses, _ = _scene(1, n_kf=2, vel_noise=0.0, px_noise=0.0)
    kf = kfs[1]
    correct_keyframe(kf, pts, CAM)
    R, t = true_poses[1]
    raw = np.array([np.linalg.norm(m.uv - _project(R, t, pts[p])) for p, m in kf.measurements.items()])
    cor = np.array([np.linalg.norm(m.uv_corrected - _project(R, t, pts[p]))
                    for p, m in kf.measurements.items()])
    assert raw.mean() > 1.0           # the rolling shutter really displaces the points
    assert cor.mean() < 0.2 * raw.mean()
    # Global shutter: nothing to correct.
    gs = Camera(CAM.fx, CAM.fy, CAM.cx, CAM.cy, CAM.width, CAM.height, 0.0)
    correct_keyframe(kf, pts, gs)
    assert all(np.array_equal(m.uv, m.uv_corrected) for m in kf.measurements.values())


def test_rolling_shutter_correction_reduces_bundle_adjustment_error():
    kfs, pts, true_poses, _ = _scene(2)
    rng = np.random.default_rng(5)
    init = {p: X + rng.normal(0, 0.03, 3) for p, X in pts.items()}
    for kf in kfs[2:]:
        kf.t_c_w = kf.t_c_w + rng.normal(0, 0.02, 3)
    fixed = {0, 1}
    raw = bundle_adjust(kfs, init, CAM, fixed, 30, scale=2.0)
    for kf in kfs:
        assert correct_keyframe(kf, init, CAM) is not None
    # Re-correct once with the adjusted map, as the mapper does ("occasionally re-corrected").
    first = bundle_adjust(kfs, init, CAM, fixed, 30, scale=2.0)
    for kf in kfs:
        correct_keyframe(kf, first.points, CAM)
    cor = bundle_adjust(kfs, init, CAM, fixed, 30, scale=2.0)
    assert cor.objective_after < 0.5 * raw.objective_after

    def point_err(res):
        return np.median([np.linalg.norm(res.points[p] - pts[p]) for p in res.points])

    assert point_err(cor) < point_err(raw)
