"""The camera-IMU time offset, from the gyro against the visual tracker's rotation.

The hybrid filter pairs every IMU sample with the visual orientation at the sample's stamp
(Langlotz 2011 sec. 5, "simultaneous measurements"). On a phone the two stamps come from
different paths: the camera's is the start of exposure (or of readout) while the rows that carry
most of the tracked texture are read a few to tens of ms later (rolling shutter), and sensor
stamps may carry a driver's delay. An offset d pairs each sample with the orientation of d
earlier or later: during a turn at 60 deg/s, 20 ms is 1.2 deg, and the field and gravity carried
into the panorama frame turn with it.

Both streams measure the same rotation: the visual tracker's between consecutive frames, the
gyro's integral over the same interval. With the IMU's clock ahead of the camera's by d, the
frame pair (t0, t1) corresponds to the gyro over (t0 + d, t1 + d), so d minimises

    sum_k | log(R_k-1^T R_k) / dt_k - (Omega(t1 + d) - Omega(t0 + d)) / dt_k - b |^2

where Omega is the gyro's running integral in camera axes and b the gyro bias (removed per
block as the residuals' mean, so that a slowly drifting bias does not matter). Only changes of
the rate tell d apart (a steady pan reads the same at any d): the hand's tremor and the pans'
starts and stops. The cost is accumulated on a grid of candidate offsets over the whole session
(the offset is a constant of the device), refined by a parabola about its minimum; its
curvature against the residuals' scatter gives the 1-sigma.

Pure numpy; the node (``hybrid_orientation_filter``) shifts the IMU stamps by the estimate once
it is confident. (The offset estimated from the field instead was tried and fitted noise: the
field's windows are too coarse in time.)
"""
from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .rotations import so3_log

Array = NDArray[np.float64]


@dataclass(frozen=True)
class TimeOffsetConfig:
    """Settings of :class:`TimeOffsetEstimator` (s)."""

    #: Candidate offsets span +-this (an offset outside it is reported as not found).
    max_offset_s: float = 0.1
    #: Spacing of the candidate grid (the minimum is refined between its points).
    step_s: float = 0.001
    #: Frame pairs are processed in blocks this long (the gyro bias is removed per block).
    block_s: float = 1.0
    #: Consecutive frames further apart than this are not a pair (the tracker was lost).
    max_frame_gap_s: float = 0.1
    #: The estimate is offered once its 1-sigma is below this ...
    max_sigma_s: float = 0.0015
    #: ... and at least this many blocks went into it.
    min_blocks: int = 2
    #: Pairs whose residual at the block's own best offset is more than this many times the
    #: block's median residual are left out (a tracker glitch, a jump of the visual estimate).
    outlier_ratio: float = 4.0
    #: The visual stream's first frames are left out for this long: a tracker's first second
    #: is its least settled (a rolling-shutter readout not yet estimated puts its orientations
    #: half a readout late; on the recorded inputs of 31 fresh seeds the first settled offset
    #: was 4.1 ms off the simulator's in the median with it, 1.3 ms without).
    skip_first_s: float = 1.0


class TimeOffsetEstimator:
    """Camera-IMU time offset d = IMU stamp - camera stamp of the same instant (module doc)."""

    def __init__(self, R_imu_cam: Array, config: TimeOffsetConfig | None = None) -> None:
        self.config = config or TimeOffsetConfig()
        self.R_imu_cam = np.asarray(R_imu_cam, dtype=float)
        c = self.config
        n = int(round(c.max_offset_s / c.step_s))
        self.candidates_s = np.arange(-n, n + 1) * c.step_s
        self.reset()

    def reset(self) -> None:
        """Forget everything (a new device or a clock jump)."""
        self._t0_ns: int | None = None
        self._gyro_t: list[float] = []  # s from _t0_ns
        self._gyro_int: list[Array] = []  # running integral of the rate, camera axes, rad
        self._last_rate: Array | None = None
        self._frame: tuple[float, Array] | None = None
        self._first_visual_s: float | None = None
        self._pairs: list[tuple[float, float, Array]] = []  # (t0, t1, visual rate in camera axes)
        self._trim_at = 512
        self.cost = np.zeros(len(self.candidates_s))
        self.pairs_used = 0
        self.blocks = 0
        self._estimate: tuple[float, float] | None = None

    def _seconds(self, t_ns: int) -> float:
        if self._t0_ns is None:
            self._t0_ns = int(t_ns)
        return (int(t_ns) - self._t0_ns) * 1e-9

    def add_gyro(self, t_ns: int, omega_imu: Array) -> None:
        """One gyro sample (rad/s, IMU axes; a constant bias does no harm), by its IMU stamp."""
        t = self._seconds(t_ns)
        rate = self.R_imu_cam.T @ np.asarray(omega_imu, dtype=float)
        if self._gyro_t:
            dt = t - self._gyro_t[-1]
            if dt <= 0.0:
                return
            assert self._last_rate is not None
            self._gyro_int.append(self._gyro_int[-1] + 0.5 * (self._last_rate + rate) * dt)
        else:
            self._gyro_int.append(np.zeros(3))
        self._gyro_t.append(t)
        self._last_rate = rate
        self._process()

    def add_visual(self, t_ns: int, R_ref_cam: Array) -> None:
        """One visual orientation (camera in a fixed reference frame), by its camera stamp."""
        t = self._seconds(t_ns)
        R = np.asarray(R_ref_cam, dtype=float)
        if self._first_visual_s is None:
            self._first_visual_s = t
        if t - self._first_visual_s < self.config.skip_first_s:
            return
        if self._frame is not None:
            t_prev, R_prev = self._frame
            dt = t - t_prev
            if 0.0 < dt <= self.config.max_frame_gap_s:
                self._pairs.append((t_prev, t, so3_log(R_prev.T @ R) / dt))
            elif dt <= 0.0:
                return
        self._frame = (t, R)
        self._process()

    # -- the cost --------------------------------------------------------------------------

    def _process(self) -> None:
        """Add a block of pairs to the cost once the gyro covers it at every candidate (or once
        the frames have stopped: what waits is a short block), and trim the gyro buffer."""
        c = self.config
        if not self._gyro_t:
            return
        newest = self._gyro_t[-1]
        if self._pairs:
            first = self._pairs[0][0]
            stale = newest - self._pairs[-1][1] > c.block_s + c.max_offset_s  # the tracker stopped
            if stale or newest - c.max_offset_s - first >= c.block_s:
                covered = [p for p in self._pairs if p[1] + c.max_offset_s <= newest]
                if covered and (stale or covered[-1][1] - first >= c.block_s):
                    self._pairs = self._pairs[len(covered):]
                    g_t = np.asarray(self._gyro_t)
                    usable = [p for p in covered if p[0] - c.max_offset_s >= g_t[0]]
                    if len(usable) >= 10:
                        self._add_block(g_t, np.asarray(self._gyro_int), usable)
        if len(self._gyro_t) >= self._trim_at:
            self._trim(newest)

    def _trim(self, newest: float) -> None:
        """Drop the gyro no pair can reach any more: before the first waiting pair, or before
        the last frame while a next frame can still pair with it (every few hundred samples)."""
        c = self.config
        reach = [newest]
        if self._pairs:
            reach.append(self._pairs[0][0])
        if self._frame is not None and newest - self._frame[0] <= c.max_frame_gap_s + 2.0 * c.max_offset_s + c.block_s:
            reach.append(self._frame[0])
        k = bisect.bisect_left(self._gyro_t, min(reach) - c.max_offset_s - 0.1)
        if k > 0:
            del self._gyro_t[:k], self._gyro_int[:k]
        self._trim_at = len(self._gyro_t) + 256

    def _add_block(self, g_t: Array, g_int: Array, pairs: list[tuple[float, float, Array]]) -> None:
        t0 = np.array([p[0] for p in pairs])
        t1 = np.array([p[1] for p in pairs])
        vis = np.array([p[2] for p in pairs])  # (n, 3)
        d = self.candidates_s
        dt = (t1 - t0)[:, None]
        gyro = np.stack([(np.interp(t1[:, None] + d, g_t, g_int[:, a]) - np.interp(t0[:, None] + d, g_t, g_int[:, a])) / dt
                         for a in range(3)], axis=-1)  # (n, candidates, 3)
        raw = vis[:, None, :] - gyro
        r = raw - raw.mean(axis=0, keepdims=True)  # the gyro bias over the block
        per_pair = np.einsum('ndk,ndk->nd', r, r)
        best = int(np.argmin(per_pair.sum(axis=0)))
        norm = np.sqrt(per_pair[:, best])
        keep = norm <= self.config.outlier_ratio * max(float(np.median(norm)), 1e-12)
        if not keep.all():  # the bias again without the outliers (a lasting jump would shift it)
            r = raw[keep] - raw[keep].mean(axis=0, keepdims=True)
            per_pair = np.einsum('ndk,ndk->nd', r, r)
        else:
            per_pair = per_pair[keep]
        self.cost += per_pair.sum(axis=0)
        self.pairs_used += int(keep.sum())
        self.blocks += 1
        self._estimate = None

    def visual_break(self) -> None:
        """The next frame does not pair with the last one (a new visual reference frame)."""
        self._frame = None

    # -- the estimate ----------------------------------------------------------------------

    def estimate(self) -> tuple[float, float] | None:
        """(offset, 1-sigma) in s, or None while the cost has no interior minimum."""
        if self._estimate is not None:
            return self._estimate
        if self.blocks == 0:
            return None
        cost = self.cost
        k = int(np.argmin(cost))
        if k == 0 or k == len(cost) - 1:
            return None
        step = self.config.step_s
        second = cost[k - 1] - 2.0 * cost[k] + cost[k + 1]  # the parabola's second difference
        if second <= 0.0:
            return None
        curv = second / step ** 2
        offset = float(self.candidates_s[k] + 0.5 * (cost[k - 1] - cost[k + 1]) / second * step)
        # residual variance per component (3 per pair, less one mean per block and axis)
        dof = max(3 * self.pairs_used - 3 * self.blocks - 1, 1)
        s2 = float(cost[k]) / dof
        sigma = math.sqrt(2.0 * s2 / curv)
        self._estimate = (offset, sigma)
        return self._estimate

    @property
    def offset_s(self) -> float | None:
        """The estimate once it is confident (``max_sigma_s``, ``min_blocks``), else None."""
        est = self.estimate()
        if est is None or self.blocks < self.config.min_blocks or est[1] > self.config.max_sigma_s:
            return None
        return est[0]


class ImuClock:
    """IMU stamps into the camera's clock: ``t_camera = t_imu - offset_ns``, the known offset
    refined by a :class:`TimeOffsetEstimator` once it is confident.

    Until then the samples of the session's first seconds (up to ``repair_ns``) are kept as
    received: when the estimate first settles, :meth:`take_kept` hands them back, so that the
    caller re-pairs them with the visual orientation at their corrected stamps (a 20 ms offset
    mis-pairs exactly the seconds in which the panorama-in-world estimate takes shape).
    """

    def __init__(self, known_offset_ns: int, estimator: TimeOffsetEstimator | None,
                 repair_ns: int = 10_000_000_000) -> None:
        self.known_offset_ns = int(known_offset_ns)
        self.offset_ns = self.known_offset_ns
        self.estimator = estimator
        self.repair_ns = int(repair_ns)
        self._settled = False
        self._kept: deque[tuple[Any, ...]] | None = deque() if estimator is not None else None

    def add(self, sample: tuple[Any, ...], omega_imu: Array) -> bool:
        """One IMU sample (``sample[0]`` its IMU stamp, ns) with its gyro rate, kept for
        re-pairing while the offset is unknown. True when the offset has just become known (then
        :meth:`take_kept` has the samples so far, this one excluded)."""
        if self.estimator is None:
            return False
        t_imu = int(sample[0])
        self.estimator.add_gyro(t_imu - self.known_offset_ns, omega_imu)
        offset = self.estimator.offset_s
        if offset is not None:
            self.offset_ns = self.known_offset_ns + int(round(offset * 1e9))
            if not self._settled:
                self._settled = True
                return True
            return False
        self.keep(sample)
        return False

    def keep(self, sample: tuple[Any, ...]) -> None:
        """Keep a sample (stamp first, IMU clock) for re-pairing while the offset is unknown."""
        if self._kept is None or self._settled:
            return
        self._kept.append(sample)
        if int(sample[0]) - int(self._kept[0][0]) > self.repair_ns:
            self._kept = None  # too late to re-pair: the offset applies from then on

    def trim_kept(self, oldest_ns: int) -> None:
        """Let go of the kept samples stamped before ``oldest_ns`` (IMU clock): before the visual
        stream starts only its first frame's latency back needs keeping."""
        while self._kept and int(self._kept[0][0]) < oldest_ns:
            self._kept.popleft()

    def take_kept(self) -> list[tuple[Any, ...]] | None:
        """The kept samples (once; None when there is nothing to re-pair)."""
        kept, self._kept = self._kept, None
        return None if kept is None else list(kept)

    def add_visual(self, t_ns: int, R_ref_cam: Array) -> None:
        if self.estimator is not None:
            self.estimator.add_visual(t_ns, R_ref_cam)

    def forget_kept(self) -> None:
        """The visual stream broke off (the tracker was lost, or its reference frame changed):
        nothing before this point is re-paired, and no frame pair spans it."""
        self._kept = None
        if self.estimator is not None:
            self.estimator.visual_break()

    def restart(self) -> None:
        """The stamps start over (a bag loop): a new estimate on the grid about the known offset;
        the offset applied so far stays until it is confident."""
        if self.estimator is not None:
            self.estimator.reset()
            self._settled = False
            self._kept = deque()
