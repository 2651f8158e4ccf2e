"""The map maker's upkeep steps (Klein & Murray 2009 sec. 3.2, 3.3, 5.2): local and global bundle
adjustment with their locked write-back and Tukey outlier removal, the initial map's scale, the
culling of measurements and keyframes, and the keyframe snapshots that let this work run outside
``SlamMap.lock`` (see :mod:`.mapper`). :class:`MapUpkeep` is a base class of
:class:`.mapper.MapMaker`, which owns the state it declares; :class:`MapperConfig` (re-exported by
:mod:`.mapper`) lives here because these steps read most of it."""
from __future__ import annotations

import copy
import logging
import queue
import threading
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .bundle_adjustment import BAResult, bundle_adjust
from .camera import Camera
from .frame_gate import FrameGate
from .culling import KEYFRAME_UTILITY_THRESHOLD, keyframes_to_cull, measurements_to_cull
from .slam_map import Keyframe, Measurement, SlamMap

logger = logging.getLogger('ar_tracking.core.slam.mapper')  # the map maker's log, as before the split

Array = NDArray[np.float64]


@dataclass(frozen=True)
class MapperConfig:
    """Mapping-thread parameters (paper values where the paper gives one)."""

    #: Sec. 5.2: new partial points per keyframe.
    max_new_points_per_kf: int = 25
    #: Corner candidates asked of the detector before the 25 are picked.
    corner_candidates: int = 100
    #: New corners must be this far (level-0 px) from existing features.
    corner_exclude_radius_px: float = 10.0
    #: Oldest partial points are dropped beyond this many (bounds the tracker's work).
    max_partial_points: int = 200
    #: A partial point that failed promotion this many times is dropped.
    max_promotion_failures: int = 3
    #: Promotion: minimum ray angle and maximum reprojection error (in sigmas of the level).
    min_parallax_deg: float = 1.0
    promote_max_error_sigma: float = 3.0
    #: Sec. 3.2.
    max_measurements_per_point: int = 8
    #: Sec. 3.3.
    max_keyframes: int = 35
    keyframe_utility_threshold: float = KEYFRAME_UTILITY_THRESHOLD
    max_keyframes_erased_per_round: int = 1
    #: Local BA: the new keyframe plus this many neighbours (most shared points) are free.
    local_ba_neighbours: int = 4
    local_ba_iterations: int = 10
    global_ba_iterations: int = 20
    init_ba_iterations: int = 15
    global_ba: bool = True
    #: Robust kernel of bundle adjustment: 'tukey' (paper) or 'huber'.
    robust: str = 'tukey'
    #: Remove measurements the Tukey kernel rejected (weight 0) after each BA.
    remove_outliers: bool = True
    #: Sec. 6.
    rolling_shutter: bool = True
    rs_recorrect_every: int = 5
    #: Inverse depth for new partial points when the keyframe measures no map point.
    default_inverse_depth: float = 1.0
    #: How long the idle thread waits for a keyframe before considering global BA.
    idle_poll_s: float = 0.02


def _snapshot_kf(kf: Keyframe, point_ids: set[int] | None = None,
                 copy_measurements: bool = False) -> Keyframe:
    """A pose/measurement copy of a keyframe for work outside the lock (no pixels).

    The measurement dict is copied (optionally restricted to ``point_ids``); the Measurement
    objects themselves are shared unless ``copy_measurements`` (needed when the copy's
    ``uv_corrected`` will be rewritten). Sharing is safe because measurement arrays are never
    modified in place, only replaced, and only by this thread: it keeps the locked copy short.
    """
    items = kf.measurements.items() if point_ids is None else \
        ((pid, m) for pid, m in kf.measurements.items() if pid in point_ids)
    meas = {pid: copy.copy(m) for pid, m in items} if copy_measurements else dict(items)
    return Keyframe(id=kf.id, stamp_ns=kf.stamp_ns, R_c_w=np.array(kf.R_c_w, float),
                    t_c_w=np.array(kf.t_c_w, float), pyramid=[], sbi=None, measurements=meas,
                    image_velocities=dict(kf.image_velocities) if copy_measurements else {},
                    fixed=kf.fixed, erased=kf.erased)


class MapUpkeep:
    """Bundle adjustment and culling of :class:`.mapper.MapMaker` (its base class): the
    attributes below are set by ``MapMaker.__init__``."""

    map: SlamMap
    camera: Camera
    config: MapperConfig
    gate: FrameGate
    stats: dict[str, Any]
    _queue: queue.Queue[tuple[Keyframe, dict[int, Measurement]]]
    _stop: threading.Event
    _preempt: threading.Event
    _state: threading.Condition
    _in_ba: bool
    _global_dirty: bool
    _weights: dict[tuple[int, int], float]

    def _set_in_ba(self, v: bool) -> None:
        with self._state:
            self._in_ba = v
            self._state.notify_all()

    def _checkpoint(self, label: str) -> None:
        """Before each step of the thread's work: wait for the tracker to be between frames."""
        self.gate.checkpoint(label)

    # ---- bundle adjustment ------------------------------------------------------------------------
    def _local_ba(self, kf_id: int) -> None:
        """Local BA: the new keyframe + neighbours sharing most points free, the rest fixed."""
        cfg = self.config
        with self.map.lock:
            kf = self.map.keyframes[kf_id]
            shared: dict[int, int] = {}
            for pid in kf.measurements:
                p = self.map.points.get(pid)
                if p is None:
                    continue
                for o in p.observers:
                    if o != kf_id:
                        shared[o] = shared.get(o, 0) + 1
            neigh = sorted((k for k in shared if not self.map.keyframes[k].erased),
                           key=lambda k: -shared[k])[: cfg.local_ba_neighbours]
            free = {kf_id, *neigh}
            point_ids = {pid for k in free for pid in self.map.keyframes[k].measurements
                         if pid in self.map.points}
            involved = {o for pid in point_ids for o in self.map.points[pid].observers
                        if o in self.map.keyframes and not self.map.keyframes[o].erased}
            involved |= free
            fixed = {k for k in involved if k not in free or self.map.keyframes[k].fixed}
            snaps = [_snapshot_kf(self.map.keyframes[k], point_ids) for k in sorted(involved)]
            pts = {pid: self.map.points[pid].xyz.copy() for pid in point_ids}
        if not pts or len(involved) < 2:
            return
        if not fixed:       # a gauge anchor is needed: hold the oldest keyframe
            fixed = {min(involved)}
        self._set_in_ba(True)
        try:
            res = bundle_adjust(snaps, pts, self.camera, fixed, cfg.local_ba_iterations,
                                robust=cfg.robust, abort=self._stop.is_set,
                                checkpoint=lambda s: self._checkpoint('local_' + s))
        finally:
            self._set_in_ba(False)
        self._checkpoint('write_back')
        self._write_back(res, fixed)
        self._record_ba(res, 'local')

    def _global_ba(self, abort_on_keyframe: bool) -> BAResult | None:
        cfg = self.config
        self._checkpoint('global_snapshot')
        with self.map.lock:
            active = [kf for kf in self.map.keyframes.values() if not kf.erased]
            point_ids = set(self.map.points)
            snaps = [_snapshot_kf(kf, point_ids) for kf in active]
            pts = {pid: p.xyz.copy() for pid, p in self.map.points.items()}
            fixed = {kf.id for kf in active if kf.fixed}
        if len(snaps) < 2 or not pts:
            self._global_dirty = False
            return None
        if not fixed:
            fixed = {min(s.id for s in snaps)}

        def abort() -> bool:
            return (self._stop.is_set() or self._preempt.is_set()
                    or (abort_on_keyframe and not self._queue.empty()))

        self._set_in_ba(True)
        try:
            res = bundle_adjust(snaps, pts, self.camera, fixed, cfg.global_ba_iterations,
                                robust=cfg.robust, abort=abort,
                                checkpoint=lambda s: self._checkpoint('global_' + s))
        finally:
            self._set_in_ba(False)
        if res.objective_after <= res.objective_before or not res.aborted:
            self._checkpoint('write_back')
            self._write_back(res, fixed)
        self._record_ba(res, 'global')
        if res.aborted:
            self.stats['global_ba_aborted'] += 1
        else:
            self._global_dirty = False
        self._checkpoint('counts')
        self._update_counts()
        return res

    def _restore_scale(self, res: BAResult, kf0: Keyframe, pts_before: dict[int, Array]) -> None:
        """Rescales a BA result about kf0's centre so kf0's mean scene depth is as before."""
        if not res.points or kf0.id not in res.poses:
            return
        R0, t0 = kf0.R_c_w, kf0.t_c_w
        ids = list(res.points)
        zb = np.array([pts_before[i] for i in ids]) @ R0[2] + t0[2]
        za = np.array([res.points[i] for i in ids]) @ R0[2] + t0[2]
        if np.mean(za) <= 1e-9:
            return
        s = float(np.mean(zb) / np.mean(za))
        c0 = -R0.T @ t0
        for i in ids:
            res.points[i] = c0 + s * (res.points[i] - c0)
        for k, (R, t) in list(res.poses.items()):
            res.poses[k] = (R, s * t - (1.0 - s) * (R @ c0))

    def _write_back(self, res: BAResult, fixed: set[int]) -> None:
        """One locked step: poses of free, still-active keyframes, surviving points, outliers."""
        cfg = self.config
        self._weights.update(res.weights)
        with self.map.lock:
            poses = {k: v for k, v in res.poses.items() if k not in fixed
                     and k in self.map.keyframes and not self.map.keyframes[k].erased}
            points = {p: x for p, x in res.points.items() if p in self.map.points}
            self.map.apply_update(poses, points)
            if cfg.remove_outliers and cfg.robust == 'tukey':
                removed = 0
                touched = set()
                for (k, p), w in res.weights.items():
                    if w <= 0.0 and p in self.map.points:
                        kf = self.map.keyframes.get(k)
                        if kf is not None and p in kf.measurements:
                            self.map.remove_measurement(k, p)
                            self._weights.pop((k, p), None)
                            touched.add(p)
                            removed += 1
                dead = [p for p in touched if len(self.map.points[p].observers) < 2]
                for p in dead:
                    self.map.remove_point(p)
                self.stats['outliers_removed'] += removed
                self.stats['points_removed'] += len(dead)

    def _record_ba(self, res: BAResult, kind: str) -> None:
        s = self.stats
        s['ba_runs'] += 1
        s[f'{kind}_ba_runs'] = s.get(f'{kind}_ba_runs', 0) + 1
        s['last_ba_ms'] = res.time_ms
        s['last_ba_iterations'] = res.iterations
        s['last_ba_objective_before'] = res.objective_before
        s['last_ba_objective_after'] = res.objective_after
        s['last_ba_kind'] = kind

    # ---- culling ----------------------------------------------------------------------------------
    def _cull_measurements(self) -> None:
        """Sec. 3.2: keep each point's 8 most useful measurements."""
        with self.map.lock:
            if not any(len(p.observers) > self.config.max_measurements_per_point
                       for p in self.map.points.values()):
                return
            snaps = [_snapshot_kf(kf) for kf in self.map.keyframes.values() if not kf.erased]
            pts = {pid: p.xyz.copy() for pid, p in self.map.points.items()
                   if len(p.observers) > self.config.max_measurements_per_point}
        cull = measurements_to_cull(snaps, pts, self.camera, self._weights,
                                    self.config.max_measurements_per_point)
        if not cull:
            return
        with self.map.lock:
            for k, p in cull:
                self.map.remove_measurement(k, p)
                self._weights.pop((k, p), None)
            self.map.version += 1
        self.stats['measurements_culled'] += len(cull)

    def _cull_keyframes(self, newest: int) -> None:
        """Sec. 3.3: with more than 35 active keyframes erase the least useful (not the first,
        not the newest)."""
        cfg = self.config
        with self.map.lock:
            active = [kf for kf in self.map.keyframes.values() if not kf.erased]
            if len(active) <= cfg.max_keyframes:
                return
            snaps = [_snapshot_kf(kf) for kf in active]
            pts = {pid: p.xyz.copy() for pid, p in self.map.points.items()}
        erase = keyframes_to_cull(snaps, pts, self.camera, self._weights, cfg.max_keyframes,
                                  cfg.keyframe_utility_threshold,
                                  cfg.max_keyframes_erased_per_round, protected={newest})
        if not erase:
            return
        with self.map.lock:
            for k in erase:
                if k in self.map.keyframes and not self.map.keyframes[k].erased:
                    self.map.erase_keyframe(k)
                    self._weights = {key: w for key, w in self._weights.items() if key[0] != k}
            orphans = [pid for pid, p in self.map.points.items() if not p.observers]
            for pid in orphans:
                self.map.remove_point(pid)
        self.stats['keyframes_culled'] += len(erase)
        self.stats['points_removed'] += len(orphans)
        logger.info('culled keyframe(s) %s', erase)

    def _update_counts(self) -> None:
        with self.map.lock:
            self.stats['points'] = len(self.map.points)
            self.stats['partial_points'] = len(self.map.partial_points)
            self.stats['keyframes_active'] = sum(not kf.erased for kf in self.map.keyframes.values())
