"""Seam measure and EDR offset smoothing (Langlotz 2011 sec. 4.1; issue #3 seam target).

The seam error is the level step between frame contributions, per boundary segment, on flat
surroundings and freed of estimation noise (map.seam_error); the naive pixel-wise mean
absolute difference across boundaries (``pixelwise``) is inflated by texture.
"""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from ar_tracking.core.panorama import ExposureConfig, ExposureFilter, MapperConfig, PanoramaMapper, seam_error
from ar_tracking.core.panorama.exposure import OFFSET_EXPOSURE
from panorama_synth import CylinderWorld, render_all, run_frames, sweep

STRIP = 24


def textured_map(seed: int, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A 256 x (24 * len(offsets)) grey map: smooth shading, sharp-edged blocks (texture; no
    block edge lies exactly on a boundary, which would look like a step, map.seam_error), sensor
    noise; vertical strips are the contributions 1, 2, ... of frames, strip k shifted
    by ``offsets[k]`` (an exposure step at each strip boundary of offsets[k] - offsets[k-1])."""
    rng = np.random.default_rng(seed)
    h, w = 256, STRIP * offsets.size
    shade = cv2.GaussianBlur(rng.normal(0, 1, (h, w)).astype(np.float32), (0, 0), 12)
    img = 100.0 + 20.0 * shade / shade.std()
    placed = 0
    while placed < 60:  # blocks across the boundaries, their vertical edges not on one
        y, x = int(rng.integers(0, h - 30)), int(rng.integers(0, w - 30))
        bh, bw = int(rng.integers(6, 30)), int(rng.integers(6, 30))
        if min(x % STRIP, STRIP - x % STRIP, (x + bw) % STRIP, STRIP - (x + bw) % STRIP) <= 2:
            continue
        img[y:y + bh, x:x + bw] += rng.uniform(-50, 50)
        placed += 1
    strip = np.arange(w) // STRIP
    img = img + offsets[strip][None, :] + rng.normal(0, 1.0, (h, w))
    contrib = np.broadcast_to(strip + 1, (h, w)).copy()
    # Unmapped columns at the end: the map wraps in u, and this one is no 360-degree map.
    img[:, -2:] = np.nan
    contrib[:, -2:] = -1
    return img, contrib


def test_step_measure_returns_the_offset_and_pixelwise_is_inflated_by_texture():
    n = 20
    alt = np.where(np.arange(n) % 2 == 1, 6.0, 0.0)  # every boundary steps by 6 levels
    stepped = seam_error(*textured_map(1, alt))
    flat = seam_error(*textured_map(1, np.zeros(n)))
    assert stepped['step'] == pytest.approx(6.0, abs=0.5)
    assert stepped['mean_step'] == pytest.approx(6.0, abs=0.5)
    assert flat['step'] < 0.4 and flat['mean_step'] < 0.3
    assert flat['boundaries'] == n - 1 and flat['kappa'] >= 1.0
    # The naive figure sees texture as seams: well above 0 without any step, above 6 with it.
    assert flat['pixelwise'] > 1.0 > 10 * flat['step']
    assert stepped['pixelwise'] > stepped['step']


def test_structure_beside_the_boundary_is_not_a_step():
    # A bright band of contrast 60 starting one pixel beside each boundary (the same scene
    # edge, a pixel off between two contributions: misregistration of a structure at the
    # seam), on alternate sides, along half of each boundary: the pixel-wise mean jumps, the
    # step measure (from the flat pairs of the other half) does not.
    n = 20
    img, contrib = textured_map(2, np.zeros(n))
    plain = seam_error(img, contrib)
    for k in range(1, n):
        x = k * STRIP
        if k % 2:
            img[:128, x - 4:x - 1] += 60.0  # left of the boundary, ending at a'
        else:
            img[:128, x + 1:x + 4] += 60.0  # right of it, from b'
        img[:128, x - 1 if k % 2 else x] += 30.0  # half of the edge's blur on a or b
    edged = seam_error(img, contrib)
    assert edged['pixelwise'] > plain['pixelwise'] + 5.0
    assert edged['step'] < plain['step'] + 0.3


def test_step_scales_with_the_offset_and_respects_min_gap():
    n = 16
    for size in (2.0, 10.0):
        res = seam_error(*textured_map(3, np.where(np.arange(n) % 2 == 1, size, 0.0)))
        assert res['step'] == pytest.approx(size, rel=0.15)
    img, contrib = textured_map(3, np.where(np.arange(n) % 2 == 1, 10.0, 0.0))
    assert seam_error(img, contrib, min_gap=2)['pairs'] == 0  # all boundaries are consecutive
    nan_map = np.full((16, 16), np.nan)
    assert math.isnan(seam_error(nan_map, np.full((16, 16), -1))['step'])


def test_offset_filter_removes_per_frame_noise_and_follows_jumps():
    rng = np.random.default_rng(4)
    truth = np.where(np.arange(300) < 150, 0.0, -30.0)  # an exposure jump of 30 levels
    z = truth + rng.normal(0, 0.4, truth.size)
    smooth = ExposureFilter(OFFSET_EXPOSURE)
    paper = ExposureFilter(ExposureConfig(**{**OFFSET_EXPOSURE.__dict__, 'smooth': False}))
    est = np.array([smooth.update(v, 0.4, 1 / 30) for v in z])
    raw = np.array([paper.update(v, 0.4, 1 / 30) for v in z])
    np.testing.assert_allclose(raw, z)  # the paper's version: each frame's own offset
    steady = np.r_[20:149, 170:299]  # frame-to-frame changes away from the jump
    assert np.std(np.diff(est)[steady]) < 0.4 * np.std(np.diff(z)[steady])
    assert abs(est[150] - truth[150]) < 2.0 and smooth.jumps >= 1


def test_smoothed_offset_leaves_smaller_seams_than_the_paper_version():
    # A 400-degree turn with an exposure jump half-way. The paper's per-frame offsets differ by
    # their estimation noise from frame to frame, a small step at every boundary; smoothed, the
    # jump is still followed at once. (The noise texture of the synthetic world is flat only
    # where it is clipped, so the steps are taken on all pixels here: flat_max=inf.)
    world = CylinderWorld(1)
    Rs = sweep(200, 2.0, seed=5)
    gains = [1.0 if k < 100 else 1.35 for k in range(200)]
    frames = render_all(world, Rs, gains)  # once: the same frames for both versions
    steps, diffs, offs = {}, {}, {}
    for smooth in (True, False):
        cfg = MapperConfig(edr_correction='offset',
                           offset_exposure=ExposureConfig(**{**OFFSET_EXPOSURE.__dict__, 'smooth': smooth}))
        mapper = PanoramaMapper(cfg)
        o = []
        for res in run_frames(mapper, frames):
            assert res.R_pano_cam is not None
            o.append(res.intensity_offset)
        steps[smooth] = mapper.seam_error(flat_max=np.inf)['step']  # dominated by the jump's seam
        diffs[smooth] = float(np.std(np.diff(o)[np.r_[5:98, 110:198]]))
        offs[smooth] = np.array(o)
    assert diffs[True] < 0.5 * diffs[False]
    assert steps[True] < 1.05 * steps[False]
    assert abs(offs[True][101] - offs[False][101]) < 3.0  # the jump is not smoothed away
    assert np.mean(offs[True][120:]) < -20
