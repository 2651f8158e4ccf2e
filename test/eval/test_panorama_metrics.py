"""evaluate_panorama on a lockstep run of panorama_mapper over the committed sample bag."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip('rclpy')

from ar_tracking.eval.panorama_metrics import evaluate_panorama, tracking_errors  # noqa: E402
from ar_tracking.io.bags import BagReader  # noqa: E402
from ar_tracking.nodes.panorama_mapper import PanoramaMapperNode  # noqa: E402
from ar_tracking.ros.runner import GraphRunner  # noqa: E402
from panorama_synth import rot  # noqa: E402

BAG = Path(__file__).resolve().parents[2] / 'bags' / 'rotation_sweep_authoring.mcap'


def test_tracking_errors_are_relative_to_the_first_frame():
    ts = np.arange(0, 11, dtype=np.int64) * 10
    R0 = rot('x', 30) @ rot('z', 50)  # the truth's first orientation is arbitrary
    truth = np.array([R0 @ rot('y', k) for k in range(11)])
    est = np.array([rot('y', k) for k in range(11)])
    est[5] = est[5] @ rot('x', 0.5)
    st, err = tracking_errors(ts, est, ts, truth)
    assert st.size == 11 and err[5] == pytest.approx(0.5, abs=1e-6)
    assert np.delete(err, 5).max() < 1e-4


def test_tracking_errors_start_over_where_a_new_panorama_starts():
    """The mapper restarted at frame 6 (published as the identity): the frames from there are
    relative to it and exact; taken relative to the first panorama they would be 6 deg off."""
    ts = np.arange(0, 11, dtype=np.int64) * 10
    truth = np.array([rot('x', 30) @ rot('y', k) for k in range(11)])
    est = np.array([rot('y', k) for k in range(6)] + [rot('y', k - 6) for k in range(6, 11)])
    st, err = tracking_errors(ts, est, ts, truth)
    assert st.size == 11 and err.max() < 1e-4
    est[6] = est[6] @ rot('x', 1e-3)  # not exactly the identity: the same panorama
    _, err = tracking_errors(ts, est, ts, truth)
    assert err[7:].min() > 5.9


@pytest.mark.skipif(not BAG.exists(), reason='sample bag missing')
def test_lockstep_run_is_reproducible_and_tracks_the_sample_bag(tmp_path):
    outs = []
    for i in range(2):
        out = tmp_path / f'out{i}.mcap'
        GraphRunner(BAG, out, graph={'panorama_mapper': PanoramaMapperNode}, max_messages=3000).run()
        outs.append(out)
    with BagReader(outs[0]) as a, BagReader(outs[1]) as b:
        ma = [(m.topic, m.rawdata) for m in a.messages(['/panorama/orientation', '/panorama/image', '/panorama/tiles'])]
        mb = [(m.topic, m.rawdata) for m in b.messages(['/panorama/orientation', '/panorama/image', '/panorama/tiles'])]
    assert ma == mb and len(ma) > 100
    res = evaluate_panorama(outs[0], source_bag=None, seam=False)
    assert res is not None
    assert res['frames'] > 100 and res['n'] == res['frames'] - res['lost_frames']
    assert res['lost_frames'] == 0
    assert res['tracking_rmse_deg'] < 0.25 and res['tracking_max_deg'] < 1.0
    assert evaluate_panorama(BAG, seam=False) is None  # no /panorama/orientation in the input


@pytest.mark.skipif(not BAG.exists(), reason='sample bag missing')
def test_camera_frames_pair_images_with_their_camera_info_and_stop_at_max_frames():
    """The frames seam_errors replays (its measures on the sample bag: test_end_to_end's
    test_seam_errors_on_the_sample_bag_prefer_edr, from the demo's evaluate)."""
    from ar_tracking.eval.panorama_metrics import camera_frames

    frames = list(camera_frames(BAG, max_frames=5))
    assert len(frames) == 5
    stamps = [s for s, _, _ in frames]
    assert stamps == sorted(set(stamps))
    for _, img, K in frames:
        assert img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3
        assert K.shape == (3, 3) and K[2, 2] == 1.0 and K[0, 0] > 0
