"""Speed and accuracy of the marker + IMU chain on this machine (``ar-tracking bench``, areas
``vi`` and ``markers``): IMU updates per second of the roll-back filter core (15 Hz camera poses
arriving 80 ms late, so every pose rolls back ~8 samples and replays them: "roll-backs
included"), the time to detect and refine the markers of one 640x480 frame, the corner accuracy
figures of :func:`ar_tracking.eval.vi_metrics.marker_corner_accuracy` (linear and gamma 2.2
images), and ``vi.seeds`` / ``markers.seeds``: the issue's targets on fresh hard-profile
robot_arcs bags (:func:`bench_seeds`: the graph run on each, scored by evaluate, with the
spread over the seeds).
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
    """Median ms to detect + refine (+ pose) the markers of a robot_arcs 640x480 frame, once
    the response gamma has settled."""
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
        for img in images:  # the response gamma settles once per camera (first ~40 markers): not timed
            if det.gamma_estimator.settled:
                break
            det.detect(img, lens, mm.ids)
        times = []
        for img in images:
            t0 = time.perf_counter()
            obs, _ = det.detect(img, lens, mm.ids)
            estimate_camera_pose(obs, mm, lens.focal_px)
            times.append((time.perf_counter() - t0) * 1e3)
        out[name] = round(float(np.median(times)), 3)
    return {'detect_ms_640x480': out['caarls'], 'detect_ms_640x480_by_refinement': out}


#: Fresh seeds of the accuracy bench (not used by any test) and their length, s. Six, so that
#: the spread says whether a target is met by the method or by the draw.
BENCH_SEEDS: tuple[int, ...] = (301, 302, 303, 304, 305, 306)
BENCH_DURATION_S = 20.0


def _pick(d: dict[str, Any], path: str) -> Any:
    for k in path.split('.'):
        if not isinstance(d, dict) or k not in d:
            return None
        d = d[k]
    return d


#: (bench key, evaluate path) of the issue's targets, per seed.
TARGET_KEYS: tuple[tuple[str, str], ...] = (
    ('vi.position_rmse_cm', 'vi.position_rmse_cm'),
    ('vi.orientation_rmse_deg', 'vi.orientation_rmse_deg'),
    ('vi.position_max_cm', 'vi.position_max_cm'),
    ('vi.fast_rotation_max_cm', 'vi.fast_rotation.filter.position_max_cm'),
    ('vi.coverage', 'vi.coverage'),
    ('vi.no_rollback_position_rmse_cm', 'vi.no_rollback.position_rmse_cm'),
    ('markers.pose_position_rmse_cm', 'markers.pose.position_rmse_cm'),
    ('markers.pose_orientation_rmse_deg', 'markers.pose.orientation_rmse_deg'),
    ('markers.pose_coverage', 'markers.pose.coverage'),
    ('markers.pose_nees_position_median', 'markers.pose.nees_position_median'),
    ('markers.pose_fast_rotation_rmse_cm', 'markers.pose.fast_rotation.position_rmse_cm'),
    ('markers.corner_bias_px', 'markers.corner_bias_px'),
    ('markers.corner_rmse_px', 'markers.corner_rmse_px'),
)


def bench_seeds(workdir: Path, seeds: tuple[int, ...] = BENCH_SEEDS,
                duration_s: float = BENCH_DURATION_S) -> dict[str, Any]:
    """The issue's targets on fresh hard-profile robot_arcs bags, one per seed: the marker +
    IMU graph run on each (mount only on /tf_static, as the bag has it), scored by evaluate;
    and OpenCV's pipeline (marker_tracker with ``corner_refinement: subpix``, no gamma handling)
    on the same images for the camera-only comparison. Returns {'by_seed': {seed: {key:
    value}}, 'spread': {key: {min, median, max}}, 'command': how to redo one seed by hand}."""
    import yaml

    from ..ros.runner import GraphRunner
    from ..sim.bagmaker import make_bag
    from .vi_metrics import evaluate_markers, evaluate_vi

    workdir.mkdir(parents=True, exist_ok=True)
    by_seed: dict[str, dict[str, Any]] = {}
    for seed in seeds:
        bag = workdir / f'robot_arcs_hard_seed{seed}.mcap'
        params = bag.with_name(bag.stem + '.params.yaml')
        if not bag.exists():
            make_bag('robot_arcs', bag, seed=seed, duration_s=duration_s, overwrite=True)
        out = workdir / f'seed{seed}.out.mcap'
        GraphRunner(bag, out, params_files=[params], named_graph='markers').run()
        metrics = {'vi': evaluate_vi(out) or {}, 'markers': evaluate_markers(out) or {}}
        row = {key: _pick(metrics, path) for key, path in TARGET_KEYS}
        side = yaml.safe_load(params.read_text())
        side['marker_tracker']['ros__parameters']['corner_refinement'] = 'subpix'
        cv_params = workdir / f'seed{seed}.opencv.params.yaml'
        cv_params.write_text(yaml.safe_dump(side))
        cv_out = workdir / f'seed{seed}.opencv.out.mcap'
        GraphRunner(bag, cv_out, params_files=[cv_params], nodes=['marker_tracker']).run()
        cv = evaluate_markers(cv_out) or {}
        row['markers.opencv_subpix_pose_position_rmse_cm'] = _pick(cv, 'pose.position_rmse_cm')
        row['markers.opencv_subpix_corner_bias_px'] = _pick(cv, 'corner_bias_px')
        by_seed[str(seed)] = row
    spread: dict[str, Any] = {}
    for key in next(iter(by_seed.values())):
        vals = [r[key] for r in by_seed.values() if r.get(key) is not None]
        if vals:
            spread[key] = {'min': min(vals), 'median': float(np.median(vals)), 'max': max(vals)}
    return {'by_seed': by_seed, 'spread': spread, 'duration_s': duration_s,
            'command': (f'ar-tracking make-bag robot_arcs --seed {seeds[0]} --duration {duration_s:g} -o x.mcap && '
                        'ar-tracking run x.mcap -o x.out.mcap --graph markers && ar-tracking evaluate x.out.mcap --json')}


def bench_markers_vi(workdir: Path) -> dict[str, Any]:
    """{'vi': {...}, 'markers': {...}} for ``ar-tracking bench``: speed, the corner accuracy
    on rendered markers (linear and gamma 2.2), and the targets on fresh seeds (written under
    workdir)."""
    from .vi_metrics import marker_corner_accuracy

    vi = bench_imu_updates()
    markers = bench_detect()
    markers.update(marker_corner_accuracy(seed=0, n_poses=24, n_noisy=2))
    markers['gamma_2_2'] = marker_corner_accuracy(seed=0, n_poses=24, n_noisy=2, display_gamma=2.2)
    seeds = bench_seeds(workdir / 'seeds')
    vi['seeds'] = {'spread': {k[3:]: v for k, v in seeds['spread'].items() if k.startswith('vi.')},
                   'by_seed': {s: {k[3:]: v for k, v in r.items() if k.startswith('vi.')} for s, r in seeds['by_seed'].items()},
                   'duration_s': seeds['duration_s'], 'command': seeds['command']}
    markers['seeds'] = {'spread': {k[8:]: v for k, v in seeds['spread'].items() if k.startswith('markers.')},
                        'by_seed': {s: {k[8:]: v for k, v in r.items() if k.startswith('markers.')} for s, r in seeds['by_seed'].items()}}
    return {'vi': vi, 'markers': markers}
