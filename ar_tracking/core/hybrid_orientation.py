"""The hybrid filter's helpers around the panorama-in-world estimate (Langlotz 2011 sec. 5).

The panorama's place in the world, R_PN of eq. 1-2, is estimated in :mod:`.world_alignment`
(the paper's EKF on per-sample compass readings, eq. 5-6, was replaced there: on hard data its
result stayed a near-constant offset of 1-3 degrees). Here:

* :class:`GyroBackup`, the "sensor-based tracking as a backup" while the visual tracker is lost
  (integrates the gyro from the last global orientation, with a gyro bias learnt against the
  visual tracker while it works);
* :class:`RotationBuffer`, to pair the visual and inertial streams by stamp (slerp between the
  bracketing samples, never arrival order);
* :class:`StreamLag`, how far the visual stream's stamps trail the IMU's when its messages
  arrive, so that a camera pipeline's latency is not taken for a lost tracker.
"""
from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass
from typing import Deque

import numpy as np
from numpy.typing import NDArray

from .imu_orientation import STANDARD_GRAVITY_M_S2
from .rotations import so3_exp, so3_log

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


class StreamLag:
    """How far one stream's stamps trail another's when its messages arrive.

    A phone's camera frame reaches the tracker tens to hundreds of milliseconds after its
    exposure, and the tracker adds its own time, while IMU samples arrive within a few ms of
    their stamps; a bag recorded at arrival keeps that order. Judged by stamps alone (the newest
    IMU stamp against the newest visual stamp) every frame of such a stream looks late, and the
    tracker would be declared lost on every frame. The lag is measured at each arrival of the
    trailing stream (the leading stream's newest stamp minus the arriving stamp) and taken as
    the median of the last ``window`` arrivals (one slow frame does not move it), never below 0.
    """

    def __init__(self, window: int = 31) -> None:
        self._lags: Deque[int] = deque(maxlen=int(window))
        self.ns = 0  # kept: read at every IMU sample

    def clear(self) -> None:
        self._lags.clear()
        self.ns = 0

    def add(self, lead_ns: int, t_ns: int) -> None:
        """One arrival of the trailing stream (stamp ``t_ns``) while the leading stream's newest
        stamp is ``lead_ns``."""
        self._lags.append(int(lead_ns) - int(t_ns))
        self.ns = max(0, int(np.median(np.fromiter(self._lags, dtype=np.int64, count=len(self._lags)))))

    @property
    def known(self) -> bool:
        """Whether any arrival went into the lag."""
        return bool(self._lags)

    @property
    def settled(self) -> bool:
        """Whether a full window of arrivals went into the lag."""
        return len(self._lags) == self._lags.maxlen


# ----------------------------------------------------------------------------------------------
# Gyro backup while the visual tracker is lost.


@dataclass(frozen=True)
class GyroBackupConfig:
    """Gyro integration and bias learning (rad, s)."""

    gyro_noise_rad_s: float = 0.01  # 1-sigma per sample of the rate
    bias_sigma_rad_s: float = 0.005  # residual bias uncertainty after learning
    bias_window_s: float = 0.3  # visual/gyro comparison interval for the bias
    bias_gain: float = 0.05  # weight of one comparison in the running bias
    max_bias_rad_s: float = 0.1  # larger observed biases are discarded as outliers
    #: Time constant of the accelerometer's pull on the backup's tilt (0: gyro only). A phone
    #: gyro's scale error (0.1-0.5 %) turns a few degrees of the user's turning into tilt over
    #: a long loss; the mean specific force points up as the hand's acceleration averages out.
    tilt_tau_s: float = 3.0
    #: Specific forces further than this share from g are not used (a jerk, a step).
    tilt_accel_gate: float = 0.15
    #: The tilt's 1-sigma the accelerometer holds it to (the hand's acceleration over tau).
    tilt_sigma_rad: float = 0.005
    gravity_m_s2: float = STANDARD_GRAVITY_M_S2


#: Deprecated name (issue 21: the core's configuration dataclasses are all called ``*Config``);
#: kept so that code written against it still runs. Use :class:`GyroBackupConfig`.
GyroBackupParams = GyroBackupConfig


class GyroBackup:
    """Camera orientation from the gyro while vision is lost ("sensor-based tracking as backup").

    The backup is anchored to the last global orientation (and its covariance) at every visual
    frame and propagates ``R_enu_cam <- R_enu_cam exp(R_cam_imu (w - b) dt)`` from there. The gyro
    bias b is learnt while vision works: over a window, the gyro-only rotation of the camera is
    compared with the visual tracker's, and their difference per second is the bias (in the
    camera frame, turned into the IMU frame). With the accelerometer, the tilt is pulled towards
    the measured up with time constant ``tilt_tau_s`` (a complementary filter on tilt only; the
    heading stays the gyro's, which outlasts a disturbed compass).
    """

    def __init__(self, R_imu_cam: Array, params: GyroBackupConfig | None = None,
                 bias_imu: Array | None = None) -> None:
        self.params = params or GyroBackupConfig()
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

    def add_gyro(self, t_ns: int, omega_imu: Array, accel_imu: Array | None = None) -> None:
        """One gyro sample (raw rate minus any configured bias, imu frame, rad/s), with the
        specific force of the same sample (imu frame, m/s^2) for the tilt correction."""
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
                    if accel_imu is not None and p.tilt_tau_s > 0:
                        self._pull_tilt(np.asarray(accel_imu, dtype=float), dt)
        self.t_ns = t_ns
        self.omega = np.asarray(omega_imu, dtype=float)
        self.chain.add(t_ns, self._chain_R)

    def _pull_tilt(self, accel_imu: Array, dt: float) -> None:
        """Turn R_enu_cam by dt / tilt_tau_s of the angle between the measured up (the specific
        force, in ENU through the current estimate) and the ENU z axis, about their common
        horizontal axis (no heading change), weighted by the share of the tilt variance the
        accelerometer's (tilt_sigma_rad^2) would remove; the variance relaxes towards it."""
        p = self.params
        assert self.R_enu_cam is not None
        norm = float(np.linalg.norm(accel_imu))
        if not abs(norm - p.gravity_m_s2) <= p.tilt_accel_gate * p.gravity_m_s2:
            return
        ux, uy, _ = (self.R_enu_cam @ (self.R_imu_cam.T @ accel_imu)) / norm
        # Pulled by how much less the accelerometer's tilt is in doubt than the gyro's own: just
        # after an anchor (a short loss) the gyro's tilt is the better one and the hand's
        # acceleration would only disturb it.
        tilt_var = 0.5 * (self.cov[0, 0] + self.cov[1, 1])
        k = min(1.0, dt / p.tilt_tau_s) * tilt_var / (tilt_var + p.tilt_sigma_rad ** 2)
        # u x z = (uy, -ux, 0): rotating u about it turns u towards z.
        self.R_enu_cam = so3_exp(np.array([k * uy, -k * ux, 0.0])) @ self.R_enu_cam
        for i in (0, 1):
            self.cov[i, i] += k * (p.tilt_sigma_rad ** 2 - self.cov[i, i])

    def _turn_since(self, t_ns: int) -> Array:
        """The camera's rotation (camera axes) from ``t_ns`` to the last gyro sample: the gyro's
        own rotation since then (the bias removed to first order), or, when the chain does not
        reach back that far, the last rate held; identity when ``t_ns`` is not behind the gyro."""
        if self.t_ns is None or self.omega is None or self.t_ns <= t_ns:
            return np.eye(3)
        dt = (self.t_ns - int(t_ns)) * 1e-9
        C_then = self.chain.at(int(t_ns))
        if C_then is not None:
            dR_imu = (C_then.T @ self._chain_R) @ so3_exp(-self.bias * dt)
            return self.R_imu_cam.T @ dR_imu @ self.R_imu_cam
        return so3_exp(self.R_imu_cam.T @ (self.omega - self.bias) * dt)

    def anchor(self, t_ns: int, R_enu_cam: Array, cov_enu: Array) -> None:
        """Set the backup to the fused orientation at a visual frame's stamp (brought to the
        gyro's time when the gyro is already ahead of the frame: a camera pipeline's latency)."""
        self.R_enu_cam = np.asarray(R_enu_cam, dtype=float) @ self._turn_since(t_ns)
        self.cov = np.array(cov_enu, dtype=float)
        self.anchor_ns = int(t_ns)

    def at(self, t_ns: int) -> Array | None:
        """The backup's orientation R_enu_cam at ``t_ns``, a frame's stamp that the gyro may
        already be ahead of (camera latency): the one at the last gyro sample turned back
        through the gyro's rotation since; None before the first anchor. A frame that returns
        after a loss is compared with this, not with the newest state: 110 ms of latency at
        50 deg/s is 5.5 deg, which looked like a restarted panorama."""
        if self.R_enu_cam is None:
            return None
        return self.R_enu_cam @ self._turn_since(t_ns).T

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
