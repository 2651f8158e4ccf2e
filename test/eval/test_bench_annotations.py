"""The annotation bench functions run and report finite times (speed itself is not tested)."""
from __future__ import annotations

import math

from ar_tracking.eval.bench_annotations import ROWS, bench_ransac, bench_tile_match


def test_bench_functions_report_finite_times():
    for value in (bench_tile_match(n=3), bench_ransac(n=3)):
        assert math.isfinite(value) and value > 0


def test_fig7_rows_switch_one_enhancement_at_a_time():
    assert ROWS['baseline'] == dict(edr=False, sensor_prior=False, ransac=False)
    assert ROWS['all'] == dict(edr=True, sensor_prior=True, ransac=True)
    assert sum(ROWS['sensor'].values()) == sum(ROWS['ransac'].values()) == sum(ROWS['edr'].values()) == 1
