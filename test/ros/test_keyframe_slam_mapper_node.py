"""keyframe_slam_mapper in-process: handheld_desk frames in, slam/* out; bad input (DESIGN sec. 7)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

from geometry_msgs.msg import PoseArray, PoseStamped  # noqa: E402
from nav_msgs.msg import Path  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image, PointCloud2  # noqa: E402

from ar_tracking.nodes.keyframe_slam_mapper import KeyframeSlamMapperNode  # noqa: E402
from ar_tracking.ros.conversions import array_to_image, stamp_ns, to_stamp  # noqa: E402
from ar_tracking.sim import handheld_desk  # noqa: E402
from conftest import spin_until  # noqa: E402

T0 = 1_700_000_000_000_000_000
W, H = 320, 240


@pytest.fixture(scope='module')
def desk_frames():
    """3.5 s of the handheld_desk scenario at 320x240 (initialisation needs ~2 s of sideways motion)."""
    return list(handheld_desk.frames(0, 3.5, W, H))


@pytest.fixture(scope='module')
def rotation_frames():
    return list(handheld_desk.frames(0, 2.0, W, H, pure_rotation_start=True))


class Harness:
    def __init__(self, context, params=None):
        cam = handheld_desk.desk_camera(W, H)
        params = {'readout_s': cam.readout_s, **(params or {})}
        self.K = cam.K
        self.node = KeyframeSlamMapperNode(context=context, parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])
        self.src = rclpy.create_node('slam_test_source', context=context)
        self.poses: list[PoseStamped] = []
        self.keyframes: list[PoseArray] = []
        self.points: list[PointCloud2] = []
        self.paths: list[Path] = []
        self.src.create_subscription(PoseStamped, 'slam/pose', self.poses.append, 100)
        self.src.create_subscription(PoseArray, 'slam/keyframes', self.keyframes.append, 100)
        self.src.create_subscription(PointCloud2, 'slam/map_points', self.points.append, 100)
        self.src.create_subscription(Path, 'slam/path', self.paths.append, 100)
        self.pub_img = self.src.create_publisher(Image, 'camera/image_raw', 10)
        self.pub_info = self.src.create_publisher(CameraInfo, 'camera/camera_info', 10)
        self.ex = SingleThreadedExecutor(context=context)
        self.ex.add_node(self.node)
        self.ex.add_node(self.src)
        assert spin_until(self.ex, lambda: self.pub_img.get_subscription_count() > 0 and self.pub_info.get_subscription_count() > 0
                          and self.node.pub_pose.get_subscription_count() > 0)
        self.n_info = 0
        self.n_img = 0

    def info(self, t_ns: int, K=None, width=W, height=H, d=(0.0,) * 5, model='plumb_bob'):
        m = CameraInfo()
        m.header.stamp = to_stamp(t_ns)
        m.header.frame_id = 'camera_optical'
        m.width, m.height = width, height
        m.k = [float(x) for x in (self.K if K is None else K).ravel()]
        m.d = [float(x) for x in d]
        m.distortion_model = model
        self.pub_info.publish(m)
        spin_until(self.ex, lambda: len(self.node.callback_stats['camera/camera_info'].durations_ms) > self.n_info, 2.0)
        self.n_info += 1

    def image(self, img, t_ns: int, encoding='mono8'):
        m = array_to_image(img, 'mono8')
        m.encoding = encoding
        m.header.stamp = to_stamp(t_ns)
        m.header.frame_id = 'camera_optical'
        self.pub_img.publish(m)
        spin_until(self.ex, lambda: len(self.node.callback_stats['camera/image_raw'].durations_ms) > self.n_img, 5.0)
        self.n_img += 1

    def frame(self, img, t_ns: int, **info):
        self.info(t_ns, **info)
        self.image(img, t_ns)

    def settle(self, s=0.2):
        spin_until(self.ex, lambda: False, s)

    def close(self):
        self.ex.shutdown()
        self.node.destroy_node()
        self.src.destroy_node()


def _stamp(f) -> int:
    return T0 + int(f.stamp_ns)


def test_initialises_and_publishes_pose_keyframes_points_and_path(ros_context, desk_frames):
    try:
        from tf2_msgs.msg import TFMessage
    except ImportError:  # tf2_msgs not built: everything but the TF checks
        TFMessage = None

    h = Harness(ros_context)
    tf_msgs: list = []
    if TFMessage is not None:
        h.src.create_subscription(TFMessage, '/tf', tf_msgs.append, 500)
    # A small bound on the path (default 100000 poses) to see it dropping the oldest poses.
    h.node.config = dataclasses.replace(h.node.config, max_path=12)
    try:
        for f in desk_frames:
            h.frame(f.image, _stamp(f))
        h.settle()
        # /tf: slam_map -> the image's frame with every pose (same stamp, same position)
        if TFMessage is not None:
            assert spin_until(h.ex, lambda: len(tf_msgs) >= len(h.poses), 5.0)
            last = tf_msgs[-1].transforms[0]
            assert (last.header.frame_id, last.child_frame_id) == ('slam_map', 'camera_optical')
            assert last.header.stamp == h.poses[-1].header.stamp
            assert last.transform.translation.x == pytest.approx(h.poses[-1].pose.position.x)
        assert h.node.set_parameters([Parameter('map_frame_id', value='desk')])[0].successful
        assert h.node.path.header.frame_id == 'desk'
        assert not h.node.set_parameters([Parameter('readout_s', value=0.01)])[0].successful
        assert len(h.poses) >= 10, h.node.last_state
        assert all(p.header.frame_id == 'slam_map' for p in h.poses)
        stamps = {_stamp(f) for f in desk_frames}
        assert all(stamp_ns(p.header) in stamps for p in h.poses)
        q = h.poses[-1].pose.orientation
        assert abs(q.x ** 2 + q.y ** 2 + q.z ** 2 + q.w ** 2 - 1) < 1e-6
        assert h.keyframes and len(h.keyframes[-1].poses) >= 2
        assert h.points and h.points[-1].width >= 20 and len(h.points[-1].data) == 12 * h.points[-1].width
        xyz = np.frombuffer(bytes(h.points[-1].data), np.float32).reshape(-1, 3)
        assert np.all(np.isfinite(xyz))
        assert h.paths and 0 < len(h.paths[-1].poses) <= 12 < len(h.poses)
        kept = [stamp_ns(m.header) for m in h.node.path.poses]
        assert len(kept) <= 12 and kept == [stamp_ns(m.header) for m in h.poses[-len(kept):]]
        # The camera moves sideways at the start: the tracked positions must move too.
        p = np.array([[m.pose.position.x, m.pose.position.y, m.pose.position.z] for m in h.poses])
        assert np.ptp(p, axis=0).max() > 0.02
    finally:
        h.close()


def test_bad_input_is_dropped_and_the_map_survives(ros_context, desk_frames):
    h = Harness(ros_context)
    try:
        f0 = desk_frames[0]
        h.image(f0.image, _stamp(f0))                      # no camera_info with this stamp
        h.frame(np.zeros((H // 2, W // 2), np.uint8), _stamp(f0) + 1000)  # size differs from camera_info
        h.info(_stamp(f0) + 2000)
        h.image(f0.image, _stamp(f0) + 2000, encoding='yuv_unknown')  # unsupported encoding
        assert h.node.frames == 2  # the two frames that had a camera_info; the last was dropped before
        h.info(_stamp(f0) + 3000, d=[0.1] * 5, model='equidistant')  # the fisheye model takes 4: ignored
        h.image(f0.image, _stamp(f0) + 3000)
        assert h.node.frames == 2  # no usable camera_info with its stamp: dropped
        assert h.node.system is None or len(h.node.system.map.keyframes) == 0
        for f in desk_frames:
            h.frame(f.image, _stamp(f))
        h.settle()
        n_poses = len(h.poses)
        assert n_poses >= 10
        kf_before = len(h.node.system.map.keyframes)
        points_before = len(h.node.system.map.points)
        t = _stamp(desk_frames[-1])
        # Textureless frames (a white wall): no pose, no keyframe, the map keeps its points.
        for _ in range(5):
            t += 50_000_000
            h.frame(np.full((H, W), 255, np.uint8), t)
        h.settle()
        assert len(h.poses) == n_poses
        assert len(h.node.system.map.keyframes) == kf_before
        assert len(h.node.system.map.points) >= points_before // 2
        # A camera_info that changes once the map exists is ignored: frames are still tracked.
        K2 = h.K.copy()
        K2[0, 0] *= 1.5
        last = desk_frames[-1]
        h.frame(last.image, t + 50_000_000, K=K2)
        assert h.node.system.camera.fx == pytest.approx(h.K[0, 0])
        # Zero and backward stamps are dropped.
        before = h.node.frames
        h.image(last.image, 0)
        h.image(last.image, t - 10_000_000)
        assert h.node.frames == before
    finally:
        h.close()


def test_pure_rotation_at_start_waits_for_sideways_motion(ros_context, rotation_frames):
    h = Harness(ros_context)
    try:
        for f in rotation_frames:
            h.frame(f.image, _stamp(f))
        h.settle()
        assert h.poses == []
        assert h.node.last_state == 'waiting'
    finally:
        h.close()
