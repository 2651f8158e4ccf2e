"""ar_view in-process: markers + orientation + image in, overlay out; bad input."""
from __future__ import annotations

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

from geometry_msgs.msg import TransformStamped  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image  # noqa: E402
from visualization_msgs.msg import Marker, MarkerArray  # noqa: E402

from ar_tracking.core.annotations.overlay import COLOURS_RGB  # noqa: E402
from ar_tracking.nodes.ar_view import ArViewNode  # noqa: E402
from ar_tracking.ros.conversions import array_to_image, image_to_array, set_quaternion, to_stamp  # noqa: E402
from ar_tracking.ros.node_base import LATCHED_QOS  # noqa: E402
from conftest import spin_until  # noqa: E402

T0 = 1_700_000_000_000_000_000
K = [300.0, 0.0, 159.5, 0.0, 300.0, 119.5, 0.0, 0.0, 1.0]


def test_overlay_draws_labels_at_their_anchor(ros_context):
    node = ArViewNode(context=ros_context)
    src = rclpy.create_node('src', context=ros_context)
    out: list[Image] = []
    src.create_subscription(Image, 'ar/overlay', out.append, 10)
    pub_img = src.create_publisher(Image, 'camera/image_raw', 10)
    pub_info = src.create_publisher(CameraInfo, 'camera/camera_info', 10)
    pub_mk = src.create_publisher(MarkerArray, 'annotations/markers', LATCHED_QOS)
    pub_or = src.create_publisher(TransformStamped, 'panorama/orientation', 10)
    ex = SingleThreadedExecutor(context=ros_context)
    ex.add_node(node)
    ex.add_node(src)
    assert spin_until(ex, lambda: all(p.get_subscription_count() > 0 for p in (pub_img, pub_info, pub_mk, pub_or)))
    arr = MarkerArray()
    m = Marker()
    m.action, m.ns, m.text = Marker.ADD, 'matched', 'Door'
    m.pose.position.z = 10.0
    bad = Marker()
    bad.action, bad.text = Marker.ADD, 'nan'
    bad.pose.position.x = float('nan')
    arr.markers = [m, bad]
    pub_mk.publish(arr)
    info = CameraInfo()
    info.header.stamp = to_stamp(T0)
    info.width, info.height, info.k = 320, 240, K
    pub_info.publish(info)
    spin_until(ex, lambda: node.K is not None and len(node.labels) == 1, 5.0)
    # Bad image: wrong encoding is dropped.
    f32 = array_to_image(np.zeros((240, 320), np.float32), '32FC1')
    f32.header.stamp = to_stamp(T0)
    pub_img.publish(f32)
    img = array_to_image(np.full((240, 320, 3), 100, np.uint8), 'rgb8')
    img.header.stamp = to_stamp(T0 + 1)
    img.header.frame_id = 'phone_cam_optical'
    pub_img.publish(img)
    tf = TransformStamped()
    tf.header.stamp = to_stamp(T0 + 1)
    set_quaternion(tf.transform.rotation, np.eye(3))
    pub_or.publish(tf)
    assert spin_until(ex, lambda: bool(out), 5.0)
    o = image_to_array(out[0])
    assert out[0].header.stamp.nanosec == 1 and o.shape == (240, 320, 3)
    # drawn when its orientation came (after the image): still in the image's own frame
    assert out[0].header.frame_id == 'phone_cam_optical' and out[0].encoding == 'rgb8'
    assert tuple(o[120, 160]) == COLOURS_RGB['matched']
    assert all(s.failures == 0 for s in node.callback_stats.values())
    node.destroy_node()
    src.destroy_node()


def test_config_file_equals_declared_defaults(ros_context):
    from pathlib import Path

    import yaml

    config = Path(__file__).resolve().parents[2] / 'config' / 'ar_view.yaml'
    params = yaml.safe_load(config.read_text())['ar_view']['ros__parameters']
    node = ArViewNode(context=ros_context)
    try:
        declared = {n for n in node._parameters if n not in ('use_sim_time', 'start_type_description_service')}
        assert set(params) == declared
        for key, value in params.items():
            assert node.get_parameter(key).value == value, key
    finally:
        node.destroy_node()
