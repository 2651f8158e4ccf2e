"""The tracking thread of PTAM on a camera phone (Klein & Murray 2009, sec. 4, 5.1, 5.2, 6).

Per frame: image pyramid; constant-velocity motion model corrected by the full-frame ESM rotation
prior on the small blurry image (sec. 4, the prior is estimated *on top of* the motion model's
prediction so translation is not counted twice); project the map points; warped 8x8 patch search
on L1 (on L2 with a looser threshold when the prior predicts fast rotation); robust SE(3) pose
update (optionally rolling-shutter aware); tracking quality (fraction of searched points found)
-> good / poor / lost. With a good pose the partially initialised points (sec. 5.2) are searched
and their inverse-depth filters updated. Keyframes are added when tracking is good, the rotation
is not fast, the camera is far enough from every keyframe (erased ones too) relative to the mean
scene depth and the mapper's queue is short; the keyframe carries the measurements of map points,
those of partial points go alongside (``MapMaker.add_keyframe``) and image velocities from the
previous frame (sec. 6). Before a map exists the two-stage initialiser (sec. 5.1) runs. When lost,
the keyframe relocaliser (ECCV'08) proposes poses.

Threading: the tracker never waits on the mapper; it reports each frame's start and end to the
mapper's frame gate (:mod:`.frame_gate`), whose steps run between frames (sec. 3). Mapper calls
are non-blocking; the map is read under ``SlamMap.lock`` only to copy point arrays, keyframe poses
and partial points (a few hundred small objects); ``stats['waited_on_mapper']`` counts frames
whose lock acquisition took more than 1 ms. A bad frame (wrong size or type, no texture) never
touches the map.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..rotations import trace_angle
from .camera import Camera, camera_in_world
from .initialiser import InitConfig, Initialiser
from .mapper import MapMaker
from .patch_search import SearchConfig, search_points
from .point_filter import predict_partial_uvs, update_inverse_depth
from .pose_update import refine_pose, se3_exp, se3_log
from .pyramid import build_pyramid, small_blurry_image
from .relocaliser import relocalise
from .rotation_prior import estimate_rotation, rotation_homography
from .slam_map import Keyframe, Measurement, SlamMap

log = logging.getLogger(__name__)

Array = NDArray[np.float64]
Image = NDArray[np.uint8]

STATES = ('initialising', 'waiting', 'tracking', 'lost', 'relocalised')


@dataclass(frozen=True)
class TrackerConfig:
    """Tracking parameters (sec. 4)."""

    #: Map points searched per frame (the paper searches 50 on the phone, sec. 7). 80 saves ~0.6 ms
    #: per frame at 640x480 with the handheld_desk ATE within about +-15 % of 120's over seeds and
    #: lengths (better on some, worse on others), so the default stays 120.
    max_points: int = 120
    search_level: int = 1  #: sec. 4: fixed search level L1
    coarse_level: int = 2  #: fast rotation: search only L2
    #: Predicted inter-frame rotation (as level-0 pixels at the image centre) that counts as fast.
    fast_rotation_px: float = 30.0
    use_rotation_prior: bool = True
    pose_iterations: int = 8
    rolling_shutter: bool = True  #: row-pose prediction in the pose update (needs readout_s > 0)
    good_fraction: float = 0.5
    lost_fraction: float = 0.2
    min_inliers: int = 10
    min_texture_std: float = 2.0  #: frames flatter than this (L2 grey std) are rejected
    #: A longer gap since the last tracked frame makes the motion model stale: the next frame is
    #: accepted only with a good match, else relocalised (as after lost frames), s.
    max_gap_s: float = 1.0
    # keyframes
    kf_min_dist_frac: float = 0.10  #: distance to the nearest keyframe / mean scene depth
    kf_min_frames: int = 4  #: frames since the last keyframe
    kf_max_mapper_queue: int = 2
    kf_low_points: int = 30  #: fewer visible points: allow a keyframe at half the distance
    # partial points (sec. 5.2)
    #: Partial points searched per frame (sec. 7 searches 12; here 12 leaves the map ~25 % sparser
    #: and the 10 s handheld_desk ATE 0.32 % -> 0.51 %, so 25).
    max_partial: int = 25
    partial_max_radius_l1: float = 8.0
    # relocalisation
    reloc_max_ssd: float | None = None
    velocity_damping: float = 0.9
    init: InitConfig = field(default_factory=InitConfig)
    search: SearchConfig = field(default_factory=SearchConfig)


@dataclass
class TrackResult:
    """What :meth:`Tracker.track` made of one frame."""

    state: str
    R_c_w: Array | None
    t_c_w: Array | None
    n_measured: int = 0
    n_inliers: int = 0
    fast_rotation: bool = False
    keyframe_added: bool = False
    message: str = ''
    stamp_ns: int = 0
    time_ms: float = 0.0
    quality: str = ''  #: 'good' | 'poor' | 'lost' when tracking


class Tracker:
    """PTAM tracker: ``track(gray, stamp_ns)`` per frame; feeds ``mapper`` with keyframes."""

    def __init__(self, camera: Camera, slam_map: SlamMap, mapper: MapMaker,
                 config: TrackerConfig | None = None) -> None:
        self.camera = camera
        self.map = slam_map
        self.mapper = mapper
        self.cfg = config or TrackerConfig()
        self.initialiser = Initialiser(camera, self.cfg.init)
        self._coarse_cam = camera.at_level(4)
        self._rng = np.random.default_rng(0)
        self.R: Array | None = None
        self.t: Array | None = None
        self.velocity = np.zeros(6)  # twist per second, left: T(t+dt) = exp(dt xi) T(t)
        self.last_stamp: int | None = None
        self.last_sbi: NDArray[np.float32] | None = None
        self.lost_frames = 0
        self.frames_since_kf = 0
        self.mean_depth = 1.0
        self._prev_meas: dict[int, Array] = {}
        self._prev_meas_stamp: int | None = None
        self._reloc_tried: set[int] = set()
        self.stats: dict[str, Any] = {'frames': 0, 'tracked': 0, 'lost': 0, 'keyframes_added': 0,
                                      'waited_on_mapper': 0, 'relocalised': 0, 'fast_rotation': 0,
                                      'bad_input': 0, 'times_ms': []}

    # ------------------------------------------------------------------------------------------
    def _result(self, state: str, msg: str, stamp: int, t0: float, **kw: Any) -> TrackResult:
        res = TrackResult(state, kw.pop('R', None), kw.pop('t', None), message=msg, stamp_ns=stamp, **kw)
        res.time_ms = (time.perf_counter() - t0) * 1e3
        self.stats['frames'] += 1
        times = self.stats['times_ms']
        times.append(res.time_ms)
        if len(times) > 5000:
            del times[:1000]
        if state == 'lost':
            self.stats['lost'] += 1
        elif state in ('tracking', 'relocalised'):
            self.stats['tracked'] += 1
        return res

    def _check_input(self, gray: Any) -> str | None:
        if not isinstance(gray, np.ndarray):
            return 'bad input: not an image array'
        if gray.dtype != np.uint8:
            return f'bad input: dtype {gray.dtype}, need uint8'
        if gray.ndim != 2:
            return f'bad input: {gray.ndim}-D array, need a single-channel image'
        if gray.shape != (self.camera.height, self.camera.width):
            return (f'bad input: image {gray.shape[1]}x{gray.shape[0]} does not match the camera '
                    f'{self.camera.width}x{self.camera.height}')
        return None

    def track(self, gray: Image, stamp_ns: int) -> TrackResult:
        """Tracks one frame; never raises on bad input (state 'lost' with a message).

        The mapper's frame gate is told when the frame starts and ends, so that mapping
        steps run between frames (sec. 3, :mod:`.frame_gate`)."""
        self.mapper.gate.frame_started()
        try:
            return self._track(gray, stamp_ns)
        finally:
            self.mapper.gate.frame_finished()

    def _track(self, gray: Image, stamp_ns: int) -> TrackResult:
        t0 = time.perf_counter()
        try:
            bad = self._check_input(gray)
            if bad is not None:
                self.stats['bad_input'] += 1
                return self._result('lost', bad, stamp_ns, t0)
            pyr = build_pyramid(gray)
            if float(pyr[2].std()) < self.cfg.min_texture_std:
                self.stats['bad_input'] += 1
                if self.R is not None:  # blind: the motion model goes stale, recover as from lost
                    self.lost_frames += 1
                    self.velocity = np.zeros(6)
                return self._result('lost', 'bad input: textureless image', stamp_ns, t0)
            sbi = small_blurry_image(pyr)
            with self.map.lock:
                have_map = len(self.map.keyframes) > 0
            if not have_map:
                res = self._initialise(pyr, sbi, stamp_ns, t0)
            else:
                res = self._track_map(pyr, sbi, stamp_ns, t0)
            self.last_sbi = sbi
            return res
        except Exception as exc:  # never let a frame take the node down
            log.exception('tracker: frame failed')
            return self._result('lost', f'error: {exc!r}', stamp_ns, t0)

    # ---- initialisation (sec. 5.1) -------------------------------------------------------------
    def _initialise(self, pyr: list[Image], sbi: NDArray[np.float32], stamp: int, t0: float) -> TrackResult:
        st = self.initialiser.process(pyr, sbi, stamp)
        if st.state != 'done':
            state = 'waiting' if st.state == 'waiting' else 'initialising'
            return self._result(state, st.message, stamp, t0, n_measured=st.n_measured, n_inliers=st.n_inliers)
        kf0, kf1, xyz0, uv0, uv1, levels = st.kf0, st.kf1, st.xyz, st.uv0, st.uv1, st.levels
        R0, t0_c_w = st.R_c_w, st.t_c_w
        # A 'done' status carries the pose and the initial map (Initialiser._finish sets them all).
        assert (kf0 is not None and kf1 is not None and xyz0 is not None and uv0 is not None
                and uv1 is not None and levels is not None and R0 is not None and t0_c_w is not None)
        kf0.id = self.map.new_keyframe_id()
        kf1.id = self.map.new_keyframe_id()
        self.mapper.initialise_map(kf0, kf1, xyz0, uv0, uv1, levels)
        self.R, self.t = R0, t0_c_w
        self.velocity = np.zeros(6)
        self.last_stamp = stamp
        self.frames_since_kf = 0
        self.lost_frames = 0
        with self.map.lock:
            ids, xyz = self.map.point_arrays()
        if len(xyz):
            z = (xyz @ self.R.T + self.t)[:, 2]
            self.mean_depth = float(np.median(z[z > 0])) if np.any(z > 0) else 1.0
        log.info('tracker: map initialised with %d points', len(ids))
        return self._result('tracking', f'initialised: {len(ids)} map points', stamp, t0,
                            R=self.R.copy(), t=self.t.copy(), n_measured=st.n_measured, n_inliers=st.n_inliers)

    # ---- map snapshot ------------------------------------------------------------------------------
    def _snapshot(self) -> dict[str, Any]:
        t_req = time.perf_counter()
        with self.map.lock:
            waited = (time.perf_counter() - t_req) > 1e-3
            ids, xyz = self.map.point_arrays()
            pts = self.map.points
            src_kf = np.array([pts[i].source_kf for i in ids], np.int64)
            src_uv = np.array([pts[i].source_uv for i in ids], float).reshape(-1, 2)
            kfs = {k: (kf.R_c_w.copy(), kf.t_c_w.copy(), kf.pyramid, kf.erased) for k, kf in self.map.keyframes.items()}
            kf_objs = list(self.map.keyframes.values())
            partial = []
            if self.map.partial_points:
                pp_list = list(self.map.partial_points.values())
                if len(pp_list) > self.cfg.max_partial:
                    sel = self._rng.choice(len(pp_list), self.cfg.max_partial, replace=False)
                    pp_list = [pp_list[i] for i in sel]
                partial = [pp for pp in pp_list if pp.source_kf in self.map.keyframes]
        if waited:
            self.stats['waited_on_mapper'] += 1
        return dict(ids=ids, xyz=xyz, src_kf=src_kf, src_uv=src_uv, kfs=kfs, kf_objs=kf_objs, partial=partial)

    # ---- tracking (sec. 4) ----------------------------------------------------------------------
    def _pose(self) -> tuple[Array, Array]:
        """The current pose (R_c_w, t_c_w). Set together by :meth:`_initialise` and at the start
        of :meth:`_track_map` (identity if a frame comes before either), so every step of
        tracking against the map has one."""
        assert self.R is not None and self.t is not None, 'tracker: no pose before tracking the map'
        return self.R, self.t

    def _predict(self, sbi: NDArray[np.float32], stamp: int) -> tuple[Array, Array, bool]:
        R_cur, t_cur = self._pose()
        dt = 0.0 if self.last_stamp is None else max(0.0, (stamp - self.last_stamp) * 1e-9)
        dR, dtv = se3_exp(self.velocity * dt)
        R_pred, t_pred = dR @ R_cur, dR @ t_cur + dtv
        total_rot = dR
        if self.cfg.use_rotation_prior and self.last_sbi is not None and self.last_sbi.shape == sbi.shape:
            H0 = rotation_homography(self._coarse_cam, dR, dtv, self.mean_depth)
            est = estimate_rotation(self.last_sbi, sbi, self._coarse_cam, H0=H0, iterations=6)
            if (np.isfinite(est.residual) and est.residual < est.residual0 and est.overlap > 0.3
                    and trace_angle(est.R_cur_prev) < 0.3):
                dRp = est.R_cur_prev
                R_pred, t_pred = dRp @ R_pred, dRp @ t_pred
                total_rot = dRp @ dR
        fast = bool(trace_angle(total_rot) * self.camera.fx > self.cfg.fast_rotation_px)
        return R_pred, t_pred, fast

    def _measure(self, pyr: list[Image], snap: dict[str, Any], R: Array, t: Array, coarse: bool,
                 radius: float | None = None) -> tuple[NDArray[np.int64], Array, Array, int, int]:
        """Searches visible map points; returns (idx into snap, uv0 found, levels, n_searched, level)."""
        xyz = snap['xyz']
        if len(xyz) == 0:
            return np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0), 0, 1
        uv, front = self.camera.project(xyz @ R.T + t)
        vis = np.nonzero(front & self.camera.in_image(uv, 4.0))[0]
        if len(vis) > self.cfg.max_points:
            vis = np.sort(self._rng.choice(vis, self.cfg.max_points, replace=False))
        if len(vis) == 0:
            return vis, np.zeros((0, 2)), np.zeros(0), 0, 1
        kfs = snap['kfs']
        src_kf = snap['src_kf'][vis]
        srcR = np.array([kfs[k][0] for k in src_kf]) if len(src_kf) else np.zeros((0, 3, 3))
        srct = np.array([kfs[k][1] for k in src_kf]) if len(src_kf) else np.zeros((0, 3))
        pyrs = {k: v[2] for k, v in kfs.items()}
        level = self.cfg.coarse_level if coarse else self.cfg.search_level
        res = search_points(pyr, self.camera, R, t, xyz[vis], pyrs, src_kf, snap['src_uv'][vis], srcR, srct,
                            level, self.cfg.search, coarse=coarse, radius=radius, uv_pred0=uv[vis])
        f = res.found
        n_searched = int(np.isfinite(res.zssd).sum()) if len(vis) else 0
        return vis[f], res.uv0[f], np.full(int(f.sum()), float(level)), max(n_searched, 1), level

    def _attempt(self, pyr: list[Image], snap: dict[str, Any], R: Array, t: Array, coarse: bool,
                 radius: float | None = None) -> dict[str, Any]:
        idx, uv, lev, n_searched, level = self._measure(pyr, snap, R, t, coarse, radius)
        out = dict(idx=idx, uv=uv, level=level, n_searched=n_searched, n_found=len(idx), R=R, t=t,
                   inliers=np.zeros(len(idx), bool), quality='lost')
        if len(idx) < max(6, self.cfg.min_inliers // 2):
            return out
        vel = self.velocity if (self.cfg.rolling_shutter and self.camera.readout_s > 0) else None
        pr = refine_pose(snap['xyz'][idx], uv, lev, self.camera, R, t, iterations=self.cfg.pose_iterations,
                         velocity=vel)
        n_in = int(pr.inliers.sum())
        frac = n_in / max(1, n_searched)
        if n_in >= self.cfg.min_inliers and frac >= self.cfg.good_fraction:
            q = 'good'
        elif n_in >= self.cfg.min_inliers and frac >= self.cfg.lost_fraction:
            q = 'poor'
        else:
            q = 'lost'
        out.update(R=pr.R_c_w, t=pr.t_c_w, inliers=pr.inliers, quality=q, n_inliers=n_in)
        return out

    def _track_map(self, pyr: list[Image], sbi: NDArray[np.float32], stamp: int, t0: float) -> TrackResult:
        snap = self._snapshot()
        if self.R is None:
            self.R, self.t = np.eye(3), np.zeros(3)
        relocalised = False
        if (self.lost_frames == 0 and self.last_stamp is not None
                and (stamp - self.last_stamp) * 1e-9 > self.cfg.max_gap_s):
            self.lost_frames = 1  # frames were dropped for long: the prediction is stale
            self.velocity = np.zeros(6)
        R_pred, t_pred, fast = self._predict(sbi, stamp)
        if self.lost_frames > 0:
            fast = False
        if fast:
            self.stats['fast_rotation'] += 1
        att = self._attempt(pyr, snap, R_pred, t_pred, coarse=fast)
        if att['quality'] != 'lost' and fast:
            pass  # sec. 4: fast rotation frames are tracked on L2 only and never become keyframes
        if att['quality'] != 'good' and self.lost_frames > 0:
            # Recovering from lost: the prediction is stale, so only a good match is trusted
            # (a 'poor' one from a wrong pose can look consistent); otherwise relocalise.
            cand = relocalise(sbi, snap['kf_objs'], self.camera, self.cfg.reloc_max_ssd)
            att2 = None
            if cand is not None:
                att2 = self._attempt(pyr, snap, cand.R_c_w, cand.t_c_w, coarse=True, radius=5.0)
                if att2['quality'] != 'lost':
                    att2 = self._attempt(pyr, snap, att2['R'], att2['t'], coarse=False)
            if att2 is not None and att2['quality'] == 'good':
                att = att2
                relocalised = True
            else:
                att = dict(att, quality='lost')
        n_meas, n_in = att['n_found'], int(att['inliers'].sum())
        if att['quality'] == 'lost':
            self.lost_frames += 1
            self.velocity = np.zeros(6)
            self.last_stamp = stamp
            self._prev_meas = {}
            return self._result('lost', f'lost: {n_in}/{att["n_searched"]} points', stamp, t0,
                                n_measured=n_meas, n_inliers=n_in, fast_rotation=fast, quality='lost')
        # Accept the pose; update the motion model.
        R_new, t_new = att['R'], att['t']
        dt = 0.0 if self.last_stamp is None else (stamp - self.last_stamp) * 1e-9
        if dt > 0 and not relocalised and self.lost_frames == 0:
            xi = se3_log(R_new @ self.R.T, t_new - R_new @ self.R.T @ self.t) / dt
            self.velocity = self.cfg.velocity_damping * xi
        else:
            self.velocity = np.zeros(6)
        self.R, self.t = R_new, t_new
        self.last_stamp = stamp
        if relocalised:
            self.stats['relocalised'] += 1
        self.lost_frames = 0
        inl_idx = att['idx'][att['inliers']]
        inl_uv = att['uv'][att['inliers']]
        if len(inl_idx):
            z = (snap['xyz'][inl_idx] @ self.R.T + self.t)[:, 2]
            if np.any(z > 0):
                self.mean_depth = float(np.median(z[z > 0]))
        # Partial points (sec. 5.2): search and filter-update with a good pose.
        partial_meas: dict[int, Measurement] = {}
        if att['quality'] == 'good' and not fast and snap['partial']:
            partial_meas = self._track_partial(pyr, snap)
        self.frames_since_kf += 1
        kf_added = False
        meas_now = {int(snap['ids'][i]): uv for i, uv in zip(inl_idx, inl_uv)}
        if att['quality'] == 'good' and not fast and not relocalised:
            kf_added = self._maybe_add_keyframe(pyr, sbi, stamp, snap, meas_now, att['level'], partial_meas)
        self._prev_meas, self._prev_meas_stamp = meas_now, stamp
        state = 'relocalised' if relocalised else 'tracking'
        return self._result(state, f'{att["quality"]}: {n_in}/{att["n_searched"]} points' + (' (L2)' if fast else ''),
                            stamp, t0, R=self.R.copy(), t=self.t.copy(), n_measured=n_meas, n_inliers=n_in,
                            fast_rotation=fast, keyframe_added=kf_added, quality=att['quality'])

    def _track_partial(self, pyr: list[Image], snap: dict[str, Any]) -> dict[int, Measurement]:
        kfs = snap['kfs']
        kf_objs = {kf.id: kf for kf in snap['kf_objs']}
        pps = [pp for pp in snap['partial'] if pp.source_kf in kf_objs]
        if not pps:
            return {}
        uvp, rad, X = self._predict_partial(pps, kfs)
        ok = np.all(np.isfinite(uvp), axis=1) & self.camera.in_image(np.nan_to_num(uvp, nan=-1e6), 8.0)
        if not np.any(ok):
            return {}
        pps = [pp for pp, o in zip(pps, ok) if o]
        uvp, rad, X = uvp[ok], rad[ok], X[ok]
        src_kf = np.array([pp.source_kf for pp in pps], np.int64)
        srcR = np.array([kfs[k][0] for k in src_kf])
        srct = np.array([kfs[k][1] for k in src_kf])
        src_uv = np.array([pp.source_uv for pp in pps], float)
        radius = float(np.clip(max(rad) / 2 ** self.cfg.search_level, self.cfg.search.radius, self.cfg.partial_max_radius_l1))
        R_cur, t_cur = self._pose()
        res = search_points(pyr, self.camera, R_cur, t_cur, X, {k: v[2] for k, v in kfs.items()}, src_kf, src_uv,
                            srcR, srct, self.cfg.search_level, self.cfg.search, radius=radius, uv_pred0=uvp)
        out: dict[int, Measurement] = {}
        sigma = float(2 ** self.cfg.search_level)
        found = np.nonzero(res.found)[0]
        if len(found) == 0:
            return out
        with self.map.lock:
            for i in found:
                pp = pps[i]
                if pp.id not in self.map.partial_points:
                    continue
                # Only accept matches within the point's own epipolar radius.
                if np.linalg.norm(res.uv0[i] - uvp[i]) > rad[i] + 2.0:
                    continue
                Rs, ts = kfs[pp.source_kf][0], kfs[pp.source_kf][1]
                update_inverse_depth(pp, R_cur, t_cur, Rs, ts, res.uv0[i], sigma, self.camera)
                out[pp.id] = Measurement(-1, pp.id, res.uv0[i], self.cfg.search_level)
        return out

    def _predict_partial(self, pps: list, kfs: dict) -> tuple[Array, Array, Array]:
        """Level-0 pixels and epipolar search radii of partial points (sec. 5.2, the point
        filter's model, :func:`.point_filter.predict_partial_uvs`), and their world points at
        q_hat."""
        Rs = np.array([kfs[pp.source_kf][0] for pp in pps])
        ts = np.array([kfs[pp.source_kf][1] for pp in pps])
        ray = np.array([pp.ray for pp in pps], float)
        q = np.array([pp.q_hat for pp in pps], float)
        R_cur, t_cur = self._pose()
        uv, r = predict_partial_uvs(ray, q, np.array([pp.info for pp in pps], float), Rs, ts,
                                    R_cur, t_cur, self.camera)
        Xs = ray / np.maximum(q, 1e-6)[:, None]
        X = np.einsum('nji,nj->ni', Rs, Xs - ts)
        return uv, r, X

    def _maybe_add_keyframe(self, pyr: list[Image], sbi: NDArray[np.float32], stamp: int, snap: dict[str, Any],
                            meas_now: dict[int, Array], level: int, partial_meas: dict[int, Measurement]) -> bool:
        if self.frames_since_kf < self.cfg.kf_min_frames:
            return False
        if self.mapper.queue_length() > self.cfg.kf_max_mapper_queue:
            return False
        R_cur, t_cur = self._pose()
        _, p_w = camera_in_world(R_cur, t_cur)
        pos = np.array([-(v[0].T @ v[1]) for v in snap['kfs'].values()])
        dmin = float(np.min(np.linalg.norm(pos - p_w, axis=1))) if len(pos) else np.inf
        need = self.cfg.kf_min_dist_frac * self.mean_depth
        if len(meas_now) < self.cfg.kf_low_points:
            need *= 0.5
        if dmin < need:
            return False
        kf_id = self.map.new_keyframe_id()
        kf = Keyframe(id=kf_id, stamp_ns=stamp, R_c_w=R_cur.copy(), t_c_w=t_cur.copy(), pyramid=pyr, sbi=sbi)
        for pid, uv in meas_now.items():
            kf.measurements[pid] = Measurement(kf_id, pid, uv, level)
        # Image velocities from the previous frame (sec. 6), level-0 px/s.
        if self._prev_meas and self._prev_meas_stamp is not None and stamp > self._prev_meas_stamp:
            dt = (stamp - self._prev_meas_stamp) * 1e-9
            for pid, uv in meas_now.items():
                prev = self._prev_meas.get(pid)
                if prev is not None:
                    kf.image_velocities[pid] = (uv - prev) / dt
        partial = {pid: Measurement(kf_id, pid, m.uv, m.level) for pid, m in partial_meas.items()}
        self.mapper.add_keyframe(kf, partial)
        self.frames_since_kf = 0
        self.stats['keyframes_added'] += 1
        log.debug('tracker: keyframe %d with %d measurements, %d partial', kf_id, len(kf.measurements), len(partial))
        return True

    def timing_ms(self) -> tuple[float, float]:
        """(p50, p95) per-frame tracking time so far."""
        t = np.array(self.stats['times_ms'])
        if len(t) == 0:
            return float('nan'), float('nan')
        return float(np.percentile(t, 50)), float(np.percentile(t, 95))
