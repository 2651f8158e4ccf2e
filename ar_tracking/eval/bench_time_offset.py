"""The camera-IMU time offset estimator (:mod:`..core.time_offset`) on a real camera-IMU pair.

EuRoC's calibration sequence ``imu_april`` (../shared/data/euroc_imu_april_detections: a
hand-held VI-Sensor in front of an AprilGrid, AprilGrid corners per 20 Hz frame and the 200 Hz
IMU, one hardware clock) gives the camera's orientation per frame by PnP on the grid's corners
(OpenCV, the sequence's intrinsics and radial-tangential distortion) and the gyro in the IMU
frame (the camera mount from EuRoC's ``T_BS``). The clocks are synchronised in hardware, so the
offset is about 0; with the IMU stamps moved by a known amount the estimate must move with them.
"""
from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from ..core.time_offset import TimeOffsetEstimator
from . import SHARED_DATA

Array = NDArray[np.float64]

EUROC_APRIL_DIR = SHARED_DATA / 'euroc_imu_april_detections'
#: cam0 of the EuRoC VI-Sensor (config.yaml of the sequence): fx, fy, cx, cy; k1, k2, p1, p2.
_K = np.array([[458.654, 0.0, 367.215], [0.0, 457.296, 248.375], [0.0, 0.0, 1.0]])
_DIST = np.array([-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05])
#: R_imu_cam: the rotation of EuRoC's cam0 ``T_BS`` (camera vectors into the body = IMU frame).
R_IMU_CAM0 = np.array([[0.0148655429818, -0.999880929698, 0.00414029679422],
                       [0.999557249008, 0.0149672133247, 0.025715529948],
                       [-0.0257744366974, 0.00375618835797, 0.999660727178]])


def april_frames(folder: Path, min_corners: int = 12) -> list[tuple[int, Array]]:
    """(stamp ns, R_grid_cam) of every frame with at least ``min_corners`` AprilGrid corners."""
    frames = []
    for path in sorted((folder / 'cam0').glob('*.csv')):
        with path.open() as fh:
            rows = [r for r in csv.reader(fh) if r and not r[0].startswith('#')]
        if len(rows) < min_corners:
            continue
        data = np.array(rows, dtype=float)
        ok, rvec, _ = cv2.solvePnP(np.ascontiguousarray(data[:, 7:10]), np.ascontiguousarray(data[:, 5:7]),
                                   _K, _DIST, flags=cv2.SOLVEPNP_ITERATIVE)
        if ok:
            frames.append((int(path.stem), cv2.Rodrigues(rvec)[0].T))
    return frames


def estimate_offset(frames: list[tuple[int, Array]], imu: Array, imu_shift_ns: int = 0) -> tuple[float, float] | None:
    """The estimator fed in stamp order: gyro rows (stamp ns, wx, wy, wz, ...) moved by
    ``imu_shift_ns``, and the frames. Returns (offset s, 1-sigma s) or None."""
    est = TimeOffsetEstimator(R_IMU_CAM0)
    events: list[tuple[int, int, Any]] = [(int(r[0]) + imu_shift_ns, 0, r[1:4]) for r in imu]
    events += [(t, 1, R) for t, R in frames]
    for t_ns, kind, value in sorted(events, key=lambda e: (e[0], e[1])):
        if kind == 0:
            est.add_gyro(t_ns, value)
        else:
            est.add_visual(t_ns, value)
    return est.estimate()


def bench_time_offset(folder: Path = EUROC_APRIL_DIR, shifts_ms: tuple[float, ...] = (0.0, 25.0, -40.0)) -> dict[str, Any]:
    """``orientation.time_offset_euroc``: per IMU shift (ms) the estimated offset and its 1-sigma
    (ms); empty when the recording is absent."""
    if not (folder / 'imu0.csv').is_file():
        return {}
    frames = april_frames(folder)
    imu = np.loadtxt(folder / 'imu0.csv', delimiter=',', comments='#')
    out: dict[str, Any] = {'frames': len(frames)}
    for shift in shifts_ms:
        found = estimate_offset(frames, imu, int(round(shift * 1e6)))
        out[f'shift_{shift:+g}ms'] = None if found is None else \
            {'offset_ms': round(found[0] * 1e3, 3), 'sigma_ms': round(found[1] * 1e3, 3)}
    return out
