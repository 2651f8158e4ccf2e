"""Hybrid orientation: vision (relative) + compass/accelerometer (absolute), Langlotz 2011 sec. 5.

Notation (paper, footnote 1: R_BA maps frame A into frame B) and ours (``R_a_b`` rotates b-vectors
into a, ../shared/DESIGN.md sec. 3):

* N = world (``enu``), D = device (``camera_optical``), P = panorama (the camera at the
  panorama's first frame);
* R_DN = R_cam_enu, the sensor orientation (gravity + field, eq. 3-4, from imu_magnetometer);
* R_DP = R_cam_pano, the visual tracker's orientation (relative to the panorama);
* R_PN = R_pano_enu, the fixed rotation of the panorama in the world that the filter estimates.

Eq. 1-2: ``R_DP R_PN = R_DN``, so each pair of simultaneous measurements gives
``R_PN = R_DP^-1 R_DN``. The EKF (eq. 5) keeps an estimate R_hat and a 3-vector error state
``m ~ N(0, P)`` in so(3) with ``R_PN = exp(m) R_hat`` (a left, panorama-frame error). The motion
model is constant (R_PN does not move) with a random-walk process noise that lets the estimate
follow a slowly drifting visual tracker. The measurement (eq. 6, read as the residual of eq. 2)
is ``z = log(R_DP^-1 R_DN R_hat^-1) = m`` with the identity Jacobian; after each update the
error is folded into R_hat (``R_hat <- exp(m) R_hat``) and reset to zero.
The global camera orientation is eq. 1 with the filtered R_PN: ``R_enu_cam = R_hat^T R_pano_cam``.

Past the paper, where sec. 7 names its limits:

* **Disturbed field** (a passing car, a steel pillar): a sample is rejected when the sensor's own
  covariance says the field's magnitude or dip is off (imu_magnetometer inflates the heading
  variance then), when its Mahalanobis distance ``z^T S^-1 z`` exceeds a chi-square gate, or when
  the short-time mean of the heading innovations leaves a band: a disturbance that only turns
  the horizontal field keeps |B| and the dip, and per sample it hides in the noise, but over half
  a second it is a bias of several degrees that the vision-anchored prediction sees at once.
* **Long stays in one direction** (sec. 7: "measuring errors for a longer time in a certain
  orientation will pull the estimate towards that orientation"): the compass error depends on the
  direction (residual hard/soft iron, local field), so samples from one direction share one
  error and do not average it out. The measurement noise of a sample is multiplied by
  ``max(1, c_b / c_ref)``, c_b being the exponentially forgotten count of recent samples in its
  heading bin: each direction's information grows only logarithmically past ``c_ref`` samples, so
  the estimate tends to the average over directions, not over time, and old samples fade.

Also here: :class:`GyroBackup`, the "sensor-based tracking as a backup" while the visual tracker
is lost (integrates the gyro from the last global orientation, with a gyro bias learnt against
the visual tracker while it works), and :class:`RotationBuffer` to pair the two streams by stamp
(slerp between the bracketing samples, never arrival order).
"""
from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass, field
from typing import Deque

import numpy as np
from numpy.typing import NDArray

from .rotations import nearest_rotation, so3_exp, so3_log

logger = logging.getLogger(__name__)

Array = NDArray[np.float64]

UP = np.array([0.0, 0.0, 1.0])
_I3 = np.eye(3)
_I3.setflags(write=False)


def slerp(R_a: Array, R_b: Array, s: float) -> Array:
    """The rotation a fraction s of the way from R_a to R_b (geodesic)."""
    return R_a @ so3_exp(s * so3_log(R_a.T @ R_b))


# ----------------------------------------------------------------------------------------------
# Pairing by stamp.


class RotationBuffer:
    """Recent stamped rotations of one stream, interpolated at any stamp inside their span.

    Used to read the visual orientation at a sensor sample's stamp (sec. 5: "simultaneous
    measurements"); a query across a gap longer than ``max_gap_ns`` (the tracker was lost) has no
    answer.
    """

    def __init__(self, max_gap_ns: int, keep_ns: int = 2_000_000_000) -> None:
        self.max_gap_ns = int(max_gap_ns)
        self.keep_ns = int(keep_ns)
        self.t: Deque[int] = deque()
        self.R: Deque[Array] = deque()

    def clear(self) -> None:
        self.t.clear()
        self.R.clear()

    def add(self, t_ns: int, R: Array) -> None:
        """Append a sample (stamps must increase; an older one is ignored)."""
        if self.t and t_ns <= self.t[-1]:
            return
        self.t.append(int(t_ns))
        self.R.append(R)
        while len(self.t) > 2 and self.t[-1] - self.t[1] > self.keep_ns:
            self.t.popleft()
            self.R.popleft()

    @property
    def newest_ns(self) -> int | None:
        return self.t[-1] if self.t else None

    def at(self, t_ns: int) -> Array | None:
        """Slerp at t_ns, or None outside the span or across a gap."""
        if not self.t or t_ns < self.t[0] or t_ns > self.t[-1]:
            return None
        # Walk back from the newest sample: queries are nearly always recent.
        i = len(self.t) - 1
        while i > 0 and self.t[i - 1] >= t_ns:
            i -= 1
        if self.t[i] == t_ns:
            return self.R[i]
        t0, t1 = self.t[i - 1], self.t[i]
        if t1 - t0 > self.max_gap_ns:
            return None
        return slerp(self.R[i - 1], self.R[i], (t_ns - t0) / (t1 - t0))


# ----------------------------------------------------------------------------------------------
# The EKF on R_PN (eq. 1-2, 5-6) with gating and direction weighting.


@dataclass
class HybridFilterParams:
    """Noise, gating and weighting settings (SI units, rad)."""

    #: Random walk of R_PN, rad/sqrt(s): lets the estimate follow a visual tracker's slow drift
    #: (the paper's fixed process noise, sec. 6.2).
    process_noise_rad_sqrt_s: float = 0.001
    #: Noise of the visual orientation, 1-sigma rad (added to the sensor's, sec. 6.2).
    visual_noise_rad: float = 0.001
    #: Sensor noise used when the input has no covariance (REP-145 -1), 1-sigma rad.
    default_sensor_sigma_rad: float = 0.03
    #: Floor on the sensor's 1-sigma (a too-confident input must not dominate), rad.
    min_sensor_sigma_rad: float = 0.01
    #: Reject a sample whose reported heading 1-sigma exceeds this (field or dip disturbed), rad.
    max_sensor_heading_sigma_rad: float = 0.15
    #: Mahalanobis gate on z^T S^-1 z (3 dof; 16.3 = 99.9 %). 0 disables.
    gate_chi2: float = 16.27
    #: Gate on the short-time mean heading innovation, rad (0 disables) ...
    heading_gate_rad: float = 0.02
    #: ... averaged with this time constant, s.
    heading_gate_window_s: float = 0.5
    #: Gates apply once the heading 1-sigma of R_PN is below this, rad (before, everything is
    #: taken: the first estimate is a single noisy reading).
    gate_after_sigma_rad: float = 0.02
    #: After this long with every sample rejected, believe the sensor again (re-seed), s.
    max_reject_s: float = 20.0
    #: Heading bins for the direction weighting (0 disables it).
    direction_bins: int = 12
    #: Samples per bin that count in full; more in one bin weigh less (see module docstring).
    direction_ref_count: float = 20.0
    #: Forgetting time of the bin counts, s.
    direction_memory_s: float = 60.0


@dataclass
class UpdateResult:
    """What one measurement did: accepted, or why not, and its innovation."""

    accepted: bool
    reason: str = ''
    innovation: Array = field(default_factory=lambda: np.zeros(3))
    mahalanobis2: float = 0.0


class PanoramaWorldFilter:
    """EKF on so(3) for R_PN = R_pano_enu (Langlotz 2011 sec. 5, eq. 1-2, 5-6); see module doc."""

    def __init__(self, params: HybridFilterParams | None = None) -> None:
        self.params = params or HybridFilterParams()
        self.reset()

    def reset(self) -> None:
        """Forget everything (clock jump, new panorama without a backup to carry the heading)."""
        p = self.params
        self.R_hat: Array = np.eye(3)  # R_pano_enu
        self.P: Array = np.eye(3) * math.pi**2
        self.initialized = False
        self.t_ns: int | None = None
        self.heading_ema = 0.0
        self.heading_gated = False
        self.rejecting_since_ns: int | None = None
        self.bins = np.zeros(max(p.direction_bins, 1))
        self.updates = 0
        self.rejected = 0

    # -- state ------------------------------------------------------------------------------

    def seed(self, t_ns: int, R_pano_enu: Array, P_pano: Array) -> None:
        """Start from one estimate (the first reading, or the backup's when vision returns)."""
        self.R_hat = nearest_rotation(np.asarray(R_pano_enu, dtype=float))
        self.P = np.array(P_pano, dtype=float)
        self.initialized = True
        self.t_ns = int(t_ns)
        self.heading_ema = 0.0
        self.heading_gated = False
        self.rejecting_since_ns = None

    def predict(self, t_ns: int, scale: float = 1.0) -> None:
        """Constant model: m stays 0, P grows by the process noise over the elapsed time
        (times ``scale``, see :meth:`update`)."""
        if self.t_ns is None:
            self.t_ns = int(t_ns)
            return
        dt = (int(t_ns) - self.t_ns) * 1e-9
        if dt > 0:
            self.P = self.P + _I3 * (self.params.process_noise_rad_sqrt_s**2 * dt * scale)
            self.t_ns = int(t_ns)

    def world_covariance(self) -> Array:
        """Covariance of R_enu_pano's error in world (ENU) axes: R_hat^T P R_hat."""
        return self.R_hat.T @ self.P @ self.R_hat

    def heading_sigma_rad(self) -> float:
        u = self.R_hat @ UP  # world up in the panorama frame
        return float(math.sqrt(max(u @ self.P @ u, 0.0)))

    def global_orientation(self, R_pano_cam: Array) -> Array:
        """Eq. 1 with the filtered R_PN: R_enu_cam = R_hat^T R_pano_cam."""
        return self.R_hat.T @ R_pano_cam

    # -- measurement ----------------------------------------------------------------------

    def _direction_factor(self, R_enu_cam: Array, dt_s: float) -> float:
        """Noise multiplier of a sample from this direction (module docstring), and count it."""
        p = self.params
        if p.direction_bins <= 0:
            return 1.0
        if dt_s > 0:
            self.bins *= math.exp(-dt_s / p.direction_memory_s)
        fwd = R_enu_cam[:, 2]
        if abs(fwd[2]) > 0.95:  # looking straight up or down: the image's up axis instead
            fwd = -R_enu_cam[:, 1]
        azimuth = math.atan2(fwd[0], fwd[1]) % (2.0 * math.pi)
        b = min(int(azimuth / (2.0 * math.pi) * p.direction_bins), p.direction_bins - 1)
        self.bins[b] += 1.0
        return max(1.0, self.bins[b] / p.direction_ref_count)

    def update(self, t_ns: int, R_pano_cam: Array, R_enu_cam: Array, cov_enu: Array | None) -> UpdateResult:
        """One pair of simultaneous visual (R_pano_cam) and sensor (R_enu_cam) orientations.

        ``cov_enu`` is the sensor's orientation covariance in world axes (None: unknown, use the
        default sigma). Returns whether the sample was used (see the gates in the module doc).
        """
        p = self.params
        dt_s = 0.0 if self.t_ns is None else max(0.0, (int(t_ns) - self.t_ns) * 1e-9)
        if cov_enu is None:
            cov_enu = np.eye(3) * p.default_sensor_sigma_rad**2
        cov_enu = np.asarray(cov_enu, dtype=float)
        floor = p.min_sensor_sigma_rad**2
        diag = cov_enu.diagonal()
        if diag.min() < floor:
            cov_enu = cov_enu + np.diag(np.maximum(floor - diag, 0.0))
        # Eq. 2: R_PN = R_DP^-1 R_DN, i.e. R_pano_enu = R_pano_cam R_cam_enu.
        R_meas = R_pano_cam @ R_enu_cam.T
        if not self.initialized:
            # First estimate "by simply reading the sensor-based orientation" (sec. 5).
            R_pe = R_meas
            self.seed(t_ns, R_pe, R_pe @ cov_enu @ R_pe.T + np.eye(3) * p.visual_noise_rad**2)
            self._direction_factor(R_enu_cam, 0.0)
            self.updates += 1
            return UpdateResult(True, 'seeded')
        factor = self._direction_factor(R_enu_cam, dt_s)
        # A stay in one direction also slows the forgetting: the filter's memory is counted in
        # directions visited, not in seconds (otherwise the random walk reopens P and the stay
        # pulls the estimate anyway, only later).
        self.predict(t_ns, 1.0 / factor)
        z = so3_log(R_meas @ self.R_hat.T)  # eq. 6: expected m, identity Jacobian
        # Sensor error e (world axes, R_enu_sensor = exp(e) R_true) enters as -R_pano_enu e.
        Rm = self.R_hat @ cov_enu @ self.R_hat.T * factor + _I3 * p.visual_noise_rad**2
        S = self.P + Rm
        S_inv = np.linalg.inv(S)
        d2 = float(z @ S_inv @ z)
        u = self.R_hat @ UP
        heading_innov = float(u @ z)
        # Short-time mean of the heading innovation, over every sample with a sane covariance.
        alpha = 1.0 - math.exp(-dt_s / p.heading_gate_window_s) if dt_s > 0 else 0.0
        self.heading_ema += alpha * (heading_innov - self.heading_ema)
        reason = self._gate(cov_enu, d2)
        if reason:
            self.rejected += 1
            if self.rejecting_since_ns is None:
                self.rejecting_since_ns = int(t_ns)
            elif (int(t_ns) - self.rejecting_since_ns) * 1e-9 > p.max_reject_s:
                logger.info('every sensor sample rejected for %.0f s: re-seeding from the sensor', p.max_reject_s)
                self.seed(t_ns, R_meas, self.R_hat @ cov_enu @ self.R_hat.T)
                return UpdateResult(True, 'reseeded', z, d2)
            return UpdateResult(False, reason, z, d2)
        self.rejecting_since_ns = None
        K = self.P @ S_inv  # H = I
        m = K @ z
        self.R_hat = so3_exp(m) @ self.R_hat  # fold the error into R_hat, reset m to 0
        I_K = _I3 - K
        self.P = I_K @ self.P @ I_K.T + K @ Rm @ K.T  # Joseph form: stays symmetric positive
        self.updates += 1
        if self.updates % 1000 == 0:
            self.R_hat = nearest_rotation(self.R_hat)
        return UpdateResult(True, '', z, d2)

    def _gate(self, cov_enu: Array, d2: float) -> str:
        p = self.params
        if math.sqrt(max(cov_enu[2, 2], 0.0)) > p.max_sensor_heading_sigma_rad:
            return 'sensor reports a disturbed field (heading sigma too large)'
        if self.heading_sigma_rad() > p.gate_after_sigma_rad:
            return ''
        if p.gate_chi2 > 0 and d2 > p.gate_chi2:
            return 'innovation outside the chi-square gate'
        if p.heading_gate_rad > 0:
            level = abs(self.heading_ema)
            # Hysteresis: once gated, stay gated until the mean is back under half the band.
            if level > p.heading_gate_rad or (self.heading_gated and level > 0.5 * p.heading_gate_rad):
                self.heading_gated = True
                return 'heading innovation biased (field turned)'
            self.heading_gated = False
        return ''


# ----------------------------------------------------------------------------------------------
# Gyro backup while the visual tracker is lost.


@dataclass
class GyroBackupParams:
    """Gyro integration and bias learning (rad, s)."""

    gyro_noise_rad_s: float = 0.01  # 1-sigma per sample of the rate
    bias_sigma_rad_s: float = 0.005  # residual bias uncertainty after learning
    bias_window_s: float = 0.3  # visual/gyro comparison interval for the bias
    bias_gain: float = 0.05  # weight of one comparison in the running bias
    max_bias_rad_s: float = 0.1  # larger observed biases are discarded as outliers


class GyroBackup:
    """Camera orientation from the gyro while vision is lost ("sensor-based tracking as backup").

    The backup is anchored to the last global orientation (and its covariance) at every visual
    frame and propagates ``R_enu_cam <- R_enu_cam exp(R_cam_imu (w - b) dt)`` from there. The gyro
    bias b is learnt while vision works: over a window, the gyro-only rotation of the camera is
    compared with the visual tracker's, and their difference per second is the bias (in the
    camera frame, turned into the IMU frame).
    """

    def __init__(self, R_imu_cam: Array, params: GyroBackupParams | None = None,
                 bias_imu: Array | None = None) -> None:
        self.params = params or GyroBackupParams()
        self.R_imu_cam = np.asarray(R_imu_cam, dtype=float)
        self.bias_prior = np.zeros(3) if bias_imu is None else np.asarray(bias_imu, dtype=float)
        self.reset()

    def reset(self) -> None:
        self.bias = self.bias_prior.copy()
        self.bias_observations = 0
        self.t_ns: int | None = None
        self.omega: Array | None = None  # last bias-corrected rate, imu frame
        self.chain = RotationBuffer(max_gap_ns=200_000_000, keep_ns=3_000_000_000)  # R_0_imu(t)
        self._chain_R = np.eye(3)
        self.visual = RotationBuffer(max_gap_ns=200_000_000, keep_ns=3_000_000_000)  # R_pano_cam
        self.R_enu_cam: Array | None = None
        self.cov: Array = np.eye(3)
        self.anchor_ns: int | None = None

    def add_gyro(self, t_ns: int, omega_imu: Array) -> None:
        """One gyro sample (raw rate minus any configured bias, imu frame, rad/s)."""
        t_ns = int(t_ns)
        if self.t_ns is not None:
            dt = (t_ns - self.t_ns) * 1e-9
            if dt <= 0:
                return
            if dt > 0.5:  # a gap: restart the chain (integration across it would be a guess)
                self.chain.clear()
                self._chain_R = np.eye(3)
            else:
                w_prev = self.omega if self.omega is not None else omega_imu
                w = 0.5 * (w_prev + np.asarray(omega_imu, dtype=float))  # trapezoid on the rate
                self._chain_R = self._chain_R @ so3_exp(w * dt)
                if self.R_enu_cam is not None:
                    w_cam = self.R_imu_cam.T @ (w - self.bias)
                    self.R_enu_cam = self.R_enu_cam @ so3_exp(w_cam * dt)
                    p = self.params
                    # Rate noise adds a random walk; a residual bias b adds (b t)^2: d/dt = 2 b^2 t.
                    since = 0.0 if self.anchor_ns is None else (t_ns - self.anchor_ns) * 1e-9
                    self.cov = self.cov + np.eye(3) * (p.gyro_noise_rad_s**2 * dt * dt
                                                       + 2.0 * p.bias_sigma_rad_s**2 * since * dt)
        self.t_ns = t_ns
        self.omega = np.asarray(omega_imu, dtype=float)
        self.chain.add(t_ns, self._chain_R)

    def anchor(self, t_ns: int, R_enu_cam: Array, cov_enu: Array) -> None:
        """Set the backup to the fused orientation at a visual frame's stamp."""
        R = np.asarray(R_enu_cam, dtype=float)
        if self.t_ns is not None and self.omega is not None and self.t_ns > t_ns:
            # The gyro is already ahead of the frame: bring the anchor to the gyro's time.
            w_cam = self.R_imu_cam.T @ (self.omega - self.bias)
            R = R @ so3_exp(w_cam * ((self.t_ns - int(t_ns)) * 1e-9))
        self.R_enu_cam = R
        self.cov = np.array(cov_enu, dtype=float)
        self.anchor_ns = int(t_ns)

    def add_visual(self, t_ns: int, R_pano_cam: Array) -> None:
        """Learn the gyro bias from the visual rotation over the last ``bias_window_s``."""
        p = self.params
        t_ns = int(t_ns)
        self.visual.add(t_ns, R_pano_cam)
        if self.chain.newest_ns is None:
            return
        t_new = min(t_ns, self.chain.newest_ns)  # the gyro may not have reached the frame yet
        t_old = t_new - int(p.bias_window_s * 1e9)
        R_vis_old, R_vis_new = self.visual.at(t_old), self.visual.at(t_new)
        C_old, C_new = self.chain.at(t_old), self.chain.at(t_new)
        if R_vis_old is None or R_vis_new is None or C_old is None or C_new is None:
            return
        dR_vis = R_vis_old.T @ R_vis_new  # camera at t_old -> camera at t_new
        dR_gyro = self.R_imu_cam.T @ (C_old.T @ C_new) @ self.R_imu_cam
        # dR_gyro ~ dR_vis exp(b_cam dt) for a short window: the residual is the bias (cam axes).
        b_cam = so3_log(dR_vis.T @ dR_gyro) / p.bias_window_s
        b_imu = self.R_imu_cam @ b_cam
        if not np.all(np.isfinite(b_imu)) or np.linalg.norm(b_imu) > p.max_bias_rad_s:
            return
        gain = max(p.bias_gain, 1.0 / (self.bias_observations + 1))
        self.bias = self.bias + gain * (b_imu - self.bias)
        self.bias_observations += 1
