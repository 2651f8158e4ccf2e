"""Lens models: OpenCV's (from CameraInfo: plumb_bob / rational_polynomial) and the seed's eq. 2.

Caarls et al. 2009, sec. 2.4, eq. 2: p_D = c * p_U with c = 1 / (1 + k1 r_u^2 + k2 r_u^4 +
k3 r_u^6), r_u = |p_U|, where D and U are distorted / undistorted metric sensor-plane
coordinates. Here the sensor plane is the normalised image plane (x/z, y/z), so k1..k3 are in
the units of the normalised plane; the seed's metric coordinates differ by the focal length only
(k_i scale with f^(2i)). The model maps undistorted to distorted in closed form; undistorting a
measured point needs the inverse, found by Newton's method on the radius (r_d = r_u c(r_u)).

Edge points are undistorted *before* the lines are fitted: "to reach our unbiased estimate we
had to correct the location of the edge points for lens distortion prior to fitting the lines".
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from . import MarkerError

Array = NDArray[np.float64]
LENS_KINDS = ('opencv', 'caarls_eq2')


def eq2_distort(p_u: Array, k: Array) -> Array:
    """Eq. 2: distorted normalised points from undistorted ones, p_D = p_U / (1 + k1 r^2 + ...)."""
    p_u = np.asarray(p_u, dtype=float)
    r2 = np.sum(p_u * p_u, axis=-1, keepdims=True)
    return p_u / (1.0 + k[0] * r2 + k[1] * r2 ** 2 + k[2] * r2 ** 3)


def eq2_undistort(p_d: Array, k: Array, iterations: int = 8) -> Array:
    """Inverse of :func:`eq2_distort` (Newton on r_u: r_u / (1 + k1 r_u^2 + ...) = r_d)."""
    p_d = np.asarray(p_d, dtype=float)
    r_d = np.linalg.norm(p_d, axis=-1)
    r = r_d.copy()
    k1, k2, k3 = float(k[0]), float(k[1]), float(k[2])
    for _ in range(iterations):
        r2 = r * r
        den = 1.0 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
        g = r / den - r_d
        dden = 2 * k1 * r + 4 * k2 * r ** 3 + 6 * k3 * r ** 5
        dg = (den - r * dden) / (den * den)
        dg = np.where(np.abs(dg) < 1e-9, 1e-9, dg)
        r = r - g / dg
    scale = np.where(r_d > 1e-15, r / np.maximum(r_d, 1e-15), 1.0)
    return p_d * scale[..., None]


@dataclass(frozen=True)
class LensModel:
    """Pixel <-> normalised undistorted image coordinates.

    ``kind`` 'opencv' uses ``dist`` (OpenCV's coefficient vector, as in CameraInfo.d);
    'caarls_eq2' uses ``eq2_k`` (k1, k2, k3 of eq. 2).
    """

    K: Array
    kind: str = 'opencv'
    dist: Array = field(default_factory=lambda: np.zeros(5))
    eq2_k: Array = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        if self.kind not in LENS_KINDS:
            raise MarkerError(f'unknown lens model {self.kind!r} (use {" or ".join(LENS_KINDS)})')
        K = np.asarray(self.K, dtype=float)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise MarkerError('camera matrix K must be a finite 3x3 matrix with positive focal lengths')

    @property
    def focal_px(self) -> float:
        return float(0.5 * (self.K[0, 0] + self.K[1, 1]))

    def undistort(self, px: Array) -> Array:
        """(N, 2) pixels -> (N, 2) normalised undistorted coordinates."""
        px = np.asarray(px, dtype=np.float64).reshape(-1, 2)
        if self.kind == 'opencv':
            if not np.any(self.dist):
                K = self.K
                return np.stack([(px[:, 0] - K[0, 2]) / K[0, 0], (px[:, 1] - K[1, 2]) / K[1, 1]], -1)
            out = cv2.undistortPoints(px.reshape(-1, 1, 2), self.K, np.asarray(self.dist, float),
                                      criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-10))
            return np.asarray(out, dtype=np.float64).reshape(-1, 2)
        K = self.K
        p_d = np.stack([(px[:, 0] - K[0, 2]) / K[0, 0], (px[:, 1] - K[1, 2]) / K[1, 1]], -1)
        return eq2_undistort(p_d, self.eq2_k)

    def distort(self, norm: Array) -> Array:
        """(N, 2) normalised undistorted coordinates -> (N, 2) pixels."""
        norm = np.asarray(norm, dtype=np.float64).reshape(-1, 2)
        if self.kind == 'opencv':
            if not np.any(self.dist):
                p = norm
            else:
                pts = np.hstack([norm, np.ones((len(norm), 1))])
                uv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), np.eye(3), np.asarray(self.dist, float))
                p = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        else:
            p = eq2_distort(norm, self.eq2_k)
        return np.stack([p[:, 0] * self.K[0, 0] + self.K[0, 2], p[:, 1] * self.K[1, 1] + self.K[1, 2]], -1)
