"""Rolling-shutter correction of keyframe measurements (Klein & Murray 2009 sec. 6).

A rolling shutter images each row at a different time, so a moving camera sees every point from
a slightly different pose. The paper removes the first-order effect before bundle adjustment:

1. From the image velocities ``m_dot_i`` of the keyframe's measured points (the tracker's
   measurements in the preceding/following frames, ``Keyframe.image_velocities``), estimate the
   instantaneous camera velocity ``xi_dot`` (6-vector) as the least-squares solution of
   ``[J_1; ...; J_n] xi_dot = [m_dot_1; ...; m_dot_n]``, ``J_i`` the 2x6 projection Jacobian of
   point i w.r.t. the keyframe pose (:func:`~.bundle_adjustment.pose_jacobians`: ``xi = (v,
   omega)`` in the camera frame, acting on the left of ``T_c_w``). The individual velocities
   are noisy and incomplete, so they are not used directly; the 6-DOF fit pools them.
2. Correct each measurement ``m_hat_i = m_i - J_i xi_dot dt_i``, ``dt_i`` the capture time of the
   measurement's row relative to the image centre. Our sensor reads **rows** (the iPhone's read
   columns), so ``dt_i = camera.row_time_offset_s(v_i)``.

The result goes into ``Measurement.uv_corrected``, which bundle adjustment uses; ``uv`` keeps the
raw search result. The mapper corrects each new keyframe and re-corrects all occasionally as the
map changes (the Jacobians depend on the point positions).
"""
from __future__ import annotations

import logging
from typing import Mapping

import numpy as np
from numpy.typing import NDArray

from .bundle_adjustment import pose_jacobians
from .camera import Camera
from .slam_map import Keyframe

logger = logging.getLogger(__name__)

Array = NDArray[np.float64]

#: Fewest points with a known image velocity for a velocity estimate (6 unknowns, 2 rows each).
MIN_POINTS = 4


def estimate_camera_velocity(R_c_w: Array, t_c_w: Array, xyz_w: Array, image_velocities: Array,
                             camera: Camera, outlier_k: float = 3.0) -> Array | None:
    """Least-squares camera velocity ``xi_dot = (v, omega)`` (6,) from point image velocities.

    ``xyz_w`` (N, 3) map points and their image velocities (N, 2) in level-0 px/s. One round of
    residual-based rejection (residual > ``outlier_k`` times the median, a cheap guard against
    mismatched velocity tracks) follows the first fit. None if fewer than ``MIN_POINTS`` points
    in front of the camera or the system is rank deficient.
    """
    xyz_w = np.asarray(xyz_w, float).reshape(-1, 3)
    vel = np.asarray(image_velocities, float).reshape(-1, 2)
    z = xyz_w @ np.asarray(R_c_w, float)[2] + float(np.asarray(t_c_w, float)[2])
    ok = (z > 1e-6) & np.all(np.isfinite(vel), axis=1)
    if ok.sum() < MIN_POINTS:
        return None
    J = pose_jacobians(camera, R_c_w, t_c_w, xyz_w[ok])
    b = vel[ok]
    keep = np.ones(len(b), bool)
    xi = None
    for _ in range(2):
        A = J[keep].reshape(-1, 6)
        if np.linalg.matrix_rank(A) < 6:
            return None
        xi, *_ = np.linalg.lstsq(A, b[keep].reshape(-1), rcond=None)
        r = np.linalg.norm(np.einsum('nij,j->ni', J, xi) - b, axis=1)
        med = float(np.median(r[keep]))
        new_keep = r <= max(outlier_k * med, 1e-9)
        if new_keep.sum() < MIN_POINTS or np.array_equal(new_keep, keep):
            break
        keep = new_keep
    return xi


def correct_keyframe(kf: Keyframe, points: Mapping[int, Array], camera: Camera) -> Array | None:
    """Sets ``uv_corrected`` of every measurement in ``kf`` (sec. 6); returns the velocity used.

    The velocity is estimated from the measurements that have an entry in
    ``kf.image_velocities`` and a position in ``points`` (point id -> xyz). Without a velocity
    estimate (or with a global shutter, ``readout_s == 0``) ``uv_corrected = uv``. Measurements
    of points missing from ``points`` are left uncorrected.
    """
    pids = [pid for pid in kf.measurements if pid in points]
    if camera.readout_s == 0.0 or not pids:
        for m in kf.measurements.values():
            m.uv_corrected = m.uv.copy()
        return None
    vel_ids = [pid for pid in pids if pid in kf.image_velocities]
    xi = None
    if len(vel_ids) >= MIN_POINTS:
        xi = estimate_camera_velocity(
            kf.R_c_w, kf.t_c_w, np.array([points[p] for p in vel_ids]),
            np.array([kf.image_velocities[p] for p in vel_ids]), camera)
    if xi is None:
        for m in kf.measurements.values():
            m.uv_corrected = m.uv.copy()
        return None
    X = np.array([np.asarray(points[p], float) for p in pids])
    J = pose_jacobians(camera, kf.R_c_w, kf.t_c_w, X)
    uv = np.array([kf.measurements[p].uv for p in pids])
    dt = camera.row_time_offset_s(uv[:, 1])
    corr = np.einsum('nij,j->ni', J, xi) * dt[:, None]
    for m in kf.measurements.values():
        m.uv_corrected = m.uv.copy()
    for p, c in zip(pids, corr):
        kf.measurements[p].uv_corrected = kf.measurements[p].uv - c
    logger.debug('kf %d rolling-shutter: |v| %.3g, |w| %.3g rad/s, max shift %.2f px', kf.id,
                 np.linalg.norm(xi[:3]), np.linalg.norm(xi[3:]),
                 float(np.abs(corr).max()) if len(corr) else 0.0)
    return xi


__all__ = ['estimate_camera_velocity', 'correct_keyframe', 'MIN_POINTS']
