"""evaluate says which truth topic it looked for when the bag has none."""
from __future__ import annotations

import logging

import pytest

from ar_tracking.eval import evaluate
from ar_tracking.eval.metrics import EvaluationError
from ar_tracking.io.bags import BagWriter, msg_class


def _bag_without_truth(tmp_path):
    path = tmp_path / 'out.mcap'
    with BagWriter(path) as w:
        w.write('/orientation/global_note', 1, msg_class('std_msgs/msg/String')(data='an estimate'))
    return path


def test_missing_truth_alone_is_an_error_naming_the_topic(tmp_path, monkeypatch):
    monkeypatch.setattr(evaluate, 'AREA_EVALUATORS', {})
    with pytest.raises(EvaluationError, match='/ground_truth/orientation'):
        evaluate.evaluate_all(_bag_without_truth(tmp_path), reference=False)


def test_missing_truth_beside_other_areas_is_a_warning_naming_the_topic(tmp_path, monkeypatch, caplog):
    monkeypatch.setattr(evaluate, 'AREA_EVALUATORS', {'other': 'test_evaluate_missing_truth:_an_area'})
    with caplog.at_level(logging.WARNING, logger='ar_tracking.eval.evaluate'):
        metrics = evaluate.evaluate_all(_bag_without_truth(tmp_path), reference=False)
    assert metrics == {'other': {'x': 1}}
    assert any('no orientation section' in r.message and '/ground_truth/orientation' in r.message for r in caplog.records)


def _an_area(path):
    return {'x': 1}
