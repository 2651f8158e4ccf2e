"""panorama_mapper in-process: synthetic frames in, orientation / map / tiles out; bad input."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

rclpy = pytest.importorskip('rclpy')

from geometry_msgs.msg import TransformStamped  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import CameraInfo, CompressedImage, Image  # noqa: E402

from ar_tracking.nodes.panorama_mapper import PanoramaMapperNode  # noqa: E402
from ar_tracking.ros.conversions import array_to_image, rotation_from_quaternion, stamp_ns, to_stamp  # noqa: E402
from ar_tracking.ros.node_base import LATCHED_QOS  # noqa: E402
from conftest import spin_until  # noqa: E402
from panorama_synth import H, K, W, CylinderWorld, angle_deg, sweep  # noqa: E402

T0 = 1_700_000_000_000_000_000
DT = 33_333_333
CONFIG = Path(__file__).resolve().parents[2] / 'config' / 'panorama_mapper.yaml'


class Harness:
    def __init__(self, context, params=None):
        overrides = [Parameter(k, value=v) for k, v in (params or {}).items()]
        self.node = PanoramaMapperNode(context=context, parameter_overrides=overrides)
        self.src = rclpy.create_node('test_source', context=context)
        self.out: list[TransformStamped] = []
        self.maps: list[Image] = []
        self.tiles: list[Image] = []
        self.src.create_subscription(TransformStamped, 'panorama/orientation', self.out.append, 100)
        self.src.create_subscription(Image, 'panorama/image', self.maps.append, LATCHED_QOS)
        self.src.create_subscription(Image, 'panorama/tiles', self.tiles.append, LATCHED_QOS)
        self.pub_img = self.src.create_publisher(Image, 'camera/image_raw', 50)
        self.pub_cmp = self.src.create_publisher(CompressedImage, 'camera/image_raw/compressed', 50)
        self.pub_info = self.src.create_publisher(CameraInfo, 'camera/camera_info', 50)
        self.ex = SingleThreadedExecutor(context=context)
        self.ex.add_node(self.node)
        self.ex.add_node(self.src)
        assert spin_until(self.ex, lambda: all(p.get_subscription_count() > 0 for p in (self.pub_img, self.pub_cmp, self.pub_info))
                          and self.node.pub_orientation.get_subscription_count() > 0)

    def info(self, t, w=W, h=H, d=(), model='plumb_bob'):
        msg = CameraInfo()
        msg.header.stamp = to_stamp(t)
        msg.header.frame_id = 'camera_optical'
        msg.width, msg.height = w, h
        msg.k = [float(x) for x in K.ravel()]
        msg.distortion_model = model
        msg.d = [float(x) for x in d]
        self.pub_info.publish(msg)
        spin_until(self.ex, lambda: False, 0.01)

    def image(self, t, arr, encoding='mono8', compressed=False):
        if compressed:
            msg = CompressedImage()
            msg.format = 'jpeg'
            msg.data = cv2.imencode('.jpg', arr, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()
        else:
            msg = array_to_image(arr, encoding)
        msg.header.stamp = to_stamp(t)
        msg.header.frame_id = 'camera_optical'
        (self.pub_cmp if compressed else self.pub_img).publish(msg)

    def wait(self, n, timeout_s=5.0):
        return spin_until(self.ex, lambda: len(self.out) >= n, timeout_s)

    def settle(self, s=0.2):
        spin_until(self.ex, lambda: False, s)

    def close(self):
        self.ex.shutdown()
        self.node.destroy_node()
        self.src.destroy_node()


@pytest.fixture(scope='module')
def world():
    return CylinderWorld(1)


def test_config_file_matches_declared_parameters(ros_context):
    params = yaml.safe_load(CONFIG.read_text())['panorama_mapper']['ros__parameters']
    node = PanoramaMapperNode(context=ros_context)
    try:
        for key, value in params.items():
            assert node.has_parameter(key), key
            assert node.get_parameter(key).value == value, key
            assert node.describe_parameter(key).description
    finally:
        node.destroy_node()


def test_publishes_orientation_map_and_tiles(ros_context, world):
    h = Harness(ros_context, {'publish_rate_hz': 2.0})
    try:
        Rs = sweep(24, 1.5)
        for k, R in enumerate(Rs):
            t = T0 + k * DT
            h.info(t)
            if k % 2:
                h.image(t, world.render(R), 'mono8')
            else:  # the compressed topic works the same (jpeg, BGR)
                h.image(t, cv2.cvtColor(world.render(R), cv2.COLOR_GRAY2BGR), compressed=True)
            assert h.wait(k + 1), k
        assert len(h.out) == 24
        for k, (msg, R) in enumerate(zip(h.out, Rs)):
            assert stamp_ns(msg.header) == T0 + k * DT
            assert msg.header.frame_id == 'panorama' and msg.child_frame_id == 'camera_optical'
            assert angle_deg(rotation_from_quaternion(msg.transform.rotation), Rs[0].T @ R) < 0.3
        assert spin_until(h.ex, lambda: len(h.maps) >= 2 and len(h.tiles) >= 2)
        m, t = h.maps[-1], h.tiles[-1]
        assert (m.encoding, m.width, m.height) == ('mono16', 2048, 512)
        assert (t.encoding, t.width, t.height) == ('mono8', 32, 8)
        assert stamp_ns(m.header) == stamp_ns(t.header) == T0 + 16 * DT  # 2 Hz by image stamps
        tiles = np.frombuffer(bytes(t.data), np.uint8)
        assert set(np.unique(tiles)) == {0, 255}
    finally:
        h.close()


LENS = np.array([-0.25, 0.07, 0.0, 0.0, 0.0])  # plumb_bob: the corners pulled in by ~8 %


def _through_the_lens(world: CylinderWorld, R: np.ndarray) -> np.ndarray:
    """The frame a camera with the lens (K, LENS) takes of ``world`` at orientation R: each pixel
    samples the world along its own (undistorted) ray."""
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    xy = cv2.undistortPoints(np.stack([xx.ravel(), yy.ravel()], -1).reshape(-1, 1, 2), K, LENS).reshape(-1, 2)
    rays = np.column_stack([xy, np.ones(len(xy))]).reshape(H, W, 3)
    u, v = world.geo.project(rays @ R.T)
    img = cv2.remap(world.tex, u.astype(np.float32), v.astype(np.float32), cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)


def test_a_lens_distortion_in_camera_info_is_undone_before_tracking(ros_context, world, capfd):
    """Frames through a lens with barrel distortion: with its coefficients in camera_info the
    node rectifies them (one log line) and tracks every frame of a 40 deg pan within 0.05 deg;
    told nothing of the lens, it loses most of them (bearings near the edges are bent by
    degrees, so no rotation explains the matches)."""
    Rs = sweep(40, 1.0)
    worst = {}
    for name, d in (('told', LENS), ('not told', ())):
        h = Harness(ros_context)
        try:
            for k, R in enumerate(Rs):
                h.info(T0 + k * DT, d=d)
                h.image(T0 + k * DT, _through_the_lens(world, R))
                assert spin_until(h.ex, lambda n=h.node, k=k: n.published + n.lost >= k + 1, 5.0), k
            h.settle()
            errors = [angle_deg(rotation_from_quaternion(m.transform.rotation), Rs[0].T @ Rs[(stamp_ns(m.header) - T0) // DT])
                      for m in h.out]
            worst[name] = (max(errors) if errors else float('inf'), len(errors))
        finally:
            h.close()
    assert worst['told'][0] < 0.05 and worst['told'][1] == 40, worst
    assert worst['not told'][1] < 20, worst
    assert 'frames are rectified to a pinhole camera' in capfd.readouterr().err


def test_bad_input_is_skipped_and_node_keeps_running(ros_context, world):
    h = Harness(ros_context)
    try:
        Rs = sweep(12, 1.0, seed=3)
        good = 0
        for k, R in enumerate(Rs):
            t = T0 + k * DT
            h.info(t)
            h.image(t, world.render(R))
            good += 1
            assert h.wait(good)
        t = T0 + 12 * DT
        h.info(t)
        h.image(t, np.zeros((100, 120), np.uint8))  # not the size camera_info says
        h.settle()
        t += DT
        h.info(t)
        bad = array_to_image(world.render(Rs[-1]), 'mono8')
        bad.encoding = 'yuv422_weird'
        bad.header.stamp = to_stamp(t)
        h.pub_img.publish(bad)  # unknown encoding
        h.settle()
        t += DT
        h.info(t)
        h.image(t, np.full((H, W), 255, np.uint8))  # a white wall: lost, nothing published
        h.settle()
        t += DT
        h.image(t, world.render(Rs[-1]))  # no camera_info for this stamp, no fallback
        h.settle()
        t += DT
        h.info(t, d=[0.1, 0.0, 0.0])  # three distortion coefficients: camera_info ignored
        h.image(t, world.render(Rs[-1]))
        h.settle()
        assert len(h.out) == good
        t += DT
        h.info(t)
        h.image(t, world.render(Rs[-1]))  # recovers (re-localises) on a good frame
        assert h.wait(good + 1)
        assert stamp_ns(h.out[-1].header) == t
        assert angle_deg(rotation_from_quaternion(h.out[-1].transform.rotation), Rs[0].T @ Rs[-1]) < 0.3
        q = h.out[-1].transform.rotation
        assert np.all(np.isfinite([q.x, q.y, q.z, q.w]))
    finally:
        h.close()


def test_fallback_intrinsics_without_camera_info(ros_context, world):
    h = Harness(ros_context, {'fallback_hfov_deg': 60.0})
    try:
        Rs = sweep(6, 1.0)
        for k, R in enumerate(Rs):
            h.image(T0 + k * DT, world.render(R))
            assert h.wait(k + 1)
        assert angle_deg(rotation_from_quaternion(h.out[-1].transform.rotation), Rs[0].T @ Rs[-1]) < 0.3
    finally:
        h.close()


def test_edr_correction_parameter_reaches_the_core(ros_context):
    node = PanoramaMapperNode(context=ros_context)
    try:
        assert node.core.config.edr_correction == 'overlap'
    finally:
        node.destroy_node()
    node = PanoramaMapperNode(context=ros_context, parameter_overrides=[Parameter('edr_correction', value='offset')])
    try:
        assert node.core.config.edr_correction == 'offset'
    finally:
        node.destroy_node()
    with pytest.raises(ValueError, match='edr_correction'):
        PanoramaMapperNode(context=ros_context, parameter_overrides=[Parameter('edr_correction', value='affine')])


def test_readout_estimate_parameter_and_its_log_line(ros_context, monkeypatch):
    """estimate_readout reaches the core; a readout the core starts to use is logged once, and
    again only when it moves by 2 ms or more, or back to a global shutter; a repainted map once."""
    node = PanoramaMapperNode(context=ros_context, parameter_overrides=[Parameter('estimate_readout', value=False),
                                                                        Parameter('repaint_max_mb', value=0.0)])
    try:
        assert node.core.config.estimate_readout is False and node.core.config.repaint_max_mb == 0.0
    finally:
        node.destroy_node()
    node = PanoramaMapperNode(context=ros_context)
    lines: list[str] = []

    class Log:
        def info(self, text: str) -> None:
            lines.append(text)

    monkeypatch.setattr(node, 'get_logger', lambda: Log())
    try:
        assert node.core.config.estimate_readout is True
        for value in (0.0281, 0.0290, 0.0300, 0.0305, 0.0310, 0.0, 0.0):
            node.core.readout_s = value
            node._log_readout()
        assert len(lines) == 3, lines
        assert 'readout 28.1' in lines[0] and 'readout 30.5' in lines[1] and 'global shutter' in lines[2]
        node.core.map.generation = 1  # the core painted its map again (core/panorama/repaint.py)
        node._log_readout()
        node._log_readout()
        assert len(lines) == 4 and 'painted again' in lines[3], lines
    finally:
        node.destroy_node()
