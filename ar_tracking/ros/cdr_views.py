"""Read-only views of a few message types straight from their CDR bytes, for raw subscriptions;
and the CDR bytes of the message types the nodes publish per sample or frame.

rclpy deserialises a message by building the Python message object field by field through its
checked setters: ~15 us for an Imu, ~9 us for a MagneticField, ~90 us for a 320x240 RGB Image
(its pixels copied into an ``array.array``). The nodes only read these messages, so on the
streams they get thousands of times per bag they subscribe with ``raw=True`` and read the
fields they use from the bytes here (~2-4 us; an Image's pixels stay in the received buffer).

A view has the attribute names of the message (``msg.header.stamp.sec``,
``msg.linear_acceleration.x``, ``msg.orientation_covariance`` as a float64 array of 9, ...), so
the node code reads a view and a real message alike, and the values are the same numbers
(IEEE doubles copied bit for bit, strings decoded as UTF-8). Only little-endian CDR (what every
ROS 2 middleware on x86/ARM writes) is read here; other bytes are deserialised by rclpy, as
are types without a view.

The other way round, :func:`imu_cdr` and :func:`transform_stamped_cdr` give the bytes of an
Imu or TransformStamped from its field values, which a publisher sends as they are (rclpy
publishes raw CDR bytes unchanged): the bytes rclpy's middleware makes of the message object
(padding zero), without building that object through its checked setters (~15-25 us a message
with the node's conversions, ~2 us here). :func:`orientation_imu_cdr` and
:func:`rotation_transform_cdr` are the nodes' per-sample outputs built on them: a rotation
matrix and covariance in, the bytes of the message ``conversions.set_quaternion`` /
``set_covariance`` / ``set_vector3`` would fill out (imu_magnetometer, panorama_mapper and the
hybrid share them instead of each building the tuple of doubles).

Layout (plain CDR, XCDR1, as ROS 2 writes it): a 4-byte encapsulation header, then the fields
in order, each primitive aligned to its size relative to the end of the encapsulation header;
a string is a uint32 length (the terminating NUL included) and its bytes; fixed arrays have no
length, sequences a uint32 count.
"""
from __future__ import annotations

import struct
from typing import Any, Callable

import numpy as np
from numpy.typing import NDArray

from ..core.rotations import matrix_to_quat_xyzw

_HEADER = struct.Struct('<iII')  # stamp.sec, stamp.nanosec, frame_id length
_U32 = struct.Struct('<I')
_IMU = struct.Struct('<37d')  # orientation 4, cov 9, angular_velocity 3, cov 9, linear_acceleration 3, cov 9
_MAG = struct.Struct('<12d')  # magnetic_field 3, cov 9
_TRANSFORM = struct.Struct('<7d')  # translation 3, rotation 4
_IMAGE_DIMS = struct.Struct('<II')  # height, width
_CAMERA_TAIL = struct.Struct('<6I')  # binning_x, binning_y, roi x_offset, y_offset, height, width
_CDR_LE = 1  # second byte of the encapsulation header: 0 CDR_BE, 1 CDR_LE


class StampView:
    __slots__ = ('sec', 'nanosec')

    def __init__(self, sec: int, nanosec: int) -> None:
        self.sec = sec
        self.nanosec = nanosec


class HeaderView:
    __slots__ = ('stamp', 'frame_id')

    def __init__(self, stamp: StampView, frame_id: str) -> None:
        self.stamp = stamp
        self.frame_id = frame_id


class Vector3View:
    __slots__ = ('x', 'y', 'z')

    def __init__(self, x: float, y: float, z: float) -> None:
        self.x = x
        self.y = y
        self.z = z


class QuaternionView:
    __slots__ = ('x', 'y', 'z', 'w')

    def __init__(self, x: float, y: float, z: float, w: float) -> None:
        self.x = x
        self.y = y
        self.z = z
        self.w = w


class ImuView:
    """sensor_msgs/Imu."""

    __slots__ = ('header', 'orientation', 'orientation_covariance', 'angular_velocity',
                 'angular_velocity_covariance', 'linear_acceleration', 'linear_acceleration_covariance')


class MagneticFieldView:
    """sensor_msgs/MagneticField."""

    __slots__ = ('header', 'magnetic_field', 'magnetic_field_covariance')


class TransformView:
    __slots__ = ('translation', 'rotation')


class TransformStampedView:
    """geometry_msgs/TransformStamped."""

    __slots__ = ('header', 'child_frame_id', 'transform')


class ImageView:
    """sensor_msgs/Image; ``data`` is a read-only memoryview of the received bytes."""

    __slots__ = ('header', 'height', 'width', 'encoding', 'is_bigendian', 'step', 'data')


class CompressedImageView:
    """sensor_msgs/CompressedImage; ``data`` is a read-only memoryview of the received bytes."""

    __slots__ = ('header', 'format', 'data')


class RegionOfInterestView:
    __slots__ = ('x_offset', 'y_offset', 'height', 'width', 'do_rectify')


class CameraInfoView:
    """sensor_msgs/CameraInfo; ``d``, ``k``, ``r``, ``p`` are float64 arrays (rclpy gives d as an
    ``array.array`` of doubles and the others as numpy arrays: the same numbers)."""

    __slots__ = ('header', 'height', 'width', 'distortion_model', 'd', 'k', 'r', 'p', 'binning_x',
                 'binning_y', 'roi')


def _string(raw: bytes, pos: int) -> tuple[str, int]:
    """The string whose uint32 length is at ``pos`` (4-aligned) and the position after it."""
    (n,) = _U32.unpack_from(raw, pos)
    end = pos + 4 + n
    if end > len(raw):
        raise ValueError('CDR string runs past the end of the message')
    return raw[pos + 4:end - 1 if n else end].decode('utf-8'), end


def _align(pos: int, size: int) -> int:
    """``pos`` moved to the next multiple of ``size`` counted from the end of the 4-byte
    encapsulation header."""
    return pos + (-(pos - 4) % size)


def _header(raw: bytes) -> tuple[HeaderView, int]:
    """The std_msgs/Header after the encapsulation header and the position after it."""
    sec, nanosec, _ = _HEADER.unpack_from(raw, 4)
    frame_id, end = _string(raw, 12)
    return HeaderView(StampView(sec, nanosec), frame_id), end


def _array(values: tuple[float, ...]) -> NDArray[np.float64]:
    return np.array(values, dtype=np.float64)


def imu_view(raw: bytes) -> ImuView:
    """An :class:`ImuView` of little-endian CDR bytes of a sensor_msgs/Imu."""
    header, pos = _header(raw)
    f = _IMU.unpack_from(raw, _align(pos, 8))
    m = ImuView()
    m.header = header
    m.orientation = QuaternionView(f[0], f[1], f[2], f[3])
    m.orientation_covariance = _array(f[4:13])
    m.angular_velocity = Vector3View(f[13], f[14], f[15])
    m.angular_velocity_covariance = _array(f[16:25])
    m.linear_acceleration = Vector3View(f[25], f[26], f[27])
    m.linear_acceleration_covariance = _array(f[28:37])
    return m


def magnetic_field_view(raw: bytes) -> MagneticFieldView:
    """A :class:`MagneticFieldView` of little-endian CDR bytes of a sensor_msgs/MagneticField."""
    header, pos = _header(raw)
    f = _MAG.unpack_from(raw, _align(pos, 8))
    m = MagneticFieldView()
    m.header = header
    m.magnetic_field = Vector3View(f[0], f[1], f[2])
    m.magnetic_field_covariance = _array(f[3:12])
    return m


def transform_stamped_view(raw: bytes) -> TransformStampedView:
    """A :class:`TransformStampedView` of little-endian CDR bytes of a
    geometry_msgs/TransformStamped."""
    header, pos = _header(raw)
    child, pos = _string(raw, _align(pos, 4))
    f = _TRANSFORM.unpack_from(raw, _align(pos, 8))
    t = TransformView()
    t.translation = Vector3View(f[0], f[1], f[2])
    t.rotation = QuaternionView(f[3], f[4], f[5], f[6])
    m = TransformStampedView()
    m.header = header
    m.child_frame_id = child
    m.transform = t
    return m


def image_view(raw: bytes) -> ImageView:
    """An :class:`ImageView` of little-endian CDR bytes of a sensor_msgs/Image (the pixels
    are not copied)."""
    header, pos = _header(raw)
    pos = _align(pos, 4)
    height, width = _IMAGE_DIMS.unpack_from(raw, pos)
    encoding, pos = _string(raw, pos + 8)
    is_bigendian = raw[pos]
    pos = _align(pos + 1, 4)
    step, n = _IMAGE_DIMS.unpack_from(raw, pos)  # step, then the data sequence's count
    start = pos + 8
    if start + n > len(raw):
        raise ValueError('CDR image data runs past the end of the message')
    m = ImageView()
    m.header = header
    m.height, m.width, m.encoding, m.is_bigendian, m.step = height, width, encoding, is_bigendian, step
    m.data = memoryview(raw)[start:start + n]
    return m


def compressed_image_view(raw: bytes) -> CompressedImageView:
    """A :class:`CompressedImageView` of little-endian CDR bytes of a
    sensor_msgs/CompressedImage (the encoded bytes are not copied)."""
    header, pos = _header(raw)
    fmt, pos = _string(raw, _align(pos, 4))
    pos = _align(pos, 4)
    (n,) = _U32.unpack_from(raw, pos)
    if pos + 4 + n > len(raw):
        raise ValueError('CDR compressed image data runs past the end of the message')
    m = CompressedImageView()
    m.header, m.format = header, fmt
    m.data = memoryview(raw)[pos + 4:pos + 4 + n]
    return m


def camera_info_view(raw: bytes) -> CameraInfoView:
    """A :class:`CameraInfoView` of little-endian CDR bytes of a sensor_msgs/CameraInfo.
    rclpy builds this message through a checked setter per array (~240 us); here ~14 us."""
    header, pos = _header(raw)
    pos = _align(pos, 4)
    height, width = _IMAGE_DIMS.unpack_from(raw, pos)
    model, pos = _string(raw, pos + 8)
    pos = _align(pos, 4)
    (n,) = _U32.unpack_from(raw, pos)
    pos = _align(pos + 4, 8)
    end = pos + 8 * (n + 30)
    if end + 4 * 6 + 1 > len(raw):
        raise ValueError('CDR camera info runs past the end of the message')
    values = np.frombuffer(raw, '<f8', n + 30, pos).astype(np.float64)
    m = CameraInfoView()
    m.header, m.height, m.width, m.distortion_model = header, height, width, model
    m.d, m.k, m.r, m.p = values[:n], values[n:n + 9], values[n + 9:n + 18], values[n + 18:]
    m.binning_x, m.binning_y, x0, y0, rh, rw = _CAMERA_TAIL.unpack_from(raw, end)
    roi = RegionOfInterestView()
    roi.x_offset, roi.y_offset, roi.height, roi.width, roi.do_rectify = x0, y0, rh, rw, bool(raw[end + 24])
    m.roi = roi
    return m


_ENCAPSULATION_LE = b'\x00\x01\x00\x00'


def _header_cdr(sec: int, nanosec: int, frame_id: str) -> bytes:
    """Encapsulation header, std_msgs/Header (stamp, frame_id with its NUL); no padding after."""
    name = frame_id.encode('utf-8')
    return _ENCAPSULATION_LE + _HEADER.pack(sec, nanosec, len(name) + 1) + name + b'\x00'


def _string_cdr(text: str, pos: int) -> bytes:
    """A CDR string starting at absolute offset ``pos``: padding to 4, length, bytes, NUL."""
    data = text.encode('utf-8')
    return _pad(pos, 4) + _U32.pack(len(data) + 1) + data + b'\x00'


def _pad(pos: int, size: int) -> bytes:
    return b'\x00' * (-(pos - 4) % size)


def imu_cdr(sec: int, nanosec: int, frame_id: str, values: Any) -> bytes:
    """CDR bytes of a sensor_msgs/Imu; ``values`` the 37 doubles in field order: orientation
    (x, y, z, w), its covariance (9), angular_velocity (3), its covariance (9),
    linear_acceleration (3), its covariance (9) (a float64 array of 37 is written as it is, no
    Python floats made of it: the nodes' :func:`orientation_imu_cdr`)."""
    v = np.asarray(values, '<f8')
    if v.shape != (37,):
        raise ValueError(f'an Imu has 37 doubles, got shape {v.shape}')
    head = _header_cdr(sec, nanosec, frame_id)
    return head + _pad(len(head), 8) + v.tobytes()


def transform_stamped_cdr(sec: int, nanosec: int, frame_id: str, child_frame_id: str, values: Any) -> bytes:
    """CDR bytes of a geometry_msgs/TransformStamped; ``values`` the 7 doubles translation (x,
    y, z) and rotation (x, y, z, w)."""
    head = _header_cdr(sec, nanosec, frame_id)
    head += _string_cdr(child_frame_id, len(head))
    return head + _pad(len(head), 8) + _TRANSFORM.pack(*values)


def image_cdr(sec: int, nanosec: int, frame_id: str, pixels: NDArray[Any], encoding: str) -> bytes:
    """CDR bytes of a sensor_msgs/Image of ``pixels`` (height x width [x channels], its rows
    unpadded, little-endian) in ``encoding``, without the ``array.array`` copy of the pixels an
    Image message object makes (``conversions.array_to_image`` checks shape and encoding)."""
    arr = np.ascontiguousarray(pixels)
    height, width = int(arr.shape[0]), int(arr.shape[1])
    step = int(np.prod(arr.shape[1:])) * arr.itemsize
    head = _header_cdr(sec, nanosec, frame_id)
    head += _pad(len(head), 4) + _IMAGE_DIMS.pack(height, width)
    head += _string_cdr(encoding, len(head)) + b'\x00'  # is_bigendian
    head += _pad(len(head), 4) + _IMAGE_DIMS.pack(step, arr.nbytes)
    return head + arr.astype(arr.dtype.newbyteorder('<'), copy=False).tobytes()


#: A covariance marked unknown (REP-145: -1 in element 0), for Imu fields a message leaves empty.
UNKNOWN_COVARIANCE = (-1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
_ZERO3 = (0.0, 0.0, 0.0)


def orientation_imu_cdr(sec: int, nanosec: int, frame_id: str, R: NDArray[np.float64] | None,
                        covariance: Any = None, angular_velocity: Any = _ZERO3,
                        angular_velocity_covariance: Any = UNKNOWN_COVARIANCE, linear_acceleration: Any = _ZERO3,
                        linear_acceleration_covariance: Any = UNKNOWN_COVARIANCE) -> bytes:
    """CDR bytes of a sensor_msgs/Imu with the orientation R (3x3: its quaternion with w >= 0,
    as ``conversions.set_quaternion`` writes it) and its 3x3 ``covariance`` (None: unknown,
    as ``conversions.set_covariance(.., None)``); R None: no orientation (the identity
    quaternion of a new message, covariance unknown). Rate and acceleration (3 values each,
    with 9-value covariances) default to zero and unknown (an orientation-only output).

    The per-sample outputs of imu_magnetometer and the hybrid filter: the 37 doubles go into
    one float64 array (no tuple of Python floats), which :func:`imu_cdr` writes."""
    values = np.empty(37, '<f8')
    if R is None:
        values[0:4] = (0.0, 0.0, 0.0, 1.0)
    else:
        values[0:4] = matrix_to_quat_xyzw(R)
    values[4:13] = UNKNOWN_COVARIANCE if covariance is None else np.asarray(covariance, dtype=np.float64).reshape(9)
    values[13:16] = angular_velocity
    values[16:25] = angular_velocity_covariance
    values[25:28] = linear_acceleration
    values[28:37] = linear_acceleration_covariance
    return imu_cdr(sec, nanosec, frame_id, values)


def rotation_transform_cdr(sec: int, nanosec: int, frame_id: str, child_frame_id: str, R: NDArray[np.float64]
                           ) -> bytes:
    """CDR bytes of a geometry_msgs/TransformStamped with zero translation and the rotation R
    (3x3, its quaternion with w >= 0): the per-frame orientation outputs of panorama_mapper
    and the hybrid filter."""
    q = matrix_to_quat_xyzw(R)
    return transform_stamped_cdr(sec, nanosec, frame_id, child_frame_id,
                                 (0.0, 0.0, 0.0, float(q[0]), float(q[1]), float(q[2]), float(q[3])))


def header_message(header: Any) -> Any:
    """A std_msgs/Header with the fields of a :class:`HeaderView` (a Header is returned as it
    is): for a node that passes its input's header on in an output message."""
    if not isinstance(header, HeaderView):
        return header
    from builtin_interfaces.msg import Time
    from std_msgs.msg import Header

    return Header(stamp=Time(sec=header.stamp.sec, nanosec=header.stamp.nanosec), frame_id=header.frame_id)


def viewer(msg_type: Any, view: Callable[[bytes], Any]) -> Callable[[bytes], Any]:
    """``raw -> view(raw)`` for little-endian CDR, else the message rclpy deserialises (a
    big-endian publisher): the decoder of a raw subscription to ``msg_type``."""
    from rclpy.serialization import deserialize_message

    def decode(raw: bytes) -> Any:
        if len(raw) >= 4 and raw[1] == _CDR_LE:
            return view(raw)
        return deserialize_message(raw, msg_type)
    return decode
