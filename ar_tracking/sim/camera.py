"""The simulated cameras.

:class:`PinholeCamera` and :class:`FrameRenderer` (rotation_sweep): 8-bit RGB frames cut from a
street panorama (pinhole, auto-exposure gain, white balance, glare and lens-flare ghosts, motion
blur, sensor noise, clipping). :class:`DeskCamera` (handheld_desk): the phone camera of Klein &
Murray 2009, a narrow field of view, a low frame rate and a rolling shutter (row ``v`` is
captured ``(v - (H-1)/2) / H * readout_s`` after the header stamp, as ar_tracking.core.slam).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from .model import GAMMA, PANO_HEIGHT, PANO_WIDTH, Array, Image, Lighting, Panorama
from .textures import smoothstep

@dataclass(frozen=True)
class PinholeCamera:
    """An ideal pinhole camera (no distortion) in the camera_optical frame."""

    width: int = 320
    height: int = 240
    hfov_rad: float = math.radians(60.0)

    @property
    def fx(self) -> float:
        return self.width / 2 / math.tan(self.hfov_rad / 2)

    @property
    def cx(self) -> float:
        return (self.width - 1) / 2

    @property
    def cy(self) -> float:
        return (self.height - 1) / 2

    @property
    def K(self) -> Array:
        return np.array([[self.fx, 0, self.cx], [0, self.fx, self.cy], [0, 0, 1.0]])

    def rays(self) -> Array:
        """Unit rays (height*width, 3) of the pixel centres, in camera_optical."""
        u, v = np.meshgrid(np.arange(self.width), np.arange(self.height))
        r = np.stack([(u - self.cx) / self.fx, (v - self.cy) / self.fx, np.ones(u.shape)], -1)
        return (r / np.linalg.norm(r, axis=-1, keepdims=True)).reshape(-1, 3)


def _pano_uv(dx: Image, dy: Image, dz: Image, unit: bool = True) -> tuple[Image, Image]:
    """Equirectangular map coordinates (u, v) of ENU directions (unit, or of any length with
    ``unit`` false), float32."""
    az = np.arctan2(dx, dy)
    az += np.float32(2 * math.pi) * (az < 0)
    u = az * np.float32(PANO_WIDTH / (2 * math.pi)) - np.float32(0.5)
    el = np.arcsin(np.clip(dz if unit else dz / np.sqrt(dx * dx + dy * dy + dz * dz), -1.0, 1.0))
    v = (np.float32(math.pi / 2) - el) * np.float32(PANO_HEIGHT / math.pi) - np.float32(0.5)
    return u, v


class FrameRenderer:
    """Camera frames from a panorama: exposure, white balance, glare, blur, noise, clipping.

    Per frame this costs a few milliseconds at 320 x 240: one ``cv2.remap`` per orientation
    sample, and sensor noise cut from a bank of pre-drawn noise (random offset per frame).
    """

    NOISE_BANK = 8
    NOISE_MARGIN = 32

    def __init__(self, pano: Panorama, light: Lighting, camera: PinholeCamera,
                 rng: np.random.Generator, noise_dn: float = 2.0) -> None:
        self.pano = pano
        self.camera = camera
        self.sun_dir = light.sun_dir
        self._rng = rng
        rays = camera.rays().astype(np.float32)
        self._rays = rays
        self._rx, self._ry, self._rz = (np.ascontiguousarray(rays[:, i]) for i in range(3))
        self._sun_visible = pano.sun_visible and light.sun_el_rad > 0
        m = self.NOISE_MARGIN
        self._noise = (rng.standard_normal(
            (self.NOISE_BANK, camera.height + m, camera.width + m, 3), dtype=np.float32)
            * np.float32(noise_dn))
        yy, xx = np.mgrid[0:camera.height, 0:camera.width]
        self._xx, self._yy = xx.astype(np.float32), yy.astype(np.float32)

    def _sample(self, R_enu_cam: Array, offset_enu: Array | None = None) -> Image:
        """The panorama seen through the camera at one orientation (3, 3), or at one per image
        row (rows, 3, 3: a rolling shutter), gamma-encoded, float. With ``offset_enu`` (m) the
        camera stands that far from the panorama's viewpoint: each ray takes the colour of the
        surface it meets from there (the panorama's depth, two fixed-point steps; sky stays
        where it is) - the parallax a phone held in front of the body's turning axis sees."""
        R = np.asarray(R_enu_cam, dtype=np.float32)
        if R.ndim == 3:  # per row: each coefficient repeated over the row's pixels
            R = np.repeat(R, self.camera.width, axis=0).transpose(1, 2, 0)
        dx = self._rx * R[0, 0] + self._ry * R[0, 1] + self._rz * R[0, 2]
        dy = self._rx * R[1, 0] + self._ry * R[1, 1] + self._rz * R[1, 2]
        dz = self._rx * R[2, 0] + self._ry * R[2, 1] + self._rz * R[2, 2]
        shape = (self.camera.height, self.camera.width)
        u, v = _pano_uv(dx, dy, dz)
        if offset_enu is not None and np.any(offset_enu):
            ox, oy, oz = (np.float32(c) for c in offset_enu)
            for _ in range(2):  # the surface point along the ray, seen from the viewpoint
                depth = cv2.remap(self.pano.depth_m, u.reshape(shape), v.reshape(shape), cv2.INTER_NEAREST,
                                  borderMode=cv2.BORDER_WRAP).reshape(-1)
                depth = np.where(np.isfinite(depth), depth, np.float32(1e7))
                u, v = _pano_uv(ox + depth * dx, oy + depth * dy, oz + depth * dz, unit=False)
        return cv2.remap(self.pano.encoded, u.reshape(shape), v.reshape(shape), cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_WRAP)

    def _glare(self, R_enu_cam: Array) -> Image | None:
        """Veiling glare and lens-flare ghosts when the visible sun is near the view (encoded)."""
        if not self._sun_visible:
            return None
        s_cam = (R_enu_cam.T @ self.sun_dir).astype(np.float32)
        off_axis = math.acos(max(-1.0, min(1.0, float(s_cam[2]))))
        if off_axis > math.radians(65):
            return None
        strength = math.exp(-off_axis / 0.35)
        cos_px = self._rx * s_cam[0] + self._ry * s_cam[1] + self._rz * s_cam[2]
        ang = np.arccos(np.clip(cos_px, -1, 1)).reshape(self.camera.height, self.camera.width)
        glare = np.float32(0.25 * strength) * np.exp(-ang / np.float32(0.25)) \
            + np.float32(0.05 * strength)
        out = glare[..., None] * np.array([1.0, 0.95, 0.85], np.float32)
        if s_cam[2] > 0.2:  # ghosts along the line from the sun's image through the centre
            ps = self.camera.K @ (s_cam / s_cam[2])
            c = np.array([self.camera.cx, self.camera.cy])
            tints = ([0.4, 0.9, 0.5], [0.9, 0.5, 0.9], [0.5, 0.7, 1.0])
            for k, (f, rad) in enumerate(((0.5, 14.0), (1.2, 24.0), (1.8, 9.0))):
                g = c + f * (c - ps[:2])
                r = np.hypot(self._xx - np.float32(g[0]), self._yy - np.float32(g[1]))
                blob = np.float32(0.12 * strength) * smoothstep(rad, rad * 0.7, r)
                out += blob[..., None] * np.array(tints[k], np.float32)
        return out

    def render(self, R_enu_cam_samples: Array, gain: float, wb_rgb: Array,
               offset_enu: Array | None = None) -> NDArray[np.uint8]:
        """An RGB8 frame; ``R_enu_cam_samples`` (n, 3, 3) spans the exposure (motion blur), or
        (n, rows, 3, 3) with one orientation per image row (a rolling shutter); ``offset_enu``:
        the camera's place relative to the panorama's viewpoint, m (parallax; None: none).

        ``gain`` multiplies linear radiance (so encoded values by ``gain ** (1/GAMMA)``).
        """
        acc = self._sample(R_enu_cam_samples[0], offset_enu)
        for R in R_enu_cam_samples[1:]:
            acc += self._sample(R, offset_enu)
        if len(R_enu_cam_samples) > 1:
            acc *= np.float32(1.0 / len(R_enu_cam_samples))
        middle = np.asarray(R_enu_cam_samples[len(R_enu_cam_samples) // 2])
        glare = self._glare(middle if middle.ndim == 2 else middle[len(middle) // 2])
        if glare is not None:
            acc += glare
        scale = (gain ** (1.0 / GAMMA)) * 255.0 * np.asarray(wb_rgb, np.float64)
        acc *= scale.astype(np.float32)
        k = int(self._rng.integers(self.NOISE_BANK))
        oy, ox = (int(v) for v in self._rng.integers(0, self.NOISE_MARGIN, 2))
        h, w = self.camera.height, self.camera.width
        acc += self._noise[k, oy:oy + h, ox:ox + w]
        acc += np.float32(0.5)
        np.clip(acc, 0, 255, out=acc)
        return acc.astype(np.uint8)


# --------------------------------------------------------------------------------------------
# Desk scene (handheld_desk): the phone camera


DESK_RATE_HZ = 20.0
DESK_READOUT_S = 0.030
DESK_EXPOSURE_S = 0.012
DESK_HFOV_DEG = 50.0
DESK_IMAGE_SIZE = (640, 480)


@dataclass(frozen=True)
class DeskCamera:
    """The phone camera: pinhole intrinsics (pixels, OpenCV pixel centres), rate and shutter."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    rate_hz: float = DESK_RATE_HZ
    readout_s: float = DESK_READOUT_S
    exposure_s: float = DESK_EXPOSURE_S

    @property
    def K(self) -> Array:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def row_time_offset_s(self, v: Array) -> Array:
        """Capture time of row(s) ``v`` relative to the header stamp (centre row), as the SLAM."""
        return (np.asarray(v, dtype=float) - (self.height - 1) / 2.0) / self.height * self.readout_s

    def slam_camera(self) -> Any:
        """The same camera as ar_tracking.core.slam.camera.Camera (for core-only checks)."""
        from ..core.slam.camera import Camera

        return Camera(self.fx, self.fy, self.cx, self.cy, self.width, self.height, self.readout_s)


def desk_camera(width: int = DESK_IMAGE_SIZE[0], height: int = DESK_IMAGE_SIZE[1], *,
                readout_s: float = DESK_READOUT_S, exposure_s: float = DESK_EXPOSURE_S,
                rate_hz: float = DESK_RATE_HZ) -> DeskCamera:
    """The scenario's camera at a given image size (the field of view stays 50 deg wide)."""
    if width < 8 or height < 8:
        raise ValueError(f'image size {width}x{height} is too small')
    if readout_s < 0 or exposure_s < 0 or rate_hz <= 0:
        raise ValueError('readout_s and exposure_s must be >= 0, rate_hz > 0')
    f = width / 2.0 / math.tan(math.radians(DESK_HFOV_DEG) / 2.0)
    return DeskCamera(int(width), int(height), f, f, (width - 1) / 2.0, (height - 1) / 2.0,
                      float(rate_hz), float(readout_s), float(exposure_s))


@dataclass(frozen=True)
class DeskFrame:
    """One camera frame: stamp (ns from the start), the mono8 image, and the true camera pose
    (camera_optical in world) at the stamp, i.e. at the capture time of the centre row."""

    stamp_ns: int
    image: NDArray[np.uint8]
    R_w_c: Array
    p_w_c: Array
    index: int = 0
    subframes: int = 1
