"""Tests of the rotation_sweep simulator: bag layout, determinism and the physics of its sensors.

Bags are short (1-4 s) and the world/panorama of a seed is cached by the simulator, so the whole
file runs in well under a minute; the 60 s properties (full turn, rate limit) are checked on the
closed-form trajectory without rendering.
"""
from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from ar_tracking.core.rotations import (camera_heading_pitch_roll_deg, matrix_to_quat_xyzw,
                                        quat_xyzw_to_matrix)
from ar_tracking.io.bags import BagReader, stamp_to_ns
from ar_tracking.sim import bagmaker, rotation_sweep as rs
from ar_tracking.sim.bagmaker import SCENARIOS, SimError, make_bag
from ar_tracking.sim.world import FrameRenderer, PinholeCamera

SEED = 1
DURATION_S = 4.0


@pytest.fixture(scope='module')
def bag_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp('sim')


@pytest.fixture(scope='module')
def authoring_bag(bag_dir: Path) -> Path:
    return make_bag('rotation_sweep', bag_dir / 'authoring', seed=SEED, duration_s=DURATION_S)


@pytest.fixture(scope='module')
def browsing_bag(bag_dir: Path) -> Path:
    return make_bag('rotation_sweep', bag_dir / 'browsing.mcap', seed=SEED, duration_s=1.0,
                    session='browsing')


@pytest.fixture(scope='module')
def short_bag(bag_dir: Path) -> Path:
    return make_bag('rotation_sweep', bag_dir / 'short.mcap', seed=SEED, duration_s=1.0)


@pytest.fixture(scope='module')
def data(authoring_bag: Path) -> dict[str, list]:
    """Every message of the authoring bag, decoded, per topic: (log time ns, message)."""
    out: dict[str, list] = {}
    with BagReader(authoring_bag) as bag:
        for topic in bag.topics:
            out[topic] = bag.read_all(topic)
    return out


def _vec(v) -> np.ndarray:
    return np.array([v.x, v.y, v.z])


def _quat(q) -> np.ndarray:
    return np.array([q.x, q.y, q.z, q.w])


def _calibration(bag: Path) -> dict:
    side = bagmaker.sidecar_path(bag)
    return yaml.safe_load(side.read_text())['imu_magnetometer']['ros__parameters']


def _imu_arrays(data: dict[str, list]) -> dict[str, np.ndarray]:
    imu = data['/imu/data_raw']
    return {
        't': np.array([t for t, _ in imu]) * 1e-9,
        'gyro': np.array([_vec(m.angular_velocity) for _, m in imu]),
        'accel': np.array([_vec(m.linear_acceleration) for _, m in imu]),
        'mag': np.array([_vec(m.magnetic_field) for _, m in data['/imu/mag']]),
        'R': quat_xyzw_to_matrix(np.array([_quat(m.transform.rotation)
                                           for _, m in data['/ground_truth/orientation']])),
        'defl': np.array([m.vector.x for _, m in data['/ground_truth/mag_disturbance']]),
    }


# --------------------------------------------------------------------------------------------
# Bag layout


def test_topics_types_rates_and_frames(authoring_bag: Path, data: dict[str, list]) -> None:
    assert authoring_bag.suffix == '.mcap' and authoring_bag.is_file()
    expected = {
        '/camera/image_raw': ('sensor_msgs/msg/Image', 30, 'camera_optical'),
        '/camera/camera_info': ('sensor_msgs/msg/CameraInfo', 30, 'camera_optical'),
        '/imu/data_raw': ('sensor_msgs/msg/Imu', 100, 'imu'),
        '/imu/mag': ('sensor_msgs/msg/MagneticField', 100, 'imu'),
        '/gps/fix': ('sensor_msgs/msg/NavSatFix', 1, 'gps'),
        '/ground_truth/orientation': ('geometry_msgs/msg/TransformStamped', 100, 'enu'),
        '/ground_truth/pose': ('geometry_msgs/msg/PoseStamped', 100, 'enu'),
        '/ground_truth/mag_disturbance': ('geometry_msgs/msg/Vector3Stamped', 100, 'enu'),
    }
    with BagReader(authoring_bag) as bag:
        topics = bag.topics
    assert topics['/tf_static'] == 'tf2_msgs/msg/TFMessage'
    assert topics['/ground_truth/annotations'] == 'visualization_msgs/msg/MarkerArray'
    for topic, (msgtype, rate, frame) in expected.items():
        assert topics[topic] == msgtype
        msgs = data[topic]
        assert len(msgs) == int(DURATION_S * rate), topic
        stamps = np.array([stamp_to_ns(m.header.stamp) for _, m in msgs])
        assert np.array_equal(stamps, [t for t, _ in msgs]), 'log time must equal header stamp'
        assert np.allclose(np.diff(stamps), 1e9 / rate, atol=1), topic
        assert {m.header.frame_id for _, m in msgs} == {frame}, topic
    # IMU, magnetometer and ground truth share stamps; camera_info pairs with every image.
    imu_stamps = [t for t, _ in data['/imu/data_raw']]
    for topic in ('/imu/mag', '/ground_truth/orientation', '/ground_truth/mag_disturbance'):
        assert [t for t, _ in data[topic]] == imu_stamps
    assert [t for t, _ in data['/camera/camera_info']] == [t for t, _ in data['/camera/image_raw']]
    first = data['/imu/data_raw'][0][0]
    assert data['/camera/image_raw'][0][0] == first == bagmaker.START_NS
    (t_tf, tf), = data['/tf_static']
    assert t_tf == first
    (tr,) = tf.transforms
    assert (tr.header.frame_id, tr.child_frame_id) == ('imu', 'camera_optical')
    assert np.allclose(quat_xyzw_to_matrix(_quat(tr.transform.rotation)), rs.R_IMU_CAM)
    assert np.allclose(_vec(tr.transform.translation), 0)
    assert all(m.child_frame_id == 'camera_optical' for _, m in data['/ground_truth/orientation'])


def test_message_contents(data: dict[str, list]) -> None:
    _, info = data['/camera/camera_info'][0]
    assert (info.width, info.height, info.distortion_model) == (320, 240, 'plumb_bob')
    assert np.all(info.d == 0) and len(info.d) == 5
    hfov = math.degrees(2 * math.atan(info.width / 2 / info.k[0]))
    assert 55 < hfov < 65 and info.k[0] == info.k[4] and info.p[0] == info.k[0]
    _, img = data['/camera/image_raw'][0]
    assert (img.encoding, img.step, len(img.data)) == ('rgb8', 960, 960 * 240)
    _, imu = data['/imu/data_raw'][0]
    assert imu.orientation_covariance[0] == -1
    assert np.allclose(np.diag(imu.angular_velocity_covariance.reshape(3, 3)), 1e-4)
    assert np.allclose(np.diag(imu.linear_acceleration_covariance.reshape(3, 3)), 0.05 ** 2)
    _, fix = data['/gps/fix'][0]
    assert fix.status.status == 0 and fix.status.service == 1
    assert fix.position_covariance_type == 2 and fix.position_covariance[0] == pytest.approx(9.0)
    assert 46.9 < fix.latitude < 47.2 and 15.3 < fix.longitude < 15.6
    _, pose = data['/ground_truth/pose'][0]
    _, gt = data['/ground_truth/orientation'][0]
    assert np.allclose(_quat(pose.pose.orientation), _quat(gt.transform.rotation))
    (_, arr), = data['/ground_truth/annotations']
    assert 4 <= len(arr.markers) <= 6
    for mk in arr.markers:
        assert (mk.type, mk.ns, mk.header.frame_id) == (9, 'ground_truth', 'enu')
        assert mk.text and mk.color.a == 1.0 and mk.scale.z == 1.0 and mk.pose.orientation.w == 1
        dist = np.linalg.norm(_vec(mk.pose.position))
        assert 10.0 < dist < 120.0
    assert len({mk.text for mk in arr.markers}) == len(arr.markers)


def test_sidecar_params(authoring_bag: Path) -> None:
    side = authoring_bag.with_name('authoring.params.yaml')
    assert side.is_file()
    p = _calibration(authoring_bag)
    assert set(p) == {'gyro_bias', 'accel_bias', 'hard_iron_offset', 'soft_iron_matrix',
                      'declination_rad', 'expected_field_t', 'expected_dip_rad'}
    assert len(p['soft_iron_matrix']) == 9 and all(type(v) is float for v in p['soft_iron_matrix'])
    assert p['expected_field_t'] == pytest.approx(48e-6) and p['expected_dip_rad'] == 1.117
    truth = rs.make_scenario(SEED, 'authoring', DURATION_S).errors
    rel = np.abs(np.array(p['gyro_bias']) / truth.gyro_bias_rad_s - 1)
    assert np.all((rel > 0.005) & (rel < 0.035)), 'close to, not exactly, the truth'
    assert np.allclose(np.array(p['soft_iron_matrix']).reshape(3, 3) @ truth.soft_iron, np.eye(3),
                       atol=0.01)


def test_same_seed_same_bytes_different_seed_different(bag_dir: Path, authoring_bag: Path,
                                                       short_bag: Path) -> None:
    bagmaker.session_view.cache_clear()  # regenerate the world and panorama from scratch
    bagmaker._world.cache_clear()
    again = make_bag('rotation_sweep', bag_dir / 'again.mcap', seed=SEED, duration_s=DURATION_S)
    assert again.read_bytes() == authoring_bag.read_bytes()
    other = make_bag('rotation_sweep', bag_dir / 'other.mcap', seed=SEED + 1, duration_s=1.0)
    assert other.read_bytes() != short_bag.read_bytes()
    with BagReader(other) as a, BagReader(short_bag) as b:
        img_a = a.read_all('/camera/image_raw')[0][1].data
        img_b = b.read_all('/camera/image_raw')[0][1].data
    assert np.mean(np.abs(img_a.astype(int) - img_b.astype(int))) > 10


def test_bad_arguments(tmp_path: Path, authoring_bag: Path) -> None:
    assert 'rotation_sweep' in SCENARIOS
    cases = [dict(scenario='nope'), dict(session='lunch'), dict(storage='zip'),
             dict(image_format='png'), dict(duration_s=-1.0), dict(duration_s=float('nan')),
             dict(seed=-3)]
    for bad in cases:
        kwargs = dict(scenario='rotation_sweep', out=tmp_path / 'x.mcap')
        kwargs.update(bad)
        with pytest.raises(SimError) as err:
            make_bag(kwargs.pop('scenario'), kwargs.pop('out'), **kwargs)
        assert '\n' not in str(err.value)
    with pytest.raises(SimError, match='already exists'):
        make_bag('rotation_sweep', authoring_bag, seed=SEED, duration_s=1.0)


# --------------------------------------------------------------------------------------------
# Sensor physics


def test_gyro_integrates_to_ground_truth(authoring_bag: Path, data: dict[str, list]) -> None:
    a = _imu_arrays(data)
    bias = np.array(_calibration(authoring_bag)['gyro_bias'])
    w_cam = (a['gyro'] - bias) @ rs.R_IMU_CAM  # imu -> camera_optical (R_IMU_CAM is symmetric)
    from scipy.spatial.transform import Rotation
    R = Rotation.from_matrix(a['R'][0])
    dt = np.diff(a['t'])
    for k in range(len(dt)):
        R = R * Rotation.from_rotvec(0.5 * (w_cam[k] + w_cam[k + 1]) * dt[k])
    err = math.degrees((R.inv() * Rotation.from_matrix(a['R'][-1])).magnitude())
    turned = math.degrees(Rotation.from_matrix(a['R'][0].T @ a['R'][-1]).magnitude())
    assert err < 1.0, f'{err:.2f} deg after {turned:.0f} deg of rotation'
    raw_R = Rotation.from_matrix(a['R'][0])  # without the bias correction it drifts
    for k in range(len(dt)):
        raw_R = raw_R * Rotation.from_rotvec(a['gyro'][k] @ rs.R_IMU_CAM * dt[k])
    assert math.degrees((raw_R.inv() * Rotation.from_matrix(a['R'][-1])).magnitude()) > 1.5


def test_accelerometer_points_up(authoring_bag: Path, data: dict[str, list]) -> None:
    a = _imu_arrays(data)
    bias = np.array(_calibration(authoring_bag)['accel_bias'])
    f = a['accel'] - bias
    up_imu = np.einsum('ij,njk,k->ni', rs.R_IMU_CAM, np.swapaxes(a['R'], 1, 2), [0, 0, 1.0])
    cos = np.sum(f * up_imu, axis=1) / np.linalg.norm(f, axis=1)
    ang = np.degrees(np.arccos(np.clip(cos, -1, 1)))
    assert np.median(ang) < 1.0 and np.percentile(ang, 99) < 2.0
    assert np.median(np.linalg.norm(f, axis=1)) == pytest.approx(9.81, abs=0.1)


def _tilt_compensated_heading_deg(accel: np.ndarray, mag: np.ndarray) -> np.ndarray:
    """Camera heading from gravity + magnetic field (TRIAD), as a compass app does."""
    up = accel / np.linalg.norm(accel, axis=1, keepdims=True)
    east = np.cross(mag, up)
    east /= np.linalg.norm(east, axis=1, keepdims=True)
    north = np.cross(up, east)
    R_enu_imu = np.stack([east, north, up], axis=1)
    heading, _, _ = camera_heading_pitch_roll_deg(R_enu_imu @ rs.R_IMU_CAM)
    return heading


def test_magnetometer_heading_and_disturbance(authoring_bag: Path, data: dict[str, list]
                                              ) -> None:
    a = _imu_arrays(data)
    p = _calibration(authoring_bag)
    S = np.array(p['soft_iron_matrix']).reshape(3, 3)
    mag = (a['mag'] - np.array(p['hard_iron_offset'])) @ S.T
    assert np.median(np.linalg.norm(mag, axis=1)) == pytest.approx(48e-6, rel=0.05)
    heading = _tilt_compensated_heading_deg(a['accel'] - np.array(p['accel_bias']), mag)
    true_heading, _, _ = camera_heading_pitch_roll_deg(a['R'])
    err = (heading - true_heading + 180) % 360 - 180
    defl = np.degrees(a['defl'])
    calm, disturbed = np.abs(defl) < 0.05, np.abs(defl) > 2.0
    assert calm.sum() > 50 and disturbed.sum() > 30, 'the bag must contain a disturbance'
    assert np.median(np.abs(err[calm])) < 1.5 and np.percentile(np.abs(err[calm]), 99) < 4.0
    assert np.median(np.abs(err[disturbed] - defl[disturbed])) < 1.5
    assert np.median(np.abs(err[disturbed])) > 1.5  # the disturbance really moves the compass


def test_disturbance_schedule_and_truth() -> None:
    scn = rs.make_scenario(5, 'authoring', 60.0)
    d = scn.disturbances
    assert 3 <= len(d.start_s) <= 5
    t = np.arange(0, 60, 0.01)
    imu = rs.simulate_imu(scn, t)
    peaks = [np.max(np.abs(imu.deflection_rad[(t >= s) & (t <= s + w)]))
             for s, w in zip(d.start_s, d.duration_s)]
    assert all(math.radians(1.9) < pk < math.radians(10.1) for pk in peaks)
    assert np.all(np.abs(np.diff(imu.deflection_rad)) < math.radians(0.5)), 'smooth onsets'
    # Some events change |B| too; without disturbance the truth field is 48 uT, 64 deg dip.
    assert np.max(np.abs(imu.extra_field_t)) > 0.5e-6
    b = scn.earth.vector_enu
    assert np.linalg.norm(b) == pytest.approx(48e-6)
    assert math.degrees(math.atan2(-b[2], math.hypot(b[0], b[1]))) == pytest.approx(64.0)


def test_trajectory_covers_full_turn_within_rate_limit() -> None:
    t = np.arange(0.0, 60.0, 0.001)
    for seed in range(4):
        for session in ('authoring', 'browsing'):
            tr = rs.make_trajectory(seed, session, 60.0)
            heading, pitch, roll = tr.angles(t)
            rate = np.degrees(np.abs(tr.heading(t, 1)))
            assert abs(math.degrees(heading[-1] - heading[0])) > 360.0
            assert rate.max() <= 90.0 and rate.max() > 70.0
            assert np.degrees(np.abs(pitch)).max() <= 21.0 and np.degrees(pitch).std() > 3.0
            assert np.degrees(np.abs(roll)).max() <= 6.0
            sway = np.linalg.norm(tr.position(t[::50]) - tr.spot_enu, axis=1)
            assert sway.max() < 0.08
    tr = rs.make_trajectory(0, 'authoring', 60.0)
    starts = {round(rs.make_trajectory(s, 'authoring', 60.0).heading0_rad, 3) for s in range(5)}
    assert len(starts) == 5, 'start heading differs per seed'
    # The angles are the heading/pitch/roll that the rotations module reads back.
    tq = np.linspace(1, 59, 200)
    h, p, r = camera_heading_pitch_roll_deg(tr.R_enu_cam(tq))
    hh, pp, rr = (np.degrees(x) for x in tr.angles(tq))
    assert np.allclose((h - hh + 180) % 360 - 180, 0, atol=1e-6)
    assert np.allclose(p, pp, atol=1e-6) and np.allclose(r, rr, atol=1e-6)
    # Exact angular velocity equals the finite difference of the orientation.
    from scipy.spatial.transform import Rotation
    eps = 1e-5
    fd = (Rotation.from_matrix(tr.R_enu_cam(tq - eps)).inv()
          * Rotation.from_matrix(tr.R_enu_cam(tq + eps))).as_rotvec() / (2 * eps)
    assert np.allclose(fd, tr.omega_cam(tq), atol=1e-6)


# --------------------------------------------------------------------------------------------
# Images and sessions


def _gray_frames(data: dict[str, list]) -> list[np.ndarray]:
    return [cv2.cvtColor(np.frombuffer(m.data, np.uint8).reshape(m.height, m.width, 3),
                         cv2.COLOR_RGB2GRAY) for _, m in data['/camera/image_raw']]


def test_images_are_textured(data: dict[str, list]) -> None:
    fast = cv2.FastFeatureDetector_create(threshold=20)
    frames = _gray_frames(data)
    counts = [len(fast.detect(g)) for g in frames]
    assert min(counts) > 100
    assert min(float(g.std()) for g in frames) > 15
    assert len({int(g.mean()) for g in frames}) > 3  # exposure, motion: frames differ


def test_whole_sweep_textured_in_both_sessions() -> None:
    """Every 20th frame of a 60 s sweep, rendered directly: FAST corners everywhere."""
    fast = cv2.FastFeatureDetector_create(threshold=20)
    cam = PinholeCamera()
    t = np.arange(0, 60, 20 / 30)
    for session in ('authoring', 'browsing'):
        _, light, pano = bagmaker.session_view(SEED, session)
        renderer = FrameRenderer(pano, light, cam, np.random.default_rng(0))
        tr = rs.make_trajectory(SEED, session, 60.0)
        for R in tr.R_enu_cam(t):
            g = cv2.cvtColor(renderer.render(R[None], 0.5, np.ones(3)), cv2.COLOR_RGB2GRAY)
            assert len(fast.detect(g)) > 80 and g.std() > 12, session


def test_browsing_same_spot_other_light(browsing_bag: Path, data: dict[str, list]) -> None:
    with BagReader(browsing_bag) as bag:
        (_, arr), = bag.read_all('/ground_truth/annotations')
        poses = bag.read_all('/ground_truth/pose')
        fixes = bag.read_all('/gps/fix')
    (_, ref), = data['/ground_truth/annotations']
    assert [m.text for m in arr.markers] == [m.text for m in ref.markers]
    assert all(np.allclose(_vec(a.pose.position), _vec(b.pose.position))
               for a, b in zip(arr.markers, ref.markers))
    pos_b = np.array([_vec(m.pose.position) for _, m in poses])
    pos_a = np.array([_vec(m.pose.position) for _, m in data['/ground_truth/pose']])
    assert np.all(np.linalg.norm(pos_b - pos_a.mean(0), axis=1) < 2.0)
    assert np.linalg.norm(pos_b.mean(0) - pos_a.mean(0)) > 0.2  # not the very same point
    assert abs(fixes[0][1].latitude - data['/gps/fix'][0][1].latitude) < 1e-3
    # The same view under both suns, as the camera (with its auto exposure) shows it.
    cam = PinholeCamera()
    anchor = np.array([_vec(m.pose.position) for m in ref.markers])[0]
    fwd = anchor / np.linalg.norm(anchor)
    right = np.cross(fwd, [0, 0, 1.0])
    right /= np.linalg.norm(right)
    R = np.stack([right, np.cross(fwd, right), fwd], axis=1)  # look at the first anchor
    views = {}
    for session in ('authoring', 'browsing'):
        scn = rs.make_scenario(SEED, session, 1.0)
        _, light, pano = bagmaker.session_view(SEED, session)
        gain = bagmaker._Plan.make(scn, pano).gain[0]
        renderer = FrameRenderer(pano, light, cam, np.random.default_rng(0))
        views[session] = renderer.render(R[None], gain, np.ones(3)).astype(float)
    diff = views['browsing'].mean() - views['authoring'].mean()
    assert abs(diff) > 5.0
    assert np.mean(np.abs(views['browsing'] - views['authoring'])) > 10.0
    assert rs.session_offset(SEED, 'browsing')[:2] @ [1, 1] != 0
    assert matrix_to_quat_xyzw(R).shape == (4,)


def test_compressed_and_sqlite3(bag_dir: Path, short_bag: Path) -> None:
    comp = make_bag('rotation_sweep', bag_dir / 'comp.mcap', seed=SEED, duration_s=1.0,
                    image_format='compressed')
    with BagReader(comp) as bag:
        assert '/camera/image_raw' not in bag.topics
        assert bag.topics['/camera/image_raw/compressed'] == 'sensor_msgs/msg/CompressedImage'
        frames = bag.read_all('/camera/image_raw/compressed')
    assert len(frames) == 30 and frames[0][1].format == 'jpeg'
    rgb = cv2.cvtColor(cv2.imdecode(frames[0][1].data, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    with BagReader(short_bag) as bag:  # same arguments but the format: the same frames
        _, raw = bag.read_all('/camera/image_raw')[0]
    raw_rgb = np.frombuffer(raw.data, np.uint8).reshape(240, 320, 3).astype(float)
    assert rgb.shape == (240, 320, 3)
    assert np.mean(np.abs(rgb - raw_rgb)) < 4.0  # channels in the right order, quality ~85
    lite = make_bag('rotation_sweep', bag_dir / 'lite', seed=SEED, duration_s=1.0,
                    storage='sqlite3')
    assert lite.is_dir() and (bag_dir / 'lite.params.yaml').is_file()
    with BagReader(lite) as bag:
        assert bag.message_count(['/imu/data_raw']) == 100
        assert bag.message_count(['/camera/image_raw']) == 30
        _, img = bag.read_all('/camera/image_raw')[0]
    assert np.array_equal(img.data, raw.data)


def test_progress_is_reported(bag_dir: Path) -> None:
    seen: list[float] = []
    make_bag('rotation_sweep', bag_dir / 'prog.mcap', seed=SEED, duration_s=1.0,
             progress=seen.append)
    assert seen and seen[-1] == 1.0 and all(0 < a <= b for a, b in zip(seen, seen[1:]))
