"""ar_view: the camera image with the annotation labels drawn where their anchors are
(Langlotz 2011 sec. 3.2 and 5: the augmented live view; Fig. 2 and 4).

Subscribes ``camera/image_raw`` (Image; rgb8, bgr8 or mono8), ``camera/camera_info``,
``annotations/markers`` (MarkerArray in the panorama frame, from annotation_matcher) and the
current orientation: ``panorama/orientation`` (R_panorama_cam at the image stamp, preferred) or
``orientation/global`` (Imu, R_enu_cam) together with ``orientation/panorama_in_world``
(R_enu_panorama). Publishes ``ar/overlay`` (rgb8, the image's stamp). Drawing is
:mod:`ar_tracking.core.annotations.overlay`; this node converts.
"""
from __future__ import annotations

from typing import Any

import cv2
import numpy as np
from geometry_msgs.msg import TransformStamped
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, Imu
from visualization_msgs.msg import Marker, MarkerArray

from ..core.annotations.overlay import Label, draw_labels, project_labels
from ..core.rectification import RectificationError, check_distortion
from ..ros.conversions import (ConversionError, compressed_to_array, image_to_array, rotation_from_quaternion,
                               stamp_ns)
from ..ros.cdr_views import (camera_info_view, compressed_image_view, image_cdr, image_view, imu_view,
                             transform_stamped_view)
from ..ros.node_base import LATCHED_QOS, RELIABLE_QOS, SENSOR_QOS, TrackingNode, run_node
from ..ros.param_table import ParamSpec, declare_params


#: The node's parameters.
PARAMS = (
    ParamSpec('max_orientation_gap_s', 0.05,
              'Largest stamp difference between an image and the orientation used to draw it, s',
              min_value=0.0, max_value=10.0),
    ParamSpec('text_scale', 0.4, 'OpenCV font scale of the labels', min_value=0.1, max_value=5.0),
)


class ArViewNode(TrackingNode):
    INPUTS = {
        'camera/image_raw': 'sensor_msgs/msg/Image',
        'camera/image_raw/compressed': 'sensor_msgs/msg/CompressedImage',
        'camera/camera_info': 'sensor_msgs/msg/CameraInfo',
        'annotations/markers': 'visualization_msgs/msg/MarkerArray',
        'panorama/orientation': 'geometry_msgs/msg/TransformStamped',
        'orientation/global': 'sensor_msgs/msg/Imu',
        'orientation/panorama_in_world': 'geometry_msgs/msg/TransformStamped',
    }
    OUTPUTS = {'ar/overlay': 'sensor_msgs/msg/Image'}
    REQUIRED_INPUTS = [('camera/image_raw', 'camera/image_raw/compressed'), 'camera/camera_info', 'annotations/markers']

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('ar_view', **kwargs)
        v = declare_params(self, PARAMS)
        self.max_gap_ns = int(1e9 * v['max_orientation_gap_s'])
        self.text_scale = v['text_scale']
        self.labels: list[Label] = []
        self.K: np.ndarray | None = None
        #: camera_info's lens distortion (coefficients, model): labels are drawn through it.
        self.D: np.ndarray | None = None
        self.model = ''
        self.pano_cam: dict[int, np.ndarray] = {}
        self.enu_cam: tuple[int, np.ndarray] | None = None
        self.enu_pano: np.ndarray | None = None
        #: images waiting for their frame's panorama/orientation: stamp -> (rgb, the image's header)
        self.pending: dict[int, tuple[np.ndarray, Any]] = {}
        self.published = 0
        self.pub = self.advertise(Image, 'ar/overlay', RELIABLE_QOS)
        self.subscribe(Image, 'camera/image_raw', self.on_image, SENSOR_QOS, view=image_view)
        self.subscribe(CompressedImage, 'camera/image_raw/compressed', self.on_compressed, SENSOR_QOS,
                       view=compressed_image_view)
        self.subscribe(CameraInfo, 'camera/camera_info', self.on_info, SENSOR_QOS, view=camera_info_view)
        self.subscribe(MarkerArray, 'annotations/markers', self.on_markers, LATCHED_QOS)
        self.subscribe(TransformStamped, 'panorama/orientation', self.on_pano_orientation, RELIABLE_QOS,
                       view=transform_stamped_view)
        self.subscribe(Imu, 'orientation/global', self.on_global, RELIABLE_QOS, view=imu_view)
        self.subscribe(TransformStamped, 'orientation/panorama_in_world', self.on_pano_in_world, RELIABLE_QOS,
                       view=transform_stamped_view)

    def on_info(self, msg: CameraInfo) -> None:
        K = np.asarray(msg.k, float).reshape(3, 3)
        if not (np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0):
            self.warn_throttled('camera/camera_info: invalid K, ignored')
            return
        try:  # the labels go where the raw (distorted) frame shows them
            self.D = check_distortion(msg.d, str(msg.distortion_model))
        except RectificationError as exc:
            self.warn_throttled(f'camera/camera_info: {exc}, ignored')
            return
        self.K, self.model = K, str(msg.distortion_model)

    def on_markers(self, msg: MarkerArray) -> None:
        labels: list[Label] = []
        for m in msg.markers:
            if m.action == Marker.DELETEALL:
                labels = []
                continue
            if m.action != Marker.ADD:
                continue
            d = np.array([m.pose.position.x, m.pose.position.y, m.pose.position.z], float)
            n = np.linalg.norm(d)
            if not np.isfinite(n) or n == 0:
                self.warn_throttled(f'annotations/markers: marker {m.id} has no direction, skipped')
                continue
            labels.append(Label(m.text, d / n, m.ns or 'matched'))
        self.labels = labels

    def on_pano_orientation(self, msg: TransformStamped) -> None:
        try:
            R = rotation_from_quaternion(msg.transform.rotation, 'panorama/orientation')
        except ConversionError as exc:
            self.warn_throttled(f'{exc}, dropped')
            return
        t = stamp_ns(msg.header)
        self.pano_cam[t] = R
        while len(self.pano_cam) > 30:
            self.pano_cam.pop(next(iter(self.pano_cam)))
        if t in self.pending:  # the image came first
            self._draw(t, *self.pending.pop(t), R)

    def on_global(self, msg: Imu) -> None:
        try:
            self.enu_cam = (stamp_ns(msg.header), rotation_from_quaternion(msg.orientation, 'orientation/global'))
        except ConversionError as exc:
            self.warn_throttled(f'{exc}, dropped')

    def on_pano_in_world(self, msg: TransformStamped) -> None:
        try:
            self.enu_pano = rotation_from_quaternion(msg.transform.rotation, 'orientation/panorama_in_world')
        except ConversionError as exc:
            self.warn_throttled(f'{exc}, dropped')

    def on_image(self, msg: Image) -> None:
        try:
            arr = image_to_array(msg)
        except ConversionError as exc:
            self.warn_throttled(f'camera/image_raw: {exc}, dropped')
            return
        if arr.dtype != np.uint8:
            self.warn_throttled(f'camera/image_raw: encoding {msg.encoding} not drawn on, dropped')
            return
        if arr.ndim == 2:
            rgb = cv2.cvtColor(arr, cv2.COLOR_GRAY2RGB)
        elif msg.encoding.startswith('bgr'):
            rgb = cv2.cvtColor(arr[:, :, :3], cv2.COLOR_BGR2RGB)
        else:
            rgb = np.ascontiguousarray(arr[:, :, :3])
        self._on_rgb(stamp_ns(msg.header), rgb, msg.header)

    def on_compressed(self, msg: CompressedImage) -> None:
        try:
            arr = compressed_to_array(msg)
        except ConversionError as exc:
            self.warn_throttled(f'camera/image_raw/compressed: {exc}, dropped')
            return
        if arr.dtype != np.uint8:
            self.warn_throttled('camera/image_raw/compressed: not an 8-bit image, dropped')
            return
        rgb = cv2.cvtColor(arr, cv2.COLOR_GRAY2RGB) if arr.ndim == 2 else cv2.cvtColor(arr[:, :, :3], cv2.COLOR_BGR2RGB)
        self._on_rgb(stamp_ns(msg.header), rgb, msg.header)

    def _on_rgb(self, t: int, rgb: np.ndarray, header: Any) -> None:
        R = self.pano_cam.get(t)
        if R is None and self.enu_cam is not None and self.enu_pano is not None \
                and abs(self.enu_cam[0] - t) <= self.max_gap_ns:
            R = self.enu_pano.T @ self.enu_cam[1]
        if R is None:
            self.pending[t] = (rgb, header)  # panorama/orientation of this frame may still come
            while len(self.pending) > 5:
                self.pending.pop(next(iter(self.pending)))
            return
        self._draw(t, rgb, header, R)

    def _draw(self, t: int, rgb: np.ndarray, header: Any, R_pano_cam: np.ndarray) -> None:
        if self.K is None:
            self.warn_throttled('ar_view: no camera_info yet, frame not drawn')
            return
        placed = project_labels(self.labels, R_pano_cam, self.K, rgb.shape[:2], self.D, self.model)
        sec, nanosec = divmod(int(t), 1_000_000_000)
        # as CDR bytes (ros.cdr_views): the pixels are not copied into an Image message
        self.pub.publish(image_cdr(sec, nanosec, header.frame_id, draw_labels(rgb, placed, self.text_scale), 'rgb8'))
        self.published += 1


def main(args: list[str] | None = None) -> int:
    return run_node(ArViewNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
