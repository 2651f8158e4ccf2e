"""The Foxglove live view: a WebSocket client connects, sees the channels and receives the
messages (raw CDR as published, orientation and poses as frame transforms), on the bridge alone
and on a graph run; the committed layout file is the one make_layout() writes."""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip('foxglove')
pytest.importorskip('websockets')

from ar_tracking.eval.bench_foxglove import FoxgloveProbe  # noqa: E402
from ar_tracking.io.bags import TYPESTORE  # noqa: E402
from ar_tracking.ros.foxglove import LAYOUT_PATH, TRANSFORMS_TOPIC, FoxgloveBridge, make_layout  # noqa: E402

T = TYPESTORE.types
SAMPLE_BAG = Path(__file__).resolve().parents[2] / 'bags' / 'rotation_sweep_browsing.mcap'


def header(sec: int, frame: str):
    return T['std_msgs/msg/Header'](stamp=T['builtin_interfaces/msg/Time'](sec=sec, nanosec=500), frame_id=frame)


def quat(x=0.0, y=0.0, z=0.0, w=1.0):
    return T['geometry_msgs/msg/Quaternion'](x=x, y=y, z=z, w=w)


def vec(x=0.0, y=0.0, z=0.0):
    return T['geometry_msgs/msg/Vector3'](x=x, y=y, z=z)


def cdr(msg, msgtype: str) -> bytes:
    return bytes(TYPESTORE.serialize_cdr(msg, msgtype))


def imu(sec: int) -> bytes:
    z = np.zeros(9)
    return cdr(T['sensor_msgs/msg/Imu'](header=header(sec, 'camera_optical'), orientation=quat(z=0.6, w=0.8),
                                        orientation_covariance=z, angular_velocity=vec(), angular_velocity_covariance=z,
                                        linear_acceleration=vec(), linear_acceleration_covariance=z),
               'sensor_msgs/msg/Imu')


def wait_for(predicate, timeout_s: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not predicate():
        time.sleep(0.01)
    return predicate()


def test_client_receives_channels_messages_and_frames() -> None:
    from foxglove.messages import FrameTransform, Quaternion, Timestamp, Vector3

    with FoxgloveBridge(port=0) as bridge:
        bridge.advertise('orientation/global', 'sensor_msgs/msg/Imu')
        bridge.advertise('slam/pose', 'geometry_msgs/msg/PoseStamped')
        bridge.advertise('annotations/markers', 'visualization_msgs/msg/MarkerArray')
        bridge.publish('orientation/global', 'sensor_msgs/msg/Imu', imu(1))  # nobody listens: not sent
        assert bridge.published == 0
        with FoxgloveProbe(bridge.url) as probe:
            assert wait_for(lambda: {'/orientation/global', '/slam/pose', TRANSFORMS_TOPIC} <= probe.topics())
            cdr_channel = next(c for c in probe.channels.values() if c['topic'] == '/orientation/global')
            assert cdr_channel['encoding'] == 'cdr' and cdr_channel['schemaName'] == 'sensor_msgs/msg/Imu'
            assert cdr_channel['schemaEncoding'] == 'ros2msg' and 'std_msgs/Header header' in cdr_channel['schema']
            time.sleep(0.2)  # the subscription reaches the server
            raw = imu(7)
            bridge.publish('orientation/global', 'sensor_msgs/msg/Imu', raw)
            pose = cdr(T['geometry_msgs/msg/PoseStamped'](
                header=header(8, 'slam_map'),
                pose=T['geometry_msgs/msg/Pose'](position=T['geometry_msgs/msg/Point'](x=1.0, y=2.0, z=3.0),
                                                 orientation=quat())), 'geometry_msgs/msg/PoseStamped')
            bridge.publish('/slam/pose', 'geometry_msgs/msg/PoseStamped', pose)
            markers = cdr(T['visualization_msgs/msg/MarkerArray'](markers=[]), 'visualization_msgs/msg/MarkerArray')
            bridge.publish('annotations/markers', 'visualization_msgs/msg/MarkerArray', markers)
            bridge.publish('orientation/global', 'sensor_msgs/msg/Imu', raw[:10])  # truncated: served, no frame
            assert wait_for(lambda: probe.counts[TRANSFORMS_TOPIC] >= 2 and probe.counts['/annotations/markers'] >= 1)
            time.sleep(0.1)
        # raw CDR as published, stamped with the header stamp
        assert probe.first['/orientation/global'] == (7_000_000_500, raw)
        assert probe.first['/slam/pose'][1] == pose and probe.counts['/orientation/global'] == 2
        assert probe.counts[TRANSFORMS_TOPIC] == 2  # the Imu and the pose, not the truncated one
        expected = FrameTransform(timestamp=Timestamp(sec=7, nsec=500), parent_frame_id='enu',
                                  child_frame_id='camera_optical', translation=Vector3(x=0.0, y=0.0, z=0.0),
                                  rotation=Quaternion(x=0.0, y=0.0, z=0.6, w=0.8)).encode()
        assert probe.first[TRANSFORMS_TOPIC] == (7_000_000_500, expected)


def test_port_in_use_is_one_error() -> None:
    from ar_tracking.ros.foxglove import FoxgloveError

    with FoxgloveBridge(port=0) as bridge:
        with pytest.raises(FoxgloveError, match='cannot start'):
            FoxgloveBridge(port=bridge.port)


@pytest.mark.skipif(not SAMPLE_BAG.exists(), reason='sample bag missing')
def test_graph_run_serves_its_topics(tmp_path) -> None:
    pytest.importorskip('rclpy')
    from ar_tracking.ros.runner import GraphRunner

    from ar_tracking.ros.graph_plan import GRAPH_NODES, load_node_class

    params = [SAMPLE_BAG.with_name(SAMPLE_BAG.stem + '.params.yaml')]
    nodes = ['imu_magnetometer', 'panorama_mapper', 'hybrid_orientation_filter']
    with FoxgloveBridge(port=0) as bridge:
        # Every channel exists before the client connects, so that it is advertised with the
        # server's hello: a channel made while a client is connected can be advertised before
        # the server can take a subscription to it ('attempted to subscribe to unknown channel'),
        # and a lockstep run of 700 messages is over in well under a second.
        channels = [bridge.advertise(topic, msgtype) for name in nodes
                    for topic, msgtype in load_node_class(GRAPH_NODES[name]).OUTPUTS.items()]
        probe = FoxgloveProbe(bridge.url, keep_first=False).start()
        try:
            assert wait_for(lambda: all(c.has_sinks() for c in channels))
            result = GraphRunner(SAMPLE_BAG, tmp_path / 'out.mcap', params_files=params, max_messages=700,
                                 nodes=nodes, output_taps=[bridge.tap]).run()
            assert wait_for(lambda: probe.counts['/orientation/global'] > 0 and probe.counts[TRANSFORMS_TOPIC] > 0)
            time.sleep(0.2)
        finally:
            probe.stop()
    assert {'/orientation/global', '/panorama/image', '/panorama/orientation', TRANSFORMS_TOPIC} <= probe.topics()
    assert probe.error is None and result.output_messages > 0
    # Subscribed before the run: everything the run published arrives.
    assert probe.counts['/panorama/orientation'] > 10 and probe.counts['/panorama/image'] >= 1


def test_layout_file_is_current() -> None:
    assert LAYOUT_PATH.read_text() == make_layout(), 'regenerate: python -m ar_tracking.ros.foxglove --layout'
    layout = json.loads(LAYOUT_PATH.read_text())
    text = json.dumps(layout)
    for topic in ('/ar/overlay', '/panorama/image', '/slam/map_points', '/slam/path', '/annotations/markers'):
        assert topic in text


def test_cli_foxglove_port_in_use_is_one_line(tmp_path, capsys) -> None:
    from ar_tracking.cli import main

    with FoxgloveBridge(port=0) as taken:
        code = main(['run', str(SAMPLE_BAG), '-o', str(tmp_path / 'o.mcap'), '--foxglove', str(taken.port)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and len(err) == 1 and 'cannot start the Foxglove server' in err[0]


@pytest.mark.parametrize('frame', ['', 'a', 'ab', 'abc', 'abcd', 'slam_map', '/enu'])
def test_frame_pose_reads_what_the_decoder_reads(frame: str) -> None:
    """The CDR shortcut of the frame transforms against rosbags' decoder, for frame ids of every
    length modulo the alignment."""
    from ar_tracking.ros.foxglove import frame_pose

    P = T['geometry_msgs/msg/Point'](x=1.5, y=-2.0, z=3.25)
    q = quat(0.1, 0.2, 0.3, 0.9)
    msgs = {
        'geometry_msgs/msg/TransformStamped': T['geometry_msgs/msg/TransformStamped'](
            header=header(4, frame), child_frame_id=frame + 'x',
            transform=T['geometry_msgs/msg/Transform'](translation=vec(1.5, -2.0, 3.25), rotation=q)),
        'geometry_msgs/msg/PoseStamped': T['geometry_msgs/msg/PoseStamped'](
            header=header(4, frame), pose=T['geometry_msgs/msg/Pose'](position=P, orientation=q)),
        'geometry_msgs/msg/PoseWithCovarianceStamped': T['geometry_msgs/msg/PoseWithCovarianceStamped'](
            header=header(4, frame), pose=T['geometry_msgs/msg/PoseWithCovariance'](
                pose=T['geometry_msgs/msg/Pose'](position=P, orientation=q), covariance=np.arange(36.0))),
    }
    for msgtype, msg in msgs.items():
        raw = cdr(msg, msgtype)
        sec, nanosec, frame_id, child, t, rot = frame_pose(msgtype, raw)
        assert (sec, nanosec, frame_id) == (4, 500, frame.lstrip('/'))
        assert child == ((frame + 'x').lstrip('/') if 'Transform' in msgtype else '')
        assert t == (1.5, -2.0, 3.25) and rot == (0.1, 0.2, 0.3, 0.9)
        assert frame_pose(msgtype, raw[:len(raw) - 8]) is None or 'Covariance' in msgtype  # cut into q
    z = np.zeros(9)
    raw = cdr(T['sensor_msgs/msg/Imu'](header=header(2, frame), orientation=q, orientation_covariance=z,
                                       angular_velocity=vec(), angular_velocity_covariance=z,
                                       linear_acceleration=vec(), linear_acceleration_covariance=z),
              'sensor_msgs/msg/Imu')
    assert frame_pose('sensor_msgs/msg/Imu', raw)[2:] == (frame.lstrip('/'), '', (0.0, 0.0, 0.0), (0.1, 0.2, 0.3, 0.9))
    assert frame_pose('sensor_msgs/msg/Imu', raw[:30]) is None
    assert frame_pose('sensor_msgs/msg/Image', raw) is None
