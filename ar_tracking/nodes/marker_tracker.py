"""marker_tracker: camera pose from square fiducial markers on a known layout (Caarls 2009 sec. 2.4).

Subscribes ``camera/image_raw`` (or ``camera/image_raw/compressed``) and ``camera/camera_info``;
publishes ``markers/pose`` (PoseWithCovarianceStamped: the camera_optical frame in the
marker-map frame, stamped with the image's capture stamp) and ``markers/detections``
(MarkerArray: one LINE_STRIP per detected marker whose points are the corner *pixel* coordinates
(x = u, y = v, z = 0) in the image of header.frame_id; ns ``accepted`` or ``rejected``, the
reason in ``text``).

The marker map comes from ``marker_map_file`` (a YAML file) or ``marker_map`` (the same document
inline, as the simulator's sidecar gives it). The lens model is OpenCV's from camera_info, or the
seed's eq. 2 (``lens_model: caarls_eq2`` with ``eq2_k``). Images are paired with camera_info
by stamp: an image whose camera_info has not arrived yet waits (up to ``info_wait_s`` of
stamps, a few frames) instead of being dropped - drivers often publish camera_info just after
the image; without a camera_info of its own stamp an image uses the latest one (intrinsics
are constant for a camera; an image whose size differs is dropped).

Real images (:mod:`ar_tracking.core.markers.detection`): the edge model runs on the image
mapped back to light with the camera's display gamma (``response_gamma``; 0 estimates it from
the markers - from their black and white levels with ``marker_print_contrast``, the printed
white/black reflectance ratio, or from the symmetry of their edges without it); each corner
carries a sigma that grows with blur, poor line fits and occlusion, and the pose covariance
follows, so that the visual-inertial filter can weigh or reject a pose.
"""
from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np
from geometry_msgs.msg import Point, PoseWithCovarianceStamped
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from visualization_msgs.msg import Marker, MarkerArray

from ..core.markers import MarkerError
from ..core.markers.detection import REFINEMENTS, MarkerDetector
from ..core.markers.lens_model import LENS_KINDS, LensModel
from ..core.markers.pose import MarkerMap, estimate_camera_pose
from ..ros.cdr_views import camera_info_view
from ..ros.conversions import (
    ConversionError,
    compressed_to_gray_u8,
    image_to_gray_u8,
    set_quaternion,
    stamp_ns,
)
from ..ros.node_base import RELIABLE_QOS, SENSOR_QOS, TrackingNode, run_node
from ..ros.param_table import ParamSpec, declare_params, length_is, one_of
from ..ros.stamp_guard import StampGuard, StampVerdict
from ..ros.tf import TfBroadcaster, transform_stamped


def _gamma_ok(v: Any) -> str | None:
    return None if v == 0.0 or v >= 0.2 else 'use 0 (estimate) or a gamma of 0.2-5'


def _contrast_ok(v: Any) -> str | None:
    return None if v == 0.0 or v > 1.0 else 'use 0 (unknown) or a ratio above 1'


#: The node's parameters.
PARAMS = (
    ParamSpec('dictionary', 'DICT_APRILTAG_36h11',
              'OpenCV ArUco/AprilTag dictionary of the markers (cv2.aruco.DICT_*)', read_only=True),
    ParamSpec('corner_refinement', 'caarls',
              'Corner refinement: caarls (edge model + line fit, Caarls 2009 sec. 2.4), subpix (OpenCV '
              'CORNER_REFINE_SUBPIX) or none', read_only=True, validate=one_of(REFINEMENTS, 'use one of')),
    ParamSpec('lens_model', 'opencv',
              'Lens model: opencv (camera_info distortion) or caarls_eq2 (eq. 2 with eq2_k)',
              read_only=True, validate=one_of(LENS_KINDS, 'use one of')),
    ParamSpec('eq2_k', [0.0, 0.0, 0.0],
              'k1, k2, k3 of the eq. 2 lens model on the normalised image plane',
              validate=length_is(3)),
    ParamSpec('marker_map_file', '',
              'YAML marker map: frame_id, markers [{id, size_m, position, orientation_xyzw}]', read_only=True),
    ParamSpec('marker_map', '',
              'The marker map inline (same YAML document as marker_map_file); used when marker_map_file is empty',
              read_only=True),
    ParamSpec('corner_sigma_px', 0.06,
              'Corner noise 1-sigma of a sharp, fully seen marker (the floor of every corner sigma), px',
              min_value=1e-4, max_value=10.0),
    ParamSpec('response_gamma', 0.0,
              "Camera's display gamma, undone before the edge fit (1: linear images; 0: estimated from the markers)",
              min_value=0.0, max_value=5.0, read_only=True, validate=_gamma_ok),
    ParamSpec('marker_print_contrast', 0.0,
              'White/black reflectance ratio of the printed markers, for the gamma estimate from their levels (0: '
              'unknown, estimate from edge symmetry)',
              min_value=0.0, max_value=1000.0, read_only=True, validate=_contrast_ok),
    ParamSpec('blur_sigma_gain', 0.25,
              'Corner sigma added per px of edge blur beyond 1 px', min_value=0.0, max_value=10.0, read_only=True),
    ParamSpec('info_wait_s', 0.2,
              'How long (in image stamps) an image waits for the camera_info of its stamp before the latest one is '
              'used, s', min_value=0.0, max_value=5.0),
    ParamSpec('min_corner_angle_deg', 25.0,
              'A quad with an interior angle below this (or above 180 minus this) is seen edge-on: rejected',
              min_value=0.0, max_value=89.99, read_only=True),
    ParamSpec('min_side_px', 12.0,
              'Markers with a side shorter than this are rejected, px',
              min_value=4.0, max_value=1000.0, read_only=True),
    ParamSpec('max_position_sigma_m', 0.5,
              'Poses whose position 1-sigma exceeds this are not published, m', min_value=1e-4, max_value=100.0),
    ParamSpec('map_frame_id', '', 'Frame of markers/pose (empty: the marker map frame_id)'),
    ParamSpec('reset_after_s', 1.0,
              'A stamp this much older than the previous one means the clock jumped back (bag loop): reset',
              min_value=0.0, max_value=3600.0),
    ParamSpec('publish_tf', True, 'Broadcast each markers/pose on /tf (map frame -> the image frame_id)'),
)


class MarkerTrackerNode(TrackingNode):
    INPUTS = {
        'camera/image_raw': 'sensor_msgs/msg/Image',
        'camera/image_raw/compressed': 'sensor_msgs/msg/CompressedImage',
        'camera/camera_info': 'sensor_msgs/msg/CameraInfo',
    }
    OUTPUTS = {
        'markers/pose': 'geometry_msgs/msg/PoseWithCovarianceStamped',
        'markers/detections': 'visualization_msgs/msg/MarkerArray',
    }
    REQUIRED_INPUTS = [('camera/image_raw', 'camera/image_raw/compressed'), 'camera/camera_info']
    #: The graph runner starts this node only with a marker map (without one it can do nothing).
    REQUIRED_PARAMS = [('marker_map_file', 'marker_map')]

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('marker_tracker', **kwargs)
        v = declare_params(self, PARAMS, live={'publish_tf': lambda x: setattr(self, 'publish_tf', x)})
        dictionary = v['dictionary']
        refinement = v['corner_refinement']
        self.lens_kind = v['lens_model']
        self.eq2_k = np.asarray(v['eq2_k'], float)
        map_file = v['marker_map_file']
        map_text = v['marker_map']
        self.corner_sigma_px = v['corner_sigma_px']
        gamma = v['response_gamma']
        contrast = v['marker_print_contrast']
        blur_gain = v['blur_sigma_gain']
        self.info_wait_ns = int(1e9 * v['info_wait_s'])
        min_angle = v['min_corner_angle_deg']
        min_side = v['min_side_px']
        self.max_position_sigma_m = v['max_position_sigma_m']
        self.map_frame_id = v['map_frame_id']
        reset_s = v['reset_after_s']
        # TF: the map -> camera (the image frame) with every published pose; live switch.
        self.publish_tf: bool = v['publish_tf']
        self.tf = TfBroadcaster(self)

        try:
            if map_file:
                self.marker_map = MarkerMap.from_yaml(map_file)
            elif map_text:
                self.marker_map = MarkerMap.from_text(map_text, 'marker_map parameter')
            else:
                self.marker_map = MarkerMap('enu', {})
            self.detector = MarkerDetector(dictionary, refinement, min_angle, min_side, response_gamma=gamma,
                                           corner_sigma_px=self.corner_sigma_px, blur_sigma_gain=blur_gain,
                                           print_contrast=contrast)
        except MarkerError as exc:
            raise ValueError(str(exc)) from exc
        if not self.marker_map.markers:
            self.get_logger().warning('marker map is empty: markers are detected but no pose is published')
        self.frame = self.map_frame_id or self.marker_map.frame_id
        self.lens: LensModel | None = None
        self.image_size: tuple[int, int] | None = None
        self._lens_key: tuple | None = None
        self.guard = StampGuard(reset_s)
        self.poses_published = 0
        #: camera_info stamps seen recently (to pair images with their own) and images waiting
        self._info_stamps: deque[int] = deque(maxlen=64)
        self._waiting: deque[tuple[int, np.ndarray, Any]] = deque()
        self._info_per_frame = False

        self.pub_pose = self.advertise(PoseWithCovarianceStamped, 'markers/pose', RELIABLE_QOS)
        self.pub_det = self.advertise(MarkerArray, 'markers/detections', RELIABLE_QOS)
        self.subscribe(CameraInfo, 'camera/camera_info', self.on_info, SENSOR_QOS, view=camera_info_view)
        self.subscribe(Image, 'camera/image_raw', self.on_image, SENSOR_QOS)
        self.subscribe(CompressedImage, 'camera/image_raw/compressed', self.on_compressed, SENSOR_QOS)
        self.get_logger().info(f'marker_tracker: {len(self.marker_map.markers)} markers in the map ({dictionary}, corners: {refinement})')

    # -- callbacks -------------------------------------------------------------------------

    def on_info(self, msg: CameraInfo) -> None:
        self._take_info(msg)
        t = stamp_ns(msg.header)
        self._info_stamps.append(t)
        if any(w[0] == t for w in self._waiting):
            self._info_per_frame = True  # this camera stamps camera_info like its images
        self._release(lambda w: w[0] <= t)

    def _release(self, ready: Any) -> None:
        """Process the waiting images, oldest first, while ``ready(entry)`` holds."""
        while self._waiting and ready(self._waiting[0]):
            _, gray, header = self._waiting.popleft()
            self._detect(gray, header)

    def _take_info(self, msg: CameraInfo) -> None:
        K = np.asarray(msg.k, dtype=float).reshape(3, 3)
        D = np.asarray(msg.d, dtype=float)
        key = (tuple(K.ravel()), tuple(D), int(msg.width), int(msg.height))
        if key == self._lens_key:
            return
        if not (np.all(np.isfinite(K)) and np.all(np.isfinite(D))) or msg.width == 0 or msg.height == 0:
            self.warn_throttled('camera_info has non-finite values or no size; ignored')
            return
        if self.lens_kind == 'opencv' and len(D) not in (0, 4, 5, 8, 12, 14):
            self.warn_throttled(f'camera_info has {len(D)} distortion coefficients; ignored')
            return
        try:
            self.lens = LensModel(K, self.lens_kind, D if len(D) else np.zeros(5), self.eq2_k)
        except MarkerError as exc:
            self.warn_throttled(f'camera_info unusable: {exc}')
            return
        self.image_size = (int(msg.width), int(msg.height))
        self._lens_key = key

    def on_image(self, msg: Image) -> None:
        try:
            gray = image_to_gray_u8(msg)
        except ConversionError as exc:
            self.warn_throttled(f'camera/image_raw: {exc}; dropped')
            return
        self._process(gray, msg.header)

    def on_compressed(self, msg: CompressedImage) -> None:
        try:
            arr = compressed_to_gray_u8(msg)
        except ConversionError as exc:
            self.warn_throttled(f'camera/image_raw/compressed: {exc}; dropped')
            return
        self._process(arr, msg.header)

    def _process(self, gray: np.ndarray, header: Any) -> None:
        verdict = self.guard.check(stamp_ns(header))
        if verdict is StampVerdict.RESET:
            self.get_logger().warning('camera: clock jumped back (bag loop?), starting over')
        elif verdict is not StampVerdict.OK:
            self.warn_throttled(f'camera: {verdict.value}; image dropped')
            return
        t = stamp_ns(header)
        if verdict is StampVerdict.RESET:
            self._waiting.clear()
        # Images older than the wait are released with the latest camera_info.
        self._release(lambda w: t - w[0] >= self.info_wait_ns)
        if t in self._info_stamps or (self.lens is not None and not self._info_per_frame):
            self._release(lambda w: True)
            self._detect(gray, header)
            return
        # Wait for the camera_info of this stamp (drivers often publish it just after the image).
        self._waiting.append((t, gray, header))

    def _detect(self, gray: np.ndarray, header: Any) -> None:
        if self.lens is None or self.image_size is None:
            self.warn_throttled('no camera_info received for this image (waited info_wait_s); image dropped')
            return
        if (gray.shape[1], gray.shape[0]) != self.image_size:
            self.warn_throttled(f'image is {gray.shape[1]}x{gray.shape[0]} but camera_info says {self.image_size[0]}x{self.image_size[1]}; dropped')
            return
        known = self.marker_map.ids
        accepted, rejected = self.detector.detect(gray, self.lens, known)
        for r in rejected:
            self.warn_throttled(f'marker {r.id} rejected: {r.reason}')
        self._publish_detections(header, accepted, rejected)
        if not accepted:
            return
        est = estimate_camera_pose(accepted, self.marker_map, self.lens.focal_px, self.corner_sigma_px)
        if est is None:
            self.warn_throttled('no valid pose from the visible markers')
            return
        sigma = float(np.sqrt(max(np.max(np.diag(est.cov)[:3]), 0.0)))
        if sigma > self.max_position_sigma_m:
            self.warn_throttled(f'pose too uncertain (position sigma {sigma:.3g} m); not published')
            return
        out = PoseWithCovarianceStamped()
        out.header.stamp = header.stamp
        out.header.frame_id = self.frame
        pos = out.pose.pose.position
        pos.x, pos.y, pos.z = (float(v) for v in est.p_map_cam)
        set_quaternion(out.pose.pose.orientation, est.R_map_cam)
        out.pose.covariance = [float(v) for v in est.cov.ravel()]
        self.pub_pose.publish(out)
        self.poses_published += 1
        if self.publish_tf and self.tf.listened:
            self.tf.send(transform_stamped(stamp_ns(header), self.frame, header.frame_id.lstrip('/') or 'camera_optical',
                                           est.R_map_cam, est.p_map_cam))

    def _publish_detections(self, header: Any, accepted: list, rejected: list) -> None:
        arr = MarkerArray()
        for ns, items in (('accepted', accepted), ('rejected', rejected)):
            for item in items:
                m = Marker()
                m.header.stamp = header.stamp
                m.header.frame_id = header.frame_id
                m.ns = ns
                m.id = int(item.id)
                m.type = Marker.LINE_STRIP
                m.action = Marker.ADD
                m.pose.orientation.w = 1.0
                m.scale.x = 1.0
                m.color.a = 1.0
                m.color.g = 1.0 if ns == 'accepted' else 0.0
                m.color.r = 0.0 if ns == 'accepted' else 1.0
                m.text = getattr(item, 'reason', '')
                pts = item.corners_px
                m.points = [Point(x=float(u), y=float(v), z=0.0) for u, v in list(pts) + [pts[0]]]
                arr.markers.append(m)
        self.pub_det.publish(arr)


def main(args: list[str] | None = None) -> int:
    return run_node(MarkerTrackerNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
