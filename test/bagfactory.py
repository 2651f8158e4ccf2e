"""Small bags written directly with rosbags, for tests that must not depend on the simulator."""
from __future__ import annotations

from pathlib import Path
from typing import Iterable

import numpy as np

from ar_tracking.core.rotations import matrix_to_quat_xyzw, rot_z
from ar_tracking.io.bags import BagWriter, msg_class, ns_to_stamp

T0_NS = 1_700_000_000_000_000_000
G = 9.80665
FIELD_ENU = 48e-6 * np.array([0.0, np.cos(np.radians(64)), -np.sin(np.radians(64))])


def _header(t_ns: int, frame: str):
    return msg_class('std_msgs/msg/Header')(stamp=ns_to_stamp(t_ns), frame_id=frame)


def _vec(v):
    return msg_class('geometry_msgs/msg/Vector3')(x=float(v[0]), y=float(v[1]), z=float(v[2]))


def imu_msg(t_ns: int, accel, gyro=(0.0, 0.0, 0.0), frame: str = 'imu'):
    Imu = msg_class('sensor_msgs/msg/Imu')
    Q = msg_class('geometry_msgs/msg/Quaternion')
    cov = np.zeros(9)
    cov[0] = -1.0
    return Imu(header=_header(t_ns, frame), orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0),
               orientation_covariance=cov, angular_velocity=_vec(gyro),
               angular_velocity_covariance=np.zeros(9), linear_acceleration=_vec(accel),
               linear_acceleration_covariance=np.zeros(9))


def mag_msg(t_ns: int, field, frame: str = 'imu'):
    MF = msg_class('sensor_msgs/msg/MagneticField')
    return MF(header=_header(t_ns, frame), magnetic_field=_vec(field), magnetic_field_covariance=np.zeros(9))


def truth_msg(t_ns: int, R_enu_cam):
    TS = msg_class('geometry_msgs/msg/TransformStamped')
    Tf = msg_class('geometry_msgs/msg/Transform')
    Q = msg_class('geometry_msgs/msg/Quaternion')
    q = matrix_to_quat_xyzw(R_enu_cam)
    return TS(header=_header(t_ns, 'enu'), child_frame_id='camera_optical',
              transform=Tf(translation=_vec((0, 0, 0)), rotation=Q(x=q[0], y=q[1], z=q[2], w=q[3])))


def tf_static_msg(t_ns: int, R_imu_cam):
    TFM = msg_class('tf2_msgs/msg/TFMessage')
    tf = truth_msg(t_ns, R_imu_cam)
    tf.header.frame_id = 'imu'
    return TFM(transforms=[tf])


R_IMU_CAM = np.diag([1.0, -1.0, -1.0])


def write_turning_imu_bag(path: Path, seconds: float = 2.0, rate_hz: float = 100.0,
                          yaw_rate_rad_s: float = 0.5, faults: Iterable[str] = (), storage: str = 'mcap') -> Path:
    """A device (IMU frame = phone: x right, y up, z to the user) turning about the vertical.

    Writes /imu/data_raw, /imu/mag, /tf_static and /ground_truth/orientation (enu -> camera).
    ``faults``: 'nan_accel', 'zero_mag', 'backwards', 'zero_stamp' inject one bad message each.
    """
    faults = set(faults)
    n = int(seconds * rate_hz)
    # Phone held upright, camera looking at the horizon: R_enu_cam has z (forward) horizontal.
    R_enu_cam0 = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    with BagWriter(path, storage=storage, overwrite=True) as w:
        w.write('/tf_static', T0_NS, tf_static_msg(T0_NS, R_IMU_CAM))
        for i in range(n):
            t = T0_NS + int(i * 1e9 / rate_hz)
            R_enu_cam = rot_z(yaw_rate_rad_s * i / rate_hz) @ R_enu_cam0
            R_enu_imu = R_enu_cam @ R_IMU_CAM.T
            accel = R_enu_imu.T @ np.array([0.0, 0.0, G])
            field = R_enu_imu.T @ FIELD_ENU
            gyro = R_enu_imu.T @ np.array([0.0, 0.0, yaw_rate_rad_s])
            w.write('/ground_truth/orientation', t, truth_msg(t, R_enu_cam))
            if i == n // 2 and 'nan_accel' in faults:
                accel = np.array([np.nan, 0.0, 9.8])
            if i == n // 2 + 1 and 'zero_mag' in faults:
                field = np.zeros(3)
            stamp = t
            if i == n // 2 + 2 and 'backwards' in faults:
                stamp = t - int(0.2e9)
            if i == n // 2 + 3 and 'zero_stamp' in faults:
                stamp = 0
            w.write('/imu/data_raw', t, imu_msg(stamp, accel, gyro))
            w.write('/imu/mag', t, mag_msg(stamp, field))
    return path
