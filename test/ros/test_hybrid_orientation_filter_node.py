"""hybrid_orientation_filter in-process: vision + imu/data in, orientation/global out; backup; bad input."""
from __future__ import annotations

import math

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

from geometry_msgs.msg import PoseStamped, TransformStamped  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import Imu, MagneticField  # noqa: E402

from ar_tracking.core.rotations import heading_tilt_error_deg, rot_z  # noqa: E402
from ar_tracking.nodes.hybrid_orientation_filter import HybridOrientationFilterNode  # noqa: E402
from ar_tracking.ros.conversions import rotation_from_quaternion, set_covariance, set_quaternion, to_stamp  # noqa: E402
from conftest import spin_until  # noqa: E402

T0 = 1_700_000_000_000_000_000
R0_ENU_CAM = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
R_IMU_CAM = np.diag([1.0, -1.0, -1.0])
R_PANO_ENU = (rot_z(-0.7) @ R0_ENU_CAM).T  # the panorama's first frame looked 0.7 rad east of north


def truth(t_s: float) -> np.ndarray:
    return rot_z(-0.7 - 0.4 * math.sin(t_s)) @ R0_ENU_CAM  # R_enu_cam


FIELD_ENU = 48e-6 * np.array([0.0, math.cos(math.radians(64)), -math.sin(math.radians(64))])
G = 9.80665


class Harness:
    def __init__(self, context, params=None):
        overrides = [Parameter(k, value=v) for k, v in (params or {}).items()]
        self.node = HybridOrientationFilterNode(context=context, parameter_overrides=overrides)
        self.src = rclpy.create_node('test_source', context=context)
        self.out: list[Imu] = []
        self.frames: list[TransformStamped] = []
        self.src.create_subscription(Imu, 'orientation/global', self.out.append, 500)
        self.src.create_subscription(TransformStamped, 'orientation/panorama_in_world', self.frames.append, 500)
        vis_type = PoseStamped if (params or {}).get('relative_input_type') == 'pose' else TransformStamped
        self.pub_vis = self.src.create_publisher(vis_type, 'panorama/orientation', 500)
        self.pub_imu = self.src.create_publisher(Imu, 'imu/data', 500)
        self.pub_raw = self.src.create_publisher(Imu, 'imu/data_raw', 500)
        self.pub_mag = self.src.create_publisher(MagneticField, 'imu/mag', 500)
        self.ex = SingleThreadedExecutor(context=context)
        self.ex.add_node(self.node)
        self.ex.add_node(self.src)
        pubs = (self.pub_vis, self.pub_imu, self.pub_raw, self.pub_mag)
        assert spin_until(self.ex, lambda: all(p.get_subscription_count() > 0 for p in pubs)
                          and self.node.pub_global.get_subscription_count() > 0)
        self.sent = 0
        self.late: list[tuple[int, np.ndarray]] = []  # frames not yet arrived (play's visual_lag_s)
        self.ahrs_sent: list[np.ndarray] = []

    def _count(self) -> int:
        return sum(len(s.durations_ms) for s in self.node.callback_stats.values())

    def send(self, pub, msg):
        self.sent += 1
        pub.publish(msg)
        assert spin_until(self.ex, lambda: self._count() >= self.sent, 5.0)

    def visual(self, t_ns, R_pano_cam, pose=False):
        if pose:
            msg = PoseStamped()
            msg.header.frame_id = 'map'
            set_quaternion(msg.pose.orientation, R_pano_cam)
        else:
            msg = TransformStamped()
            msg.header.frame_id = 'panorama'
            msg.child_frame_id = 'camera_optical'
            set_quaternion(msg.transform.rotation, R_pano_cam)
        msg.header.stamp = to_stamp(t_ns)
        self.send(self.pub_vis, msg)

    def sensor(self, t_ns, R_enu_imu, sigma=0.02, quat=None):
        """imu/data: an AHRS orientation."""
        msg = Imu()
        msg.header.stamp = to_stamp(t_ns)
        msg.header.frame_id = 'imu'
        set_quaternion(msg.orientation, R_enu_imu)
        if quat is not None:
            msg.orientation.x, msg.orientation.y, msg.orientation.z, msg.orientation.w = quat
        set_covariance(msg.orientation_covariance, np.eye(3) * sigma**2)
        self.ahrs_sent.append(R_enu_imu)
        self.send(self.pub_imu, msg)

    def raw(self, t_ns, w_imu, accel_imu):
        msg = Imu()
        msg.header.stamp = to_stamp(t_ns)
        msg.header.frame_id = 'imu'
        msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z = map(float, w_imu)
        msg.linear_acceleration.x, msg.linear_acceleration.y, msg.linear_acceleration.z = map(float, accel_imu)
        set_covariance(msg.orientation_covariance, None)
        self.send(self.pub_raw, msg)

    def mag(self, t_ns, field_imu):
        msg = MagneticField()
        msg.header.stamp = to_stamp(t_ns)
        msg.header.frame_id = 'imu'
        msg.magnetic_field.x, msg.magnetic_field.y, msg.magnetic_field.z = map(float, field_imu)
        self.send(self.pub_mag, msg)

    def play(self, t0_s, t1_s, rng, sensor=True, visual=True, field_turn=0.0, pose=False, ahrs=False,
             R_pano_enu=R_PANO_ENU, hard_iron=None, imu_offset_ns=0, mag_every=1, mag_shift_s=0.0,
             visual_lag_s=0.0, mag_hold=1):
        """IMU + field at 50 Hz (hand acceleration and noise), vision at 25 Hz, the motion of
        truth(); ``field_turn`` turns the horizontal field (|B| and dip kept); ``hard_iron`` (T,
        imu frame) is added to every field sample; ``imu_offset_ns`` is added to the stamps of
        imu/data_raw and imu/mag (a camera-IMU time offset); the field is sampled every
        ``mag_every`` IMU samples, ``mag_shift_s`` after them (a magnetometer of its own rate); a
        frame arrives after the IMU samples of the next ``visual_lag_s`` (camera latency); with
        ``mag_hold`` > 1 the field is published with every IMU sample but measured only every
        ``mag_hold``-th, the others repeating it (a driver that publishes a slower magnetometer's
        last value at the IMU's rate)."""
        hard_iron = np.zeros(3) if hard_iron is None else hard_iron
        for k in range(int(round(t0_s * 50)), int(round(t1_s * 50))):
            t = k / 50.0
            t_ns = T0 + k * 20_000_000
            t_imu = t_ns + imu_offset_ns
            R = truth(t)
            R_imu_enu = (R @ R_IMU_CAM.T).T
            w_cam = np.array([0.0, 0.4 * math.cos(t), 0.0])  # heading rate about camera y (down)
            hand = rng.normal(0.0, 0.1, 3)  # m/s^2, zero mean
            if sensor and k % mag_every == 0:
                if k % mag_hold == 0:
                    R_mag = (truth(t + mag_shift_s) @ R_IMU_CAM.T).T
                    held = R_mag @ (rot_z(field_turn) @ FIELD_ENU) + hard_iron + rng.normal(0, 0.2e-6, 3)
                self.mag(t_imu + int(mag_shift_s * 1e9), held)
            self.raw(t_imu, R_IMU_CAM @ w_cam, R_imu_enu @ (np.array([0.0, 0.0, G]) + hand))
            if ahrs:
                self.sensor(t_ns, rot_z(rng.normal(0, 0.02)) @ R @ R_IMU_CAM.T)
            if visual and k % 2 == 0:
                self.late.append((t_ns, R_pano_enu @ R))
            while self.late and self.late[0][0] + visual_lag_s * 1e9 <= t_ns:
                t_v, R_v = self.late.pop(0)
                self.visual(t_v, R_v, pose=pose)

    def close(self):
        self.ex.shutdown()
        self.node.destroy_node()
        self.src.destroy_node()


def heading_err(msg) -> float:
    t_s = ((msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec) - T0) * 1e-9
    R = rotation_from_quaternion(msg.orientation)
    return float(heading_tilt_error_deg(R, truth(t_s))[1])


def finite(msg) -> bool:
    q = [msg.orientation.x, msg.orientation.y, msg.orientation.z, msg.orientation.w]
    return bool(np.all(np.isfinite(q)) and np.all(np.isfinite(msg.orientation_covariance)))


@pytest.mark.parametrize('pose', [False, True])
def test_global_orientation_is_eq_1_with_the_estimated_panorama_frame(ros_context, pose):
    params = {'relative_input_type': 'pose'} if pose else None
    h = Harness(ros_context, params)
    try:
        h.play(0.0, 6.0, np.random.default_rng(0), pose=pose)
        assert len(h.out) >= 140
        assert all(m.header.frame_id == 'camera_optical' for m in h.out)
        assert all(abs(heading_err(m)) < 0.5 for m in h.out[-20:])
        assert h.out[-1].orientation_covariance[8] > 0
        assert h.out[-1].orientation_covariance[8] < h.out[0].orientation_covariance[8]
        R_enu_pano = rotation_from_quaternion(h.frames[-1].transform.rotation)
        assert h.frames[-1].header.frame_id == 'enu'
        assert heading_tilt_error_deg(R_enu_pano, R_PANO_ENU.T)[0] < 0.5
    finally:
        h.close()


def test_gyro_backup_publishes_while_vision_is_lost_and_vision_resumes(ros_context):
    h = Harness(ros_context)
    try:
        rng = np.random.default_rng(1)
        h.play(0.0, 4.0, rng)
        n_before = len(h.out)
        h.play(4.0, 5.0, rng, visual=False)  # lost for 1 s
        backup = h.out[n_before:]
        assert len(backup) >= 20  # ~30 Hz from the gyro
        assert all(abs(heading_err(m)) < 1.0 for m in backup)
        assert backup[-1].orientation_covariance[0] > h.out[n_before - 1].orientation_covariance[0]
        h.play(5.0, 5.6, rng)
        assert abs(heading_err(h.out[-1])) < 0.5
    finally:
        h.close()


def _assert_placed_from_the_gyro(h: Harness, n: int, new_frame: np.ndarray) -> None:
    """Every output from the n-th on within 1 deg of the truth, and the new panorama frame
    learnt (orientation/panorama_in_world within 1 deg of it)."""
    assert all(abs(heading_err(m)) < 1.0 for m in h.out[n:])
    R_enu_pano = rotation_from_quaternion(h.frames[-1].transform.rotation)
    assert heading_tilt_error_deg(R_enu_pano, new_frame.T)[0] < 1.0


def test_a_restarted_panorama_is_placed_in_the_world_from_the_gyro(ros_context):
    """Vision lost, then back in a new panorama frame (the tracker restarted 40 deg away): the
    output carries on from the gyro backup without a jump, and the new frame is learnt."""
    h = Harness(ros_context)
    try:
        rng = np.random.default_rng(7)
        h.play(0.0, 4.0, rng)
        h.play(4.0, 4.6, rng, visual=False)
        n = len(h.out)
        new_frame = rot_z(math.radians(40.0)) @ R_PANO_ENU
        h.play(4.6, 7.0, rng, R_pano_enu=new_frame)
        _assert_placed_from_the_gyro(h, n, new_frame)
    finally:
        h.close()


def test_a_new_panorama_close_to_the_old_one_is_known_by_its_first_frame(ros_context):
    """The tracker restarts after a loss while the camera looks 3.6 deg from where the old
    panorama started: too close to tell from a lost tracker's return by the jump, but a new
    panorama publishes its first frame as the identity. The new frame is placed in the world
    from the gyro; taken for the old one, the output would be 3.6 deg off."""
    h = Harness(ros_context)
    try:
        rng = np.random.default_rng(11)
        h.play(0.0, 4.0, rng)
        h.play(4.0, 6.46, rng, visual=False)
        t_first = 6.44
        new_frame = truth(t_first).T
        assert 3.0 < heading_tilt_error_deg(new_frame.T, R_PANO_ENU.T)[0] < 4.0
        h.visual(T0 + int(round(t_first * 50)) * 20_000_000, np.eye(3))
        n = len(h.out)
        h.play(6.46, 9.0, rng, R_pano_enu=new_frame)
        _assert_placed_from_the_gyro(h, n, new_frame)
    finally:
        h.close()


def test_gyro_rate_output_fills_the_gaps_between_frames(ros_context):
    h = Harness(ros_context, {'gyro_rate_output': True})
    try:
        h.play(0.0, 4.0, np.random.default_rng(4))
        stamps = [m.header.stamp.nanosec + 10**9 * m.header.stamp.sec for m in h.out]
        assert len(h.out) > 180  # 50 Hz rather than the camera's 25 Hz
        assert all(abs(heading_err(m)) < 1.0 for m in h.out[-40:])
        assert stamps == sorted(set(stamps))  # one output per stamp
    finally:
        h.close()


def test_without_a_camera_the_output_is_the_ahrs_in_the_camera_frame(ros_context):
    h = Harness(ros_context)
    try:
        h.play(0.0, 1.0, np.random.default_rng(5), visual=False, ahrs=True)
        # after visual_timeout_s (0.2 s) without a frame: every imu/data sample from then on
        assert spin_until(h.ex, lambda: len(h.out) >= 40, 2.0) and len(h.out) == 40
        assert h.out[0].header.stamp == to_stamp(T0 + 200_000_000)
        for m, R_enu_imu in zip(h.out, h.ahrs_sent[10:]):
            assert np.allclose(rotation_from_quaternion(m.orientation), R_enu_imu @ R_IMU_CAM, atol=1e-9)
            assert m.orientation_covariance[8] == pytest.approx(0.02 ** 2)
    finally:
        h.close()


def test_bad_input_is_skipped_never_crashes_never_nan(ros_context):
    h = Harness(ros_context)
    try:
        rng = np.random.default_rng(2)
        h.play(0.0, 3.0, rng)
        n = len(h.out)
        t_ns = T0 + 150 * 20_000_000
        bad = TransformStamped()
        bad.header.stamp = to_stamp(t_ns + 3)
        bad.transform.rotation.w = 2.0  # not unit
        h.send(h.pub_vis, bad)
        h.visual(T0 + 140 * 20_000_000, R_PANO_ENU @ truth(2.8))  # stamp out of order (0.2 s back)
        h.raw(t_ns + 4, [float('nan'), 0.0, 0.0], [0.0, 0.0, G])
        h.raw(t_ns + 5, [0.0, 0.0, 0.0], [0.0, float('inf'), G])
        h.mag(t_ns + 6, [float('nan'), 0.0, 0.0])
        h.mag(t_ns + 7, [0.0, 0.0, 0.0])
        assert len(h.out) == n  # nothing published for bad messages
        assert all(s.failures == 0 for s in h.node.callback_stats.values())
        # The field silent for 2 s (a magnetometer stuck upstream): vision goes on, the
        # estimate stays.
        h.play(3.0, 5.0, rng, sensor=False)
        assert len(h.out) > n + 40
        assert all(abs(heading_err(m)) < 1.0 for m in h.out[n:])
        assert all(finite(m) for m in h.out)
    finally:
        h.close()


def test_turned_field_does_not_pull_the_heading(ros_context):
    h = Harness(ros_context)
    try:
        rng = np.random.default_rng(3)
        h.play(0.0, 4.0, rng)
        h.play(4.0, 6.0, rng, field_turn=math.radians(8.0))  # field turned by 8 deg, same |B| and dip
        assert all(abs(heading_err(m)) < 1.0 for m in h.out[-50:])
    finally:
        h.close()


def test_a_large_residual_hard_iron_is_reported_once_with_the_offset_that_removes_it(ros_context, capfd):
    """A magnetometer calibrated with hard_iron_offset o but carrying o + 5 uT: once the
    rotations pin the field fit, one warning names the offset that removes (most of) it; a
    small residual is not reported."""
    extra = np.array([4e-6, 0.0, -3e-6])  # horizontal in the phone held upright (y up)
    offset = np.array([1e-6, 2e-6, -1e-6])
    for hard_iron, expect in ((extra, True), (0.2 * extra, False)):
        h = Harness(ros_context, {'hard_iron_offset': offset.tolist()})
        try:
            h.play(0.0, 12.0, np.random.default_rng(4), hard_iron=offset + hard_iron)
        finally:
            h.close()
        lines = [ln for ln in capfd.readouterr().err.splitlines() if 'uT of hard iron' in ln]
        assert len(lines) == (1 if expect else 0)
        if expect:
            found = np.array([float(x) for x in lines[0].split('hard_iron_offset: [')[1].split(']')[0].split(',')])
            # +-23 deg of heading in 12 s: the fit's ridge still holds part of h back.
            moved = (found - offset)[[0, 2]] / extra[[0, 2]]
            assert np.all((moved > 0.5) & (moved < 1.2))


def test_imu_to_camera_rotation_comes_from_tf_static(ros_context, capfd):
    from types import SimpleNamespace

    h = Harness(ros_context, {'imu_to_camera_quat_xyzw': [0.0, 0.0, 0.0, 1.0]})  # wrong: identity
    try:
        h.node.on_static_transforms([SimpleNamespace(parent='imu', child='camera_optical', rotation=R_IMU_CAM)])
        assert np.allclose(h.node.R_imu_cam, R_IMU_CAM)
        assert 'differs from imu_to_camera_quat_xyzw by 180.0 deg' in capfd.readouterr().err
        h.play(0.0, 5.0, np.random.default_rng(6))
        assert all(abs(heading_err(m)) < 0.7 for m in h.out[-20:])  # 90 deg off with the parameter
    finally:
        h.close()


def test_config_file_keys_are_declared_with_equal_defaults(ros_context):
    from pathlib import Path

    import yaml

    path = Path(__file__).resolve().parents[2] / 'config' / 'hybrid_orientation_filter.yaml'
    params = yaml.safe_load(path.read_text())['hybrid_orientation_filter']['ros__parameters']
    node = HybridOrientationFilterNode(context=ros_context)
    try:
        declared = {name: node.get_parameter(name).value for name in node._parameters if name not in ('use_sim_time', 'start_type_description_service')}
        assert set(params) == set(declared)
        for key, value in params.items():
            assert declared[key] == pytest.approx(value) if isinstance(value, float) else declared[key] == value, key
    finally:
        node.destroy_node()


def test_tf_follows_orientation_global_and_frames_switch_live(ros_context):
    """/tf carries world -> camera with every orientation/global, the IMU mount comes once on
    /tf_static; frame names and publish_tf change live, a read-only parameter refuses."""
    TFMessage = pytest.importorskip('tf2_msgs.msg', reason='tf2_msgs not built (./ar-tracking.sh builds it)').TFMessage

    from ar_tracking.ros.tf import TF_STATIC_QOS

    h = Harness(ros_context)
    tf_msgs: list = []
    static: list = []
    h.src.create_subscription(TFMessage, '/tf', tf_msgs.append, 500)
    h.src.create_subscription(TFMessage, '/tf_static', static.append, TF_STATIC_QOS)
    try:
        assert spin_until(h.ex, lambda: h.node.tf._pub.get_subscription_count() > 0)
        rng = np.random.default_rng(5)
        h.play(0.0, 3.0, rng)
        assert spin_until(h.ex, lambda: len(tf_msgs) >= len(h.out) > 0, 5.0)
        tf = tf_msgs[-1].transforms[0]
        assert (tf.header.frame_id, tf.child_frame_id) == ('enu', 'camera_optical')
        assert tf.header.stamp == h.out[-1].header.stamp
        np.testing.assert_allclose(rotation_from_quaternion(tf.transform.rotation),
                                   rotation_from_quaternion(h.out[-1].orientation), atol=1e-9)
        assert spin_until(h.ex, lambda: len(static) >= 1, 5.0)
        mount = static[-1].transforms[0]
        assert (mount.header.frame_id, mount.child_frame_id) == ('imu', 'camera_optical')
        np.testing.assert_allclose(rotation_from_quaternion(mount.transform.rotation), R_IMU_CAM, atol=1e-9)

        assert h.node.set_parameters([Parameter('world_frame_id', value='world'),
                                      Parameter('camera_frame_id', value='phone_camera')])[0].successful
        h.play(3.0, 3.5, rng)
        assert spin_until(h.ex, lambda: tf_msgs[-1].transforms[0].child_frame_id == 'phone_camera', 5.0)
        assert tf_msgs[-1].transforms[0].header.frame_id == 'world'
        assert h.out[-1].header.frame_id == 'phone_camera'

        assert h.node.set_parameters([Parameter('publish_tf', value=False)])[0].successful
        spin_until(h.ex, lambda: False, 0.2)
        before = len(tf_msgs)
        h.play(3.5, 4.0, rng)
        spin_until(h.ex, lambda: False, 0.3)
        assert len(tf_msgs) == before and len(h.out) > 0

        assert not h.node.set_parameters([Parameter('camera_frame_id', value='')])[0].successful
        frozen = h.node.set_parameters([Parameter('window_s', value=2.0)])[0]
        assert not frozen.successful and 'read-only' in frozen.reason
    finally:
        h.close()


def test_declination_changes_live(ros_context):
    """declination_rad set at run time turns the panorama's place in the world (and with it
    every published heading) about up by the change, at once."""
    from ar_tracking.core.rotations import so3_log

    h = Harness(ros_context)
    try:
        rng = np.random.default_rng(7)
        h.play(0.0, 3.0, rng)
        assert spin_until(h.ex, lambda: len(h.frames) > 0, 5.0)
        before = rotation_from_quaternion(h.frames[-1].transform.rotation)  # R_enu_pano
        count = len(h.frames)
        assert h.node.set_parameters([Parameter('declination_rad', value=0.1)])[0].successful
        h.play(3.0, 3.1, rng)
        assert spin_until(h.ex, lambda: len(h.frames) > count, 5.0)
        after = rotation_from_quaternion(h.frames[-1].transform.rotation)
        turn = so3_log(after @ before.T)  # in ENU: about up by the declination (+ 0.1 s of data)
        # magnetic north 0.1 rad east of true north: headings grow by 0.1, a turn of -0.1 about up
        assert turn[2] == pytest.approx(-0.1, abs=0.01)
        assert abs(turn[0]) < 0.01 and abs(turn[1]) < 0.01
    finally:
        h.close()


def test_imu_mount_from_a_tf_static_publisher(ros_context):
    """Where tf2_msgs exists the node listens to /tf_static itself (a latched publisher, as
    robot_state_publisher's): the IMU -> camera rotation comes from it."""
    TFMessage = pytest.importorskip('tf2_msgs.msg', reason='tf2_msgs not built (./ar-tracking.sh builds it)').TFMessage
    from geometry_msgs.msg import TransformStamped as TS

    from ar_tracking.core.rotations import rot_z
    from ar_tracking.ros.tf import TF_STATIC_QOS

    h = Harness(ros_context)
    try:
        mount = rot_z(0.3) @ R_IMU_CAM
        tf = TS()
        tf.header.frame_id, tf.child_frame_id = 'imu', 'camera_optical'
        set_quaternion(tf.transform.rotation, mount)
        pub = h.src.create_publisher(TFMessage, '/tf_static', TF_STATIC_QOS)
        pub.publish(TFMessage(transforms=[tf]))
        assert spin_until(h.ex, lambda: np.allclose(h.node.R_imu_cam, mount, atol=1e-9), 5.0)
    finally:
        h.close()


def test_a_camera_imu_time_offset_is_estimated_and_the_samples_paired_with_it(ros_context):
    """IMU stamps 30 ms later than the camera's for the same instant: the node finds the offset
    from the gyro against the visual rotation and pairs the samples in the camera's clock (the
    heading follows the truth more closely than with the offset ignored)."""
    worst = {}
    for estimate in (True, False):
        h = Harness(ros_context, {'estimate_time_offset': estimate})
        try:
            h.play(0.0, 8.0, np.random.default_rng(5), imu_offset_ns=30_000_000)
            late = [abs(heading_err(m)) for m in h.out
                    if (m.header.stamp.sec * 10**9 + m.header.stamp.nanosec) - T0 > 5e9]
            worst[estimate] = max(late)
            if estimate:
                assert abs(h.node.clock.offset_ns - 30_000_000) < 2_000_000
            else:
                assert h.node.clock.offset_ns == 0
        finally:
            h.close()
    assert worst[True] < 0.5 * worst[False], worst


def _field_runs(ros_context, runs: dict[str, dict]) -> tuple[dict[str, float], dict[str, int]]:
    """Per named run of ``play`` (8 s, its keyword arguments): the worst heading error after 5 s
    and how many field samples the alignment used."""
    worst, used = {}, {}
    for name, kwargs in runs.items():
        h = Harness(ros_context, {'estimate_time_offset': False})
        try:
            h.play(0.0, 8.0, np.random.default_rng(7), **kwargs)
            worst[name] = max(abs(heading_err(m)) for m in h.out
                              if (m.header.stamp.sec * 10**9 + m.header.stamp.nanosec) - T0 > 5e9)
            used[name] = h.node.align._field_samples
        finally:
            h.close()
    return worst, used


def test_a_magnetometer_of_its_own_rate_is_paired_by_its_own_stamps(ros_context):
    """Field samples at 12.5 Hz, stamped 30 ms after the IMU samples they follow (the phone turns
    at up to 23 deg/s): each is paired with the visual orientation at its own stamp, so the
    heading is as good as with the field at every IMU sample."""
    worst, used = _field_runs(ros_context, {'own rate': {'mag_every': 4, 'mag_shift_s': 0.03}, 'with the imu': {}})
    # every field sample once (not once per IMU sample next to it), the last few still waiting
    assert 95 <= used['own rate'] <= 100 and 390 <= used['with the imu'] <= 400, used
    assert worst['own rate'] < 1.5 * worst['with the imu'] + 0.05, worst


def test_a_field_repeated_at_the_imu_rate_counts_once(ros_context, capfd):
    """A driver that publishes the magnetometer's last value with every IMU sample (x-io's
    example recording does: a new field every few samples) gives repeats that are no new
    measurements: counted as such, the field windows would hold four times the samples they
    have and the repeats, paired with later orientations, would lag the turn. Each value counts
    once, at the stamp it first came with, so the heading is that of a field at its own rate."""
    worst, used = _field_runs(ros_context, {'held': {'mag_hold': 4}, 'own rate': {'mag_every': 4}})
    assert 95 <= used['held'] <= 100, used
    assert worst['held'] < 1.2 * worst['own rate'] + 0.02, worst
    assert 'imu/mag repeats' in capfd.readouterr().err


def test_a_camera_stream_that_arrives_late_is_not_taken_for_a_lost_tracker(ros_context, capfd):
    """Frames that reach the node 0.3 s after IMU samples of the same time (a phone's camera
    pipeline and tracker; a bag recorded at arrival keeps that order): every frame is published
    at its own stamp, no gyro backup in between, the samples are paired as without the lag, and
    the heading is as good."""
    used, worst, stamps = {}, {}, {}
    for lag in (0.0, 0.3):
        h = Harness(ros_context, {'estimate_time_offset': False})
        try:
            h.play(0.0, 6.0, np.random.default_rng(11), visual_lag_s=lag)
            stamps[lag] = [(m.header.stamp.sec * 10**9 + m.header.stamp.nanosec) - T0 for m in h.out]
            worst[lag] = max(abs(heading_err(m)) for m, t in zip(h.out, stamps[lag]) if 3e9 <= t <= 5.6e9)
            used[lag] = (h.node.align._n, h.node.align._field_samples)
        finally:
            h.close()
    assert capfd.readouterr().err.count('arrives 300 ms behind the IMU samples') == 1  # said once
    assert all(t % 40_000_000 == 0 for t in stamps[0.3]), 'an output between frames: the backup'
    assert len(stamps[0.3]) >= len(stamps[0.0]) - 9  # the frames still on their way at the end
    # the IMU and field samples the lagging stream still waits for are the last 0.3 s (15 each)
    assert used[0.0][0] - 16 <= used[0.3][0] <= used[0.0][0], used
    assert used[0.0][1] - 16 <= used[0.3][1] <= used[0.0][1], used
    assert abs(worst[0.3] - worst[0.0]) < 0.01, worst  # the same estimates at the same stamps


def test_vision_returning_during_a_turn_behind_the_gyro_is_the_same_panorama(ros_context, capfd):
    """Frames 0.3 s behind the IMU (camera latency), the tracker lost from 5.0 to 6.3 s and back
    while the phone turns at 23 deg/s: the returning frame is compared with the gyro backup at
    its own stamp, so it is the same panorama (no re-seed; compared with the newest backup it
    was 7 deg away and the panorama was placed in the world again from the backup), and the
    heading after the return is as good as before the loss."""
    h = Harness(ros_context, {'estimate_time_offset': False})
    try:
        rng = np.random.default_rng(5)
        h.play(0.0, 5.0, rng, visual_lag_s=0.3)
        h.play(5.0, 6.3, rng, visual=False, visual_lag_s=0.3)
        h.play(6.3, 9.0, rng, visual_lag_s=0.3)
        stamped = [((m.header.stamp.sec * 10**9 + m.header.stamp.nanosec) - T0, heading_err(m)) for m in h.out]
        before = max(abs(e) for t, e in stamped if 3e9 <= t <= 4.9e9)
        after = max(abs(e) for t, e in stamped if 6.3e9 <= t <= 8.5e9)
    finally:
        h.close()
    assert 'vision returned' not in capfd.readouterr().err
    assert after < before + 0.3, (before, after)


def test_a_camera_graph_does_not_start_on_the_ahrs_while_its_first_frame_is_on_its_way(ros_context):
    """imu/data from the start, the first frame 0.1 s later (within visual_timeout_s): no output
    follows the AHRS; every output is a frame's."""
    h = Harness(ros_context)
    try:
        h.play(0.0, 2.0, np.random.default_rng(12), ahrs=True, visual_lag_s=0.1)
        stamps = [(m.header.stamp.sec * 10**9 + m.header.stamp.nanosec) - T0 for m in h.out]
        assert len(stamps) >= 40 and all(t % 40_000_000 == 0 for t in stamps), stamps[:10]
    finally:
        h.close()
