"""What the re-detector keeps between two ``result`` calls (NCC surfaces of the guided search,
the candidates' directions) changes nothing: every result equals the one computed from scratch
on the same state."""
from __future__ import annotations

import copy
import math

import numpy as np

from annotation_synth import GEO, M_ENU_PANO, UP, displaced_spot_case, make_case, rotated_by, tiles_of
from ar_tracking.core.annotations.matching import Candidate, MatchConfig, ReDetector
from ar_tracking.core.annotations.matching.placement import Alignment, CandidateDirections


def _detector(case, n: int = 6) -> ReDetector:
    det = ReDetector(case.patches, case.dirs, ['p'] * n, MatchConfig(),
                     R_enu_source=[M_ENU_PANO @ rotated_by(case.R_target_source, 2.0, axis=-UP)] * n)
    det.set_orientation(M_ENU_PANO)
    return det


def _from_scratch(det: ReDetector) -> Alignment:
    """The result of a copy of ``det`` with nothing kept from earlier calls."""
    ref = copy.deepcopy(det)
    ref._clear_kept()
    ref.dirty = True
    return ref.result()[1]


def _same(a: Alignment, b: Alignment) -> None:
    def fields(al: Alignment):
        return [(p.index, p.u, p.v, p.status, repr(p.score), p.supported, p.direction.tobytes(),
                 None if p.predicted is None else np.asarray(p.predicted).tobytes())
                for p in al.placements + al.landmarks]

    assert (a.R_target_source is None) == (b.R_target_source is None)
    if a.R_target_source is not None:
        assert a.R_target_source.tobytes() == b.R_target_source.tobytes()
    assert fields(a) == fields(b)
    assert repr(a.parallax) == repr(b.parallax)
    assert repr(a.parallax_gate_px) == repr(b.parallax_gate_px)
    assert (a.supported, a.support, a.support_reason) == (b.supported, b.support, b.support_reason)


def test_a_kept_ncc_surface_is_reused_only_on_the_same_map_pixels():
    case = make_case(seed=7)
    det = _detector(case)
    det.step(case.target, case.mapped, 0)  # the map, no tile
    tu, tv = case.truth_uv[2]
    first = det._ncc_window([(2, tu, tv)], 25.0, 4.0)[0]
    assert first is not None
    again = det._ncc_window([(2, tu + 0.2, tv - 0.1)], 25.0, 4.0)[0]  # the same window, other offsets
    assert again is not None and again[0] is first[0] and not np.array_equal(again[1], first[1])
    # A few pixels under the window change (the map was painted again there): computed anew.
    x, y = int(round(tu - 7.5)), int(round(tv - 7.5))
    painted = case.target.copy()
    painted[y:y + 16, x + 4:x + 20] = painted[y:y + 16, x + 4:x + 20] * 0.5 + 60.0
    det.step(painted, case.mapped, 0)
    fresh = _detector(case)
    fresh.step(painted, case.mapped, 0)
    now = det._ncc_window([(2, tu, tv)], 25.0, 4.0)[0]
    ref = fresh._ncc_window([(2, tu, tv)], 25.0, 4.0)[0]
    assert now is not None and ref is not None
    assert now[0].tobytes() == ref[0].tobytes() and now[0].tobytes() != first[0].tobytes()
    # The same pixels with part of them no longer mapped: computed anew too.
    hole = case.mapped.copy()
    hole[y:y + 3, x:x + 40] = False
    det.step(painted, hole, 0)
    fresh.step(painted, hole, 0)
    now, ref = det._ncc_window([(2, tu, tv)], 25.0, 4.0)[0], fresh._ncc_window([(2, tu, tv)], 25.0, 4.0)[0]
    assert now is not None and ref is not None
    assert now[0].tobytes() == ref[0].tobytes() and (now[0] == -1.0).sum() > (first[0] == -1.0).sum()


def test_results_with_what_is_kept_equal_results_from_scratch_while_the_map_grows():
    """Tiles finished a few columns at a time, the map painted again in between under matched
    annotations: after every step the result equals that of the same state from scratch."""
    case = make_case(seed=11, n=10)
    det = _detector(case, 10)
    rng = np.random.default_rng(3)
    all_tiles = tiles_of(case.mapped)
    target = case.target.copy()
    kept_any = False
    for last_column in (8, 12, 16, 20, 24, 28, 32, 32, 32):
        mapped = case.mapped.copy()
        mapped[:, last_column * 64:] = False
        if last_column == 32:  # painted again: a few annotations' surroundings change
            for u, v in case.truth_uv[rng.choice(10, 3, replace=False)]:
                x, y = int(round(u)) - 20, int(round(v)) - 6
                target[y:y + 12, max(x, 0):x + 40] += rng.normal(0, 6.0, target[y:y + 12, max(x, 0):x + 40].shape)
        gray = np.where(mapped, target, 0.0).astype(np.float32)
        tiles = all_tiles.copy()
        tiles[:, last_column:] = 0
        det.add_finished_tiles(tiles)
        det.step(gray, mapped)
        det.dirty = True
        expected = _from_scratch(det)
        got = det.result()[1]
        _same(got, expected)
        kept_any = kept_any or bool(det._ncc_surfaces)
    assert kept_any and got.parallax is not None and got.supported
    assert sum(p.status == 'matched' for p in got.placements) >= 6
    assert not math.isnan(got.parallax_gate_px)


def test_kept_candidate_directions_are_those_unprojected_now():
    dirs = CandidateDirections(GEO)
    a, b, c = Candidate(100.25, 200.5, 0.9, 0.9), Candidate(1800.75, 300.0, 0.8, 0.8), Candidate(5.5, 99.0, 0.7, 0.7)

    def check(cands):
        got = dirs.of_list(cands)
        want = GEO.unproject(np.array([x.u for x in cands]), np.array([x.v for x in cands])) if cands else np.zeros((0, 3))
        assert got.tobytes() == want.tobytes() and not got.flags.writeable
        for x in cands:
            assert dirs.of(x).tobytes() == GEO.unproject(np.array(x.u), np.array(x.v)).tobytes()
        return got

    first = check([a, b])
    dirs.next_round()
    assert check([a, b]) is first  # kept from the round before
    assert check([a, c]) is not first and check([]).shape == (0, 3)
    dirs.next_round()
    dirs.next_round()  # a round that used nothing: the kept ones are gone
    assert check([a, b]) is not first


def test_a_kept_parallax_fit_is_reused_only_for_the_same_inputs():
    """Each input of the fit changed alone (the rotation's predictions, the matches, where one
    was found, the up direction) gives the fit from scratch; the same inputs give the kept one."""
    t = np.array([1.2, -0.6, 0.0])
    case, truth, _ = displaced_spot_case(34, t, np.array([35.0, 45.0, 40.0, 50.0, 42.0, 38.0]))
    ids = list(range(6))
    predicted = case.dirs @ case.R_target_source.T
    det = _detector(case)

    def fresh(*args):
        return _detector(case)._parallax_fit(*args)

    def same(a, b):
        assert repr(a.model) == repr(b.model) and a.corrected.tobytes() == b.corrected.tobytes()
        assert repr((a.depth_ratio_sigma, a.prediction_sigma, a.gate_px)) == repr(
            (b.depth_ratio_sigma, b.prediction_sigma, b.gate_px))

    matched = [0, 1, 2, 3, 4]
    first = det._parallax_fit(ids, predicted, matched, truth[matched], UP)
    assert det._parallax_fit(ids, predicted.copy(), list(matched), truth[matched].copy(), UP.copy()) is first
    moved = truth[matched].copy()
    moved[2] = truth[2] + np.array([0.004, 0.0, 0.0])
    tilted = UP + np.array([0.0, 0.0, 0.01])
    for args in ((ids, predicted, matched, moved, UP),
                 (ids, predicted, [0, 1, 2, 3, 5], truth[matched], UP),  # other matches, same observations
                 (ids, predicted @ rotated_by(np.eye(3), 0.3, axis=UP).T, matched, truth[matched], UP),
                 (ids, predicted, matched, truth[matched], tilted / np.linalg.norm(tilted))):
        got = det._parallax_fit(*args)
        assert got is not first
        same(got, fresh(*args))
    same(first, fresh(ids, predicted, matched, truth[matched], UP))


def test_the_parallax_fit_median_is_numpys():
    from ar_tracking.core.window_statistics import median as _median  # what fit_parallax takes

    rng = np.random.default_rng(8)
    for n in range(1, 60):
        x = np.abs(rng.normal(size=n)) * 10.0 ** rng.uniform(-4, 1)
        x[: n // 3] = np.round(x[: n // 3], 2)  # ties
        assert _median(x) == float(np.median(x))
    assert math.isnan(_median(np.array([1.0, np.nan, 2.0])))


def test_windows_asked_for_together_equal_windows_asked_for_one_at_a_time():
    case = make_case(seed=7)
    det = _detector(case)
    det.step(case.target, case.mapped, 0)
    rng = np.random.default_rng(2)
    at = [(int(i), float(u + rng.uniform(-3, 3)), float(v + rng.uniform(-3, 3)))
          for i, (u, v) in enumerate(case.truth_uv)]
    at.append((0, 5.3, 2.0))  # beyond the top row: no window
    at.append((1, 2040.6, 200.2))  # across the map's seam
    for radius, v_tol in ((25.0, 4.0), (13.5, None)):
        together = det._ncc_window(at, radius, v_tol)
        assert together[-2] is None and together[-1] is not None
        for one, win in zip(at, together):
            alone = _detector(case)
            alone.step(case.target, case.mapped, 0)
            ref = alone._ncc_window([one], radius, v_tol)[0]
            assert (win is None) == (ref is None)
            if win is not None and ref is not None:
                assert [a.tobytes() for a in win] == [a.tobytes() for a in ref]


def test_the_nearest_candidate_distance_is_numpys_nanmin():
    from ar_tracking.core.annotations.matching.alignment import _nearest

    rng = np.random.default_rng(4)
    for k in (1, 2, 3):
        dd = rng.uniform(0, 40, (50, 12, k))
        dd[rng.uniform(size=dd.shape) < 0.2] = np.inf  # beyond the vertical tolerance
        dd[:, :, 1:][rng.uniform(size=dd[:, :, 1:].shape) < 0.3] = np.nan  # no such candidate
        assert _nearest(dd).tobytes() == np.nanmin(dd, axis=2).tobytes()
