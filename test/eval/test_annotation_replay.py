"""The matcher-only replay (eval/annotation_replay.py) on the sample bags: it reproduces the
graph run's labels, and the parameters it is given take effect."""
from __future__ import annotations

import pytest

pytest.importorskip('rclpy')

from ar_tracking.eval.annotation_metrics import evaluate_annotations  # noqa: E402
from ar_tracking.eval.annotation_replay import replay_matcher  # noqa: E402
from ar_tracking.io.bags import BagReader  # noqa: E402
from conftest import SAMPLE_AUTHORING, SAMPLE_BROWSING  # noqa: E402


@pytest.mark.skipif(not (SAMPLE_AUTHORING.exists() and SAMPLE_BROWSING.exists()), reason='sample bags missing')
def test_replay_reproduces_the_run_and_takes_its_parameters(sample_authored, sample_browsed, tmp_path, ros_context):
    """On the graph run of the browsing bag with the authored store (conftest's session
    fixtures, shared with test_annotations_end_to_end)."""
    store, run_out = sample_authored[0], sample_browsed
    live = evaluate_annotations(run_out)
    assert live is not None and live['n'] >= 4

    same = replay_matcher(run_out, store, tmp_path / 'replayed.mcap', context=ros_context)
    assert same is not None and same['n'] == live['n']
    assert abs(same['redetection_rate'] - live['redetection_rate']) <= 1.0 / live['n'] + 1e-9
    with BagReader(tmp_path / 'replayed.mcap') as a, BagReader(run_out) as b:
        assert a.message_count(['/panorama/image']) == b.message_count(['/panorama/image'])  # the rest is copied
        assert a.message_count(['/annotations/markers']) > 0

    # No alignment can gather 50 matches: every label stays approximate, none counts.
    strict = replay_matcher(run_out, store, tmp_path / 'strict.mcap', params={'min_support_matches': 50},
                            context=ros_context)
    assert strict is not None and strict['redetection_rate'] == 0.0 and strict['approximate'] == live['n']
