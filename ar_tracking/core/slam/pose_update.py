"""6-DoF camera pose refinement from 3-D map points and their measured pixels (sec. 4, PTAM).

Gauss-Newton on SE(3) with left-multiplied increments ``T <- exp(xi) T``, ``xi = (v, w)``, and a
Tukey biweight M-estimator (as PTAM): residuals are normalised by each measurement's standard
deviation ``2**level`` level-0 pixels, the robust scale is re-estimated from their median each
iteration (with a floor of one sigma), points beyond Tukey's cut-off get weight 0 (outliers).

Rolling shutter (sec. 6): with ``velocity`` (the constant-velocity model's twist, per second, in
the camera frame at the header stamp) and ``camera.readout_s`` > 0, each point is predicted with
the pose at its own row time ``dt = camera.row_time_offset_s(v)``, ``T(dt) = exp(dt * velocity) T``,
to first order; the estimated pose is the one at the header stamp.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .camera import Camera
from ..rotations import skew, so3_exp, so3_log

log = logging.getLogger(__name__)

Array = NDArray[np.float64]

TUKEY_C = 4.685


@dataclass
class PoseResult:
    """Refined pose, Tukey inlier mask, robust objective (sum of Tukey rho, sigma units) etc."""

    R_c_w: Array
    t_c_w: Array
    inliers: NDArray[np.bool_]
    objective: float
    robust_scale: float
    iterations: int
    #: (6, 6) information matrix J^T W J at the solution (xi = (v, w)), for quality checks.
    information: Array


def se3_exp(xi: Array) -> tuple[Array, Array]:
    """(R, t) of the twist ``xi = (v, w)`` (SE(3) exponential)."""
    xi = np.asarray(xi, float).reshape(6)
    v, w = xi[:3], xi[3:]
    th = float(np.linalg.norm(w))
    R = so3_exp(w)
    Wx = skew(w)
    if th < 1e-8:
        V = np.eye(3) + 0.5 * Wx
    else:
        V = np.eye(3) + (1 - np.cos(th)) / th ** 2 * Wx + (th - np.sin(th)) / th ** 3 * (Wx @ Wx)
    return R, V @ v


def se3_log(R: Array, t: Array) -> Array:
    """Twist ``(v, w)`` of (R, t) (inverse of :func:`se3_exp`)."""
    w = so3_log(np.asarray(R, float))
    th = float(np.linalg.norm(w))
    Wx = skew(w)
    if th < 1e-8:
        Vinv = np.eye(3) - 0.5 * Wx
    else:
        Vinv = (np.eye(3) - 0.5 * Wx
                + (1 / th ** 2) * (1 - (th * np.sin(th)) / (2 * (1 - np.cos(th)))) * (Wx @ Wx))
    return np.concatenate([Vinv @ np.asarray(t, float).reshape(3), w])


def tukey_weight(r: Array, c: float) -> Array:
    """Tukey biweight weights of normalised residual magnitudes ``r`` with cut-off ``c``."""
    u = np.asarray(r) / c
    return np.where(np.abs(u) < 1.0, (1 - u * u) ** 2, 0.0)


def tukey_rho(r: Array, c: float) -> Array:
    u2 = np.minimum((np.asarray(r) / c) ** 2, 1.0)
    return c * c / 6.0 * (1 - (1 - u2) ** 3)


def project_with_jacobian(X_w: Array, camera: Camera, R_c_w: Array, t_c_w: Array,
                          velocity: Array | None = None, dt: Array | None = None
                          ) -> tuple[Array, Array, NDArray[np.bool_]]:
    """Pixels (N, 2), d pixel / d xi (N, 2, 6) for ``T <- exp(xi) T``, and an in-front mask.

    With ``velocity`` (6,) and per-point ``dt`` (N,), each point uses the first-order row pose
    ``x_c(dt) = x_c + dt * (v + w x x_c)``.
    """
    Xc = X_w @ R_c_w.T + t_c_w
    if velocity is not None and dt is not None:
        v, w = velocity[:3], velocity[3:]
        Xc = Xc + dt[:, None] * (v[None, :] + np.cross(w[None, :], Xc))
    z = Xc[:, 2]
    front = z > 1e-6
    zs = np.where(front, z, 1.0)
    iz = 1.0 / zs
    x, y = Xc[:, 0] * iz, Xc[:, 1] * iz
    uv = np.column_stack([camera.fx * x + camera.cx, camera.fy * y + camera.cy])
    n = len(X_w)
    J = np.zeros((n, 2, 6))
    # d uv / d Xc
    J[:, 0, 0] = camera.fx * iz
    J[:, 0, 2] = -camera.fx * x * iz
    J[:, 1, 1] = camera.fy * iz
    J[:, 1, 2] = -camera.fy * y * iz
    # d Xc / d w = -[Xc]x  -> du/dw = du/dXc @ (-[Xc]x)
    X, Y, Z = Xc[:, 0], Xc[:, 1], Xc[:, 2]
    J[:, 0, 3] = camera.fx * (-x * y)
    J[:, 0, 4] = camera.fx * (1 + x * x)
    J[:, 0, 5] = camera.fx * (-y)
    J[:, 1, 3] = camera.fy * (-1 - y * y)
    J[:, 1, 4] = camera.fy * (x * y)
    J[:, 1, 5] = camera.fy * x
    del X, Y, Z
    return uv, J, front


def _normalised_residuals(X_w: Array, uv_meas: Array, inv_sig: Array, camera: Camera, R: Array, t: Array,
                          vel: Array | None, dt: Array | None, with_jacobian: bool = True
                          ) -> tuple[Array, Array, Array | None, NDArray[np.bool_]]:
    """Sigma-normalised residuals ``e`` (N, 2) = (projection - measurement) / sigma, their
    Jacobian (2N, 6) (the u rows then the v rows, as :func:`project_with_jacobian`, divided by
    sigma) and the in-front mask: the inner loop of :func:`refine_pose`, without temporaries."""
    Xc = X_w @ R.T + t
    if vel is not None and dt is not None:
        v, w = vel[:3], vel[3:]
        X, Y, Z = Xc[:, 0], Xc[:, 1], Xc[:, 2]
        Xc = Xc + dt[:, None] * np.column_stack([v[0] + w[1] * Z - w[2] * Y, v[1] + w[2] * X - w[0] * Z,
                                                  v[2] + w[0] * Y - w[1] * X])
    z = Xc[:, 2]
    front = z > 1e-6
    iz = 1.0 / np.where(front, z, 1.0)
    x, y = Xc[:, 0] * iz, Xc[:, 1] * iz
    e = np.empty((len(X_w), 2))
    e[:, 0] = (camera.fx * x + camera.cx - uv_meas[:, 0]) * inv_sig
    e[:, 1] = (camera.fy * y + camera.cy - uv_meas[:, 1]) * inv_sig
    if not with_jacobian:
        return e, e, None, front
    n = len(X_w)
    J = np.empty((2 * n, 6))
    fxs, fys = camera.fx * inv_sig, camera.fy * inv_sig
    xy = x * y
    Ju, Jv = J[:n], J[n:]
    Ju[:, 0] = fxs * iz
    Ju[:, 1] = 0.0
    Ju[:, 2] = -fxs * x * iz
    Ju[:, 3] = -fxs * xy
    Ju[:, 4] = fxs * (1 + x * x)
    Ju[:, 5] = -fxs * y
    Jv[:, 0] = 0.0
    Jv[:, 1] = fys * iz
    Jv[:, 2] = -fys * y * iz
    Jv[:, 3] = -fys * (1 + y * y)
    Jv[:, 4] = fys * xy
    Jv[:, 5] = fys * x
    return e, e.T.reshape(-1), J, front


def refine_pose(X_w: Array, uv_meas: Array, levels: NDArray[np.int64] | Array, camera: Camera,
                R_c_w: Array, t_c_w: Array, iterations: int = 8, velocity: Array | None = None,
                min_scale: float = 1.0, max_scale: float = 8.0, damping: float = 1e-6,
                fixed_scale: float | None = None) -> PoseResult:
    """Robust Gauss-Newton pose update (Tukey) from points ``X_w`` measured at ``uv_meas`` (level 0).

    ``levels`` gives each measurement's sigma ``2**level`` pixels. ``velocity`` (6,) = (v, w) per
    second in the camera frame enables the rolling-shutter row-pose prediction (needs
    ``camera.readout_s > 0``). ``fixed_scale`` pins the Tukey scale (comparable objectives, as
    in the initialiser's hypothesis test). Returns the refined pose, inliers (Tukey weight > 0) and the robust
    objective (sum of Tukey rho of sigma-normalised residuals).
    """
    X_w = np.asarray(X_w, float).reshape(-1, 3)
    uv_meas = np.asarray(uv_meas, float).reshape(-1, 2)
    inv_sig = 2.0 ** -np.asarray(levels, float).reshape(-1)
    R = np.asarray(R_c_w, float).copy()
    t = np.asarray(t_c_w, float).reshape(3).copy()
    n = len(X_w)
    if n < 3:
        return PoseResult(R, t, np.zeros(n, bool), float('inf'), float('nan'), 0, np.zeros((6, 6)))
    use_rs = velocity is not None and camera.readout_s > 0
    dt = camera.row_time_offset_s(uv_meas[:, 1]) if use_rs else None
    vel = np.asarray(velocity, float).reshape(6) if use_rs else None
    scale = min_scale if fixed_scale is None else float(fixed_scale)
    it = 0
    H = np.zeros((6, 6))
    eye6 = np.eye(6)
    for it in range(1, iterations + 1):  # noqa: B007 - the count is returned
        e, e_flat, J, front = _normalised_residuals(X_w, uv_meas, inv_sig, camera, R, t, vel, dt)
        en = np.where(front, np.hypot(e[:, 0], e[:, 1]), 1e6)
        scale = (float(fixed_scale) if fixed_scale is not None
                 else float(np.clip(1.4826 * np.median(en), min_scale, max_scale)))
        c = TUKEY_C * scale
        w = tukey_weight(en, c) * front
        if w.sum() < 1e-9:
            break
        w2 = np.concatenate([w, w])
        Jw = J * w2[:, None]
        H = Jw.T @ J
        g = Jw.T @ e_flat
        try:
            xi = -np.linalg.solve(H + damping * eye6 * max(1.0, np.trace(H) / 6), g)
        except np.linalg.LinAlgError:
            break
        dR, dtv = se3_exp(xi)
        R = dR @ R
        t = dR @ t + dtv
        if np.linalg.norm(xi) < 1e-6:  # ~1e-3 level-0 px at the image centre
            break
    e, _, J, front = _normalised_residuals(X_w, uv_meas, inv_sig, camera, R, t, vel, dt)
    en = np.where(front, np.hypot(e[:, 0], e[:, 1]), 1e6)
    c = TUKEY_C * scale
    w = tukey_weight(en, c)
    obj = float(tukey_rho(en, c).sum())
    H = (J * np.concatenate([w, w])[:, None]).T @ J
    # Orthonormalise R against drift.
    U, _, Vt = np.linalg.svd(R)
    R = U @ Vt
    return PoseResult(R, t, w > 0, obj, scale, it, H)
