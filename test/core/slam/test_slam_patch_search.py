"""Warped 8x8 patch search with ZSSD and ESM sub-pixel refinement (Klein & Murray 2009 sec. 4)."""
from __future__ import annotations

import numpy as np

from ar_tracking.core.slam.patch_search import (affine_from_poses, choose_source_level, search_points)
from ar_tracking.core.slam.pyramid import build_pyramid, multiscale_corners
from slam_synth import DeskScene, look_at, make_camera


def _setup(far: bool = False):
    sc = DeskScene(0)
    cam = make_camera(320, 240)
    Rs, ts = look_at(np.array([0.0, -0.15, 0.5]), np.zeros(3))
    eye = np.array([0.06, -0.3, 0.9]) if far else np.array([0.06, -0.12, 0.45])
    Rc, tc = look_at(eye, np.array([0.03, 0.02, 0.0]))
    ps = build_pyramid(sc.render(cam, Rs, ts, supersample=2))
    pc = build_pyramid(sc.render(cam, Rc, tc, supersample=2))
    uv, _ = multiscale_corners(ps, max_corners=120)
    X = sc.points_at(cam, Rs, ts, uv)
    uvt, _ = cam.project(X @ Rc.T + tc)
    ok = cam.in_image(uvt, 20) & np.isfinite(X).all(1)
    return cam, ps, pc, Rs, ts, Rc, tc, uv[ok], X[ok], uvt[ok]


def test_finds_points_subpixel() -> None:
    cam, ps, pc, Rs, ts, Rc, tc, uv, X, uvt = _setup()
    n = len(X)
    assert n > 30
    pred = uvt + np.random.default_rng(1).normal(0, 2.5, (n, 2))
    res = search_points(pc, cam, Rc, tc, X, {0: ps}, np.zeros(n, int), uv, np.repeat(Rs[None], n, 0),
                        np.repeat(ts[None], n, 0), uv_pred0=pred)
    assert res.level == 1
    assert res.found.mean() > 0.85
    err = np.linalg.norm(res.uv0[res.found] - uvt[res.found], axis=1)
    assert np.median(err) < 0.5 and np.percentile(err, 90) < 1.5


def test_source_level_follows_scale() -> None:
    cam, ps, pc, Rs, ts, Rc, tc, uv, X, uvt = _setup(far=True)
    n = len(X)
    A = affine_from_poses(X, cam, Rc, tc, np.repeat(Rs[None], n, 0), np.repeat(ts[None], n, 0))
    # farther camera: one current L1 pixel covers ~2 * 1.8 source px -> source level 2 mostly
    assert np.median(choose_source_level(A, 1, 5)) == 2
    res = search_points(pc, cam, Rc, tc, X, {0: ps}, np.zeros(n, int), uv, np.repeat(Rs[None], n, 0),
                        np.repeat(ts[None], n, 0))
    assert res.found.mean() > 0.6
    assert np.median(np.linalg.norm(res.uv0[res.found] - uvt[res.found], axis=1)) < 1.0


def test_rejects_wrong_image_and_coarse_level() -> None:
    cam, ps, pc, Rs, ts, Rc, tc, uv, X, uvt = _setup()
    n = len(X)
    args = ({0: ps}, np.zeros(n, int), uv, np.repeat(Rs[None], n, 0), np.repeat(ts[None], n, 0))
    flat = build_pyramid(np.full((240, 320), 100, np.uint8))
    assert not search_points(flat, cam, Rc, tc, X, *args).found.any()
    other = build_pyramid(DeskScene(5).render(cam, Rc, tc, supersample=2))
    assert search_points(other, cam, Rc, tc, X, *args).found.mean() < 0.3
    res2 = search_points(pc, cam, Rc, tc, X, *args, search_level=2, coarse=True)
    assert res2.level == 2 and res2.found.mean() > 0.6
    assert np.median(np.linalg.norm(res2.uv0[res2.found] - uvt[res2.found], axis=1)) < 2.0
