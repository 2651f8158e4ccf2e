"""Cylindrical map geometry of the panoramic mapper (Langlotz 2011 sec. 3.1, Fig. 1).

The map is a cylinder around the camera centre whose axis is the vertical (y) axis of the
``panorama`` frame (= camera_optical at the first frame: x right, y down, z forward). A
direction ``d = (x, y, z)`` in that frame falls on map column ``u = f_c * atan2(x, z) + W/2``
and row ``v = f_c * y / hypot(x, z) + H/2``, with ``f_c = W / (2 pi)`` pixels per radian,
so 2048 columns cover 360 degrees (0.176 deg/px) and the first frame's optical axis lands at
the centre of the map, far from the wrap at u = 0 = W. Pixel (u, v) has its centre at integer
coordinates. Everything here is vectorised numpy; no state.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..rotations import rot_y

Array = NDArray[np.float64]


@dataclass(frozen=True)
class CylinderGeometry:
    """Size of the map and the projections between directions and map pixels."""

    width: int = 2048
    height: int = 512

    @property
    def f(self) -> float:
        """Map pixels per radian, horizontally and (at the horizon) vertically."""
        return self.width / (2.0 * math.pi)

    def project(self, d: Array) -> tuple[Array, Array]:
        """Map coordinates (u in [0, W), v) of directions ``d`` (..., 3) in the panorama frame."""
        x, y, z = d[..., 0], d[..., 1], d[..., 2]
        rho = np.maximum(np.hypot(x, z), 1e-12)
        u = np.mod(np.arctan2(x, z) * self.f + self.width / 2.0, self.width)
        v = y / rho * self.f + self.height / 2.0
        return u, v

    def column_distance(self, u1: ArrayLike, u2: ArrayLike) -> Array:
        """|u1 - u2| in columns the short way round the cylinder (the map wraps at W)."""
        W = self.width
        return np.abs((np.asarray(u1, dtype=float) - np.asarray(u2, dtype=float) + W / 2) % W - W / 2)

    def map_distance(self, u1: ArrayLike, v1: ArrayLike, u2: ArrayLike, v2: ArrayLike) -> Array:
        """Euclidean map distance (pixels) between (u1, v1) and (u2, v2) across the wrap."""
        return np.hypot(self.column_distance(u1, u2), np.asarray(v1, dtype=float) - np.asarray(v2, dtype=float))

    def unproject(self, u: Array, v: Array) -> Array:
        """Unit directions (..., 3) of map coordinates ``u``, ``v`` (inverse of :meth:`project`)."""
        theta = (np.asarray(u, float) - self.width / 2.0) / self.f
        h = (np.asarray(v, float) - self.height / 2.0) / self.f
        d = np.stack(np.broadcast_arrays(np.sin(theta), h, np.cos(theta)), axis=-1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def column_terms(self, u: Array) -> tuple[Array, Array]:
        """(sin theta, cos theta) of map columns: with :meth:`row_terms` a map pixel's
        (unnormalised) direction is (sin theta, h, cos theta), separable in u and v, which lets
        the mapper project whole blocks of map pixels with broadcast sums."""
        theta = (np.asarray(u, float) - self.width / 2.0) / self.f
        return np.sin(theta), np.cos(theta)

    def row_terms(self, v: Array) -> Array:
        """h = y / rho of map rows (see :meth:`column_terms`)."""
        return (np.asarray(v, float) - self.height / 2.0) / self.f


def rotation_about_axis_y(angle_rad: float) -> Array:
    """Rotation about the panorama's y axis (the cylinder axis): a pure shift of the map by
    ``angle_rad * f`` columns; used by relocalisation, whose map search finds such a shift."""
    return rot_y(angle_rad)


def camera_rays(K: Array, x: ArrayLike, y: ArrayLike, unit: bool = True) -> Array:
    """Bearing vectors (..., 3) in camera_optical of pixel coordinates (x, y), broadcast against
    each other: unit vectors, or with ``unit=False`` the rays (xn, yn, 1) (enough where only the
    direction matters, e.g. :meth:`CylinderGeometry.project`).

    The three components are written into one array of the broadcast shape, without broadcast
    copies and a stack: on the tracker's template grids (``x`` (n, 1, P) and ``y`` (n, P, 1),
    every grid pixel's ray) 150 grids take 33 us instead of 42, the time of the hand-written
    copy the tracker had instead."""
    fx, fy, cx, cy, skew = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
    yn = (np.asarray(y, float) - cy) / fy
    xn = (np.asarray(x, float) - cx - skew * yn) / fx
    r = np.empty(xn.shape + (3,))  # xn has the broadcast shape of x and y (it uses yn)
    r[..., 0] = xn
    r[..., 1] = yn
    r[..., 2] = 1.0
    if unit:
        r /= np.linalg.norm(r, axis=-1, keepdims=True)
    return r


def project_xyz(K: Array, px: Array, py: Array, pz: Array) -> tuple[Array, Array, NDArray[np.bool_]]:
    """Pixel coordinates of camera-frame points given as their three coordinate arrays, and
    whether they are in front (z > 1e-6; points behind get z = 1 so the division stays finite).
    Separate arrays let a caller that computes the coordinates one by one (the mapper's
    separable map-pixel directions) skip the strided columns of an (N, 3) array."""
    front = pz > 1e-6
    zs = np.where(front, pz, 1.0)
    xn, yn = px / zs, py / zs
    return K[0, 0] * xn + K[0, 1] * yn + K[0, 2], K[1, 1] * yn + K[1, 2], front


def image_rows(K: Array, py: Array, pz: Array) -> Array:
    """The row coordinates alone of :func:`project_xyz` (the same values): what a rolling
    shutter's row times need before the points are projected again."""
    return K[1, 1] * (py / np.where(pz > 1e-6, pz, 1.0)) + K[1, 2]


def project_to_image(K: Array, p_cam: Array) -> tuple[Array, Array, NDArray[np.bool_]]:
    """Pixel coordinates of camera-frame points (..., 3) and whether they are in front
    (:func:`project_xyz` of the three columns)."""
    return project_xyz(K, p_cam[..., 0], p_cam[..., 1], p_cam[..., 2])


def row_rotations(row_motion: tuple[Array, float], y: ArrayLike, height: int) -> Array:
    """Rolling shutter: the camera's turn (n, 3, 3) between a frame's stamp and the reading of
    image rows ``y``, ``exp(omega dt)`` with ``dt = readout (y + 0.5) / height`` (``row_motion`` =
    (omega rad/s in camera axes, readout s)); R_pano_cam at row y is R_pano_cam(stamp) times it.

    One axis for every row, so the Rodrigues formula I + sin(a) [k]x + (1 - cos(a)) [k]x^2 with
    the angles a = |omega| dt as a few whole-array products (scipy's Rotation took 100 us a
    call here, three calls per tracked frame)."""
    omega, readout = row_motion
    w = np.asarray(omega, float)
    dt = _row_times(readout, y, height)
    rate = math.sqrt(float(w.dot(w)))
    if rate < 1e-300:
        return np.broadcast_to(np.eye(3), dt.shape + (3, 3)).copy()
    Kx, Kx2 = _axis_terms(w.tobytes())
    angle = rate * dt
    out = np.sin(angle)[:, None, None] * Kx
    out += (1.0 - np.cos(angle))[:, None, None] * Kx2
    out += _EYE
    return out


_EYE = np.eye(3)
_EYE.flags.writeable = False


@lru_cache(maxsize=8)
def _axis_terms(omega_bytes: bytes) -> tuple[Array, Array]:
    """[k]x and [k]x^2 (read-only) of the unit axis k of the rate ``omega`` (its float64
    bytes), as :func:`row_rotations` computed them: kept, since the tracker turns three sets of
    rows by the same rate per frame."""
    w = np.frombuffer(omega_bytes, dtype=np.float64)
    kx, ky, kz = (w / math.sqrt(float(w.dot(w)))).tolist()
    Kx = np.array([[0.0, -kz, ky], [kz, 0.0, -kx], [-ky, kx, 0.0]])
    Kx2 = Kx @ Kx
    Kx.flags.writeable = False
    Kx2.flags.writeable = False
    return Kx, Kx2


def _row_times(readout: float, y: ArrayLike, height: int) -> Array:
    """When rows ``y`` (clipped to the image, NaN as row 0) were read after the stamp, s."""
    # fmax/fmin pass a NaN's other argument: NaN -> 0, -inf -> 0, +inf -> height.
    rows = np.fmin(np.fmax(np.asarray(y, dtype=float), 0.0), float(height))
    return readout * (rows + 0.5) / height


def to_row_cameras(row_motion: tuple[Array, float], y: Array, height: int, px: Array, py: Array, pz: Array
                   ) -> tuple[Array, Array, Array]:
    """Camera coordinates (px, py, pz) at the frame's stamp turned into those of the camera
    that read row ``y`` (the inverse of :func:`row_rotations`, one axis for all points: the
    Rodrigues formula per point, for the map's many pixels)."""
    omega, readout = row_motion
    w = np.asarray(omega, float)
    rate = float(np.linalg.norm(w))
    if rate < 1e-12 or readout <= 0.0:
        return px, py, pz
    kx, ky, kz = (w / rate).tolist()
    theta = -rate * _row_times(readout, y, height)  # turning back
    c, s = np.cos(theta), np.sin(theta)
    dot = (kx * px + ky * py + kz * pz) * (1.0 - c)
    cx, cy, cz = ky * pz - kz * py, kz * px - kx * pz, kx * py - ky * px  # k x p
    return (px * c + cx * s + kx * dot, py * c + cy * s + ky * dot, pz * c + cz * s + kz * dot)
