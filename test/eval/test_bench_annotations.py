"""The annotation bench functions run and report finite times (speed itself is not tested)."""
from __future__ import annotations

import math

from ar_tracking.eval.bench_annotations import ROWS, bench_ransac, bench_tile_match


def test_bench_functions_report_finite_times():
    for value in (bench_tile_match(n=3), bench_ransac(n=3), bench_ransac(n=3, gravity=True)):
        assert math.isfinite(value) and value > 0


def test_fig7_rows_switch_one_enhancement_at_a_time():
    assert ROWS['baseline'] == dict(edr=False, sensor_prior=False, ransac=False)
    assert ROWS['all'] == dict(edr=True, sensor_prior=True, ransac=True)
    assert sum(ROWS['sensor'].values()) == sum(ROWS['ransac'].values()) == sum(ROWS['edr'].values()) == 1


def test_make_bag_lighting_argument(tmp_path):
    """The Fig. 7 'same lighting' column is a public make_bag option: lighting=session changes
    nothing, another session's sun changes the images, a bad name is refused."""
    import pytest

    from ar_tracking.sim.bagmaker import SimError, make_bag, session_view

    kw = dict(seed=3, duration_s=1.0, session='browsing')
    plain = make_bag('rotation_sweep', tmp_path / 'plain.mcap', **kw)
    same = make_bag('rotation_sweep', tmp_path / 'same.mcap', lighting='browsing', **kw)
    other = make_bag('rotation_sweep', tmp_path / 'other.mcap', lighting='authoring', **kw)
    assert same.read_bytes() == plain.read_bytes()
    assert other.read_bytes() != plain.read_bytes()
    _, light_b, _ = session_view(3, 'browsing')
    _, light_a, _ = session_view(3, 'browsing', 'authoring')
    assert light_a.sun_el_rad < light_b.sun_el_rad  # low afternoon sun vs midday sun
    with pytest.raises(SimError, match='lighting'):
        make_bag('rotation_sweep', tmp_path / 'bad.mcap', lighting='dusk', **kw)


def test_fig7_authoring_stores_the_estimate_and_uses_the_truth_only_for_the_click():
    """_authored: the anchor is cut where it truly appears (the simulated user's click), but the
    orientation stored for the prior is the estimate, and the landmarks' up is the estimate's."""
    from types import SimpleNamespace

    import numpy as np

    from annotation_synth import GEO, M_ENU_PANO, rotated_by, texture
    from ar_tracking.core.annotations.world_orientation import PanoramaWorld
    from ar_tracking.eval.bench_annotations import _authored

    gray = texture(5)
    mapped = np.zeros(gray.shape, bool)
    mapped[100:420] = True
    estimate = rotated_by(M_ENU_PANO, 2.0)  # 2 deg off in heading
    anchor = SimpleNamespace(direction=M_ENU_PANO @ GEO.unproject(np.array(900.0), np.array(250.0)))
    auth = {'anchors': [anchor], True: {'gray': gray, 'mapped': mapped, 'R_enu_pano_truth': M_ENU_PANO,
                                        'world': PanoramaWorld(estimate, np.eye(3) * 1e-4, 'world_alignment')}}
    out = _authored(auth, True, GEO)
    assert np.array_equal(out['R_enu_pano'], estimate)
    u, v = GEO.project(out['dirs'][0])
    assert abs(u - 900.0) <= 0.5 and abs(v - 250.0) <= 0.5  # cut at the click, not the estimate
    assert out['landmarks'] and all(lm.direction @ estimate[2] > 0 for lm in out['landmarks'][:24])
    auth[True]['world'] = None
    assert _authored(auth, True, GEO) is None  # no estimate, nothing authored for the prior
