"""The matcher-only replay (eval/annotation_replay.py) on the sample bags: it reproduces the
graph run's labels, and the parameters it is given take effect."""
from __future__ import annotations

from pathlib import Path

import pytest

pytest.importorskip('rclpy')

from ar_tracking.annotate import annotate_bag  # noqa: E402
from ar_tracking.eval.annotation_metrics import evaluate_annotations  # noqa: E402
from ar_tracking.eval.annotation_replay import replay_matcher  # noqa: E402
from ar_tracking.io.bags import BagReader  # noqa: E402
from ar_tracking.ros.runner import GraphRunner  # noqa: E402

BAGS = Path(__file__).resolve().parents[2] / 'bags'
AUTHORING, BROWSING = BAGS / 'rotation_sweep_authoring.mcap', BAGS / 'rotation_sweep_browsing.mcap'


@pytest.mark.skipif(not (AUTHORING.exists() and BROWSING.exists()), reason='sample bags missing')
def test_replay_reproduces_the_run_and_takes_its_parameters(tmp_path, ros_context):
    from ar_tracking.eval.annotation_metrics import simulated_user_positions

    store = tmp_path / 'notes.db'
    annotate_bag(AUTHORING, store, positions=simulated_user_positions(AUTHORING))
    params = tmp_path / 'p.yaml'
    params.write_text(f'annotation_matcher:\n  ros__parameters:\n    store_path: {store}\n')
    run = GraphRunner(BROWSING, tmp_path / 'out.mcap', params_files=[params], named_graph='annotations').run()
    live = evaluate_annotations(run.out_path)
    assert live is not None and live['n'] >= 4

    same = replay_matcher(run.out_path, store, tmp_path / 'replayed.mcap', context=ros_context)
    assert same is not None and same['n'] == live['n']
    assert abs(same['redetection_rate'] - live['redetection_rate']) <= 1.0 / live['n'] + 1e-9
    with BagReader(tmp_path / 'replayed.mcap') as a, BagReader(run.out_path) as b:
        assert a.message_count(['/panorama/image']) == b.message_count(['/panorama/image'])  # the rest is copied
        assert a.message_count(['/annotations/markers']) > 0

    # No alignment can gather 50 matches: every label stays approximate, none counts.
    strict = replay_matcher(run.out_path, store, tmp_path / 'strict.mcap', params={'min_support_matches': 50},
                            context=ros_context)
    assert strict is not None and strict['redetection_rate'] == 0.0 and strict['approximate'] == live['n']
