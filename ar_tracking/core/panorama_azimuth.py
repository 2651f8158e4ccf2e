"""The panorama's azimuth distortion under a camera that turns about the user, learnt from the gyro.

Langlotz 2011 sec. 3.1 maps the panorama under a camera that turns about its own centre. A
person turns the phone about their body: the camera moves on a circle of 0.2-0.4 m radius r,
and a surface at distance d slides past it ``r / d`` faster than the turn. Each frame is placed
in the map from the map's content, so a sequentially built panorama is stretched in azimuth by
about ``r / d`` of the near content it was placed with (0.4-0.8 % on the simulator's street with
parallax, so 1.5-3 deg over a full turn), and where the turn meets its own start the two ends
disagree by that much (the seam). The tracker is consistent with its map, so the tracked
orientation is off by a distortion c(psi) that depends on where in the panorama the camera looks:
``psi_panorama = psi_true + c(psi_panorama)`` - a ramp from the first frame, with a jump at the seam
once the turn has closed. One constant panorama -> world rotation (sec. 5, eq. 1-2) cannot remove
it; on the street with parallax it was the largest part of the hybrid's heading error.

The gyro measures the true turn. Between two tracked frames i, j (``pair_s`` apart) the panorama's
azimuth increment minus the gyro's is

    d_ij = c(psi_j) - c(psi_i) - b dt - g dpsi_gyro

with b the gyro's residual bias about the panorama's up axis (a random walk) and g the gyro's scale
error. g is taken as 0 by default (``scale_sigma``): before a turn closes nothing tells it from the
panorama's stretch, and estimating it under a prior of 0.3 % cost the simulator's street seeds
0.1-0.3 deg; a phone gyro's scale error (0.1-0.5 %) is then left in c. c is periodic, linear between
``knots`` azimuths, smooth (a prior on its second differences), and 0 where the first frame looked
(the panorama's frame is that frame's: nothing has accumulated there). A Kalman filter on (c, b, g),
one update per frame; a comparison more than ``max_residual_rad`` off is left out (the seam's jump
is not learnt: see ``_compare``). :meth:`AzimuthDistortion.correct` turns a tracked orientation back
by c about up. No ROS here.
"""
from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.linalg.blas import dger

from .rotations import (QuatFloats, quat_wxyz_conj_floats, quat_wxyz_log_along, quat_wxyz_mul_floats,
                        quat_wxyz_of_rows)


Array = NDArray[np.float64]
#: (up, azimuth 0, azimuth 90 deg) unit vectors of the panorama frame, as Python floats.
_Axes = tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]]
#: The two knots about an azimuth and the weight of the second (:meth:`AzimuthDistortion._knots_of`).
_Knots = tuple[int, int, float]


@dataclass(frozen=True)
class AzimuthDistortionConfig:
    """Model and noise of :class:`AzimuthDistortion` (rad, s)."""

    #: Azimuths of the periodic piecewise-linear c(psi) (36: every 10 deg).
    knots: int = 36
    #: Time between the two frames of a gyro comparison.
    pair_s: float = 0.5
    #: A pair whose frames are further apart than this (the tracker was lost between) is not used.
    max_pair_s: float = 0.8
    #: 1-sigma of one comparison d_ij (two tracked orientations, the gyro between them).
    pair_noise_rad: float = math.radians(0.15)
    #: Prior 1-sigma of c at a knot.
    distortion_sigma_rad: float = math.radians(3.0)
    #: 1-sigma of c's second difference between neighbouring knots (its smoothness).
    smoothness_rad: float = math.radians(0.2)
    #: Prior 1-sigma of the residual gyro bias about up, and its random walk (rad/s/sqrt(s)).
    bias_sigma_rad_s: float = math.radians(0.3)
    bias_walk_rad_s: float = 2e-4
    #: Prior 1-sigma of the gyro's scale error; 0 does not estimate it.
    scale_sigma: float = 0.0
    #: A comparison this far from the prediction crosses a jump of the map (the seam, or a
    #: wrong relocalisation) and is left out.
    max_residual_rad: float = math.radians(1.0)
    #: Above this camera elevation the azimuth is ill-defined: no comparison, no correction.
    max_elevation_rad: float = math.radians(60.0)

    def __post_init__(self) -> None:
        if self.knots < 4:
            raise ValueError('knots must be >= 4')
        if not 0 < self.pair_s <= self.max_pair_s:
            raise ValueError('need 0 < pair_s <= max_pair_s')


class AzimuthDistortion:
    """Online estimate of the panorama's azimuth distortion c(psi) (module docstring).

    Feed the gyro (:meth:`add_gyro`) and each tracked frame with the panorama's up axis
    (:meth:`add_visual`), in one clock; read :meth:`correct`."""

    def __init__(self, R_imu_cam: Array, config: AzimuthDistortionConfig | None = None) -> None:
        self.config = config or AzimuthDistortionConfig()
        self.R_imu_cam = np.asarray(R_imu_cam, dtype=float)
        # R_imu_cam's rows as floats, for the frame's product in Python (redone when the
        # attribute is replaced: the node sets a new mount).
        self._mount: tuple[Array, list[list[float]]] | None = None
        self.reset()

    def reset(self) -> None:
        """Forget everything (a new panorama)."""
        c = self.config
        K = c.knots
        n = K + 2
        # Information of the prior: independent knots, plus the smoothness of c.
        info = np.zeros((n, n))
        info[:K, :K] = np.eye(K) / c.distortion_sigma_rad ** 2
        D = np.zeros((K, K))
        for k in range(K):
            D[k, k] = -2.0
            D[k, (k - 1) % K] += 1.0
            D[k, (k + 1) % K] += 1.0
        info[:K, :K] += D.T @ D / c.smoothness_rad ** 2
        info[K, K] = 1.0 / c.bias_sigma_rad_s ** 2
        info[K + 1, K + 1] = 1.0 / c.scale_sigma ** 2 if c.scale_sigma > 0 else 1e12
        self.P = np.linalg.inv(info)
        self.x = np.zeros(n)
        self.e1: Array | None = None  # azimuth 0 in the panorama frame (the first frame's view)
        self.t_filter_ns: int | None = None
        # Gyro chain R_0_imu(t) of recent samples: stamps and unit quaternions (w, x, y, z) as
        # Python floats (per IMU sample, numpy's per-call overhead was most of the cost).
        self._gyro_t: list[int] = []
        self._gyro_q: list[QuatFloats] = []
        self._chain = 0  # counts the chain's restarts: a kept R_0_imu belongs to one chain
        self._omega: tuple[float, float, float] | None = None
        self._axes_key: tuple[float, float, float] | None = None
        self._axes: _Axes | None = None
        #: Recent frames: (stamp, the camera's forward axis (R_pano_cam's third column) and
        #: R_pano_imu as a quaternion, both as Python floats; the gyro chain's R_0_imu at the
        #: stamp and the chain it is of, kept for the frame's later comparison; the azimuth axes
        #: the frame's azimuth was taken about and its two knots there (:meth:`_knots_of`),
        #: reused while the axes stay).
        self._frames: deque[tuple[int, list[float], QuatFloats, QuatFloats, int, _Axes | None, _Knots | None]] = deque()
        #: The frames' stamps (increasing), for a bisection to the frame pair_s back.
        self._frame_t: deque[int] = deque()
        #: Frames the gyro has not reached yet (a frame may arrive before the IMU samples of its
        #: time): (stamp, R_pano_cam, up).
        self._waiting: deque[tuple[int, Array, Array | None]] = deque(maxlen=64)
        #: The last frame's forward axis, the axes its azimuth was taken about and its knots
        #: there: :meth:`correct` of that frame about the same axes reuses them.
        self._last_view: tuple[list[float], _Axes, _Knots | None] | None = None
        self.pairs = 0
        self.outliers = 0

    # -- inputs ----------------------------------------------------------------------------

    def add_gyro(self, t_ns: int, omega_imu: Array) -> None:
        """One gyro sample (rad/s, imu frame, any configured bias removed), in the frames' clock.
        A stamp that does not increase, or a gap over ``max_pair_s``, starts the chain over."""
        t_ns = int(t_ns)
        w = (float(omega_imu[0]), float(omega_imu[1]), float(omega_imu[2]))
        ts, qs = self._gyro_t, self._gyro_q
        q = (1.0, 0.0, 0.0, 0.0)
        if ts:
            dt = (t_ns - ts[-1]) * 1e-9
            if dt <= 0.0 or dt > self.config.max_pair_s:
                ts.clear()
                qs.clear()
                self._chain += 1
            else:  # the trapezoid rate over the step, as one rotation
                p = self._omega if self._omega is not None else w
                vx, vy, vz = 0.5 * (p[0] + w[0]) * dt, 0.5 * (p[1] + w[1]) * dt, 0.5 * (p[2] + w[2]) * dt
                angle = math.sqrt(vx * vx + vy * vy + vz * vz)
                c = math.cos(0.5 * angle)
                k = math.sin(0.5 * angle) / angle if angle > 1e-12 else 0.5
                dx, dy, dz = k * vx, k * vy, k * vz
                a, b, e, f = qs[-1]
                q = (a * c - b * dx - e * dy - f * dz, a * dx + b * c + e * dz - f * dy,
                     a * dy - b * dz + e * c + f * dx, a * dz + b * dy - e * dx + f * c)
        self._omega = w
        ts.append(t_ns)
        qs.append(q)
        if len(ts) > 400:  # keep about 2 x max_pair_s
            keep_ns = int(2e9 * self.config.max_pair_s)
            cut = bisect.bisect_left(ts, t_ns - keep_ns) - 1
            if cut > 0:
                del ts[:cut]
                del qs[:cut]
        while self._waiting and self._waiting[0][0] <= t_ns:
            self._frame(*self._waiting.popleft())

    def _gyro_at(self, t_ns: int) -> QuatFloats | None:
        """The gyro chain's R_0_imu at t_ns (interpolated between samples), None outside it; as
        Python floats, for the comparison's quaternion algebra (:func:`.rotations.quat_wxyz_mul_floats`)."""
        ts = self._gyro_t
        if not ts or t_ns < ts[0] or t_ns > ts[-1]:
            return None
        if t_ns == ts[-1]:  # a frame whose stamp the gyro has just reached (the stamps increase)
            return self._gyro_q[-1]
        k = bisect.bisect_left(ts, t_ns)
        a = self._gyro_q[k]
        if ts[k] != t_ns:  # normalised linear interpolation: one sample's turn apart
            b, s = self._gyro_q[k - 1], (ts[k] - t_ns) / (ts[k] - ts[k - 1])
            sign = 1.0 if sum(x * y for x, y in zip(a, b)) >= 0.0 else -1.0
            w, x, y, z = ((1.0 - s) * p + s * sign * q for p, q in zip(a, b))
            norm = math.sqrt(w * w + x * x + y * y + z * z)
            a = (w / norm, x / norm, y / norm, z / norm)
        return a

    def add_visual(self, t_ns: int, R_pano_cam: Array, up_pano: Array | None) -> None:
        """A tracked frame (its raw panorama orientation) and the panorama's up axis (None while
        unknown: the frame is kept, nothing is learnt)."""
        t_ns = int(t_ns)
        R = np.asarray(R_pano_cam, dtype=float)
        up = None if up_pano is None else np.asarray(up_pano, dtype=float)
        if not self._gyro_t or t_ns > self._gyro_t[-1]:  # compared when the gyro gets there
            self._waiting.append((t_ns, R, up))
            return
        self._frame(t_ns, R, up)

    def _frame(self, t_ns: int, R: Array, up_pano: Array | None) -> None:
        if self._frames and t_ns <= self._frames[-1][0]:
            return
        C = self._gyro_at(t_ns)
        if C is None:  # before the gyro's chain (it restarted after a gap)
            return
        # The IMU's orientation in the panorama frame by the tracker, R_pano_cam R_cam_imu (on
        # Python floats: three numpy calls on 3x3 matrices cost more than the arithmetic).
        mount = self._mount
        if mount is None or mount[0] is not self.R_imu_cam:
            mount = self._mount = (self.R_imu_cam, np.asarray(self.R_imu_cam, dtype=float).tolist())
        (a0, a1, a2), (b0, b1, b2), (c0, c1, c2) = mount[1]
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = R.ravel().tolist()
        q_pano_imu = quat_wxyz_of_rows(
            r00 * a0 + r01 * a1 + r02 * a2, r00 * b0 + r01 * b1 + r02 * b2, r00 * c0 + r01 * c1 + r02 * c2,
            r10 * a0 + r11 * a1 + r12 * a2, r10 * b0 + r11 * b1 + r12 * b2, r10 * c0 + r11 * c1 + r12 * c2,
            r20 * a0 + r21 * a1 + r22 * a2, r20 * b0 + r21 * b1 + r22 * b2, r20 * c0 + r21 * c1 + r22 * c2)
        if self.e1 is None and up_pano is not None:
            self.e1 = self._horizontal(R[:, 2], up_pano)
            if self.e1 is not None:  # c = 0 where the panorama starts (a firm pseudo-observation)
                h = np.zeros(self.x.size)
                h[:self.config.knots] = self._basis(0.0)
                self._update(h, 0.0 - float(h @ self.x), 1e-5)
        forward = [r02, r12, r22]
        axes, knots = None, None
        if up_pano is not None and self.e1 is not None:
            # The axes about up once per frame, and this frame's azimuth's knots about them
            # (kept with the frame: it is the older frame of a later comparison, about the
            # same axes while up stays the same).
            axes = self._axes_of(up_pano)
            psi = None if axes is None else self._azimuth_about(forward, axes)
            knots = None if psi is None else self._knots_of(psi)
            if axes is not None:
                self._last_view = (forward, axes, knots)
            self._compare(t_ns, forward, q_pano_imu, C, axes, knots)
        frames, stamps = self._frames, self._frame_t
        frames.append((t_ns, forward, q_pano_imu, C, self._chain, axes, knots))
        stamps.append(t_ns)
        oldest_ns = t_ns - int(1e9 * self.config.max_pair_s)
        while frames and stamps[0] < oldest_ns:
            frames.popleft()
            stamps.popleft()

    # -- output ----------------------------------------------------------------------------

    def distortion(self, R_pano_cam: Array, up_pano: Array | None) -> float:
        """c (rad) where R_pano_cam looks: 0 before the panorama's azimuth is known or when it
        looks too steeply up or down."""
        return self._distortion_at(np.asarray(R_pano_cam, dtype=float)[:, 2].tolist(), up_pano)

    def _distortion_at(self, forward: list[float], up_pano: Array | None) -> float:
        """:meth:`distortion` of the camera's forward axis (floats, panorama frame); the knots of
        the last frame's azimuth when it is that frame about the same axes (a frame is usually
        corrected right after it was compared)."""
        if self.e1 is None or up_pano is None:
            return 0.0
        axes = self._axes_of(up_pano)
        if axes is None:
            return 0.0
        last = self._last_view
        if last is not None and last[1] is axes and last[0] == forward:
            knots = last[2]
        else:
            psi = self._azimuth_about(forward, axes)
            knots = None if psi is None else self._knots_of(psi)
        if knots is None:
            return 0.0
        k0, k1, f = knots
        return (1.0 - f) * self.x.item(k0) + f * self.x.item(k1)

    def correct(self, R_pano_cam: Array, up_pano: Array | None) -> Array:
        """R_pano_cam turned back by the distortion about up: the orientation in the panorama's
        frame as an undistorted panorama would have given it."""
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = np.asarray(R_pano_cam, dtype=float).ravel().tolist()
        c = self._distortion_at([r02, r12, r22], up_pano)
        if c == 0.0 or self._axes is None:
            return np.asarray(R_pano_cam, dtype=float)
        # The rotation T by -c about the unit up axis (Rodrigues) and T R_pano_cam, as floats
        # (one numpy call instead of three).
        ux, uy, uz = self._axes[0]
        sn, cs = math.sin(-c), math.cos(-c)
        v = 1.0 - cs
        t00, t01, t02 = cs + v * ux * ux, v * ux * uy - sn * uz, v * ux * uz + sn * uy
        t10, t11, t12 = v * uy * ux + sn * uz, cs + v * uy * uy, v * uy * uz - sn * ux
        t20, t21, t22 = v * uz * ux - sn * uy, v * uz * uy + sn * ux, cs + v * uz * uz
        return np.array((
            t00 * r00 + t01 * r10 + t02 * r20, t00 * r01 + t01 * r11 + t02 * r21, t00 * r02 + t01 * r12 + t02 * r22,
            t10 * r00 + t11 * r10 + t12 * r20, t10 * r01 + t11 * r11 + t12 * r21, t10 * r02 + t11 * r12 + t12 * r22,
            t20 * r00 + t21 * r10 + t22 * r20, t20 * r01 + t21 * r11 + t22 * r21,
            t20 * r02 + t21 * r12 + t22 * r22)).reshape(3, 3)

    @property
    def scale_error(self) -> float:
        """The gyro's estimated scale error g."""
        return float(self.x[-1])

    # -- internals -------------------------------------------------------------------------

    def _horizontal(self, v: Array, up: Array) -> Array | None:
        up = up / np.linalg.norm(up)
        h = v - (v @ up) * up
        norm = float(np.linalg.norm(h))
        if norm < math.cos(self.config.max_elevation_rad):
            return None
        return h / norm

    def _axes_of(self, up_pano: Array) -> _Axes | None:
        """(up, azimuth 0, azimuth 90 deg) unit vectors for this up axis (kept while it stays)."""
        ux, uy, uz = np.asarray(up_pano, dtype=float).tolist()
        key = (ux, uy, uz)
        if key != self._axes_key:
            assert self.e1 is not None
            up = np.array(key) / np.linalg.norm(key)
            e1 = self.e1 - (self.e1 @ up) * up
            norm = float(np.linalg.norm(e1))
            if norm < 0.5:
                self._axes_key, self._axes = key, None
            else:
                e1 /= norm
                e2 = np.cross(up, e1)
                self._axes_key = key
                self._axes = (tuple(up.tolist()), tuple(e1.tolist()), tuple(e2.tolist()))
        return self._axes

    def _azimuth_about(self, forward: list[float], axes: _Axes) -> float | None:
        """Azimuth (rad) of the camera's forward axis (floats, panorama frame) about the axes of
        :meth:`_axes_of` (not None); None when it looks too steeply up or down."""
        u, e1, e2 = axes
        fx, fy, fz = forward
        if abs(fx * u[0] + fy * u[1] + fz * u[2]) > math.sin(self.config.max_elevation_rad):
            return None
        return math.atan2(fx * e2[0] + fy * e2[1] + fz * e2[2], fx * e1[0] + fy * e1[1] + fz * e1[2])

    def _knots_of(self, psi: float) -> tuple[int, int, float]:
        """The two knots about azimuth psi and the weight of the second (c is linear between)."""
        K = self.config.knots
        x = (psi % (2.0 * math.pi)) / (2.0 * math.pi) * K
        k0 = int(math.floor(x)) % K
        return k0, (k0 + 1) % K, x - math.floor(x)

    def _basis(self, psi: float) -> Array:
        k0, k1, f = self._knots_of(psi)
        b = np.zeros(self.config.knots)
        b[k0] += 1.0 - f
        b[k1] += f
        return b

    def _compare(self, t_ns: int, fwd_j: list[float], qa_j: QuatFloats, c_j: QuatFloats, axes: _Axes | None,
                 knots_j: _Knots | None) -> None:
        """The comparison of this frame (the knots of its azimuth about ``axes``, the current
        :meth:`_axes_of`) with the last frame at least pair_s before it.
        With A = R_pano_imu by the tracker and G = C_i^T C_j the gyro's turn from i to j (imu
        axes), the tracker's turn beyond the gyro's is A_j G^T A_i^T, and the gyro's turn in
        panorama axes A_i G A_i^T; their components about up are d and dpsi_gyro."""
        cfg = self.config
        t_old = t_ns - int(cfg.pair_s * 1e9)
        # The last frame at or before t_old (the stamps increase): a bisection, not a scan.
        at = bisect.bisect_right(self._frame_t, t_old) - 1
        if at < 0:
            return
        t_i, fwd_i, qa_i, c_i_kept, chain_i, axes_i, knots_kept = self._frames[at]
        if (t_ns - t_i) * 1e-9 > cfg.max_pair_s:
            return
        # The chain's R_0_imu at t_i as it was when frame i arrived, while the chain still
        # holds t_i (samples are only appended to it, and trimmed from its start).
        kept = chain_i == self._chain and self._gyro_t and t_i >= self._gyro_t[0]
        c_i = c_i_kept if kept else self._gyro_at(t_i)
        if axes is None or knots_j is None:
            return
        # Frame i's azimuth's knots as taken when it arrived, if about the same axes (the same
        # floats, so the same values); about the current ones otherwise.
        if axes_i is axes:
            knots_i = knots_kept
        else:
            psi_i = self._azimuth_about(fwd_i, axes)
            knots_i = None if psi_i is None else self._knots_of(psi_i)
        if c_i is None or knots_i is None:
            return
        u = axes[0]
        # d = log(A_j G^T A_i^T) along up, with G = C_i^T C_j (on Python floats, .rotations)
        g = quat_wxyz_mul_floats(quat_wxyz_conj_floats(c_i), c_j)
        qa_i_inv = quat_wxyz_conj_floats(qa_i)
        d = quat_wxyz_log_along(quat_wxyz_mul_floats(quat_wxyz_mul_floats(qa_j, quat_wxyz_conj_floats(g)), qa_i_inv), u)
        dt = (t_ns - t_i) * 1e-9
        K = cfg.knots
        # h: the two frames' knot weights (two may share a knot), the bias's -dt, the scale's
        j0, j1, fj = knots_j
        i0, i1, fi = knots_i
        h = np.zeros(K + 2)
        h[j0] += 1.0 - fj
        h[j1] += fj
        h[i0] -= 1.0 - fi
        h[i1] -= fi
        h[K] = -dt
        if cfg.scale_sigma > 0:  # the gyro's turn about up, for its scale error (0: not estimated)
            h[K + 1] = -quat_wxyz_log_along(quat_wxyz_mul_floats(quat_wxyz_mul_floats(qa_i, g), qa_i_inv), u)
        self._predict(t_ns)
        r = d - float(h.dot(self.x))
        if abs(r) > cfg.max_residual_rad:
            # The map jumps between the two frames (the seam, where a turn met its own start
            # and the two ends of the panorama disagree by the stretch of the whole turn), or a
            # relocalisation was wrong. A smooth c has no jump to give it, and an update would
            # put it into the bias and spread it along the turn (a synthetic 2 % stretch ended
            # 5 deg off): the comparison is left out, and c across the seam stays what the
            # smooth prior makes of it (the jump is not learnt: docs/orientation.md).
            self.outliers += 1
            return
        self._update(h, r, cfg.pair_noise_rad)
        self.pairs += 1

    def _predict(self, t_ns: int) -> None:
        if self.t_filter_ns is not None and t_ns > self.t_filter_ns:
            K = self.config.knots
            self.P[K, K] += self.config.bias_walk_rad_s ** 2 * (t_ns - self.t_filter_ns) * 1e-9
        self.t_filter_ns = t_ns

    def _update(self, h: Array, residual: float, sigma: float) -> None:
        """Kalman update by one scalar measurement z = h x (1-sigma ``sigma``) whose residual
        z - h x is ``residual`` (the caller has it already). The covariance's
        rank-one downdate P - (P h)(P h)^T / s is one in-place BLAS ``dger`` with v = P h / sqrt(s)
        (numpy's outer product, division and subtraction were three passes over the 38 x 38
        matrix, the update's largest cost); v_i v_j = v_j v_i, so P stays symmetric as computed."""
        Ph = self.P.dot(h)  # (ndarray.dot: less per-call cost than @ on small arrays)
        s = float(h.dot(Ph)) + sigma ** 2
        self.x = self.x + Ph * (residual / s)
        v = Ph * (1.0 / math.sqrt(s))
        # P.T is the same matrix in Fortran order, updated in place (a copy if it ever is not).
        self.P = dger(-1.0, v, v, 1, 1, self.P.T, 1, 1, 1).T  # incx, incy, a, overwrite x, y, a
