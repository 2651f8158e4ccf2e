"""The phone's sensor models of rotation_sweep: the earth's field, magnetic disturbances, and
the IMU and magnetometer errors (Langlotz et al. 2011, section 5: what the hybrid orientation
filter has to cope with).

* :class:`EarthField`: |B|, dip and declination at the spot; :class:`Disturbances`: smooth local
  field changes (steel, cars, electronics) that turn the horizontal field and, in the 'kind'
  profile, also change |B| and dip; :func:`heading_deflection` the compass error they cause.
* :class:`SensorErrors`: gyro and accelerometer biases and noise, hard and soft iron, and in the
  'hard' profile a drifting gyro bias (:class:`BiasDrift`) and accelerometer scale errors.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from ..core.rotations import rot_z
from .rng import rng_stream

Array = NDArray[np.float64]

HARD_GYRO_DRIFT_PER_MINUTE_RAD_S = (0.002, 0.005)  # typical |change| of the bias over 60 s
HARD_ACCEL_SCALE_ERROR = (0.005, 0.01)  # per axis, random sign
#: Gyro sensitivity error per axis, random sign: what a factory trim leaves (MEMS datasheets give
#: +-0.4 to +-1 % tolerances; the bias is calibrated by users, the scale seldom).
HARD_GYRO_SCALE_ERROR = (0.001, 0.005)


@dataclass(frozen=True)
class EarthField:
    """The undisturbed local geomagnetic field."""

    magnitude_t: float = 48e-6
    dip_rad: float = math.radians(64.0)  # inclination, positive = pointing down
    declination_rad: float = 0.0  # magnetic north east of true north

    @property
    def vector_enu(self) -> Array:
        """The field vector in ENU, tesla (north and down components, east with declination)."""
        h = self.magnitude_t * math.cos(self.dip_rad)
        return np.array([h * math.sin(self.declination_rad), h * math.cos(self.declination_rad),
                         -self.magnitude_t * math.sin(self.dip_rad)])


@dataclass(frozen=True)
class Disturbances:
    """Transient magnetic disturbances with smooth on/off ramps.

    Without ``turn_rad`` (profile 'kind') each event adds a constant extra field scaled by its
    envelope. With it (profile 'hard') the events turn the horizontal part of the undisturbed
    field ``base_enu`` about the up axis by ``envelope @ turn_rad`` (counter-clockwise
    positive), so |B| and the dip angle stay exactly those of the earth field throughout."""

    start_s: Array
    duration_s: Array
    ramp_s: Array
    field_enu: Array  # (k, 3) extra field at full strength, tesla
    turn_rad: Array | None = None  # (k,) turn of the horizontal field at full strength
    base_enu: Array | None = None  # the field that is turned (needed with turn_rad)

    def envelope(self, t: Array) -> Array:
        """(N, k) strength 0..1 of each event."""
        t = np.asarray(t, dtype=float)[..., None]
        rise = np.clip((t - self.start_s) / self.ramp_s, 0, 1)
        fall = np.clip((self.start_s + self.duration_s - t) / self.ramp_s, 0, 1)
        x = np.minimum(rise, fall)
        return 0.5 - 0.5 * np.cos(math.pi * x)

    def field(self, t: Array) -> Array:
        """Extra field (N, 3) in ENU, tesla."""
        if self.turn_rad is None:
            return self.envelope(t) @ self.field_enu
        assert self.base_enu is not None
        angle = self.envelope(t) @ self.turn_rad
        c, s = np.cos(angle), np.sin(angle)
        bx, by = float(self.base_enu[0]), float(self.base_enu[1])
        return np.stack([c * bx - s * by - bx, s * bx + c * by - by, np.zeros_like(angle)], -1)


def make_disturbances(rng: np.random.Generator, duration_s: float, earth: EarthField,
                      keep_field: bool = False) -> Disturbances:
    """3-5 events per minute (at least one), each deflecting a compass by 2-10 degrees.

    ``keep_field`` (profile 'hard'): the same schedule and deflections (the same draws), but
    every event only turns the horizontal field, keeping |B| and dip (hard to detect)."""
    n = max(1, int(round(duration_s / 60.0 * rng.uniform(3.0, 5.0))))
    slot = duration_s / n
    b = earth.vector_enu
    bh = np.array([b[0], b[1], 0.0])
    starts, durs, ramps, fields, turns = [], [], [], [], []
    for k in range(n):
        dur = min(rng.uniform(2.0, 5.0), 0.8 * slot)
        ramp = min(rng.uniform(0.4, 1.0), dur / 3)
        start = k * slot + rng.uniform(0.1 * slot, max(0.1 * slot, slot - dur - 0.05 * slot))
        defl = math.radians(rng.uniform(2.0, 10.0)) * (1 if rng.random() < 0.5 else -1)
        scale = 1.0 if rng.random() < 0.5 else rng.uniform(0.88, 1.15)
        # The compass error equals the counter-clockwise turn of the horizontal field.
        turned = scale * (rot_z(defl) @ bh)
        extra = turned - bh
        if scale != 1.0:
            extra[2] = rng.uniform(-4e-6, 4e-6)  # some events also change dip and |B|
        if keep_field:
            extra = rot_z(defl) @ bh - bh
        starts.append(start)
        durs.append(dur)
        ramps.append(ramp)
        fields.append(extra)
        turns.append(defl)
    if keep_field:
        return Disturbances(np.array(starts), np.array(durs), np.array(ramps), np.array(fields),
                            np.array(turns), b.copy())
    return Disturbances(np.array(starts), np.array(durs), np.array(ramps), np.array(fields))


def heading_deflection(b_true_enu: Array, b_meas_enu: Array) -> Array:
    """Compass error (rad) caused by measuring ``b_meas`` instead of ``b_true`` (both (..., 3))."""
    cross = b_true_enu[..., 0] * b_meas_enu[..., 1] - b_true_enu[..., 1] * b_meas_enu[..., 0]
    dot = b_true_enu[..., 0] * b_meas_enu[..., 0] + b_true_enu[..., 1] * b_meas_enu[..., 1]
    return np.arctan2(cross, dot)


@dataclass(frozen=True)
class BiasDrift:
    """A random walk sampled at knots (linear in between, held outside), added to a bias."""

    knot_s: Array  # (k,)
    value: Array  # (k, 3), value[0] = 0: the drift starts from the calibrated constant part

    def at(self, t: Array) -> Array:
        """(N, 3) drift at times ``t`` (s)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        return np.stack([np.interp(t, self.knot_s, self.value[:, i]) for i in range(3)], -1)


@dataclass(frozen=True)
class SensorErrors:
    """The device's true sensor errors (the sidecar holds a slightly wrong estimate of them).

    ``gyro_bias_drift``, ``accel_scale`` and ``gyro_scale`` exist in the 'hard' profile only (None
    otherwise): the gyro bias at time t is ``gyro_bias_rad_s + gyro_bias_drift.at(t)``, the
    accelerometer measures ``accel_scale * specific_force + accel_bias_m_s2``, the gyro
    ``gyro_scale * rate + bias``."""

    gyro_bias_rad_s: Array
    accel_bias_m_s2: Array
    hard_iron_t: Array
    soft_iron: Array  # A in: measured = A @ true + hard_iron
    gyro_noise_rad_s: float = 0.01
    accel_noise_m_s2: float = 0.05
    mag_noise_t: float = 0.3e-6
    gyro_bias_drift: BiasDrift | None = None
    accel_scale: Array | None = None  # (3,) per-axis scale factor (1 + error)
    gyro_scale: Array | None = None  # (3,) per-axis scale factor (1 + error)

    def gyro_bias_at(self, t: Array) -> Array:
        """(N, 3) true gyro bias at times ``t`` (rad/s)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        bias = np.broadcast_to(self.gyro_bias_rad_s, (len(t), 3)).copy()
        if self.gyro_bias_drift is not None:
            bias += self.gyro_bias_drift.at(t)
        return bias


def make_sensor_errors(rng: np.random.Generator) -> SensorErrors:
    """A phone's errors: gyro bias 0.5-1 deg/s, accel bias ~0.05 m/s^2, hard iron 2-6 uT per
    axis, soft iron within a few percent of identity (symmetric)."""
    signs = lambda: rng.choice([-1.0, 1.0], 3)  # noqa: E731
    A = np.eye(3) + np.diag(rng.uniform(-0.04, 0.04, 3))
    off = rng.uniform(-0.03, 0.03, 3)
    A[0, 1] = A[1, 0] = off[0]
    A[0, 2] = A[2, 0] = off[1]
    A[1, 2] = A[2, 1] = off[2]
    return SensorErrors(
        gyro_bias_rad_s=np.radians(rng.uniform(0.5, 1.0, 3)) * signs(),
        accel_bias_m_s2=rng.uniform(0.03, 0.07, 3) * signs(),
        hard_iron_t=rng.uniform(2e-6, 6e-6, 3) * signs(),
        soft_iron=A,
    )


def make_gyro_bias_drift(rng: np.random.Generator, duration_s: float) -> BiasDrift:
    """A random walk of the gyro bias from 0, knots every second; its step is set so that
    the typical |change| over a minute is 2-5 mrad/s (drawn per device)."""
    per_minute = rng.uniform(*HARD_GYRO_DRIFT_PER_MINUTE_RAD_S)
    # E|w(60 s)| of a 3-axis walk of step sigma per second is sigma * sqrt(60) * 1.596.
    sigma = per_minute / (math.sqrt(60.0) * 1.596)
    n = int(math.ceil(duration_s)) + 2
    steps = rng.normal(0.0, sigma, (n - 1, 3))
    value = np.vstack([np.zeros((1, 3)), np.cumsum(steps, axis=0)])
    return BiasDrift(np.arange(n, dtype=float), value)


def make_hard_sensor_errors(seed: int, session: str, duration_s: float, kind: SensorErrors
                            ) -> SensorErrors:
    """The 'kind' device plus a drifting gyro bias (stream 'gyro-drift'), accelerometer
    scale errors of 0.5-1 % per axis (stream 'accel-scale') and gyro scale errors of 0.1-0.5 %
    per axis (stream 'gyro-scale')."""
    drift = make_gyro_bias_drift(rng_stream(seed, 'gyro-drift', session), duration_s)
    rng = rng_stream(seed, 'accel-scale', session)
    scale = 1.0 + rng.uniform(*HARD_ACCEL_SCALE_ERROR, 3) * rng.choice([-1.0, 1.0], 3)
    rng = rng_stream(seed, 'gyro-scale', session)
    gyro_scale = 1.0 + rng.uniform(*HARD_GYRO_SCALE_ERROR, 3) * rng.choice([-1.0, 1.0], 3)
    return replace(kind, gyro_bias_drift=drift, accel_scale=scale, gyro_scale=gyro_scale)
