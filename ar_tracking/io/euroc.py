"""Convert an EuRoC MAV (ASL) dataset folder into a bag the package's graph and evaluation read.

EuRoC (Burri et al., IJRR 2016) is the common benchmark of visual(-inertial) SLAM, distributed as
folders of PNG images and CSV files rather than bags. :func:`euroc_to_bag` turns one into:

* ``/camera/image_raw`` sensor_msgs/Image mono8 (cam0) and ``/camera/camera_info`` (pinhole
  intrinsics of ``cam0/sensor.yaml``; ``radial-tangential`` distortion becomes ``plumb_bob``
  with d = [k1, k2, p1, p2, 0], ``equidistant`` stays ``equidistant``), frame camera_optical
  (EuRoC's camera frame is already x right, y down, z forward);
* ``/imu/data_raw`` sensor_msgs/Imu (imu0: gyro and accelerometer, no orientation, variances
  from the noise densities of ``imu0/sensor.yaml``), frame imu;
* ``/tf_static``: imu -> camera_optical from the two ``T_BS`` extrinsics;
* ``/ground_truth/pose`` PoseStamped (frame world, the camera in the world) from a CSV
  ``#timestamp, p_x, p_y, p_z, q_w, q_x, q_y, q_z`` (more columns are ignored; stamps in ns,
  possibly written as ``123.000``, or in seconds). ``gt_frame='camera'`` (default for a given
  file) means the rows are camera poses; ``'body'`` means body (IMU) poses, which are moved to
  the camera with T_BS (the default for ``mav0/state_groundtruth_estimate0/data.csv``, used when
  no file is given and it exists). ``invert_gt_quaternion`` conjugates the quaternions, for files
  that store R_cam_world instead of R_world_cam (e.g. ORB-SLAM's ``V101_GT.txt``).

Log time = header stamp = the EuRoC stamp (one hardware clock for all sensors). Every problem
with the input is raised as :class:`EurocError` with one line naming the file (and line).
"""
from __future__ import annotations

import csv
import logging
import math
from dataclasses import dataclass
from decimal import Decimal, InvalidOperation
from pathlib import Path
from typing import Any, Callable, Iterator

import cv2
import numpy as np
import yaml
from numpy.typing import NDArray

from ..core.rotations import matrix_to_quat_xyzw, quat_xyzw_to_matrix
from .bags import BagError, BagWriter, msg_class, ns_to_stamp
from ..errors import ArTrackingError

logger = logging.getLogger(__name__)

Array = NDArray[np.float64]

FRAME_CAMERA, FRAME_IMU, FRAME_WORLD = 'camera_optical', 'imu', 'world'
TOPIC_IMAGE = '/camera/image_raw'
TOPIC_CAMERA_INFO = '/camera/camera_info'
TOPIC_IMU = '/imu/data_raw'
TOPIC_GT_POSE = '/ground_truth/pose'
TOPIC_TF_STATIC = '/tf_static'
BODY_GT = Path('state_groundtruth_estimate0') / 'data.csv'


class EurocError(ArTrackingError):
    """An EuRoC folder cannot be converted. The message is one line meant for the user."""


@dataclass(frozen=True)
class CameraCalib:
    width: int
    height: int
    K: Array
    distortion_model: str
    d: Array
    T_body_cam: Array


@dataclass(frozen=True)
class ImuCalib:
    T_body_imu: Array
    gyro_var: float
    accel_var: float


def _mav0(folder: Path) -> Path:
    if not folder.is_dir():
        raise EurocError(f'{folder}: no such folder')
    for cand in (folder / 'mav0', folder):
        if (cand / 'cam0').is_dir():
            return cand
    raise EurocError(f'{folder}: not an EuRoC folder (no mav0/cam0 inside)')


def _read_yaml(path: Path) -> dict[str, Any]:
    """EuRoC's sensor.yaml (OpenCV style: a '%YAML:1.0' first line that PyYAML does not take)."""
    try:
        text = path.read_text()
    except OSError as exc:
        raise EurocError(f'{path}: cannot read ({exc.strerror or exc})') from exc
    text = '\n'.join(line for line in text.splitlines() if not line.startswith('%YAML'))
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise EurocError(f'{path}: not valid YAML ({str(exc).splitlines()[0]})') from exc
    if not isinstance(doc, dict):
        raise EurocError(f'{path}: expected a mapping of sensor settings')
    return doc


def _matrix4(doc: dict[str, Any], path: Path) -> Array:
    T = doc.get('T_BS')
    if T is None:
        return np.eye(4)
    try:
        M = np.asarray(T['data'] if isinstance(T, dict) else T, dtype=float).reshape(4, 4)
    except (TypeError, ValueError, KeyError) as exc:
        raise EurocError(f'{path}: T_BS is not a 4x4 matrix') from exc
    R = M[:3, :3]
    if not np.all(np.isfinite(M)) or not np.allclose(R @ R.T, np.eye(3), atol=1e-3):
        raise EurocError(f'{path}: T_BS does not hold a rotation')
    return M


def read_camera_calib(path: Path) -> CameraCalib:
    """cam0/sensor.yaml: resolution, intrinsics [fu, fv, cu, cv], distortion, T_BS."""
    doc = _read_yaml(path)
    try:
        w, h = (int(v) for v in doc['resolution'])
        fu, fv, cu, cv = (float(v) for v in doc['intrinsics'])
    except (KeyError, TypeError, ValueError) as exc:
        raise EurocError(f'{path}: needs resolution [w, h] and intrinsics [fu, fv, cu, cv]') from exc
    model = str(doc.get('camera_model', 'pinhole'))
    if model != 'pinhole':
        raise EurocError(f'{path}: camera_model {model!r} is not supported (pinhole only)')
    dist = str(doc.get('distortion_model', 'radial-tangential'))
    try:
        coeffs = [float(v) for v in doc.get('distortion_coefficients', [])]
    except (TypeError, ValueError) as exc:
        raise EurocError(f'{path}: distortion_coefficients must be numbers') from exc
    if dist in ('radial-tangential', 'radtan', 'plumb_bob'):
        if len(coeffs) not in (4, 5):
            raise EurocError(f'{path}: radial-tangential needs 4 coefficients k1, k2, p1, p2, got {len(coeffs)}')
        ros_model, d = 'plumb_bob', np.array((coeffs + [0.0])[:5])
    elif dist == 'equidistant':
        if len(coeffs) != 4:
            raise EurocError(f'{path}: equidistant needs 4 coefficients, got {len(coeffs)}')
        ros_model, d = 'equidistant', np.array(coeffs)
    else:
        raise EurocError(f'{path}: distortion_model {dist!r} is not supported')
    if w <= 0 or h <= 0 or not all(math.isfinite(v) for v in (fu, fv, cu, cv)) or fu <= 0 or fv <= 0:
        raise EurocError(f'{path}: resolution and focal lengths must be positive')
    K = np.array([[fu, 0.0, cu], [0.0, fv, cv], [0.0, 0.0, 1.0]])
    return CameraCalib(w, h, K, ros_model, d, _matrix4(doc, path))


def read_imu_calib(path: Path) -> ImuCalib:
    """imu0/sensor.yaml: T_BS and the white-noise densities as per-sample variances."""
    if not path.is_file():
        return ImuCalib(np.eye(4), 0.0, 0.0)
    doc = _read_yaml(path)
    try:
        rate = float(doc.get('rate_hz', 200.0))
        g = float(doc.get('gyroscope_noise_density', 0.0))
        a = float(doc.get('accelerometer_noise_density', 0.0))
    except (TypeError, ValueError) as exc:
        raise EurocError(f'{path}: rate_hz and the noise densities must be numbers') from exc
    return ImuCalib(_matrix4(doc, path), g * g * rate, a * a * rate)


def _stamp_ns(token: str) -> int:
    """ns from '1403715274312143104', '1403715274312143104.000' or seconds '1403715274.3121431'."""
    try:
        v = Decimal(token.strip())
    except InvalidOperation as exc:
        raise ValueError(f'bad timestamp {token!r}') from exc
    if not v.is_finite() or v < 0:
        raise ValueError(f'bad timestamp {token!r}')
    if v < Decimal(10) ** 12:  # seconds
        v = v * Decimal(10) ** 9
    return int(v.to_integral_value())


def _csv_rows(path: Path, min_cols: int) -> Iterator[tuple[int, list[str]]]:
    """(line number, fields) of a CSV with '#' comments, at least ``min_cols`` columns each."""
    try:
        f = path.open(newline='')
    except OSError as exc:
        raise EurocError(f'{path}: cannot read ({exc.strerror or exc})') from exc
    with f:
        for lineno, row in enumerate(csv.reader(f), 1):
            if not row or not ''.join(row).strip() or row[0].lstrip().startswith('#'):
                continue
            if len(row) == 1 and ' ' in row[0].strip():  # space-separated variant
                row = row[0].split()
            if len(row) < min_cols:
                raise EurocError(f'{path}:{lineno}: expected {min_cols} columns, got {len(row)}')
            yield lineno, [c.strip() for c in row]


def read_images_csv(path: Path) -> list[tuple[int, str]]:
    """cam0/data.csv: (stamp ns, file name) sorted by stamp, duplicates dropped."""
    rows: list[tuple[int, str]] = []
    for lineno, row in _csv_rows(path, 2):
        try:
            rows.append((_stamp_ns(row[0]), row[1]))
        except ValueError as exc:
            raise EurocError(f'{path}:{lineno}: {exc}') from exc
    return _sorted_unique(rows, path)


def _sorted_unique(rows: list[Any], path: Path) -> list[Any]:
    rows.sort(key=lambda r: r[0])
    out = [r for i, r in enumerate(rows) if i == 0 or r[0] != rows[i - 1][0]]
    if len(out) < len(rows):
        logger.warning('%s: %d rows with a repeated timestamp dropped', path, len(rows) - len(out))
    return out


def _numbers(path: Path, lineno: int, row: list[str], cols: slice) -> list[float]:
    try:
        vals = [float(v) for v in row[cols]]
    except ValueError as exc:
        raise EurocError(f'{path}:{lineno}: not a number ({exc})') from exc
    if not all(math.isfinite(v) for v in vals):
        raise EurocError(f'{path}:{lineno}: NaN or infinite value')
    return vals


def read_imu_csv(path: Path) -> tuple[NDArray[np.int64], Array]:
    """imu0/data.csv: stamps (ns) and (N, 6) [wx, wy, wz, ax, ay, az]."""
    rows = []
    for lineno, row in _csv_rows(path, 7):
        try:
            t = _stamp_ns(row[0])
        except ValueError as exc:
            raise EurocError(f'{path}:{lineno}: {exc}') from exc
        rows.append((t, _numbers(path, lineno, row, slice(1, 7))))
    rows = _sorted_unique(rows, path)
    return (np.array([r[0] for r in rows], np.int64).reshape(-1),
            np.array([r[1] for r in rows], float).reshape(-1, 6))


def read_groundtruth_csv(path: Path, invert_quaternion: bool = False) -> tuple[NDArray[np.int64], Array, Array]:
    """Stamps (ns), positions (N, 3) and R (N, 3, 3) of ``#timestamp, p_x,p_y,p_z, q_w,q_x,q_y,q_z``."""
    if not path.is_file():
        raise EurocError(f'{path}: no such ground-truth file')
    rows = []
    for lineno, row in _csv_rows(path, 8):
        try:
            t = _stamp_ns(row[0])
        except ValueError as exc:
            raise EurocError(f'{path}:{lineno}: {exc}') from exc
        v = _numbers(path, lineno, row, slice(1, 8))
        q_wxyz = np.array(v[3:7])
        n = float(np.linalg.norm(q_wxyz))
        if abs(n - 1.0) > 0.01:
            raise EurocError(f'{path}:{lineno}: quaternion of norm {n:.3f} (expected q_w, q_x, q_y, q_z of norm 1)')
        rows.append((t, v[:3], q_wxyz / n))
    rows = _sorted_unique(rows, path)
    if not rows:
        raise EurocError(f'{path}: no ground-truth rows')
    q = np.array([r[2] for r in rows])
    q_xyzw = q[:, [1, 2, 3, 0]]
    if invert_quaternion:
        q_xyzw[:, :3] *= -1.0
    return np.array([r[0] for r in rows], np.int64), np.array([r[1] for r in rows], float), quat_xyzw_to_matrix(q_xyzw)


def _load_image(path: Path, calib: CameraCalib) -> NDArray[np.uint8]:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise EurocError(f'{path}: missing or not an image')
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    if img.dtype != np.uint8:
        raise EurocError(f'{path}: unsupported pixel type {img.dtype}')
    if img.shape != (calib.height, calib.width):
        raise EurocError(f'{path}: {img.shape[1]}x{img.shape[0]} image, sensor.yaml says '
                         f'{calib.width}x{calib.height}')
    return np.ascontiguousarray(img)


def euroc_to_bag(folder: str | Path, out_bag: str | Path, groundtruth_csv: str | Path | None = None,
                 invert_gt_quaternion: bool = False, *, gt_frame: str | None = None,
                 storage: str = 'mcap', overwrite: bool = False,
                 progress: Callable[[float], None] | None = None) -> Path:
    """Write the bag (module docstring) and return its path ('.mcap' added for mcap storage).

    ``folder`` is the dataset folder (holding mav0/) or mav0 itself. Without ``groundtruth_csv``
    the body ground truth ``mav0/state_groundtruth_estimate0/data.csv`` is used when present."""
    mav0 = _mav0(Path(folder))
    cam_dir = mav0 / 'cam0'
    calib = read_camera_calib(cam_dir / 'sensor.yaml')
    images = read_images_csv(cam_dir / 'data.csv')
    if not images:
        raise EurocError(f'{cam_dir / "data.csv"}: no images listed')
    missing = [name for _, name in images if not (cam_dir / 'data' / name).is_file()]
    if missing:
        raise EurocError(f'{cam_dir / "data"}: {len(missing)} of {len(images)} listed images are missing '
                         f'(first: {missing[0]})')
    imu_dir = mav0 / 'imu0'
    imu_calib = read_imu_calib(imu_dir / 'sensor.yaml')
    imu_t, imu = (read_imu_csv(imu_dir / 'data.csv') if (imu_dir / 'data.csv').is_file()
                  else (np.zeros(0, np.int64), np.zeros((0, 6))))
    if not len(imu_t):
        logger.warning('%s: no IMU data; the bag has images only', mav0)
    T_imu_cam = np.linalg.inv(imu_calib.T_body_imu) @ calib.T_body_cam

    gt_path = Path(groundtruth_csv) if groundtruth_csv is not None else None
    if gt_path is None and (mav0 / BODY_GT).is_file():
        gt_path = mav0 / BODY_GT
        gt_frame = gt_frame or 'body'
    gt_frame = gt_frame or 'camera'
    if gt_frame not in ('camera', 'body'):
        raise EurocError(f"gt_frame must be 'camera' or 'body', got {gt_frame!r}")
    gt_t, gt_p, gt_R = np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3, 3))
    if gt_path is not None:
        gt_t, gt_p, gt_R = read_groundtruth_csv(gt_path, invert_gt_quaternion)
        if gt_frame == 'body':  # T_W_cam = T_W_B T_B_cam
            gt_p = gt_p + gt_R @ calib.T_body_cam[:3, 3]
            gt_R = gt_R @ calib.T_body_cam[:3, :3]
        overlap = np.sum((gt_t >= images[0][0]) & (gt_t <= images[-1][0]))
        logger.info('%s: %d ground-truth poses (%d during the images)', gt_path, len(gt_t), overlap)

    out = Path(out_bag)
    if storage == 'mcap' and out.suffix != '.mcap':
        out = out.with_name(out.name + '.mcap')
    if out.exists() and not overwrite:
        raise EurocError(f'{out}: already exists (choose another name or overwrite)')
    try:
        with BagWriter(out, storage=storage, overwrite=overwrite) as bag:  # type: ignore[arg-type]
            _write(bag, cam_dir, calib, images, imu_t, imu, imu_calib, T_imu_cam, gt_t, gt_p, gt_R, progress)
    except BagError as exc:
        raise EurocError(str(exc)) from exc
    logger.info('wrote %s: %d images, %d IMU samples, %d ground-truth poses', out, len(images), len(imu_t), len(gt_t))
    return out


def _header(ns: int, frame: str) -> Any:
    return msg_class('std_msgs/msg/Header')(stamp=ns_to_stamp(int(ns)), frame_id=frame)


def _vec(v: Array) -> Any:
    return msg_class('geometry_msgs/msg/Vector3')(x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _quat(q_xyzw: Array) -> Any:
    return msg_class('geometry_msgs/msg/Quaternion')(x=float(q_xyzw[0]), y=float(q_xyzw[1]),
                                                     z=float(q_xyzw[2]), w=float(q_xyzw[3]))


def _write(bag: BagWriter, cam_dir: Path, calib: CameraCalib, images: list[tuple[int, str]],
           imu_t: NDArray[np.int64], imu: Array, imu_calib: ImuCalib, T_imu_cam: Array,
           gt_t: NDArray[np.int64], gt_p: Array, gt_R: Array,
           progress: Callable[[float], None] | None) -> None:
    Image = msg_class('sensor_msgs/msg/Image')
    CameraInfo = msg_class('sensor_msgs/msg/CameraInfo')
    Roi = msg_class('sensor_msgs/msg/RegionOfInterest')
    Imu = msg_class('sensor_msgs/msg/Imu')
    Point = msg_class('geometry_msgs/msg/Point')
    Pose = msg_class('geometry_msgs/msg/Pose')
    PoseStamped = msg_class('geometry_msgs/msg/PoseStamped')
    TransformStamped = msg_class('geometry_msgs/msg/TransformStamped')
    Transform = msg_class('geometry_msgs/msg/Transform')

    t_first = min([images[0][0]] + ([int(imu_t[0])] if len(imu_t) else []) + ([int(gt_t[0])] if len(gt_t) else []))
    bag.write(TOPIC_TF_STATIC, t_first, msg_class('tf2_msgs/msg/TFMessage')(transforms=[TransformStamped(
        header=_header(t_first, FRAME_IMU), child_frame_id=FRAME_CAMERA,
        transform=Transform(translation=_vec(T_imu_cam[:3, 3]), rotation=_quat(matrix_to_quat_xyzw(T_imu_cam[:3, :3]))))]))
    K = calib.K
    P = np.hstack([K, np.zeros((3, 1))])
    q_gt = matrix_to_quat_xyzw(gt_R) if len(gt_t) else np.zeros((0, 4))
    gyro_cov = np.diag([imu_calib.gyro_var] * 3).ravel() if imu_calib.gyro_var > 0 else np.r_[-1.0, np.zeros(8)]
    accel_cov = np.diag([imu_calib.accel_var] * 3).ravel() if imu_calib.accel_var > 0 else np.r_[-1.0, np.zeros(8)]
    orient_cov = np.r_[-1.0, np.zeros(8)]

    events = sorted([(int(t), 0, i) for i, t in enumerate(gt_t)] + [(int(t), 1, i) for i, t in enumerate(imu_t)]
                    + [(t, 2, i) for i, (t, _) in enumerate(images)])
    n_img = len(images)
    every = max(1, n_img // 50)
    for ns, kind, i in events:
        if kind == 0:
            bag.write(TOPIC_GT_POSE, ns, PoseStamped(header=_header(ns, FRAME_WORLD), pose=Pose(
                position=Point(x=float(gt_p[i, 0]), y=float(gt_p[i, 1]), z=float(gt_p[i, 2])), orientation=_quat(q_gt[i]))))
        elif kind == 1:
            bag.write(TOPIC_IMU, ns, Imu(
                header=_header(ns, FRAME_IMU), orientation=_quat(np.array([0.0, 0.0, 0.0, 0.0])),
                orientation_covariance=orient_cov, angular_velocity=_vec(imu[i, :3]),
                angular_velocity_covariance=gyro_cov, linear_acceleration=_vec(imu[i, 3:]),
                linear_acceleration_covariance=accel_cov))
        else:
            img = _load_image(cam_dir / 'data' / images[i][1], calib)
            bag.write(TOPIC_CAMERA_INFO, ns, CameraInfo(
                header=_header(ns, FRAME_CAMERA), height=calib.height, width=calib.width,
                distortion_model=calib.distortion_model, d=calib.d.astype(float), k=K.ravel(),
                r=np.eye(3).ravel(), p=P.ravel(), binning_x=0, binning_y=0,
                roi=Roi(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)))
            bag.write(TOPIC_IMAGE, ns, Image(
                header=_header(ns, FRAME_CAMERA), height=calib.height, width=calib.width, encoding='mono8',
                is_bigendian=0, step=calib.width, data=img.reshape(-1)))
            if progress is not None and (i % every == 0 or i == n_img - 1):
                progress((i + 1) / n_img)
