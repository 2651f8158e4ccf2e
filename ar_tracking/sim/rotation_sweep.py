"""Scenario ``rotation_sweep``: a person at one spot sweeps a phone around, with its sensors.

This is the situation of Langlotz et al. 2011: the user stands at an annotated spot and turns
the phone (more than a full turn, with pauses and changes of direction), so that a panorama
can be mapped and annotations re-detected; the phone's gyroscope, accelerometer, magnetometer
and GPS are recorded alongside the camera. Everything here is deterministic given
``(seed, session)`` and cheap to evaluate at any time, because the motion is given in closed form.

Frames and conventions (../shared/DESIGN.md section 3):

* ``R_enu_cam`` rotates camera_optical vectors (x right, y down, z forward) into ENU.
* The phone's IMU body frame is x right, y up along the screen, z out of the screen toward the
  user: ``R_IMU_CAM = diag(1, -1, -1)``.
* Orientation is built from a heading (compass azimuth of the optical axis, clockwise from
  north), a pitch (elevation of the optical axis) and a roll (about the optical axis, positive
  when the image turns clockwise for the user): ``R = Rz(-heading) @ R0 @ Rx(pitch) @ Rz(roll)``,
  ``R0`` being the level camera looking north. This matches
  :func:`ar_tracking.core.rotations.camera_heading_pitch_roll_deg`.
* The magnetic disturbance's heading deflection is what a compass would be off by: the
  compass heading computed from the disturbed field minus the one from the true field
  (positive = the compass reads too far clockwise, i.e. the field turned counter-clockwise).

Profiles (``profile`` argument of :func:`make_scenario`):

* ``'hard'`` (default) models what real phones do; each new phenomenon draws from its own
  random stream (so the ``'kind'`` streams are untouched), the disturbances and exposure jumps
  reuse the kind draws (same schedule) and only change their effect: hand linear acceleration
  (a hand motion of a few cm at 0.5-3 Hz and the phone 0.2-0.4 m in front of the body's
  turning axis: |a| RMS about 0.7 m/s^2, 1-2 m/s^2 in sweeps); magnetic disturbances that turn
  the horizontal field by 2-10 deg about the up axis with |B| and dip unchanged (also during
  the ramps); a rough magnetometer calibration (residual hard iron 0.4-1.2 uT per axis,
  soft-iron correction 20-50 % off its deviation from identity: against the 21 uT horizontal
  field a compass error that swings by about 3-9 deg peak to peak with heading); a gyro bias
  that drifts by a random walk (a few mrad/s per minute) from the
  constant part the calibration measured; accelerometer scale errors of 0.5-1 %; auto-exposure
  jumps 1.5 times larger; and a **camera-IMU time offset**: the IMU and magnetometer header
  stamps are the true sample time plus a constant offset of 2-8 ms (either sign,
  :attr:`Scenario.imu_time_offset_ns`), while camera stamps and the ground truth
  (``/ground_truth/*``) carry the true capture time; and a **camera pipeline latency**: a
  frame is written to the bag (arrives) 30-120 ms after its stamp
  (:attr:`Scenario.camera_latency_ns`), behind the IMU samples of that time, as in a bag a
  phone records at arrival.
* ``'kind'``: the earlier, easier simulator (hand sway of 1 cm, phone 2-4 cm from the turning
  axis, half the disturbances change |B| and dip, calibration 1-3 % off, constant gyro bias, no
  time offset). Its bags are byte for byte those of the simulator before the profiles existed
  (the paper's Fig. 8 comparison).

The camera images are rendered by rotation only, from the panorama of the standing spot: the
hand motion and the lever arm move the ground-truth position, not the image (no parallax).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from .imu import imu_samples, specific_force_cam
from .phone_sensors import (Disturbances, EarthField, SensorErrors, heading_deflection, make_disturbances,
                            make_hard_sensor_errors, make_sensor_errors)
from .gps import EARTH_RADIUS_M, GPS_RATE_HZ, GpsSamples, simulate_gps  # noqa: F401 (re-exported)
from .rng import rng_stream

Array = NDArray[np.float64]

GRAVITY_M_S2 = 9.81
#: camera_optical -> imu (vectors): x stays, y (down) becomes -y (up the screen), z (forward)
#: becomes -z (out of the screen, toward the user).
R_IMU_CAM = np.diag([1.0, -1.0, -1.0])
#: The level camera looking north: camera x -> east, y -> down, z -> north.
R0_ENU_CAM = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

IMU_RATE_HZ = 100
CAMERA_RATE_HZ = 30
MAX_PAN_PEAK_DEG_S = 84.0  # leaves room for hand tremor below the 90 deg/s limit
EXPOSURE_TIME_S = 0.012

SESSIONS = ('authoring', 'browsing')
PROFILES = ('hard', 'kind')

#: Hard profile (ranges drawn per scenario; see the module docstring).
HARD_LEVER_ARM_M = (0.2, 0.4)  # phone in front of the body's turning axis
HARD_HAND_SWEEP_M = (0.01, 0.03)  # per axis, at 0.5-1.2 Hz (acceleration amplitude <= 0.5 m/s^2)
HARD_HAND_SWEEP_MAX_ACCEL_M_S2 = 0.5
HARD_HAND_TREMOR_ACCEL_M_S2 = (0.05, 0.2)  # per axis, at 1.5-3 Hz
HARD_IRON_RESIDUAL_T = (0.4e-6, 1.2e-6)  # per axis, random sign: 1.5-5 deg of heading error swing
HARD_SOFT_IRON_RESIDUAL = (0.2, 0.5)  # of the soft-iron correction's deviation from identity
HARD_IMU_TIME_OFFSET_S = (0.002, 0.008)  # |offset|, random sign
HARD_READOUT_S = (0.008, 0.030)  # a phone camera's rolling-shutter readout (not in the sidecar)
HARD_CAMERA_LATENCY_S = (0.03, 0.12)  # a frame is logged this long after its stamp (pipeline latency)
HARD_EXPOSURE_JUMP_FACTOR = 1.5  # auto-exposure jumps of 30-75 % instead of 20-50 %

#: Latitude/longitude around which the spots of all seeds lie (Graz), degrees.
BASE_LATITUDE_DEG = 47.06
BASE_LONGITUDE_DEG = 15.45


# --------------------------------------------------------------------------------------------
# Smooth signals in closed form


@dataclass(frozen=True)
class SineSum:
    """``offset + sum_i amp_i * sin(2 pi f_i t + phase_i)`` with exact derivatives."""

    offset: float
    amp: Array
    freq_hz: Array
    phase: Array

    def eval(self, t: Array, order: int = 0) -> Array:
        """Value (order 0) or time derivative of order 1 or 2 at times ``t`` (s)."""
        t = np.asarray(t, dtype=float)[..., None]
        w = 2 * math.pi * self.freq_hz
        arg = w * t + self.phase
        if order == 0:
            return self.offset + np.sum(self.amp * np.sin(arg), axis=-1)
        if order == 1:
            return np.sum(self.amp * w * np.cos(arg), axis=-1)
        return -np.sum(self.amp * w * w * np.sin(arg), axis=-1)

    @staticmethod
    def random(rng: np.random.Generator, total_amp: float, f_lo: float, f_hi: float, n: int,
               offset: float = 0.0) -> 'SineSum':
        """``n`` components whose amplitudes sum to ``total_amp`` (so |x - offset| <= it)."""
        weights = rng.uniform(0.3, 1.0, n)
        return SineSum(offset, total_amp * weights / weights.sum(), rng.uniform(f_lo, f_hi, n),
                       rng.uniform(0, 2 * math.pi, n))


@dataclass(frozen=True)
class PanProfile:
    """Pan rate as a train of non-overlapping ``sin^2`` bumps (smooth start and stop).

    Bump k starts at ``start_s[k]``, lasts ``width_s[k]`` and peaks at ``peak_rad_s[k]`` (signed),
    so the peak rate is exactly the largest ``|peak|`` and the angle turned is ``peak*width/2``.
    """

    start_s: Array
    width_s: Array
    peak_rad_s: Array

    def _tau(self, t: Array) -> Array:
        t = np.asarray(t, dtype=float)[..., None]
        return np.clip((t - self.start_s) / self.width_s, 0.0, 1.0)

    def angle(self, t: Array) -> Array:
        """Heading turned since the start (rad)."""
        tau = self._tau(t)
        integral = tau / 2 - np.sin(2 * math.pi * tau) / (4 * math.pi)
        return np.sum(self.peak_rad_s * self.width_s * integral, axis=-1)

    def rate(self, t: Array) -> Array:
        """Pan rate (rad/s)."""
        return np.sum(self.peak_rad_s * np.sin(math.pi * self._tau(t)) ** 2, axis=-1)

    def accel(self, t: Array) -> Array:
        """Pan acceleration (rad/s^2)."""
        tau = self._tau(t)
        inside = (tau > 0) & (tau < 1)
        return np.sum(inside * self.peak_rad_s * math.pi / self.width_s
                      * np.sin(2 * math.pi * tau), axis=-1)

    @property
    def total_turn_rad(self) -> float:
        """Sum of |angle| of all sweeps (how much the user turned, both directions)."""
        return float(np.sum(np.abs(self.peak_rad_s) * self.width_s / 2))


def make_pan_profile(rng: np.random.Generator, duration_s: float) -> PanProfile:
    """Sweeps with pauses; mostly one direction, sometimes back; > one full turn per 40 s."""
    direction = 1.0 if rng.random() < 0.6 else -1.0
    starts, widths, peaks = [], [], []
    t = rng.uniform(0.6, 1.2)  # hold still first, as people do when an app starts
    while t < duration_s:
        w = rng.uniform(1.2, 4.0)
        peak = rng.uniform(78.0, MAX_PAN_PEAK_DEG_S) if rng.random() < 0.25 else \
            rng.uniform(22.0, 70.0)
        sign = direction if rng.random() < 0.78 else -direction
        starts.append(t)
        widths.append(w)
        peaks.append(sign * math.radians(peak))
        t += w + rng.uniform(0.25, 1.6)
    pk = np.array(peaks)
    wd = np.array(widths)
    # Make sure the net turn exceeds a full turn (+ margin) on bags of 40 s or more.
    need = math.radians(400.0) if duration_s >= 40.0 else 0.0
    for k in np.argsort(-wd):
        if abs(np.sum(pk * wd / 2)) >= need:
            break
        if np.sign(pk[k]) != direction:
            pk[k] = -pk[k]
    return PanProfile(np.array(starts), wd, pk)


# --------------------------------------------------------------------------------------------
# Trajectory


def orientation_from_angles(heading: Array, pitch: Array, roll: Array) -> Array:
    """R_enu_cam (N, 3, 3) from heading / pitch / roll (radians, see the module docstring)."""
    heading, pitch, roll = (np.atleast_1d(np.asarray(a, dtype=float))
                            for a in (heading, pitch, roll))
    ch, sh = np.cos(heading), np.sin(heading)
    Rz = np.zeros((len(heading), 3, 3))
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = ch, sh, -sh, ch, 1.0
    cp, sp = np.cos(pitch), np.sin(pitch)
    Rx = np.zeros((len(pitch), 3, 3))
    Rx[:, 0, 0], Rx[:, 1, 1], Rx[:, 1, 2], Rx[:, 2, 1], Rx[:, 2, 2] = 1.0, cp, -sp, sp, cp
    cr, sr = np.cos(roll), np.sin(roll)
    Rr = np.zeros((len(roll), 3, 3))
    Rr[:, 0, 0], Rr[:, 0, 1], Rr[:, 1, 0], Rr[:, 1, 1], Rr[:, 2, 2] = cr, -sr, sr, cr, 1.0
    return Rz @ R0_ENU_CAM @ Rx @ Rr


@dataclass(frozen=True)
class Trajectory:
    """Closed-form motion of the phone: orientation, angular velocity, position, acceleration."""

    duration_s: float
    heading0_rad: float
    pan: PanProfile
    heading_tremor: SineSum
    pitch: SineSum
    roll: SineSum
    hand: tuple[SineSum, SineSum, SineSum]  # x, y, z hand sway (m)
    lever_arm_m: float  # phone in front of the body's rotation axis
    spot_enu: Array  # where the person stands (camera height), metres

    def heading(self, t: Array, order: int = 0) -> Array:
        """Compass heading of the optical axis (rad, unwrapped) or its derivative of ``order``."""
        base = self.heading0_rad if order == 0 else 0.0
        pan = (self.pan.angle, self.pan.rate, self.pan.accel)[order](t)
        return base + pan + self.heading_tremor.eval(t, order)

    def angles(self, t: Array) -> tuple[Array, Array, Array]:
        """(heading, pitch, roll) in radians at times ``t``."""
        return self.heading(t), self.pitch.eval(t), self.roll.eval(t)

    def R_enu_cam(self, t: Array) -> Array:
        """Camera orientation (N, 3, 3) at times ``t`` (s from the start)."""
        return orientation_from_angles(*self.angles(t))

    def omega_cam(self, t: Array) -> Array:
        """Angular velocity of the camera in its own frame (N, 3), rad/s (exact)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        dh, dp, dr = self.heading(t, 1), self.pitch.eval(t, 1), self.roll.eval(t, 1)
        p, r = self.pitch.eval(t), self.roll.eval(t)
        # omega = Rz(r)^T Rx(p)^T (0, dh, 0) + Rz(r)^T (dp, 0, 0) + (0, 0, dr)
        v = np.stack([np.zeros_like(dh), dh * np.cos(p), -dh * np.sin(p)], -1)  # Rx(p)^T (0,dh,0)
        v[:, 0] += dp
        cr, sr = np.cos(r), np.sin(r)
        return np.stack([cr * v[:, 0] + sr * v[:, 1], -sr * v[:, 0] + cr * v[:, 1], v[:, 2] + dr],
                        -1)

    def position(self, t: Array) -> Array:
        """Camera position in ENU (N, 3), metres."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        yaw = self.heading(t) - self.heading_tremor.eval(t)  # the body turns, the wrist trembles
        lever = self.lever_arm_m * np.stack([np.sin(yaw), np.cos(yaw), np.zeros_like(yaw)], -1)
        sway = np.stack([h.eval(t) for h in self.hand], -1)
        return self.spot_enu + lever + sway

    def acceleration(self, t: Array) -> Array:
        """Camera acceleration in ENU (N, 3), m/s^2 (exact)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        yaw = self.heading(t) - self.heading_tremor.eval(t)
        d1 = self.heading(t, 1) - self.heading_tremor.eval(t, 1)
        d2 = self.heading(t, 2) - self.heading_tremor.eval(t, 2)
        L = self.lever_arm_m
        lever = L * np.stack([d2 * np.cos(yaw) - d1 ** 2 * np.sin(yaw),
                              -d2 * np.sin(yaw) - d1 ** 2 * np.cos(yaw), np.zeros_like(yaw)], -1)
        return lever + np.stack([h.eval(t, 2) for h in self.hand], -1)


def session_offset(seed: int, session: str) -> Array:
    """Where the session's person stands relative to the authoring spot (ENU, metres)."""
    if session == 'authoring':
        return np.zeros(3)
    rng = rng_stream(seed, 'standing', session)
    r, a = rng.uniform(0.4, 1.5), rng.uniform(0, 2 * math.pi)
    return np.array([r * math.sin(a), r * math.cos(a), rng.uniform(-0.1, 0.1)])


def check_profile(profile: str) -> None:
    """Raises ValueError for a profile other than 'hard' and 'kind'."""
    if profile not in PROFILES:
        raise ValueError(f'unknown profile {profile!r} (use {" or ".join(PROFILES)})')


def make_trajectory(seed: int, session: str, duration_s: float, profile: str = 'hard'
                    ) -> Trajectory:
    """The sweep of one session: random start heading, pan bumps, pitch/roll wander, tremor.

    The 'hard' profile adds the hand's linear motion (:func:`_hard_hand_motion`) and puts the
    phone 0.2-0.4 m in front of the body's turning axis (stream 'hand-motion'); everything
    else is the 'kind' trajectory."""
    check_profile(profile)
    rng = rng_stream(seed, 'trajectory', session)
    deg = math.radians
    mean_pitch = rng.uniform(0.0, 8.0)
    kind = Trajectory(
        duration_s=float(duration_s),
        heading0_rad=float(rng.uniform(0, 2 * math.pi)),
        pan=make_pan_profile(rng, duration_s),
        heading_tremor=_tremor(rng),
        pitch=_add(SineSum.random(rng, deg(19.0 - abs(mean_pitch)), 0.02, 0.12, 3,
                                  offset=deg(mean_pitch)), _tremor(rng)),
        roll=_add(SineSum.random(rng, deg(3.5), 0.04, 0.3, 3), _tremor(rng)),
        hand=tuple(SineSum.random(rng, 0.01, 0.08, 0.35, 2) for _ in range(3)),  # type: ignore
        lever_arm_m=float(rng.uniform(0.02, 0.04)),
        spot_enu=session_offset(seed, session),
    )
    if profile == 'kind':
        return kind
    hand_rng = rng_stream(seed, 'hand-motion', session)
    lever = float(hand_rng.uniform(*HARD_LEVER_ARM_M))
    extra = [_hard_hand_motion(hand_rng) for _ in range(3)]
    return replace(kind, hand=tuple(_add(h, e) for h, e in zip(kind.hand, extra, strict=True)),
                   lever_arm_m=lever)


def _hard_hand_motion(rng: np.random.Generator) -> SineSum:
    """One axis of the hand's linear motion (m): a sweep of 1-3 cm at 0.5-1.2 Hz (its
    acceleration amplitude capped at 0.5 m/s^2) and a tremor of 0.05-0.2 m/s^2 at 1.5-3 Hz.
    Zero-mean velocity, bounded position, exact acceleration."""
    f = np.array([rng.uniform(0.5, 1.2), rng.uniform(1.5, 3.0)])
    w2 = (2 * math.pi * f) ** 2
    sweep = min(rng.uniform(*HARD_HAND_SWEEP_M), HARD_HAND_SWEEP_MAX_ACCEL_M_S2 / w2[0])
    tremor = rng.uniform(*HARD_HAND_TREMOR_ACCEL_M_S2) / w2[1]
    return SineSum(0.0, np.array([sweep, tremor]), f, rng.uniform(0, 2 * math.pi, 2))


def _tremor(rng: np.random.Generator) -> SineSum:
    """Hand sway (~0.1 deg, 1.5-3 Hz) and physiological tremor (~0.02 deg, 7-10 Hz)."""
    amp = np.radians([rng.uniform(0.05, 0.1), rng.uniform(0.01, 0.02)])
    return SineSum(0.0, amp, np.array([rng.uniform(1.5, 3.0), rng.uniform(7.0, 10.0)]),
                   rng.uniform(0, 2 * math.pi, 2))


def _add(a: SineSum, b: SineSum) -> SineSum:
    return SineSum(a.offset + b.offset, np.concatenate([a.amp, b.amp]),
                   np.concatenate([a.freq_hz, b.freq_hz]), np.concatenate([a.phase, b.phase]))


# --------------------------------------------------------------------------------------------
# Scenario and sensor samples (the sensor models: .phone_sensors; the IMU: .imu)


@dataclass(frozen=True)
class Scenario:
    """Everything of one (seed, session) recording except the world's pictures."""

    seed: int
    session: str
    duration_s: float
    trajectory: Trajectory
    earth: EarthField
    disturbances: Disturbances
    errors: SensorErrors
    origin_lat_lon_alt: tuple[float, float, float]
    profile: str = 'hard'
    #: IMU / magnetometer header stamp minus the true sample time (0 in the 'kind' profile).
    imu_time_offset_ns: int = 0
    #: Rolling-shutter readout of the camera, s: row r of a frame stamped t is exposed around
    #: t + readout_s (r + 0.5) / rows (0: a global shutter, the 'kind' profile's).
    readout_s: float = 0.0
    #: Whether the readout was asked for (and so goes into the sidecar, as a user who knows
    #: their camera would give it) or is the hard profile's own (which a user seldom knows).
    readout_declared: bool = False
    #: How long after its stamp a camera frame is logged, ns (the order it arrives in: a phone's
    #: camera pipeline delivers frames tens of ms after the IMU samples of the same time).
    camera_latency_ns: int = 0


def make_scenario(seed: int, session: str, duration_s: float,
                  declination_rad: float = 0.0, profile: str = 'hard',
                  imu_time_offset_s: float | None = None, readout_s: float | None = None,
                  camera_latency_s: float | None = None) -> Scenario:
    """The scenario for a seed and session; the spot (and so the GPS origin) is the seed's.

    ``profile``: 'hard' (default, a realistic phone) or 'kind' (the earlier, easier simulator);
    see the module docstring. ``imu_time_offset_s`` replaces the profile's camera-IMU time
    offset (e.g. a phone whose driver delays the camera's stamps by tens of ms); ``readout_s``
    replaces the profile's rolling-shutter readout (hard: 8-30 ms, drawn per seed and session;
    kind: 0, a global shutter); ``camera_latency_s`` the camera frames' arrival latency (hard:
    30-120 ms; kind: 0); everything else stays the seed's."""
    if session not in SESSIONS:
        raise ValueError(f'unknown session {session!r} (use {" or ".join(SESSIONS)})')
    check_profile(profile)
    hard = profile == 'hard'
    earth = EarthField(declination_rad=declination_rad)
    spot = rng_stream(seed, 'spot')
    origin = (BASE_LATITUDE_DEG + spot.uniform(-0.03, 0.03),
              BASE_LONGITUDE_DEG + spot.uniform(-0.045, 0.045), 353.0 + spot.uniform(-5, 40))
    errors = make_sensor_errors(rng_stream(seed, 'device', session))
    offset_ns = 0
    if hard:
        errors = make_hard_sensor_errors(seed, session, duration_s, errors)
        rng = rng_stream(seed, 'imu-time-offset', session)
        offset_ns = int(round(rng.uniform(*HARD_IMU_TIME_OFFSET_S) * 1e9)) * \
            (1 if rng.random() < 0.5 else -1)
    if imu_time_offset_s is not None:
        offset_ns = int(round(imu_time_offset_s * 1e9))
    readout = 0.0
    if hard:
        readout = float(rng_stream(seed, 'camera-readout', session).uniform(*HARD_READOUT_S))
    if readout_s is not None:
        readout = float(readout_s)
    latency = 0.0
    if hard:
        latency = float(rng_stream(seed, 'camera-latency', session).uniform(*HARD_CAMERA_LATENCY_S))
    if camera_latency_s is not None:
        latency = float(camera_latency_s)
    return Scenario(
        seed=seed, session=session, duration_s=float(duration_s),
        trajectory=make_trajectory(seed, session, duration_s, profile), earth=earth,
        disturbances=make_disturbances(rng_stream(seed, 'disturbances', session), duration_s,
                                       earth, keep_field=hard),
        errors=errors,
        origin_lat_lon_alt=origin,
        profile=profile,
        imu_time_offset_ns=offset_ns,
        readout_s=readout,
        readout_declared=readout_s is not None and readout_s > 0,
        camera_latency_ns=int(round(latency * 1e9)),
    )


@dataclass(frozen=True)
class ImuSamples:
    """IMU-rate samples: measurements in the imu frame and the ground truth."""

    t_s: Array
    gyro_rad_s: Array  # (N, 3) imu frame
    accel_m_s2: Array  # (N, 3) imu frame, specific force
    mag_t: Array  # (N, 3) imu frame, raw (hard and soft iron, disturbance, noise)
    R_enu_cam: Array  # (N, 3, 3) truth
    position_enu: Array  # (N, 3) truth
    deflection_rad: Array  # (N,) compass error caused by the disturbance
    extra_field_t: Array  # (N,) |B + disturbance| - |B|
    gyro_bias_rad_s: Array  # (N, 3) truth: the constant bias plus its drift (hard profile)


def simulate_imu(scn: Scenario, t_s: Array) -> ImuSamples:
    """Gyro, accelerometer and magnetometer samples at true times ``t_s`` (exact motion +
    errors; gyro and accelerometer by :func:`.imu.imu_samples`). Their header stamps are ``t_s``
    plus ``scn.imu_time_offset_ns`` (bagmaker)."""
    rng = rng_stream(scn.seed, 'imu-noise', scn.session)
    traj, err = scn.trajectory, scn.errors
    n = len(t_s)
    R = traj.R_enu_cam(t_s)
    gyro, accel = imu_samples(
        traj.omega_cam(t_s), specific_force_cam(R, traj.acceleration(t_s), GRAVITY_M_S2), rng=rng,
        R_imu_cam=R_IMU_CAM, gyro_bias_rad_s=err.gyro_bias_rad_s,
        accel_bias_m_s2=err.accel_bias_m_s2, gyro_noise_rad_s=err.gyro_noise_rad_s,
        accel_noise_m_s2=err.accel_noise_m_s2,
        gyro_drift_rad_s=None if err.gyro_bias_drift is None else err.gyro_bias_drift.at(t_s),
        accel_scale=err.accel_scale, gyro_scale=err.gyro_scale)
    R_imu_enu = R_IMU_CAM @ np.swapaxes(R, 1, 2)
    b = scn.earth.vector_enu
    b_meas = b + scn.disturbances.field(t_s)
    mag = np.einsum('nij,nj->ni', R_imu_enu, b_meas) @ err.soft_iron.T + err.hard_iron_t
    mag += rng.normal(0.0, err.mag_noise_t, (n, 3))
    return ImuSamples(
        t_s=np.asarray(t_s, float), gyro_rad_s=gyro, accel_m_s2=accel, mag_t=mag, R_enu_cam=R,
        position_enu=traj.position(t_s),
        deflection_rad=heading_deflection(np.broadcast_to(b, b_meas.shape), b_meas),
        extra_field_t=np.linalg.norm(b_meas, axis=1) - np.linalg.norm(b),
        gyro_bias_rad_s=err.gyro_bias_at(t_s),
    )


@dataclass(frozen=True)
class Exposure:
    """Auto-exposure and white balance of the phone camera: jumps plus slow drift."""

    jump_s: Array
    jump_factor: Array
    jump_wb: Array  # (k, 3) white balance after each jump
    drift: SineSum  # log-gain drift

    def at(self, t: Array) -> tuple[Array, Array]:
        """(gain factor (N,), white balance (N, 3)) at times ``t``; a jump takes ~0.1 s."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        step = np.clip((t[:, None] - self.jump_s) / 0.1, 0, 1)
        log_gain = step @ np.log(self.jump_factor) + self.drift.eval(t)
        wb = np.ones((len(t), 3))
        for k in range(len(self.jump_s)):  # white balance moves with the jumps
            prev = self.jump_wb[k - 1] if k else np.ones(3)
            wb += step[:, k:k + 1] * (self.jump_wb[k] - prev)
        return np.exp(log_gain), wb


def make_exposure(seed: int, session: str, duration_s: float, profile: str = 'hard'
                  ) -> Exposure:
    """Several jumps of 20-50 % a minute (at least one on a 5 s bag), back toward the middle;
    30-75 % in the 'hard' profile (the same draws, larger jumps)."""
    check_profile(profile)
    scale = HARD_EXPOSURE_JUMP_FACTOR if profile == 'hard' else 1.0
    rng = rng_stream(seed, 'exposure', session)
    n = max(1, int(round(duration_s / 60.0 * rng.uniform(4.0, 7.0)))) if duration_s >= 3 else 0
    times = np.sort(rng.uniform(0.15, 0.9, n)) * duration_s if n else np.zeros(0)
    factors, wbs = [], []
    log_g = 0.0
    for _ in range(n):
        m = rng.uniform(0.2, 0.5)
        if scale != 1.0:
            m *= scale
        up = rng.random() < 1.0 / (1.0 + math.exp(4.0 * log_g))
        f = 1.0 + m if up else 1.0 / (1.0 + m)
        log_g += math.log(f)
        factors.append(f)
        wb = rng.uniform(0.96, 1.04, 3)
        wbs.append(wb / wb[1])
    return Exposure(times, np.array(factors, float), np.array(wbs, float).reshape(-1, 3),
                    SineSum.random(rng, 0.12, 1 / 45.0, 1 / 15.0, 2))


def calibration_params(scn: Scenario) -> dict[str, list[float] | float]:
    """What a user would have measured for this device: the truth with 1-3 % errors.

    The soft-iron matrix is the inverse of the true distortion with its deviation from identity
    a few percent off; everything is plain Python floats for YAML. In the 'hard' profile the
    magnetometer calibration is rough (stream 'calibration-residual'): the hard-iron offset is
    0.4-1.2 uT off per axis and the soft-iron matrix's deviation from identity 20-50 % off; the
    gyro bias is an estimate of the constant part only (the drift is not in it).
    """
    rng = rng_stream(scn.seed, 'calibration', scn.session)
    err = scn.errors

    def off(v: Array) -> Array:
        return v * (1.0 + rng.uniform(0.01, 0.03, np.shape(v)) * rng.choice([-1, 1], np.shape(v)))

    S = np.linalg.inv(err.soft_iron)
    S_est = np.eye(3) + off(S - np.eye(3))
    gyro_bias, accel_bias, hard_iron = (off(err.gyro_bias_rad_s), off(err.accel_bias_m_s2),
                                        off(err.hard_iron_t))
    if scn.profile == 'hard':
        res = rng_stream(scn.seed, 'calibration-residual', scn.session)
        hard_iron = err.hard_iron_t + res.uniform(*HARD_IRON_RESIDUAL_T, 3) * \
            res.choice([-1.0, 1.0], 3)
        rel = res.uniform(*HARD_SOFT_IRON_RESIDUAL, (3, 3)) * res.choice([-1.0, 1.0], (3, 3))
        rel = np.triu(rel) + np.triu(rel, 1).T  # the truth is symmetric: so is the estimate
        S_est = np.eye(3) + (S - np.eye(3)) * (1.0 + rel)
    return {
        'gyro_bias': [float(x) for x in gyro_bias],
        'accel_bias': [float(x) for x in accel_bias],
        'hard_iron_offset': [float(x) for x in hard_iron],
        'soft_iron_matrix': [float(x) for x in S_est.ravel()],
        'declination_rad': float(scn.earth.declination_rad),
        'expected_field_t': float(scn.earth.magnitude_t),
        'expected_dip_rad': float(round(scn.earth.dip_rad, 4)),
    }


def _blur_offsets(traj: Trajectory, t_s: float, fx_px: float) -> Array:
    """Times (s, relative to ``t_s``) spread over the exposure centred there: 1-5 of them,
    more when the camera turns fast (about one per 1.2 pixels of motion)."""
    speed = float(np.linalg.norm(traj.omega_cam(np.array([t_s]))[0]))
    n = int(min(5, max(1, math.ceil(speed * EXPOSURE_TIME_S * fx_px / 1.2))))
    return np.linspace(-0.5, 0.5, n) * EXPOSURE_TIME_S if n > 1 else np.zeros(1)


def blur_samples(traj: Trajectory, t_s: float, fx_px: float) -> Array:
    """Orientations spread over the exposure (1-5 of them, more when turning fast)."""
    return traj.R_enu_cam(t_s + _blur_offsets(traj, t_s, fx_px))


def frame_orientations(traj: Trajectory, t_s: float, fx_px: float, readout_s: float, rows: int) -> Array:
    """The orientations a frame stamped ``t_s`` is rendered with: :func:`blur_samples` (n, 3, 3)
    for a global shutter; with a rolling shutter (``readout_s`` > 0) one set per image row,
    (n, rows, 3, 3), row r exposed around ``t_s + readout_s (r + 0.5) / rows``."""
    if readout_s <= 0.0:
        return blur_samples(traj, t_s, fx_px)
    blur = _blur_offsets(traj, t_s + 0.5 * readout_s, fx_px)  # as many as the middle row needs
    row_t = t_s + readout_s * (np.arange(rows) + 0.5) / rows
    return traj.R_enu_cam((blur[:, None] + row_t[None, :]).ravel()).reshape(len(blur), rows, 3, 3)
