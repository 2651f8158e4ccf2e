"""Gyro-aided attitude and heading (AHRS): the sensor-only orientation of ``imu_magnetometer``.

The engine is VQF (Laidig & Seel 2023, "VQF: Highly accurate IMU orientation estimation with
bias estimation and magnetic disturbance rejection", PyPI ``vqf``): gyro strapdown integration
with an accelerometer correction low-passed in an almost-inertial frame (tau_acc), a heading
correction from the magnetometer (tau_mag), gyro bias estimation at rest and in motion, rest
detection and magnetic disturbance rejection (the field's norm and dip are learnt; a sample
whose norm or dip departs is not used, the gyro carries the heading). It was chosen on evidence:
on the BROAD trials it beats Madgwick-type filters and the per-sample tilt-compass of Langlotz
eq. 3-4 by factors of 10-100 (``ar-tracking bench --areas orientation``).

What this module adds around it, for a ROS node fed by real drivers:

* **stamps, not a fixed rate**: VQF integrates with a fixed sample time ``Ts``; a sample whose
  stamp gap differs (driver jitter, a dropped sample) has its rate scaled by ``dt / Ts`` so the
  integrated angle is right. ``Ts`` is the configured period or the median of the first gaps.
* **magnetometer at its own pace**: the newest field sample that is at most ``max_mag_age_s``
  old is used at each IMU sample; none (missing, stale, ``use_mag=False``) means a 6D update.
  No IMU sample ever waits for the magnetometer, so a returning magnetometer cannot release a
  burst downstream.
* **calibration, declination, a covariance** (REP-145): tilt and heading 1-sigma that grow with
  the evidence (sustained acceleration beyond gravity; a rejected or missing field, for as long
  as the gyro alone carries the heading, at the rate of the remaining bias uncertainty).
* **bad samples** (non-finite, zero-norm accelerometer, stamps going back) are refused with a
  reason, never passed to the filter.

The per-sample tilt-compass of eq. 3-4 stays in :mod:`.imu_orientation` as the paper's
sensor-only baseline of Fig. 8 (``method: compass`` in the node).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .imu_orientation import STANDARD_GRAVITY_M_S2, ImuCalibration
from .rotations import quat_wxyz_to_matrix, rot_z
from ..errors import ArTrackingError

Array = NDArray[np.float64]

#: Samples whose gaps set the sample time when none is configured.
_RATE_PROBE = 8
#: VQF's defaults magMaxRejectionTime and magRejectionFactor (its rejection timer, mirrored).
_MAG_MAX_REJECTION_S = 60.0
_MAG_REJECTION_FACTOR = 2.0


class AhrsError(ArTrackingError, ValueError):
    """An AHRS setting that cannot work (one line for the user)."""


@dataclass(frozen=True)
class AhrsConfig:
    """Settings of :class:`Ahrs` (SI units).

    The VQF time constants are the published defaults (tau_acc 3 s, tau_mag 9 s); the noise
    figures only shape the reported covariance.
    """

    #: IMU sample period, s (0: the median of the first stamp gaps).
    sample_period_s: float = 0.0
    #: Use the magnetometer for heading (False: 6D, heading from the gyro only).
    use_mag: bool = True
    #: Oldest field sample that is still used with an IMU sample, s.
    max_mag_age_s: float = 0.1
    tau_acc_s: float = 3.0
    tau_mag_s: float = 9.0
    #: VQF's magnetic disturbance rejection (norm and dip of the field against a learnt reference).
    mag_disturbance_rejection: bool = True
    #: VQF's gyro bias estimation at rest and in motion.
    bias_estimation: bool = True
    #: Magnetic north is this far east of true north, rad.
    declination_rad: float = 0.0
    gravity_m_s2: float = STANDARD_GRAVITY_M_S2
    #: 1-sigma floors of the reported orientation, rad (what VQF reaches on clean data).
    tilt_sigma_floor_rad: float = math.radians(0.5)
    heading_sigma_floor_rad: float = math.radians(2.0)
    #: Heading 1-sigma before any field sample was used (the 6D heading is arbitrary), rad.
    heading_sigma_unknown_rad: float = math.pi
    #: Gyro white noise, rad/s per sample (heading random walk while the field is not used).
    gyro_noise_rad_s: float = 0.01
    #: Constant orientation 1-sigma instead of the model, rad (imu_filter_madgwick's
    #: ``orientation_stddev``; 0: the model).
    constant_sigma_rad: float = 0.0

    def __post_init__(self) -> None:
        for name in ('sample_period_s', 'max_mag_age_s', 'tau_acc_s', 'tau_mag_s', 'gravity_m_s2',
                     'tilt_sigma_floor_rad', 'heading_sigma_floor_rad', 'heading_sigma_unknown_rad',
                     'gyro_noise_rad_s', 'constant_sigma_rad', 'declination_rad'):
            if not math.isfinite(getattr(self, name)):
                raise AhrsError(f'{name} must be finite')
        if self.sample_period_s < 0 or self.max_mag_age_s < 0 or self.constant_sigma_rad < 0:
            raise AhrsError('sample_period_s, max_mag_age_s and constant_sigma_rad must be >= 0')
        if self.tau_acc_s <= 0 or self.tau_mag_s <= 0:
            raise AhrsError('tau_acc_s and tau_mag_s must be > 0')


@dataclass(frozen=True)
class AhrsEstimate:
    """One orientation of the IMU body in ENU with its covariance and what stood behind it."""

    t_ns: int
    R_enu_body: Array
    #: 3x3, rad^2, about the ENU x, y, z axes (roll/pitch/yaw errors of REP-145).
    covariance: Array
    #: The field sample was used (False: 6D update; missing, stale or disturbed field; use_mag off).
    mag_used: bool

    @property
    def heading_sigma_rad(self) -> float:
        return float(math.sqrt(self.covariance[2, 2]))

    @property
    def tilt_sigma_rad(self) -> float:
        return float(math.sqrt(self.covariance[0, 0]))


def _finite3(v: Any) -> Array | None:
    """The sample as a float (3,) array, or None when it is not three finite numbers."""
    a = np.asarray(v, dtype=float)
    if a.shape != (3,):
        return None
    x, y, z = a.tolist()
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        return None
    return a


class Ahrs:
    """VQF on stamped, calibrated samples with a covariance (see the module docstring).

    ``update(t_ns, gyro, accel, mag_t=None, mag_t_ns=None)`` takes one IMU sample (raw body-frame
    rate in rad/s, specific force in m/s^2) and, optionally, the newest field sample (raw,
    tesla) with its stamp. It returns an :class:`AhrsEstimate`, or a string saying why the
    sample was refused (the node logs it throttled). Until the sample time is known (the first
    few gaps, when not configured) a provisional filter answers, and the probe samples are then
    replayed into the final one: every accepted sample has an estimate.
    """

    def __init__(self, config: AhrsConfig | None = None, calibration: ImuCalibration | None = None) -> None:
        self.config = config or AhrsConfig()
        self.calibration = calibration or ImuCalibration()
        self._R_decl = rot_z(-self.config.declination_rad)
        self.reset()

    def reset(self) -> None:
        """Forget the state (a clock jump back, a new bag)."""
        self._vqf: Any = None
        self._ts = self.config.sample_period_s
        self._probe: list[tuple[int, Array, Array, Array | None, int | None]] = []
        self._restart_state()
        if self._ts > 0:
            self._make_filter(self._ts)

    def _restart_state(self) -> None:
        """The per-sample state around the filter (stamps, covariance model)."""
        self.t_ns: int | None = None
        self._acc_dev_lp = 0.0
        # 6D by choice: the world frame's heading is the start's, known exactly at first;
        # with a magnetometer expected, the heading is unknown until a field sample is used.
        self._heading_var_extra = self.config.heading_sigma_unknown_rad ** 2 if self.config.use_mag else 0.0
        self._mag_ever_used = False
        self._unaided_s = 0.0
        self._reject_s = _MAG_MAX_REJECTION_S + 0.01

    @property
    def sample_period_s(self) -> float:
        """The measured or configured sample time (0 while it is still being measured)."""
        return self._ts

    def _make_filter(self, ts: float, provisional: bool = False) -> None:
        from vqf import VQF

        c = self.config
        self._filter_ts = ts
        if not provisional:
            self._ts = ts
        self._vqf = VQF(ts, tauAcc=c.tau_acc_s, tauMag=c.tau_mag_s,
                        motionBiasEstEnabled=c.bias_estimation, restBiasEstEnabled=c.bias_estimation,
                        magDistRejectionEnabled=c.mag_disturbance_rejection)

    def update(self, t_ns: int, gyro: Any, accel: Any, mag_t: Any = None,
               mag_t_ns: int | None = None) -> AhrsEstimate | str:
        """One sample: its estimate, or the reason it was refused."""
        g = _finite3(gyro)
        a = _finite3(accel)
        if g is None or a is None:
            return 'gyro or accelerometer sample is not finite'
        if float(a @ a) < 1e-12:
            return 'accelerometer sample has zero norm'
        m = None
        if mag_t is not None:
            m = _finite3(mag_t)
            if m is not None and float(m @ m) < 1e-24:
                m = None
        t_ns = int(t_ns)
        if self.t_ns is not None and t_ns <= self.t_ns:
            return 'stamp is not newer than the previous sample'
        g = self.calibration.gyro(g)
        a = self.calibration.accel(a)
        if m is not None:
            m = self.calibration.mag(m)
        if self._ts <= 0:
            # The sample time is being measured: answer from a provisional filter (nominal
            # 100 Hz, the rate scaled by the stamp gaps) so that every sample has an output;
            # once the probe is full, the filter is rebuilt with the measured period and the
            # probe samples are replayed into it.
            if self._vqf is None:
                self._make_filter(0.01, provisional=True)
            self._probe.append((t_ns, g, a, m, mag_t_ns))
            if len(self._probe) <= _RATE_PROBE:
                return self._step(t_ns, g, a, m, mag_t_ns)
            gaps = np.diff([p[0] for p in self._probe]) * 1e-9
            probe, self._probe = self._probe, []
            self._restart_state()
            self._make_filter(float(np.median(gaps)))
            for args in probe[:-1]:
                self._step(*args)
            return self._step(*probe[-1])  # the probe holds _RATE_PROBE + 1 samples: never empty
        return self._step(t_ns, g, a, m, mag_t_ns)

    def _step(self, t_ns: int, g: Array, a: Array, m: Array | None, mag_t_ns: int | None) -> AhrsEstimate:
        c = self.config
        vqf = self._vqf
        dt = self._filter_ts if self.t_ns is None else (t_ns - self.t_ns) * 1e-9
        self.t_ns = t_ns
        # VQF integrates rate * Ts: scale the rate so that a jittered or late sample turns by
        # rate * (its own dt).
        scale = dt / self._filter_ts
        vqf.updateGyr(g * scale if abs(scale - 1.0) > 1e-6 else g)
        vqf.updateAcc(a)
        fresh = (m is not None and c.use_mag
                 and (mag_t_ns is None or abs(t_ns - int(mag_t_ns)) * 1e-9 <= c.max_mag_age_s))
        if fresh:
            vqf.updateMag(m)
        disturbed = bool(vqf.getMagDistDetected()) if fresh else False
        used = fresh and self._field_used(disturbed, dt)
        if used and not self._mag_ever_used:
            # VQF takes the first field samples with gain 1/N: the heading is that of a
            # single compass reading at once, not an unknown one converging with tau_mag.
            self._mag_ever_used = True
            self._heading_var_extra = c.heading_sigma_floor_rad ** 2
        R = quat_wxyz_to_matrix(vqf.getQuat9D() if (c.use_mag and self._mag_ever_used) else vqf.getQuat6D())
        if c.use_mag and self._mag_ever_used and c.declination_rad:
            R = self._R_decl @ R
        return AhrsEstimate(t_ns, R, self._covariance(dt, a, used), bool(used))

    def _field_used(self, disturbed: bool, dt: float) -> bool:
        """Whether VQF's heading correction took this field sample (mirrors its rejection
        timer: a disturbed field is ignored for at most ``_MAG_MAX_REJECTION_S``, then taken at
        reduced gain; the timer starts expired, so the first field is taken at once)."""
        if not self.config.mag_disturbance_rejection:
            return True
        if disturbed:
            if self._reject_s <= _MAG_MAX_REJECTION_S:
                self._reject_s += dt
                return False
            return True
        self._reject_s = max(self._reject_s - _MAG_REJECTION_FACTOR * dt, 0.0)
        return True

    def _covariance(self, dt: float, a: Array, mag_ok: bool) -> Array:
        """Tilt and heading variance (module docstring): floors, plus sustained acceleration
        for tilt (low-passed with tau_acc, as VQF's correction is), plus the heading's random
        walk while the field is not used: gyro noise (sigma^2 dt) and the remaining bias
        uncertainty b of VQF's estimate, whose heading error b t grows as d(b t)^2 = 2 b^2 t dt."""
        c = self.config
        if c.constant_sigma_rad > 0:
            return np.eye(3) * c.constant_sigma_rad ** 2
        dt = max(dt, 0.0)
        x, y, z = a.tolist()
        dev = abs(math.sqrt(x * x + y * y + z * z) - c.gravity_m_s2) / c.gravity_m_s2
        self._acc_dev_lp += min(1.0, dt / c.tau_acc_s) * (dev - self._acc_dev_lp)
        tilt_var = c.tilt_sigma_floor_rad ** 2 + self._acc_dev_lp ** 2
        if mag_ok:
            # The field is in use: the extra heading uncertainty decays with tau_mag.
            self._heading_var_extra *= math.exp(-dt / c.tau_mag_s)
            self._unaided_s = 0.0
        else:
            _, bias_sigma = self._vqf.getBiasEstimate()
            self._unaided_s += dt
            self._heading_var_extra += c.gyro_noise_rad_s ** 2 * dt + 2.0 * bias_sigma ** 2 * self._unaided_s * dt
        heading_var = min(c.heading_sigma_floor_rad ** 2 + self._heading_var_extra, math.pi ** 2)
        return np.array([[tilt_var, 0.0, 0.0], [0.0, tilt_var, 0.0], [0.0, 0.0, heading_var]])
