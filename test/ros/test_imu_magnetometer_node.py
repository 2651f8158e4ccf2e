"""imu_magnetometer in-process: publish raw IMU + field in, check imu/data out; bad input."""
from __future__ import annotations

import math

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import Imu, MagneticField  # noqa: E402

from ar_tracking.core.rotations import rot_z, so3_log  # noqa: E402
from ar_tracking.nodes.imu_magnetometer import ImuMagnetometerNode  # noqa: E402
from ar_tracking.ros.conversions import quat_xyzw, rotation_from_quaternion, to_stamp  # noqa: E402
from conftest import spin_until  # noqa: E402

G = 9.80665
FIELD_ENU = 48e-6 * np.array([0.0, math.cos(math.radians(64)), -math.sin(math.radians(64))])
T0 = 1_700_000_000_000_000_000


class Harness:
    def __init__(self, context, params=None):
        overrides = [Parameter(k, value=v) for k, v in (params or {}).items()]
        self.node = ImuMagnetometerNode(context=context, parameter_overrides=overrides)
        self.src = rclpy.create_node('test_source', context=context)
        self.out: list[Imu] = []
        self.src.create_subscription(Imu, 'imu/data', self.out.append, 50)
        self.pub_imu = self.src.create_publisher(Imu, 'imu/data_raw', 50)
        self.pub_mag = self.src.create_publisher(MagneticField, 'imu/mag', 50)
        self.ex = SingleThreadedExecutor(context=context)
        self.ex.add_node(self.node)
        self.ex.add_node(self.src)
        assert spin_until(self.ex, lambda: self.pub_imu.get_subscription_count() > 0
                          and self.pub_mag.get_subscription_count() > 0
                          and self.node.pub_data.get_subscription_count() > 0)

    def send(self, t_ns, accel, field, mag_first=False):
        imu = Imu()
        imu.header.stamp = to_stamp(t_ns)
        imu.header.frame_id = 'imu'
        imu.linear_acceleration.x, imu.linear_acceleration.y, imu.linear_acceleration.z = map(float, accel)
        mag = MagneticField()
        mag.header = imu.header
        mag.magnetic_field.x, mag.magnetic_field.y, mag.magnetic_field.z = map(float, field)
        if mag_first:
            self.pub_mag.publish(mag)
            spin_until(self.ex, lambda: False, 0.02)
            self.pub_imu.publish(imu)
        else:
            self.pub_imu.publish(imu)
            spin_until(self.ex, lambda: False, 0.02)
            self.pub_mag.publish(mag)

    def wait(self, n, timeout_s=5.0):
        return spin_until(self.ex, lambda: len(self.out) >= n, timeout_s)

    def close(self):
        self.ex.shutdown()
        self.node.destroy_node()
        self.src.destroy_node()


def sample(R_enu_imu, field_enu=FIELD_ENU):
    return R_enu_imu.T @ np.array([0.0, 0.0, G]), R_enu_imu.T @ field_enu


def test_compass_method_is_eq_3_4_with_the_newest_field_sample(ros_context):
    h = Harness(ros_context, {'method': 'compass'})
    try:
        truths = []
        for i in range(6):
            R = rot_z(0.3 * i) @ np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # upright phone
            truths.append(R)
            h.send(T0 + i * 10_000_000, *sample(R), mag_first=True)
        assert h.wait(6)
        for msg, R in zip(h.out, truths):
            est = rotation_from_quaternion(msg.orientation)
            assert np.allclose(est, R, atol=1e-6)
            assert msg.header.frame_id == 'imu'
            cov = np.array(msg.orientation_covariance).reshape(3, 3)
            assert cov[0, 0] > 0 and cov[2, 2] > 0 and np.allclose(cov, cov.T)
        stamps = [m.header.stamp.nanosec for m in h.out]
        assert stamps == sorted(stamps)
    finally:
        h.close()


def _turning(h, n, rate_rad_s=0.5, field_for=lambda i: FIELD_ENU, mag_every=1, t0=T0):
    """n samples of an upright phone turning about up at a constant rate (gyro consistent)."""
    R0 = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
    truths = []
    for i in range(n):
        R = rot_z(rate_rad_s * i * 0.01) @ R0
        truths.append(R)
        f_enu = field_for(i)
        accel, field = sample(R), (None if f_enu is None else R.T @ f_enu)
        accel = accel[0]
        gyro = R.T @ np.array([0.0, 0.0, rate_rad_s])
        imu = Imu()
        imu.header.stamp = to_stamp(t0 + i * 10_000_000)
        imu.header.frame_id = 'imu'
        imu.angular_velocity.x, imu.angular_velocity.y, imu.angular_velocity.z = map(float, gyro)
        imu.linear_acceleration.x, imu.linear_acceleration.y, imu.linear_acceleration.z = map(float, accel)
        if i % mag_every == 0 and field is not None:
            mag = MagneticField()
            mag.header = imu.header
            mag.magnetic_field.x, mag.magnetic_field.y, mag.magnetic_field.z = map(float, field)
            h.pub_mag.publish(mag)
            spin_until(h.ex, lambda: False, 0.005)
        h.pub_imu.publish(imu)
        # Without a field sample of its stamp the node holds the IMU sample until the next one
        # shows none is coming (one sample of delay, never more): wait for what is due.
        due = i + 1 if field is not None else i
        assert spin_until(h.ex, lambda due=due: len(h.out) >= due, 2.0), f"sample {i}: {len(h.out)} published, {due} due"
    return truths


def test_vqf_method_tracks_a_turning_phone_with_the_gyro(ros_context):
    h = Harness(ros_context, {'constant_dt': 0.01})
    try:
        truths = _turning(h, 150)
        assert h.wait(150)
        err = [np.degrees(np.linalg.norm(so3_log(rotation_from_quaternion(m.orientation).T @ R)))
               for m, R in zip(h.out, truths)]
        assert max(err) < 1.0  # the first field sample sets the heading, the gyro carries it
        cov = np.array(h.out[-1].orientation_covariance).reshape(3, 3)
        assert 0 < cov[0, 0] < cov[2, 2] < 0.1
    finally:
        h.close()


def test_without_magnetometer_runs_6d_with_growing_heading_covariance(ros_context):
    h = Harness(ros_context, {'constant_dt': 0.01, 'use_mag': False})
    try:
        truths = _turning(h, 120, field_for=lambda i: None)
        assert h.wait(120)
        tilt = [np.degrees(math.acos(np.clip((rotation_from_quaternion(m.orientation) @ [0, 0, 1]) @ (R @ [0, 0, 1]), -1, 1)))
                for m, R in zip(h.out, truths)]
        assert max(tilt) < 0.5
        heading_var = [m.orientation_covariance[8] for m in h.out]
        assert heading_var[-1] > heading_var[10] > 0
    finally:
        h.close()


def test_magnetometer_dropout_neither_stalls_nor_floods(ros_context):
    """IMU samples are published one for one while the field is missing (6D, heading variance
    growing) and when it comes back: nothing is held back and released as a burst."""
    h = Harness(ros_context, {'constant_dt': 0.01})
    try:
        _turning(h, 200, field_for=lambda i: None if 60 <= i < 140 else FIELD_ENU)
        assert h.wait(200)
        spin_until(h.ex, lambda: False, 0.2)
        assert len(h.out) == 200
        var = [m.orientation_covariance[8] for m in h.out]
        assert var[135] > var[100] > var[75]  # grows while the field is missing (older than max_mag_age_s)
        assert var[199] < var[139]  # and shrinks once it is back
    finally:
        h.close()


def test_world_frame_ned_and_declination(ros_context):
    decl = math.radians(10.0)
    h = Harness(ros_context, {'world_frame': 'ned', 'declination_rad': decl, 'method': 'compass'})
    try:
        R = np.eye(3)  # body axes = magnetic ENU axes
        h.send(T0, *sample(R), mag_first=True)
        assert h.wait(1)
        R_ned_body = rotation_from_quaternion(h.out[0].orientation)
        # body y axis points to magnetic north = 10 deg east of true north: in NED (x north, y east)
        y_axis = R_ned_body[:, 1]
        assert math.degrees(math.atan2(y_axis[1], y_axis[0])) == pytest.approx(10.0, abs=1e-6)
        assert R_ned_body[2, 2] == pytest.approx(-1.0)  # body z (up) is -down
    finally:
        h.close()


def test_madgwick_declination_and_mag_bias_names_are_honoured(ros_context):
    bias = np.array([3e-6, -2e-6, 1e-6])
    h = Harness(ros_context, {'method': 'compass', 'declination': math.radians(10.0),
                              'mag_bias_x': bias[0], 'mag_bias_y': bias[1], 'mag_bias_z': bias[2]})
    try:
        accel, field = sample(np.eye(3))
        h.send(T0, accel, field + bias, mag_first=True)
        assert h.wait(1)
        y_axis = rotation_from_quaternion(h.out[0].orientation)[:, 1]
        assert math.degrees(math.atan2(y_axis[0], y_axis[1])) == pytest.approx(10.0, abs=1e-6)
    finally:
        h.close()


def test_covariance_rises_under_magnetic_disturbance(ros_context):
    h = Harness(ros_context, {'expected_field_t': 48e-6, 'expected_dip_rad': math.radians(64), 'method': 'compass'})
    try:
        R = np.eye(3)
        h.send(T0, *sample(R), mag_first=True)
        disturbed = FIELD_ENU + np.array([8e-6, 0.0, 0.0])
        h.send(T0 + 10_000_000, *sample(R, disturbed), mag_first=True)
        assert h.wait(2)
        clean, bad = (np.array(m.orientation_covariance) for m in h.out)
        assert bad[8] > 4 * clean[8]  # heading variance
    finally:
        h.close()


@pytest.mark.parametrize('fault', ['nan_accel', 'inf_field', 'zero_field', 'zero_accel', 'older_stamp', 'zero_stamp'])
def test_bad_messages_are_skipped_and_node_keeps_running(ros_context, fault, capfd):
    h = Harness(ros_context, {'constant_dt': 0.01})
    try:
        R = np.eye(3)
        accel, field = sample(R)
        h.send(T0 + 100_000_000, accel, field, mag_first=True)
        assert h.wait(1)
        bad_accel, bad_field, t_bad = accel.copy(), field.copy(), T0 + 110_000_000
        if fault == 'nan_accel':
            bad_accel[0] = float('nan')
        elif fault == 'inf_field':
            bad_field[2] = float('inf')
        elif fault == 'zero_field':
            bad_field[:] = 0.0
        elif fault == 'zero_accel':
            bad_accel[:] = 0.0
        elif fault == 'older_stamp':
            t_bad = T0 + 50_000_000
        elif fault == 'zero_stamp':
            t_bad = 0
        h.send(t_bad, bad_accel, bad_field, mag_first=True)
        h.send(T0 + 120_000_000, accel, field, mag_first=True)
        # A bad field sample is dropped and the IMU sample pairs with a good one 10 ms away;
        # a bad IMU sample (or stamp) produces no output at all.
        expected = 3 if fault.endswith('_field') else 2
        assert h.wait(expected)
        spin_until(h.ex, lambda: False, 0.2)
        assert len(h.out) == expected
        for m in h.out:
            assert np.all(np.isfinite(quat_xyzw(m.orientation)))
            assert np.allclose(rotation_from_quaternion(m.orientation), R, atol=1e-6)
            assert np.all(np.isfinite(m.orientation_covariance))
        err = capfd.readouterr().err
        assert 'dropped' in err or 'skipped' in err or 'not published' in err
        assert 'Traceback' not in err
    finally:
        h.close()


def test_clock_jump_back_resets_and_goes_on(ros_context, capfd):
    h = Harness(ros_context, {'constant_dt': 0.01})
    try:
        accel, field = sample(np.eye(3))
        for i in range(3):
            h.send(T0 + 5_000_000_000 + i * 10_000_000, accel, field)
        assert h.wait(3)
        for i in range(5):  # 5 s back: the bag looped. A sample or two at the seam may be lost.
            h.send(T0 + 10_000_000 * (i + 1), accel, field)
        assert h.wait(6)
        after = [m for m in h.out if m.header.stamp.sec == T0 // 10**9 and m.header.stamp.nanosec < 10**9]
        assert len(after) >= 3
        assert 'clock jumped back' in capfd.readouterr().err
    finally:
        h.close()


def test_rejects_bad_parameter_values(ros_context):
    with pytest.raises(ValueError, match='world_frame'):
        ImuMagnetometerNode(context=ros_context, parameter_overrides=[Parameter('world_frame', value='xyz')])
    with pytest.raises(ValueError, match='soft_iron_matrix'):
        ImuMagnetometerNode(context=ros_context, parameter_overrides=[Parameter('soft_iron_matrix', value=[0.0] * 9)])
    node = ImuMagnetometerNode(context=ros_context)
    try:
        result = node.set_parameters([Parameter('world_frame', value='up')])[0]
        assert not result.successful and 'world_frame' in result.reason
        assert node.get_parameter('world_frame').value == 'enu'
    finally:
        node.destroy_node()


def test_throttling_is_per_warning_not_per_node(ros_context, capfd):
    """Two kinds of bad input in a row: both are reported; a repeat of one is throttled."""
    node = ImuMagnetometerNode(context=ros_context)
    try:
        for _ in range(3):
            node.warn_throttled('first kind of problem')
            node.warn_throttled('second kind of problem')
        err = capfd.readouterr().err
        assert err.count('first kind of problem') == 1 and err.count('second kind of problem') == 1
    finally:
        node.destroy_node()


def test_live_parameters_change_the_output_and_read_only_ones_refuse(ros_context):
    """declination_rad, world_frame and publish_tf apply from the next sample on; a parameter
    the filter is built from (method) refuses a change instead of returning success."""
    TFMessage = pytest.importorskip('tf2_msgs.msg', reason='tf2_msgs not built (./ar-tracking.sh builds it)').TFMessage

    h = Harness(ros_context, {'method': 'compass', 'declination_rad': 0.1})
    tf_seen: list = []
    h.src.create_subscription(TFMessage, '/tf', tf_seen.append, 50)
    try:
        R = np.eye(3)  # body y axis = magnetic north
        h.send(T0, *sample(R), mag_first=True)
        assert h.wait(1)

        def north_deg(msg):  # direction of the body y axis, degrees east of true north (ENU)
            y = rotation_from_quaternion(msg.orientation)[:, 1]
            return math.degrees(math.atan2(y[0], y[1]))

        assert north_deg(h.out[-1]) == pytest.approx(math.degrees(0.1), abs=1e-6)
        result = h.node.set_parameters([Parameter('declination_rad', value=0.5)])[0]
        assert result.successful
        h.send(T0 + 10_000_000, *sample(R), mag_first=True)
        assert h.wait(2)
        assert north_deg(h.out[-1]) == pytest.approx(math.degrees(0.5), abs=1e-6)

        assert h.node.set_parameters([Parameter('world_frame', value='ned')])[0].successful
        assert h.node.set_parameters([Parameter('publish_tf', value=True)])[0].successful
        h.send(T0 + 20_000_000, *sample(R), mag_first=True)
        assert h.wait(3)
        assert rotation_from_quaternion(h.out[-1].orientation)[2, 2] == pytest.approx(-1.0)  # up is -down
        assert spin_until(h.ex, lambda: len(tf_seen) >= 1, 5.0)
        tf = tf_seen[-1].transforms[0]
        assert (tf.header.frame_id, tf.child_frame_id) == ('ned', 'imu')

        bad = h.node.set_parameters([Parameter('world_frame', value='xyz')])[0]
        assert not bad.successful and h.node.world_frame == 'ned'
        frozen = h.node.set_parameters([Parameter('method', value='vqf')])[0]
        assert not frozen.successful and 'read-only' in frozen.reason
        assert h.node.method == 'compass'
    finally:
        h.close()


def test_a_burst_of_a_second_of_samples_is_taken_whole(ros_context):
    """The node's process stalls (here: nobody spins) while a second of 100 Hz samples arrives:
    every one is still taken (STREAM_QOS keeps 200; the sensor-data default kept 5)."""
    h = Harness(ros_context)
    try:
        R = np.eye(3)
        for i in range(100):
            accel, field = sample(R)
            imu = Imu()
            imu.header.stamp = to_stamp(T0 + i * 10_000_000)
            imu.header.frame_id = 'imu'
            imu.linear_acceleration.x, imu.linear_acceleration.y, imu.linear_acceleration.z = map(float, accel)
            mag = MagneticField()
            mag.header = imu.header
            mag.magnetic_field.x, mag.magnetic_field.y, mag.magnetic_field.z = map(float, field)
            h.pub_imu.publish(imu)
            h.pub_mag.publish(mag)
        taken = lambda: [len(h.node.callback_stats[t].durations_ms) for t in ('imu/data_raw', 'imu/mag')]  # noqa: E731
        assert spin_until(h.ex, lambda: taken() == [100, 100], 5.0), taken()
    finally:
        h.close()
