"""Partially initialised points (Klein & Murray 2009 sec. 5.2) and two-view triangulation.

A new corner of keyframe K becomes a point ``p_K = (x, y, 1)^T / q`` in K's camera frame with
``q ~ N(q_hat, 1/info)``: the ray ``(x, y, 1)`` is known (the un-projected corner), only the
inverse depth q is free. Between keyframes the tracker measures the point in ordinary frames and
:func:`update_inverse_depth` refines ``q`` with a scalar *extended information filter*; the
information ``info`` starts at 0 (sigma = infinity). Cameras and ``x, y`` are taken as perfectly
known, so a measurement only informs q through the reprojection error *along the epipolar line*
(the direction ``d uv / d q``); the error across the line carries no information about q.

As in the paper the filter serves data association only: :func:`predict_partial_uv` gives the
search position and an uncertainty-based radius along the epipolar line, and once a second
keyframe measures the point the mapper re-triangulates it against the source keyframe with
:func:`triangulate_two_view`, discarding the filter state.

Inverse-depth projection: with ``R = R_c_w R_src_w^T`` and ``t = t_c_w - R t_src_w`` the point in
the current camera is ``R ray / q + t``, which projects like the homogeneous vector
``h(q) = R ray + q t``; so ``uv(q) = pi(h(q))`` and ``d uv/dq = J_pi(h) t`` stay finite at q = 0
(the point at infinity, the vanishing end of the epipolar line).
"""
from __future__ import annotations

import logging

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .camera import Camera
from .slam_map import Keyframe, PartialPoint

logger = logging.getLogger(__name__)

Array = NDArray[np.float64]

#: Smallest inverse depth kept by the filter (q must stay positive: the point is in front).
Q_MIN = 1e-6


def _relative(R_c_w: Array, t_c_w: Array, R_src_w: Array, t_src_w: Array) -> tuple[Array, Array]:
    """(R, t) mapping source-camera coordinates into the current camera."""
    R = np.asarray(R_c_w, float) @ np.asarray(R_src_w, float).T
    return R, np.asarray(t_c_w, float) - R @ np.asarray(t_src_w, float)


def _project_h(camera: Camera, h: Array) -> tuple[Array, Array]:
    """Pixel of homogeneous camera vector ``h`` (3,) and d uv / d h (2, 3)."""
    iz = 1.0 / h[2]
    uv = np.array([camera.fx * h[0] * iz + camera.cx, camera.fy * h[1] * iz + camera.cy])
    J = np.array([[camera.fx * iz, 0.0, -camera.fx * h[0] * iz * iz],
                  [0.0, camera.fy * iz, -camera.fy * h[1] * iz * iz]])
    return uv, J


def update_inverse_depth(pp: PartialPoint, R_c_w: Array, t_c_w: Array, R_src_w: Array,
                         t_src_w: Array, uv_meas_level0: Array, sigma_px: float,
                         camera: Camera, iterations: int = 3) -> None:
    """Scalar extended information filter update of ``pp.q_hat`` / ``pp.info`` (sec. 5.2).

    Prior ``q ~ N(q0, 1/info0)``; measurement ``uv = pi(R ray + q t) + noise(sigma_px)``. The
    update is the (iterated) Gauss-Newton minimiser of
    ``info0 (q - q0)^2 + |uv - uv(q)|^2 / sigma^2`` linearised at the current estimate, i.e.
    ``info = info0 + H^T H / sigma^2`` and ``q = q0 + info^-1 H^T r / sigma^2`` with
    ``H = d uv/dq`` pointing along the epipolar line, so only the along-line reprojection error
    moves q. A few iterations (iterated EKF) handle the non-linearity of the first update, when
    ``info0 = 0``. Measurements with no baseline (``|H|`` ~ 0) or behind the camera are ignored.
    Updates ``pp.q_hat``, ``pp.info``, ``pp.n_updates`` in place.
    """
    R, t = _relative(R_c_w, t_c_w, R_src_w, t_src_w)
    ray = np.asarray(pp.ray, float)
    z = np.asarray(uv_meas_level0, float).reshape(2)
    a = R @ ray
    inv_var = 1.0 / float(sigma_px) ** 2
    q0, info0 = float(pp.q_hat), max(0.0, float(pp.info))
    q = q0
    HtH = 0.0
    for _ in range(max(1, iterations)):
        h = a + q * t
        if h[2] <= 1e-9:
            logger.debug('partial point %d behind the camera; update skipped', pp.id)
            return
        uv, Jh = _project_h(camera, h)
        H = Jh @ t
        HtH = float(H @ H)
        if HtH * inv_var < 1e-12:
            return      # no baseline: the measurement says nothing about depth
        r = z - uv
        info = info0 + HtH * inv_var
        step = (float(H @ r) * inv_var - info0 * (q - q0)) / info
        q_new = max(Q_MIN, q + step)
        if abs(q_new - q) < 1e-9 * max(1.0, abs(q)):
            q = q_new
            break
        q = q_new
    h = a + q * t
    if h[2] > 1e-9:
        _, Jh = _project_h(camera, h)
        H = Jh @ t
        HtH = float(H @ H)
    pp.q_hat = float(q)
    pp.info = float(info0 + HtH * inv_var)
    pp.n_updates += 1


def partial_point_world(pp: PartialPoint, kf_src: Keyframe) -> Array:
    """The point ``R_src_w^T (ray / q_hat - t_src_w)`` in the map frame (3,)."""
    X_s = np.asarray(pp.ray, float) / max(Q_MIN, float(pp.q_hat))
    return np.asarray(kf_src.R_c_w, float).T @ (X_s - np.asarray(kf_src.t_c_w, float))


def predict_partial_uvs(rays: Array, q_hat: ArrayLike, info: ArrayLike, R_src_w: Array, t_src_w: Array,
                        R_c_w: Array, t_c_w: Array, camera: Camera, n_sigma: float = 2.0,
                        min_radius_px: float = 4.0, max_radius_px: float = 48.0,
                        prior_depth_factor: float = 3.0) -> tuple[Array, Array]:
    """Predicted level-0 pixels (N, 2) of N partial points and their search radii (N,) along
    their epipolar lines; ``R_src_w`` (N, 3, 3) and ``t_src_w`` (N, 3) are the source keyframes.

    The position is the projection with ``q_hat``. The radius covers the epipolar segment
    between the projections of ``q_hat -/+ n_sigma / sqrt(info)`` (clamped to q > 0); with no
    information yet (``info = 0``, sigma = infinity) it covers q from 0 (infinity) to
    ``prior_depth_factor * q_hat``. The radius is at least ``min_radius_px`` (the patch search's
    own radius, sec. 4) and at most ``max_radius_px`` (also when an end of the segment is behind
    the camera). A point predicted behind the camera has NaN pixels.
    """
    R_src_w = np.asarray(R_src_w, float).reshape(-1, 3, 3)
    t_src_w = np.asarray(t_src_w, float).reshape(-1, 3)
    Rrel = np.einsum('ij,nkj->nik', np.asarray(R_c_w, float), R_src_w)  # R_cur R_src^T
    trel = np.asarray(t_c_w, float)[None, :] - np.einsum('nij,nj->ni', Rrel, t_src_w)
    a = np.einsum('nij,nj->ni', Rrel, np.asarray(rays, float).reshape(-1, 3))
    q = np.maximum(np.asarray(q_hat, float).reshape(-1), Q_MIN)
    info = np.asarray(info, float).reshape(-1)

    def project(qq: Array) -> Array:
        h = a + qq[:, None] * trel
        z = np.where(h[:, 2] > 1e-9, h[:, 2], np.nan)
        return np.column_stack([camera.fx * h[:, 0] / z + camera.cx, camera.fy * h[:, 1] / z + camera.cy])

    uv = project(q)
    known = info > 0.0
    s = np.where(known, n_sigma / np.sqrt(np.where(known, info, 1.0)), 0.0)
    q_lo = np.where(known, np.maximum(0.0, q - s), 0.0)
    q_hi = np.where(known, q + s, prior_depth_factor * q)
    r = np.maximum(np.linalg.norm(project(q_lo) - uv, axis=1), np.linalg.norm(project(q_hi) - uv, axis=1))
    return uv, np.clip(np.nan_to_num(r, nan=max_radius_px), min_radius_px, max_radius_px)


def predict_partial_uv(pp: PartialPoint, kf_src: Keyframe, R_c_w: Array, t_c_w: Array,
                       camera: Camera, n_sigma: float = 2.0, min_radius_px: float = 4.0,
                       max_radius_px: float = 48.0, prior_depth_factor: float = 3.0
                       ) -> tuple[Array, float]:
    """:func:`predict_partial_uvs` for one partial point: (uv (2,), radius)."""
    uv, r = predict_partial_uvs(pp.ray, [pp.q_hat], [pp.info], kf_src.R_c_w, kf_src.t_c_w, R_c_w, t_c_w,
                                camera, n_sigma, min_radius_px, max_radius_px, prior_depth_factor)
    return uv[0], float(r[0])


def triangulate_two_view(R0_c_w: Array, t0_c_w: Array, uv0: Array, R1_c_w: Array, t1_c_w: Array,
                         uv1: Array, camera: Camera, min_parallax_deg: float = 1.0,
                         max_error_px: float = 4.0) -> tuple[Array, NDArray[np.bool_]]:
    """Linear (DLT) triangulation of level-0 pixel pairs in two keyframes (sec. 5.2 promotion).

    ``uv0`` / ``uv1`` are (2,) or (N, 2). Returns (xyz (N, 3) in the map frame, good (N,)):
    a point is good if it lies in front of both cameras, the rays meet at an angle of at least
    ``min_parallax_deg`` (else depth is ill-conditioned) and both reprojection errors are at most
    ``max_error_px``. Each point solves the 4x4 homogeneous system in normalised coordinates by
    SVD (H&Z 12.2), batched.
    """
    uv0 = np.atleast_2d(np.asarray(uv0, float))
    uv1 = np.atleast_2d(np.asarray(uv1, float))
    n = len(uv0)
    P0 = np.hstack([np.asarray(R0_c_w, float), np.asarray(t0_c_w, float).reshape(3, 1)])
    P1 = np.hstack([np.asarray(R1_c_w, float), np.asarray(t1_c_w, float).reshape(3, 1)])
    r0 = camera.unproject(uv0)
    r1 = camera.unproject(uv1)
    A = np.empty((n, 4, 4))
    A[:, 0] = r0[:, [0]] * P0[2] - P0[0]
    A[:, 1] = r0[:, [1]] * P0[2] - P0[1]
    A[:, 2] = r1[:, [0]] * P1[2] - P1[0]
    A[:, 3] = r1[:, [1]] * P1[2] - P1[1]
    _, _, Vt = np.linalg.svd(A)
    Xh = Vt[:, -1, :]
    w = Xh[:, 3]
    finite = np.abs(w) > 1e-12
    xyz = Xh[:, :3] / np.where(finite, w, 1.0)[:, None]
    Xc0 = xyz @ P0[:, :3].T + P0[:, 3]
    Xc1 = xyz @ P1[:, :3].T + P1[:, 3]
    front = finite & (Xc0[:, 2] > 1e-6) & (Xc1[:, 2] > 1e-6)
    # Parallax: angle between the two viewing rays in the world frame.
    c0 = -P0[:, :3].T @ P0[:, 3]
    c1 = -P1[:, :3].T @ P1[:, 3]
    d0 = xyz - c0
    d1 = xyz - c1
    cosang = np.einsum('ij,ij->i', d0, d1) / np.maximum(
        np.linalg.norm(d0, axis=1) * np.linalg.norm(d1, axis=1), 1e-12)
    parallax = np.degrees(np.arccos(np.clip(cosang, -1.0, 1.0)))
    e0 = np.linalg.norm(camera.project(Xc0)[0] - uv0, axis=1)
    e1 = np.linalg.norm(camera.project(Xc1)[0] - uv1, axis=1)
    good = front & (parallax >= min_parallax_deg) & (e0 <= max_error_px) & (e1 <= max_error_px)
    return xyz, good


def mean_inverse_depth(R_c_w: Array, t_c_w: Array, xyz_w: Array, default: float = 1.0) -> float:
    """The scene's mean inverse depth seen from a camera (sec. 5.2 initial ``q_hat``)."""
    xyz_w = np.asarray(xyz_w, float).reshape(-1, 3)
    if len(xyz_w) == 0:
        return float(default)
    z = xyz_w @ np.asarray(R_c_w, float)[2] + float(np.asarray(t_c_w, float)[2])
    z = z[z > 1e-6]
    if len(z) == 0:
        return float(default)
    return float(np.mean(1.0 / z))


__all__ = ['update_inverse_depth', 'partial_point_world', 'predict_partial_uv', 'predict_partial_uvs',
           'triangulate_two_view', 'mean_inverse_depth', 'Q_MIN']
