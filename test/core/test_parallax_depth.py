"""The annotations' own depth ratio on top of the common-depth parallax model
(core/annotations/parallax.py: fit_depth_scale; MatchConfig.parallax_scale_sigma).."""
from __future__ import annotations

import numpy as np
import pytest

from annotation_synth import M_ENU_PANO, UP, displaced_spot_case, rotated_by
from ar_tracking.core.annotations.matching import Candidate, MatchConfig, ReDetector
from ar_tracking.core.annotations.parallax import (_horizontal_axes, depth_scale_sigma, fit_depth_scale, fit_parallax,
                                                   heading_residuals, prediction_sigma)


def test_horizontal_axes_equal_numpys_cross_products():
    rng = np.random.default_rng(5)
    for up in [*rng.normal(size=(200, 3)), np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])]:
        up = up / np.linalg.norm(up)
        helper = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
        e1 = np.cross(up, helper)
        e1 /= np.linalg.norm(e1)
        got1, got2 = _horizontal_axes(up)
        assert np.array_equal(got1, e1) and np.array_equal(got2, np.cross(up, e1))


def _near_and_far(seed: int, t: np.ndarray, n: int, near: float, far: float):
    """n points around the panorama, every third at ``far`` (the mask), the others at ``near``."""
    is_far = np.arange(n) % 3 == 2
    case, truth, uv = displaced_spot_case(seed, t, np.where(is_far, far, near))
    return case, truth, uv, case.dirs @ case.R_target_source.T, is_far


def test_depth_scale_is_the_ratio_of_the_depths():
    # The model fitted on 12 points at 20 m; 6 anchors at 40 m turn half as far.
    t = np.array([1.2, -0.7, 0.0])
    _, truth, _, predicted, far = _near_and_far(40, t, 18, 20.0, 40.0)
    model = fit_parallax(predicted[~far], truth[~far], UP, sigma_match=0.001, sigma_parallax=1.0)
    s = fit_depth_scale(model, predicted[far], truth[far], sigma_match=0.001, sigma_scale=10.0)
    assert s == pytest.approx(0.5, abs=0.03)
    # Fitted on the near points themselves: 1; with none: the prior, 1.
    assert fit_depth_scale(model, predicted[~far], truth[~far], 0.001, 10.0) == pytest.approx(1.0, abs=0.03)
    assert fit_depth_scale(model, predicted[:0], truth[:0]) == 1.0
    # The prior pulls a poorly determined ratio towards 1.
    weak = fit_depth_scale(model, predicted[far], truth[far], sigma_match=0.05, sigma_scale=0.1)
    assert s < weak < 1.0
    # And the scaled model moves the far anchors to their true headings (to the 0.2 deg the
    # elevated points' small-angle azimuths leave).
    before = np.degrees(np.abs(heading_residuals(model, predicted[far], truth[far])))
    after = np.degrees(np.abs(heading_residuals(model.scaled(s), predicted[far], truth[far])))
    assert after.max() < 0.3 and before.max() > 1.5


def test_depth_scale_moves_an_inferred_annotation_on_a_far_facade():
    # 16 landmarks at 22 m (trees, near corners) set the common depth; 8 annotations on facades
    # at 45 m, one without a candidate (inferred).
    t = np.array([1.0, 0.5, 0.0])
    n = 24
    case, truth, uv, _, far = _near_and_far(42, t, n, 22.0, 45.0)
    gone = int(np.flatnonzero(far)[1])
    errors = {}
    for sigma in (0.0, 0.5):
        det = ReDetector(case.patches, case.dirs, ['p'] * n, MatchConfig(parallax_scale_sigma=sigma),
                         R_enu_source=[M_ENU_PANO @ rotated_by(case.R_target_source, 2.0, axis=-UP)] * n,
                         landmark=list(~far))
        det.set_orientation(M_ENU_PANO)
        for i in set(range(n)) - {gone}:
            det.candidates[i].items = [Candidate(float(uv[i, 0]), float(uv[i, 1]), 0.9, 0.9)]
        det.dirty = True
        _, al = det.result()
        assert al.parallax is not None
        p = next(p for p in al.placements if p.index == gone)
        assert p.status == 'inferred'
        errors[sigma] = float(np.degrees(np.arccos(np.clip(p.direction @ truth[gone], -1, 1))))
        assert all(q.status == 'matched' for q in al.placements if q.index != gone)
    assert errors[0.0] > 1.0 and errors[0.5] < 0.3


def test_depth_scale_sigma_is_the_posterior_of_the_ratio():
    t = np.array([1.2, -0.7, 0.0])
    _, truth, _, predicted, far = _near_and_far(40, t, 18, 20.0, 40.0)
    model = fit_parallax(predicted[~far], truth[~far], UP, sigma_match=0.001, sigma_parallax=1.0)
    # No match: the prior; each match narrows it, the more the larger the model's term at it.
    assert depth_scale_sigma(model, predicted[:0], 0.01, 0.3) == pytest.approx(0.3)
    one = depth_scale_sigma(model, predicted[far][:1], 0.01, 0.3)
    every = depth_scale_sigma(model, predicted[far], 0.01, 0.3)
    assert every < one < 0.3
    # The linear least squares of fit_depth_scale: residual = (s - 1) x term, prior on s.
    term = model.shift(predicted[far]) - model.c
    A = np.concatenate([term / 0.01, [1.0 / 0.3]])[:, None]
    assert every == pytest.approx(float(np.sqrt(np.linalg.inv(A.T @ A)[0, 0])), rel=1e-9)


def test_inferred_label_is_approximate_while_few_annotations_pin_the_depth_ratio():
    # 16 landmarks at 22 m, 8 annotations on facades at 45 m; annotation `gone` has no candidate.
    t = np.array([1.0, 0.5, 0.0])
    n = 24
    case, truth, uv, _, far = _near_and_far(42, t, n, 22.0, 45.0)
    ann = np.flatnonzero(far)
    gone = int(ann[1])

    def inferred(matched_annotations: int, limit: float, scatter: float = 0.0):
        det = ReDetector(case.patches, case.dirs, ['p'] * n,
                         MatchConfig(parallax_scale_sigma=0.3, depth_ratio_support_rad=limit,
                                     depth_ratio_scatter=scatter),
                         R_enu_source=[M_ENU_PANO @ rotated_by(case.R_target_source, 2.0, axis=-UP)] * n,
                         landmark=list(~far))
        det.set_orientation(M_ENU_PANO)
        with_candidate = set(np.flatnonzero(~far)) | set(ann[ann != gone][:matched_annotations])
        for i in with_candidate:
            det.candidates[i].items = [Candidate(float(uv[i, 0]), float(uv[i, 1]), 0.9, 0.9)]
        det.dirty = True
        _, al = det.result()
        p = next(p for p in al.placements if p.index == gone)
        assert al.supported and p.status == 'inferred' and np.isfinite(al.depth_ratio_sigma)
        term = abs(float(al.parallax.shift(case.dirs[gone] @ al.R_target_source.T)[0] - al.parallax.c))
        return p, term * al.depth_ratio_sigma

    few, spread_few = inferred(1, np.radians(0.4))
    many, spread_many = inferred(7, np.radians(0.4))
    assert spread_many < np.radians(0.4) < spread_few
    assert not few.supported and many.supported
    off, _ = inferred(1, 0.0)
    assert off.supported  # the rule off: the local matches alone decide
    # The label's own facade may differ from the fitted ratio whatever the matches: with that
    # scatter its term alone keeps it approximate.
    scattered, _ = inferred(7, np.radians(0.4), scatter=0.5)
    assert not scattered.supported


def test_prediction_sigma_grows_away_from_bunched_matches():
    # Matches only in one 60-deg sector: the model is pinned there, extrapolated on the far side.
    t = np.array([1.0, 0.5, 0.0])
    _, truth, _, predicted, _ = _near_and_far(44, t, 24, 25.0, 25.0)
    model0 = fit_parallax(predicted, truth, UP)
    az = np.degrees(model0.azimuth(predicted))
    sector = np.abs(((az - az[0]) + 180.0) % 360.0 - 180.0) <= 30.0
    assert 3 <= sector.sum() < 24
    model = fit_parallax(predicted[sector], truth[sector], UP, 0.01, 0.02)
    sig = prediction_sigma(model, predicted[sector], truth[sector], predicted, 0.01, 0.02)
    inside = sig[sector].max()
    opposite = np.abs(((az - az[0]) + 180.0) % 360.0 - 180.0) >= 150.0
    assert sig[opposite].min() > 2.0 * inside
    # Matches all around: small everywhere.
    spread = prediction_sigma(model0, predicted, truth, predicted, 0.01, 0.02)
    assert spread.max() < sig[opposite].min()


def test_inferred_label_far_from_bunched_matches_is_approximate_with_prediction_support():
    # Landmarks and annotations matched only within 50 deg of one azimuth; the label opposite.
    t = np.array([1.0, 0.5, 0.0])
    n = 24
    case, truth, uv, predicted, far = _near_and_far(46, t, n, 22.0, 45.0)
    model = fit_parallax(predicted, truth, UP)
    az = np.degrees(model.azimuth(predicted))
    ann = np.flatnonzero(far)
    gone = int(ann[0])
    off = np.abs(((az - az[gone]) + 180.0) % 360.0 - 180.0)
    bunch = [i for i in range(n) if off[i] >= 130.0 and i != gone]
    assert sum(far[bunch]) >= 2 and sum(~far[bunch]) >= 3

    def label(prediction_support: bool):
        cfg = MatchConfig(parallax_scale_sigma=0.3, local_support_matches=0, bracket_support_px=0.0,
                          depth_ratio_scatter=0.0, depth_ratio_support_rad=np.radians(0.55),
                          prediction_support=prediction_support)
        det = ReDetector(case.patches, case.dirs, ['p'] * n, cfg,
                         R_enu_source=[M_ENU_PANO @ rotated_by(case.R_target_source, 2.0, axis=-UP)] * n,
                         landmark=list(~far))
        det.set_orientation(M_ENU_PANO)
        for i in bunch:
            det.candidates[i].items = [Candidate(float(uv[i, 0]), float(uv[i, 1]), 0.9, 0.9)]
        det.dirty = True
        _, al = det.result()
        assert al.supported
        return next(p for p in al.placements if p.index == gone), al

    without, _ = label(False)
    with_it, al = label(True)
    assert without.status == with_it.status == 'inferred'
    assert al.prediction_sigma[gone] > np.radians(0.55)
    assert without.supported and not with_it.supported


@pytest.mark.parametrize('trim, elevation, scale_sigma', [(0.0, False, 0.3), (3.0, True, 0.3), (3.0, False, 0.0),
                                                          (3.0, True, 0.5)])
def test_leave_one_out_predictions_equal_one_fit_per_match(trim, elevation, scale_sigma):
    """The batched leave-one-out (one solve of m normal equations) gives what fitting the model
    on the other matches one by one gives: to rounding, with the trimmed refit, the elevation and
    the annotations' depth scale - also with an outlier among the matches and with 2 matches."""
    from ar_tracking.core.annotations.parallax import leave_one_out_predictions

    rng = np.random.default_rng(17)
    for m in (2, 3, 9, 25):
        up = UP + rng.normal(0, 0.03, 3)
        az, el = rng.uniform(-np.pi, np.pi, m), rng.uniform(-0.3, 0.3, m)
        predicted = np.stack([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)], axis=1)
        turn = 0.004 + 0.01 * np.cos(az) + rng.normal(0, 0.002, m)
        turn[m // 2] += 0.08  # a near tree among the matches
        observed = np.stack([np.cos(az + turn) * np.cos(el), np.sin(az + turn) * np.cos(el), np.sin(el)], axis=1)
        ann = np.arange(m) % 2 == 0
        got = leave_one_out_predictions(predicted, observed, up, 0.01, 0.02, trim, elevation,
                                        ann if scale_sigma > 0 else None, scale_sigma)
        for r in range(m):
            others = np.arange(m) != r
            loo = fit_parallax(predicted[others], observed[others], up, 0.01, 0.02, trim, elevation)
            if scale_sigma > 0 and ann[r]:
                loo = loo.scaled(fit_depth_scale(loo, predicted[others & ann], observed[others & ann], 0.01,
                                                 scale_sigma))
            assert np.allclose(got[r], loo.apply(predicted[r])[0], rtol=0, atol=1e-12)
        assert not np.allclose(got, predicted, atol=1e-4)  # it moved them
