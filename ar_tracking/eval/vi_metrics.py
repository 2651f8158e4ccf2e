"""Measures of the marker + IMU fusion (Caarls 2009 sec. 2.6, Fig. 10) and of the marker corners.

:func:`evaluate_vi` scores a runner output bag that holds ``/vi/odometry``, ``/markers/pose``,
``/imu/data_raw`` and ``/ground_truth/pose`` (camera in the world). Names (DESIGN sec. 8):

* ``vi.position_rmse_cm``, ``vi.orientation_rmse_deg``: vi/odometry against the truth at its
  stamps (after ``WARMUP_S`` from the first output, while the filter converges);
* ``vi.camera_only.*``: the camera alone with a hold of the last pose that has *arrived*
  (log time of /markers/pose = capture + processing delay), scored at the IMU stamps - the
  seed's Fig. 10a "no filter, first order hold on pose estimate from the camera";
  ``vi.camera_only_extrapolated.*`` extrapolates linearly from the last two arrived poses;
  ``vi.camera_at_capture.*`` scores each pose at its own capture stamp (Fig. 10b's plusses: the
  accuracy of the camera measurements themselves);
* ``vi.no_rollback.*``: the same filter core run offline on the bag's IMU and poses in arrival
  order, applying each pose when it arrives; ``vi.offline_rollback.*`` is the same offline run
  with roll-back, so the two differ in nothing else. The offline runs use the core's default
  noise and the IMU -> camera rotation of /tf_static; the node's own output (``vi.*``) uses
  whatever parameters it ran with;
* ``vi.by_speed_cm_s.<v>.*``: the same at the robot_arcs cruise speeds (truth speed within 3 %);
  ``vi.fast_rotation.*`` while the truth turns faster than FAST_RATE_RAD_S (quick pans);
  ``vi.coverage``: share of the truth time (after the warm-up) with a fused estimate.

:func:`evaluate_markers` scores ``markers/pose`` alone (camera only, at capture stamps, with its
coverage and covariance consistency) and the corners of ``markers/detections`` against the
simulator's ``/ground_truth/marker_corners`` (area ``markers``).

:func:`marker_corner_accuracy` renders markers with exactly known corners and compares the
seed's refinement with OpenCV's CORNER_REFINE_SUBPIX and with no refinement:
``markers.corner_rmse_px.<method>`` (noisy images) and ``markers.corner_bias_px.<method>``
(RMS corner error on noise-free images: the systematic part).
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..core.rotations import angle_of, interpolate_rotations, matrix_to_rotvec, quat_xyzw_to_matrix, rotvec_to_matrix
from ..core.vio.rollback import FusionConfig, PoseMeasurement, RollbackFusion
from ..io.bags import BagReader, stamp_to_ns

logger = logging.getLogger(__name__)
Array = NDArray[np.float64]

WARMUP_S = 1.0
DECIMALS = 4
TOPIC_ODOM = '/vi/odometry'
TOPIC_POSE = '/markers/pose'
TOPIC_IMU = '/imu/data_raw'
TOPIC_TRUTH = '/ground_truth/pose'


@dataclass
class PoseSeries:
    t_ns: NDArray[np.int64]
    p: Array
    R: Array
    log_ns: NDArray[np.int64] | None = None
    cov: Array | None = None

    def __len__(self) -> int:
        return len(self.t_ns)


def _quat(q: Any) -> list[float]:
    return [q.x, q.y, q.z, q.w]


def _series(t: list[int], p: list[Any], q: list[Any], log: list[int] | None = None, cov: list[Any] | None = None) -> PoseSeries:
    order = np.argsort(np.asarray(t, dtype=np.int64), kind='stable')
    R = quat_xyzw_to_matrix(np.asarray(q, float)) if q else np.zeros((0, 3, 3))
    return PoseSeries(np.asarray(t, np.int64)[order], np.asarray(p, float).reshape(-1, 3)[order], np.asarray(R)[order],
                      None if log is None else np.asarray(log, np.int64)[order],
                      None if cov is None else np.asarray(cov, float).reshape(-1, 6, 6)[order])


@dataclass
class ViData:
    truth: PoseSeries
    odom: PoseSeries
    camera: PoseSeries
    imu_t: NDArray[np.int64]
    imu: Array          # (N, 6) gyro, accel
    R_imu_cam: Array
    t_imu_cam: Array = field(default_factory=lambda: np.zeros(3))   # camera origin in the IMU frame


def load_vi(path: str | Path) -> ViData | None:
    """Read what :func:`evaluate_vi` needs; None when the bag has no /vi/odometry or no truth."""
    with BagReader(path) as bag:
        topics = bag.topics
        if TOPIC_ODOM not in topics or TOPIC_TRUTH not in topics:
            return None
        R_imu_cam, t_imu_cam = np.eye(3), np.zeros(3)
        for m in bag.messages(['/tf_static']):
            for tf in bag.deserialize(m).transforms:
                if tf.header.frame_id.lstrip('/') == 'imu' and tf.child_frame_id.lstrip('/') == 'camera_optical':
                    R_imu_cam = quat_xyzw_to_matrix(np.asarray(_quat(tf.transform.rotation)))
                    tr = tf.transform.translation
                    t_imu_cam = np.array([tr.x, tr.y, tr.z], float)
        cols: dict[str, tuple[list, list, list, list, list]] = {t: ([], [], [], [], []) for t in (TOPIC_TRUTH, TOPIC_ODOM, TOPIC_POSE)}
        imu_t, imu = [], []
        for m in bag.messages([TOPIC_TRUTH, TOPIC_ODOM, TOPIC_POSE, TOPIC_IMU]):
            msg = bag.deserialize(m)
            if m.topic == TOPIC_IMU:
                a, g = msg.linear_acceleration, msg.angular_velocity
                imu_t.append(stamp_to_ns(msg.header.stamp))
                imu.append([g.x, g.y, g.z, a.x, a.y, a.z])
                continue
            pose = msg.pose.pose if m.topic != TOPIC_TRUTH else msg.pose
            q = _quat(pose.orientation)
            if not np.all(np.isfinite(q)) or abs(np.linalg.norm(q) - 1) > 1e-3:
                continue
            c = cols[m.topic]
            c[0].append(stamp_to_ns(msg.header.stamp))
            c[1].append([pose.position.x, pose.position.y, pose.position.z])
            c[2].append(q)
            c[3].append(m.log_time_ns)
            if m.topic == TOPIC_POSE:
                c[4].append(np.asarray(msg.pose.covariance, float))
    truth = _series(*cols[TOPIC_TRUTH][:3])
    odom = _series(*cols[TOPIC_ODOM][:3])
    cam = _series(*cols[TOPIC_POSE][:4], cols[TOPIC_POSE][4])
    if len(truth) < 2 or len(odom) == 0:
        return None
    order = np.argsort(np.asarray(imu_t, np.int64), kind='stable')
    return ViData(truth, odom, cam, np.asarray(imu_t, np.int64)[order], np.asarray(imu, float).reshape(-1, 6)[order],
                  R_imu_cam, t_imu_cam)


def truth_at(truth: PoseSeries, t_ns: NDArray[np.int64]) -> tuple[Array, Array, NDArray[np.bool_]]:
    """Truth position (linear) and orientation (slerp) at stamps inside its time span."""
    inside = (t_ns >= truth.t_ns[0]) & (t_ns <= truth.t_ns[-1])
    tq = (t_ns[inside] - truth.t_ns[0]) * 1e-9
    tt = (truth.t_ns - truth.t_ns[0]) * 1e-9
    p = np.stack([np.interp(tq, tt, truth.p[:, i]) for i in range(3)], -1)
    R, _ = interpolate_rotations(tt, truth.R, tq)
    return p, R, inside


def _errors(truth: PoseSeries, t_ns: NDArray[np.int64], p: Array, R: Array) -> tuple[Array, Array, NDArray[np.int64]]:
    pt, Rt, inside = truth_at(truth, t_ns)
    perr = np.linalg.norm(p[inside] - pt, axis=1)
    oerr = np.degrees(angle_of(R[inside] @ np.swapaxes(Rt, 1, 2)))
    return perr, oerr, t_ns[inside]


def _summary(perr: Array, oerr: Array) -> dict[str, Any]:
    if len(perr) == 0:
        return {'position_rmse_cm': None, 'orientation_rmse_deg': None, 'n': 0}
    return {
        'position_rmse_cm': round(float(100 * np.sqrt(np.mean(perr ** 2))), DECIMALS),
        'position_max_cm': round(float(100 * perr.max()), DECIMALS),
        'orientation_rmse_deg': round(float(np.sqrt(np.mean(oerr ** 2))), DECIMALS),
        'n': int(len(perr)),
    }


def hold_camera(cam: PoseSeries, t_ns: NDArray[np.int64], extrapolate: bool = False) -> tuple[Array, Array, NDArray[np.bool_]]:
    """The camera pose available at each t: the last one that arrived (log time <= t), held or
    extrapolated linearly from the last two arrived poses."""
    assert cam.log_ns is not None
    order = np.argsort(cam.log_ns, kind='stable')
    arr_t, cap_t = cam.log_ns[order], cam.t_ns[order]
    P, R = cam.p[order], cam.R[order]
    j = np.searchsorted(arr_t, t_ns, side='right') - 1
    ok = j >= (1 if extrapolate else 0)
    j = j[ok]
    if not extrapolate:
        return P[j], R[j], ok
    dt_prev = (cap_t[j] - cap_t[j - 1]) * 1e-9
    ahead = (t_ns[ok] - cap_t[j]) * 1e-9
    f = np.where(dt_prev > 0, ahead / np.maximum(dt_prev, 1e-9), 0.0)
    p = P[j] + (P[j] - P[j - 1]) * f[:, None]
    rel = matrix_to_rotvec(R[j] @ np.swapaxes(R[j - 1], 1, 2)) * f[:, None]
    return p, rotvec_to_matrix(rel) @ R[j], ok


def run_offline(data: ViData, rollback: bool, config: FusionConfig | None = None) -> PoseSeries:
    """The filter core on the bag's IMU and poses in arrival order (IMU stamp = arrival)."""
    cfg = config or FusionConfig(R_imu_cam=data.R_imu_cam, t_imu_cam=data.t_imu_cam)
    if cfg.rollback != rollback:
        from dataclasses import replace

        cfg = replace(cfg, rollback=rollback)
    fusion = RollbackFusion(cfg)
    if not rollback:  # applied on arrival, the filter re-initialises often: that is the point, not news
        quiet = logging.getLogger('ar_tracking.core.vio.rollback')
        level = quiet.level
        quiet.setLevel(logging.ERROR)
        try:
            return _run_events(data, fusion)
        finally:
            quiet.setLevel(level)
    return _run_events(data, fusion)


def _run_events(data: ViData, fusion: RollbackFusion) -> PoseSeries:
    """Feed the bag's IMU samples and camera poses (in arrival order) to a fusion core."""
    cam = data.camera
    assert cam.log_ns is not None and cam.cov is not None
    events = sorted([(int(t), 0, i) for i, t in enumerate(data.imu_t)]
                    + [(int(t), -1, i) for i, t in enumerate(cam.log_ns)])
    t_out, p_out, R_out = [], [], []
    for _t, kind, i in events:
        if kind == -1:
            cov = cam.cov[i] if cam.cov[i][0, 0] != -1 else None
            fusion.add_pose(PoseMeasurement(int(cam.t_ns[i]), cam.R[i], cam.p[i], cov))
            continue
        fusion.add_imu(int(data.imu_t[i]), data.imu[i, :3], data.imu[i, 3:])
        s = fusion.state
        if s is not None:
            R, p = fusion.camera_pose(s)
            t_out.append(int(data.imu_t[i]))
            p_out.append(p)
            R_out.append(R)
    return PoseSeries(np.asarray(t_out, np.int64), np.asarray(p_out).reshape(-1, 3), np.asarray(R_out).reshape(-1, 3, 3))


def _after_warmup(s: PoseSeries, t0: int) -> PoseSeries:
    keep = s.t_ns >= t0
    return PoseSeries(s.t_ns[keep], s.p[keep], s.R[keep],
                      None if s.log_ns is None else s.log_ns[keep], None if s.cov is None else s.cov[keep])


def _speed_at(truth: PoseSeries, t_ns: NDArray[np.int64]) -> Array:
    tt = truth.t_ns * 1e-9
    v = np.linalg.norm(np.gradient(truth.p, tt, axis=0), axis=1)
    return np.interp(t_ns * 1e-9, tt, v)


def evaluate_vi(bag_path: str | Path, offline: bool = True) -> dict[str, Any] | None:
    """The ``vi`` measures of a runner output bag (module docstring); None without /vi/odometry."""
    data = load_vi(bag_path)
    if data is None:
        return None
    t0 = int(data.odom.t_ns[0] + WARMUP_S * 1e9)
    odom = _after_warmup(data.odom, t0)
    out: dict[str, Any] = {}
    pe, oe, t_f = _errors(data.truth, odom.t_ns, odom.p, odom.R)
    out.update(_summary(pe, oe))
    out['coverage'] = coverage(data.truth, odom.t_ns, t0)
    series = {'filter': (pe, oe, t_f)}
    if len(data.camera):
        cam = _after_warmup(data.camera, t0)
        cpe, coe, _ = _errors(data.truth, cam.t_ns, cam.p, cam.R)
        out['camera_at_capture'] = _summary(cpe, coe)
        grid = odom.t_ns
        for key, extra in (('camera_only', False), ('camera_only_extrapolated', True)):
            p, R, ok = hold_camera(data.camera, grid, extra)
            hpe, hoe, t_h = _errors(data.truth, grid[ok], p, R)
            out[key] = _summary(hpe, hoe)
            series[key] = (hpe, hoe, t_h)
        if offline and len(data.imu_t):
            for key, rb in (('offline_rollback', True), ('no_rollback', False)):
                s = _after_warmup(run_offline(data, rb), t0)
                ope, ooe, t_o = _errors(data.truth, s.t_ns, s.p, s.R)
                out[key] = _summary(ope, ooe)
                series[key] = (ope, ooe, t_o)
    from ..sim.robot_arcs import ARC_SPEEDS_M_S

    by_speed: dict[str, Any] = {}
    for v in ARC_SPEEDS_M_S:
        entry: dict[str, Any] = {}
        for key, (perr, oerr, ts) in series.items():
            sel = np.abs(_speed_at(data.truth, ts) - v) < 0.03 * v
            if sel.sum() >= 10:
                entry[key] = _summary(perr[sel], oerr[sel])
        if entry:
            by_speed[str(int(round(v * 100)))] = entry
    if by_speed:
        out['by_speed_cm_s'] = by_speed
    fast: dict[str, Any] = {}
    for key, (perr, oerr, ts) in series.items():
        sel = _rate_at(data.truth, ts) > FAST_RATE_RAD_S
        if sel.sum() >= 5:
            fast[key] = _summary(perr[sel], oerr[sel])
    if fast:
        out['fast_rotation'] = fast
    return out


#: Truth angular rate above which a stamp counts as a quick pan (rad/s, ~57 deg/s).
FAST_RATE_RAD_S = 1.0


def _rate_at(truth: PoseSeries, t_ns: NDArray[np.int64]) -> Array:
    """Truth angular rate (rad/s) at stamps, from consecutive truth orientations."""
    if len(truth) < 2:
        return np.zeros(len(t_ns))
    dt = np.diff(truth.t_ns) * 1e-9
    rel = angle_of(truth.R[1:] @ np.swapaxes(truth.R[:-1], 1, 2))
    rate = rel / np.maximum(dt, 1e-9)
    mid = (truth.t_ns[1:] + truth.t_ns[:-1]) // 2
    return np.interp(t_ns * 1e-9, mid * 1e-9, rate)


def coverage(truth: PoseSeries, t_ns: NDArray[np.int64], start_ns: int, gap_s: float = 0.2) -> float | None:
    """Share of the truth time after ``start_ns`` that has an estimate no older than ``gap_s``."""
    span = truth.t_ns[(truth.t_ns >= start_ns)]
    if len(span) == 0:
        return None
    t = np.sort(np.asarray(t_ns, np.int64))
    j = np.searchsorted(t, span, side='right') - 1
    ok = (j >= 0) & ((span - t[np.maximum(j, 0)]) <= int(gap_s * 1e9))
    return round(float(ok.mean()), DECIMALS)


# --- markers/pose (camera only) and the corners against the truth ----------------------------

TOPIC_DETECTIONS = '/markers/detections'
TOPIC_TRUTH_CORNERS = '/ground_truth/marker_corners'
TOPIC_CAMERA_INFO = '/camera/camera_info'


def evaluate_markers(bag_path: str | Path) -> dict[str, Any] | None:
    """The ``markers`` measures of a runner output bag; None without /markers/pose or truth.

    * ``markers.pose.*``: every markers/pose against the truth at its capture stamp (camera
      only, no IMU): ``position_rmse_cm``, ``position_max_cm``, ``orientation_rmse_deg``, ``n``;
      ``coverage`` = poses / camera frames (camera_info stamps, or the truth-corner frames);
      ``nees_position_median`` (the position error weighed by the pose's own covariance: 3 when
      the covariance is honest, much more when it claims too much); ``fast_rotation.*`` the
      same over the frames taken while the camera turned faster than FAST_RATE_RAD_S (pans);
    * ``markers.corner_bias_px`` (mean offset of the detected corners away from their marker's
      centre: negative = inward) and ``markers.corner_rmse_px``, against
      /ground_truth/marker_corners (simulator bags; markers the truth marks as partly occluded
      are left out and counted in ``corners_occluded_detected``), matched by stamp and ID
      with the accepted /markers/detections.
    """
    with BagReader(bag_path) as bag:
        topics = bag.topics
        if TOPIC_POSE not in topics or TOPIC_TRUTH not in topics:
            return None
        cols: dict[str, list] = {TOPIC_TRUTH: [[], [], []], TOPIC_POSE: [[], [], [], []]}
        frames: set[int] = set()
        truth_frames: set[int] = set()
        det: dict[tuple[int, int], Array] = {}
        gt: dict[tuple[int, int], tuple[Array, bool]] = {}
        wanted = [TOPIC_TRUTH, TOPIC_POSE, TOPIC_DETECTIONS, TOPIC_TRUTH_CORNERS, TOPIC_CAMERA_INFO]
        for m in bag.messages([t for t in wanted if t in topics]):
            msg = bag.deserialize(m)
            if m.topic == TOPIC_CAMERA_INFO:
                frames.add(stamp_to_ns(msg.header.stamp))
                continue
            if m.topic in (TOPIC_DETECTIONS, TOPIC_TRUTH_CORNERS):
                for mk in msg.markers:
                    pts = np.array([[p.x, p.y] for p in mk.points[:4]], float)
                    if len(pts) != 4:
                        continue
                    key = (stamp_to_ns(mk.header.stamp), int(mk.id))
                    if m.topic == TOPIC_DETECTIONS and mk.ns == 'accepted':
                        det[key] = pts
                    elif m.topic == TOPIC_TRUTH_CORNERS:
                        gt[key] = (pts, mk.ns == 'occluded')
                        truth_frames.add(key[0])
                continue
            pm = msg.pose.pose if m.topic == TOPIC_POSE else msg.pose
            q = _quat(pm.orientation)
            if not np.all(np.isfinite(q)) or abs(np.linalg.norm(q) - 1) > 1e-3:
                continue
            c = cols[m.topic]
            c[0].append(stamp_to_ns(msg.header.stamp))
            c[1].append([pm.position.x, pm.position.y, pm.position.z])
            c[2].append(q)
            if m.topic == TOPIC_POSE:
                c[3].append(np.asarray(msg.pose.covariance, float))
    tc, pc = cols[TOPIC_TRUTH], cols[TOPIC_POSE]
    truth = _series(tc[0], tc[1], tc[2])
    cam = _series(pc[0], pc[1], pc[2], None, pc[3])
    if len(truth) < 2:
        return None
    out: dict[str, Any] = {}
    pose: dict[str, Any] = {}
    if len(cam):
        pe, oe, t_in = _errors(truth, cam.t_ns, cam.p, cam.R)
        pose.update(_summary(pe, oe))
        n_frames = len(frames) or len(truth_frames)
        pose['coverage'] = round(len(cam) / n_frames, DECIMALS) if n_frames else None
        pt, _, inside = truth_at(truth, cam.t_ns)
        nees = []
        assert cam.cov is not None
        for e, c in zip(cam.p[inside] - pt, cam.cov[inside]):
            P = c[:3, :3]
            if c[0, 0] > 0 and np.all(np.isfinite(P)):
                try:
                    nees.append(float(e @ np.linalg.solve(P, e)))
                except np.linalg.LinAlgError:
                    continue
        pose['nees_position_median'] = round(float(np.median(nees)), DECIMALS) if nees else None
        sel = _rate_at(truth, t_in) > FAST_RATE_RAD_S
        if sel.sum():
            pose['fast_rotation'] = _summary(pe[sel], oe[sel])
    else:
        pose.update(_summary(np.zeros(0), np.zeros(0)))
        pose['coverage'] = 0.0
    out['pose'] = pose
    if gt:
        offsets, errs, occluded = [], [], 0
        for key, pts in det.items():
            if key not in gt:
                continue
            g, occ = gt[key]
            if occ:
                occluded += 1
                continue
            out_dir = (g - g.mean(0)) / np.linalg.norm(g - g.mean(0), axis=1, keepdims=True)
            offsets.append(float(np.mean(np.sum((pts - g) * out_dir, axis=1))))
            errs.append(pts - g)
        if errs:
            e = np.concatenate(errs)
            out['corner_bias_px'] = round(float(np.mean(offsets)), DECIMALS)
            out['corner_rmse_px'] = round(float(np.sqrt(np.mean(np.sum(e ** 2, axis=1)))), DECIMALS)
            out['corners_markers'] = len(offsets)
            out['corners_occluded_detected'] = occluded
    return out


# --- marker corners -----------------------------------------------------------------------

def marker_corner_accuracy(seed: int = 0, n_poses: int = 24, n_noisy: int = 2,
                           noise: float = 2.0, blur_sigma_px: float = 0.6,
                           display_gamma: float = 1.0) -> dict[str, Any]:
    """Corner RMSE and bias of the refinements on rendered markers with known corners.

    A 30 cm AprilTag at 1.5-3.5 m, tilted up to ~35 deg and turned in-plane at random, is
    rendered (robot_arcs' renderer: exact corners, 8x supersampling, Gaussian blur, noise) in a
    640x480 ideal pinhole camera, in light; ``display_gamma`` > 1 encodes the frame as a camera
    does (I = 255 (L / 255)^(1 / gamma)) after blur and noise. Methods: ``caarls`` (the edge
    model with the gamma estimated from the marker's black/white levels and its print contrast),
    ``caarls_edge_symmetry`` (the gamma from the symmetry of its edges, no print contrast),
    ``caarls_given_gamma`` (the gamma given), ``opencv_subpix``, ``none``. Returns {'corner_rmse_px': {method: ..},
    'corner_bias_px': {method: ..} (RMS on noise-free images), 'corner_outward_px': {method: ..}
    (mean offset of the corners away from the marker centre on the noisy images), 'n_corners'}.
    """
    import cv2

    from ..core.markers.detection import MarkerDetector
    from ..core.markers.lens_model import LensModel
    from ..core.rotations import rot_x, rot_y, rot_z
    from ..sim import robot_arcs as ra
    from ..sim.world import rng_stream

    rng = rng_stream(seed, 'corner-accuracy')
    cam = ra.Camera()
    lens = LensModel(cam.K)
    methods = {'caarls': MarkerDetector(refinement='caarls', print_contrast=ra.WHITE / ra.BLACK),
               'caarls_edge_symmetry': MarkerDetector(refinement='caarls'),
               'caarls_given_gamma': MarkerDetector(refinement='caarls', response_gamma=display_gamma),
               'opencv_subpix': MarkerDetector(refinement='subpix'),
               'none': MarkerDetector(refinement='none')}
    noisy: dict[str, list[Array]] = {k: [] for k in methods}
    clean: dict[str, list[Array]] = {k: [] for k in methods}
    outward: dict[str, list[float]] = {k: [] for k in methods}
    for _ in range(n_poses):
        R_m = ra.R_ENU_WALL_MARKER @ rot_y(rng.uniform(-0.6, 0.6)) @ rot_x(rng.uniform(-0.6, 0.6)) @ rot_z(rng.uniform(-math.pi, math.pi))
        mk = ra.MarkerSpec(5, 0.30, np.array([rng.uniform(-0.6, 0.6), 3.2, 1.0 + rng.uniform(-0.4, 0.4)]), R_m)
        p_cam = np.array([0.0, rng.uniform(-0.3, 1.7), 1.0])
        for level, store, reps in ((0.0, clean, 1), (noise, noisy, n_noisy)):
            for _ in range(reps):
                img, truth = ra.render_frame(cam, ra.R0_ENU_CAM, p_cam, [mk], rng, blur_sigma_px, level)
                if mk.id not in truth:
                    continue
                if display_gamma != 1.0:
                    img = np.rint(255.0 * np.power(img / 255.0, 1.0 / display_gamma)).astype(np.uint8)
                results = {k: d.detect(img, lens)[0] for k, d in methods.items()}
                if not all(len(r) == 1 and r[0].id == mk.id for r in results.values()):
                    continue
                g = truth[mk.id]
                out_dir = (g - g.mean(0)) / np.linalg.norm(g - g.mean(0), axis=1, keepdims=True)
                for k, r in results.items():
                    store[k].append(r[0].corners_px - g)
                    if level > 0:
                        outward[k].append(float(np.mean(np.sum((r[0].corners_px - g) * out_dir, axis=1))))
    del cv2
    out: dict[str, Any] = {'corner_rmse_px': {}, 'corner_bias_px': {}, 'corner_mean_error_px': {}, 'corner_outward_px': {}}
    for k in methods:
        e = np.concatenate(noisy[k]) if noisy[k] else np.zeros((0, 2))
        c = np.concatenate(clean[k]) if clean[k] else np.zeros((0, 2))
        out['corner_rmse_px'][k] = round(float(np.sqrt(np.mean(np.sum(e ** 2, 1)))), DECIMALS) if len(e) else None
        out['corner_bias_px'][k] = round(float(np.sqrt(np.mean(np.sum(c ** 2, 1)))), DECIMALS) if len(c) else None
        out['corner_mean_error_px'][k] = round(float(np.linalg.norm(e.mean(0))), DECIMALS) if len(e) else None
        out['corner_outward_px'][k] = round(float(np.mean(outward[k])), DECIMALS) if outward[k] else None
    out['n_corners'] = int(sum(len(x) for x in noisy['caarls']))
    return out
