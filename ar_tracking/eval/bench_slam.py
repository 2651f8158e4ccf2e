"""Speed of the keyframe SLAM core on this machine (``ar-tracking bench --areas slam``).

* ``track_ms_p50/p95_<W>x<H>``: the time of :meth:`Tracker.track` per frame (pyramid, rotation
  prior, patch search, pose update, partial points, keyframe decision) on the handheld_desk
  scenario, with the mapping thread running beside it as in a live run. Frames are rendered
  before timing starts and, as from a camera, handed over at the scenario's frame rate
  (``realtime``; the mapping thread works while the tracker waits for the next frame, Klein &
  Murray 2009 sec. 3); ``realtime=False`` feeds them back to back (no idle time at all). Only
  frames tracked against a map count (the initialisation frames are reported apart:
  ``init_ms_p95``). ``mapper_steps_in_frame`` is the share of the mapping thread's steps that
  overlapped a frame (:mod:`ar_tracking.core.slam.frame_gate`).
* ``tracking_waits``: the share of frames whose tracking waited on mapping (the map lock held
  longer than 1 ms by the mapping thread). Klein & Murray 2009 sec. 3: bundle adjustment must
  never block tracking, so the target is 0.
* ``ba_iteration_ms``: one Levenberg-Marquardt iteration of bundle adjustment with 35 keyframes
  and 300 points (8 measurements each; sec. 7 of the paper: 750 ms on the iPhone 3G), median
  of repeats; ``ba_call_ms`` includes building the gtsam graph and reading the result back.
* ``scenario.*``: tracked ratio and ATE of the same core run (a quick check that the timed
  tracker is the one that works; the graph's figures come from ``ar-tracking evaluate``).
"""
from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from . import SHARED_DATA

logger = logging.getLogger(__name__)


def _frames(seed: int, duration_s: float, width: int, height: int) -> list[Any]:
    from ..sim import handheld_desk

    return list(handheld_desk.frames(seed, duration_s, width, height))


def bench_tracking(width: int, height: int, duration_s: float = 20.0, seed: int = 0,
                   realtime: bool = True) -> dict[str, Any]:
    """Tracking time per frame of the core on ``duration_s`` of handheld_desk at width x height."""
    from ..core.slam.system import SlamSystem
    from ..sim import handheld_desk
    from .slam_metrics import slam_metrics_from_arrays
    from ..core.rotations import matrix_to_quat_xyzw

    frames = _frames(seed, duration_s, width, height)
    camera = handheld_desk.desk_camera(width, height).slam_camera()
    tracked_ms: list[float] = []
    init_ms: list[float] = []
    est: list[tuple[int, np.ndarray, np.ndarray]] = []
    with SlamSystem(camera) as system:
        t_start = time.perf_counter()
        stamp0 = int(frames[0].stamp_ns) if frames else 0
        for f in frames:
            if realtime:  # wait for the frame as for a camera
                wait = t_start + (int(f.stamp_ns) - stamp0) * 1e-9 - time.perf_counter()
                if wait > 0:
                    time.sleep(wait)
            res = system.process(f.image, int(f.stamp_ns) + 1)
            (tracked_ms if res.state in ('tracking', 'relocalised') else init_ms).append(res.time_ms)
        stats = system.stats()
        gate_obj = getattr(system.mapper, 'gate', None)
        gate = dict(gate_obj.stats) if gate_obj is not None else {'steps_in_frame': 0, 'checkpoints': 0}
        est = list(system.path)
    waits = int(stats.get('waited_on_mapper', 0))
    out: dict[str, Any] = {
        f'track_ms_p50_{width}x{height}': round(float(np.percentile(tracked_ms, 50)), 2) if tracked_ms else None,
        f'track_ms_p95_{width}x{height}': round(float(np.percentile(tracked_ms, 95)), 2) if tracked_ms else None,
        f'init_ms_p95_{width}x{height}': round(float(np.percentile(init_ms, 95)), 2) if init_ms else None,
        f'tracking_waits_{width}x{height}': round(waits / max(1, len(frames)), 4),
        f'mapper_steps_in_frame_{width}x{height}': round(gate['steps_in_frame'] / max(1, gate['checkpoints']), 3),
    }
    if est:
        gt_t = np.array([int(f.stamp_ns) + 1 for f in frames], dtype=np.int64)
        m = slam_metrics_from_arrays(
            np.array([e[0] for e in est], dtype=np.int64), np.array([e[2] for e in est]),
            matrix_to_quat_xyzw(np.array([e[1] for e in est])), gt_t, np.array([f.p_w_c for f in frames]),
            matrix_to_quat_xyzw(np.array([f.R_w_c for f in frames])), len(frames))
        out[f'scenario_{width}x{height}'] = {k: m.get(k) for k in ('tracked_ratio', 'ate_rmse_m', 'ate_ratio', 'path_length_m')}
    return out


def benchmark_one_iteration(n_keyframes: int = 35, n_points: int = 300, seed: int = 0,
                            repeats: int = 5) -> dict[str, float]:
    """Times one BA iteration on the synthetic problem of :mod:`ar_tracking.sim.ba_problem`
    (the sec. 7 figure).

    Returns the median over ``repeats`` of the full call of ``bundle_adjust_one_iteration``
    (graph construction + one LM iteration + read-back; ``ms_call``) and of the single
    ``LevenbergMarquardtOptimizer.iterate()`` alone (linearise + Schur-ordered sparse Cholesky
    solve + error; ``ms_iterate``), and the problem size.
    """
    from ..core.slam.bundle_adjustment import bundle_adjust_one_iteration, prepare_lm
    from ..sim.ba_problem import make_synthetic_ba_problem

    prob = make_synthetic_ba_problem(n_keyframes, n_points, seed)
    calls, iters = [], []
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        bundle_adjust_one_iteration(prob.keyframes, prob.points, prob.camera, prob.fixed_kf_ids)
        calls.append(time.perf_counter() - t0)
    # The bare iteration on a prebuilt graph.
    prepared = prepare_lm(prob.keyframes, prob.points, prob.camera, prob.fixed_kf_ids)
    for _ in range(max(1, repeats)):
        opt = prepared.optimizer()
        t0 = time.perf_counter()
        opt.iterate()
        iters.append(time.perf_counter() - t0)
    out = {'ms_call': float(np.median(calls) * 1e3), 'ms_iterate': float(np.median(iters) * 1e3),
           'keyframes': float(prepared.n_keyframes), 'points': float(prepared.n_points),
           'measurements': float(prepared.n_measurements)}
    logger.info('one BA iteration, %d keyframes / %d points / %d measurements: %.1f ms '
                '(%.1f ms including graph construction)', prepared.n_keyframes, prepared.n_points,
                prepared.n_measurements, out['ms_iterate'], out['ms_call'])
    return out


def bench_ba(seed: int = 0) -> dict[str, Any]:
    """One bundle-adjustment iteration with 35 keyframes and 300 points."""
    r = benchmark_one_iteration(n_keyframes=35, n_points=300, seed=seed, repeats=10)
    return {'ba_iteration_ms': round(float(r['ms_iterate']), 2), 'ba_call_ms': round(float(r['ms_call']), 2),
            'ba_problem': {k: int(r[k]) for k in ('keyframes', 'points', 'measurements')}}


def bench_slam(duration_s: float = 20.0) -> dict[str, Any]:
    """The slam bench area (see the module docstring)."""
    start = time.perf_counter()
    out: dict[str, Any] = {}
    out.update(bench_ba())
    for w, h in ((320, 240), (640, 480)):
        out.update(bench_tracking(w, h, duration_s))
    real = real_euroc_slice()
    if real is not None:
        out['real_euroc_v1_01'] = real
    out['tracking_waits'] = max(out.get('tracking_waits_320x240', 0), out.get('tracking_waits_640x480', 0))
    out['bench_s'] = round(time.perf_counter() - start, 1)
    return out


def real_euroc_slice(data_dir: str | Path | None = None) -> dict[str, Any] | None:
    """The SLAM core on the real EuRoC V1_01 slice in ../shared/data (None when absent).

    The slice has 95 frames of the MAV standing still (no parallax: a monocular SLAM must keep
    waiting for sideways motion and publish nothing) and 10 in-flight frames (0.5 s, 0.18 m,
    12 deg). On the 10 frames the figures are the frames needed to initialise, the frames tracked
    after it, and, against the Vicon ground truth, the error of the relative rotation between the
    first keyframe and the last tracked frame and the angle between the estimated and true direction of
    travel (scale-free, as monocular SLAM has no scale; an ATE over 2-3 poses would be
    meaningless after a similarity alignment).
    """
    import cv2

    from ..core.rotations import angle_of
    from ..core.slam.camera import Rectifier
    from ..core.slam.system import SlamSystem
    from ..io.euroc import read_camera_calib, read_groundtruth_csv, read_images_csv

    root = Path(data_dir) if data_dir is not None else SHARED_DATA / 'euroc_v1_01_micro'
    if not (root / 'mav0' / 'cam0' / 'sensor.yaml').is_file():
        return None
    calib = read_camera_calib(root / 'mav0' / 'cam0' / 'sensor.yaml')
    rectify = Rectifier.from_calibration(calib.K, calib.d, calib.width, calib.height)
    camera = rectify.camera

    def load(path: Path) -> np.ndarray:
        return rectify(cv2.imread(str(path), cv2.IMREAD_GRAYSCALE))

    out: dict[str, Any] = {}
    static = read_images_csv(root / 'mav0' / 'cam0' / 'data.csv')
    with SlamSystem(camera) as system:
        states = [system.process(load(root / 'mav0' / 'cam0' / 'data' / name), t).state for t, name in static]
    out['static_frames'] = len(static)
    out['static_tracked_frames'] = sum(s in ('tracking', 'relocalised') for s in states)

    gt_t, gt_p, gt_R = read_groundtruth_csv(root / 'groundtruth_cam0' / 'V101_GT.txt', invert_quaternion=True)
    files = sorted((root / 'extra_inflight_cam0_jpg').glob('*.jpg'))
    tracked: list[tuple[int, np.ndarray, np.ndarray]] = []
    init_frames = None
    with SlamSystem(camera) as system:
        for k, f in enumerate(files):
            res = system.process(load(f), int(f.stem))
            if res.state in ('tracking', 'relocalised') and res.R_c_w is not None:
                init_frames = k if init_frames is None else init_frames
                tracked.append((int(f.stem), res.R_c_w.T, -res.R_c_w.T @ res.t_c_w))
        with system.map.lock:
            first = min(system.map.keyframes.values(), key=lambda kf: kf.id, default=None)
            if first is not None and tracked:  # from the first keyframe: the whole motion of the slice
                tracked.insert(0, (int(first.stamp_ns), first.R_c_w.T.copy(), first.position_w.copy()))
    out['inflight_frames'] = len(files)
    out['inflight_init_after_frames'] = init_frames
    out['inflight_tracked_frames'] = max(0, len(tracked) - 1)
    if len(tracked) >= 2:
        index = {int(t): i for i, t in enumerate(gt_t)}
        (t0, R0, p0), (t1, R1, p1) = tracked[0], tracked[-1]
        if t0 in index and t1 in index:
            g0, g1 = index[t0], index[t1]
            R_rel_est = R0.T @ R1
            R_rel_gt = gt_R[g0].T @ gt_R[g1]
            out['inflight_rel_rotation_error_deg'] = round(float(np.degrees(angle_of(R_rel_est.T @ R_rel_gt))), 3)
            d_est = R0.T @ (p1 - p0)
            d_gt = gt_R[g0].T @ (gt_p[g1] - gt_p[g0])
            cos = float(d_est @ d_gt / max(1e-12, np.linalg.norm(d_est) * np.linalg.norm(d_gt)))
            out['inflight_direction_error_deg'] = round(float(np.degrees(np.arccos(np.clip(cos, -1, 1)))), 2)
            out['inflight_true_motion'] = {'m': round(float(np.linalg.norm(gt_p[g1] - gt_p[g0])), 4),
                                           'deg': round(float(np.degrees(angle_of(R_rel_gt))), 3)}
    return out
