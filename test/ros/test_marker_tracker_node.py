"""marker_tracker in-process: rendered markers in, markers/pose + detections out; bad input."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

rclpy = pytest.importorskip('rclpy')

from geometry_msgs.msg import PoseWithCovarianceStamped  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image  # noqa: E402
from visualization_msgs.msg import MarkerArray  # noqa: E402

from ar_tracking.nodes.marker_tracker import MarkerTrackerNode  # noqa: E402
from ar_tracking.ros.conversions import array_to_image, stamp_ns, to_stamp  # noqa: E402
from ar_tracking.sim import robot_arcs as ra  # noqa: E402
from conftest import spin_until  # noqa: E402

T0 = 1_700_000_000_000_000_000
CONFIG = Path(__file__).resolve().parents[2] / 'config' / 'marker_tracker.yaml'


def _frame(t_s: float, seed: int = 0):
    cam = ra.Camera()
    tr = ra.truth_at(ra.ArcSchedule.make(10.0), np.array([t_s]))
    mapped, unknown = ra.wall_markers()
    img, _ = ra.render_frame(cam, tr.R_enu_cam[0], tr.position[0], mapped + unknown, np.random.default_rng(seed))
    return img, tr


class Harness:
    def __init__(self, context, params=None):
        inline = yaml.safe_dump(ra.marker_map_doc(ra.wall_markers()[0]), default_flow_style=True)
        params = {'marker_map': inline, **(params or {})}
        self.node = MarkerTrackerNode(context=context, parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])
        self.src = rclpy.create_node('mt_test_source', context=context)
        self.poses: list[PoseWithCovarianceStamped] = []
        self.dets: list[MarkerArray] = []
        self.src.create_subscription(PoseWithCovarianceStamped, 'markers/pose', self.poses.append, 50)
        self.src.create_subscription(MarkerArray, 'markers/detections', self.dets.append, 50)
        self.pub_img = self.src.create_publisher(Image, 'camera/image_raw', 10)
        self.pub_info = self.src.create_publisher(CameraInfo, 'camera/camera_info', 10)
        self.ex = SingleThreadedExecutor(context=context)
        self.ex.add_node(self.node)
        self.ex.add_node(self.src)
        assert spin_until(self.ex, lambda: self.pub_img.get_subscription_count() > 0 and self.pub_info.get_subscription_count() > 0
                          and self.node.pub_pose.get_subscription_count() > 0 and self.node.pub_det.get_subscription_count() > 0)

    def info(self, width=640, height=480, stamp_ns=0):
        m = CameraInfo()
        m.header.stamp = to_stamp(stamp_ns)
        m.header.frame_id = 'camera_optical'
        m.width, m.height = width, height
        m.k = [float(x) for x in ra.Camera().K.ravel()]
        m.d = [0.0] * 5
        m.distortion_model = 'plumb_bob'
        self.pub_info.publish(m)
        spin_until(self.ex, lambda: len(self.node.callback_stats['camera/camera_info'].durations_ms) > self.n_info, 2.0)
        self.n_info += 1

    n_info = 0
    n_img = 0

    def image(self, img, t_ns):
        m = array_to_image(img, 'mono8')
        m.header.stamp = to_stamp(t_ns)
        m.header.frame_id = 'camera_optical'
        self.pub_img.publish(m)
        spin_until(self.ex, lambda: len(self.node.callback_stats['camera/image_raw'].durations_ms) > self.n_img, 3.0)
        self.n_img += 1
        spin_until(self.ex, lambda: False, 0.05)

    def close(self):
        self.ex.shutdown()
        self.node.destroy_node()
        self.src.destroy_node()


def test_pose_from_markers_and_bad_input(ros_context):
    h = Harness(ros_context)
    try:
        img, tr = _frame(2.0)
        h.image(img, T0)                         # no camera_info yet: waits for one
        assert not h.poses
        h.info()                                 # unstamped camera_info: the latest is used
        h.image(img[:240, :320].copy(), T0 + 1)  # releases the waiting image; this one's size differs: dropped
        assert spin_until(h.ex, lambda: len(h.poses) == 1, 3.0) and stamp_ns(h.poses[0].header) == T0
        h.image(img, T0 + 2)
        assert spin_until(h.ex, lambda: len(h.poses) == 2, 3.0)
        msg = h.poses[1]
        assert stamp_ns(msg.header) == T0 + 2 and msg.header.frame_id == 'enu'
        p = np.array([msg.pose.pose.position.x, msg.pose.pose.position.y, msg.pose.pose.position.z])
        assert np.linalg.norm(p - tr.position[0]) < 0.01
        cov = np.array(msg.pose.covariance).reshape(6, 6)
        assert np.all(np.isfinite(cov)) and np.all(np.linalg.eigvalsh(cov) > 0)
        det = h.dets[-1]
        accepted = sorted(m.id for m in det.markers if m.ns == 'accepted')
        rejected = [(m.id, m.text) for m in det.markers if m.ns == 'rejected']
        assert accepted == [0, 1, 2, 3]
        assert rejected == [(17, 'ID not in the marker map')]   # unknown ID
        h.image(img, T0 + 1)                     # stamp going back: dropped
        assert len(h.poses) == 2
        bad = Image()
        bad.header.stamp = to_stamp(T0 + 5)
        bad.encoding, bad.width, bad.height, bad.step = 'mono8', 640, 480, 640
        bad.data = bytes(10)                      # truncated
        h.pub_img.publish(bad)
        spin_until(h.ex, lambda: False, 0.1)
        assert len(h.poses) == 2 and h.node.callback_stats['camera/image_raw'].failures == 0
    finally:
        h.close()


def test_image_waits_for_the_camera_info_of_its_stamp(ros_context):
    """A driver that publishes camera_info just after each image: no image is lost, each is
    processed when its camera_info comes; one whose camera_info never comes goes after info_wait_s."""
    h = Harness(ros_context, {'info_wait_s': 0.1})
    try:
        img, _ = _frame(2.0)
        for k in range(3):
            t = T0 + k * 50_000_000
            h.image(img, t)
            assert len(h.poses) == k                  # waiting for its camera_info
            h.info(stamp_ns=t)
            assert spin_until(h.ex, lambda k=k: len(h.poses) == k + 1, 3.0)
            assert stamp_ns(h.poses[-1].header) == t
        h.image(img, T0 + 150_000_000)                # its camera_info is lost
        h.image(img, T0 + 200_000_000)
        assert len(h.poses) == 3
        h.image(img, T0 + 260_000_000)                # 110 ms later: the lost one goes with the latest
        assert spin_until(h.ex, lambda: len(h.poses) == 4, 3.0)
        assert stamp_ns(h.poses[-1].header) == T0 + 150_000_000
    finally:
        h.close()


def test_edge_on_markers_are_rejected(ros_context):
    # With a strict angle limit every (perspective-distorted) marker counts as seen edge-on.
    h = Harness(ros_context, {'min_corner_angle_deg': 89.99})
    try:
        h.info()
        img, _ = _frame(1.0)
        h.image(img, T0 + 10)
        assert spin_until(h.ex, lambda: len(h.dets) >= 1, 2.0)
        assert not h.poses
        reasons = [m.text for m in h.dets[-1].markers if m.ns == 'rejected']
        assert any('edge-on' in r for r in reasons)
    finally:
        h.close()


def test_config_file_matches_declared_defaults(ros_context):
    params = yaml.safe_load(CONFIG.read_text())['marker_tracker']['ros__parameters']
    node = MarkerTrackerNode(context=ros_context)
    try:
        for key, value in params.items():
            assert node.has_parameter(key), key
            declared = node.get_parameter(key).value
            assert (list(declared) == value) if isinstance(value, list) else declared == value, key
            assert node.describe_parameter(key).description
    finally:
        node.destroy_node()
    with pytest.raises(ValueError):
        MarkerTrackerNode(context=ros_context, parameter_overrides=[Parameter('marker_map', value='markers: [{id: 1}]')])


def test_pose_is_broadcast_on_tf(ros_context):
    TFMessage = pytest.importorskip('tf2_msgs.msg', reason='tf2_msgs not built (./ar-tracking.sh builds it)').TFMessage

    h = Harness(ros_context)
    tf_msgs: list = []
    h.src.create_subscription(TFMessage, '/tf', tf_msgs.append, 50)
    try:
        img, tr = _frame(2.0)
        h.info()
        h.image(img, T0)
        assert spin_until(h.ex, lambda: len(h.poses) == 1 and len(tf_msgs) == 1, 3.0)
        tf = tf_msgs[0].transforms[0]
        assert (tf.header.frame_id, tf.child_frame_id) == ('enu', 'camera_optical')
        assert tf.transform.translation.x == pytest.approx(h.poses[0].pose.pose.position.x)
        assert h.node.set_parameters([Parameter('publish_tf', value=False)])[0].successful
        h.image(img, T0 + 1)
        assert spin_until(h.ex, lambda: len(h.poses) == 2, 3.0) and len(tf_msgs) == 1
    finally:
        h.close()
