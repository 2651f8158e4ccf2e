"""How well the panorama's place in the world is known: the covariance of R_PN's tilt and
heading (:mod:`.world_alignment`), from what its two least-squares solves leave.

* **tilt**: the hand's acceleration enters the tapered mean of the specific force as the
  difference of its velocity averaged over the two weight ramps (L s each) divided by the span
  T - a tilt error that falls as 1/T, not as 1/sqrt(T) like white noise - and the ramps'
  averaging of a sway of period P shrinks it by about P / (pi L);
* **heading**: the field's direction is off by the noise of the windows, averaged through the
  (f_P, h) normal equations, and by the bias the hard-iron ridge leaves: before the phone has
  turned, the ridge holds h near zero and the field is off by the residual hard iron; after a
  turn the two separate and the windows' scatter averages down. Both are read along the east
  direction of the panorama frame.
"""
from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def hand_tilt_variance(hand_velocity_m_s: float, hand_period_s: float, ramp_s: float, span_s: float,
                       g: float) -> float:
    """Variance (rad^2) of the gravity direction left by the hand's motion (module docstring)."""
    v_eff = hand_velocity_m_s * min(1.0, hand_period_s / (math.pi * max(ramp_s, 1e-3)))
    return (v_eff / (g * max(span_s, 0.5))) ** 2


def field_heading_mse(sum_w: float, sum_R: Array, n_windows: float, window_sigma_rad: float,
                      east: Array, f_h: float, ridge: float, hard_iron_sigma: float) -> float:
    """Mean squared error (rad^2) of the field's heading after a solve of m = R_imu_P f + h.

    ``sum_w``, ``sum_R``: the weighted sample count and sum of R_imu_P of the solve (its data
    normal equations); ``n_windows``: the weighted number of windows; ``window_sigma_rad``: the
    scatter of the windows' headings (each window's noise); ``east``: the unit vector
    perpendicular to f and up (panorama frame) and ``f_h`` the horizontal field (relative to
    |B|); ``ridge``: the solve's weight on h = 0; ``hard_iron_sigma``: 1-sigma of the true
    residual hard iron (relative), which the ridge biases the solution against."""
    if sum_w <= 0 or n_windows <= 0 or f_h <= 0:
        return window_sigma_rad ** 2
    noise = (window_sigma_rad * f_h) ** 2 * sum_w / n_windows  # per sample: a window's mean scatters so
    A = np.zeros((6, 6))
    A[:3, :3] = np.eye(3) * sum_w
    A[:3, 3:] = sum_R.T
    A[3:, :3] = sum_R
    A[3:, 3:] = np.eye(3) * sum_w
    B = np.linalg.inv(A + np.diag([0.0, 0.0, 0.0, ridge, ridge, ridge]))
    variance = noise * (B @ A @ B)[:3, :3]
    bias = ridge * B[:3, 3:]  # d(error of f) / d(true h)
    mse = variance + hard_iron_sigma ** 2 * (bias @ bias.T)
    return float(east @ mse @ east) / f_h ** 2
