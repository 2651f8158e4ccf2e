"""Message <-> numpy conversions on rclpy message objects (no node, no DDS)."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Quaternion, Vector3
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import CompressedImage, Image, Imu, MagneticField
from std_msgs.msg import Header

from ar_tracking.ros.conversions import (
    IMAGE_ENCODINGS,
    ConversionError,
    array_to_image,
    compressed_to_array,
    covariance_is_known,
    finite_vector3,
    image_to_array,
    image_to_gray_u8,
    message_class,
    quat_xyzw,
    rotation_from_quaternion,
    set_covariance,
    set_quaternion,
    set_vector3,
    stamp_ns,
    to_stamp,
    vector3,
)

SEC = 1_000_000_000
PROPERTY = settings(max_examples=25, deadline=None, derandomize=True)


def image_arrays(encoding: str):
    dtype, channels = IMAGE_ENCODINGS[encoding]
    shape = st.tuples(st.integers(1, 9), st.integers(1, 9))
    if channels > 1:
        shape = shape.map(lambda hw: (*hw, channels))
    elements = (
        st.floats(-1e6, 1e6, width=32, allow_nan=False) if dtype.kind == 'f' else None
    )
    return hnp.arrays(dtype, shape, elements=elements)


def raw_image(arr: np.ndarray, encoding: str, pad: int = 0, big_endian: bool = False) -> Image:
    """An Image filled by hand (as a foreign driver would), with optional row padding."""
    height, width = arr.shape[:2]
    wire = arr.astype(arr.dtype.newbyteorder('>' if big_endian else '<'))
    rows = wire.reshape(height, -1).view(np.uint8).reshape(height, -1)
    padding = np.full((height, pad), 0xEE, dtype=np.uint8)
    data = np.hstack([rows, padding])
    msg = Image()
    msg.height, msg.width, msg.encoding = height, width, encoding
    msg.is_bigendian = 1 if big_endian else 0
    msg.step = data.shape[1]
    msg.data = data.tobytes()
    return msg


# --- images ---------------------------------------------------------------------------------

@pytest.mark.parametrize('encoding', sorted(IMAGE_ENCODINGS))
def test_image_round_trip_every_encoding(encoding):
    @PROPERTY
    @given(arr=image_arrays(encoding))
    def check(arr):
        msg = array_to_image(arr, encoding)
        dtype, channels = IMAGE_ENCODINGS[encoding]
        assert msg.encoding == encoding
        assert (msg.height, msg.width) == arr.shape[:2]
        assert msg.step == arr.shape[1] * channels * dtype.itemsize
        assert len(msg.data) == msg.step * msg.height
        out = image_to_array(msg)
        assert out.dtype == dtype
        assert out.shape == arr.shape
        np.testing.assert_array_equal(out, arr)

    check()


@pytest.mark.parametrize('encoding', ['mono8', 'rgb8', 'mono16', 'bgra8', 'rgb16', '32FC1'])
@pytest.mark.parametrize('pad', [1, 3, 64])
def test_row_padding_is_skipped(encoding, pad):
    dtype, channels = IMAGE_ENCODINGS[encoding]
    rng = np.random.default_rng(pad)
    shape = (5, 7) if channels == 1 else (5, 7, channels)
    arr = (rng.random(shape) * 1000).astype(dtype)
    msg = raw_image(arr, encoding, pad=pad)
    assert msg.step > msg.width * channels * dtype.itemsize
    np.testing.assert_array_equal(image_to_array(msg), arr)


@pytest.mark.parametrize('encoding', ['mono16', '16UC1', 'rgb16', '32FC1'])
def test_big_endian_is_read_correctly(encoding):
    dtype, channels = IMAGE_ENCODINGS[encoding]
    shape = (4, 6) if channels == 1 else (4, 6, channels)
    arr = (np.arange(np.prod(shape)).reshape(shape) * 257 + 1).astype(dtype)  # asymmetric bytes
    for pad in (0, 2):
        msg = raw_image(arr, encoding, pad=pad, big_endian=True)
        out = image_to_array(msg)
        assert out.dtype == dtype  # native order after reading
        np.testing.assert_array_equal(out, arr)
    # the same bytes read as little-endian would be different values: the flag matters
    msg.is_bigendian = 0
    assert not np.array_equal(image_to_array(msg), arr)


def test_big_endian_mono16_known_value():
    msg = Image(height=1, width=2, encoding='mono16', is_bigendian=1, step=4)
    msg.data = bytes([0x12, 0x34, 0xAB, 0xCD])
    np.testing.assert_array_equal(image_to_array(msg), [[0x1234, 0xABCD]])
    msg.is_bigendian = 0
    np.testing.assert_array_equal(image_to_array(msg), [[0x3412, 0xCDAB]])


def good_mono8() -> Image:
    return array_to_image(np.arange(12, dtype=np.uint8).reshape(3, 4), 'mono8')


@pytest.mark.parametrize(
    'change',
    [
        {'step': 3},  # smaller than a row
        {'height': 4},  # data shorter than step * height
        {'step': 5},  # padded step, but the data was not padded
        {'encoding': 'yuv422'},
        {'encoding': 'bayer_rggb8'},
        {'encoding': ''},
        {'height': 0, 'data': b''},
        {'width': 0, 'step': 0},
        {'data': b''},
    ],
)
def test_unusable_images_raise_conversion_error(change):
    msg = good_mono8()
    for key, value in change.items():
        setattr(msg, key, value)
    with pytest.raises(ConversionError) as exc:
        image_to_array(msg)
    assert '\n' not in str(exc.value)


def test_extra_trailing_data_is_tolerated():
    msg = good_mono8()
    msg.data = bytes(msg.data) + b'\x00' * 7
    np.testing.assert_array_equal(image_to_array(msg), np.arange(12).reshape(3, 4))


def test_array_to_image_rejects_mismatched_shapes():
    with pytest.raises(ConversionError):
        array_to_image(np.zeros((2, 2)), 'rgb8')
    with pytest.raises(ConversionError):
        array_to_image(np.zeros((2, 2, 3)), 'mono8')
    with pytest.raises(ConversionError):
        array_to_image(np.zeros((2, 2, 4)), 'bgr8')
    with pytest.raises(ConversionError):
        array_to_image(np.zeros((2, 2)), 'yuv422')


def test_array_to_image_fills_a_given_message():
    msg = Image()
    msg.header.frame_id = 'camera_optical'
    out = array_to_image(np.zeros((2, 3), np.uint16), 'mono16', msg)
    assert out is msg and msg.header.frame_id == 'camera_optical'
    assert msg.step == 6 and msg.is_bigendian == 0


def test_gray_from_rgb8_and_bgr8_use_the_channel_order():
    arr = np.zeros((2, 2, 3), np.uint8)
    arr[..., 0] = 255  # first channel: red in rgb8, blue in bgr8
    gray_rgb = image_to_gray_u8(array_to_image(arr, 'rgb8'))
    gray_bgr = image_to_gray_u8(array_to_image(arr, 'bgr8'))
    assert gray_rgb.dtype == np.uint8 and gray_rgb.shape == (2, 2)
    assert np.all(gray_rgb == 76)  # 0.299 * 255
    assert np.all(gray_bgr == 29)  # 0.114 * 255
    rng = np.random.default_rng(0)
    arr = rng.integers(0, 256, (6, 5, 3), dtype=np.uint8)
    np.testing.assert_array_equal(
        image_to_gray_u8(array_to_image(arr, 'rgb8')), cv2.cvtColor(arr, cv2.COLOR_RGB2GRAY)
    )
    np.testing.assert_array_equal(
        image_to_gray_u8(array_to_image(arr, 'bgr8')), cv2.cvtColor(arr, cv2.COLOR_BGR2GRAY)
    )


def test_gray_from_four_channels():
    arr = np.zeros((2, 2, 4), np.uint8)
    arr[..., 0] = 255
    arr[..., 3] = 17  # alpha is ignored
    assert np.all(image_to_gray_u8(array_to_image(arr, 'rgba8')) == 76)
    assert np.all(image_to_gray_u8(array_to_image(arr, 'bgra8')) == 29)


def test_gray_from_mono16_keeps_the_high_byte():
    arr = np.array([[0x0000, 0x00FF], [0xAB12, 0xFFFF]], dtype=np.uint16)
    gray = image_to_gray_u8(array_to_image(arr, 'mono16'))
    assert gray.dtype == np.uint8
    np.testing.assert_array_equal(gray, [[0x00, 0x00], [0xAB, 0xFF]])
    msg = raw_image(arr, 'mono16', pad=2, big_endian=True)
    np.testing.assert_array_equal(image_to_gray_u8(msg), [[0x00, 0x00], [0xAB, 0xFF]])


def test_gray_from_mono8_and_float():
    arr = np.arange(6, dtype=np.uint8).reshape(2, 3)
    np.testing.assert_array_equal(image_to_gray_u8(array_to_image(arr, 'mono8')), arr)
    f = np.array([[-1.0, 0.0, 0.5, 1.0, 2.0]], np.float32)
    np.testing.assert_array_equal(image_to_gray_u8(array_to_image(f, '32FC1')), [[0, 0, 127, 255, 255]])


def compressed(arr: np.ndarray, fmt: str) -> CompressedImage:
    ok, buf = cv2.imencode('.' + fmt, arr)
    assert ok
    msg = CompressedImage()
    msg.format = fmt
    msg.data = buf.tobytes()
    return msg


def test_compressed_png_is_lossless():
    rng = np.random.default_rng(1)
    bgr = rng.integers(0, 256, (12, 17, 3), dtype=np.uint8)
    np.testing.assert_array_equal(compressed_to_array(compressed(bgr, 'png')), bgr)
    gray = rng.integers(0, 256, (12, 17), dtype=np.uint8)
    np.testing.assert_array_equal(compressed_to_array(compressed(gray, 'png')), gray)


def test_compressed_jpeg_decodes_close():
    yy, xx = np.mgrid[0:48, 0:64]
    bgr = np.stack([xx * 4, yy * 5, (xx + yy) * 2], axis=-1).astype(np.uint8)
    out = compressed_to_array(compressed(bgr, 'jpeg'))
    assert out.shape == bgr.shape and out.dtype == np.uint8
    assert np.mean(np.abs(out.astype(int) - bgr.astype(int))) < 4.0


@pytest.mark.parametrize('data', [b'', b'not an image at all', bytes(range(256)) * 4])
def test_compressed_garbage_raises(data):
    msg = CompressedImage()
    msg.format = 'jpeg'
    msg.data = data
    with pytest.raises(ConversionError):
        compressed_to_array(msg)


def test_compressed_truncated_png_raises():
    msg = compressed(np.random.default_rng(2).integers(0, 256, (20, 20), dtype=np.uint8), 'png')
    msg.data = bytes(msg.data)[:30]
    with pytest.raises(ConversionError):
        compressed_to_array(msg)


# --- quaternions, vectors, covariances --------------------------------------------------------

def quaternion(x, y, z, w) -> Quaternion:
    return Quaternion(x=float(x), y=float(y), z=float(z), w=float(w))


def test_quaternion_round_trip():
    for R in Rotation.random(50, random_state=3).as_matrix():
        q = set_quaternion(Quaternion(), R)
        assert q.w >= 0
        assert np.linalg.norm(quat_xyzw(q)) == pytest.approx(1.0)
        np.testing.assert_allclose(rotation_from_quaternion(q), R, atol=1e-12)


def test_quaternion_wire_order_is_xyzw():
    # 90 deg about z: (x, y, z, w) = (0, 0, sqrt(1/2), sqrt(1/2))
    q = quaternion(0, 0, np.sqrt(0.5), np.sqrt(0.5))
    np.testing.assert_allclose(rotation_from_quaternion(q) @ [1, 0, 0], [0, 1, 0], atol=1e-12)


@pytest.mark.parametrize(
    'values',
    [(np.nan, 0, 0, 1), (0, 0, 0, np.inf), (0, 0, 0, 0), (0, 0, 0, 2), (0.5, 0.5, 0.5, 0.4)],
)
def test_quaternion_rejects_nan_and_non_unit(values):
    with pytest.raises(ConversionError):
        rotation_from_quaternion(quaternion(*values))


def test_quaternion_nearly_unit_is_normalised():
    R = rotation_from_quaternion(quaternion(0, 0, 0, 1.0005))
    np.testing.assert_allclose(R, np.eye(3), atol=1e-15)


def test_vectors():
    v = set_vector3(Vector3(), np.array([1.0, -2.0, 3.5]))
    np.testing.assert_array_equal(vector3(v), [1.0, -2.0, 3.5])
    np.testing.assert_array_equal(finite_vector3(v, 'accel'), [1.0, -2.0, 3.5])
    with pytest.raises(ConversionError, match='accel'):
        finite_vector3(Vector3(x=np.nan), 'accel')
    with pytest.raises(ConversionError, match='mag'):
        finite_vector3(Vector3(z=-np.inf), 'mag')
    with pytest.raises(ConversionError):
        finite_vector3(Vector3(), 'field')


def test_set_covariance_unknown_is_rep145():
    imu = Imu()
    set_covariance(imu.orientation_covariance, np.eye(3))
    set_covariance(imu.orientation_covariance, None)
    cov = np.asarray(imu.orientation_covariance)
    assert cov[0] == -1.0
    np.testing.assert_array_equal(cov[1:], 0.0)
    assert not covariance_is_known(imu.orientation_covariance)


def test_set_covariance_known_is_row_major():
    cov = np.arange(9, dtype=float).reshape(3, 3) + 0.5
    mag = MagneticField()
    set_covariance(mag.magnetic_field_covariance, cov)
    np.testing.assert_array_equal(np.asarray(mag.magnetic_field_covariance), cov.reshape(9))
    assert covariance_is_known(mag.magnetic_field_covariance)
    assert covariance_is_known(Imu().orientation_covariance)  # all zeros: known (and zero)
    assert not covariance_is_known([])


# --- time and message classes ---------------------------------------------------------------

@settings(max_examples=200, deadline=None, derandomize=True)
@given(ns=st.integers(0, 2**31 * SEC - 1))
def test_stamp_round_trip(ns):
    stamp = to_stamp(ns)
    assert isinstance(stamp, Time)
    assert 0 <= stamp.nanosec < SEC
    assert stamp_ns(stamp) == ns
    header = Header()
    to_stamp(ns, header.stamp)
    assert stamp_ns(header) == ns


def test_stamp_keeps_nanoseconds_at_epoch_times():
    ns = 1_700_000_000 * SEC + 123_456_789
    stamp = to_stamp(ns)
    assert (stamp.sec, stamp.nanosec) == (1_700_000_000, 123_456_789)
    assert stamp_ns(stamp) == ns
    assert stamp_ns(to_stamp(ns + 1)) - stamp_ns(stamp) == 1


def test_message_class():
    assert message_class('sensor_msgs/msg/Imu') is Imu
    assert message_class('sensor_msgs/Imu') is Imu
    assert message_class('geometry_msgs/msg/Quaternion') is Quaternion


@pytest.mark.parametrize(
    'name', ['Imu', 'sensor_msgs/msg/Nope', 'nope_msgs/msg/Imu', 'a/b/c/d', '', 'sensor_msgs//Imu']
)
def test_message_class_bad_names(name):
    with pytest.raises(ConversionError):
        message_class(name)
