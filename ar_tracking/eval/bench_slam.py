"""Speed of the keyframe SLAM core on this machine (``ar-tracking bench --areas slam``).

* ``track_ms_p50/p95_<W>x<H>``: the time of :meth:`Tracker.track` per frame (pyramid, rotation
  prior, patch search, pose update, partial points, keyframe decision) on the handheld_desk
  scenario, with the mapping thread running beside it as in a live run. Frames are rendered
  before timing starts. Only frames tracked against a map count (the initialisation frames are
  reported apart: ``init_ms_p95``).
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

import time
from typing import Any

import numpy as np


def _frames(seed: int, duration_s: float, width: int, height: int) -> list[Any]:
    from ..sim import handheld_desk

    return list(handheld_desk.frames(seed, duration_s, width, height))


def bench_tracking(width: int, height: int, duration_s: float = 20.0, seed: int = 0) -> dict[str, Any]:
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
        for f in frames:
            res = system.process(f.image, int(f.stamp_ns) + 1)
            (tracked_ms if res.state in ('tracking', 'relocalised') else init_ms).append(res.time_ms)
        stats = system.stats()
        est = list(system.path)
    waits = int(stats.get('waited_on_mapper', 0))
    out: dict[str, Any] = {
        f'track_ms_p50_{width}x{height}': round(float(np.percentile(tracked_ms, 50)), 2) if tracked_ms else None,
        f'track_ms_p95_{width}x{height}': round(float(np.percentile(tracked_ms, 95)), 2) if tracked_ms else None,
        f'init_ms_p95_{width}x{height}': round(float(np.percentile(init_ms, 95)), 2) if init_ms else None,
        f'tracking_waits_{width}x{height}': round(waits / max(1, len(frames)), 4),
    }
    if est:
        gt_t = np.array([int(f.stamp_ns) + 1 for f in frames], dtype=np.int64)
        m = slam_metrics_from_arrays(
            np.array([e[0] for e in est], dtype=np.int64), np.array([e[2] for e in est]),
            matrix_to_quat_xyzw(np.array([e[1] for e in est])), gt_t, np.array([f.p_w_c for f in frames]),
            matrix_to_quat_xyzw(np.array([f.R_w_c for f in frames])), len(frames))
        out[f'scenario_{width}x{height}'] = {k: m.get(k) for k in ('tracked_ratio', 'ate_rmse_m', 'ate_ratio', 'path_length_m')}
    return out


def bench_ba(seed: int = 0) -> dict[str, Any]:
    """One bundle-adjustment iteration with 35 keyframes and 300 points."""
    from ..core.slam.bundle_adjustment import benchmark_one_iteration

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
    out['tracking_waits'] = max(out.get('tracking_waits_320x240', 0), out.get('tracking_waits_640x480', 0))
    out['bench_s'] = round(time.perf_counter() - start, 1)
    return out
