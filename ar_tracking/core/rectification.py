"""Undoing a calibrated lens distortion, so that the pinhole model of the trackers holds.

A camera_info carries the lens distortion of the images (``D``; ``distortion_model``
``plumb_bob`` / ``rational_polynomial``, OpenCV's radial-tangential coefficients, or
``equidistant``, OpenCV's fisheye model). The panorama tracker and the SLAM tracker both
assume a pinhole camera: a frame whose corners are pulled in by 10 % turns every bearing
near the edge by degrees, and a panorama painted from such frames disagrees with itself.
:class:`Rectification` remaps each frame once to a pinhole image (alpha 0 of
``getOptimalNewCameraMatrix``: every output pixel has image content) and gives that image's K.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from ..errors import ArTrackingError

Array = NDArray[np.float64]

#: Lengths of the OpenCV radial-tangential (plumb_bob, rational_polynomial, thin prism, tilted)
#: coefficient vectors; ``equidistant`` takes 4.
OPENCV_LENGTHS = (0, 4, 5, 8, 12, 14)
EQUIDISTANT = 'equidistant'


class RectificationError(ArTrackingError, ValueError):
    """Distortion coefficients this module cannot use (a length or model it does not know)."""


def check_distortion(D: Any, model: str = '') -> Array:
    """The coefficients as a float array, or RectificationError for non-finite values, a length
    OpenCV does not take, or an equidistant model without 4 coefficients."""
    d = np.asarray(D, dtype=float).reshape(-1)
    if not np.all(np.isfinite(d)):
        raise RectificationError('distortion coefficients are not finite')
    if model == EQUIDISTANT:
        if d.size not in (0, 4):
            raise RectificationError(f'equidistant distortion needs 4 coefficients, got {d.size}')
    elif d.size not in OPENCV_LENGTHS:
        raise RectificationError(f'{d.size} distortion coefficients (OpenCV takes {", ".join(map(str, OPENCV_LENGTHS[1:]))})')
    return d


@dataclass(frozen=True)
class Rectification:
    """K of the rectified (pinhole) images and the remap that makes them; without distortion
    (all coefficients 0) the images pass through unchanged and K is the calibration's."""

    K: Array
    maps: tuple[Any, Any] | None = None

    @staticmethod
    def from_calibration(K: Array, D: Array, width: int, height: int, model: str = '') -> 'Rectification':
        """Built once per calibration (``initUndistortRectifyMap``: a few ms at 640 x 480)."""
        K = np.asarray(K, dtype=float)
        D = check_distortion(D, model)
        if not np.any(D != 0):
            return Rectification(K)
        size = (int(width), int(height))
        if model == EQUIDISTANT:
            Kn = np.asarray(cv2.fisheye.estimateNewCameraMatrixForUndistortRectify(K, D, size, np.eye(3), balance=0.0),
                            dtype=float)
            maps = cv2.fisheye.initUndistortRectifyMap(K, D, np.eye(3), Kn, size, cv2.CV_16SC2)
        else:
            # float64 K in, float64 out (np.asarray only narrows OpenCV's MatLike, no copy).
            Kn = np.asarray(cv2.getOptimalNewCameraMatrix(K, D, size, 0.0)[0], dtype=float)
            maps = cv2.initUndistortRectifyMap(K, D, None, Kn, size, cv2.CV_16SC2)
        return Rectification(Kn, maps)

    @property
    def identity(self) -> bool:
        return self.maps is None

    def __call__(self, image: NDArray[Any]) -> NDArray[Any]:
        """The image (grey or colour) as the pinhole camera ``K`` would have taken it."""
        if self.maps is None:
            return image
        return np.asarray(cv2.remap(image, self.maps[0], self.maps[1], cv2.INTER_LINEAR), dtype=image.dtype)


class RectificationCache:
    """The :class:`Rectification` of the calibration in use, built again only when the
    calibration changes (camera_info arrives with every frame; ``initUndistortRectifyMap`` per
    frame would cost more than the tracking)."""

    def __init__(self) -> None:
        self._key: tuple[bytes, bytes, str, int, int] | None = None
        self._rect: Rectification | None = None

    def get(self, K: Array, D: Array, width: int, height: int, model: str = '') -> tuple[Rectification, bool]:
        """(the rectification, whether it was built by this call). Raises RectificationError
        for coefficients :func:`check_distortion` rejects."""
        K = np.asarray(K, dtype=float)
        D = np.asarray(D, dtype=float)
        key = (K.tobytes(), D.tobytes(), model, int(width), int(height))
        if self._rect is None or key != self._key:
            self._rect, self._key = Rectification.from_calibration(K, D, width, height, model), key
            return self._rect, True
        return self._rect, False


def project_through_lens(K: Array, D: Array, p_cam: Array, model: str = '') -> tuple[Array, Array, NDArray[np.bool_]]:
    """Pixel coordinates (x, y) of camera-frame points (n, 3) in the *distorted* image of the
    lens (K, D), and whether each is in front: where a label belongs on the raw frame of a
    camera whose orientation the trackers estimated on rectified frames (the rectification
    keeps the camera's axes). Points behind the camera get NaN."""
    p = np.asarray(p_cam, dtype=float).reshape(-1, 3)
    D = check_distortion(D, model)
    front = p[:, 2] > 1e-9
    x = np.full(len(p), np.nan)
    y = np.full(len(p), np.nan)
    if front.any():
        pts = p[front].reshape(-1, 1, 3)
        zero = np.zeros(3)
        if model == EQUIDISTANT:
            uv = cv2.fisheye.projectPoints(pts, zero, zero, np.asarray(K, float), D)[0]
        else:
            uv = cv2.projectPoints(pts, zero, zero, np.asarray(K, float), D)[0]
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        x[front], y[front] = uv[:, 0], uv[:, 1]
    return x, y, front
