"""A synthetic bundle-adjustment problem with its ground truth (tests and the sec. 7 benchmark).

Keyframes on an arc around a point cloud, measured with pixel noise and optional outliers, the
free keyframes and the points started from noisy values: what
:func:`ar_tracking.core.slam.bundle_adjustment.bundle_adjust` must bring back to the truth. It
lived in the core module until issue 21 (test fixtures with truth belong to sim, which may
import core; core never imports sim). Same draws in the same order as before, so a seed gives
the same problem.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from ..core.slam.bundle_adjustment import project_world
from ..core.slam.camera import Camera
from ..core.slam.slam_map import Keyframe, Measurement

Array = NDArray[np.float64]


@dataclass
class SyntheticBAProblem:
    """Noisy-initialised keyframes and points with the ground truth (for tests / benchmarks)."""

    camera: Camera
    keyframes: list[Keyframe]
    points: dict[int, Array]
    true_poses: dict[int, tuple[Array, Array]]
    true_points: dict[int, Array]
    fixed_kf_ids: tuple[int, ...]
    outliers: set[tuple[int, int]]


def look_at(position: Array, target: Array, up: Array | None = None) -> tuple[Array, Array]:
    """(R_c_w, t_c_w) of a camera at ``position`` with its optical axis towards ``target``
    (``up`` default -y, the image's up in a y-down world)."""
    up = np.array([0.0, -1.0, 0.0]) if up is None else up
    z = np.asarray(target, float) - np.asarray(position, float)
    z /= np.linalg.norm(z)
    x = np.cross(up, z)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(np.array([1.0, 0.0, 0.0]), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R_c_w = np.vstack([x, y, z])
    return R_c_w, -R_c_w @ np.asarray(position, float)


def _small_rotation(rng: np.random.Generator, sigma: float) -> Array:
    R, _ = cv2.Rodrigues(rng.normal(0.0, sigma, 3))
    return np.asarray(R, dtype=np.float64)  # float64 in, float64 out: no copy


def make_synthetic_ba_problem(n_keyframes: int = 35, n_points: int = 300, seed: int = 0, *,
                              noise_px: float = 0.5, max_obs_per_point: int = 8,
                              outlier_fraction: float = 0.0, outlier_px: float = 30.0,
                              pose_noise_rad: float = 0.01, pose_noise_m: float = 0.03,
                              point_noise_m: float = 0.05,
                              camera: Camera | None = None) -> SyntheticBAProblem:
    """Keyframes on an arc around a point cloud, each point measured by up to 8 keyframes.

    Keyframes 0 and 1 keep their true poses and are listed in ``fixed_kf_ids`` (fixing two
    keyframes fixes the monocular gauge including scale); the others and all points start from
    noisy values. Measurements carry ``noise_px`` Gaussian noise (level 0, sigma 1) and a fraction
    ``outlier_fraction`` are moved by ``outlier_px`` in a random direction.
    """
    rng = np.random.default_rng(seed)
    cam = camera or Camera(fx=500.0, fy=500.0, cx=319.5, cy=239.5, width=640, height=480)
    true_pts = {i: rng.uniform(-1.0, 1.0, 3) for i in range(n_points)}
    P = np.array([true_pts[i] for i in range(n_points)])
    true_poses: dict[int, tuple[Array, Array]] = {}
    keyframes: list[Keyframe] = []
    outliers: set[tuple[int, int]] = set()
    angles = np.linspace(-0.7, 0.7, n_keyframes)
    vis: list[list[int]] = [[] for _ in range(n_points)]
    for k, a in enumerate(angles):
        pos = np.array([4.0 * np.sin(a), 0.4 * np.sin(3.0 * a + 0.3), -4.0 * np.cos(a)])
        target = rng.normal(0.0, 0.15, 3)
        R, t = look_at(pos, target)
        true_poses[k] = (R, t)
        uv, z = project_world(cam, R, t, P)
        ok = (z > 0.1) & cam.in_image(uv, border=4.0)
        for i_vis in np.nonzero(ok)[0]:
            vis[i_vis].append(k)
    meas: dict[int, dict[int, Measurement]] = {k: {} for k in range(n_keyframes)}
    for i in range(n_points):
        if len(vis[i]) < 2:
            continue
        chosen = vis[i] if len(vis[i]) <= max_obs_per_point else list(
            rng.choice(vis[i], max_obs_per_point, replace=False))
        for k in chosen:
            R, t = true_poses[int(k)]
            uv, _ = project_world(cam, R, t, P[i])
            uv = uv[0] + rng.normal(0.0, noise_px, 2)
            if rng.random() < outlier_fraction:
                ang = rng.uniform(0, 2 * np.pi)
                uv = uv + outlier_px * np.array([np.cos(ang), np.sin(ang)])
                outliers.add((int(k), i))
            meas[int(k)][i] = Measurement(kf_id=int(k), point_id=i, uv=uv, level=0)
    fixed = (0, 1) if n_keyframes > 1 else (0,)
    for k in range(n_keyframes):
        R, t = true_poses[k]
        if k not in fixed:
            R = _small_rotation(rng, pose_noise_rad) @ R
            t = t + rng.normal(0.0, pose_noise_m, 3)
        keyframes.append(Keyframe(id=k, stamp_ns=k * 100_000_000, R_c_w=R.copy(), t_c_w=t.copy(),
                                  pyramid=[], measurements=meas[k], fixed=k == 0))
    observed = {m.point_id for kf in keyframes for m in kf.measurements.values()}
    pts = {i: true_pts[i] + rng.normal(0.0, point_noise_m, 3) for i in sorted(observed)}
    return SyntheticBAProblem(cam, keyframes, pts, true_poses,
                              {i: true_pts[i] for i in sorted(observed)}, fixed, outliers)


__all__ = ['SyntheticBAProblem', 'look_at', 'make_synthetic_ba_problem']
