"""Absolute orientation from gravity and the magnetic field (Langlotz et al. 2011, sec. 5).

The accelerometer measures gravity ``g_t`` and the magnetometer the field ``m_t`` in the device
frame. Eq. 3-4 of the paper ask for the rotation R_DN = [r_x r_y r_z] (world -> device) with

    g_t = R_DN g        (3)   pitch and roll come from gravity alone,
    m_t . r_z = 0       (4)   the field only fixes the heading (it may vary in the up/north plane).

In our ENU world (x east, y north, z up) the axis that the field must be orthogonal to is east,
so the solution is the gravity-first TRIAD construction: ``up`` is the normalised specific force,
``east`` is ``m x up`` normalised (m . east = 0 exactly), ``north = up x east``. The rows of
R_enu_imu are east, north and up expressed in the device frame. A declination D (magnetic north
D east of true north) turns magnetic ENU into true ENU by a rotation of -D about up.

The orientation covariance is not a constant: it grows with the evidence that the sensors do
not see plain gravity and the undisturbed local field (|a| away from g, |m| or the dip angle
away from the local field), which is what makes the estimate usable by a fusion filter
(Langlotz sec. 7 names magnetic disturbance as the weak point of the sensor-only estimate).
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from .rotations import rot_z

logger = logging.getLogger(__name__)

Array = NDArray[np.float64]

STANDARD_GRAVITY_M_S2 = 9.80665


@dataclass
class ImuCalibration:
    """Per-device sensor calibration (what a calibration session measures).

    calibrated gyro = raw - gyro_bias; calibrated accel = raw - accel_bias;
    calibrated field = soft_iron_matrix @ (raw - hard_iron_offset).
    """

    gyro_bias: Array = field(default_factory=lambda: np.zeros(3))  # rad/s
    accel_bias: Array = field(default_factory=lambda: np.zeros(3))  # m/s^2
    hard_iron_offset: Array = field(default_factory=lambda: np.zeros(3))  # tesla
    soft_iron_matrix: Array = field(default_factory=lambda: np.eye(3))  # unitless

    def __post_init__(self) -> None:
        self.gyro_bias = np.asarray(self.gyro_bias, dtype=float).reshape(3)
        self.accel_bias = np.asarray(self.accel_bias, dtype=float).reshape(3)
        self.hard_iron_offset = np.asarray(self.hard_iron_offset, dtype=float).reshape(3)
        self.soft_iron_matrix = np.asarray(self.soft_iron_matrix, dtype=float).reshape(3, 3)
        for name in ('gyro_bias', 'accel_bias', 'hard_iron_offset', 'soft_iron_matrix'):
            if not np.all(np.isfinite(getattr(self, name))):
                raise ValueError(f'calibration {name} is not finite')
        if abs(np.linalg.det(self.soft_iron_matrix)) < 1e-6:
            raise ValueError('calibration soft_iron_matrix is singular')

    def gyro(self, raw: Array) -> Array:
        return np.asarray(raw, dtype=float) - self.gyro_bias

    def accel(self, raw: Array) -> Array:
        return np.asarray(raw, dtype=float) - self.accel_bias

    def mag(self, raw: Array) -> Array:
        return self.soft_iron_matrix @ (np.asarray(raw, dtype=float) - self.hard_iron_offset)


@dataclass
class FieldModel:
    """The local reference field and the noise of the sensors, for the covariance.

    ``field_t`` and ``dip_rad`` of 0 mean "unknown": they are then learnt as a slow running
    mean of what the (calibrated) magnetometer reports.
    """

    gravity_m_s2: float = STANDARD_GRAVITY_M_S2
    field_t: float = 0.0  # local |B|, tesla (e.g. from a world magnetic model)
    dip_rad: float = 0.0  # inclination, positive when the field points below the horizon
    declination_rad: float = 0.0  # magnetic north is this far east of true north
    accel_noise_m_s2: float = 0.05  # 1-sigma per axis
    mag_noise_t: float = 0.3e-6  # 1-sigma per axis


def orientation_from_gravity_and_field(
    accel: Array, mag: Array, declination_rad: float = 0.0
) -> Array | None:
    """R_enu_body from one accelerometer and one magnetometer sample (eq. 3-4).

    Returns None when the inputs cannot define an orientation (non-finite, zero-norm, or the
    field parallel to gravity).
    """
    a = np.asarray(accel, dtype=float)
    m = np.asarray(mag, dtype=float)
    if a.shape != (3,) or m.shape != (3,):
        return None
    # On Python floats: numpy's per-call cost was most of a per-sample estimate.
    ax, ay, az = a.tolist()
    mx, my, mz = m.tolist()
    if not all(math.isfinite(v) for v in (ax, ay, az, mx, my, mz)):
        return None
    a_norm = math.sqrt(ax * ax + ay * ay + az * az)
    m_norm = math.sqrt(mx * mx + my * my + mz * mz)
    if a_norm < 1e-6 or m_norm < 1e-12:
        return None
    ux, uy, uz = ax / a_norm, ay / a_norm, az / a_norm
    mx, my, mz = mx / m_norm, my / m_norm, mz / m_norm
    ex, ey, ez = my * uz - mz * uy, mz * ux - mx * uz, mx * uy - my * ux  # east = m x up
    east_norm = math.sqrt(ex * ex + ey * ey + ez * ez)
    if east_norm < 1e-3:  # field (nearly) vertical: heading undefined
        return None
    ex, ey, ez = ex / east_norm, ey / east_norm, ez / east_norm
    R_magenu_body = np.array([[ex, ey, ez],
                              [uy * ez - uz * ey, uz * ex - ux * ez, ux * ey - uy * ex],  # north = up x east
                              [ux, uy, uz]])
    if declination_rad:
        return rot_z(-declination_rad) @ R_magenu_body
    return R_magenu_body


def field_dip_rad(accel: Array, mag: Array) -> float:
    """Inclination of the measured field below the horizon, from the gravity direction."""
    cos = -float(mag @ accel) / math.sqrt(float(mag @ mag) * float(accel @ accel))
    return math.asin(min(1.0, max(-1.0, cos)))


@dataclass
class OrientationEstimate:
    """One absolute orientation with its covariance and the diagnostics behind it."""

    R_enu_body: Array
    covariance: Array  # 3x3, rad^2, about the ENU x, y, z axes (roll, pitch, yaw)
    accel_deviation: float  # | |a| - g | / g
    field_deviation: float  # | |m| - B | / B
    dip_deviation_rad: float  # | dip - dip_ref |

    @property
    def heading_sigma_rad(self) -> float:
        return float(np.sqrt(self.covariance[2, 2]))

    @property
    def tilt_sigma_rad(self) -> float:
        return float(np.sqrt(self.covariance[0, 0]))


class GravityFieldOrientation:
    """Eq. 3-4 on calibrated samples, with an honest, changing covariance.

    Covariance model (1-sigma, radians):
      tilt    = accel_noise / g + | |a| - g | / g          (an unmodelled acceleration of d*g
                                                           tilts the estimate by up to ~d rad)
      heading = mag_noise / B_h + (| |m| - B | / B + |dip - dip_ref|) / cos(dip_ref)
                + tilt * tan(dip_ref)                      (a disturbance of relative size d
                                                           turns a horizontal field B_h = B cos(dip)
                                                           by up to d / cos(dip); tilt errors leak
                                                           into heading through the dip)
    """

    #: Weight of a new sample in the running mean of |B| and dip when they are learnt.
    LEARN_RATE = 0.002

    def __init__(self, calibration: ImuCalibration | None = None, model: FieldModel | None = None):
        self.calibration = calibration or ImuCalibration()
        self.model = model or FieldModel()
        self._field_ref = self.model.field_t if self.model.field_t > 0 else None
        self._dip_ref = self.model.dip_rad if self.model.field_t > 0 else None

    def reset(self) -> None:
        """Forget what was learnt online (after a clock jump, a new bag)."""
        self._field_ref = self.model.field_t if self.model.field_t > 0 else None
        self._dip_ref = self.model.dip_rad if self.model.field_t > 0 else None

    def estimate(self, accel_raw: Array, mag_raw: Array) -> OrientationEstimate | None:
        """Orientation from raw (uncalibrated) samples; None when they define none."""
        a = self.calibration.accel(accel_raw)
        m = self.calibration.mag(mag_raw)
        R = orientation_from_gravity_and_field(a, m, self.model.declination_rad)  # None if not finite
        if R is None:
            return None
        g = self.model.gravity_m_s2
        a_norm, m_norm = math.sqrt(float(a @ a)), math.sqrt(float(m @ m))
        dip = field_dip_rad(a, m)
        if self._field_ref is None or self._dip_ref is None:
            self._field_ref, self._dip_ref = m_norm, dip
        field_ref, dip_ref = self._field_ref, self._dip_ref
        accel_dev = abs(a_norm - g) / g
        field_dev = abs(m_norm - field_ref) / field_ref
        dip_dev = abs(dip - dip_ref)
        if self.model.field_t <= 0:  # learn the reference slowly, away from disturbances
            w = self.LEARN_RATE if field_dev < 0.1 else self.LEARN_RATE * 0.1
            self._field_ref = (1 - w) * field_ref + w * m_norm
            self._dip_ref = (1 - w) * dip_ref + w * dip
        cos_dip = max(math.cos(dip_ref), 0.1)
        tilt_sigma = self.model.accel_noise_m_s2 / g + accel_dev
        heading_sigma = (
            self.model.mag_noise_t / max(field_ref * cos_dip, 1e-9)
            + (field_dev + dip_dev) / cos_dip
            + tilt_sigma * abs(math.tan(dip_ref))
        )
        heading_sigma = min(heading_sigma, math.pi)
        tilt_sigma = min(tilt_sigma, math.pi)
        cov = np.array([[tilt_sigma ** 2, 0.0, 0.0], [0.0, tilt_sigma ** 2, 0.0], [0.0, 0.0, heading_sigma ** 2]])
        return OrientationEstimate(R, cov, accel_dev, field_dev, dip_dev)
