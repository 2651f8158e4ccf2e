"""Settings of :class:`.world_alignment.WorldAlignment` (the panorama's place in the world):
the weights, priors, robust-fit and cluster-choice constants it uses, in SI units with field
quantities relative to the field's strength. Kept apart from the estimator so that each stays
readable; :mod:`.world_alignment` re-exports it."""
from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class WorldAlignmentConfig:
    """Settings of :class:`WorldAlignment` (SI units; field quantities relative to |B|)."""

    #: Prior 1-sigma of the accelerometer bias left by the calibration, m/s^2. Kept tight: the
    #: horizontal part of a bias averages out as the phone turns anyway, and a loose bias
    #: absorbs accelerometer scale errors (which rotate with the phone) and tilts g_P.
    accel_bias_sigma_m_s2: float = 0.01
    #: Width of the field fit's ridge on the residual hard iron, relative to |B| (weighed against
    #: ``field_model_sigma`` per sample): deliberately looser than the residual a calibration
    #: leaves (``hard_iron_prior_sigma``), so that h follows the rotations once they tell it apart.
    hard_iron_sigma: float = 0.2
    #: Width of the field fit's ridge on the residual soft iron (the entries of the symmetric E in
    #: m = (I + E) R_imu_P f_P + h), relative like ``hard_iron_sigma``; 0 leaves E out.
    soft_iron_sigma: float = 0.1
    #: Length of the gravity weights' ramps at both ends of the session, s (a taper kills the
    #: velocity term of the mean at its ends).
    gravity_ramp_s: float = 3.0
    #: Prior 1-sigma of the lever arm (the IMU's offset from the centre it turns about, in the
    #: IMU frame), m; 0 switches the lever-arm model off.
    lever_arm_sigma_m: float = 0.5
    #: Low-pass time constant of the rate and specific force in the lever-arm model, s.
    lever_arm_tau_s: float = 0.05
    #: At most this many windows are kept (then neighbours are merged two by two).
    max_windows: int = 20000
    #: A new panorama frame known to better than this (1-sigma) keeps the old frame's windows
    #: turned into it (:meth:`WorldAlignment.reanchor`); a looser one starts afresh from a prior:
    #: the window statistics count windows, not their weights, and old windows a few degrees off
    #: would outvote the new ones.
    reanchor_max_sigma_rad: float = math.radians(2.0)
    #: Re-solve the field every this long (sample stamps), s ...
    solve_period_s: float = 1.0
    #: ... or, early in a session, every this share of its span (at least every 0.1 s): the
    #: first seconds are when each new degree of rotation tells the hard iron apart most, and
    #: a solve over a few windows is cheap.
    solve_period_share: float = 0.1
    #: ... and late in a long session every this share of its span when that is longer than
    #: ``solve_period_s`` (from 50 s on at 0.02): a solve reads every window of the session, so
    #: at a fixed period the cost per sample grows with the session (1.5 ms per solve at 400
    #: windows, 200 s); a period in proportion keeps it constant. 0: always ``solve_period_s``.
    solve_period_long_share: float = 0.02
    #: IRLS iterations per solve.
    irls_iterations: int = 2
    #: Cauchy scale in robust sigmas of the residual norm.
    cauchy_scale: float = 2.5
    #: Floor of the robust residual sigma, relative to |B| (a perfect sensor is not trusted more).
    min_field_sigma: float = 0.005
    #: Per-sample error of the field model (unmodelled iron, small disturbances), relative to |B|:
    #: weighs the hard-iron prior (h moves only where the rotations tell it from a turned field).
    field_model_sigma: float = 0.02
    #: Correlation time of the residuals (hand motion, disturbances), s: sets how many samples
    #: a prior carried into a new panorama is worth.
    correlation_s: float = 0.25
    #: Typical speed of the phone in the hand (the velocity term of the gravity mean), m/s.
    hand_velocity_m_s: float = 0.3
    #: Typical period of the hand's sway, s: a weight ramp of L seconds averages the hand's
    #: velocity down by about ``hand_period_s / (pi L)`` (tilt covariance).
    hand_period_s: float = 1.25
    #: 1-sigma of the residual hard iron a calibration leaves, relative to |B| (heading
    #: covariance: before the phone has turned, it is all that bounds the field's direction).
    hard_iron_prior_sigma: float = 0.025
    #: 1-sigma of the residual soft iron's entries a calibration leaves (heading covariance:
    #: what the soft-iron ridge holds back over a partial turn).
    soft_iron_prior_sigma: float = 0.01
    #: Another cluster of window headings takes over from the one the last solve chose only
    #: when its episode cost (below) is lower by this many nats (hysteresis).
    mode_switch_nats: float = 1.0
    #: Typical length of a magnetic disturbance, s: each second a hypothesis has to call
    #: disturbed costs 1 / this many nats.
    disturbance_duration_s: float = 3.0
    #: Cost of one disturbance episode (a maximal run of windows off the hypothesised field),
    #: nats: -log of the odds that a disturbance starts. It is what makes a field the phone
    #: returns to the Earth's: calling it disturbed takes two episodes with the same deflection.
    disturbance_onset_nats: float = 3.0
    #: Runs of fewer windows than this off a field are noise, not episodes (no onset cost).
    min_episode_windows: int = 2
    #: Share of the windows whose densest interval gives the heading spread (a quarter: still
    #: one cluster's when a disturbance holds as many windows as the clean field).
    cluster_share: float = 0.25
    #: Windows whose heading is more than this many Cauchy widths off the chosen cluster get
    #: no weight (and count as off it in the episode cost).
    reject_widths: float = 2.0
    #: Window of the robust field fit, s (short, so that a disturbance of a few seconds is a
    #: minority of the windows early in a session too).
    window_s: float = 0.5
    #: 1-sigma floors of the result, rad.
    tilt_floor_rad: float = math.radians(0.05)
    heading_floor_rad: float = math.radians(0.15)
    declination_rad: float = 0.0
