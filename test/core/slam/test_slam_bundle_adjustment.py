"""gtsam bundle adjustment (Klein & Murray 2009 sec. 3, 7) on seeded synthetic problems."""
from __future__ import annotations

import numpy as np

from ar_tracking.core.slam.bundle_adjustment import (bundle_adjust, bundle_adjust_one_iteration,
                                                     point_jacobians, pose_from_gtsam, pose_jacobians,
                                                     pose_to_gtsam, project_world, robust_weights)
from ar_tracking.core.slam.camera import Camera
from ar_tracking.eval.bench_slam import benchmark_one_iteration
from ar_tracking.sim.ba_problem import make_synthetic_ba_problem


def _rot_err(Ra, Rb):
    return np.degrees(np.arccos(np.clip((np.trace(Ra @ Rb.T) - 1) / 2, -1, 1)))


def test_pose_conversion_round_trip_and_jacobians_match_numeric():
    cam = Camera(400.0, 410.0, 160.0, 120.0, 320, 240)
    prob = make_synthetic_ba_problem(3, 20, 0, camera=cam)
    R, t = prob.true_poses[2]
    R2, t2 = pose_from_gtsam(pose_to_gtsam(R, t))
    assert np.allclose(R, R2) and np.allclose(t, t2)
    X = np.array(list(prob.true_points.values()))[:5]
    B = point_jacobians(cam, R, t, X)
    J = pose_jacobians(cam, R, t, X)
    eps = 1e-6
    for i in range(3):
        d = np.zeros(3)
        d[i] = eps
        num = (project_world(cam, R, t, X + d)[0] - project_world(cam, R, t, X - d)[0]) / (2 * eps)
        assert np.allclose(B[:, :, i], num, atol=1e-3)
    import cv2
    for i in range(6):
        xi = np.zeros(6)
        xi[i] = eps
        uv = []
        for s in (1, -1):
            dR, _ = cv2.Rodrigues(s * xi[3:])
            uv.append(project_world(cam, dR @ R, dR @ t + s * xi[:3], X)[0])
        assert np.allclose(J[:, :, i], (uv[0] - uv[1]) / (2 * eps), atol=1e-3)


def test_ba_recovers_poses_and_points_with_outliers_flagged():
    prob = make_synthetic_ba_problem(10, 150, seed=1, noise_px=0.5, outlier_fraction=0.05,
                                     outlier_px=30.0)
    assert len(prob.outliers) > 20
    res = bundle_adjust(prob.keyframes, prob.points, prob.camera, prob.fixed_kf_ids, iterations=30)
    assert res.objective_after < 0.2 * res.objective_before
    # Points and poses back to the truth (gauge fixed by keyframes 0 and 1).
    init_err = np.median([np.linalg.norm(prob.points[i] - prob.true_points[i]) for i in res.points])
    err = np.array([np.linalg.norm(res.points[i] - prob.true_points[i]) for i in res.points])
    assert np.median(err) < 0.01 < init_err
    for k, (R, t) in res.poses.items():
        Rt, tt = prob.true_poses[k]
        assert _rot_err(R, Rt) < 0.1
        assert np.linalg.norm(-R.T @ t + Rt.T @ tt) < 0.02
    # Fixed keyframes are returned unchanged.
    for k in prob.fixed_kf_ids:
        assert np.allclose(res.poses[k][1], prob.keyframes[k].t_c_w)
    # The Tukey weights flag the outliers and keep the inliers.
    w_out = np.array([res.weights[k] for k in prob.outliers if k in res.weights])
    w_in = np.array([w for k, w in res.weights.items() if k not in prob.outliers])
    assert np.all(w_out == 0.0)
    assert np.mean(w_in > 0.5) > 0.98


def test_least_squares_is_dragged_by_outliers_where_tukey_is_not():
    prob = make_synthetic_ba_problem(8, 120, seed=2, outlier_fraction=0.08, outlier_px=40.0)
    tukey = bundle_adjust(prob.keyframes, prob.points, prob.camera, prob.fixed_kf_ids, 30)
    plain = bundle_adjust(prob.keyframes, prob.points, prob.camera, prob.fixed_kf_ids, 30,
                          robust='none')

    def med_err(res):
        return np.median([np.linalg.norm(res.points[i] - prob.true_points[i]) for i in res.points])

    assert med_err(tukey) < 0.5 * med_err(plain)


def test_one_iteration_and_abort():
    prob = make_synthetic_ba_problem(35, 300, seed=0)
    res = bundle_adjust_one_iteration(prob.keyframes, prob.points, prob.camera, prob.fixed_kf_ids)
    assert res.iterations == 1 and res.n_measurements == 2400 and len(res.poses) == 35
    assert res.objective_after < res.objective_before
    polls = [0]

    def abort() -> bool:
        polls[0] += 1
        return polls[0] > 2

    res2 = bundle_adjust(prob.keyframes, prob.points, prob.camera, prob.fixed_kf_ids, 20,
                         abort=abort)
    assert res2.aborted and res2.iterations == 2
    assert res2.objective_after < res2.objective_before


def test_one_iteration_benchmark_is_fast():
    """Sec. 7: 750 ms per iteration (35 kf, 300 points) on the phone; target <= 50 ms here.
    Loose bound (shared CPU); the measured figure is logged by the benchmark."""
    bench = benchmark_one_iteration(repeats=3)
    assert bench['keyframes'] == 35 and bench['points'] == 300
    assert bench['ms_iterate'] < 100.0


def test_robust_weights_shapes():
    d = np.array([0.0, 1.0, 4.0, 10.0])
    w = robust_weights(d, 'tukey', 4.685)
    assert w[0] == 1.0 and 0 < w[2] < w[1] < 1 and w[3] == 0.0
    wh = robust_weights(d, 'huber', 1.345)
    assert wh[0] == 1.0 and wh[3] > 0
