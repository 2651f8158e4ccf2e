"""The covariance of the panorama's place in the world (core/alignment_covariance)."""
from __future__ import annotations

import math

import numpy as np

from ar_tracking.core.alignment_covariance import field_heading_mse, hand_tilt_variance
from ar_tracking.core.rotations import rot_z

F_H = 0.44  # horizontal field relative to |B| (dip 64 deg)
EAST = np.array([1.0, 0.0, 0.0])


def normal_sums(angles_rad: np.ndarray, per_window: int = 50) -> tuple[float, np.ndarray, float]:
    """Sums of a solve whose windows saw the phone at these headings (about z)."""
    R = np.array([rot_z(a) for a in angles_rad])
    return float(per_window * len(R)), per_window * R.sum(axis=0), float(len(R))


def test_before_a_turn_the_heading_is_as_uncertain_as_the_residual_hard_iron():
    sw, S, n = normal_sums(np.zeros(10))
    mse = field_heading_mse(sw, S, n, math.radians(0.3), EAST, F_H, ridge=0.01 * sw, hard_iron_sigma=0.025)
    # h biases f by all of itself: 0.025 / 0.44 rad = 3.3 deg.
    assert math.degrees(math.sqrt(mse)) > 0.9 * math.degrees(0.025 / F_H)


def test_after_a_turn_the_windows_scatter_averages_down():
    sw, S, n = normal_sums(np.linspace(0.0, 2 * math.pi, 80, endpoint=False))
    sigma = math.radians(0.3)
    mse = field_heading_mse(sw, S, n, sigma, EAST, F_H, ridge=0.01 * sw, hard_iron_sigma=0.025)
    assert math.sqrt(mse) < 0.2 * math.degrees(0.025 / F_H) * math.pi / 180
    assert abs(math.sqrt(mse) / (sigma / math.sqrt(n)) - 1.0) < 0.3


def test_a_partial_turn_lies_in_between():
    sw0, S0, n0 = normal_sums(np.zeros(20))
    sw1, S1, n1 = normal_sums(np.radians(np.linspace(0.0, 30.0, 20)))
    sw2, S2, n2 = normal_sums(np.radians(np.linspace(0.0, 180.0, 20)))
    mse = [field_heading_mse(sw, S, n, math.radians(0.3), EAST, F_H, ridge=0.01 * sw, hard_iron_sigma=0.025)
           for sw, S, n in ((sw0, S0, n0), (sw1, S1, n1), (sw2, S2, n2))]
    assert mse[0] > mse[1] > mse[2]


def test_the_tilt_variance_falls_with_the_span_and_the_ramp():
    early = hand_tilt_variance(0.3, 1.25, ramp_s=0.5, span_s=1.0, g=9.81)
    late = hand_tilt_variance(0.3, 1.25, ramp_s=3.0, span_s=30.0, g=9.81)
    assert math.degrees(math.sqrt(early)) > 1.0  # the first second: the hand's sway is all there
    assert math.degrees(math.sqrt(late)) < 0.02  # averaged over 3 s ramps, then over 30 s
    assert hand_tilt_variance(0.3, 1.25, ramp_s=3.0, span_s=30.0, g=9.81) < \
        hand_tilt_variance(0.3, 1.25, ramp_s=0.5, span_s=30.0, g=9.81)
