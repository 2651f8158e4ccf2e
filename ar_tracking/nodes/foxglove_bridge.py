"""foxglove_bridge: serves a live graph's topics to Foxglove over its WebSocket protocol.

For graphs that run as separate node processes (a ROS install, a phone streaming live): the
node subscribes to ``topics`` (raw CDR, no deserialisation) and hands every message to
:class:`ar_tracking.ros.foxglove.FoxgloveBridge`, which serves it on ``ws://host:port`` with the
message definition as schema, and orientation/pose topics also as frame transforms (the camera
as a 3D frame in ENU). ``ar-tracking run --foxglove`` does the same inside the graph runner
without this node. Open the URL in Foxglove with the layout ``config/foxglove_layout.json``.

Subscriptions are best effort (they hear reliable and best-effort publishers alike) with a short
history: a viewer that cannot keep up sees fewer frames, the graph never waits for it.
"""
from __future__ import annotations

from typing import Any

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from ..ros.conversions import message_class
from ..ros.foxglove import DEFAULT_PORT, FoxgloveBridge, FoxgloveError
from ..ros.node_base import TrackingNode, run_node
from ..ros.param_table import ParamSpec, declare_params

#: The graph's topics a viewer wants, with their types (DESIGN.md sec. 2).
LIVE_TOPICS = {
    'orientation/global': 'sensor_msgs/msg/Imu',
    'orientation/panorama_in_world': 'geometry_msgs/msg/TransformStamped',
    'imu/data': 'sensor_msgs/msg/Imu',
    'panorama/orientation': 'geometry_msgs/msg/TransformStamped',
    'panorama/image': 'sensor_msgs/msg/Image',
    'panorama/tiles': 'sensor_msgs/msg/Image',
    'annotations/markers': 'visualization_msgs/msg/MarkerArray',
    'annotations/alignment': 'geometry_msgs/msg/TransformStamped',
    'ar/overlay': 'sensor_msgs/msg/Image',
    'slam/pose': 'geometry_msgs/msg/PoseStamped',
    'slam/map_points': 'sensor_msgs/msg/PointCloud2',
    'slam/keyframes': 'geometry_msgs/msg/PoseArray',
    'slam/path': 'nav_msgs/msg/Path',
    'markers/pose': 'geometry_msgs/msg/PoseWithCovarianceStamped',
    'markers/detections': 'visualization_msgs/msg/MarkerArray',
    'vi/odometry': 'nav_msgs/msg/Odometry',
    'vi/predicted_pose': 'geometry_msgs/msg/PoseStamped',
    'camera/image_raw': 'sensor_msgs/msg/Image',
    'camera/image_raw/compressed': 'sensor_msgs/msg/CompressedImage',
    'camera/camera_info': 'sensor_msgs/msg/CameraInfo',
    'gps/fix': 'sensor_msgs/msg/NavSatFix',
}
#: Served unless ``topics`` says otherwise: the outputs of the graph (not the raw camera).
DEFAULT_TOPICS = [t for t in LIVE_TOPICS if not t.startswith(('camera/', 'gps/'))]
VIEWER_QOS = QoSProfile(depth=5, reliability=ReliabilityPolicy.BEST_EFFORT,
                        durability=DurabilityPolicy.VOLATILE, history=HistoryPolicy.KEEP_LAST)

#: The bridge's parameters.
PARAMS = (
    ParamSpec('port', DEFAULT_PORT,
              'WebSocket port of the Foxglove server (0: any free port)', min_value=0, max_value=65535),
    ParamSpec('host', '127.0.0.1', 'Address the server listens on (0.0.0.0: every interface)'),
    ParamSpec('world_frame_id', 'enu', 'Parent frame of the orientation topics (orientation/global, imu/data)'),
    ParamSpec('topics', list(DEFAULT_TOPICS),
              'Topics served (relative names of the graph: ' + ', '.join(LIVE_TOPICS) + ')'),
)


class FoxgloveBridgeNode(TrackingNode):
    INPUTS: dict[str, str] = {}  # a viewer: the graph runner never starts it (run --foxglove does the job there)
    OUTPUTS: dict[str, str] = {}

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('foxglove_bridge', **kwargs)
        v = declare_params(self, PARAMS)
        port = v['port']
        host = v['host']
        world = v['world_frame_id']
        topics = v['topics']
        unknown = [t for t in topics if t.lstrip('/') not in LIVE_TOPICS]
        if unknown:
            raise ValueError(f'parameter topics: unknown topic(s) {", ".join(unknown)}; known: {", ".join(LIVE_TOPICS)}')
        try:
            self.bridge = FoxgloveBridge(port=port, host=host, world_frame=world)
        except FoxgloveError as exc:
            raise ValueError(str(exc)) from exc
        for topic in topics:
            name = topic.lstrip('/')
            msgtype = LIVE_TOPICS[name]
            self.subscribe(message_class(msgtype), name, self.bridge.tap(name, msgtype), VIEWER_QOS, raw=True)
        self.get_logger().info(f'foxglove_bridge: {len(topics)} topics on ws://{host}:{self.bridge.port}')

    @property
    def port(self) -> int:
        return self.bridge.port

    def close(self) -> None:
        bridge = getattr(self, 'bridge', None)
        if bridge is not None:
            bridge.close()


def main(args: list[str] | None = None) -> int:
    return run_node(FoxgloveBridgeNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
