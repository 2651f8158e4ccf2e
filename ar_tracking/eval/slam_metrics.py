"""Measures of the monocular keyframe SLAM (Klein & Murray 2009) against the ground truth.

A monocular map has its own frame and scale (the first keyframe, the scale of the stereo
initialisation), so the estimate is compared with the truth after a Sim(3) alignment (Umeyama,
with scale) of the whole tracked trajectory. Everything is computed with ``evo`` (the standard
trajectory-evaluation package), not by hand:

* the estimate (``/slam/pose``: the camera in ``slam_map``) and the truth (``/ground_truth/pose``:
  the camera in the world) are associated by stamp (``evo.core.sync.associate_trajectories``,
  nearest stamp within ``max_diff_s``, 10 ms by default);
* ``ate_rmse_m``: RMSE of the translation part of the absolute pose error
  (``evo.core.metrics.APE``) after ``PoseTrajectory3D.align(correct_scale=True)``; also
  ``ate_mean_m``, ``ate_max_m``, ``ate_rot_rmse_deg`` and the alignment ``scale``;
* ``rpe_rmse``: RMSE (m) of the translation part of the relative pose error
  (``evo.core.metrics.RPE``, all pairs ``delta`` apart) on the same aligned trajectory, with
  ``delta`` = the number of associated poses in ``RPE_DELTA_S`` = 1 s at their median spacing
  (``rpe_delta_frames``: 20 at 20 Hz; a pair spans more than 1 s across tracking gaps);
  ``rpe_rot_rmse_deg`` likewise;
* ``tracked_ratio`` = frames with a pose / camera frames. Camera frames are counted from
  ``/camera/image_raw`` (or ``.../compressed``) in the bag, else from ``/camera/camera_info``
  (the runner does not copy images into its output bag, but it does copy camera_info), else
  from the images of the runner's source bag;
* ``keyframes``: number of poses in the last ``/slam/keyframes``; ``points``: number of points
  in the last ``/slam/map_points``;
* ``path_length_m``: the true path length over the tracked span (first to last pose, evo's
  ``path_length`` of the truth there); ``ate_ratio`` = ``ate_rmse_m / path_length_m``.

:func:`slam_metrics` reads a bag; :func:`slam_metrics_from_arrays` does the same from arrays
(stamps in ns, positions, quaternions in x, y, z, w order). :func:`evaluate_slam` is the
``slam`` area of ``ar-tracking evaluate`` (None when the bag has no ``/slam/pose`` topic).
"""
from __future__ import annotations

import copy
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..io.bags import BagReader, stamp_to_ns

logger = logging.getLogger(__name__)

Array = NDArray[np.float64]

TOPIC_POSE = '/slam/pose'
TOPIC_KEYFRAMES = '/slam/keyframes'
TOPIC_POINTS = '/slam/map_points'
TOPIC_TRUTH = '/ground_truth/pose'
IMAGE_TOPICS = ('/camera/image_raw', '/camera/image_raw/compressed')
TOPIC_CAMERA_INFO = '/camera/camera_info'
RPE_DELTA_S = 1.0
MAX_DIFF_S = 0.01
DECIMALS = 6

#: Every measure this module returns (None when it cannot be computed).
MEASURES = ('ate_rmse_m', 'ate_mean_m', 'ate_max_m', 'ate_rot_rmse_deg', 'scale', 'rpe_rmse',
            'rpe_rot_rmse_deg', 'rpe_delta_frames', 'tracked_ratio', 'tracked_frames', 'frames',
            'keyframes', 'points', 'path_length_m', 'ate_ratio', 'n_associated')


@dataclass
class SlamAlignment:
    """What the metrics were computed on (for figures): associated truth and aligned estimate."""

    t_s: Array            # associated stamps, s from the first pose or truth sample
    p_truth: Array        # (N, 3)
    p_est_aligned: Array  # (N, 3)
    errors_m: Array       # translation APE per pose
    scale: float


def _empty(n_frames: int | None, keyframes: int | None, points: int | None) -> dict[str, Any]:
    out: dict[str, Any] = {k: None for k in MEASURES}
    out.update(frames=n_frames, keyframes=keyframes, points=points, tracked_frames=0,
               tracked_ratio=0.0 if n_frames else None)
    return out


def _clean(stamps_ns: Any, p: Any, q_xyzw: Any) -> tuple[NDArray[np.int64], Array, Array]:
    """Finite poses with unit quaternions, sorted by stamp, one per stamp (the last one)."""
    t = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
    p = np.asarray(p, dtype=float).reshape(-1, 3)
    q = np.asarray(q_xyzw, dtype=float).reshape(-1, 4)
    if not len(t) == len(p) == len(q):
        raise ValueError(f'stamps, positions and quaternions differ in length ({len(t)}, {len(p)}, {len(q)})')
    ok = np.all(np.isfinite(p), axis=1) & np.all(np.isfinite(q), axis=1)
    ok &= np.abs(np.linalg.norm(np.where(np.isfinite(q), q, 0.0), axis=1) - 1.0) < 1e-3
    if not ok.all():
        logger.warning('slam metrics: %d invalid poses ignored', int((~ok).sum()))
    t, p, q = t[ok], p[ok], q[ok]
    order = np.argsort(t, kind='stable')
    t, p, q = t[order], p[order], q[order]
    last = np.r_[t[1:] != t[:-1], True] if len(t) else np.zeros(0, bool)
    return t[last], p[last], q[last] / np.linalg.norm(q[last], axis=1, keepdims=True)


def _traj(t_ns: NDArray[np.int64], p: Array, q_xyzw: Array, t0_ns: int) -> Any:
    from evo.core.trajectory import PoseTrajectory3D

    return PoseTrajectory3D(positions_xyz=p, orientations_quat_wxyz=q_xyzw[:, [3, 0, 1, 2]],
                            timestamps=(t_ns - t0_ns) * 1e-9)


def _compute(stamps_ns_est: Any, p_est: Any, quat_xyzw_est: Any, stamps_ns_gt: Any, p_gt: Any,
             quat_xyzw_gt: Any, n_frames: int | None, keyframes: int | None = None,
             points: int | None = None, max_diff_s: float = MAX_DIFF_S
             ) -> tuple[dict[str, Any], SlamAlignment | None]:
    from evo.core import metrics, sync

    te, pe, qe = _clean(stamps_ns_est, p_est, quat_xyzw_est)
    out = _empty(n_frames, keyframes, points)
    out['tracked_frames'] = int(len(te))
    if n_frames:
        out['tracked_ratio'] = round(min(1.0, len(te) / n_frames), DECIMALS)
    tg, pg, qg = _clean(stamps_ns_gt, p_gt, quat_xyzw_gt)
    if len(te) == 0 or len(tg) < 2:
        return out, None
    t0 = int(min(te[0], tg[0]))
    span = (tg >= te[0]) & (tg <= te[-1])
    if span.sum() >= 2:
        out['path_length_m'] = round(float(_traj(tg[span], pg[span], qg[span], t0).path_length), DECIMALS)
    try:
        ref, est = sync.associate_trajectories(_traj(tg, pg, qg, t0), _traj(te, pe, qe, t0), max_diff=max_diff_s)
    except sync.SyncException as exc:
        logger.warning('slam metrics: no estimate matches the ground truth by stamp (%s)', exc)
        return out, None
    out['n_associated'] = int(ref.num_poses)
    if ref.num_poses < 3:
        logger.warning('slam metrics: only %d poses associated with the truth: no ATE', ref.num_poses)
        return out, None
    aligned = copy.deepcopy(est)
    try:
        _, _, scale = aligned.align(ref, correct_scale=True)
    except Exception as exc:  # evo's GeometryException: degenerate (e.g. all poses at one point)
        logger.warning('slam metrics: Sim(3) alignment failed (%s)', exc)
        return out, None
    if not math.isfinite(scale) or scale <= 0:
        return out, None
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, aligned))
    ape_rot = metrics.APE(metrics.PoseRelation.rotation_angle_deg)
    ape_rot.process_data((ref, aligned))
    stat = metrics.StatisticsType
    out.update(ate_rmse_m=round(float(ape.get_statistic(stat.rmse)), DECIMALS),
               ate_mean_m=round(float(ape.get_statistic(stat.mean)), DECIMALS),
               ate_max_m=round(float(ape.get_statistic(stat.max)), DECIMALS),
               ate_rot_rmse_deg=round(float(ape_rot.get_statistic(stat.rmse)), DECIMALS),
               scale=round(float(scale), DECIMALS))
    if out['path_length_m']:
        out['ate_ratio'] = round(out['ate_rmse_m'] / out['path_length_m'], DECIMALS)
    dt = float(np.median(np.diff(aligned.timestamps)))
    delta = max(1, int(round(RPE_DELTA_S / dt))) if dt > 0 else 1
    if aligned.num_poses > delta:
        rpe = metrics.RPE(metrics.PoseRelation.translation_part, delta=delta,
                          delta_unit=metrics.Unit.frames, all_pairs=True)
        rpe.process_data((ref, aligned))
        rpe_rot = metrics.RPE(metrics.PoseRelation.rotation_angle_deg, delta=delta,
                              delta_unit=metrics.Unit.frames, all_pairs=True)
        rpe_rot.process_data((ref, aligned))
        out.update(rpe_rmse=round(float(rpe.get_statistic(stat.rmse)), DECIMALS),
                   rpe_rot_rmse_deg=round(float(rpe_rot.get_statistic(stat.rmse)), DECIMALS),
                   rpe_delta_frames=delta)
    detail = SlamAlignment(np.asarray(aligned.timestamps, float), np.asarray(ref.positions_xyz), np.asarray(aligned.positions_xyz),
                           np.asarray(ape.error), float(scale))
    return out, detail


def slam_metrics_from_arrays(stamps_ns_est: Any, p_est: Any, quat_xyzw_est: Any, stamps_ns_gt: Any,
                             p_gt: Any, quat_xyzw_gt: Any, n_frames: int | None,
                             keyframes: int | None = None, points: int | None = None,
                             max_diff_s: float = MAX_DIFF_S) -> dict[str, Any]:
    """The measures (module docstring) from arrays: stamps in ns, positions (N, 3), quaternions
    (N, 4) in x, y, z, w order; ``n_frames`` camera frames (None: no tracked_ratio)."""
    return _compute(stamps_ns_est, p_est, quat_xyzw_est, stamps_ns_gt, p_gt, quat_xyzw_gt,
                    n_frames, keyframes, points, max_diff_s)[0]


@dataclass
class SlamBagData:
    """What the measures need from a bag."""

    est: tuple[NDArray[np.int64], Array, Array]
    truth: tuple[NDArray[np.int64], Array, Array]
    n_frames: int | None
    keyframes: int | None
    points: int | None
    has_pose_topic: bool


def _pose_arrays(rows: list[tuple[int, list[float], list[float]]]) -> tuple[NDArray[np.int64], Array, Array]:
    if not rows:
        return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 4))
    return (np.array([r[0] for r in rows], np.int64), np.array([r[1] for r in rows], float),
            np.array([r[2] for r in rows], float))


def _count_frames(bag: BagReader) -> int | None:
    topics = bag.topics
    images = [t for t in IMAGE_TOPICS if t in topics]
    if images:
        return max(bag.message_count([t]) for t in images)
    if TOPIC_CAMERA_INFO in topics:
        return bag.message_count([TOPIC_CAMERA_INFO])
    return None


def load_slam(bag_path: str | Path) -> SlamBagData:
    """Read the SLAM outputs, the truth and the camera frame count of a (runner output) bag."""
    est: list[tuple[int, list[float], list[float]]] = []
    truth: list[tuple[int, list[float], list[float]]] = []
    keyframes = points = None
    with BagReader(bag_path) as bag:
        topics = bag.topics
        n_frames = _count_frames(bag)
        wanted = [t for t in (TOPIC_POSE, TOPIC_TRUTH, TOPIC_KEYFRAMES, TOPIC_POINTS) if t in topics]
        for m in bag.messages(wanted):
            msg = bag.deserialize(m)
            if m.topic == TOPIC_KEYFRAMES:
                keyframes = len(msg.poses)
                continue
            if m.topic == TOPIC_POINTS:
                points = int(msg.width) * int(msg.height)
                continue
            pose = msg.pose
            row = (stamp_to_ns(msg.header.stamp), [pose.position.x, pose.position.y, pose.position.z],
                   [pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w])
            (est if m.topic == TOPIC_POSE else truth).append(row)
    if n_frames is None:
        n_frames = _frames_in_source(bag_path)
    return SlamBagData(_pose_arrays(est), _pose_arrays(truth), n_frames, keyframes, points,
                       TOPIC_POSE in topics)


def _frames_in_source(bag_path: str | Path) -> int | None:
    """Camera frames of the input bag a runner output was made from (when it still exists)."""
    from .evaluate import source_bag_of

    src = source_bag_of(Path(bag_path))
    if src is None:
        return None
    try:
        with BagReader(src) as bag:
            return _count_frames(bag)
    except Exception as exc:  # a missing or broken source bag only costs tracked_ratio
        logger.warning('slam metrics: cannot count the frames of %s (%s)', src, exc)
        return None


def slam_metrics(bag_path: str | Path, max_diff_s: float = MAX_DIFF_S) -> dict[str, Any]:
    """The ``slam`` measures of a bag (module docstring); values are None when they cannot be
    computed (no /slam/pose: everything but frames, keyframes and points)."""
    return slam_metrics_with_alignment(bag_path, max_diff_s)[0]


def slam_metrics_with_alignment(bag_path: str | Path, max_diff_s: float = MAX_DIFF_S
                                ) -> tuple[dict[str, Any], SlamAlignment | None]:
    """:func:`slam_metrics` and the aligned trajectories behind it (for figures)."""
    d = load_slam(bag_path)
    return _compute(*d.est, *d.truth, d.n_frames, d.keyframes, d.points, max_diff_s)


def evaluate_slam(bag_path: str | Path) -> dict[str, Any] | None:
    """The ``slam`` area of ``ar-tracking evaluate``: None when the bag has no /slam/ topic (no
    SLAM ran). A SLAM that ran but never tracked (e.g. a camera that did not move sideways) gives
    tracked_ratio 0 and no ATE."""
    with BagReader(bag_path) as bag:
        if not any(t.startswith('/slam/') for t in bag.topics):
            return None
    return slam_metrics(bag_path)
