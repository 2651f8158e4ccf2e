"""The rolling shutter's readout time, estimated from the tracked frames themselves.

A phone camera reads its rows one after the other: row y of a frame is seen ``readout (y + 0.5)
/ height`` after the stamp (:func:`.cylinder.row_rotations`). The tracker and the map turn each
row by the camera's rate over that time (``MapperConfig.readout_s``), but a user's bag seldom
says what the readout is, and an unmodelled 30 ms readout shears every frame by a degree or two
during a pan, enough to lose tracking. The readout is observable whenever the camera turns: a
readout off by ``D`` leaves each inlier of the frame's rotation fit with a residual that grows
with its row, ``D v_i (Omega x p_i)``, where ``p_i = R b'_i`` is the matched bearing (turned by
the readout used) in the panorama frame, ``v_i = (y_i + 0.5) / height`` and ``Omega = R omega``
the camera's rate in the panorama frame - less the same term of the frame that painted the map
there (:func:`frame_reading`). Per frame, the small correction of its rotation is eliminated
(Schur complement of the 4 x 4 normal equations) and the frame gives one reading of the
readout with its information; the readings are combined with a Cauchy weight about the
running estimate (a frame whose rate came from a frame pair across a sudden stop says little)
and the result's sigma is scaled by the readings' scatter. The estimate replaces the configured
readout once it is known well and is clearly not a global shutter - from fewer frames once the
tracker has been lost while the readout was still 0 (the shear may be what lost it) - and, once
used, only a later estimate that passes the same test replaces it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..rotations import cross_rows

Array = NDArray[np.float64]


@dataclass(frozen=True)
class ReadoutConfig:
    """Settings of :class:`ReadoutEstimator` (seconds, radians)."""

    #: Frames turning slower than this carry no reading (their information is tiny anyway).
    min_rate_rad_s: float = 0.1
    #: Readings need this many inliers.
    min_inliers: int = 12
    #: The estimate is used once its 1-sigma is below this ...
    apply_sigma_s: float = 0.003
    #: ... and it is larger than this and than ``significance`` sigmas (else: a global shutter,
    #: and the configured readout stays).
    min_readout_s: float = 0.002
    significance: float = 3.0
    #: Readings are clipped to +-this (a readout beyond a frame interval is not one).
    max_readout_s: float = 0.05
    #: Cauchy scale of a reading's deviation from the running estimate, in its own sigmas.
    cauchy_sigmas: float = 3.0
    #: Angular noise floor of a matched bearing, rad (a perfect fit is not trusted more).
    min_noise_rad: float = 2e-4
    #: Readings are forgotten over about this many readings (exponentially). A reading taken
    #: with a readout far from the true one is biased towards the one used: the rotation fit's
    #: inlier threshold cuts off the rows the wrong readout shears most. Each reading with the
    #: latest estimate is closer, so the estimate converges as the old readings fade.
    memory_readings: float = 50.0
    #: Readings needed before the estimate is used ...
    min_readings: int = 10
    #: ... or this many once the tracker was lost with readout 0 in use: the shear of an
    #: unmodelled readout during a fast turn may be what lost it (a session that starts with a
    #: fast turn can lose tracking a few frames before the estimate has ``min_readings``).
    min_readings_lost: int = 3


@dataclass(frozen=True)
class RowFit:
    """The inliers of one frame's rotation fit (n rows each)."""

    #: Matched bearings turned by the readout used, in the panorama frame (R b'_i), unit.
    rays: Array
    #: Map directions minus ``rays`` (d_i - R b'_i).
    residuals: Array
    #: Row positions ``(y + 0.5) / height`` in [0, 1].
    rows: Array
    #: Indices of the matched map keypoints.
    keypoints: NDArray[np.int64]


@dataclass(frozen=True)
class Painting:
    """How the map pixels under a fit's rays were painted (n rows each, :class:`RowFit`'s)."""

    #: The painting frame's rate, rad/s, panorama axes.
    omega_pano: Array
    #: Row positions ``(y + 0.5) / height`` of the pixels in the painting frame.
    rows: Array
    #: The readout the painting turned its rows by, s.
    readout_s: Array


def frame_reading(fit: RowFit, omega_pano: Array, readout_used_s: float, painting: Painting | None = None,
                  min_noise_rad: float = 2e-4) -> tuple[float, float] | None:
    """(readout s, information 1 / var) from one frame's fit; None when the frame cannot tell.

    The map was painted with a readout too, so a map pixel sits off its true direction by
    ``(s - s_j) v_j Omega_j x d`` (s the true readout; frame j painted it at its row v_j,
    turning at Omega_j with readout s_j), and the residual of ray i is

        r_i = dtheta x p_i + (s - s_k) v_i Omega x p_i - (s - s_j) v_j Omega_j x p_i,

    linear in (dtheta, s). Without ``painting`` the map is taken as exact. The information
    comes from the difference of the two frames' row motions: a map painted during the same
    pan as the frame looks right to it whatever the readout, a pan the other way does not."""
    p, r, v = fit.rays, fit.residuals, fit.rows
    n = p.shape[0]
    if n < 3:
        return None
    motion = v[:, None] * np.asarray(omega_pano, float)[None, :]  # v_i Omega
    q_axis, o_axis = motion, readout_used_s * motion
    if painting is not None:
        paint = painting.rows[:, None] * painting.omega_pano  # v_j Omega_j
        q_axis, o_axis = motion - paint, o_axis - painting.readout_s[:, None] * paint
    q = cross_rows(q_axis, p)  # dr/ds per ray
    y = r + cross_rows(o_axis, p)  # = dtheta x p + s q
    # A_tt = sum I - p p^T; A_ts = sum p x q; A_ss = sum |q|^2; g_t = sum p x y; g_s = sum q . y
    A_tt = n * np.eye(3) - p.T @ p
    A_ts = cross_rows(p, q).sum(axis=0)
    A_ss = float(np.einsum('ij,ij->', q, q))
    g_t = cross_rows(p, y).sum(axis=0)
    g_s = float(np.einsum('ij,ij->', q, y))
    try:
        sol = np.linalg.solve(A_tt, np.column_stack([A_ts, g_t]))
    except np.linalg.LinAlgError:
        return None
    info = A_ss - float(A_ts @ sol[:, 0])
    if not info > 1e-12:
        return None
    s = (g_s - float(A_ts @ sol[:, 1])) / info
    dtheta = sol[:, 1] - sol[:, 0] * s
    e = y - cross_rows(dtheta[None, :], p) - s * q
    noise2 = max(float(np.einsum('ij,ij->', e, e)) / max(2 * n - 4, 1), min_noise_rad ** 2)
    return s, info / noise2


class ReadoutEstimator:
    """Running estimate of the readout from :func:`frame_reading` of each tracked frame."""

    def __init__(self, config: ReadoutConfig | None = None) -> None:
        self.config = config or ReadoutConfig()
        self.reset()

    def reset(self) -> None:
        self._sw = 0.0  # sum of weights
        self._sws = 0.0  # sum of weight x reading
        self._sws2 = 0.0  # sum of weight x reading^2
        self._n = 0
        self._n_eff = 0.0  # readings, forgotten like the sums
        self._applied: float | None = None  # the last estimate readout() gave
        self._lost = False  # tracker_lost() was called: min_readings_lost suffice

    def add(self, readout_used_s: float, omega_cam: Array, R_pano_cam: Array, fit: RowFit | None,
            painting: Painting | None = None) -> None:
        """One tracked frame: the readout its fit used, the camera's rate (rad/s, camera axes),
        its orientation, its inliers and how the map under them was painted."""
        c = self.config
        if fit is None or fit.rays.shape[0] < c.min_inliers or not np.all(np.isfinite(omega_cam)):
            return
        if float(np.linalg.norm(omega_cam)) < c.min_rate_rad_s:
            return
        reading = frame_reading(fit, R_pano_cam @ np.asarray(omega_cam, float), readout_used_s, painting,
                                c.min_noise_rad)
        if reading is None:
            return
        s = min(max(reading[0], -c.max_readout_s), c.max_readout_s)
        info = reading[1]
        w = info
        if self._n >= 10 and self._sw > 0:
            # Cauchy about the running mean, in the reading's sigma widened by the readings'
            # scatter (a reading's own sigma leaves out the model's errors, and a weight in it
            # alone would freeze an early estimate).
            mean, scatter = self._moments()
            z = (s - mean) / math.sqrt(1.0 / info + scatter) / c.cauchy_sigmas
            w = info / (1.0 + z * z)
        keep = 1.0 - 1.0 / max(c.memory_readings, 1.0)
        self._sw = keep * self._sw + w
        self._sws = keep * self._sws + w * s
        self._sws2 = keep * self._sws2 + w * s * s
        self._n_eff = keep * self._n_eff + 1.0
        self._n += 1

    def _moments(self) -> tuple[float, float]:
        """Weighted mean and variance of the readings kept."""
        mean = self._sws / self._sw
        return mean, max(self._sws2 / self._sw - mean * mean, 0.0)

    @property
    def frames(self) -> int:
        """Frames that gave a reading."""
        return self._n

    def estimate(self) -> tuple[float, float] | None:
        """(readout s, 1-sigma s), the sigma scaled up by the readings' scatter; None before
        any reading."""
        if self._n == 0 or self._sw <= 0:
            return None
        mean, var = self._moments()
        scale = max(1.0, self._sw * var / max(self._n_eff - 1.0, 1.0))  # sum w (s - mean)^2 / dof
        return mean, math.sqrt(scale / self._sw)

    def tracker_lost(self) -> None:
        """The tracker was lost while the readout was not yet in use: from now on
        ``min_readings_lost`` readings suffice (the shear may be what lost it)."""
        self._lost = True

    def readout(self, configured_s: float) -> float:
        """The readout to use: ``configured_s`` until the estimate is known to ``apply_sigma_s``
        from ``min_readings`` frames (``min_readings_lost`` after :meth:`tracker_lost`); then the estimate, or 0 (a global shutter) when it is not clearly away from zero. Once
        used, an estimate is replaced only by a later one that passes the same test (a few
        scattered readings widen the sigma for a while; falling back to the configured value
        then would shear the frames again)."""
        c = self.config
        est = self.estimate()
        if est is None or self._n < (c.min_readings_lost if self._lost else c.min_readings) or est[1] > c.apply_sigma_s:
            return configured_s if self._applied is None else self._applied
        value, sigma = est
        self._applied = value if abs(value) >= max(c.min_readout_s, c.significance * sigma) else 0.0
        return self._applied
