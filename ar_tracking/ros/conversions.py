"""Message <-> numpy conversions (rclpy message objects).

Quaternions on the wire are (x, y, z, w); arrays here say their order in their names.
Images are converted through bytes (``tobytes`` / ``np.frombuffer``), handling ``step``,
encodings and byte order as cv_bridge does, because filling ``Image.data`` element-wise is
three orders of magnitude slower. Every function that reads a message raises
:class:`ConversionError` (one line, fit for a throttled log) when the message is unusable.
"""
from __future__ import annotations

import importlib
import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..core.rotations import matrix_to_quat_xyzw, quat_xyzw_to_matrix
from ..errors import ArTrackingError


class ConversionError(ArTrackingError, ValueError):
    """A message cannot be converted: the reason in one line."""


# --- time ---------------------------------------------------------------------------------

def stamp_ns(header_or_stamp: Any) -> int:
    """Integer nanoseconds of a Header or builtin_interfaces/Time."""
    stamp = getattr(header_or_stamp, 'stamp', header_or_stamp)
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def to_stamp(ns: int, stamp: Any | None = None) -> Any:
    """A builtin_interfaces/Time for integer nanoseconds (fills ``stamp`` if given)."""
    if stamp is None:
        from builtin_interfaces.msg import Time

        stamp = Time()
    ns = int(ns)
    stamp.sec = ns // 1_000_000_000
    stamp.nanosec = ns % 1_000_000_000
    return stamp


# --- vectors, quaternions, covariances -----------------------------------------------------

def vector3(v: Any) -> NDArray[np.float64]:
    """geometry_msgs/Vector3 (or Point) as a float array; not checked for finiteness."""
    return np.array([v.x, v.y, v.z], dtype=float)


def finite_vector3(v: Any, what: str) -> NDArray[np.float64]:
    """A finite, non-zero 3-vector from a message field, else ConversionError.

    Checked on the three floats before the array is made (math, not numpy: this runs for every
    IMU and field sample, 100-400 Hz per sensor, and numpy's per-call overhead was most of it)."""
    x, y, z = float(v.x), float(v.y), float(v.z)
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        raise ConversionError(f'{what} is not finite: {[x, y, z]}')
    if x == 0.0 and y == 0.0 and z == 0.0:
        raise ConversionError(f'{what} is all zero')
    return np.array([x, y, z], dtype=float)


def imu_sample(msg: Any, topic: str = 'imu/data_raw') -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(specific force, angular rate) of a sensor_msgs/Imu, else ConversionError: the
    acceleration must be finite and non-zero, the rate finite."""
    accel = finite_vector3(msg.linear_acceleration, f'{topic} linear_acceleration')
    w = msg.angular_velocity
    wx, wy, wz = float(w.x), float(w.y), float(w.z)
    if not (math.isfinite(wx) and math.isfinite(wy) and math.isfinite(wz)):
        raise ConversionError(f'{topic} angular_velocity is not finite')
    return accel, np.array([wx, wy, wz], dtype=float)


def set_vector3(target: Any, values: NDArray[np.float64]) -> Any:
    target.x, target.y, target.z = (float(values[0]), float(values[1]), float(values[2]))
    return target


def quat_xyzw(q: Any) -> NDArray[np.float64]:
    return np.array([q.x, q.y, q.z, q.w], dtype=float)


def rotation_from_quaternion(q: Any, what: str = 'quaternion', tol: float = 1e-3) -> NDArray[np.float64]:
    """Rotation matrix of a geometry_msgs/Quaternion; rejects NaN and non-unit quaternions."""
    arr = quat_xyzw(q)
    if not np.all(np.isfinite(arr)):
        raise ConversionError(f'{what} is not finite')
    norm = np.linalg.norm(arr)
    if abs(norm - 1.0) > tol:
        raise ConversionError(f'{what} is not a unit quaternion (norm {norm:.4g})')
    return quat_xyzw_to_matrix(arr / norm)


def set_quaternion(target: Any, R: NDArray[np.float64]) -> Any:
    """Fill a geometry_msgs/Quaternion from a rotation matrix (canonical sign w >= 0)."""
    q = matrix_to_quat_xyzw(R)
    target.x, target.y, target.z, target.w = (float(q[0]), float(q[1]), float(q[2]), float(q[3]))
    return target


def covariance_is_known(cov: Any) -> bool:
    """REP-145: element 0 of -1 means "not provided"."""
    return len(cov) > 0 and float(cov[0]) != -1.0


def set_covariance(target: Any, cov: NDArray[np.float64] | None) -> None:
    """Write a 3x3 covariance into a float64[9] field, or mark it unknown (-1) when None."""
    flat = np.zeros(9) if cov is None else np.asarray(cov, dtype=float).reshape(9)
    if cov is None:
        flat[0] = -1.0
    for i in range(9):
        target[i] = float(flat[i])


# --- images --------------------------------------------------------------------------------

#: encoding -> (numpy dtype, channels)
IMAGE_ENCODINGS: dict[str, tuple[np.dtype, int]] = {
    'mono8': (np.dtype(np.uint8), 1),
    '8UC1': (np.dtype(np.uint8), 1),
    'mono16': (np.dtype(np.uint16), 1),
    '16UC1': (np.dtype(np.uint16), 1),
    'rgb8': (np.dtype(np.uint8), 3),
    'bgr8': (np.dtype(np.uint8), 3),
    '8UC3': (np.dtype(np.uint8), 3),
    'rgba8': (np.dtype(np.uint8), 4),
    'bgra8': (np.dtype(np.uint8), 4),
    'rgb16': (np.dtype(np.uint16), 3),
    'bgr16': (np.dtype(np.uint16), 3),
    '16UC3': (np.dtype(np.uint16), 3),
    '32FC1': (np.dtype(np.float32), 1),
}


def image_to_array(msg: Any) -> NDArray[Any]:
    """sensor_msgs/Image -> array (H, W) or (H, W, C) in the message's own channel order.

    Honours ``step`` (row padding) and ``is_bigendian``; rejects unknown encodings and
    buffers that do not match width, height and step.
    """
    enc = msg.encoding
    if enc not in IMAGE_ENCODINGS:
        raise ConversionError(f'unsupported image encoding {enc!r}')
    dtype, channels = IMAGE_ENCODINGS[enc]
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    row_bytes = width * channels * dtype.itemsize
    if height <= 0 or width <= 0:
        raise ConversionError(f'image has no pixels ({width}x{height})')
    if step < row_bytes:
        raise ConversionError(f'image step {step} is smaller than a row ({row_bytes} bytes)')
    data = msg.data
    # a memoryview (an Image view of the received bytes, ros.cdr_views) is read in place
    buf = data if isinstance(data, memoryview) else data.tobytes() if hasattr(data, 'tobytes') else bytes(data)
    if len(buf) < step * height:
        raise ConversionError(
            f'image data has {len(buf)} bytes, expected step*height = {step * height}'
        )
    rows = np.frombuffer(buf, dtype=np.uint8, count=step * height).reshape(height, step)
    pixels = rows[:, :row_bytes]
    wire_dtype = dtype.newbyteorder('>' if msg.is_bigendian else '<') if dtype.itemsize > 1 else dtype
    arr = np.ascontiguousarray(pixels).view(wire_dtype).reshape(height, width, channels)
    if wire_dtype != dtype:  # big-endian data on a little-endian machine: swap to native
        arr = arr.astype(dtype)
    return arr[:, :, 0] if channels == 1 else arr


def array_to_image(arr: NDArray[Any], encoding: str, msg: Any | None = None) -> Any:
    """numpy array -> sensor_msgs/Image (little-endian, no padding)."""
    if msg is None:
        from sensor_msgs.msg import Image

        msg = Image()
    if encoding not in IMAGE_ENCODINGS:
        raise ConversionError(f'unsupported image encoding {encoding!r}')
    dtype, channels = IMAGE_ENCODINGS[encoding]
    arr = np.ascontiguousarray(arr, dtype=dtype)
    if (arr.ndim == 2 and channels != 1) or (arr.ndim == 3 and arr.shape[2] != channels):
        raise ConversionError(f'array of shape {arr.shape} does not fit encoding {encoding}')
    msg.height, msg.width = int(arr.shape[0]), int(arr.shape[1])
    msg.encoding = encoding
    msg.is_bigendian = 0
    msg.step = int(arr.shape[1] * channels * dtype.itemsize)
    msg.data = arr.tobytes()
    return msg


def image_to_gray_u8(msg: Any) -> NDArray[np.uint8]:
    """Any supported Image as an 8-bit grey image (what the trackers work on)."""
    import cv2

    arr = image_to_array(msg)
    enc = msg.encoding
    if arr.dtype == np.uint16:
        arr = (arr >> 8).astype(np.uint8)
    elif arr.dtype == np.float32:
        arr = np.clip(arr * 255.0, 0, 255).astype(np.uint8)
    if arr.ndim == 2:
        return arr
    code = {
        3: cv2.COLOR_RGB2GRAY if enc.startswith('rgb') else cv2.COLOR_BGR2GRAY,
        4: cv2.COLOR_RGBA2GRAY if enc.startswith('rgb') else cv2.COLOR_BGRA2GRAY,
    }[arr.shape[2]]
    return cv2.cvtColor(arr, code)


def compressed_to_array(msg: Any) -> NDArray[np.uint8]:
    """sensor_msgs/CompressedImage (jpeg/png) -> BGR or grey array."""
    import cv2

    data = msg.data  # a memoryview (a CompressedImage view of the received bytes) is read in place
    buf = np.frombuffer(data if isinstance(data, memoryview) else bytes(data), dtype=np.uint8)
    if buf.size == 0:
        raise ConversionError('compressed image is empty')
    img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ConversionError(f'compressed image ({msg.format!r}) does not decode')
    return img


def compressed_to_gray_u8(msg: Any) -> NDArray[np.uint8]:
    """sensor_msgs/CompressedImage (jpeg/png, grey, BGR or BGRA, 8 or 16 bit) -> 8-bit grey."""
    import cv2

    arr = compressed_to_array(msg)
    if arr.ndim == 3:
        arr = cv2.cvtColor(arr, cv2.COLOR_BGRA2GRAY if arr.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    if arr.dtype != np.uint8:
        arr = (arr >> 8).astype(np.uint8)
    return arr


# --- message classes -----------------------------------------------------------------------

def message_class(msgtype: str) -> Any:
    """The rclpy message class for 'pkg/msg/Name' (also accepts 'pkg/Name')."""
    parts = msgtype.split('/')
    if len(parts) == 2:
        parts = [parts[0], 'msg', parts[1]]
    if len(parts) != 3:
        raise ConversionError(f'not a message type name: {msgtype!r}')
    try:
        module = importlib.import_module(f'{parts[0]}.{parts[1]}')
        return getattr(module, parts[2])
    except (ImportError, AttributeError) as exc:
        raise ConversionError(f'message type {msgtype} is not installed') from exc
