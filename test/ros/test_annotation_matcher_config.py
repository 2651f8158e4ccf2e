"""annotation_matcher's parameters -> MatchConfig (nodes/annotation_matcher.py: match_config)."""
from __future__ import annotations

import dataclasses
import math

import pytest

from ar_tracking.core.annotations.matching import MatchConfig
from ar_tracking.nodes.annotation_matcher import PARAMS, match_config

F = 2048 / (2 * math.pi)


def _defaults() -> dict:
    return {p.name: p.default for p in PARAMS}


def test_every_parameter_named_as_a_field_reaches_the_config():
    fields = {f.name for f in dataclasses.fields(MatchConfig)}
    shared = sorted(fields & set(_defaults()))
    assert len(shared) >= 25
    for name in shared:
        values = _defaults()
        values[name] = (not values[name]) if isinstance(values[name], bool) else values[name] * 0.5 + 0.3
        assert values[name] != _defaults()[name]
        assert getattr(match_config(values, F), name) == values[name], name


@pytest.mark.parametrize('deg, field', [('prior_window_deg', 'prior_window_px'), ('local_support_deg', 'local_support_px'),
                                        ('bracket_support_deg', 'bracket_support_px'),
                                        ('matched_agreement_deg', 'matched_agreement_px')])
def test_degrees_become_map_pixels(deg: str, field: str):
    values = _defaults()
    values[deg] = 7.0
    assert getattr(match_config(values, F), field) == pytest.approx(math.radians(7.0) * F)


def test_depth_ratio_limit_in_radians():
    values = _defaults()
    values['depth_ratio_support_deg'] = 0.4
    assert match_config(values, F).depth_ratio_support_rad == pytest.approx(math.radians(0.4))
