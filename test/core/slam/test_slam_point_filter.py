"""Partially initialised points (Klein & Murray 2009 sec. 5.2): inverse-depth EIF, prediction,
two-view triangulation, on seeded synthetic geometry."""
from __future__ import annotations

import cv2
import numpy as np

from ar_tracking.core.slam.camera import Camera
from ar_tracking.core.slam.point_filter import (mean_inverse_depth, partial_point_world,
                                                predict_partial_uv, triangulate_two_view,
                                                update_inverse_depth)
from ar_tracking.core.slam.slam_map import Keyframe, PartialPoint

CAM = Camera(fx=300.0, fy=300.0, cx=159.5, cy=119.5, width=320, height=240)


def _kf(R, t, kf_id=0):
    return Keyframe(id=kf_id, stamp_ns=0, R_c_w=np.asarray(R, float), t_c_w=np.asarray(t, float),
                    pyramid=[])


def _source_and_point(rng):
    """A source keyframe slightly off the origin and a partial point on one of its rays."""
    R_src, _ = cv2.Rodrigues(np.array([0.05, -0.1, 0.02]))
    t_src = np.array([0.1, -0.05, 0.2])
    uv_src = np.array([200.0, 90.0])
    ray = CAM.unproject(uv_src)[0]
    depth = 3.0
    X_w = R_src.T @ (ray * depth - t_src)
    pp = PartialPoint(id=7, source_kf=0, source_level=0, source_uv=uv_src, ray=ray, q_hat=1.0 / 1.5)
    return _kf(R_src, t_src), pp, X_w, depth


def _frame(R_src, t_src, dx, dy=0.0):
    """A camera translated by (dx, dy) in the source camera frame, slightly rotated."""
    Rd, _ = cv2.Rodrigues(np.array([0.0, 0.02 * dx, 0.0]))
    R = Rd @ R_src
    t = Rd @ t_src - np.array([dx, dy, 0.0])
    return R, t


def test_inverse_depth_filter_converges_and_information_grows():
    rng = np.random.default_rng(0)
    src, pp, X_w, depth = _source_and_point(rng)
    _, r0 = predict_partial_uv(pp, src, *_frame(src.R_c_w, src.t_c_w, 0.05), CAM)
    infos = [pp.info]
    for k in range(1, 16):
        R, t = _frame(src.R_c_w, src.t_c_w, 0.02 * k, 0.005 * k)
        uv = CAM.project((R @ X_w + t)[None])[0][0] + rng.normal(0.0, 0.5, 2)
        update_inverse_depth(pp, R, t, src.R_c_w, src.t_c_w, uv, 1.0, CAM)
        infos.append(pp.info)
    assert pp.n_updates == 15
    assert np.all(np.diff(infos) > 0)
    sigma_q = 1.0 / np.sqrt(pp.info)
    assert abs(pp.q_hat - 1.0 / depth) < 3.0 * sigma_q + 1e-3
    assert abs(1.0 / pp.q_hat - depth) < 0.15
    assert np.linalg.norm(partial_point_world(pp, src) - X_w) < 0.15
    # Prediction with the converged estimate: close to the truth, tight radius along the line.
    R, t = _frame(src.R_c_w, src.t_c_w, 0.4)
    uv_pred, r1 = predict_partial_uv(pp, src, R, t, CAM)
    uv_true = CAM.project((R @ X_w + t)[None])[0][0]
    assert np.linalg.norm(uv_pred - uv_true) < 3.0
    assert r1 < r0


def test_first_update_from_infinite_uncertainty_is_nonlinear_solved():
    """With info = 0 the iterated update lands on the measured depth even from a bad q_hat."""
    src, pp, X_w, depth = _source_and_point(np.random.default_rng(1))
    pp.q_hat = 2.0      # depth 0.5 instead of 3
    R, t = _frame(src.R_c_w, src.t_c_w, 0.3)
    uv = CAM.project((R @ X_w + t)[None])[0][0]
    update_inverse_depth(pp, R, t, src.R_c_w, src.t_c_w, uv, 1.0, CAM, iterations=10)
    assert abs(1.0 / pp.q_hat - depth) < 0.05


def test_no_baseline_and_cross_epipolar_error_leave_depth_unchanged():
    src, pp, X_w, _ = _source_and_point(np.random.default_rng(2))
    # Pure rotation about the source centre: the epipolar "line" is a point, no depth information.
    Rr, _ = cv2.Rodrigues(np.array([0.0, 0.05, 0.0]))
    R = Rr @ src.R_c_w
    t = Rr @ src.t_c_w
    uv = CAM.project((R @ X_w + t)[None])[0][0]
    q0 = pp.q_hat
    update_inverse_depth(pp, R, t, src.R_c_w, src.t_c_w, uv, 1.0, CAM)
    assert pp.info == 0.0 and pp.q_hat == q0 and pp.n_updates == 0
    # With baseline, an error perpendicular to the epipolar line does not move q.
    pp.q_hat, pp.info = 1.0 / 3.0, 50.0
    R, t = _frame(src.R_c_w, src.t_c_w, 0.2)
    uv_pred, _ = predict_partial_uv(pp, src, R, t, CAM)
    uv_far, _ = predict_partial_uv(PartialPoint(8, 0, 0, pp.source_uv, pp.ray, 0.1), src, R, t, CAM)
    along = (uv_far - uv_pred) / np.linalg.norm(uv_far - uv_pred)
    perp = np.array([-along[1], along[0]])
    update_inverse_depth(pp, R, t, src.R_c_w, src.t_c_w, uv_pred + 3.0 * perp, 1.0, CAM)
    assert abs(pp.q_hat - 1.0 / 3.0) < 2e-3
    pp2 = PartialPoint(9, 0, 0, pp.source_uv, pp.ray, 1.0 / 3.0, 50.0)
    update_inverse_depth(pp2, R, t, src.R_c_w, src.t_c_w, uv_pred + 3.0 * along, 1.0, CAM)
    assert abs(pp2.q_hat - 1.0 / 3.0) > 5e-3


def test_triangulate_two_view_recovers_points_and_flags_bad_geometry():
    rng = np.random.default_rng(3)
    R0, t0 = np.eye(3), np.zeros(3)
    R1, _ = cv2.Rodrigues(np.array([0.0, -0.08, 0.0]))
    t1 = np.array([-0.3, 0.0, 0.02])
    X = rng.uniform([-1, -1, 2.5], [1, 1, 4.0], (50, 3))
    uv0 = CAM.project(X @ R0.T + t0)[0]
    uv1 = CAM.project(X @ R1.T + t1)[0]
    xyz, good = triangulate_two_view(R0, t0, uv0, R1, t1, uv1, CAM)
    assert good.all()
    assert np.abs(xyz - X).max() < 1e-6
    # Noisy: still close.
    xyz_n, good_n = triangulate_two_view(R0, t0, uv0 + rng.normal(0, 0.3, uv0.shape), R1, t1,
                                         uv1 + rng.normal(0, 0.3, uv1.shape), CAM)
    assert good_n.mean() > 0.9 and np.median(np.linalg.norm(xyz_n - X, axis=1)) < 0.1
    # Tiny baseline: parallax below the limit -> not good.
    _, good_small = triangulate_two_view(R0, t0, uv0, R0, t0 + np.array([-1e-3, 0, 0]),
                                         CAM.project(X + np.array([-1e-3, 0, 0]))[0], CAM)
    assert not good_small.any()
    # Inconsistent match (40 px off the epipolar geometry) -> not good.
    _, good_bad = triangulate_two_view(R0, t0, uv0[0], R1, t1, uv1[0] + np.array([0.0, 40.0]), CAM)
    assert not good_bad[0]


def test_mean_inverse_depth():
    X = np.array([[0, 0, 2.0], [0, 0, 4.0], [0, 0, -1.0]])
    assert np.isclose(mean_inverse_depth(np.eye(3), np.zeros(3), X), (0.5 + 0.25) / 2)
    assert mean_inverse_depth(np.eye(3), np.zeros(3), np.zeros((0, 3)), 0.7) == 0.7
