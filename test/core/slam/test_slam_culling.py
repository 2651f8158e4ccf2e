"""Measurement culling (sec. 3.2) and keyframe culling by utility voting (sec. 3.3)."""
from __future__ import annotations

import numpy as np

from ar_tracking.core.slam.bundle_adjustment import project_world
from ar_tracking.core.slam.camera import Camera
from ar_tracking.core.slam.culling import (keyframe_utilities, keyframes_to_cull,
                                           measurements_to_cull, point_measurement_metrics,
                                           rank_utilities)
from ar_tracking.core.slam.slam_map import Keyframe, Measurement
from ar_tracking.sim.ba_problem import look_at

CAM = Camera(fx=400.0, fy=400.0, cx=319.5, cy=239.5, width=640, height=480)


def _ring(n, radius=4.0, spread=1.2, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for k, a in enumerate(np.linspace(-spread / 2, spread / 2, n)):
        pos = np.array([radius * np.sin(a), rng.normal(0, 0.3), -radius * np.cos(a)])
        R, t = look_at(pos, np.zeros(3))
        out.append(Keyframe(id=k, stamp_ns=k, R_c_w=R, t_c_w=t, pyramid=[], fixed=k == 0))
    return out


def _observe(kfs, points, rng, levels=None):
    for pid, X in points.items():
        for kf in kfs:
            uv, z = project_world(CAM, kf.R_c_w, kf.t_c_w, X)
            if z[0] > 0 and CAM.in_image(uv)[0]:
                lv = 0 if levels is None else int(levels(kf.id, pid))
                kf.measurements[pid] = Measurement(kf.id, pid, uv[0] + rng.normal(0, 0.3, 2), lv)


def test_information_metric_matches_determinant_definition():
    kfs = _ring(5)
    X = np.array([0.1, -0.2, 0.3])
    poses = [(kf.R_c_w, kf.t_c_w) for kf in kfs]
    sig = np.array([1.0, 2.0, 1.0, 4.0, 1.0])
    w = np.array([1.0, 1.0, 0.5, 1.0, 0.0])
    m = point_measurement_metrics(X, poses, sig, w, CAM)
    from ar_tracking.core.slam.bundle_adjustment import point_jacobians
    Vj = [w[j] / sig[j] ** 2 * point_jacobians(CAM, *poses[j], X[None])[0].T
          @ point_jacobians(CAM, *poses[j], X[None])[0] for j in range(5)]
    V = sum(Vj)
    for j in range(5):
        assert np.isclose(m[j], np.linalg.det(V) - np.linalg.det(V - Vj[j]), rtol=1e-9)
    assert m[4] == 0.0          # a zero-weight (outlier) measurement carries no information


def test_measurement_culling_keeps_the_eight_most_useful():
    rng = np.random.default_rng(1)
    kfs = _ring(12, spread=1.4, seed=1)
    points = {i: rng.uniform(-0.5, 0.5, 3) for i in range(30)}
    # Mixed levels so that usefulness differs beyond geometry; one outlier weight.
    _observe(kfs, points, rng, levels=lambda k, p: (k * 7 + p) % 3)
    weights = {(3, 0): 0.0}
    cull = measurements_to_cull(kfs, points, CAM, weights, max_per_point=8)
    by_point = {}
    for k, p in cull:
        by_point.setdefault(p, set()).add(k)
    assert by_point, 'every point is seen by 12 keyframes: something must be culled'
    for pid, X in points.items():
        obs = [kf for kf in kfs if pid in kf.measurements]
        m = point_measurement_metrics(
            X, [(kf.R_c_w, kf.t_c_w) for kf in obs],
            np.array([kf.measurements[pid].sigma_px for kf in obs]),
            np.array([weights.get((kf.id, pid), 1.0) for kf in obs]), CAM)
        expected = {obs[j].id for j in np.argsort(-m, kind='stable')[8:]}
        assert by_point.get(pid, set()) == expected
        assert len(obs) - len(expected) == min(8, len(obs))
    assert 3 in by_point[0]       # the zero-weight measurement is among the culled


def test_rank_utilities_follow_the_voting_rule():
    assert np.allclose(rank_utilities(np.array([5.0, 1.0])), [0.5, 0.5])
    assert np.allclose(rank_utilities(np.array([1.0, 3.0, 2.0])), [1 / 6, 3 / 6, 2 / 6])
    u = rank_utilities(np.array([6.0, 5.0, 4.0, 3.0, 2.0, 1.0]))
    assert np.allclose(u, [0.4, 0.3, 0.2, 0.1, 0.0, 0.0])
    assert np.allclose(rank_utilities(np.array([1.0])), [0.0])


def _outward_ring(n, n_points, rng):
    """n keyframes near the centre of a cylindrical wall looking outward (no ends: every
    keyframe shares points with both neighbours), points on the wall."""
    cam = Camera(fx=400.0, fy=400.0, cx=319.5, cy=239.5, width=640, height=480)
    kfs = []
    for k in range(n):
        th = 2 * np.pi * k / n
        d = np.array([np.cos(th), 0.0, np.sin(th)])
        R, t = look_at(0.3 * d, 4.0 * d)
        kfs.append(Keyframe(id=k, stamp_ns=k, R_c_w=R, t_c_w=t, pyramid=[], fixed=k == 0))
    th = rng.uniform(0, 2 * np.pi, n_points)
    points = {i: np.array([4 * np.cos(a), rng.uniform(-1, 1), 4 * np.sin(a)])
              for i, a in enumerate(th)}
    return cam, kfs, points


def _measure(cam, kfs, points):
    for pid, X in points.items():
        for kf in kfs:
            uv, z = project_world(cam, kf.R_c_w, kf.t_c_w, X)
            if z[0] > 0 and cam.in_image(uv)[0]:
                kf.measurements[pid] = Measurement(kf.id, pid, uv[0], 0)


def test_keyframe_culling_removes_a_redundant_duplicate_not_a_unique_keyframe():
    rng = np.random.default_rng(2)
    cam, kfs, points = _outward_ring(8, 400, rng)
    # Keyframe 8 duplicates keyframe 3 (same place, a hair apart).
    kfs.append(Keyframe(id=8, stamp_ns=8, R_c_w=kfs[3].R_c_w.copy(), t_c_w=kfs[3].t_c_w + 2e-3,
                        pyramid=[]))
    _measure(cam, kfs[:8], points)
    # Only points triangulable from the original ring exist in a map; the duplicate then
    # measures those it sees (points seen by the twins alone would have no baseline).
    points = {p: X for p, X in points.items() if sum(p in kf.measurements for kf in kfs[:8]) >= 2}
    for kf in kfs[:8]:
        kf.measurements = {p: m for p, m in kf.measurements.items() if p in points}
    _measure(cam, kfs[8:], points)
    util = keyframe_utilities(kfs, points, cam)
    ranked = sorted(util, key=util.get)
    assert set(ranked[:2]) == {3, 8}             # the duplicated pair ranks lowest
    erase = keyframes_to_cull(kfs, points, cam, max_keyframes=8, utility_threshold=1e9)
    assert len(erase) == 1 and erase[0] in (3, 8)
    # Without its twin the survivor is as useful as any other keyframe again.
    twin = 3 if erase[0] == 8 else 8
    rest = [kf for kf in kfs if kf.id != erase[0]]
    util_rest = keyframe_utilities(rest, points, cam)
    assert util_rest[twin] > 1.5 * util[twin]
    assert util_rest[twin] > min(util_rest.values())
    # Not over the limit, or nobody below the threshold: nothing is culled.
    assert keyframes_to_cull(kfs, points, cam, max_keyframes=9, utility_threshold=1e9) == []
    assert keyframes_to_cull(kfs, points, cam, max_keyframes=8, utility_threshold=0.0) == []
    # Never the fixed first keyframe nor a protected one, however many must go.
    erase_many = keyframes_to_cull(kfs, points, cam, max_keyframes=2, utility_threshold=1e9,
                                   max_erase=7, protected={8})
    assert len(erase_many) == 7 and 0 not in erase_many and 8 not in erase_many
