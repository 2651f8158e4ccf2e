"""Speed of the marker + IMU cores on this machine (``ar-tracking bench``, area ``vi`` and
``markers``): IMU updates per second of the roll-back filter core (15 Hz camera poses arriving
80 ms late, so every pose rolls back ~8 samples and replays them: "roll-backs included"), the
time to detect and refine the markers of one 640x480 frame, and the corner accuracy figures of
:func:`ar_tracking.eval.vi_metrics.marker_corner_accuracy`.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np


def bench_imu_updates(duration_s: float = 20.0, seed: int = 0) -> dict[str, Any]:
    """IMU samples per second through RollbackFusion with late poses (robot_arcs motion)."""
    from ..core.vio.rollback import FusionConfig, PoseMeasurement, RollbackFusion
    from ..sim import robot_arcs as ra

    sched = ra.ArcSchedule.make(duration_s)
    imu_t = np.arange(1, int(duration_s * 1e9), 10_000_000, dtype=np.int64)
    truth = ra.truth_at(sched, imu_t * 1e-9)
    gyro, accel = ra.simulate_imu(truth, ra.make_imu_errors(seed), seed)
    cam_idx = np.arange(0, len(imu_t), 100 // 15 + 1)
    arrivals = {int(i + 8): int(i) for i in cam_idx}
    fusion = RollbackFusion(FusionConfig(R_imu_cam=ra.R_IMU_CAM))
    start = time.perf_counter()
    for i in range(len(imu_t)):
        j = arrivals.get(i)
        if j is not None:
            fusion.add_pose(PoseMeasurement(int(imu_t[j]) - 3_000_000, truth.R_enu_cam[j], truth.position[j]))
        fusion.add_imu(int(imu_t[i]), gyro[i], accel[i])
    wall = time.perf_counter() - start
    return {'imu_updates_per_s': round(len(imu_t) / wall, 1),
            'propagations_per_s': round(fusion.imu_updates / wall, 1),
            'rollbacks': int(fusion.rollbacks), 'imu_samples': int(len(imu_t))}


def bench_detect(frames: int = 20, seed: int = 0) -> dict[str, Any]:
    """Median ms to detect + refine (+ pose) the markers of a robot_arcs 640x480 frame."""
    from ..core.markers.detection import MarkerDetector
    from ..core.markers.lens_model import LensModel
    from ..core.markers.pose import MapMarker, MarkerMap, estimate_camera_pose
    from ..sim import robot_arcs as ra
    from ..sim.world import rng_stream

    cam = ra.Camera()
    lens = LensModel(cam.K)
    mapped, unknown = ra.wall_markers()
    mm = MarkerMap('enu', {m.id: MapMarker(m.id, m.size_m, m.position, m.R_world_marker) for m in mapped})
    sched = ra.ArcSchedule.make(20.0)
    tr = ra.truth_at(sched, np.linspace(0.5, 19.5, frames))
    rng = rng_stream(seed, 'bench-detect')
    images = [ra.render_frame(cam, tr.R_enu_cam[k], tr.position[k], mapped + unknown, rng)[0] for k in range(frames)]
    out: dict[str, Any] = {}
    for name in ('caarls', 'subpix', 'none'):
        det = MarkerDetector(refinement=name)
        times = []
        for img in images:
            t0 = time.perf_counter()
            obs, _ = det.detect(img, lens, mm.ids)
            estimate_camera_pose(obs, mm, lens.focal_px)
            times.append((time.perf_counter() - t0) * 1e3)
        out[name] = round(float(np.median(times)), 3)
    return {'detect_ms_640x480': out['caarls'], 'detect_ms_640x480_by_refinement': out}


def bench_markers_vi(workdir: Path) -> dict[str, Any]:
    """{'vi': {...}, 'markers': {...}} for ``ar-tracking bench`` (workdir is unused: nothing is
    written; kept for the common bench signature)."""
    from .vi_metrics import marker_corner_accuracy

    vi = bench_imu_updates()
    markers = bench_detect()
    markers.update(marker_corner_accuracy(seed=0, n_poses=24, n_noisy=2))
    return {'vi': vi, 'markers': markers}
