"""keyframe_slam_mapper: PTAM-style monocular keyframe SLAM on a camera phone (Klein & Murray 2009).

Subscribes ``camera/image_raw`` (or ``camera/image_raw/compressed``) paired by stamp with
``camera/camera_info``. Publishes, for every tracked frame, ``slam/pose`` (PoseStamped: the
camera_optical frame in the map frame ``slam_map``, the image's stamp) and, at ``map_rate_hz``
(by image stamps) and whenever a keyframe was added, ``slam/keyframes`` (PoseArray of the
active keyframes), ``slam/map_points`` (PointCloud2 x, y, z float32) and ``slam/path``
(nav_msgs/Path of the tracked poses). The map frame is the first keyframe's camera frame; its
scale is set at initialisation (the initial plane at depth 1, sec. 5.1).

The algorithm is :mod:`ar_tracking.core.slam`; tracking runs in the callback, bundle adjustment
in the core's background thread. In a lockstep graph run the node waits for the mapping thread
to go idle *after* it has published the frame's outputs, so runs are reproducible; tracking
itself never waits on mapping.

Bad input (DESIGN sec. 7): an image with no camera_info, of another size than camera_info says,
with an unknown encoding, a zero or backward stamp is dropped with a throttled warning; a
camera_info that changes once the map exists is ignored (the map stays consistent with the
intrinsics it was built with); textureless frames and pure rotation at start are reported by the
tracker (lost / waiting) and never touch the map. A distorted camera (non-zero ``d``) is
undistorted before tracking.
"""
from __future__ import annotations

from typing import Any

import numpy as np
from geometry_msgs.msg import Pose, PoseArray, PoseStamped
from nav_msgs.msg import Path
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2, PointField

from ..core.rectification import RectificationError, check_distortion
from ..core.slam.camera import Rectifier, camera_in_world
from ..core.slam.system import SlamConfig, SlamSystem
from ..core.stamp_pairing import NearestStampPairer
from ..ros.cdr_views import camera_info_view
from ..ros.conversions import ConversionError, compressed_to_gray_u8, image_to_gray_u8, set_quaternion, stamp_ns, to_stamp
from ..ros.node_base import LATCHED_QOS, RELIABLE_QOS, SENSOR_QOS, TrackingNode, run_node
from ..ros.param_table import ParamSpec, declare_params, frame_name
from ..ros.stamp_guard import StampGuard, StampVerdict
from ..ros.tf import TfBroadcaster, transform_stamped

Info = tuple[np.ndarray, np.ndarray, str, tuple[int, int]]  # K, D, distortion model, (height, width)


def point_cloud(points_xyz: np.ndarray, frame_id: str, stamp: Any) -> PointCloud2:
    """PointCloud2 with float32 x, y, z fields (unordered, height 1) from an (N, 3) array."""
    pts = np.ascontiguousarray(np.asarray(points_xyz, dtype=np.float32).reshape(-1, 3))
    msg = PointCloud2()
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.height, msg.width = 1, len(pts)
    msg.fields = [PointField(name=n, offset=4 * i, datatype=PointField.FLOAT32, count=1)
                  for i, n in enumerate('xyz')]
    msg.is_bigendian = False
    msg.point_step, msg.row_step = 12, 12 * len(pts)
    msg.is_dense = True
    msg.data = pts.tobytes()
    return msg



def _empty_or_frame_name(v: Any) -> str | None:
    return None if not v else frame_name(v)


#: The node's parameters.
PARAMS = (
    ParamSpec('readout_s', 0.0,
              'Rolling-shutter readout time, top to bottom row, s (0: global shutter; sec. 6)',
              min_value=0.0, max_value=0.2, read_only=True),
    ParamSpec('map_frame_id', 'slam_map',
              'frame_id of the outputs (the map frame: the first keyframe, scale set at initialisation; the TF '
              'parent)', validate=frame_name),
    ParamSpec('camera_frame_id', '',
              'TF child frame: the camera (empty: the image header frame_id, else camera_optical)',
              validate=_empty_or_frame_name),
    ParamSpec('publish_tf', True, 'Broadcast each tracked pose on /tf (map_frame_id -> camera frame)'),
    ParamSpec('map_rate_hz', 1.0,
              'Rate of slam/map_points, slam/keyframes and slam/path, by image stamps (also published at each new '
              'keyframe), Hz', min_value=0.01, max_value=100.0, read_only=True),
    ParamSpec('camera_info_max_gap_s', 0.005,
              'Largest stamp difference between an image and the camera_info paired with it, s',
              min_value=0.0, max_value=1.0, read_only=True),
    ParamSpec('reset_after_s', 1.0,
              'An image stamp this much older than the previous one means the clock jumped back (bag loop): start a '
              'new map', min_value=0.0, max_value=3600.0),
)

def _pose(R_w_c: np.ndarray, p_w_c: np.ndarray, target: Pose | None = None) -> Pose:
    pose = Pose() if target is None else target
    pose.position.x, pose.position.y, pose.position.z = (float(v) for v in p_w_c)
    set_quaternion(pose.orientation, R_w_c)
    return pose


class KeyframeSlamMapperNode(TrackingNode):
    INPUTS = {
        'camera/image_raw': 'sensor_msgs/msg/Image',
        'camera/image_raw/compressed': 'sensor_msgs/msg/CompressedImage',
        'camera/camera_info': 'sensor_msgs/msg/CameraInfo',
    }
    OUTPUTS = {
        'slam/pose': 'geometry_msgs/msg/PoseStamped',
        'slam/map_points': 'sensor_msgs/msg/PointCloud2',
        'slam/keyframes': 'geometry_msgs/msg/PoseArray',
        'slam/path': 'nav_msgs/msg/Path',
    }
    REQUIRED_INPUTS = [('camera/image_raw', 'camera/image_raw/compressed'), 'camera/camera_info']

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('keyframe_slam_mapper', **kwargs)
        v = declare_params(self, PARAMS, live={
            'map_frame_id': self._set_map_frame,
            'camera_frame_id': lambda x: setattr(self, 'camera_frame', x),
            'publish_tf': lambda x: setattr(self, 'publish_tf', x),
            'reset_after_s': lambda x: setattr(self.guard, 'reset_after_ns', int(x * 1e9)),
        })
        self.readout_s = v['readout_s']
        self.frame_id: str = v['map_frame_id']
        self.camera_frame: str = v['camera_frame_id']
        self.publish_tf: bool = v['publish_tf']
        self.map_period_ns = int(1e9 / v['map_rate_hz'])
        self.max_info_gap_ns = int(1e9 * v['camera_info_max_gap_s'])
        reset_s = v['reset_after_s']
        self.config = SlamConfig(readout_s=self.readout_s)

        self.guard = StampGuard(reset_s)
        self.pairer: NearestStampPairer[np.ndarray, Info] = NearestStampPairer(self.max_info_gap_ns)
        self.system: SlamSystem | None = None
        self.info: Info | None = None
        self.rectify: Rectifier | None = None
        self.last_map_pub_ns: int | None = None
        self.path = Path()
        self.path.header.frame_id = self.frame_id
        self.last_state = ''
        self.tracked = 0
        self.frames = 0

        self.pub_pose = self.advertise(PoseStamped, 'slam/pose', RELIABLE_QOS)
        self.pub_points = self.advertise(PointCloud2, 'slam/map_points', LATCHED_QOS)
        self.pub_keyframes = self.advertise(PoseArray, 'slam/keyframes', LATCHED_QOS)
        self.pub_path = self.advertise(Path, 'slam/path', LATCHED_QOS)
        self.tf = TfBroadcaster(self)
        self.image_frame = ''
        if self.publish_tf and not self.tf.available:
            self.get_logger().warning('publish_tf: tf2_msgs is not installed here; no TF is published')
        self.subscribe(Image, 'camera/image_raw', self.on_image, SENSOR_QOS)
        self.subscribe(CompressedImage, 'camera/image_raw/compressed', self.on_compressed, SENSOR_QOS)
        self.subscribe(CameraInfo, 'camera/camera_info', self.on_camera_info, SENSOR_QOS, view=camera_info_view)
        self.get_logger().info(f'keyframe_slam_mapper: map frame {self.frame_id}, rolling-shutter readout {self.readout_s * 1e3:.1f} ms')
        if self.readout_s == 0.0:  # a phone camera unmodelled costs ~20 % of the accuracy (issue 20)
            self.get_logger().info(
                'readout_s is 0 (global shutter assumed); for a rolling-shutter camera (most phones) set its '
                'readout time, e.g. 30 ms: -p readout_s:=0.03, or in a params file '
                'keyframe_slam_mapper: {ros__parameters: {readout_s: 0.03}}')

    # -- inputs ----------------------------------------------------------------------------

    def on_image(self, msg: Image) -> None:
        try:
            gray = image_to_gray_u8(msg)
        except ConversionError as exc:
            self.warn_throttled(f'camera/image_raw: {exc}; frame dropped')
            return
        self.image_frame = msg.header.frame_id.lstrip('/')
        self._on_frame(stamp_ns(msg.header), gray)

    def on_compressed(self, msg: CompressedImage) -> None:
        try:
            arr = compressed_to_gray_u8(msg)
        except ConversionError as exc:
            self.warn_throttled(f'camera/image_raw/compressed: {exc}; frame dropped')
            return
        self.image_frame = msg.header.frame_id.lstrip('/')
        self._on_frame(stamp_ns(msg.header), arr)

    def on_camera_info(self, msg: CameraInfo) -> None:
        K = np.asarray(msg.k, float).reshape(3, 3)
        try:
            D = check_distortion(msg.d, str(msg.distortion_model))
        except RectificationError:
            D = None
        if (D is None or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0
                or K[2, 2] != 1.0 or msg.width <= 0 or msg.height <= 0):
            self.warn_throttled('camera/camera_info: invalid K, distortion or size; ignored')
            return
        calibration = (K, D, str(msg.distortion_model), (int(msg.height), int(msg.width)))  # 'equidistant': fisheye
        for t, gray, info in self.pairer.add_secondary(stamp_ns(msg.header), calibration):
            self._handle(t, gray, info)

    def _on_frame(self, t: int, gray: np.ndarray) -> None:
        verdict = self.guard.check(t)
        if verdict is StampVerdict.RESET:
            self.get_logger().warning('camera: clock jumped back (bag loop?), starting a new map')
            self._reset()
        elif verdict is not StampVerdict.OK:
            self.warn_throttled(f'camera: {verdict.value}; frame dropped')
            return
        for t_, gray_, info in self.pairer.add_primary(t, gray):
            self._handle(t_, gray_, info)

    # -- processing ------------------------------------------------------------------------

    def _reset(self) -> None:
        if self.system is not None:
            self.system.close()
        self.system = None
        self.info = None
        self.rectify = None
        self.pairer.reset()
        self.last_map_pub_ns = None
        self.path = Path()
        self.path.header.frame_id = self.frame_id

    def _start_or_check(self, info: Info) -> None:
        """Builds the SLAM system on the first camera_info; afterwards warns if it changed (the
        map keeps the intrinsics it was built with)."""
        K, D, model, (h, w) = info
        if self.info is None:
            self.rectify = Rectifier.from_calibration(K, D, w, h, self.readout_s, model)
            self.system = SlamSystem(self.rectify.camera, self.config)
            self.info = info
            return
        K0, D0, _model0, size0 = self.info
        if size0 != (h, w) or not np.allclose(K0, K, rtol=1e-6, atol=1e-6) \
                or not np.array_equal(np.trim_zeros(D0, 'b'), np.trim_zeros(D, 'b')):
            self.warn_throttled('camera/camera_info changed while the map exists; the new intrinsics are ignored')

    def _handle(self, t: int, gray: np.ndarray, info: Info | None) -> None:
        self.frames += 1
        if info is None:
            self.warn_throttled('camera: no camera_info with the image stamp; frame skipped (tracking reports lost)')
            return
        K, D, _model, (h, w) = info
        if gray.shape != (h, w):
            self.warn_throttled(f'camera: frame is {gray.shape[1]}x{gray.shape[0]} but camera_info says {w}x{h}; frame skipped')
            return
        self._start_or_check(info)
        assert self.system is not None and self.rectify is not None
        if gray.shape != (self.system.camera.height, self.system.camera.width):
            self.warn_throttled('camera: frame size differs from the map camera; frame skipped')
            return
        res = self.system.process(self.rectify(gray), t)
        if res.state != self.last_state:
            text = res.message if res.message.startswith(res.state) else f'{res.state}: {res.message}'
            self.get_logger().info(f'slam: {text}')
            self.last_state = res.state
        stamp = to_stamp(t)
        if res.R_c_w is not None and res.t_c_w is not None:
            R_w_c, p_w_c = camera_in_world(res.R_c_w, res.t_c_w)
            out = PoseStamped()
            out.header.stamp = stamp
            out.header.frame_id = self.frame_id
            _pose(R_w_c, p_w_c, out.pose)
            self.pub_pose.publish(out)
            if self.publish_tf and self.tf.listened:
                self.tf.send(transform_stamped(t, self.frame_id, self.camera_frame or self.image_frame or 'camera_optical', R_w_c, p_w_c))
            self.path.poses.append(out)
            if len(self.path.poses) > self.config.max_path:
                # Same bound as SlamSystem.path: drop the oldest tenth at once (amortised).
                del self.path.poses[: len(self.path.poses) // 10]
            self.tracked += 1
        elif res.state == 'lost' and res.message:
            self.warn_throttled(f'slam lost: {res.message}')
        if self.lockstep_hooks is not None:
            # Reproducible lockstep runs: the map is read (and the next frame tracked) only once
            # the mapping thread has taken this frame's keyframe in and finished its bundle
            # adjustment, never half-way through it (live tracking never waits).
            self.system.wait_for_mapping()
        if res.keyframe_added or self.last_map_pub_ns is None or t - self.last_map_pub_ns >= self.map_period_ns:
            self._publish_map(t)

    def _publish_map(self, t: int) -> None:
        assert self.system is not None
        self.last_map_pub_ns = t
        stamp = to_stamp(t)
        kfs = PoseArray()
        kfs.header.stamp = stamp
        kfs.header.frame_id = self.frame_id
        kfs.poses = [_pose(R_w_c, p_w_c) for _, R_w_c, p_w_c in self.system.keyframe_poses()]
        self.pub_keyframes.publish(kfs)
        self.pub_points.publish(point_cloud(self.system.map_points(), self.frame_id, stamp))
        self.path.header.stamp = stamp
        self.pub_path.publish(self.path)

    def _set_map_frame(self, value: str) -> None:
        self.frame_id = value
        self.path.header.frame_id = value

    def destroy_node(self) -> None:
        if self.system is not None:
            self.system.close()
            self.system = None
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return run_node(KeyframeSlamMapperNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
