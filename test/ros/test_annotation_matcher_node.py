"""annotation_matcher in-process: a store, a synthetic map and tiles in, markers out; bad input."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

rclpy = pytest.importorskip('rclpy')

from geometry_msgs.msg import TransformStamped  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import Image, NavSatFix, NavSatStatus  # noqa: E402
from visualization_msgs.msg import MarkerArray  # noqa: E402

from annotation_synth import GEO, annotation, make_case, tiles_of  # noqa: E402
from ar_tracking.core.annotations.store import SqliteAnnotationStore  # noqa: E402
from ar_tracking.nodes.annotation_matcher import AnnotationMatcherNode  # noqa: E402
from ar_tracking.ros.conversions import array_to_image, rotation_from_quaternion, to_stamp  # noqa: E402
from ar_tracking.ros.node_base import LATCHED_QOS  # noqa: E402
from conftest import spin_until  # noqa: E402

T0 = 1_700_000_000_000_000_000
CONFIG = Path(__file__).resolve().parents[2] / 'config' / 'annotation_matcher.yaml'
LAT, LON = 47.0458, 15.4251


def make_store(path: Path, case) -> Path:
    with SqliteAnnotationStore(path, create=True) as s:
        s.add([annotation(p, d, text=f'label {i}', lat=LAT, lon=LON) for i, (p, d) in enumerate(zip(case.patches, case.dirs))])
    return path


def fix_msg(t, lat=LAT, lon=LON, status=NavSatStatus.STATUS_FIX, sigma=3.0) -> NavSatFix:
    msg = NavSatFix()
    msg.header.stamp = to_stamp(t)
    msg.status.status = status
    msg.latitude, msg.longitude, msg.altitude = lat, lon, 350.0
    msg.position_covariance = [sigma ** 2, 0.0, 0.0, 0.0, sigma ** 2, 0.0, 0.0, 0.0, sigma ** 2]
    msg.position_covariance_type = NavSatFix.COVARIANCE_TYPE_DIAGONAL_KNOWN
    return msg


class Harness:
    def __init__(self, context, params):
        overrides = [Parameter(k, value=v) for k, v in params.items()]
        self.node = AnnotationMatcherNode(context=context, parameter_overrides=overrides)
        self.src = rclpy.create_node('test_source', context=context)
        self.markers: list[MarkerArray] = []
        self.alignments: list[TransformStamped] = []
        self.src.create_subscription(MarkerArray, 'annotations/markers', self.markers.append, LATCHED_QOS)
        self.src.create_subscription(TransformStamped, 'annotations/alignment', self.alignments.append, 10)
        self.pub_map = self.src.create_publisher(Image, 'panorama/image', LATCHED_QOS)
        self.pub_tiles = self.src.create_publisher(Image, 'panorama/tiles', LATCHED_QOS)
        self.pub_fix = self.src.create_publisher(NavSatFix, 'gps/fix', 10)
        self.ex = SingleThreadedExecutor(context=context)
        self.ex.add_node(self.node)
        self.ex.add_node(self.src)
        assert spin_until(self.ex, lambda: all(p.get_subscription_count() > 0 for p in (self.pub_map, self.pub_tiles, self.pub_fix)))

    def fix(self, t, lat=LAT, lon=LON, status=NavSatStatus.STATUS_FIX, sigma=3.0):
        self.pub_fix.publish(fix_msg(t, lat, lon, status, sigma))
        spin_until(self.ex, lambda: False, 0.05)

    def map(self, t, gray, mapped, encoding='mono16', tile_value=255):
        arr = np.where(mapped, np.clip(gray * 257.0, 1, 65535), 0).astype(np.uint16) if encoding == 'mono16' else gray
        img = array_to_image(arr, encoding)
        img.header.stamp = to_stamp(t)
        img.header.frame_id = 'panorama'
        tiles = array_to_image(np.where(tiles_of(mapped) > 0, tile_value, 0).astype(np.uint8), 'mono8')
        tiles.header.stamp = to_stamp(t)
        self.pub_map.publish(img)
        self.pub_tiles.publish(tiles)


def test_matches_store_annotations_in_the_map(ros_context, tmp_path):
    case = make_case(seed=11)
    store = make_store(tmp_path / 'a.db', case)
    h = Harness(ros_context, {'store_path': str(store), 'budget_ms': 1000.0})
    h.fix(T0)
    assert h.node.detector is not None and h.node.detector.n == 6
    h.map(T0 + 1, case.target, case.mapped)
    assert spin_until(h.ex, lambda: h.node.detector.tiles_done == int((tiles_of(case.mapped) > 0).sum()) and h.markers, 10.0)
    spin_until(h.ex, lambda: False, 0.2)
    last = h.markers[-1]
    texts = {m.text: m for m in last.markers if m.action == 0}
    assert len(texts) == 6
    for i, (u, v) in enumerate(case.truth_uv):
        m = texts[f'label {i}']
        d = np.array([m.pose.position.x, m.pose.position.y, m.pose.position.z])
        truth = GEO.unproject(np.array(u), np.array(v))
        assert np.degrees(math.acos(np.clip(d / np.linalg.norm(d) @ truth, -1, 1))) < 0.3
        assert m.ns in ('matched', 'inferred') and m.header.frame_id == 'panorama'
    assert h.alignments
    R = rotation_from_quaternion(h.alignments[-1].transform.rotation)
    assert np.degrees(np.arccos(np.clip((np.trace(R.T @ case.R_target_source) - 1) / 2, -1, 1))) < 0.2


def test_a_repainted_map_is_matched_again(ros_context, tmp_path):
    """panorama_mapper paints its map again once a rolling shutter's readout is known and says so
    by the finished tiles' value (255, then 254): what was matched in the old pixels is
    dropped and every finished tile is matched again; the same value again changes nothing."""
    case = make_case(seed=11)
    store = make_store(tmp_path / 'a.db', case)
    h = Harness(ros_context, {'store_path': str(store), 'budget_ms': 1000.0})
    h.fix(T0)
    n_tiles = int((tiles_of(case.mapped) > 0).sum())
    h.map(T0 + 1, case.target, case.mapped)
    first = h.node.detector
    assert spin_until(h.ex, lambda: first.tiles_done == n_tiles and h.markers, 10.0)
    h.map(T0 + 2, case.target, case.mapped)  # the same map, later: nothing new to match
    spin_until(h.ex, lambda: False, 0.2)
    assert h.node.detector is first and first.tiles_done == n_tiles
    h.markers.clear()
    h.map(T0 + 3, case.target, case.mapped, tile_value=254)
    assert spin_until(h.ex, lambda: h.node.detector is not first and h.node.detector.tiles_done == n_tiles
                      and h.markers, 10.0)
    spin_until(h.ex, lambda: False, 0.2)
    assert len({m.text for m in h.markers[-1].markers if m.action == 0}) == 6


def test_landmarks_are_loaded_matched_and_never_published(ros_context, tmp_path):
    from ar_tracking.core.annotations.store import Landmark

    case = make_case(seed=15, n=10)  # 4 annotations and 6 landmarks of panorama p1
    store = tmp_path / 'a.db'
    with SqliteAnnotationStore(store, create=True) as s:
        s.add([annotation(p, d, text=f'label {i}', lat=LAT, lon=LON)
               for i, (p, d) in enumerate(zip(case.patches[:4], case.dirs[:4]))])
        s.add_landmarks([Landmark('p1', p, d) for p, d in zip(case.patches[4:], case.dirs[4:])]
                        + [Landmark('other', case.patches[4], case.dirs[4])])  # not loaded
    h = Harness(ros_context, {'store_path': str(store), 'budget_ms': 1000.0})
    h.fix(T0)
    det = h.node.detector
    assert det is not None and det.n == 10 and list(det.landmark) == [False] * 4 + [True] * 6
    h.map(T0 + 1, case.target, case.mapped)
    assert spin_until(h.ex, lambda: det.tiles_done == int((tiles_of(case.mapped) > 0).sum()) and h.markers, 10.0)
    spin_until(h.ex, lambda: False, 0.2)
    texts = sorted(m.text for m in h.markers[-1].markers if m.action == 0)
    assert texts == [f'label {i}' for i in range(4)]
    _, al = det.result()
    assert sorted(p.index for p in al.landmarks) == list(range(4, 10))
    # Switched off, the node loads the annotations alone.
    off = AnnotationMatcherNode(context=ros_context, parameter_overrides=[
        Parameter('store_path', value=str(store)), Parameter('landmarks', value=False)])
    try:
        off.on_fix(fix_msg(T0))
        assert off.detector is not None and off.detector.n == 4 and not off.detector.landmark.any()
    finally:
        off.destroy_node()


def test_budget_spreads_the_work_over_frames(ros_context, tmp_path):
    case = make_case(seed=12)
    store = make_store(tmp_path / 'a.db', case)
    h = Harness(ros_context, {'store_path': str(store), 'budget_ms': 1.0, 'op_cost_ms': 0.5})
    h.fix(T0)
    h.map(T0 + 1, case.target, case.mapped)
    assert spin_until(h.ex, lambda: h.node.detector.tiles_done >= 1, 5.0)
    spin_until(h.ex, lambda: False, 0.2)
    assert h.node.detector.tiles_done == 1  # 2 ops of 6 annotations: one tile per frame
    assert len(h.node.detector.queue) > 0


def test_bad_input_is_logged_and_the_node_keeps_running(ros_context, tmp_path):
    case = make_case(seed=13)
    store = make_store(tmp_path / 'a.db', case)
    h = Harness(ros_context, {'store_path': str(store), 'budget_ms': 1000.0})
    h.fix(T0, status=NavSatStatus.STATUS_NO_FIX)
    h.fix(T0 + 1, lat=float('nan'))
    assert h.node.detector is None
    h.fix(T0 + 2, lat=LAT + 1.0)  # 111 km away: no annotations nearby
    assert h.node.detector is None
    h.map(T0 + 3, case.target.astype(np.float32), case.mapped, encoding='32FC1')  # wrong encoding
    bad_tiles = array_to_image(np.zeros((3, 5), np.uint8), 'mono8')
    bad_tiles.header.stamp = to_stamp(T0 + 4)
    h.pub_tiles.publish(bad_tiles)
    small = array_to_image(np.zeros((10, 10), np.uint16), 'mono16')
    small.header.stamp = to_stamp(T0 + 5)
    h.pub_map.publish(small)
    spin_until(h.ex, lambda: False, 0.2)
    assert h.node.gray is None and not h.markers
    assert all(s.failures == 0 for s in h.node.callback_stats.values())
    # A good fix and map still work afterwards (after the reload period).
    h.fix(T0 + 20_000_000_000)
    assert h.node.detector is not None
    h.map(T0 + 20_000_000_001, case.target, case.mapped)
    assert spin_until(h.ex, lambda: bool(h.markers), 10.0)


def test_missing_store_file_keeps_running(ros_context, tmp_path):
    h = Harness(ros_context, {'store_path': str(tmp_path / 'missing.db')})
    h.fix(T0)
    assert h.node.detector is None
    assert all(s.failures == 0 for s in h.node.callback_stats.values())
    assert not (tmp_path / 'missing.db').exists()


def test_poor_gps_loads_every_annotation(ros_context, tmp_path):
    case = make_case(seed=14)
    store = make_store(tmp_path / 'a.db', case)
    h = Harness(ros_context, {'store_path': str(store)})
    h.fix(T0, lat=LAT + 0.01, sigma=200.0)  # 1.1 km off, but GPS is poor
    assert h.node.detector is not None and h.node.detector.n == 6


def test_config_file_equals_declared_defaults(ros_context):
    params = yaml.safe_load(CONFIG.read_text())['annotation_matcher']['ros__parameters']
    node = AnnotationMatcherNode(context=ros_context)
    try:
        declared = {name for name in node._parameters if name not in ('use_sim_time', 'start_type_description_service')}
        assert set(params) == declared
        for key, value in params.items():
            assert node.get_parameter(key).value == value, key
    finally:
        node.destroy_node()


def test_alignment_parameters_reach_the_match_config(ros_context):
    overrides = {'gravity_alignment': False, 'gravity_v_px': 6.5, 'parallax_model': False, 'prior_alignment': False,
                 'parallax_gate_sigmas': 0.0, 'parallax_trim_sigmas': 1.5}
    node = AnnotationMatcherNode(context=ros_context, parameter_overrides=[Parameter(k, value=v) for k, v in overrides.items()])
    try:
        cfg = node.match_config
        assert (cfg.gravity_alignment, cfg.gravity_v_px, cfg.parallax_model, cfg.prior_alignment,
                cfg.parallax_gate_sigmas, cfg.parallax_trim_sigmas) == (False, 6.5, False, False, 0.0, 1.5)
    finally:
        node.destroy_node()
    node = AnnotationMatcherNode(context=ros_context)
    try:
        assert node.match_config.gravity_alignment and node.match_config.parallax_model
    finally:
        node.destroy_node()


def test_sensor_prior_is_the_mean_of_the_orientation_samples(ros_context):
    from scipy.spatial.transform import Rotation

    h = Harness(ros_context, {})
    pub = h.src.create_publisher(TransformStamped, 'orientation/panorama_in_world', 10)
    assert spin_until(h.ex, lambda: pub.get_subscription_count() > 0)
    base = Rotation.from_euler('zyx', [30.0, 2.0, -1.0], degrees=True)
    for k, tilt in enumerate((1.5, -1.5, 0.5, -0.5)):  # noisy samples, symmetric about base
        R = base * Rotation.from_rotvec([np.radians(tilt), 0.0, 0.0])
        msg = TransformStamped()
        msg.header.stamp = to_stamp(T0 + k * 50_000_000)
        msg.header.frame_id, msg.child_frame_id = 'enu', 'panorama'
        x, y, z, w = R.as_quat()
        msg.transform.rotation.x, msg.transform.rotation.y, msg.transform.rotation.z, msg.transform.rotation.w = x, y, z, w
        pub.publish(msg)
        assert spin_until(h.ex, lambda k=k: len(h.node.callback_stats['orientation/panorama_in_world'].durations_ms) > k)
    err = np.degrees((Rotation.from_matrix(h.node.R_enu_pano) * base.inv()).magnitude())
    assert err < 0.01  # a single sample is 0.5-1.5 deg off


def test_unsupported_alignment_publishes_approximate_labels_and_no_alignment(ros_context, tmp_path):
    """With fewer matches than min_support_matches the labels are marked approximate (grey, with
    their uncertainty), or not published at all with show_approximate false."""
    case = make_case(seed=11)
    store = make_store(tmp_path / 'a.db', case)
    for show in (True, False):
        h = Harness(ros_context, {'store_path': str(store), 'budget_ms': 1000.0, 'min_support_matches': 7,
                                  'show_approximate': show})
        h.fix(T0)
        h.map(T0 + 1, case.target, case.mapped)
        assert spin_until(h.ex, lambda h=h: h.node.detector.tiles_done == int((tiles_of(case.mapped) > 0).sum())
                          and h.markers, 10.0)
        spin_until(h.ex, lambda: False, 0.2)
        shown = [m for m in h.markers[-1].markers if m.action == 0]
        if show:
            assert len(shown) == 6 and {m.ns for m in shown} == {'approximate'}
            assert all(m.scale.x > 0 and m.color.g == m.color.r for m in shown)
        else:
            assert shown == []
        assert not h.alignments
        h.ex.remove_node(h.node)
        h.node.destroy_node()
        h.src.destroy_node()


def test_params_shorthand_without_ros_parameters_is_rejected_loudly(tmp_path):
    """README once showed `annotation_matcher: {store_path: ...}`, which ROS 2 ignores: it is an
    error that says where the parameter goes."""
    from ar_tracking.ros.params import ParamsError, load_params_file

    bad = tmp_path / 'p.yaml'
    bad.write_text(yaml.safe_dump({'annotation_matcher': {'store_path': 'notes.db'}}))
    with pytest.raises(ParamsError, match='store_path must go under ros__parameters'):
        load_params_file(bad)
    good = tmp_path / 'g.yaml'
    good.write_text(yaml.safe_dump({'annotation_matcher': {'ros__parameters': {'store_path': 'notes.db'}}}))
    assert load_params_file(good) == {'annotation_matcher': {'store_path': 'notes.db'}}


def test_sensor_prior_weighs_each_sample_by_its_inverse_heading_variance(ros_context):
    from scipy.spatial.transform import Rotation
    from sensor_msgs.msg import Imu

    h = Harness(ros_context, {})
    good = Rotation.from_euler('zyx', [30.0, 2.0, -1.0], degrees=True)
    early = good * Rotation.from_euler('z', 3.0, degrees=True)  # the filter's first, poorer estimate
    cam = Rotation.from_euler('zyx', [10.0, 0.0, 5.0], degrees=True)  # camera in the panorama
    for k, (R, sigma_deg) in enumerate(((early, 3.0), (good, 0.3))):
        t = T0 + k * 50_000_000
        po = TransformStamped()
        po.header.stamp = to_stamp(t)
        x, y, z, w = cam.as_quat()
        po.transform.rotation.x, po.transform.rotation.y, po.transform.rotation.z, po.transform.rotation.w = x, y, z, w
        h.node.on_panorama_orientation(po)
        imu = Imu()
        imu.header.stamp = to_stamp(t)
        x, y, z, w = (R * cam).as_quat()
        imu.orientation.x, imu.orientation.y, imu.orientation.z, imu.orientation.w = x, y, z, w
        imu.orientation_covariance[0] = imu.orientation_covariance[4] = 1e-4
        imu.orientation_covariance[8] = np.radians(sigma_deg) ** 2
        h.node.on_global(imu)
    err = np.degrees((Rotation.from_matrix(h.node.R_enu_pano) * good.inv()).magnitude())
    assert err < 3.0 / 50  # weights 1:100 put it 3/101 deg from the good sample; equal ones 1.5
