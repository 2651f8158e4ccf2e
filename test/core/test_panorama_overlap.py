"""EDR correction fitted on the frame's overlap with the map (edr_correction='overlap'), and the
frame outline that limits mapping to the pixels a frame can see.

Synthetic, seeded frames of a textured cylinder (exact truth) from test/panorama_synth.py.
"""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from ar_tracking.core.panorama import (MapConfig, MapperConfig, OverlapExposureConfig, PanoramaMap,
                                       PanoramaMapper, fit_overlap_exposure)
from panorama_synth import K, CylinderWorld, render_all, rot, run_frames, sweep


@pytest.fixture(scope='module')
def world() -> CylinderWorld:
    return CylinderWorld(1)


def _pairs(rng: np.random.Generator, n: int, gain: float, offset: float, noise: float = 1.0):
    frame = rng.uniform(10, 240, n).astype(np.float32)
    return (gain * frame + offset + rng.normal(0, noise, n)).astype(np.float32), frame


def test_fit_recovers_gain_and_offset_despite_misaligned_samples():
    rng = np.random.default_rng(3)
    mapv, frame = _pairs(rng, 2000, 0.74, 6.0)
    bad = rng.choice(2000, 300, replace=False)  # e.g. something bright moved: far from the line
    mapv[bad] += rng.uniform(20, 80, 300)
    gain, offset = fit_overlap_exposure(mapv, frame)
    assert gain == pytest.approx(0.74, abs=0.005) and offset == pytest.approx(6.0, abs=0.5)
    # Least squares without the trim is pulled away: the trim is what recovers the line.
    untrimmed = fit_overlap_exposure(mapv, frame, OverlapExposureConfig(iterations=1))
    assert abs(untrimmed[1] - 6.0) > 1.0 or abs(untrimmed[0] - 0.74) > 0.01
    # Started from a previous frame's fit, one fit fewer reaches the same line.
    warm = fit_overlap_exposure(mapv, frame, initial=(0.75, 5.0))
    assert warm[0] == pytest.approx(gain, abs=0.002) and warm[1] == pytest.approx(offset, abs=0.3)


def test_fit_refuses_what_it_cannot_determine():
    rng = np.random.default_rng(5)
    mapv, frame = _pairs(rng, 30, 1.0, 0.0)
    assert fit_overlap_exposure(mapv, frame) is None  # too few samples
    mapv, frame = _pairs(rng, 500, 1.0, 0.0)
    assert fit_overlap_exposure(mapv, np.full_like(frame, 255.0)) is None  # all clipped
    assert fit_overlap_exposure(mapv, np.full_like(frame, 100.0)) is None  # no spread: gain unknown
    assert fit_overlap_exposure(mapv * 0 + 5.0, frame) is None  # gain 0: not an exposure
    assert fit_overlap_exposure(np.full_like(mapv, np.nan), frame) is None  # nothing mapped


def _mapped_after(world: CylinderWorld, Rs: list[np.ndarray], scale: int = 1) -> PanoramaMap:
    """A map of the frames at Rs; ``scale`` 2: the frames upscaled to 640 x 480 (K with them)."""
    pano = PanoramaMap(MapConfig())
    Ks = np.diag([scale, scale, 1.0]) @ K
    Ks[:2, 2] += (scale - 1) / 2
    for k, R in enumerate(Rs):
        img = world.render(R, rng=np.random.default_rng(k))
        if scale != 1:
            img = cv2.resize(img, (img.shape[1] * scale, img.shape[0] * scale), interpolation=cv2.INTER_LINEAR)
        pano.map_frame(img, Ks, R, k + 1)
    return pano


def test_overlap_pairs_are_the_frame_and_map_values_of_the_overlap(world):
    pano = _mapped_after(world, [rot('y', 0.0)])
    R = rot('y', 10.0)  # a pan: 50 of the frame's 60 degrees are mapped already
    gray = world.render(R, rng=np.random.default_rng(9))
    mapv, frame = pano.overlap_pairs(gray, K, R, step=4)
    seen = pano.overlap_pairs(gray, K, rot('y', 0.0), step=4)[0].size
    assert 0.7 * seen < mapv.size < 0.9 * seen
    # Same world, same exposure: the values agree up to interpolation and noise.
    assert np.median(np.abs(mapv - frame)) < 3.0
    # Under another exposure the pairs carry it, and the fit recovers it.
    brighter = world.render(R, gain=1.3, offset=-5.0, rng=np.random.default_rng(9))
    gain, offset = fit_overlap_exposure(*pano.overlap_pairs(brighter, K, R, step=4))
    assert gain == pytest.approx(1 / 1.3, abs=0.02) and offset == pytest.approx(5.0 / 1.3, abs=1.5)
    # A frame that sees no mapped pixel has nothing to fit on.
    assert pano.overlap_pairs(gray, K, rot('y', 180.0)) is None


@pytest.mark.parametrize('scale', [1, 2])
def test_the_outline_mask_loses_no_pixel_of_the_frame(world, monkeypatch, scale):
    # Mapping tests only the pixels inside the frame's projected outline. With pitch, roll and
    # the wrap (the map's u = 0 column), at 320 x 240 and at 640 x 480 (frame pixels finer than
    # the map's), the masked mapping must write exactly what testing every pixel of the
    # bounding box writes.
    views = [rot('y', 0.0), rot('y', 183.0) @ rot('x', 25.0) @ rot('z', 12.0),
             rot('y', 179.0) @ rot('x', -40.0), rot('y', 90.0) @ rot('z', 45.0), rot('x', 80.0)]
    masked = _mapped_after(world, views, scale)
    # The outline really narrows the search: a rolled, pitched frame fills little of its box.
    box, mask = PanoramaMap().footprint_mask(K, views[1], (240, 320))
    assert 0.3 < mask.mean() < 0.9

    def everything(self, K_, R_, size):
        box, _ = self._footprint_of(K_, R_, size)
        return box, np.ones((max(box[3] - box[2], 0), box[1] - box[0]), bool)

    monkeypatch.setattr(PanoramaMap, 'footprint_mask', everything)
    full = _mapped_after(world, views, scale)
    assert np.array_equal(masked.mapped, full.mapped)
    assert np.array_equal(masked.contribution, full.contribution)
    np.testing.assert_array_equal(masked.gray, full.gray)


def test_overlap_correction_follows_gain_and_offset_changes(world):
    # Exposure (gain) and veiling glare (offset) change during a 400-degree turn. The keypoint
    # offset of sec. 4.1 fits one offset at the keypoints' mean brightness and leaves steps of
    # (g - 1) * (I - mean) elsewhere; the overlap fit follows both terms.
    Rs = sweep(200, 2.0, seed=5)
    gains = np.where(np.arange(200) < 70, 1.0, np.where(np.arange(200) < 140, 1.3, 0.8))
    offsets = np.where(np.arange(200) < 100, 0.0, 12.0)
    frames = render_all(world, Rs, gains, offsets)  # once: the same frames for the three maps
    steps = {}
    for name, cfg in (('overlap', MapperConfig(edr_correction='overlap')),
                      ('offset', MapperConfig(edr_correction='offset')),
                      ('8bit', MapperConfig(map=MapConfig(edr=False)))):
        mapper = PanoramaMapper(cfg)
        res = run_frames(mapper, frames)
        if name != '8bit':
            assert all(r.R_pano_cam is not None for r in res)
        steps[name] = mapper.seam_error(flat_max=np.inf)['step']
    assert steps['overlap'] < 0.5 * steps['offset'] < 0.5 * steps['8bit']
