"""foxglove_bridge node: a live graph's topic reaches a Foxglove WebSocket client; bad topics and
a taken port are one error; config/foxglove_bridge.yaml equals the declared defaults."""
from __future__ import annotations

import time
from pathlib import Path

import pytest
import yaml

pytest.importorskip('rclpy')
pytest.importorskip('foxglove')
pytest.importorskip('websockets')

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import Imu  # noqa: E402

from ar_tracking.eval.bench_foxglove import FoxgloveProbe  # noqa: E402
from ar_tracking.nodes.foxglove_bridge import FoxgloveBridgeNode  # noqa: E402
from ar_tracking.ros.foxglove import TRANSFORMS_TOPIC, FoxgloveBridge  # noqa: E402
from ar_tracking.ros.node_base import RELIABLE_QOS  # noqa: E402

CONFIG = Path(__file__).resolve().parents[2] / 'config' / 'foxglove_bridge.yaml'


def test_live_topic_reaches_the_client(ros_context) -> None:
    node = FoxgloveBridgeNode(context=ros_context, parameter_overrides=[
        Parameter('port', value=0), Parameter('topics', value=['orientation/global', 'ar/overlay'])])
    source = Node('source', context=ros_context)
    pub = source.create_publisher(Imu, 'orientation/global', RELIABLE_QOS)
    ex = SingleThreadedExecutor(context=ros_context)
    ex.add_node(node)
    ex.add_node(source)
    try:
        with FoxgloveProbe(f'ws://127.0.0.1:{node.port}') as probe:
            deadline = time.monotonic() + 8.0
            while time.monotonic() < deadline and not (probe.counts['/orientation/global'] and probe.counts[TRANSFORMS_TOPIC]):
                if {'/orientation/global', TRANSFORMS_TOPIC} <= probe.topics() and pub.get_subscription_count():
                    msg = Imu()
                    msg.header.stamp.sec = 3
                    msg.header.frame_id = 'camera_optical'
                    msg.orientation.w = 1.0
                    pub.publish(msg)
                ex.spin_once(timeout_sec=0.05)
        assert {'/orientation/global', '/ar/overlay', TRANSFORMS_TOPIC} <= probe.topics()
        assert probe.counts['/orientation/global'] >= 1 and probe.counts[TRANSFORMS_TOPIC] >= 1
        assert probe.first['/orientation/global'][0] == 3_000_000_000
    finally:
        ex.shutdown()
        node.close()
        node.destroy_node()
        source.destroy_node()


def test_unknown_topic_and_taken_port_are_errors(ros_context) -> None:
    with pytest.raises(ValueError, match='unknown topic'):
        FoxgloveBridgeNode(context=ros_context, parameter_overrides=[
            Parameter('port', value=0), Parameter('topics', value=['no/such'])])
    with FoxgloveBridge(port=0) as taken:
        with pytest.raises(ValueError, match='cannot start the Foxglove server'):
            FoxgloveBridgeNode(context=ros_context, parameter_overrides=[Parameter('port', value=taken.port)])


def test_config_file_equals_the_declared_defaults(ros_context) -> None:
    params = yaml.safe_load(CONFIG.read_text())['foxglove_bridge']['ros__parameters']
    node = FoxgloveBridgeNode(context=ros_context, parameter_overrides=[Parameter('port', value=0)])
    try:
        for key, value in params.items():
            assert node.has_parameter(key) and node.describe_parameter(key).description
            if key != 'port':
                declared = node.get_parameter(key).value
                assert (list(declared) if isinstance(value, list) else declared) == value, key
        assert params['port'] == 8765
    finally:
        node.close()
        node.destroy_node()
