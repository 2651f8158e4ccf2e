"""Tests of the rotation_sweep simulator: bag layout, determinism and the physics of its sensors.

Bags are short (1-4 s) and the world/panorama of a seed is cached by the simulator, so the whole
file runs in well under a minute; the 60 s properties (full turn, rate limit, hand acceleration,
gyro drift, residual iron) are checked on the closed-form scenario without rendering. The
default ('hard') profile and the 'kind' one (the earlier simulator, byte for byte) are both
tested; physics tests take the profile as a parameter.
"""
from __future__ import annotations

import hashlib
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from ar_tracking.core.rotations import (camera_heading_pitch_roll_deg, matrix_to_quat_xyzw,
                                        quat_xyzw_to_matrix)
from ar_tracking.io.bags import BagReader, read_metadata, stamp_to_ns
from ar_tracking.sim import bagmaker, rotation_sweep as rs, rotation_sweep_bag
from ar_tracking.sim.bagmaker import SCENARIOS, SimError, make_bag
from ar_tracking.sim.camera import FrameRenderer, PinholeCamera

SEED = 1
DURATION_S = 4.0
KIND_DURATION_S = 3.0
#: make_bag('rotation_sweep', seed=1, duration_s=3.0, profile='kind') must keep giving the
#: messages of the simulator before profiles existed (commit 1eb25d9). Checked by
#: _kind_numbers: the topics, types and log times byte for byte (sha256), and per topic the
#: floats' count, sum and sum of squares to 1e-9 - not their bytes: matrix products differ in the
#: last bit between processors' BLAS kernels (an AMD EPYC without AVX-512 gave another sha256 of
#: the payloads than the machine the reference was made on, with the same code), and between
#: OpenCV releases the images' interpolation does (4.14 -> 5.0: 4.5 % of the pixels, mean
#: |difference| 0.05 levels), so the images are compared by their mean intensity every 15th frame.
KIND_3S_STAMPS_SHA256 = 'bbff87de1d7dd8f5a62bad872633b6a4c5c2cc8bde8e513ba113a14e0dfd9684'
KIND_3S_NUMBERS = {
    '/camera/camera_info': (90, 150436.12651596754, 34798140.00000001),
    '/gps/fix': (3, 1441.1792520165618, 431409.4966397498),
    '/ground_truth/annotations': (1, -123.75923931879205, 19193.199600574255),
    '/ground_truth/mag_disturbance': (300, -22.798148082635674, 2.8390485352296486),
    '/ground_truth/orientation': (300, 3.6122451661057684, 300.311099669566),
    '/ground_truth/pose': (300, 3.6122451661057684, 300.311099669566),
    '/imu/data_raw': (300, 2866.9462994843216, 28946.8156486004),
    '/imu/mag': (300, -0.019573758514464662, 6.506631602868033e-07),
    '/tf_static': (1, 1.0, 1.0),
}
KIND_3S_IMAGE_MEANS = [105.472, 101.361, 98.269, 95.73, 92.938, 94.782]


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
def kind_bag(bag_dir: Path) -> Path:
    return make_bag('rotation_sweep', bag_dir / 'kind.mcap', seed=SEED,
                    duration_s=KIND_DURATION_S, profile='kind')


def _read(bag_path: Path) -> dict[str, list]:
    out: dict[str, list] = {}
    with BagReader(bag_path) as bag:
        for topic in bag.topics:
            out[topic] = bag.read_all(topic)
    return out


@pytest.fixture(scope='module')
def data(authoring_bag: Path) -> dict[str, list]:
    """Every message of the authoring bag, decoded, per topic: (log time ns, message)."""
    return _read(authoring_bag)


@pytest.fixture(scope='module')
def kind_data(kind_bag: Path) -> dict[str, list]:
    return _read(kind_bag)


@pytest.fixture(params=['hard', 'kind'])
def profile_bag(request: pytest.FixtureRequest) -> tuple[str, Path, dict[str, list]]:
    """(profile, bag, its messages): the 4 s default (hard) bag or the 3 s kind bag."""
    if request.param == 'hard':
        return 'hard', request.getfixturevalue('authoring_bag'), request.getfixturevalue('data')
    return 'kind', request.getfixturevalue('kind_bag'), request.getfixturevalue('kind_data')


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
    scn = rs.make_scenario(SEED, 'authoring', DURATION_S)
    latency = scn.camera_latency_ns  # the hard profile's: frames are logged after their stamps
    assert 30_000_000 <= latency <= 120_000_000
    for topic, (msgtype, rate, frame) in expected.items():
        assert topics[topic] == msgtype
        msgs = data[topic]
        assert len(msgs) == int(DURATION_S * rate), topic
        stamps = np.array([stamp_to_ns(m.header.stamp) for _, m in msgs])
        late = latency if topic.startswith('/camera/') else 0
        assert np.array_equal(stamps + late, [t for t, _ in msgs]), 'log time = header stamp (+ camera latency)'
        assert np.allclose(np.diff(stamps), 1e9 / rate, atol=1), topic
        assert {m.header.frame_id for _, m in msgs} == {frame}, topic
    # IMU and magnetometer share stamps, the ground truth is at the true sample times (the
    # stamps minus the camera-IMU time offset); camera_info pairs with every image.
    off = scn.imu_time_offset_ns
    imu_stamps = np.array([t for t, _ in data['/imu/data_raw']])
    assert np.array_equal([t for t, _ in data['/imu/mag']], imu_stamps)
    for topic in ('/ground_truth/orientation', '/ground_truth/pose',
                  '/ground_truth/mag_disturbance'):
        assert np.array_equal([t for t, _ in data[topic]], imu_stamps - off), topic
    assert [t for t, _ in data['/camera/camera_info']] == [t for t, _ in data['/camera/image_raw']]
    first = data['/ground_truth/orientation'][0][0]
    assert data['/camera/image_raw'][0][0] - latency == first == bagmaker.START_NS
    assert imu_stamps[0] == bagmaker.START_NS + off
    (t_tf, tf), = data['/tf_static']
    assert t_tf == bagmaker.START_NS + min(0, off)  # the first message of the bag
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


@pytest.mark.parametrize('profile', ['hard', 'kind'])
def test_sidecar_params(profile: str, request: pytest.FixtureRequest) -> None:
    bag = request.getfixturevalue('authoring_bag' if profile == 'hard' else 'kind_bag')
    side = bagmaker.sidecar_path(bag)
    assert side.is_file() and side.name == bag.stem + '.params.yaml'
    text = side.read_text()
    assert text.startswith('# Calibration of the simulated device of ')
    assert f'# Simulator profile: {profile} (' in text
    doc = yaml.safe_load(text)
    p = doc['imu_magnetometer']['ros__parameters']
    assert set(p) == {'gyro_bias', 'accel_bias', 'hard_iron_offset', 'soft_iron_matrix',
                      'declination_rad', 'expected_field_t', 'expected_dip_rad'}
    assert len(p['soft_iron_matrix']) == 9 and all(type(v) is float for v in p['soft_iron_matrix'])
    assert p['expected_field_t'] == pytest.approx(48e-6) and p['expected_dip_rad'] == 1.117
    # The hybrid filter gets the same calibration values.
    hybrid = doc['hybrid_orientation_filter']['ros__parameters']
    assert hybrid == {k: p[k] for k in ('gyro_bias', 'accel_bias', 'hard_iron_offset',
                                        'soft_iron_matrix', 'declination_rad')}
    truth = rs.make_scenario(SEED, 'authoring', DURATION_S, profile=profile).errors
    rel = np.abs(np.array(p['gyro_bias']) / truth.gyro_bias_rad_s - 1)
    assert np.all((rel > 0.005) & (rel < 0.035)), 'close to, not exactly, the (constant) truth'
    S_est, S = np.array(p['soft_iron_matrix']).reshape(3, 3), np.linalg.inv(truth.soft_iron)
    residual = np.abs(np.array(p['hard_iron_offset']) - truth.hard_iron_t)
    if profile == 'kind':
        assert np.allclose(S_est @ truth.soft_iron, np.eye(3), atol=0.01)
        assert np.all(residual < 0.035 * np.abs(truth.hard_iron_t))
    else:  # a rough calibration: hard iron 0.4-1.2 uT off per axis, soft iron 20-50 % off
        assert np.all((residual > 0.399e-6) & (residual < 1.201e-6))
        dev_rel = np.abs((S_est - np.eye(3)) / (S - np.eye(3)) - 1)
        assert np.all((dev_rel > 0.2 - 1e-9) & (dev_rel < 0.5 + 1e-9))
        assert np.allclose(S_est, S_est.T)


def test_profile_recorded_for_evaluation(authoring_bag: Path, kind_bag: Path) -> None:
    """Hard bags name their profile, the simulator's revision and their parallax (on by
    default in the hard profile) in an MCAP metadata record; kind bags carry none, exactly like
    the bags of the earlier simulator."""
    from ar_tracking.sim.rotation_sweep_bag import SIM_REVISION

    assert read_metadata(authoring_bag, bagmaker.SIM_METADATA) == {
        'scenario': 'rotation_sweep', 'profile': 'hard', 'seed': str(SEED),
        'session': 'authoring', 'revision': SIM_REVISION, 'parallax': 'true'}
    assert read_metadata(kind_bag, bagmaker.SIM_METADATA) is None


def _numbers(value: object) -> list[float]:
    """Every floating-point number of a decoded message, depth first (integers - stamps, sizes -
    are left out: the log times stand for the stamps)."""
    if isinstance(value, (float, np.floating)):
        return [float(value)]
    if isinstance(value, np.ndarray):
        return value.astype(np.float64).ravel().tolist() if value.dtype.kind == 'f' else []
    if isinstance(value, (list, tuple)):
        return [x for v in value for x in _numbers(v)]
    fields = getattr(value, '__dataclass_fields__', None)
    if fields is None:
        return []
    return [x for name in fields if name != '__msgtype__' for x in _numbers(getattr(value, name))]


def _kind_numbers(bag_path: Path) -> tuple[str, dict[str, tuple[int, float, float]], list[float]]:
    """What the kind profile's bag must keep giving: a sha256 of every message's topic, type and
    log time (integers, exact), per topic (count, sum, sum of squares) of every float the
    messages but the images carry, and the images' mean intensity."""
    digest = hashlib.sha256()
    sums: dict[str, list[float]] = {}
    means = []
    with BagReader(bag_path) as bag:
        for m in bag.messages():
            if m.topic == '/camera/image_raw':
                means.append(float(np.frombuffer(bytes(bag.deserialize(m).data), np.uint8).mean()))
                continue
            for part in (m.topic.encode(), m.msgtype.encode(), m.log_time_ns.to_bytes(8, 'little')):
                digest.update(part)
            x = np.array(_numbers(bag.deserialize(m)), np.float64)
            acc = sums.setdefault(m.topic, [0, 0.0, 0.0])
            acc[0] += 1
            acc[1] += float(x.sum())
            acc[2] += float(x @ x)
    return digest.hexdigest(), {k: (int(v[0]), v[1], v[2]) for k, v in sorted(sums.items())}, means


def test_kind_profile_is_the_earlier_simulator(kind_bag: Path) -> None:
    stamps, sums, means = _kind_numbers(kind_bag)
    assert stamps == KIND_3S_STAMPS_SHA256
    assert sums.keys() == KIND_3S_NUMBERS.keys()
    for topic, (count, total, squares) in KIND_3S_NUMBERS.items():
        assert sums[topic][0] == count, topic
        assert sums[topic][1:] == pytest.approx((total, squares), rel=1e-9, abs=1e-9), topic
    assert len(means) == 90
    assert np.allclose(means[::15], KIND_3S_IMAGE_MEANS, atol=0.05)


def test_cli_profile_option() -> None:
    from ar_tracking.cli import build_parser

    parse = build_parser().parse_args
    assert parse(['make-bag', 'rotation_sweep', '-o', 'x.mcap']).profile == 'hard'
    assert parse(['make-bag', 'rotation_sweep', '-o', 'x.mcap', '--profile', 'kind']).profile \
        == 'kind'
    with pytest.raises(SystemExit):
        parse(['make-bag', 'rotation_sweep', '-o', 'x.mcap', '--profile', 'easy'])


def test_same_seed_same_bytes_different_seed_different(bag_dir: Path, authoring_bag: Path,
                                                       short_bag: Path) -> None:
    rotation_sweep_bag._session_view.cache_clear()  # regenerate the world and panorama from scratch
    rotation_sweep_bag._world.cache_clear()
    again = make_bag('rotation_sweep', bag_dir / 'again.mcap', seed=SEED, duration_s=DURATION_S)
    assert again.read_bytes() == authoring_bag.read_bytes()
    # another seed: 5, that of the rolling-shutter and latency tests below (built once)
    other = make_bag('rotation_sweep', bag_dir / 'other.mcap', seed=5, duration_s=1.0)
    assert other.read_bytes() != short_bag.read_bytes()
    with BagReader(other) as a, BagReader(short_bag) as b:
        img_a = a.read_all('/camera/image_raw')[0][1].data
        img_b = b.read_all('/camera/image_raw')[0][1].data
    assert np.mean(np.abs(img_a.astype(int) - img_b.astype(int))) > 10


def test_bad_arguments(tmp_path: Path, authoring_bag: Path) -> None:
    assert 'rotation_sweep' in SCENARIOS
    cases = [dict(scenario='nope'), dict(session='lunch'), dict(storage='zip'),
             dict(image_format='png'), dict(duration_s=-1.0), dict(duration_s=float('nan')),
             dict(seed=-3), dict(profile='easy')]
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


def test_gyro_integrates_to_ground_truth(profile_bag: tuple[str, Path, dict[str, list]]
                                         ) -> None:
    _, bag, data = profile_bag
    a = _imu_arrays(data)
    bias = np.array(_calibration(bag)['gyro_bias'])
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


def _angle_deg(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    cos = np.sum(u * v, axis=1) / np.linalg.norm(u, axis=1) / np.linalg.norm(v, axis=1)
    return np.degrees(np.arccos(np.clip(cos, -1, 1)))


def test_accelerometer_points_up(profile_bag: tuple[str, Path, dict[str, list]]) -> None:
    """Kind: the hand hardly accelerates, the accelerometer measures gravity. Hard: it measures
    gravity plus the hand's acceleration (the second difference of the true position), with
    0.5-1 % scale errors, and no longer points up."""
    profile, bag, data = profile_bag
    a = _imu_arrays(data)
    bias = np.array(_calibration(bag)['accel_bias'])
    f = a['accel'] - bias
    R_imu_enu = np.einsum('ij,njk->nik', rs.R_IMU_CAM, np.swapaxes(a['R'], 1, 2))
    up_imu = R_imu_enu @ np.array([0, 0, 1.0])
    ang = _angle_deg(f, up_imu)
    if profile == 'kind':
        assert np.median(ang) < 1.0 and np.percentile(ang, 99) < 2.0
        assert np.median(np.linalg.norm(f, axis=1)) == pytest.approx(9.81, abs=0.1)
        return
    pos = np.array([_vec(m.pose.position) for _, m in data['/ground_truth/pose']])
    acc = (pos[2:] - 2 * pos[1:-1] + pos[:-2]) / 0.01 ** 2  # true sample times: 10 ms apart
    f_true = np.einsum('nij,nj->ni', R_imu_enu[1:-1], acc + [0, 0, rs.GRAVITY_M_S2])
    ang_true = _angle_deg(f[1:-1], f_true)
    assert np.median(ang_true) < 1.0 and np.percentile(ang_true, 99) < 2.0
    ratio = np.linalg.norm(f[1:-1], axis=1) / np.linalg.norm(f_true, axis=1)
    assert abs(np.median(ratio) - 1) < 0.02
    assert np.sqrt(np.mean(np.sum(acc ** 2, axis=1))) > 0.3  # m/s^2, the hand moves
    assert np.median(ang) > 1.0  # so gravity alone no longer explains the samples


def _tilt_compensated_heading_deg(accel: np.ndarray, mag: np.ndarray) -> np.ndarray:
    """Camera heading from gravity + magnetic field (TRIAD), as a compass app does."""
    up = accel / np.linalg.norm(accel, axis=1, keepdims=True)
    east = np.cross(mag, up)
    east /= np.linalg.norm(east, axis=1, keepdims=True)
    north = np.cross(up, east)
    R_enu_imu = np.stack([east, north, up], axis=1)
    heading, _, _ = camera_heading_pitch_roll_deg(R_enu_imu @ rs.R_IMU_CAM)
    return heading


def test_magnetometer_heading_and_disturbance(profile_bag: tuple[str, Path, dict[str, list]]
                                              ) -> None:
    """Kind: a compass app (tilt from the accelerometer, the sidecar calibration) reads the true
    heading plus the disturbance. Hard: the accelerometer tilt is spoiled by the hand's
    acceleration and the sidecar calibration is rough, so the field is checked with the true
    tilt and the true calibration; the sidecar's residual iron adds a heading error."""
    profile, bag, data = profile_bag
    a = _imu_arrays(data)
    p = _calibration(bag)
    S = np.array(p['soft_iron_matrix']).reshape(3, 3)
    mag = (a['mag'] - np.array(p['hard_iron_offset'])) @ S.T
    defl = np.degrees(a['defl'])
    calm, disturbed = np.abs(defl) < 0.05, np.abs(defl) > 2.0
    assert calm.sum() > 50 and disturbed.sum() > 30, 'the bag must contain a disturbance'
    if profile == 'kind':
        assert np.median(np.linalg.norm(mag, axis=1)) == pytest.approx(48e-6, rel=0.05)
        heading = _tilt_compensated_heading_deg(a['accel'] - np.array(p['accel_bias']), mag)
        true_heading, _, _ = camera_heading_pitch_roll_deg(a['R'])
        err = (heading - true_heading + 180) % 360 - 180
    else:
        truth = rs.make_scenario(SEED, 'authoring', DURATION_S).errors
        true_mag = (a['mag'] - truth.hard_iron_t) @ np.linalg.inv(truth.soft_iron).T
        assert np.median(np.linalg.norm(true_mag, axis=1)) == pytest.approx(48e-6, rel=0.05)
        R_enu_imu = a['R'] @ rs.R_IMU_CAM.T
        b = rs.EarthField().vector_enu
        def compass_error_deg(m: np.ndarray) -> np.ndarray:  # noqa: E306
            m_enu = np.einsum('nij,nj->ni', R_enu_imu, m)
            return np.degrees(rs.heading_deflection(np.broadcast_to(b, m_enu.shape), m_enu))
        err = compass_error_deg(true_mag)
        residual = compass_error_deg(mag) - err  # what the rough calibration adds
        assert np.median(np.abs(residual)) > 1.0
    assert np.median(np.abs(err[calm])) < 1.5 and np.percentile(np.abs(err[calm]), 99) < 4.0
    assert np.median(np.abs(err[disturbed] - defl[disturbed])) < 1.5
    assert np.median(np.abs(err[disturbed])) > 1.5  # the disturbance really moves the compass


@pytest.mark.parametrize('profile', ['hard', 'kind'])
def test_disturbance_schedule_and_truth(profile: str) -> None:
    scn = rs.make_scenario(5, 'authoring', 60.0, profile=profile)
    d = scn.disturbances
    assert 3 <= len(d.start_s) <= 5
    t = np.arange(0, 60, 0.01)
    imu = rs.simulate_imu(scn, t)
    peaks = [np.max(np.abs(imu.deflection_rad[(t >= s) & (t <= s + w)]))
             for s, w in zip(d.start_s, d.duration_s, strict=True)]
    assert all(math.radians(1.9) < pk < math.radians(10.1) for pk in peaks)
    assert np.all(np.abs(np.diff(imu.deflection_rad)) < math.radians(0.5)), 'smooth onsets'
    b = scn.earth.vector_enu
    b_meas = b + d.field(t)
    dip = np.arctan2(-b_meas[:, 2], np.hypot(b_meas[:, 0], b_meas[:, 1]))
    if profile == 'kind':  # some events change |B| too
        assert np.max(np.abs(imu.extra_field_t)) > 0.5e-6
    else:  # every event only turns the horizontal field: |B| and dip stay, also in the ramps
        assert np.max(np.abs(np.linalg.norm(b_meas, axis=1) / np.linalg.norm(b) - 1)) < 1e-9
        assert np.max(np.abs(dip / scn.earth.dip_rad - 1)) < 1e-9
        assert np.max(np.abs(imu.extra_field_t)) < 1e-9 * np.linalg.norm(b)
        kind = rs.make_scenario(5, 'authoring', 60.0, profile='kind').disturbances
        assert np.array_equal(kind.start_s, d.start_s)  # the same schedule as the kind profile
        kind_defl = rs.heading_deflection(np.broadcast_to(b, b_meas.shape), b + kind.field(t))
        assert np.max(np.abs(kind_defl - imu.deflection_rad)) < math.radians(1.0)
    # Without disturbance the truth field is 48 uT, 64 deg dip.
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
            kind = rs.make_trajectory(seed, session, 60.0, profile='kind')
            sway = np.linalg.norm(kind.position(t[::50]) - kind.spot_enu, axis=1)
            assert sway.max() < 0.08
            # The hard profile moves the hand (a few cm) at a 0.2-0.4 m lever arm; same angles.
            assert np.array_equal(kind.angles(t[::50])[0], tr.angles(t[::50])[0])
            assert 0.2 <= tr.lever_arm_m <= 0.4
            sway = np.linalg.norm(tr.position(t[::50]) - tr.spot_enu, axis=1)
            assert sway.max() < tr.lever_arm_m + 0.1
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


def test_hand_linear_acceleration() -> None:
    """Hard: the hand sways and trembles (a few cm at 0.5-3 Hz) and the phone is 0.2-0.4 m in
    front of the turning body: |a| RMS above 0.3 m/s^2, peaks of 1-2.5 m/s^2 in the sweeps.
    Kind: the earlier 1 cm sway and 2-4 cm lever arm, RMS below 0.1 m/s^2."""
    t = np.arange(0.0, 60.0, 0.01)
    for seed in range(3):
        hard = rs.make_trajectory(seed, 'authoring', 60.0)
        kind = rs.make_trajectory(seed, 'authoring', 60.0, profile='kind')
        a_hard = np.linalg.norm(hard.acceleration(t), axis=1)
        a_kind = np.linalg.norm(kind.acceleration(t), axis=1)
        assert np.sqrt(np.mean(a_hard ** 2)) > 0.3 and 1.0 < a_hard.max() < 2.5
        assert np.sqrt(np.mean(a_kind ** 2)) < 0.1
        sweeping = np.abs(hard.pan.rate(t)) > math.radians(40)
        assert np.percentile(a_hard[sweeping], 90) > 0.5
    # The acceleration is exact: the second difference of the closed-form position.
    tq, h = np.linspace(1, 59, 300), 1e-3
    fd = (hard.position(tq + h) - 2 * hard.position(tq) + hard.position(tq - h)) / h ** 2
    assert np.allclose(fd, hard.acceleration(tq), atol=1e-3)
    # Bounded position: the hand motion is a sum of sines (zero-mean velocity).
    for axis in hard.hand:
        assert np.all(axis.freq_hz >= 0.08) and np.sum(np.abs(axis.amp)) < 0.06


def test_gyro_bias_drift() -> None:
    """Hard: the bias starts at the constant part (what the sidecar estimates) and drifts by a
    random walk of a few mrad/s per minute, which the samples carry; kind: constant."""
    t = np.arange(0.0, 60.0, 0.01)
    scn = rs.make_scenario(SEED, 'authoring', 60.0)
    imu = rs.simulate_imu(scn, t)
    b = imu.gyro_bias_rad_s
    assert np.allclose(b[0], scn.errors.gyro_bias_rad_s, atol=1e-12)
    assert np.linalg.norm(b[-1] - b[0]) > 0.001
    omega_imu = scn.trajectory.omega_cam(t) @ rs.R_IMU_CAM.T
    drift = b - scn.errors.gyro_bias_rad_s
    rest = imu.gyro_rad_s - omega_imu - scn.errors.gyro_bias_rad_s
    slope = np.sum(rest * drift) / np.sum(drift * drift)
    assert 0.7 < slope < 1.3, 'the samples carry the drift'
    changes = [np.linalg.norm(np.diff(rs.make_scenario(s, 'authoring', 60.0).errors
                                      .gyro_bias_at(np.array([0.0, 60.0])), axis=0))
               for s in range(12)]
    assert 0.0015 < np.median(changes) < 0.006
    kind = rs.make_scenario(SEED, 'authoring', 60.0, profile='kind')
    kind_imu = rs.simulate_imu(kind, t)
    assert kind.errors.gyro_bias_drift is None
    assert np.all(kind_imu.gyro_bias_rad_s == kind.errors.gyro_bias_rad_s)


def test_residual_iron_makes_heading_error_vary_with_heading() -> None:
    """Hard: the sidecar's rough calibration leaves a heading error that varies with heading
    (mostly the residual hard iron against the 21 uT horizontal field); kind: well under a
    degree. Measured as the compass error with the sidecar calibration minus the one with the
    true calibration, on the same samples (so noise and disturbances cancel)."""
    t = np.arange(0.0, 60.0, 0.05)
    for profile, lo, hi in (('hard', 2.0, 30.0), ('kind', 0.0, 1.5)):
        scn = rs.make_scenario(SEED, 'authoring', 60.0, profile=profile)
        imu = rs.simulate_imu(scn, t)
        p = rs.calibration_params(scn)
        R_enu_imu = imu.R_enu_cam @ rs.R_IMU_CAM.T
        b = scn.earth.vector_enu

        def compass_error_deg(hard_iron: np.ndarray, S: np.ndarray, R_enu_imu: np.ndarray = R_enu_imu,
                              imu: rs.ImuSamples = imu, b: np.ndarray = b) -> np.ndarray:
            m = np.einsum('nij,nj->ni', R_enu_imu, (imu.mag_t - hard_iron) @ S.T)
            return np.degrees(rs.heading_deflection(np.broadcast_to(b, m.shape), m))

        residual = (compass_error_deg(np.array(p['hard_iron_offset']),
                                      np.array(p['soft_iron_matrix']).reshape(3, 3))
                    - compass_error_deg(scn.errors.hard_iron_t,
                                        np.linalg.inv(scn.errors.soft_iron)))
        heading = np.radians(camera_heading_pitch_roll_deg(imu.R_enu_cam)[0])
        # First harmonic in heading: what a hard-iron residual gives.
        X = np.stack([np.ones_like(heading), np.cos(heading), np.sin(heading)], 1)
        coef = np.linalg.lstsq(X, residual, rcond=None)[0]
        amplitude = math.hypot(coef[1], coef[2])
        assert lo < 2 * amplitude < hi, (profile, amplitude)


def test_imu_time_offset(data: dict[str, list], kind_data: dict[str, list]) -> None:
    """Hard: IMU and magnetometer stamps = true sample time + a constant 2-8 ms offset (either
    sign); the ground truth and the camera keep the true time. Kind: no offset."""
    offsets = [rs.make_scenario(s, 'authoring', 10.0).imu_time_offset_ns for s in range(20)]
    assert all(2_000_000 <= abs(o) <= 8_000_000 for o in offsets)
    assert min(offsets) < 0 < max(offsets)
    off = rs.make_scenario(SEED, 'authoring', DURATION_S).imu_time_offset_ns
    assert off == offsets[SEED]
    for d, expected in ((data, off), (kind_data, 0)):
        imu = np.array([t for t, _ in d['/imu/data_raw']])
        mag = np.array([stamp_to_ns(m.header.stamp) for _, m in d['/imu/mag']])
        gt = np.array([stamp_to_ns(m.header.stamp) for _, m in d['/ground_truth/orientation']])
        assert np.all(imu - gt == expected) and np.all(mag - gt == expected)
        assert np.all((gt - bagmaker.START_NS) % 10_000_000 == 0)  # the true 100 Hz grid
    assert rs.make_scenario(SEED, 'authoring', DURATION_S, profile='kind').imu_time_offset_ns == 0


def test_a_chosen_imu_time_offset_moves_only_the_imu_stamps(tmp_path: Path) -> None:
    """make-bag --imu-time-offset-ms: the IMU and magnetometer stamps are that much later than
    the truth and the camera (a phone with a larger offset), the rest of the seed unchanged."""
    from ar_tracking.cli import build_parser

    assert build_parser().parse_args(['make-bag', 'rotation_sweep', '-o', 'x.mcap', '--imu-time-offset-ms', '-25'])\
        .imu_time_offset_ms == -25.0
    chosen = rs.make_scenario(SEED, 'authoring', 10.0, imu_time_offset_s=-0.025)
    assert chosen.imu_time_offset_ns == -25_000_000
    assert np.array_equal(chosen.errors.hard_iron_t, rs.make_scenario(SEED, 'authoring', 10.0).errors.hard_iron_t)
    bag = make_bag('rotation_sweep', tmp_path / 'late.mcap', seed=SEED, duration_s=1.0, imu_time_offset_s=0.04)
    with BagReader(bag) as b:
        imu = [stamp_to_ns(m.header.stamp) for _, m in b.read_all('/imu/data_raw')]
        mag = [stamp_to_ns(m.header.stamp) for _, m in b.read_all('/imu/mag')]
        gt = [stamp_to_ns(m.header.stamp) for _, m in b.read_all('/ground_truth/orientation')]
        cam = [stamp_to_ns(m.header.stamp) for _, m in b.read_all('/camera/image_raw')]
    assert np.all(np.array(imu) - np.array(gt) == 40_000_000) and np.all(np.array(mag) - np.array(gt) == 40_000_000)
    assert cam[0] == gt[0]
    for bad in (float('nan'), 2.0, True):
        with pytest.raises(SimError, match='IMU time offset'):
            make_bag('rotation_sweep', tmp_path / 'bad.mcap', seed=SEED, duration_s=1.0, imu_time_offset_s=bad)
    with pytest.raises(SimError, match='rotation_sweep option'):
        make_bag('robot_arcs', tmp_path / 'arcs.mcap', seed=SEED, duration_s=1.0, imu_time_offset_s=0.01)


def test_a_rolling_shutter_renders_each_row_at_its_own_time() -> None:
    """make-bag --readout-ms: row r of a frame stamped t shows the scene at t + readout (r + 0.5)
    / rows - during a pan the bottom rows are shifted against a global-shutter frame by the
    turn over the readout, the top rows hardly."""
    from ar_tracking.cli import build_parser

    assert build_parser().parse_args(['make-bag', 'rotation_sweep', '-o', 'x.mcap', '--readout-ms', '30']).readout_ms == 30
    traj = rs.make_trajectory(SEED, 'authoring', 20.0)
    t = np.arange(0.5, 19.5, 0.01)
    t_pan = float(t[int(np.argmax(np.linalg.norm(traj.omega_cam(t), axis=1)))])
    rows = 240
    R_rs = rs.frame_orientations(traj, t_pan, 277.0, 0.03, rows)
    assert R_rs.shape[1:] == (rows, 3, 3)
    mid = len(R_rs) // 2
    for r, dt in ((0, 0.03 * 0.5 / rows), (rows - 1, 0.03 * (rows - 0.5) / rows)):
        assert np.allclose(R_rs[mid, r], traj.R_enu_cam(np.array([t_pan + dt]))[0], atol=1e-3)
    assert rs.frame_orientations(traj, t_pan, 277.0, 0.0, rows).ndim == 3  # global: (n, 3, 3)
    with pytest.raises(SimError, match='readout'):
        make_bag('rotation_sweep', Path('/nonexistent/x.mcap'), seed=SEED, duration_s=1.0, readout_s=0.5)
    with pytest.raises(SimError, match='rotation_sweep option'):
        make_bag('handheld_desk', Path('/nonexistent/x.mcap'), seed=SEED, duration_s=1.0, readout_s=0.01)


def test_rolling_shutter_frames_shear_during_a_pan(tmp_path: Path) -> None:
    import cv2

    frames = {}
    for ms in (0.0, 30.0):
        bag = make_bag('rotation_sweep', tmp_path / f'rs{ms:g}.mcap', seed=5, duration_s=3.0, readout_s=ms * 1e-3)
        with BagReader(bag) as b:
            frames[ms] = [(stamp_to_ns(m.header.stamp), np.frombuffer(bytes(m.data), np.uint8).reshape(m.height, m.width, 3))
                          for _, m in b.read_all('/camera/image_raw')]
    traj = rs.make_trajectory(5, 'authoring', 3.0)
    t = np.array([(s - frames[0.0][0][0]) * 1e-9 for s, _ in frames[0.0]])
    k = int(np.argmax(np.linalg.norm(traj.omega_cam(t), axis=1)))
    a, b = (cv2.cvtColor(frames[ms][k][1], cv2.COLOR_RGB2GRAY).astype(np.float32) for ms in (0.0, 30.0))
    sidecar = (tmp_path / 'rs30.params.yaml').read_text()
    assert 'panorama_mapper' in sidecar and 'readout_s: 0.03' in sidecar  # the camera's readout for the mapper
    assert 'panorama_mapper' not in (tmp_path / 'rs0.params.yaml').read_text()
    top = cv2.phaseCorrelate(a[:40], b[:40])[0][0]
    bottom = cv2.phaseCorrelate(a[-40:], b[-40:])[0][0]
    assert abs(bottom) > 2.5 and abs(bottom) > 3 * abs(top)


def test_camera_frames_arrive_after_their_stamps_as_a_phone_delivers_them(tmp_path: Path) -> None:
    """The hard profile draws a pipeline latency per seed and session (30-120 ms): every frame
    is logged that long after its stamp, behind the IMU samples of its time; make-bag
    --camera-latency-ms sets one (0: logged at its stamp); kind bags have none; a bad value is
    one clear error."""
    from ar_tracking.cli import build_parser

    hard = [rs.make_scenario(s, 'authoring', 5.0).camera_latency_ns for s in range(20)]
    lo, hi = (int(x * 1e9) for x in rs.HARD_CAMERA_LATENCY_S)
    assert all(lo <= x <= hi for x in hard) and len(set(hard)) == 20
    assert rs.make_scenario(3, 'authoring', 5.0, profile='kind').camera_latency_ns == 0
    assert build_parser().parse_args(['make-bag', 'rotation_sweep', '-o', 'x.mcap', '--camera-latency-ms',
                                      '250']).camera_latency_ms == 250
    for ms in (0.0, 250.0):  # seed 5 as in the test above: the simulator's cached view of it
        bag = make_bag('rotation_sweep', tmp_path / f'lat{ms:g}.mcap', seed=5, duration_s=1.0,
                       camera_latency_s=ms * 1e-3)
        with BagReader(bag) as b:
            late = {(m.log_time_ns - stamp_to_ns(b.deserialize(m).header.stamp))
                    for m in b.messages(['/camera/image_raw', '/camera/camera_info'])}
            imu_first = next(iter(b.messages(['/imu/data_raw']))).log_time_ns
            cam_first = next(iter(b.messages(['/camera/image_raw']))).log_time_ns
        assert late == {int(ms * 1e6)}
        assert (cam_first > imu_first + 200_000_000) == (ms > 0)
    with pytest.raises(SimError, match='camera latency'):
        make_bag('rotation_sweep', tmp_path / 'bad.mcap', seed=5, duration_s=1.0, camera_latency_s=-0.01)
    with pytest.raises(SimError, match='rotation_sweep option'):
        make_bag('robot_arcs', tmp_path / 'arcs.mcap', seed=5, duration_s=1.0, camera_latency_s=0.05)


def test_the_hard_profile_has_a_rolling_shutter_it_does_not_declare() -> None:
    """A phone camera reads its rows over 8-30 ms, and a user seldom knows how long: the hard
    profile draws the readout per seed and session and leaves it out of the sidecar (the mapper
    estimates it); an asked-for readout is declared; the kind profile stays a global shutter."""
    hard = [rs.make_scenario(s, 'authoring', 5.0).readout_s for s in range(20)]
    assert all(rs.HARD_READOUT_S[0] <= r <= rs.HARD_READOUT_S[1] for r in hard) and len(set(hard)) == 20
    assert rs.make_scenario(3, 'browsing', 5.0).readout_s != rs.make_scenario(3, 'authoring', 5.0).readout_s
    assert not rs.make_scenario(3, 'authoring', 5.0).readout_declared
    assert rs.make_scenario(3, 'authoring', 5.0, profile='kind').readout_s == 0.0
    asked = rs.make_scenario(3, 'authoring', 5.0, readout_s=0.02)
    assert asked.readout_s == 0.02 and asked.readout_declared
    assert rs.make_scenario(3, 'authoring', 5.0, readout_s=0.0).readout_s == 0.0


def test_exposure_jumps_larger_in_hard_profile() -> None:
    hard = rs.make_exposure(SEED, 'authoring', 60.0)
    kind = rs.make_exposure(SEED, 'authoring', 60.0, profile='kind')
    assert np.array_equal(hard.jump_s, kind.jump_s) and len(kind.jump_s) >= 3
    m_kind = np.exp(np.abs(np.log(kind.jump_factor))) - 1
    m_hard = np.exp(np.abs(np.log(hard.jump_factor))) - 1
    assert np.all((m_kind >= 0.2) & (m_kind <= 0.5))
    assert np.allclose(m_hard, 1.5 * m_kind)


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
        _, light, pano = rotation_sweep_bag.session_view(SEED, session)
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
               for a, b in zip(arr.markers, ref.markers, strict=True))
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
        _, light, pano = rotation_sweep_bag.session_view(SEED, session)
        gain = rotation_sweep_bag.Plan.make(scn, pano).gain[0]
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
    assert seen and seen[-1] == 1.0 and all(0 < a <= b for a, b in zip(seen, seen[1:], strict=False))
