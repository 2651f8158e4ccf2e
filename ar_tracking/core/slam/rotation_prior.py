"""Full-frame 3-DoF rotation estimation on the small blurry image (Klein & Murray 2009, sec. 4).

The phone's narrow field of view, low frame rate and long exposures blur the image whenever the
camera turns; PTAM then aligns successive *coarsest* pyramid levels (20x15 from 320x240, 40x30 from
640x480) directly, which acts as a gyroscope (ECCV'08, sec. 4 here). The warp of a pure rotation is
the homography ``H = K R K^-1``. We minimise ``sum_x (I(H x) + b - T(x))^2`` over the rotation and
an intensity offset ``b`` with efficient second-order minimisation (ESM, Benhimane & Malis 2007):
the Jacobian uses the mean of the warped-image and template gradients, which gives near-quadratic
convergence at the cost of Gauss-Newton; the rotation is updated by right composition
``R <- R exp(delta)`` so the warp Jacobian is evaluated at the template pixels.

The optional pre-warp ``H0`` lets the tracker express the prior as a rotation *correction* on top of
its constant-velocity prediction (``H = K dR K^-1 H0``, H0 the prediction's homography of the mean
scene plane), so image motion caused by translation is not counted twice.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from ..rotations import so3_exp
from .camera import Camera

log = logging.getLogger(__name__)

Array = NDArray[np.float64]


@dataclass
class RotationEstimate:
    """Result of :func:`estimate_rotation`.

    ``R_cur_prev`` rotates previous-frame camera coordinates into the current frame (the pure
    rotation explaining the image motion, after any pre-warp); ``residual`` is the RMS intensity
    residual over the overlapping pixels (grey levels), ``residual0`` the same at the start;
    ``overlap`` the fraction of template pixels used.
    """

    R_cur_prev: Array
    residual: float
    residual0: float
    iterations: int
    overlap: float
    converged: bool


class _Grid:
    """Per-size cache of the template pixel grid and the rotation warp Jacobian (d pix / d w)."""

    _cache: dict[tuple, '_Grid'] = {}

    def __init__(self, cam: Camera, h: int, w: int) -> None:
        v, u = np.mgrid[0:h, 0:w].astype(np.float64)
        x = (u - cam.cx) / cam.fx
        y = (v - cam.cy) / cam.fy
        # d(pixel)/d(w) of pi(exp(w) r), r = (x, y, 1), at w = 0.
        self.Ju = (cam.fx * np.stack([-x * y, 1 + x * x, -y], -1)).reshape(-1, 3)
        self.Jv = (cam.fy * np.stack([-1 - y * y, x * y, x], -1)).reshape(-1, 3)

    @classmethod
    def get(cls, cam: Camera, h: int, w: int) -> '_Grid':
        key = (cam.fx, cam.fy, cam.cx, cam.cy, h, w)
        g = cls._cache.get(key)
        if g is None:
            if len(cls._cache) > 16:
                cls._cache.clear()
            g = cls._cache[key] = _Grid(cam, h, w)
        return g


def _gradients(img: NDArray[np.float32]) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=1, scale=0.5, borderType=cv2.BORDER_REPLICATE)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=1, scale=0.5, borderType=cv2.BORDER_REPLICATE)
    # CV_32F output: np.asarray only narrows OpenCV's MatLike type (no copy).
    return np.asarray(gx, dtype=np.float32), np.asarray(gy, dtype=np.float32)


def estimate_rotation(template: NDArray[np.float32], image: NDArray[np.float32], camera: Camera,
                      R_init: Array | None = None, H0: Array | None = None, iterations: int = 8,
                      border: int = 1, min_step_rad: float = 1e-4) -> RotationEstimate:
    """ESM alignment of ``image`` (current SBI) to ``template`` (previous SBI) by a rotation.

    ``camera`` must be the camera *at the images' pyramid level* (``Camera.at_level``). The model is
    ``image(K R K^-1 H0 x) + b = template(x)``; ``H0`` (level pixels, default identity) is a fixed
    pre-warp. Returns the rotation R (``R_cur_prev`` when H0 is identity) and the residuals.
    """
    T0 = np.asarray(template, dtype=np.float32)
    img = np.asarray(image, dtype=np.float32)
    h, w = T0.shape
    K = camera.K
    Kinv = np.linalg.inv(K)
    ones = np.ones((h, w), np.float32)
    if H0 is not None:
        # Move the template into the pre-warped frame: T(y) = T0(H0^-1 y).
        T = np.asarray(cv2.warpPerspective(T0, H0, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE),
                       dtype=np.float32)  # float32 in, float32 out: no copy
        tmask = cv2.warpPerspective(ones, H0, (w, h), flags=cv2.INTER_LINEAR, borderValue=0) > 0.999
    else:
        T = T0
        tmask = np.ones((h, w), bool)
    if border > 0:
        tmask[:border, :] = tmask[-border:, :] = False
        tmask[:, :border] = tmask[:, -border:] = False
    grid = _Grid.get(camera, h, w)
    Tgx, Tgy = _gradients(T)
    R = np.eye(3) if R_init is None else np.asarray(R_init, dtype=float).copy()
    b = 0.0
    res0 = np.nan
    rms = np.nan
    it = 0
    converged = False
    overlap = 0.0
    for it in range(1, iterations + 1):
        H = K @ R @ Kinv  # template pixel -> image pixel
        Iw = np.asarray(cv2.warpPerspective(img, H, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                            borderMode=cv2.BORDER_REPLICATE), dtype=np.float32)
        vmask = cv2.warpPerspective(ones, H, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                    borderValue=0) > 0.999
        m = (vmask & tmask).reshape(-1)
        overlap = float(m.mean())
        if m.sum() < 12:
            break
        Igx, Igy = _gradients(Iw)
        r = (Iw.reshape(-1) + b - T.reshape(-1))[m].astype(np.float64)
        rms = float(np.sqrt(np.mean(r * r)))
        if it == 1:
            res0 = rms
        gx = 0.5 * (Igx.reshape(-1) + Tgx.reshape(-1))[m]
        gy = 0.5 * (Igy.reshape(-1) + Tgy.reshape(-1))[m]
        J = np.empty((len(r), 4))
        J[:, :3] = gx[:, None] * grid.Ju[m] + gy[:, None] * grid.Jv[m]
        J[:, 3] = 1.0
        JtJ = J.T @ J + 1e-6 * np.eye(4)
        try:
            # float64 system: np.asarray narrows numpy's floating[Any] solve type (no copy).
            delta = np.asarray(-np.linalg.solve(JtJ, J.T @ r), dtype=np.float64)
        except np.linalg.LinAlgError:
            break
        R = R @ so3_exp(delta[:3])
        b += float(delta[3])
        if np.linalg.norm(delta[:3]) < min_step_rad:
            converged = True
            break
    # Final residual at the returned rotation.
    H = K @ R @ Kinv
    Iw = np.asarray(cv2.warpPerspective(img, H, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                        borderMode=cv2.BORDER_REPLICATE), dtype=np.float32)
    vmask = cv2.warpPerspective(ones, H, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                borderValue=0) > 0.999
    m = vmask & tmask
    if m.sum() >= 12:
        r_final = (Iw + b - T)[m]
        rms = float(np.sqrt(np.mean(r_final.astype(np.float64) ** 2)))
        overlap = float(m.mean())
    if np.isnan(res0):
        res0 = rms
    return RotationEstimate(R, rms, res0, it, overlap, converged)


def rotation_homography(camera: Camera, R_cur_prev: Array, t_cur_prev: Array | None = None,
                        depth: float = 1.0) -> Array:
    """Pixel homography prev -> cur of the fronto-parallel plane at ``depth`` in the previous camera.

    ``H = K (R + t n^T / depth) K^-1`` with ``n = (0, 0, 1)``; with ``t`` None a pure rotation.
    """
    M = np.asarray(R_cur_prev, dtype=float).copy()
    if t_cur_prev is not None:
        M[:, 2] += np.asarray(t_cur_prev, dtype=float).reshape(3) / max(depth, 1e-6)
    return camera.K @ M @ np.linalg.inv(camera.K)
