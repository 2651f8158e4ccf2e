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


def test_vectorised_zssd_search_matches_brute_force() -> None:
    """The batched ZSSD (row im2col matmul + stacked integral image) equals a per-point loop."""
    import cv2

    from ar_tracking.core.slam.patch_search import PATCH, SearchConfig, search
    rng = np.random.default_rng(4)
    img = cv2.GaussianBlur(rng.integers(0, 256, (120, 160)).astype(np.uint8), (0, 0), 1.2)
    img = cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX)
    n = 40
    uv = rng.uniform(12, 100, (n, 2))
    S = PATCH + 2
    templates = (rng.normal(0, 40, (n, S, S)) + 128).astype(np.float32)
    for radius in (4.0, 6.5):
        found, pos, best = search(img, templates, uv, SearchConfig(esm_iterations=0), radius=radius)
        r = int(np.floor(radius))
        for i in range(n):
            T = templates[i, 1:-1, 1:-1].astype(float)
            T -= T.mean()
            x0, y0 = np.rint(uv[i] - (PATCH - 1) / 2.0).astype(int)
            z = {}
            for dy in range(-r, r + 1):
                for dx in range(-r, r + 1):
                    if dx * dx + dy * dy <= radius * radius + 1e-9:
                        w = img[y0 + dy:y0 + dy + PATCH, x0 + dx:x0 + dx + PATCH].astype(float)
                        z[(dx, dy)] = float(((w - w.mean() - T) ** 2).sum()) / PATCH ** 2
            (bx, by), bz = min(z.items(), key=lambda kv: kv[1])
            assert abs(best[i] - bz) < 1e-3 * max(1.0, bz)
            assert np.allclose(pos[i], [x0 + bx + (PATCH - 1) / 2.0, y0 + by + (PATCH - 1) / 2.0])


def test_templates_from_several_keyframes_and_levels_match_per_point_warps() -> None:
    import cv2

    from ar_tracking.core.slam.patch_search import PATCH, warp_templates
    pyrs = {k: build_pyramid(DeskScene(k).render(make_camera(320, 240), *look_at(np.array([0.0, -0.15, 0.5]),
                                                                                     np.zeros(3)), supersample=1))
            for k in (3, 7)}
    rng = np.random.default_rng(2)
    n = 30
    src_kf = rng.choice([3, 7, 9], n)  # keyframe 9 has no pyramid: invalid
    uv = rng.uniform(30, 200, (n, 2))
    A = np.eye(2)[None] * rng.choice([0.5, 1.0, 2.0, 4.0], n)[:, None, None]
    A[:, 0, 1] = rng.normal(0, 0.1, n)
    out, ls, valid = warp_templates(pyrs, src_kf, uv, A, 1)
    S = PATCH + 2
    off = np.arange(S) - (S - 1) / 2.0
    dx, dy = np.meshgrid(off, off)
    for i in range(n):
        if src_kf[i] == 9:
            assert not valid[i]
            continue
        M = A[i] * 2.0 / 2.0 ** ls[i]
        c = (uv[i] + 0.5) / 2.0 ** ls[i] - 0.5
        mx = (c[0] + M[0, 0] * dx + M[0, 1] * dy).astype(np.float32)
        my = (c[1] + M[1, 0] * dx + M[1, 1] * dy).astype(np.float32)
        ref = cv2.remap(pyrs[src_kf[i]][ls[i]], mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        assert np.array_equal(out[i], ref.astype(np.float32))
        h, w = pyrs[src_kf[i]][ls[i]].shape
        assert valid[i] == (mx.min() >= 0 and my.min() >= 0 and mx.max() <= w - 1 and my.max() <= h - 1)
