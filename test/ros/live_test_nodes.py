"""Nodes for the realtime runner tests that run them in processes of their own (a spawned
process imports them by name, so they live at module level)."""
from __future__ import annotations

import time
from typing import Any

from sensor_msgs.msg import Imu, MagneticField

from ar_tracking.ros.node_base import TrackingNode


class SlowNode(TrackingNode):
    """Takes 100 ms per IMU sample."""

    INPUTS = {'imu/data_raw': 'sensor_msgs/msg/Imu'}
    OUTPUTS: dict = {}

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('slow', **kwargs)
        self.subscribe(Imu, 'imu/data_raw', lambda msg: time.sleep(0.1))


class DyingNode(TrackingNode):
    """Raises on its 10th field sample: the node's process dies mid-run."""

    INPUTS = {'imu/mag': 'sensor_msgs/msg/MagneticField'}
    OUTPUTS: dict = {}

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('dying', **kwargs)
        self.seen = 0
        self.create_subscription(MagneticField, 'imu/mag', self.on_mag, 10)

    def on_mag(self, msg: MagneticField) -> None:
        self.seen += 1
        if self.seen == 10:
            raise RuntimeError('sensor driver lost')


class LaggingRelay(TrackingNode):
    """Republishes each IMU sample on relay/imu after 300 ms of work: at the end of a run it
    still has a backlog, published with gaps longer than a downstream node's drain wait."""

    INPUTS = {'imu/data_raw': 'sensor_msgs/msg/Imu'}
    OUTPUTS = {'relay/imu': 'sensor_msgs/msg/Imu'}

    def __init__(self, **kwargs: Any) -> None:
        from ar_tracking.ros.node_base import STREAM_QOS

        super().__init__('relay', **kwargs)
        # Reliable (advertise's default), as the graph's nodes publish: the runner's recorder
        # subscribes reliably and would never match a best-effort publisher.
        self.pub = self.advertise(Imu, 'relay/imu')
        self.subscribe(Imu, 'imu/data_raw', self.on_imu, STREAM_QOS)

    def on_imu(self, msg: Imu) -> None:
        time.sleep(0.3)
        self.pub.publish(msg)


class RelayCounter(TrackingNode):
    """Takes relay/imu (downstream of LaggingRelay)."""

    INPUTS = {'relay/imu': 'sensor_msgs/msg/Imu'}
    OUTPUTS: dict = {}

    def __init__(self, **kwargs: Any) -> None:
        from ar_tracking.ros.node_base import STREAM_QOS

        super().__init__('counter', **kwargs)
        self.subscribe(Imu, 'relay/imu', lambda msg: None, STREAM_QOS)


class BestEffortRelay(TrackingNode):
    """Republishes each IMU sample on relay/imu best effort, as a sensor driver does (the
    runner's recorder must take the reliability the publisher offers to match it)."""

    INPUTS = {'imu/data_raw': 'sensor_msgs/msg/Imu'}
    OUTPUTS = {'relay/imu': 'sensor_msgs/msg/Imu'}

    def __init__(self, **kwargs: Any) -> None:
        from ar_tracking.ros.node_base import STREAM_QOS

        super().__init__('relay', **kwargs)
        self.pub = self.advertise(Imu, 'relay/imu', STREAM_QOS)
        self.subscribe(Imu, 'imu/data_raw', self.pub.publish, STREAM_QOS)


class Relay(TrackingNode):
    """Republishes each IMU sample on relay/imu at once (reliable, as the graph's nodes)."""

    INPUTS = {'imu/data_raw': 'sensor_msgs/msg/Imu'}
    OUTPUTS = {'relay/imu': 'sensor_msgs/msg/Imu'}

    def __init__(self, **kwargs: Any) -> None:
        from ar_tracking.ros.node_base import STREAM_QOS

        super().__init__('relay', **kwargs)
        self.pub = self.advertise(Imu, 'relay/imu')
        self.subscribe(Imu, 'imu/data_raw', self.pub.publish, STREAM_QOS)


class TripleRelay(TrackingNode):
    """Publishes every field sample three times on relay/mag, each with its own z (and once on
    relay/debug, a topic it does not declare: no one records it)."""

    INPUTS = {'imu/mag': 'sensor_msgs/msg/MagneticField'}
    OUTPUTS = {'relay/mag': 'sensor_msgs/msg/MagneticField'}

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('triple', **kwargs)
        self.pub = self.advertise(MagneticField, 'relay/mag')
        self.debug = self.advertise(MagneticField, 'relay/debug')
        self.subscribe(MagneticField, 'imu/mag', self.on_mag)

    def on_mag(self, msg: MagneticField) -> None:
        self.debug.publish(msg)
        for k in range(3):
            msg.magnetic_field.z = float(k)
            self.pub.publish(msg)


class LatestField(TrackingNode):
    """Takes relay/mag with depth 1 (the latest value only) and relay/imu, and publishes on
    joined/imu each IMU sample with the z of the last field it took as its orientation.w."""

    INPUTS = {'relay/mag': 'sensor_msgs/msg/MagneticField', 'relay/imu': 'sensor_msgs/msg/Imu'}
    OUTPUTS = {'joined/imu': 'sensor_msgs/msg/Imu'}

    def __init__(self, **kwargs: Any) -> None:
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        super().__init__('latest', **kwargs)
        self.z = -1.0
        self.pub = self.advertise(Imu, 'joined/imu')
        self.subscribe(MagneticField, 'relay/mag', self.on_mag, QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE))
        self.subscribe(Imu, 'relay/imu', self.on_imu, QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))

    def on_mag(self, msg: MagneticField) -> None:
        self.z = msg.magnetic_field.z

    def on_imu(self, msg: Imu) -> None:
        msg.orientation.w = self.z
        self.pub.publish(msg)


class Echo(TrackingNode):
    """Takes relay/imu and publishes it on imu/data_raw: with Relay, a cycle."""

    INPUTS = {'relay/imu': 'sensor_msgs/msg/Imu'}
    OUTPUTS = {'imu/data_raw': 'sensor_msgs/msg/Imu'}

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('echo', **kwargs)
        self.pub = self.advertise(Imu, 'imu/data_raw')
        self.subscribe(Imu, 'relay/imu', self.pub.publish)
