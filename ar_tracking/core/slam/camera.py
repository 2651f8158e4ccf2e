"""The pinhole camera of the SLAM system: projection, pyramid-level coordinates, row times.

Pyramid level L halves the image L times (level 0 = full resolution, PTAM uses five levels,
Klein & Murray 2009 sec. 3.1). Pixel centres follow OpenCV: a level-0 coordinate ``u0`` is
``(u_L + 0.5) * 2**L - 0.5`` at level L.

Rolling shutter (sec. 6): a frame's header stamp is the capture time of the image centre row;
row ``v`` (level-0 pixels) is captured ``(v - (height - 1) / 2) / height * readout_s`` later
(top rows earlier). ``readout_s = 0`` is a global shutter.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..rectification import Rectification

Array = NDArray[np.float64]

PYRAMID_LEVELS = 5


@dataclass(frozen=True)
class Camera:
    """Intrinsics at level 0 (pixels), image size, and the rolling-shutter readout time."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    readout_s: float = 0.0

    @property
    def K(self) -> Array:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def at_level(self, level: int) -> 'Camera':
        """The same camera for the level-``level`` image of the pyramid."""
        s = 0.5 ** level
        return Camera(self.fx * s, self.fy * s, (self.cx + 0.5) * s - 0.5, (self.cy + 0.5) * s - 0.5,
                      max(1, self.width >> level), max(1, self.height >> level), self.readout_s)

    def project(self, X_c: Array) -> tuple[Array, NDArray[np.bool_]]:
        """Pixels (N, 2) of camera-frame points (N, 3) and a mask of points in front (z > 1e-6)."""
        X_c = np.atleast_2d(np.asarray(X_c, dtype=float))
        z = X_c[:, 2]
        front = z > 1e-6
        zs = np.where(front, z, 1.0)
        uv = np.column_stack([self.fx * X_c[:, 0] / zs + self.cx, self.fy * X_c[:, 1] / zs + self.cy])
        return uv, front

    def unproject(self, uv: Array) -> Array:
        """Rays (N, 3) on the z = 1 plane through pixels (N, 2)."""
        uv = np.atleast_2d(np.asarray(uv, dtype=float))
        return np.column_stack([(uv[:, 0] - self.cx) / self.fx, (uv[:, 1] - self.cy) / self.fy,
                                np.ones(len(uv))])

    def in_image(self, uv: Array, border: float = 0.0) -> NDArray[np.bool_]:
        uv = np.atleast_2d(uv)
        return ((uv[:, 0] >= border) & (uv[:, 1] >= border)
                & (uv[:, 0] <= self.width - 1 - border) & (uv[:, 1] <= self.height - 1 - border))

    def row_time_offset_s(self, v: Array) -> Array:
        """Capture time of level-0 row(s) ``v`` relative to the header stamp (the centre row)."""
        return (np.asarray(v, dtype=float) - (self.height - 1) / 2.0) / self.height * self.readout_s


@dataclass(frozen=True)
class Rectifier:
    """Undoes a calibrated lens distortion so that :class:`Camera` (a pinhole) holds.

    Built once from K and the OpenCV distortion coefficients of camera_info; ``camera`` is the
    pinhole of the rectified images (alpha 0: no undefined border). Without distortion the
    images pass through unchanged.
    """

    camera: Camera
    rectification: Rectification  # the remap (core/rectification.py); camera.K is its K

    @staticmethod
    def from_calibration(K: Array, D: Array, width: int, height: int, readout_s: float = 0.0,
                         model: str = '') -> 'Rectifier':
        rect = Rectification.from_calibration(K, D, width, height, model)  # see core/rectification.py
        Kn = rect.K
        camera = Camera(float(Kn[0, 0]), float(Kn[1, 1]), float(Kn[0, 2]), float(Kn[1, 2]), width, height, readout_s)
        return Rectifier(camera, rect)

    def __call__(self, gray: NDArray[np.uint8]) -> NDArray[np.uint8]:
        return self.rectification(gray)


def level_to_level0(uv: Array, level: int) -> Array:
    """Level-``level`` pixel coordinates to level 0."""
    return (np.asarray(uv, dtype=float) + 0.5) * (2 ** level) - 0.5


def level0_to_level(uv: Array, level: int) -> Array:
    """Level-0 pixel coordinates to level ``level``."""
    return (np.asarray(uv, dtype=float) + 0.5) / (2 ** level) - 0.5


def camera_in_world(R_c_w: Array, t_c_w: Array) -> tuple[Array, Array]:
    """(R_w_c, p_w_c): the camera's orientation and position in the map frame."""
    R_w_c = np.asarray(R_c_w).T
    return R_w_c, -R_w_c @ np.asarray(t_c_w)
