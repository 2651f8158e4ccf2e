"""Visual-inertial fusion of Caarls et al. 2009 sec. 2.5: two error-state Kalman filters
(orientation + gyro bias, position + velocity + accelerometer bias) driven by the IMU, corrected
by late camera poses with roll-back and replay (Fig. 7 and 8)."""

from ...errors import ArTrackingError


class VioError(ArTrackingError, ValueError):
    """Bad argument to the visual-inertial cores (one line)."""
