"""Keyframe SLAM core on the real EuRoC V1_01 slice in ../shared/data (skipped when absent)."""
from __future__ import annotations

import pytest

from ar_tracking.eval.bench_slam import real_euroc_slice
from conftest import SHARED_DATA

EUROC = SHARED_DATA / 'euroc_v1_01_micro'


@pytest.mark.skipif(not EUROC.is_dir(), reason='../shared/data/euroc_v1_01_micro not present')
def test_real_euroc_slice_waits_while_static_and_tracks_in_flight():
    r = real_euroc_slice(EUROC)
    assert r is not None
    # Standing still: no parallax, so no map and no pose (monocular SLAM must wait).
    assert r['static_frames'] == 95 and r['static_tracked_frames'] == 0
    # In flight (0.18 m, 12 deg in 10 frames): initialises and tracks the rest of the slice.
    assert r['inflight_init_after_frames'] is not None and r['inflight_init_after_frames'] <= 8
    assert r['inflight_tracked_frames'] >= 2
    assert r['inflight_true_motion']['deg'] > 10
    assert r['inflight_rel_rotation_error_deg'] < 1.0
    assert r['inflight_direction_error_deg'] < 20.0
