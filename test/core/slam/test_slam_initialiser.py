"""Two-stage homography initialisation (Klein & Murray 2009 sec. 5.1)."""
from __future__ import annotations

import numpy as np

from ar_tracking.core.slam.initialiser import WAIT_ROTATION_MSG, Initialiser, refine_homography
from ar_tracking.core.slam.pyramid import build_pyramid, small_blurry_image
from slam_synth import DeskScene, look_at, make_camera, sideways_then_6dof


def _run(poses, cam, scene):
    ini = Initialiser(cam)
    out = []
    for i, (R, t) in enumerate(poses):
        pyr = build_pyramid(scene.render(cam, R, t, supersample=2))
        out.append(ini.process(pyr, small_blurry_image(pyr), i))
        if out[-1].state == 'done':
            break
    return out


def test_homography_refinement_recovers_h() -> None:
    rng = np.random.default_rng(0)
    rays = np.column_stack([rng.uniform(-0.5, 0.5, (60, 2)), np.ones(60)])
    H = np.array([[1.02, 0.01, 0.03], [-0.02, 0.99, -0.01], [0.02, -0.01, 1.0]])
    H /= np.cbrt(np.linalg.det(H))
    K = make_camera().K
    Y = rays @ H.T
    uv = np.column_stack([K[0, 0] * Y[:, 0] / Y[:, 2] + K[0, 2], K[1, 1] * Y[:, 1] / Y[:, 2] + K[1, 2]])
    uv[:5] += 30.0  # outliers
    H2, inl = refine_homography(np.eye(3), rays, uv, K, 2.0, iterations=10)
    assert np.allclose(H2 / H2[2, 2], H / H[2, 2], atol=2e-3)
    assert not inl[:5].any() and inl[5:].all()


def test_sideways_motion_initialises() -> None:
    cam = make_camera(320, 240)
    poses = sideways_then_6dof(n_side=30, n_free=5)
    out = _run(poses, cam, DeskScene(0))
    assert out[-1].state == 'done', [o.message for o in out[-3:]]
    assert all(o.state != 'waiting' for o in out)
    st = out[-1]
    R0, t0 = poses[0]
    R1, t1 = poses[len(out) - 1]
    Rrel = R1 @ R0.T
    trel = t1 - Rrel @ t0
    ang = np.degrees(np.arccos(np.clip((np.trace(st.R_c_w @ Rrel.T) - 1) / 2, -1, 1)))
    assert ang < 3.0
    cosang = st.t_c_w @ trel / np.linalg.norm(st.t_c_w) / np.linalg.norm(trel)
    assert cosang > 0.95
    assert len(st.xyz) > 30 and st.kf0.fixed and st.kf1 is not None
    # scale: the plane at distance ~1 from the first keyframe -> median point depth ~1
    assert 0.7 < np.median(st.xyz[:, 2]) < 1.6


def test_pure_rotation_keeps_waiting() -> None:
    cam = make_camera(320, 240)
    eye = np.array([0.0, -0.15, 0.5])
    poses = [look_at(eye, np.array([0.12 * np.sin(a), 0.0, 0.0])) for a in np.linspace(0, 1.2, 22)]
    out = _run(poses, cam, DeskScene(0))
    assert all(o.state != 'done' for o in out)
    assert out[-1].state == 'waiting' and out[-1].message == WAIT_ROTATION_MSG
