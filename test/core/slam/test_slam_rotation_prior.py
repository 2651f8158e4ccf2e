"""Full-frame ESM rotation estimate on the small blurry image (Klein & Murray 2009 sec. 4)."""
from __future__ import annotations

import time

import numpy as np

from ar_tracking.core.slam.pyramid import build_pyramid, small_blurry_image
from ar_tracking.core.rotations import trace_angle
from ar_tracking.core.slam.rotation_prior import estimate_rotation, rotation_homography
from slam_synth import DeskScene, look_at, make_camera, rotvec


def test_recovers_rotation_and_is_fast() -> None:
    cam = make_camera(640, 480)
    sc = DeskScene(1)
    R, t = look_at(np.array([0.0, -0.15, 0.5]), np.zeros(3))
    dR = rotvec(np.array([0.03, -0.05, 0.02]))
    a = small_blurry_image(build_pyramid(sc.render(cam, R, t)))
    b = small_blurry_image(build_pyramid(sc.render(cam, dR @ R, dR @ t)))
    c4 = cam.at_level(4)
    assert a.shape == (30, 40)
    est = estimate_rotation(a, b, c4)
    assert np.degrees(trace_angle(est.R_cur_prev @ dR.T)) < 0.6
    assert est.residual < 0.5 * est.residual0
    # with the true rotation as a pre-warp nothing is left to explain
    est2 = estimate_rotation(a, b, c4, H0=rotation_homography(c4, dR))
    assert np.degrees(trace_angle(est2.R_cur_prev)) < 0.6
    t0 = time.perf_counter()
    for _ in range(20):
        estimate_rotation(a, b, c4, iterations=5)
    assert (time.perf_counter() - t0) / 20 < 0.01  # ~1 ms alone; loose for a shared machine
