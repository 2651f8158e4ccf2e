"""bag_replay and camera_replay in-process: what they publish, remapping, /clock, bad bags."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rosgraph_msgs.msg import Clock  # noqa: E402
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, Imu, MagneticField  # noqa: E402

from ar_tracking.nodes.bag_replay import BagReplayNode  # noqa: E402
from ar_tracking.nodes.camera_replay import CameraReplayNode  # noqa: E402
from ar_tracking.ros.conversions import image_to_array, stamp_ns  # noqa: E402
from ar_tracking.ros.player import ClockTicker  # noqa: E402
from bagfactory import write_turning_imu_bag  # noqa: E402
from conftest import spin_until  # noqa: E402


def collect(context, subs):
    listener = rclpy.create_node('listener', context=context)
    got = {topic: [] for topic, _ in subs}
    for topic, cls in subs:
        listener.create_subscription(cls, topic, got[topic].append, 500)
    return listener, got


def start(context, cls, listener, params):
    """Listener first, so that the replay (which starts at once) is not missed."""
    ex = SingleThreadedExecutor(context=context)
    ex.add_node(listener)
    spin_until(ex, lambda: False, 0.2)
    node = cls(context=context, parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])
    ex.add_node(node)
    return node, ex


def test_bag_replay_publishes_selected_topics_remapped_with_clock(ros_context, tmp_path):
    bag = write_turning_imu_bag(tmp_path / 'in.mcap', seconds=0.5)
    listener, got = collect(ros_context, [('renamed/raw', Imu), ('imu/mag', MagneticField), ('/clock', Clock)])
    # Give DDS time to match before the player starts: a slow rate spreads the 100 messages.
    node, ex = start(ros_context, BagReplayNode, listener, {
        'bag_path': str(bag), 'rate': 0.5, 'topics': ['/imu/data_raw', '/imu/mag'],
        'remap': ['/imu/data_raw:=renamed/raw']})
    try:
        assert spin_until(ex, lambda: len(got['renamed/raw']) >= 45 and len(got['imu/mag']) >= 45, 10)
        stamps = [stamp_ns(m.header) for m in got['renamed/raw']]
        assert stamps == sorted(stamps)
        assert got['/clock'] and stamp_ns(got['/clock'][-1].clock) >= stamps[0]
        # /clock at 100 Hz of bag time (clock_rate_hz), not before each of the 200 Hz of messages
        ticks = [stamp_ns(m.clock) for m in got['/clock']]
        assert all(b - a >= 10_000_000 for a, b in zip(ticks, ticks[1:])), ticks
    finally:
        node.close()
        node.destroy_node()
        listener.destroy_node()


def test_bag_replay_loops(ros_context, tmp_path):
    bag = write_turning_imu_bag(tmp_path / 'in.mcap', seconds=0.1)
    listener, got = collect(ros_context, [('imu/mag', MagneticField)])
    node, ex = start(ros_context, BagReplayNode, listener, {
        'bag_path': str(bag), 'rate': 1.0, 'loop': True, 'topics': ['/imu/mag']})
    try:
        assert spin_until(ex, lambda: len(got['imu/mag']) >= 25, 10)  # 10 per pass
        stamps = [stamp_ns(m.header) for m in got['imu/mag']]
        assert any(b < a for a, b in zip(stamps, stamps[1:]))  # the clock went back: a new pass
    finally:
        node.close()
        node.destroy_node()
        listener.destroy_node()


def test_camera_replay_plays_the_sample_bag(ros_context):
    bag = Path(__file__).resolve().parents[2] / 'bags' / 'rotation_sweep_authoring.mcap'
    if not bag.is_file():
        pytest.fail('sample bag missing from bags/')
    listener, got = collect(ros_context, [('camera/image_raw/compressed', CompressedImage),
                                          ('camera/camera_info', CameraInfo), ('imu/data_raw', Imu)])
    node, ex = start(ros_context, CameraReplayNode, listener, {'bag_path': str(bag), 'rate': 2.0})
    try:
        assert spin_until(ex, lambda: len(got['camera/image_raw/compressed']) >= 10 and len(got['camera/camera_info']) >= 10, 15)
        assert not got['imu/data_raw']  # camera topics only
        info = got['camera/camera_info'][0]
        assert (info.width, info.height) == (320, 240)
        assert stamp_ns(got['camera/image_raw/compressed'][0].header) == stamp_ns(info.header)
    finally:
        node.close()
        node.destroy_node()
        listener.destroy_node()


@pytest.mark.parametrize('content', ['missing', 'garbage'])
def test_replay_of_a_bad_bag_fails_with_one_clear_error(ros_context, tmp_path, content):
    path = tmp_path / 'bad.mcap'
    if content == 'garbage':
        path.write_bytes(b'\x89garbage' * 100)
    with pytest.raises(ValueError, match='bad.mcap'):
        BagReplayNode(context=ros_context, parameter_overrides=[Parameter('bag_path', value=str(path))])


def test_replay_cli_bad_bag_is_one_line(tmp_path):
    import subprocess
    import sys

    path = tmp_path / 'bad.mcap'
    path.write_bytes(b'nope')
    proc = subprocess.run([sys.executable, '-m', 'ar_tracking.cli', 'replay', str(path)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode != 0 and 'Traceback' not in proc.stderr
    assert any('bad.mcap' in line for line in proc.stderr.splitlines())


def test_camera_replay_node_publishes_raw_images(ros_context, tmp_path):
    """A raw-image bag (the first second of the sample bag's frames, decoded and written as
    rgb8 Image messages with their camera_info, as make_bag's raw format writes them; simulating
    a raw bag took ~5 s for its panorama): Image messages decode to the recorded pixels."""
    import cv2

    from ar_tracking.io.bags import BagReader, BagWriter
    from ar_tracking.sim.messages import Msgs

    sample = Path(__file__).resolve().parents[2] / 'bags' / 'rotation_sweep_authoring.mcap'
    if not sample.is_file():
        pytest.fail('sample bag missing from bags/')
    bag, msgs, recorded = tmp_path / 'raw.mcap', Msgs(), {}
    with BagReader(sample) as src, BagWriter(bag) as dst:
        for m in src.messages(['/camera/image_raw/compressed', '/camera/camera_info']):
            if len(recorded) == 30:
                break
            msg = src.deserialize(m)
            if m.topic == '/camera/camera_info':
                dst.write(m.topic, m.log_time_ns, m.rawdata, m.msgtype)
                continue
            rgb = cv2.cvtColor(cv2.imdecode(np.asarray(msg.data, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
            recorded[stamp_ns(msg.header)] = rgb
            dst.write('/camera/image_raw', m.log_time_ns, msgs.image(stamp_ns(msg.header), rgb))
    listener, got = collect(ros_context, [('camera/image_raw', Image)])
    node, ex = start(ros_context, CameraReplayNode, listener, {'bag_path': str(bag), 'rate': 1.0})
    try:
        assert spin_until(ex, lambda: len(got['camera/image_raw']) >= 10, 15)
        for img in got['camera/image_raw']:
            arr = image_to_array(img)
            assert arr.shape == (240, 320, 3) and arr.std() > 5
            assert np.array_equal(arr, recorded[stamp_ns(img.header)])
    finally:
        node.close()
        node.destroy_node()
        listener.destroy_node()


def test_clock_ticker_ticks_once_per_period_of_bag_time_and_when_time_goes_back():
    ticker = ClockTicker(10_000_000)
    stamps = (0, 4_000_000, 9_999_999, 10_000_000, 15_000_000, 25_000_000, 5_000_000, 6_000_000)
    assert [ticker.due(t) for t in stamps] == [True, False, False, True, False, True, True, False]
    every = ClockTicker(0)
    assert all(every.due(t) for t in (0, 0, 1, 1))
