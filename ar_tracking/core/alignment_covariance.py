"""How well the panorama's place in the world is known: the covariance of R_PN's tilt and
heading (:mod:`.world_alignment`), from what its two least-squares solves leave.

* **tilt**: the hand's acceleration enters the tapered mean of the specific force as the
  difference of its velocity averaged over the two weight ramps (L s each) divided by the
  weights' sum (T - L) - a tilt error that falls as 1/T, not as 1/sqrt(T) like white noise - and
  the ramps' averaging of a sway of period P shrinks it by at most P / (pi L). The variance
  divides by T instead of T - L: with the averaging factor an upper bound the two roughly
  balance (the simulator's sweeps: per-axis NEES of the tilt 0.2-0.8 in the first 2 s);
* **heading**: the field's direction is off by the noise of the windows, carried through the
  field solve's normal equations, by the bias its hard- and soft-iron ridges leave, and by the error of a
  prior carried into a new panorama: before the phone has turned, the ridge holds h near zero
  and the field is off by the residual hard iron; after a turn the two separate and the
  windows' scatter averages down. All of it is read along the east direction of the panorama
  frame.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.linalg.lapack import dgesv

Array = NDArray[np.float64]
_FIRST3 = np.eye(12)[:, :3]  # identity columns for up to 12 unknowns


def solve_regular(A: Array, b: Array) -> Array:
    """x of A x = b by LAPACK's dgesv, as np.linalg.solve, without its wrapper's checks (~10 us
    of a small solve). For the alignment's square, regular normal equations (with ridges)."""
    _, _, x, info = dgesv(A, b)
    if info != 0:
        raise np.linalg.LinAlgError('Singular matrix')
    return np.asarray(x, dtype=np.float64)


def hand_tilt_variance(hand_velocity_m_s: float, hand_period_s: float, ramp_s: float, span_s: float,
                       g: float) -> float:
    """Variance (rad^2) of the gravity direction left by the hand's motion (module docstring)."""
    v_eff = hand_velocity_m_s * min(1.0, hand_period_s / (math.pi * max(ramp_s, 1e-3)))
    return (v_eff / (g * max(span_s, 0.5))) ** 2


@dataclass(frozen=True)
class FieldErrorParts:
    """The 3x3 parts of the error covariance of f_P (relative to |B|) after one field solve."""

    #: Per unit of per-sample noise variance: B A_data B (f block).
    noise: Array
    #: Per unit of the true residual hard iron's variance: the ridge's bias, (B_fh ridge)^2.
    hard_iron: Array
    #: Per unit of the true residual soft iron's variance (each entry): (B_fE ridge)^2.
    soft_iron: Array
    #: Per unit of the carried prior's variance (rad^2): (B_ff w_prior)^2.
    prior: Array
    #: Samples per window (weighted), to turn the windows' scatter into per-sample noise.
    samples_per_window: float


def field_error_parts(A_solved: Array, A_data: Array, hard_iron_ridge: float, soft_iron_ridge: float,
                      prior_weight: float, samples_per_window: float) -> FieldErrorParts:
    """Split the error of f_P = the first three unknowns of ``A_solved x = rhs`` (f, h and,
    when solved, the six soft-iron entries) into its sources. ``A_data``: the part of
    ``A_solved`` the samples give (no ridge, no prior); ``hard_iron_ridge`` / ``soft_iron_ridge``:
    the weights on h = 0 (unknowns 3-5) and E = 0 (6-11); ``prior_weight``: the weight on f =
    the carried prior (0 without one)."""
    # The first three rows of A^-1, as A^-T's first three columns (the rows needed, without
    # np.linalg.inv's wrapper).
    B_f = solve_regular(A_solved.T, _FIRST3[:len(A_solved)]).T
    bias_h = hard_iron_ridge * B_f[:, 3:6]
    bias_e = soft_iron_ridge * B_f[:, 6:]
    bias_p = prior_weight * B_f[:, :3]
    return FieldErrorParts(noise=B_f.dot(A_data).dot(B_f.T), hard_iron=bias_h.dot(bias_h.T),
                           soft_iron=bias_e.dot(bias_e.T), prior=bias_p.dot(bias_p.T),
                           samples_per_window=samples_per_window)


def field_heading_mse(parts: FieldErrorParts, window_sigma_rad: float, east: Array, f_h: float,
                      hard_iron_sigma: float, soft_iron_sigma: float = 0.0, prior_sigma_rad: float = 0.0) -> float:
    """Mean squared error (rad^2) of the field's heading: the windows' heading scatter
    ``window_sigma_rad`` as each window's noise, a true residual hard iron of 1-sigma
    ``hard_iron_sigma`` (relative to |B|) and soft iron of ``soft_iron_sigma`` per entry, and a
    carried prior off by ``prior_sigma_rad``, read along ``east`` (unit, panorama frame) and
    divided by the horizontal field ``f_h``."""
    if f_h <= 0:
        return window_sigma_rad ** 2
    per_sample = (window_sigma_rad * f_h) ** 2 * parts.samples_per_window
    mse = (per_sample * parts.noise + hard_iron_sigma ** 2 * parts.hard_iron
           + soft_iron_sigma ** 2 * parts.soft_iron + prior_sigma_rad ** 2 * parts.prior)
    return float(east.dot(mse).dot(east)) / f_h ** 2
