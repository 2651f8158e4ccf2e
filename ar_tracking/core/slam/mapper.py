"""The map maker: PTAM's background mapping thread (Klein & Murray 2009 sec. 3, 5.2, 6).

The tracker hands over keyframes through :meth:`MapMaker.add_keyframe`, which only queues them
(the tracking thread must never wait on mapping). The mapping thread, for each queued keyframe:

1. inserts it into the :class:`SlamMap` (its measurements of map points become observations)
   and removes the points the tracker flagged ``bad``;
2. promotes every partially initialised point it measured (sec. 5.2): re-triangulated against
   the point's source keyframe and inserted as a Cartesian :class:`MapPoint` with both
   measurements; the inverse-depth filter state is discarded. The map point keeps the partial
   point's id (both come from :meth:`SlamMap.new_point_id`, so ids never clash) and the tracker
   can keep its associations. A pair with too little parallax stays partial until a later
   keyframe promotes it (dropped after a few failures);
3. applies the rolling-shutter correction (sec. 6) to the keyframe's measurements, and every few
   keyframes re-corrects all keyframes ("occasionally re-corrected");
4. detects multi-scale corners (sec. 3.1, :func:`.pyramid.multiscale_corners`) and adds up to 25
   far from existing features as new partial points with ``q_hat`` the scene's mean inverse depth
   seen from the keyframe and ``info = 0`` (sec. 5.2);
5. runs local bundle adjustment (the new keyframe and its neighbours sharing the most points
   free, every other keyframe measuring those points fixed), removes Tukey outliers (weight 0);
6. culls measurements beyond each point's 8 most useful (sec. 3.2) and, with more than 35 active
   keyframes, the least useful keyframe (sec. 3.3; erased keyframes stay in memory).

When the queue is empty and the map changed, it runs global bundle adjustment over all active
keyframes (the first, ``fixed``, anchors the gauge), aborted as soon as a new keyframe arrives
(or :meth:`MapMaker.initialise_map` or :meth:`MapMaker.stop` is called).

Locking: bundle adjustment never runs under ``SlamMap.lock``. Each step copies what it needs
under the lock, computes without it and writes back in one short locked step
(:meth:`SlamMap.apply_update`), skipping keyframes erased and points deleted in the meantime.
Note that gtsam's optimiser holds the Python GIL for one LM iteration (~10 ms for 35 keyframes /
300 points here), and Python work of the two threads time-slices on the GIL. So, as in the paper
(sec. 3: "bundle adjustment only runs while the tracking thread is waiting for a new frame"), the
thread's work is cut into steps (one BA iteration, one keyframe-insertion step) and each step
waits at :attr:`MapMaker.gate` (:class:`.frame_gate.FrameGate`) until the tracker is between
frames with time for the step before the next frame is due.

The bundle adjustment and culling steps (5, 6 and the global BA) and :class:`MapperConfig` are in
:mod:`.map_upkeep` (:class:`MapMaker` inherits them); this module is the thread, the queue and
the keyframe insertion.
"""
from __future__ import annotations

import logging
import queue
import threading
import time
from dataclasses import replace
from typing import Any, Iterable, Mapping

import numpy as np
from numpy.typing import NDArray

from .bundle_adjustment import BAResult, bundle_adjust, project_world
from .camera import Camera
from .frame_gate import FrameGate
from .map_upkeep import MapperConfig, MapUpkeep, _snapshot_kf
from .point_filter import mean_inverse_depth, predict_partial_uvs, triangulate_two_view
from .pyramid import multiscale_corners
from .rolling_shutter import correct_keyframe
from .slam_map import Keyframe, MapPoint, Measurement, PartialPoint, SlamMap

logger = logging.getLogger(__name__)

Array = NDArray[np.float64]


class MapMaker(MapUpkeep):
    """PTAM's mapping thread over a shared :class:`SlamMap` (see module docstring).

    Public API: :meth:`start`, :meth:`stop`, :meth:`initialise_map` (synchronous),
    :meth:`add_keyframe` (non-blocking), :meth:`queue_length`, :attr:`busy`, :attr:`stats`,
    plus :meth:`wait_idle` and :meth:`process_queue` (synchronous, thread not running) for
    offline use and tests.
    """

    def __init__(self, slam_map: SlamMap, camera: Camera, config: MapperConfig | None = None) -> None:
        self.map = slam_map
        self.camera = camera
        self.config = config or MapperConfig()
        self._queue: queue.Queue[tuple[Keyframe, dict[int, Measurement]]] = queue.Queue()
        self._stop = threading.Event()
        #: Set while a caller (initialise_map) waits for the work lock: global BA yields to it.
        self._preempt = threading.Event()
        self._thread: threading.Thread | None = None
        #: Serialises the map maker's own work (the thread vs initialise_map / process_queue).
        self._work = threading.Lock()
        self._state = threading.Condition()
        self._pending = 0
        self._in_ba = False
        self._global_dirty = False
        self._kf_since_rs = 0
        #: Latest M-estimator weight per (kf id, point id), for the culling metric (sec. 3.2).
        self._weights: dict[tuple[int, int], float] = {}
        self._promotion_failures: dict[int, int] = {}
        #: The tracker reports frame starts/ends here; the thread's steps wait for idle time.
        self.gate = FrameGate()
        self.stats: dict[str, Any] = {
            'keyframes_added': 0, 'ba_runs': 0, 'local_ba_runs': 0, 'global_ba_runs': 0,
            'global_ba_aborted': 0, 'last_ba_ms': 0.0, 'last_ba_iterations': 0,
            'last_ba_objective_before': 0.0, 'last_ba_objective_after': 0.0,
            'keyframes_culled': 0, 'measurements_culled': 0, 'outliers_removed': 0,
            'points_removed': 0, 'points_promoted': 0, 'promotions_failed': 0,
            'partials_added': 0, 'partials_dropped': 0, 'points': 0, 'keyframes_active': 0,
            'rs_corrections': 0, 'errors': 0,
        }

    # ---- thread control ------------------------------------------------------------------------
    def start(self) -> None:
        """Starts the daemon mapping thread (no-op if running)."""
        if self._thread is not None and self._thread.is_alive():
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name='slam-mapper', daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 10.0) -> None:
        """Asks the thread to finish (aborting a global BA between iterations) and joins it."""
        self._stop.set()
        self.gate.release()
        if self._thread is not None:
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                logger.warning('mapping thread did not stop within %.1f s', timeout_s)
            else:
                self._thread = None

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def queue_length(self) -> int:
        """Keyframes queued and not yet taken up by the thread."""
        return self._queue.qsize()

    @property
    def busy(self) -> bool:
        """True while keyframes are queued or being processed, or bundle adjustment runs."""
        with self._state:
            return self._pending > 0 or self._in_ba

    def wait_idle(self, timeout_s: float = 10.0, include_global_ba: bool = False) -> bool:
        """Blocks until every queued keyframe is processed (and, optionally, global BA is done)."""
        deadline = time.monotonic() + timeout_s
        with self.gate.opened(), self._state:  # the caller waits for us: no frame to give way to
            while True:
                idle = self._pending == 0 and not (include_global_ba and (
                    self._in_ba or (self._global_dirty and self.config.global_ba)))
                if idle:
                    return True
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._state.wait(min(left, 0.05))

    # ---- public work ---------------------------------------------------------------------------
    def add_keyframe(self, kf: Keyframe, partial_measurements: Mapping[int, Measurement]) -> None:
        """Queues a keyframe (non-blocking). ``kf.measurements``: map point id -> Measurement;
        ``partial_measurements``: partial point id -> its Measurement in this keyframe."""
        with self._state:
            self._pending += 1
        self._queue.put((kf, dict(partial_measurements)))

    def initialise_map(self, kf0: Keyframe, kf1: Keyframe, xyz_w: Array, uv0: Array, uv1: Array,
                       levels: Iterable[int]) -> None:
        """Builds the initial two-keyframe map (sec. 5.1 end) synchronously.

        Adds both keyframes (``kf0.fixed = True``), one MapPoint per row of ``xyz_w`` (source
        kf0 at ``uv0``/level) measured in both keyframes, runs a short bundle adjustment with kf0
        fixed, restores the initial scale (mean depth in kf0, the plane at depth 1 of sec. 5.1,
        since one fixed keyframe leaves monocular scale free), removes Tukey outliers and seeds
        partial points in both keyframes.
        """
        xyz_w = np.asarray(xyz_w, float).reshape(-1, 3)
        uv0 = np.asarray(uv0, float).reshape(-1, 2)
        uv1 = np.asarray(uv1, float).reshape(-1, 2)
        levels = [int(v) for v in levels]
        self._preempt.set()
        with self.gate.opened(), self._work:
            self._preempt.clear()
            with self.map.lock:
                kf0.fixed = True
                self.map.add_keyframe(kf0)
                self.map.add_keyframe(kf1)
                for X, a, b, lv in zip(xyz_w, uv0, uv1, levels):
                    pid = self.map.new_point_id()
                    self.map.add_point(MapPoint(id=pid, xyz=X.copy(), source_kf=kf0.id,
                                                source_level=lv, source_uv=a.copy()))
                    self.map.add_measurement(Measurement(kf0.id, pid, a, lv))
                    self.map.add_measurement(Measurement(kf1.id, pid, b, lv))
                snap = [_snapshot_kf(kf0), _snapshot_kf(kf1)]
                pts = {pid: p.xyz.copy() for pid, p in self.map.points.items()}
            self._set_in_ba(True)
            try:
                res = bundle_adjust(snap, pts, self.camera, {kf0.id},
                                    self.config.init_ba_iterations, robust=self.config.robust)
            finally:
                self._set_in_ba(False)
            self._restore_scale(res, snap[0], pts)
            self._write_back(res, fixed={kf0.id})
            self._record_ba(res, 'init')
            for kf in (kf0, kf1):
                self._add_partial_points(kf)
            self._global_dirty = True
            self.stats['keyframes_added'] += 2
            self._update_counts()
        logger.info('map initialised: %d points, BA %.1f -> %.1f', len(xyz_w),
                    res.objective_before, res.objective_after)

    def process_queue(self, global_ba: bool = True) -> int:
        """Processes all queued keyframes in the caller's thread (thread not running); returns
        how many. With ``global_ba`` (and ``config.global_ba``) a global bundle adjustment follows
        when the map changed, as the idle thread would do."""
        n = 0
        while True:
            try:
                kf, partial = self._queue.get_nowait()
            except queue.Empty:
                if n and global_ba and self.config.global_ba and self._global_dirty:
                    with self._work:
                        self._global_ba(False)
                return n
            try:
                with self._work:
                    self._process_keyframe(kf, partial)
            finally:
                with self._state:
                    self._pending -= 1
                    self._state.notify_all()
            n += 1

    def global_bundle_adjust(self, abort_on_keyframe: bool = True) -> BAResult | None:
        """Global BA over all active keyframes now (synchronous; the thread does this when idle)."""
        with self.gate.opened(), self._work:
            return self._global_ba(abort_on_keyframe)

    # ---- thread --------------------------------------------------------------------------------
    def _run(self) -> None:
        logger.debug('mapping thread started')
        self.gate.bind()
        while not self._stop.is_set():
            try:
                item = self._queue.get(timeout=self.config.idle_poll_s)
            except queue.Empty:
                item = None
            try:
                if item is not None:
                    with self._work:
                        self._process_keyframe(*item)
                elif self._global_dirty and self.config.global_ba:
                    with self._work:
                        self._global_ba(True)
                self.gate.idle()
            except Exception:       # keep mapping alive; the error is logged and counted
                self.stats['errors'] += 1
                logger.exception('mapping step failed')
                if item is None:
                    self._global_dirty = False
            finally:
                if item is not None:
                    with self._state:
                        self._pending -= 1
                        self._state.notify_all()
        logger.debug('mapping thread stopped')

    # ---- one keyframe ----------------------------------------------------------------------------
    def _process_keyframe(self, kf: Keyframe, partial: dict[int, Measurement]) -> None:
        t0 = time.perf_counter()
        self._checkpoint('insert')
        with self.map.lock:
            # Points the tracker flagged bad (outlier tracks) leave the map.
            bad = [pid for pid, p in self.map.points.items() if p.bad]
            for pid in bad:
                self.map.remove_point(pid)
            self.stats['points_removed'] += len(bad)
            # Measurements of points deleted since the tracker made them are dropped.
            for pid in [p for p in kf.measurements if p not in self.map.points]:
                del kf.measurements[pid]
            for pid, m in kf.measurements.items():
                m.kf_id, m.point_id = kf.id, pid
            self.map.add_keyframe(kf)
        self.stats['keyframes_added'] += 1
        self._checkpoint('promote')
        self._promote(kf, partial)
        if self.config.rolling_shutter:
            self._checkpoint('rolling_shutter')
            self._kf_since_rs += 1
            if self._kf_since_rs >= self.config.rs_recorrect_every:
                self._kf_since_rs = 0
                self._rolling_shutter(None)
            else:
                self._rolling_shutter([kf.id])
        self._checkpoint('partial_points')
        self._add_partial_points(kf)
        self._checkpoint('local_ba')
        self._local_ba(kf.id)
        self._checkpoint('cull_measurements')
        self._cull_measurements()
        self._checkpoint('cull_keyframes')
        self._cull_keyframes(kf.id)
        self._global_dirty = True
        self._checkpoint('counts')
        self._update_counts()
        logger.debug('keyframe %d mapped in %.1f ms', kf.id, (time.perf_counter() - t0) * 1e3)

    def _promote(self, kf: Keyframe, partial: dict[int, Measurement]) -> None:
        """Sec. 5.2: re-triangulate measured partial points against their source keyframe."""
        if not partial:
            return
        cfg = self.config
        jobs = []
        with self.map.lock:
            R1, t1 = np.array(kf.R_c_w, float), np.array(kf.t_c_w, float)
            for ppid, m in partial.items():
                pp = self.map.partial_points.get(ppid)
                if pp is None:
                    continue
                src = self.map.keyframes.get(pp.source_kf)
                if src is None or src.erased or src.id == kf.id:
                    self.map.partial_points.pop(ppid, None)
                    self.stats['partials_dropped'] += 1
                    continue
                jobs.append((ppid, np.array(pp.source_uv, float), int(pp.source_level),
                             np.array(src.R_c_w, float), np.array(src.t_c_w, float), src.id, m))
        if not jobs:
            return
        results = []
        for ppid, suv, slev, R0, t0, sid, m in jobs:
            max_err = cfg.promote_max_error_sigma * max(2.0 ** slev, m.sigma_px)
            xyz_1, good_1 = triangulate_two_view(R0, t0, suv, R1, t1, m.uv, self.camera,
                                                 cfg.min_parallax_deg, max(max_err, 2.0))
            results.append((ppid, suv, slev, R0, t0, sid, m, xyz_1[0], bool(good_1[0])))
        with self.map.lock:
            for ppid, suv, slev, _R0, _t0, sid, m, xyz, good in results:
                pp = self.map.partial_points.get(ppid)
                src = self.map.keyframes.get(sid)
                if pp is None or src is None or src.erased or ppid in self.map.points:
                    continue
                if good:
                    self.map.add_point(MapPoint(id=ppid, xyz=xyz, source_kf=sid,
                                                source_level=slev, source_uv=suv))
                    self.map.add_measurement(Measurement(sid, ppid, suv, slev))
                    self.map.add_measurement(Measurement(kf.id, ppid, m.uv, m.level))
                    del self.map.partial_points[ppid]
                    self._promotion_failures.pop(ppid, None)
                    self.stats['points_promoted'] += 1
                else:
                    n = self._promotion_failures.get(ppid, 0) + 1
                    self._promotion_failures[ppid] = n
                    self.stats['promotions_failed'] += 1
                    # Too little parallax (or an inconsistent match): stays partial, so a later
                    # keyframe can promote it; the tracker already fed this frame to its filter.
                    if n >= cfg.max_promotion_failures:
                        del self.map.partial_points[ppid]
                        self._promotion_failures.pop(ppid, None)
                        self.stats['partials_dropped'] += 1

    def _rolling_shutter(self, kf_ids: list[int] | None) -> None:
        """Sec. 6 on the given (default: all active) keyframes; writes only ``uv_corrected``."""
        if self.camera.readout_s == 0.0:
            return
        with self.map.lock:
            kfs = [self.map.keyframes[k] for k in kf_ids] if kf_ids is not None else \
                [kf for kf in self.map.keyframes.values() if not kf.erased]
            snaps = [_snapshot_kf(kf, copy_measurements=True) for kf in kfs if not kf.erased]
            needed = {pid for s in snaps for pid in s.measurements}
            pts = {pid: self.map.points[pid].xyz.copy() for pid in needed if pid in self.map.points}
        done = []
        for s in snaps:
            xi = correct_keyframe(s, pts, self.camera)
            if xi is not None:
                done.append(s)
        if not done:
            return
        with self.map.lock:
            for s in done:
                kf = self.map.keyframes.get(s.id)
                if kf is None or kf.erased:
                    continue
                for pid, sm in s.measurements.items():
                    m = kf.measurements.get(pid)
                    if m is not None:
                        m.uv_corrected = sm.uv_corrected
        self.stats['rs_corrections'] += len(done)

    def _add_partial_points(self, kf: Keyframe) -> None:
        """Sec. 5.2: up to 25 new corners far from existing features become partial points."""
        cfg = self.config
        if not kf.pyramid or cfg.max_new_points_per_kf <= 0:
            return
        with self.map.lock:
            R, t = np.array(kf.R_c_w, float), np.array(kf.t_c_w, float)
            meas_uv = [m.uv.copy() for m in kf.measurements.values()]
            meas_xyz = [self.map.points[p].xyz.copy() for p in kf.measurements
                        if p in self.map.points]
            _, all_xyz = self.map.point_arrays()
            partial = []
            srcs: dict[int, Keyframe] = {}
            for pp in self.map.partial_points.values():
                src = self.map.keyframes.get(pp.source_kf)
                if src is None:
                    continue
                if src.id not in srcs:
                    srcs[src.id] = _snapshot_kf(src, set())
                partial.append((replace(pp, ray=np.array(pp.ray, float)), srcs[src.id]))
        own = [np.asarray(pp.source_uv, float) for pp, src in partial if src.id == kf.id]
        others = [(pp, src) for pp, src in partial if src.id != kf.id]
        excl = list(meas_uv) + own
        if others:  # where the partial points of other keyframes fall in this one (batched)
            uv, _ = predict_partial_uvs(np.array([pp.ray for pp, _ in others]), [pp.q_hat for pp, _ in others],
                                        [pp.info for pp, _ in others], np.array([src.R_c_w for _, src in others]),
                                        np.array([src.t_c_w for _, src in others]), R, t, self.camera)
            excl.extend(uv[np.all(np.isfinite(uv), axis=1)])
        if len(all_xyz):
            uvp, z = project_world(self.camera, R, t, all_xyz)
            excl.extend(uvp[(z > 1e-6) & self.camera.in_image(uvp)])
        excl_arr = np.array(excl, float).reshape(-1, 2)
        try:
            uv_new, _ = multiscale_corners(kf.pyramid, max_corners=cfg.corner_candidates,
                                           exclude_uv=excl_arr,
                                           exclude_radius_px=cfg.corner_exclude_radius_px)[:2]
        except Exception:
            logger.exception('corner detection failed on keyframe %d', kf.id)
            return
        uv_new = np.asarray(uv_new, float).reshape(-1, 2)[: cfg.max_new_points_per_kf]
        if len(uv_new) == 0:
            return
        ref = np.array(meas_xyz) if meas_xyz else all_xyz
        q0 = mean_inverse_depth(R, t, ref, cfg.default_inverse_depth)
        rays = self.camera.unproject(uv_new)
        with self.map.lock:
            if kf.id not in self.map.keyframes:
                return
            for uv, ray in zip(uv_new, rays):
                pid = self.map.new_point_id()
                self.map.partial_points[pid] = PartialPoint(
                    id=pid, source_kf=kf.id, source_level=0, source_uv=uv.copy(), ray=ray,
                    q_hat=q0, info=0.0)
            self.stats['partials_added'] += len(uv_new)
            excess = len(self.map.partial_points) - cfg.max_partial_points
            if excess > 0:
                for pid in sorted(self.map.partial_points)[:excess]:
                    del self.map.partial_points[pid]
                    self._promotion_failures.pop(pid, None)
                self.stats['partials_dropped'] += excess



__all__ = ['MapperConfig', 'MapMaker']
