"""The live view: the graph's topics over the Foxglove WebSocket protocol (foxglove-sdk).

:class:`FoxgloveBridge` starts a WebSocket server (``foxglove.start_server`` on a private SDK
context) and serves each topic it is handed as it is: the raw CDR bytes with the message's
``ros2msg`` definition as schema, which Foxglove decodes like a ROS 2 connection (Image,
PointCloud2, Path, MarkerArray, ...). No conversion, no copy on the Python side, and nothing is
sent on a channel no client subscribes to.

Orientation and pose topics also become ``foxglove.FrameTransform`` messages on
``/foxglove/transforms``, so the 3D panel shows the camera as a frame in the world:

========================================  ======================  ===============================
topic (type)                              parent                  child
========================================  ======================  ===============================
``orientation/global`` (Imu)              ``world_frame`` (enu)   header.frame_id (camera_optical)
``imu/data`` (Imu)                        ``world_frame``         header.frame_id (imu)
``orientation/panorama_in_world`` (TF)    header.frame_id         child_frame_id (panorama)
``slam/pose`` (PoseStamped)               header.frame_id         ``slam_camera``
``vi/predicted_pose`` (PoseStamped)       header.frame_id         ``vi_camera``
``markers/pose`` (PoseWithCov.Stamped)    header.frame_id         ``marker_camera``
========================================  ======================  ===============================

(``panorama/orientation``, panorama -> camera, is served as a topic only: as a frame it would
give the camera a second parent.) The annotation markers live in the ``panorama`` frame, which
``orientation/panorama_in_world`` places in the world. ``config/foxglove_layout.json`` (made by
:func:`make_layout`) arranges a 3D panel, the AR overlay and the panorama.

Message time on the wire is the header stamp (capture time), so live and replayed data line up.
The module needs no rclpy: the runner hands it the raw bytes its recorder already receives, and
the ``foxglove_bridge`` node does the same for a live graph.
"""
from __future__ import annotations

import logging
import struct
import threading
import time
from pathlib import Path
from typing import Any, Callable

from ..errors import ArTrackingError

logger = logging.getLogger(__name__)

#: Default port of Foxglove's WebSocket connection.
DEFAULT_PORT = 8765
#: The channel of the derived frame transforms.
TRANSFORMS_TOPIC = '/foxglove/transforms'
#: topic -> child frame for pose topics (their parent is the message's header.frame_id).
POSE_CHILD_FRAMES = {'/slam/pose': 'slam_camera', '/vi/predicted_pose': 'vi_camera', '/markers/pose': 'marker_camera'}
#: Imu topics whose orientation is the header frame in the world frame.
ORIENTATION_TOPICS = ('/orientation/global', '/imu/data')
#: TransformStamped topics served as frames.
TRANSFORM_TOPICS = ('/orientation/panorama_in_world',)
#: The layout file in the repository.
LAYOUT_PATH = Path(__file__).resolve().parents[2] / 'config' / 'foxglove_layout.json'


class FoxgloveError(ArTrackingError):
    """The live view cannot start (one line: the SDK is missing, the port is taken)."""


def _stamp_ns(raw: bytes) -> int | None:
    """header.stamp of a CDR message that starts with a std_msgs/Header (None if too short)."""
    if len(raw) < 12:
        return None
    sec, nsec = struct.unpack_from('<iI' if raw[1] == 1 else '>iI', raw, 4)
    return sec * 1_000_000_000 + nsec


def _cdr_string(data: memoryview, pos: int, order: str) -> tuple[str, int]:
    """A CDR string at ``pos`` (4-aligned length with its NUL, then the bytes); the text and the
    position after it."""
    pos += -pos % 4
    (n,) = struct.unpack_from(order + 'I', data, pos)
    if n == 0 or pos + 4 + n > len(data):
        raise ValueError('truncated string')
    return bytes(data[pos + 4:pos + 3 + n]).decode('utf-8', 'replace').lstrip('/'), pos + 4 + n


#: Message types whose frame is read straight from the CDR bytes, and the doubles between the
#: header (and child_frame_id) and the quaternion: Imu starts with it, the poses with a position.
_FRAME_LAYOUTS = {
    'sensor_msgs/msg/Imu': (False, False),
    'geometry_msgs/msg/TransformStamped': (True, True),
    'geometry_msgs/msg/PoseStamped': (False, True),
    'geometry_msgs/msg/PoseWithCovarianceStamped': (False, True),
}


def frame_pose(msgtype: str, raw: bytes) -> tuple[int, int, str, str, tuple[float, float, float],
                                                   tuple[float, float, float, float]] | None:
    """(stamp sec, nanosec, header.frame_id, child_frame_id, translation, rotation xyzw) of an Imu,
    TransformStamped, PoseStamped or PoseWithCovarianceStamped, read from its CDR bytes without
    deserialising the message (a few microseconds instead of ~15 for a generic decoder); None for
    other types or a truncated message."""
    layout = _FRAME_LAYOUTS.get(msgtype)
    if layout is None or len(raw) < 16:
        return None
    has_child, has_translation = layout
    order = '<' if raw[1] == 1 else '>'
    data = memoryview(raw)[4:]  # CDR alignment counts from the end of the encapsulation header
    try:
        sec, nanosec = struct.unpack_from(order + 'iI', data, 0)
        frame_id, pos = _cdr_string(data, 8, order)
        child = ''
        if has_child:
            child, pos = _cdr_string(data, pos, order)
        pos += -pos % 8
        t = (0.0, 0.0, 0.0)
        if has_translation:
            t = struct.unpack_from(order + '3d', data, pos)
            pos += 24
        q = struct.unpack_from(order + '4d', data, pos)
    except (struct.error, ValueError):
        return None
    return sec, nanosec, frame_id, child, t, q


class FoxgloveBridge:
    """A Foxglove WebSocket server fed with raw CDR messages (see the module docstring).

    ``port`` 0 takes a free port (see :attr:`port`). Thread-safe: the runner's recorder thread
    and node threads may publish at once."""

    def __init__(self, port: int = DEFAULT_PORT, host: str = '127.0.0.1', *, world_frame: str = 'enu',
                 name: str = 'ar_tracking') -> None:
        try:
            import foxglove
            from foxglove.channels import FrameTransformChannel
        except ImportError as exc:
            raise FoxgloveError('the live view needs foxglove-sdk: pip install foxglove-sdk') from exc
        self._foxglove = foxglove
        self.world_frame = world_frame
        self._context = foxglove.Context()
        try:
            self._server = foxglove.start_server(name=name, host=host, port=port, context=self._context)
        except Exception as exc:  # the SDK raises its own error types (port in use, bad host)
            raise FoxgloveError(f'cannot start the Foxglove server on {host}:{port} ({exc})') from exc
        self._channels: dict[str, Any] = {}
        #: topics whose messages start with a std_msgs/Header (their stamp is the message time)
        self._stamped: set[str] = set()
        self._lock = threading.Lock()
        self._transforms = FrameTransformChannel(TRANSFORMS_TOPIC, context=self._context)
        self.published = 0
        #: time spent in publish() (the caller's thread), s: what the live view adds to the graph's path
        self.busy_s = 0.0
        logger.info('Foxglove live view on ws://%s:%d', host, self.port)

    @property
    def port(self) -> int:
        return int(self._server.port)

    @property
    def url(self) -> str:
        return f'ws://127.0.0.1:{self.port}'

    def advertise(self, topic: str, msgtype: str) -> Any:
        """The channel of ``topic`` (created on first use, so clients see it before any data)."""
        topic = '/' + topic.lstrip('/')
        channel = self._channels.get(topic)
        if channel is not None:
            return channel
        with self._lock:
            channel = self._channels.get(topic)
            if channel is None:
                from ..io.bags import TYPESTORE

                msgdef, _ = TYPESTORE.generate_msgdef(msgtype, ros_version=2)
                schema = self._foxglove.Schema(name=msgtype, encoding='ros2msg', data=msgdef.encode())
                channel = self._foxglove.Channel(topic, schema=schema, message_encoding='cdr',
                                                 context=self._context)
                first_field = next((line for line in msgdef.splitlines() if line.strip()
                                    and not line.lstrip().startswith('#')), '')
                if first_field.split()[:1] in (['std_msgs/Header'], ['Header']):
                    self._stamped.add(topic)
                self._channels[topic] = channel
        return channel

    def publish(self, topic: str, msgtype: str, raw: bytes) -> None:
        """Serve one message (raw CDR) on its topic, and its frame on /foxglove/transforms."""
        start = time.perf_counter()
        try:
            self._publish(topic, msgtype, raw)
        finally:
            self.busy_s += time.perf_counter() - start

    def _publish(self, topic: str, msgtype: str, raw: bytes) -> None:
        topic = '/' + topic.lstrip('/')
        channel = self.advertise(topic, msgtype)
        stamp = _stamp_ns(raw) if topic in self._stamped else None
        if channel.has_sinks():
            channel.log(bytes(raw), log_time=stamp)
            self.published += 1
        if (topic in ORIENTATION_TOPICS or topic in TRANSFORM_TOPICS or topic in POSE_CHILD_FRAMES) \
                and self._transforms.has_sinks():
            try:
                frame = self._frame(topic, msgtype, raw)
            except Exception as exc:  # noqa: BLE001 - a message we cannot decode: not a frame
                logger.debug('%s: no frame (%s)', topic, exc)
                return
            if frame is not None:
                self._transforms.log(frame, log_time=stamp)

    def _frame(self, topic: str, msgtype: str, raw: bytes) -> Any:
        """The FrameTransform a message stands for (None for other types or a message too short)."""
        from foxglove.messages import FrameTransform, Quaternion, Timestamp, Vector3

        pose = frame_pose(msgtype, raw)
        if pose is None:
            return None
        sec, nanosec, frame_id, child_frame_id, t, q = pose
        if msgtype == 'sensor_msgs/msg/Imu' and topic in ORIENTATION_TOPICS:
            parent, child = self.world_frame, frame_id or ('camera_optical' if 'global' in topic else 'imu')
        elif msgtype == 'geometry_msgs/msg/TransformStamped':
            parent, child = frame_id, child_frame_id
        elif topic in POSE_CHILD_FRAMES:
            parent, child = frame_id, POSE_CHILD_FRAMES[topic]
        else:
            return None
        if not parent or not child or not any(q):
            return None
        return FrameTransform(timestamp=Timestamp(sec=sec, nsec=nanosec), parent_frame_id=parent,
                              child_frame_id=child, translation=Vector3(x=t[0], y=t[1], z=t[2]),
                              rotation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]))

    def tap(self, topic: str, msgtype: str) -> Callable[[bytes], None]:
        """A callback that serves every raw message of one topic."""
        self.advertise(topic, msgtype)
        return lambda raw: self.publish(topic, msgtype, raw)

    def close(self) -> None:
        """Stop the server (clients are disconnected)."""
        server = getattr(self, '_server', None)
        if server is not None:
            server.stop()
            self._server = None

    def __enter__(self) -> 'FoxgloveBridge':
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def make_layout() -> str:
    """The Foxglove layout of config/foxglove_layout.json (as JSON text): a 3D panel in the world
    frame (camera, panorama and SLAM frames, SLAM points and path, annotation markers) beside
    the AR overlay and the panorama map."""
    import foxglove.layouts as fl

    three_d = fl.ThreeDeePanel(title='world (enu)', config=fl.ThreeDeeConfig(
        follow_tf='enu', fixed_frame='enu',
        topics={
            '/slam/map_points': fl.BaseRendererPointCloudTopicSettings(visible=True),
            '/slam/path': fl.BaseRendererBaseSettings(visible=True),
            '/slam/keyframes': fl.BaseRendererPosesTopicSettings(visible=True),
            '/annotations/markers': fl.BaseRendererRosMarkerTopicSettings(visible=True),
            '/markers/detections': fl.BaseRendererRosMarkerTopicSettings(visible=True),
        }))
    overlay = fl.ImagePanel(title='AR overlay', config=fl.ImageConfig(
        image_mode=fl.ImageModeConfig(image_topic='/ar/overlay')))
    panorama = fl.ImagePanel(title='panorama', config=fl.ImageConfig(
        image_mode=fl.ImageModeConfig(image_topic='/panorama/image')))
    layout = fl.Layout(content=fl.SplitContainer(direction='row', items=[
        fl.SplitItem(proportion=1, content=three_d),
        fl.SplitItem(proportion=1, content=fl.SplitContainer(direction='column', items=[
            fl.SplitItem(proportion=1, content=overlay),
            fl.SplitItem(proportion=1, content=panorama),
        ])),
    ]))
    import json

    return json.dumps(json.loads(layout.to_json()), indent=1, sort_keys=True) + '\n'


if __name__ == '__main__':  # python -m ar_tracking.ros.foxglove --layout: rewrite config/foxglove_layout.json
    import sys

    if sys.argv[1:] != ['--layout']:
        sys.exit('usage: python -m ar_tracking.ros.foxglove --layout')
    LAYOUT_PATH.write_text(make_layout())
    print(LAYOUT_PATH)
