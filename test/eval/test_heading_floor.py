"""The hand-motion floor of the heading (eval.heading_floor): its pieces and one seed."""
from __future__ import annotations

import math

import numpy as np

from ar_tracking.core.rotations import heading_tilt_error_deg
from ar_tracking.eval.heading_floor import _enu_from_up_and_field, hand_motion_floor, ramped_running_mean


def test_ramped_running_mean_keeps_a_constant_and_averages_a_sway_away():
    t = np.arange(0.0, 30.0, 0.01)
    const = np.tile([0.0, 0.0, 9.81], (len(t), 1))
    assert np.allclose(ramped_running_mean(t, const, 0.5, 3.0), const)
    sway = np.stack([0.5 * np.sin(2 * math.pi * 0.7 * t + 1.0)] * 3, axis=-1)
    mean = ramped_running_mean(t, sway, 0.5, 3.0)
    # early: no period completed, the mean is most of the amplitude; late: (v(T) - v(0)) / T
    assert np.max(np.abs(mean[t < 0.3, 0])) > 0.3
    assert np.max(np.abs(mean[t > 20.0, 0])) < 0.01


def test_a_tilt_about_north_turns_the_heading_by_tan_dip_times_it():
    dip = math.radians(64.0)
    field = np.array([0.0, math.cos(dip), -math.sin(dip)])
    assert np.allclose(_enu_from_up_and_field(np.array([[0.0, 0.0, 1.0]]), field)[0], np.eye(3))
    tilt = math.radians(1.0)
    for up in ([math.sin(tilt), 0.0, math.cos(tilt)], [0.0, math.sin(tilt), math.cos(tilt)]):
        R_axes = _enu_from_up_and_field(np.array([up]), field)
        _, heading, err_tilt = heading_tilt_error_deg(R_axes[0].T, np.eye(3))
        assert abs(float(err_tilt) - 1.0) < 0.01
        expected = math.degrees(math.tan(dip) * tilt) if up[0] else 0.0  # toward north: no heading
        assert abs(abs(float(heading)) - expected) < 0.02


def test_the_floor_of_a_seed_is_in_the_first_seconds():
    floor = hand_motion_floor(341, duration_s=20.0)
    assert 1.5 < floor['dip_deg'] < 89.0
    assert floor['heading_rmse_deg_first_2s'] > 0.5
    assert floor['heading_rmse_deg_after_2s'] < 0.5 * floor['heading_rmse_deg_first_2s']
    assert 0.0 < floor['tilt_rmse_deg'] < 1.0


def test_bench_seeds_rates_the_first_seconds_against_the_floor():
    from ar_tracking.eval.bench_hybrid import _first_seconds_over_floor

    def row(first, sway, compass):
        return {'heading_split': {'orientation/global_heading_rmse_deg_first_2s': first},
                'hand_motion_floor': {'heading_rmse_deg_first_2s': sway}, 'compass_floor_first_1s_deg': compass}

    rows = {'1': row(5.0, 3.0, 4.0), '2': row(10.0, 3.0, 4.0), '3': row(2.5, 3.0, 4.0)}
    assert _first_seconds_over_floor(rows) == 1.0  # floors of 5: ratios 0.5, 1, 2
    assert _first_seconds_over_floor({'1': {'heading_split': {}}}) is None
