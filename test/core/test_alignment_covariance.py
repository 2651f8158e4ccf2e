"""The covariance of the panorama's place in the world (core/alignment_covariance)."""
from __future__ import annotations

import math

import numpy as np

from ar_tracking.core.alignment_covariance import field_error_parts, field_heading_mse, hand_tilt_variance
from ar_tracking.core.rotations import rot_z

F_H = 0.44  # horizontal field relative to |B| (dip 64 deg)
EAST = np.array([1.0, 0.0, 0.0])


def heading_mse(angles_rad: np.ndarray, window_sigma: float = math.radians(0.3), per_window: int = 50,
                hard_iron_sigma: float = 0.025) -> float:
    """The heading MSE after an (f, h) solve (ridge 0.01 per sample on h) whose windows saw the
    phone at these headings (about z)."""
    R = np.array([rot_z(a) for a in angles_rad])
    sw, S = float(per_window * len(R)), per_window * R.sum(axis=0)
    A = np.block([[np.eye(3) * sw, S.T], [S, np.eye(3) * sw]])
    ridge = 0.01 * sw
    parts = field_error_parts(A + np.diag([0, 0, 0, ridge, ridge, ridge]), A, ridge, 0.0, 0.0, per_window)
    return field_heading_mse(parts, window_sigma, EAST, F_H, hard_iron_sigma)


def test_before_a_turn_the_heading_is_as_uncertain_as_the_residual_hard_iron():
    mse = heading_mse(np.zeros(10))
    # h biases f by all of itself: 0.025 / 0.44 rad = 3.3 deg.
    assert math.degrees(math.sqrt(mse)) > 0.9 * math.degrees(0.025 / F_H)


def test_after_a_turn_the_windows_scatter_averages_down():
    sigma = math.radians(0.3)
    mse = heading_mse(np.linspace(0.0, 2 * math.pi, 80, endpoint=False), sigma)
    assert math.sqrt(mse) < 0.2 * 0.025 / F_H
    assert abs(math.sqrt(mse) / (sigma / math.sqrt(80)) - 1.0) < 0.3


def test_a_partial_turn_lies_in_between():
    mse = [heading_mse(np.radians(np.linspace(0.0, span, 20))) for span in (0.0, 30.0, 180.0)]
    assert mse[0] > mse[1] > mse[2]


def test_a_carried_prior_bounds_the_heading_before_a_turn():
    """A new panorama seeded with the orientation carried over (prior weight far above the
    ridge): the heading is as uncertain as the prior, not as the residual hard iron."""
    R = np.array([rot_z(0.0)] * 10)
    sw, S = 500.0, 50 * R.sum(axis=0)
    A = np.block([[np.eye(3) * sw, S.T], [S, np.eye(3) * sw]])
    ridge, wp = 0.01 * sw, 50.0 * sw
    solved = A + np.diag([wp, wp, wp, ridge, ridge, ridge])
    parts = field_error_parts(solved, A, ridge, 0.0, wp, 50.0)
    sigma = math.sqrt(field_heading_mse(parts, math.radians(0.3), EAST, F_H, 0.025, 0.0, math.radians(0.2)))
    assert math.radians(0.1) < sigma < math.radians(0.5)  # was 3 deg without the prior in the sum


def test_the_tilt_variance_falls_with_the_span_and_the_ramp():
    early = hand_tilt_variance(0.3, 1.25, ramp_s=0.5, span_s=1.0, g=9.81)
    late = hand_tilt_variance(0.3, 1.25, ramp_s=3.0, span_s=30.0, g=9.81)
    assert math.degrees(math.sqrt(early)) > 1.0  # the first second: the hand's sway is all there
    assert math.degrees(math.sqrt(late)) < 0.02  # averaged over 3 s ramps, then over 30 s
    assert hand_tilt_variance(0.3, 1.25, ramp_s=3.0, span_s=30.0, g=9.81) < \
        hand_tilt_variance(0.3, 1.25, ramp_s=0.5, span_s=30.0, g=9.81)
