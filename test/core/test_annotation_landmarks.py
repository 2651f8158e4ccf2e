"""Landmarks of a source panorama: their selection and their part in the alignment."""
from __future__ import annotations

import numpy as np
import pytest

from annotation_synth import (GEO, M_ENU_PANO, ROWS, UP, displaced_spot_case, make_case,
                              rotated_by, texture)
from ar_tracking.core.annotations.landmarks import LandmarkConfig, select_landmarks
from ar_tracking.core.annotations.matching import Candidate, MatchConfig, ReDetector


def _source_map(seed: int = 5) -> tuple[np.ndarray, np.ndarray]:
    gray = texture(seed)
    mapped = np.zeros(gray.shape, bool)
    mapped[ROWS[0]:ROWS[1]] = True
    return np.where(mapped, gray, 0).astype(np.float32), mapped


def test_select_landmarks_skips_repeated_texture_the_ground_and_neighbours():
    gray, mapped = _source_map()
    # A facade: columns 600..1000 repeat one 14 px wide strip (every window a look-alike).
    strip = gray[:, 600:614].copy()
    for x in range(600, 1000, 14):
        w = min(14, 1000 - x)
        gray[:, x:x + w] = strip[:, :w]
    # Asked for many, every unique corner is taken, none on the repeated facade (a margin of
    # the search radius at its ends); the facade's corners themselves are there (they are
    # taken when self-similarity is allowed).
    for limit, on_facade in ((LandmarkConfig.max_self_similarity, 0), (1.01, 50)):
        many = select_landmarks(gray, mapped, GEO, up=UP, config=LandmarkConfig(count=300, max_self_similarity=limit))
        u = np.array([lm.u for lm in many])
        n_facade = int(np.sum((u > 600 + 48) & (u < 1000 - 48 - 16)))
        assert (n_facade == 0) if on_facade == 0 else (n_facade >= on_facade)
    avoid = GEO.unproject(np.array([1500.0]), np.array([200.0])).reshape(1, 3)
    cfg = LandmarkConfig(count=30, support_count=0)
    lms = select_landmarks(gray, mapped, GEO, up=UP, config=cfg, avoid=avoid)
    assert len(lms) == 30
    u = np.array([lm.u for lm in lms])
    v = np.array([lm.v for lm in lms])
    # Above the horizon only: the map's middle row looks level with this up direction.
    assert np.all([lm.direction @ UP > np.sin(np.radians(cfg.min_elevation_deg)) - 1e-9 for lm in lms])
    assert np.all(v < GEO.height / 2)
    # Spread: no two closer than half the mean spacing, none at the annotation.
    sep = GEO.width / (2 * cfg.count)
    du = np.abs((u[:, None] - u[None] + 1024) % 2048 - 1024)
    d = np.hypot(du, v[:, None] - v[None]) + np.eye(len(u)) * 1e9
    assert d.min() >= sep
    assert np.min(np.hypot(np.abs((u - 1500 + 1024) % 2048 - 1024), v - 200)) >= sep
    # The least self-similar come first, all below the limit; patches are the map's.
    s = [lm.self_similarity for lm in lms]
    assert s == sorted(s) and s[-1] <= cfg.max_self_similarity
    # Without an up direction the lower half of the map is used too.
    both = select_landmarks(gray, mapped, GEO, up=None, config=cfg)
    assert any(lm.v > GEO.height / 2 + 20 for lm in both)


def test_support_landmarks_surround_each_anchor_and_skip_its_look_alikes():
    gray, mapped = _source_map()
    # Anchor 0 on plain texture, anchor 1 on a facade repeating one 14 px strip (columns
    # 600..1000): every corner there has look-alikes within the search radius.
    strip = gray[:, 600:614].copy()
    for x in range(600, 1000, 14):
        gray[:, x:x + 14] = strip[:, :14]
    anchors_uv = np.array([[1500.0, 300.0], [800.0, 200.0]])
    avoid = GEO.unproject(anchors_uv[:, 0], anchors_uv[:, 1])
    cfg = LandmarkConfig(count=20)
    lms = select_landmarks(gray, mapped, GEO, up=UP, config=cfg, avoid=avoid)
    general, support = lms[:cfg.count], lms[cfg.count:]
    assert len(general) == cfg.count and len(support) == cfg.support_count  # anchor 0's only
    u = np.array([lm.u for lm in support])
    v = np.array([lm.v for lm in support])
    du = np.abs((u - 1500.0 + 1024) % 2048 - 1024)
    assert np.all(du <= cfg.support_u_px) and np.all(np.abs(v - 300.0) <= cfg.support_v_px)
    assert np.all(np.hypot(du, v - 300.0) >= cfg.support_exclude_px)
    # Below the horizon too (the anchor is), apart from each other and from the others.
    assert np.any(v > GEO.height / 2)
    uu = np.array([lm.u for lm in lms])
    vv = np.array([lm.v for lm in lms])
    d = np.hypot(np.abs((uu[:, None] - uu[None] + 1024) % 2048 - 1024), vv[:, None] - vv[None])
    assert (d + np.eye(len(lms)) * 1e9)[cfg.count:].min() >= cfg.support_separation_px
    assert max(lm.self_similarity for lm in support) <= cfg.max_self_similarity
    alone = select_landmarks(gray, mapped, GEO, up=UP, config=LandmarkConfig(count=20, support_count=0), avoid=avoid)
    assert [(lm.u, lm.v) for lm in alone] == [(lm.u, lm.v) for lm in general]


def test_select_landmarks_on_an_untextured_map_finds_none():
    gray = np.full((GEO.height, GEO.width), 90.0, np.float32)
    mapped = np.ones(gray.shape, bool)
    assert select_landmarks(gray, mapped, GEO, up=UP) == []
    assert select_landmarks(*_source_map(), GEO, config=LandmarkConfig(count=0)) == []


def test_landmarks_are_aligned_but_neither_placed_nor_scored():
    case = make_case(seed=7, n=8)
    flags = [False] * 4 + [True] * 4
    # Group 'a': its annotations match with 0.6, its landmarks with 0.99; group 'b' (the same
    # patches, another panorama) matches its annotations with 0.8: b scores best.
    patches = case.patches * 2
    dirs = np.vstack([case.dirs, case.dirs])
    det = ReDetector(patches, dirs, ['a'] * 8 + ['b'] * 8, MatchConfig(sensor_prior=False),
                     landmark=flags * 2)
    for i in range(16):
        u, v = case.truth_uv[i % 8]
        ncc = 0.99 if flags[i % 8] else (0.6 if i < 8 else 0.8)
        det.candidates[i].items = [Candidate(float(u), float(v), ncc, ncc)]
    det.dirty = True
    group, al = det.result()
    assert group == 'b'
    assert sorted(p.index for p in al.placements) == [8, 9, 10, 11]
    assert sorted(p.index for p in al.landmarks) == [12, 13, 14, 15]
    assert all(p.status == 'matched' for p in al.placements + al.landmarks)


def _displaced_spot(seed: int, matched: int, inferred: int, landmarks: int):
    """A browsing spot 1.3 m from the authoring one; anchors and landmarks 30-70 m away; the
    first ``matched`` annotations and every landmark have their true candidate."""
    rng = np.random.default_rng(seed)
    n = matched + inferred + landmarks
    depths = rng.uniform(30.0, 70.0, n)
    case, truth, uv = displaced_spot_case(seed, np.array([1.1, 0.7, 0.0]), depths)
    order = rng.permutation(n)  # annotations and landmarks all around the circle
    case.patches = [case.patches[k] for k in order]
    case.dirs, truth, uv = case.dirs[order], truth[order], uv[order]
    n_ann = matched + inferred
    flags = [False] * n_ann + [True] * landmarks
    R_enu_source = M_ENU_PANO @ rotated_by(case.R_target_source, 1.5, axis=-UP)  # compass 1.5 deg off
    det = ReDetector(case.patches, case.dirs, ['p'] * n, MatchConfig(), R_enu_source=[R_enu_source] * n,
                     landmark=flags)
    det.set_orientation(M_ENU_PANO)
    for i in list(range(matched)) + list(range(n_ann, n)):
        det.candidates[i].items = [Candidate(float(uv[i, 0]), float(uv[i, 1]), 0.85, 0.85)]
    det.dirty = True
    return det, truth


def _worst_inferred_error_deg(det: ReDetector, truth: np.ndarray) -> float:
    _, al = det.result()
    errs = [np.degrees(np.arccos(np.clip(p.direction @ truth[p.index], -1, 1)))
            for p in al.placements if p.status == 'inferred']
    assert errs
    return float(max(errs))


@pytest.mark.parametrize('seed', [11, 12, 15])
def test_landmarks_place_the_inferred_annotations_of_a_displaced_spot(seed):
    # Two annotations matched, two not: alone, their parallax sets the heading and the two
    # others land off (the model needs three matches); with 16 landmark matches the rotation
    # and the parallax are fitted around the whole circle (what remains is the anchors' own
    # depth differing from the common one: 30-70 m here).
    without, truth = _displaced_spot(seed, 2, 2, 0)
    with_lm, truth_lm = _displaced_spot(seed, 2, 2, 16)
    err_without = _worst_inferred_error_deg(without, truth)
    err_with = _worst_inferred_error_deg(with_lm, truth_lm)
    assert err_without > 1.0 and err_with < 0.5


def test_parallax_gate_rejects_a_look_alike_the_wide_gate_keeps():
    # With many landmark matches the leave-one-out predictions are good to a pixel; a
    # look-alike 14 px (one facade repetition) from the truth with a far better NCC (0.95 vs
    # 0.6) wins inside the 25 px placement gate, not inside the fitted gate.
    placed = {}
    for sigmas in (0.0, 3.0):
        det, truth = _displaced_spot(21, 4, 0, 16)
        det.config = MatchConfig(parallax_gate_sigmas=sigmas)
        c = det.candidates[0].items[0]
        det.candidates[0].items = [Candidate(c.u - 14.0, c.v, 0.95, 0.95), Candidate(c.u, c.v, 0.6, 0.6)]
        det.dirty = True
        _, al = det.result()
        p0 = next(p for p in al.placements if p.index == 0)
        placed[sigmas] = (p0.u - c.u, al.parallax_gate_px)
    assert placed[0.0][0] == pytest.approx(-14.0) and np.isnan(placed[0.0][1])
    assert placed[3.0][0] == pytest.approx(0.0) and placed[3.0][1] < 14.0


def _sector_spot(t_enu: np.ndarray, supports: bool) -> tuple[ReDetector, np.ndarray]:
    """An anchor (index 0, unmatched) 70 m away with no other match within 60 deg; three
    matched anchors and six landmarks 70-75 m away on one side, ten landmarks 32 m away on the
    other; with ``supports``, four matched landmarks around anchor 0 at its depth."""
    # (u, v in the source map, depth m, landmark, matched)
    points = [(1000, 250, 70, False, False), (1900, 200, 70, False, True), (200, 260, 70, False, True),
              (420, 230, 70, False, True)]
    points += [(u, 180, 32, True, True) for u in np.linspace(1350, 1800, 10)]
    points += [(u, 170, 75, True, True) for u in np.linspace(60, 560, 6)]
    if supports:
        points += [(1000 + du, 250 + dv, 70, True, True) for du, dv in ((-30, -8), (-14, 12), (16, -10), (33, 6))]
    u, v, depth = (np.array([p[k] for p in points], float) for k in range(3))
    R = rotated_by(np.eye(3), np.degrees(300 / GEO.f), axis=(0.0, 1.0, 0.0))
    dirs = GEO.unproject(u, v)
    seen = (dirs @ R.T) @ M_ENU_PANO.T * depth[:, None] - t_enu
    truth = (seen / np.linalg.norm(seen, axis=1, keepdims=True)) @ M_ENU_PANO
    tu, tv = GEO.project(truth)
    n = len(points)
    R_enu_source = M_ENU_PANO @ rotated_by(R, 1.5, axis=-UP)  # compass 1.5 deg off
    det = ReDetector([np.zeros((16, 16), np.uint8)] * n, dirs, ['p'] * n, MatchConfig(),
                     R_enu_source=[R_enu_source] * n, landmark=[p[3] for p in points])
    det.set_orientation(M_ENU_PANO)
    for i, p in enumerate(points):
        if p[4]:
            det.candidates[i].items = [Candidate(float(tu[i]), float(tv[i]), 0.85, 0.85)]
    det.dirty = True
    return det, truth


def test_support_landmarks_pin_the_parallax_fit_at_an_unmatched_anchor():
    # The common-depth sinusoid fitted on matches 32 m away on one side and 70-75 m on the
    # other is an extrapolation at the unmatched anchor, more than a degree off; four support
    # landmarks around it bring it within half a degree.
    t = np.array([0.5, 1.2, 0.0])
    errs = []
    for supports in (False, True):
        det, truth = _sector_spot(t, supports)
        _, al = det.result()
        p = al.placements[0]
        assert p.index == 0 and p.status == 'inferred'
        errs.append(float(np.degrees(np.arccos(np.clip(p.direction @ truth[0], -1, 1)))))
    assert errs[0] > 1.0 and errs[1] < 0.5
