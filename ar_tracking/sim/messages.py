"""ROS message builders and the conventions shared by every simulated bag.

Topic names, frame ids and the fixed start stamp of the bags (DESIGN.md sections 2, 3 and 5), and
:class:`Msgs`, which builds the rosbags message objects the scenarios write. Every scenario imports
these from here (never from :mod:`.bagmaker`, which imports the scenarios), so there is no import
cycle between the dispatcher and the scenarios.
"""
from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from ..io.bags import msg_class, ns_to_stamp
from .camera import PinholeCamera
from .scenario import SimError

#: Stamp of the first message (2023-11-14T22:13:20Z): fixed, so bags are reproducible.
START_NS = 1_700_000_000 * 1_000_000_000
JPEG_QUALITY = 85

TOPIC_IMAGE = '/camera/image_raw'
TOPIC_IMAGE_COMPRESSED = '/camera/image_raw/compressed'
TOPIC_CAMERA_INFO = '/camera/camera_info'
TOPIC_IMU = '/imu/data_raw'
TOPIC_MAG = '/imu/mag'
TOPIC_GPS = '/gps/fix'
TOPIC_TF_STATIC = '/tf_static'
TOPIC_GT_ORIENTATION = '/ground_truth/orientation'
TOPIC_GT_POSE = '/ground_truth/pose'
TOPIC_GT_ANNOTATIONS = '/ground_truth/annotations'
TOPIC_GT_MAG_DISTURBANCE = '/ground_truth/mag_disturbance'

FRAME_CAMERA = 'camera_optical'
FRAME_IMU = 'imu'
FRAME_GPS = 'gps'
FRAME_WORLD = 'enu'


class Msgs:
    """Builders of the rosbags message objects used here."""

    def __init__(self) -> None:
        self.Header = msg_class('std_msgs/msg/Header')
        self.Vector3 = msg_class('geometry_msgs/msg/Vector3')
        self.Quaternion = msg_class('geometry_msgs/msg/Quaternion')
        self.Point = msg_class('geometry_msgs/msg/Point')
        self.Pose = msg_class('geometry_msgs/msg/Pose')
        self.Transform = msg_class('geometry_msgs/msg/Transform')

    def header(self, ns: int, frame_id: str) -> Any:
        return self.Header(stamp=ns_to_stamp(ns), frame_id=frame_id)

    def vec(self, v: np.ndarray) -> Any:
        return self.Vector3(x=float(v[0]), y=float(v[1]), z=float(v[2]))

    def quat(self, q_xyzw: np.ndarray) -> Any:
        return self.Quaternion(x=float(q_xyzw[0]), y=float(q_xyzw[1]), z=float(q_xyzw[2]),
                               w=float(q_xyzw[3]))

    def transform_stamped(self, ns: int, parent: str, child: str, t: np.ndarray,
                          q_xyzw: np.ndarray) -> Any:
        return msg_class('geometry_msgs/msg/TransformStamped')(
            header=self.header(ns, parent), child_frame_id=child,
            transform=self.Transform(translation=self.vec(t), rotation=self.quat(q_xyzw)))

    def pose_stamped(self, ns: int, frame: str, p: np.ndarray, q_xyzw: np.ndarray) -> Any:
        return msg_class('geometry_msgs/msg/PoseStamped')(
            header=self.header(ns, frame),
            pose=self.Pose(position=self.Point(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                           orientation=self.quat(q_xyzw)))

    def imu(self, ns: int, gyro: np.ndarray, accel: np.ndarray, gyro_var: float,
            accel_var: float) -> Any:
        return msg_class('sensor_msgs/msg/Imu')(
            header=self.header(ns, FRAME_IMU),
            orientation=self.Quaternion(x=0.0, y=0.0, z=0.0, w=0.0),
            orientation_covariance=np.array([-1.0] + [0.0] * 8),
            angular_velocity=self.vec(gyro),
            angular_velocity_covariance=np.diag([gyro_var] * 3).ravel(),
            linear_acceleration=self.vec(accel),
            linear_acceleration_covariance=np.diag([accel_var] * 3).ravel())

    def mag(self, ns: int, field_t: np.ndarray, var: float) -> Any:
        return msg_class('sensor_msgs/msg/MagneticField')(
            header=self.header(ns, FRAME_IMU), magnetic_field=self.vec(field_t),
            magnetic_field_covariance=np.diag([var] * 3).ravel())

    def vector3_stamped(self, ns: int, frame: str, v: np.ndarray) -> Any:
        return msg_class('geometry_msgs/msg/Vector3Stamped')(header=self.header(ns, frame),
                                                             vector=self.vec(v))

    def navsat(self, ns: int, lat: float, lon: float, alt: float, sig_h: float,
               sig_v: float) -> Any:
        NavSatFix = msg_class('sensor_msgs/msg/NavSatFix')
        Status = msg_class('sensor_msgs/msg/NavSatStatus')
        return NavSatFix(
            header=self.header(ns, FRAME_GPS),
            status=Status(status=Status.STATUS_FIX, service=Status.SERVICE_GPS),
            latitude=float(lat), longitude=float(lon), altitude=float(alt),
            position_covariance=np.diag([sig_h ** 2, sig_h ** 2, sig_v ** 2]).ravel(),
            position_covariance_type=NavSatFix.COVARIANCE_TYPE_DIAGONAL_KNOWN)

    def camera_info(self, ns: int, cam: PinholeCamera) -> Any:
        K = cam.K
        P = np.hstack([K, np.zeros((3, 1))])
        return msg_class('sensor_msgs/msg/CameraInfo')(
            header=self.header(ns, FRAME_CAMERA), height=cam.height, width=cam.width,
            distortion_model='plumb_bob', d=np.zeros(5), k=K.ravel(), r=np.eye(3).ravel(),
            p=P.ravel(), binning_x=0, binning_y=0,
            roi=msg_class('sensor_msgs/msg/RegionOfInterest')(
                x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))

    def image(self, ns: int, rgb: np.ndarray) -> Any:
        h, w = rgb.shape[:2]
        return msg_class('sensor_msgs/msg/Image')(
            header=self.header(ns, FRAME_CAMERA), height=h, width=w, encoding='rgb8',
            is_bigendian=0, step=3 * w, data=np.ascontiguousarray(rgb).reshape(-1))

    def compressed(self, ns: int, rgb: np.ndarray) -> Any:
        ok, buf = cv2.imencode('.jpg', cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR),
                               [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        if not ok:  # pragma: no cover - OpenCV always encodes a valid uint8 image
            raise SimError('JPEG encoding failed')
        return msg_class('sensor_msgs/msg/CompressedImage')(
            header=self.header(ns, FRAME_CAMERA), format='jpeg', data=buf.reshape(-1))

    def markers(self, ns: int, labels: list[str], positions: list[np.ndarray]) -> Any:
        Marker = msg_class('visualization_msgs/msg/Marker')
        out = []
        for i, (label, p) in enumerate(zip(labels, positions, strict=True)):
            out.append(Marker(
                header=self.header(ns, FRAME_WORLD), ns='ground_truth', id=i,
                type=Marker.TEXT_VIEW_FACING, action=Marker.ADD,
                pose=self.Pose(position=self.Point(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                               orientation=self.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)),
                scale=self.Vector3(x=0.0, y=0.0, z=1.0),
                color=msg_class('std_msgs/msg/ColorRGBA')(r=1.0, g=0.85, b=0.1, a=1.0),
                lifetime=msg_class('builtin_interfaces/msg/Duration')(sec=0, nanosec=0),
                frame_locked=False, points=[], colors=[], texture_resource='',
                texture=msg_class('sensor_msgs/msg/CompressedImage')(
                    header=self.header(0, ''), format='', data=np.zeros(0, np.uint8)),
                uv_coordinates=[], text=label, mesh_resource='',
                mesh_file=msg_class('visualization_msgs/msg/MeshFile')(
                    filename='', data=np.zeros(0, np.uint8)),
                mesh_use_embedded_materials=False))
        return msg_class('visualization_msgs/msg/MarkerArray')(markers=out)
