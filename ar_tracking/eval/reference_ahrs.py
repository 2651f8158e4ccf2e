"""A reference row for ``evaluate``: VQF (online, its defaults) run on the bag's own IMU samples.

Every orientation figure of a bag is put next to what the strongest public AHRS gets from the
same samples (Laidig & Seel 2023, PyPI ``vqf``; no camera), so that a reader sees at once
whether an estimator helps. The samples are the raw ``/imu/data_raw`` and ``/imu/mag`` the
runner copies into the output bag, calibrated with the device calibration a user gave
``imu_magnetometer`` (the ``<bag>.params.yaml`` beside the source bag, when there is one); the
body orientation becomes the camera's with the bag's ``/tf_static``. This runs in the
evaluation only: no node reads it.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..io.bags import BagReader, stamp_to_ns
from ..io.static_tf import static_transforms
from .metrics import CAMERA_FRAME, OrientationSeries

logger = logging.getLogger(__name__)

Array = NDArray[np.float64]

IMU_TOPIC = '/imu/data_raw'
MAG_TOPIC = '/imu/mag'


def _calibration(source_bag: Path | None) -> dict[str, Any]:
    """imu_magnetometer's parameters from the sidecar of the source bag (empty without one)."""
    if source_bag is None:
        return {}
    stem = source_bag.name[: -len(source_bag.suffix)] if source_bag.suffix else source_bag.name
    sidecar = source_bag.with_name(stem + '.params.yaml')
    if not sidecar.is_file():
        return {}
    from ..ros.params import ParamsError, load_params_file

    try:
        table = load_params_file(sidecar)
    except ParamsError as exc:
        logger.warning('reference AHRS: %s', exc)
        return {}
    merged = dict(table.get('**', {}))
    merged.update(table.get('imu_magnetometer', {}))
    return merged


def vqf_reference(path: str | Path, source_bag: Path | None = None) -> OrientationSeries | None:
    """R_enu_cam of VQF on the bag's IMU samples at the IMU stamps; None without them."""
    from vqf import VQF

    from ..core.imu_orientation import ImuCalibration
    from ..core.rotations import quat_wxyz_to_matrix

    with BagReader(path) as bag:
        topics = bag.topics
        if topics.get(IMU_TOPIC) != 'sensor_msgs/msg/Imu':
            return None
        imu = [bag.deserialize(m) for m in bag.messages([IMU_TOPIC])]
        mag = [bag.deserialize(m) for m in bag.messages([MAG_TOPIC])] if MAG_TOPIC in topics else []
        tfs = static_transforms(bag, '/tf_static')
    if len(imu) < 10:
        return None
    imu_frame = (imu[0].header.frame_id or 'imu').lstrip('/')
    R_imu_cam = None
    for t in tfs:
        if t.parent.lstrip('/') == imu_frame and t.child.lstrip('/') == CAMERA_FRAME:
            R_imu_cam = np.asarray(t.rotation)
        elif t.child.lstrip('/') == imu_frame and t.parent.lstrip('/') == CAMERA_FRAME:
            R_imu_cam = np.asarray(t.rotation).T
    if R_imu_cam is None:
        if imu_frame != CAMERA_FRAME:
            logger.warning('reference AHRS: no /tf_static %s -> %s; not scored', imu_frame, CAMERA_FRAME)
            return None
        R_imu_cam = np.eye(3)
    p = _calibration(source_bag)
    cal = ImuCalibration(
        gyro_bias=p.get('gyro_bias', [0.0] * 3), accel_bias=p.get('accel_bias', [0.0] * 3),
        hard_iron_offset=p.get('hard_iron_offset', [0.0] * 3),
        soft_iron_matrix=np.reshape(p.get('soft_iron_matrix', np.eye(3).ravel()), (3, 3)))
    t = np.array([stamp_to_ns(m.header.stamp) for m in imu], dtype=np.int64)
    order = np.argsort(t, kind='stable')
    ts = float(np.median(np.diff(t[order]))) * 1e-9
    if not ts > 0:
        return None
    mt = np.array([stamp_to_ns(m.header.stamp) for m in mag], dtype=np.int64)
    mv = np.array([[m.magnetic_field.x, m.magnetic_field.y, m.magnetic_field.z] for m in mag]) if mag else np.zeros((0, 3))
    f = VQF(ts)
    stamps: list[int] = []
    R: list[Array] = []
    j = -1
    for k in order:
        m = imu[k]
        g = cal.gyro([m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z])
        a = cal.accel([m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z])
        if not (np.all(np.isfinite(g)) and np.all(np.isfinite(a))) or not np.any(a):
            continue
        while j + 1 < len(mt) and mt[j + 1] <= t[k]:
            j += 1
        f.updateGyr(g)
        f.updateAcc(a)
        if j >= 0 and abs(int(t[k]) - int(mt[j])) <= 100_000_000:
            field = cal.mag(mv[j])
            if np.all(np.isfinite(field)) and np.any(field):
                f.updateMag(field * 1e6)
        stamps.append(int(t[k]))
        R.append(quat_wxyz_to_matrix(f.getQuat9D()) @ R_imu_cam)
    return OrientationSeries.from_lists(stamps, R) if stamps else None
