"""The parallax model's elevation term and the matched-label agreement rule
(core/annotations/parallax.py: ParallaxModel.elevation; MatchConfig.parallax_elevation and
matched_agreement_px)."""
from __future__ import annotations

import numpy as np
import pytest

from annotation_synth import GEO, M_ENU_PANO, UP, displaced_spot_case, rotated_by
from ar_tracking.core.annotations.matching import Candidate, MatchConfig, ReDetector
from ar_tracking.core.annotations.parallax import _horizontal_axes, fit_parallax, prediction_sigma


def _facades(seed: int, n: int = 40, depth: float = 15.0):
    """Anchors around a spot at ``depth`` m, 2 m below to 8 m above the eye, seen again from a
    spot displaced 1.4 m: (up, directions from the first spot, from the second)."""
    rng = np.random.default_rng(seed)
    up = np.array([0.05, -1.0, 0.02])
    up /= np.linalg.norm(up)
    e1, e2 = _horizontal_axes(up)
    th = rng.uniform(-np.pi, np.pi, n)
    P = depth * (np.cos(th)[:, None] * e1 + np.sin(th)[:, None] * e2) + rng.uniform(-2.0, 8.0, n)[:, None] * up
    t = 1.2 * e1 - 0.7 * e2
    first = P / np.linalg.norm(P, axis=1, keepdims=True)
    second = (P - t) / np.linalg.norm(P - t, axis=1, keepdims=True)
    return up, first, second


def _angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=1), -1.0, 1.0)))


def test_elevation_term_follows_the_displacement_without_a_new_parameter():
    up, first, second = _facades(3)
    plain = fit_parallax(first, second, up, sigma_match=0.001, sigma_parallax=1.0)
    model = fit_parallax(first, second, up, sigma_match=0.001, sigma_parallax=1.0, elevation=True)
    assert (model.a, model.b, model.c) == (plain.a, plain.b, plain.c)  # fitted on the headings alone
    assert _angles_deg(first, second).max() > 4.0
    # The heading model alone leaves the elevated anchors' rise and fall (over a degree); the
    # quadrature term takes it to the small-angle remainder.
    assert _angles_deg(plain.apply(first), second).max() > 1.5
    assert _angles_deg(model.apply(first), second).max() < 0.5
    # elevation_shift is the change apply() makes (small-angle), 0 at eye level and without the term.
    rise = np.arcsin(np.clip(model.apply(first) @ up, -1, 1)) - np.arcsin(np.clip(plain.apply(first) @ up, -1, 1))
    assert np.allclose(model.elevation_shift(first), rise, atol=np.radians(0.1))
    level = first - np.outer(first @ up, up)
    assert np.allclose(model.elevation_shift(level), 0.0, atol=1e-12)
    assert not plain.elevation_shift(first).any()
    # The scaled model (a depth ratio) keeps the term.
    assert model.scaled(0.5).elevation


def test_prediction_sigma_adds_the_elevation_terms_uncertainty():
    up, first, second = _facades(4)
    sector = np.abs(np.degrees(np.arctan2(first @ _horizontal_axes(up)[1], first @ _horizontal_axes(up)[0]))) < 40
    assert 3 <= sector.sum() < len(first)
    plain = fit_parallax(first[sector], second[sector], up)
    model = fit_parallax(first[sector], second[sector], up, elevation=True)
    s0 = prediction_sigma(plain, first[sector], second[sector], first)
    s1 = prediction_sigma(model, first[sector], second[sector], first)
    assert np.all(s1 >= s0) and np.any(s1 > 1.2 * s0)
    level = first - np.outer(first @ up, up)
    assert np.allclose(prediction_sigma(model, first[sector], second[sector], level),
                       prediction_sigma(plain, first[sector], second[sector], level))


@pytest.mark.parametrize('offset_deg, shown', [(0.6, True), (1.6, False)])
def test_matched_label_far_from_its_prediction_is_approximate(offset_deg: float, shown: bool):
    # 16 anchors at 30 m seen from 0.5 m away, every other one a landmark (the local tests need
    # their density); annotation `odd` matched `offset_deg` from its true position (a look-alike
    # one repetition away), every other one where it is.
    n = 16
    case, truth, uv = displaced_spot_case(50, np.array([0.4, -0.3, 0.0]), np.full(n, 30.0))
    odd = 5

    def label(agreement_px: float):
        det = ReDetector(case.patches, case.dirs, ['p'] * n, MatchConfig(matched_agreement_px=agreement_px),
                         R_enu_source=[M_ENU_PANO @ rotated_by(case.R_target_source, 1.0, axis=-UP)] * n,
                         landmark=list(np.arange(n) % 2 == 0))
        det.set_orientation(M_ENU_PANO)
        for i in range(n):
            du = np.radians(offset_deg) * GEO.f if i == odd else 0.0
            det.candidates[i].items = [Candidate(float(uv[i, 0] + du), float(uv[i, 1]), 0.9, 0.9)]
        det.dirty = True
        _, al = det.result()
        assert al.supported
        return next(p for p in al.placements if p.index == odd)

    p = label(np.radians(1.2) * GEO.f)
    assert p.status == 'matched' and p.predicted is not None
    u, v = GEO.project(p.predicted)
    assert float(GEO.map_distance(p.u, p.v, u, v)) == pytest.approx(np.radians(offset_deg) * GEO.f, abs=1.5)
    assert p.supported is shown
    assert label(0.0).supported  # the rule off
