"""Pyramid and multi-scale Shi-Tomasi corners (Klein & Murray 2009 sec. 3.1), small blurry image."""
from __future__ import annotations

import numpy as np

from ar_tracking.core.slam.camera import level0_to_level
from ar_tracking.core.slam.pyramid import (DEFAULT_MIN_SCORE, build_pyramid, multiscale_corners,
                                           shi_tomasi_score, small_blurry_image)
from slam_synth import DeskScene, look_at, make_camera


def _frame() -> list[np.ndarray]:
    cam = make_camera(320, 240)
    R, t = look_at(np.array([0.0, -0.15, 0.5]), np.zeros(3))
    return build_pyramid(DeskScene(0).render(cam, R, t, supersample=2))


def test_pyramid_levels_halve() -> None:
    pyr = build_pyramid(np.zeros((240, 320), np.uint8))
    assert [p.shape for p in pyr] == [(240, 320), (120, 160), (60, 80), (30, 40), (15, 20)]
    assert all(p.dtype == np.uint8 for p in pyr)


def test_corners_are_corners_at_three_levels_and_sorted() -> None:
    pyr = _frame()
    uv, lv, sc = multiscale_corners(pyr, max_corners=80, return_scores=True)
    assert 30 <= len(uv) <= 80
    assert lv.dtype.kind == 'i' and np.all(lv == 0)
    assert np.all(np.diff(sc) <= 1e-12), 'sorted by decreasing score'
    for level in (0, 1, 2):
        s = shi_tomasi_score(pyr[level])
        p = np.rint(level0_to_level(uv, level)).astype(int)
        # the corner (or a direct neighbour, rounding across levels) is a good ST corner here
        best = np.max([s[np.clip(p[:, 1] + dy, 0, s.shape[0] - 1), np.clip(p[:, 0] + dx, 0, s.shape[1] - 1)]
                       for dy in (-1, 0, 1) for dx in (-1, 0, 1)], axis=0)
        assert np.mean(best >= DEFAULT_MIN_SCORE) > 0.95
    assert np.all((uv >= 8) & (uv <= np.array([320 - 9, 240 - 9])))


def test_exclusion_and_flat_image() -> None:
    pyr = _frame()
    uv, _ = multiscale_corners(pyr, max_corners=50)
    uv2, _ = multiscale_corners(pyr, max_corners=50, exclude_uv=uv[:10], exclude_radius_px=10.0)
    d = np.linalg.norm(uv2[:, None] - uv[None, :10], axis=2)
    assert d.min() > 10.0
    flat = build_pyramid(np.full((240, 320), 128, np.uint8))
    assert len(multiscale_corners(flat)[0]) == 0


def test_small_blurry_image() -> None:
    sbi = small_blurry_image(_frame())
    assert sbi.shape == (15, 20) and sbi.dtype == np.float32
    assert abs(float(sbi.mean())) < 1e-3 and float(sbi.std()) > 1.0
