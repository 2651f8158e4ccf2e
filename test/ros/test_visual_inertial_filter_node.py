"""visual_inertial_filter in-process: IMU + late marker poses in, vi/odometry out; bad input."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

rclpy = pytest.importorskip('rclpy')

from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import Imu  # noqa: E402

from ar_tracking.nodes.visual_inertial_filter import VisualInertialFilterNode  # noqa: E402
from ar_tracking.ros.conversions import set_quaternion, set_vector3, stamp_ns, to_stamp  # noqa: E402
from ar_tracking.sim import robot_arcs as ra  # noqa: E402
from conftest import spin_until  # noqa: E402

T0 = 1_700_000_000_000_000_000
CONFIG = Path(__file__).resolve().parents[2] / 'config' / 'visual_inertial_filter.yaml'


class Harness:
    def __init__(self, context, params=None):
        params = {'imu_to_camera_xyzw': [1.0, 0.0, 0.0, 0.0], **(params or {})}
        self.node = VisualInertialFilterNode(context=context, parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])
        self.src = rclpy.create_node('vi_test_source', context=context)
        self.odom: list[Odometry] = []
        self.pred: list[PoseStamped] = []
        self.src.create_subscription(Odometry, 'vi/odometry', self.odom.append, 1000)
        self.src.create_subscription(PoseStamped, 'vi/predicted_pose', self.pred.append, 1000)
        self.pub_imu = self.src.create_publisher(Imu, 'imu/data_raw', 1000)
        self.pub_pose = self.src.create_publisher(PoseWithCovarianceStamped, 'markers/pose', 100)
        self.ex = SingleThreadedExecutor(context=context)
        self.ex.add_node(self.node)
        self.ex.add_node(self.src)
        assert spin_until(self.ex, lambda: self.pub_imu.get_subscription_count() > 0 and self.pub_pose.get_subscription_count() > 0
                          and self.node.pub_odom.get_subscription_count() > 0)

    def imu(self, t_ns, gyro, accel):
        m = Imu()
        m.header.stamp = to_stamp(t_ns)
        m.header.frame_id = 'imu'
        set_vector3(m.angular_velocity, gyro)
        set_vector3(m.linear_acceleration, accel)
        n = self.node.core.imu_updates
        self.pub_imu.publish(m)
        spin_until(self.ex, lambda: self.node.callback_stats['imu/data_raw'].durations_ms and len(self.node.callback_stats['imu/data_raw'].durations_ms) >= self.sent_imu + 1, 2.0)
        self.sent_imu += 1
        return n

    sent_imu = 0
    sent_pose = 0

    def pose(self, t_ns, R, p, cov=None):
        m = PoseWithCovarianceStamped()
        m.header.stamp = to_stamp(t_ns)
        m.header.frame_id = 'enu'
        set_vector3(m.pose.pose.position, p)
        set_quaternion(m.pose.pose.orientation, R)
        c = np.eye(6) * 1e-5 if cov is None else cov
        m.pose.covariance = [float(x) for x in np.asarray(c).ravel()]
        self.pub_pose.publish(m)
        spin_until(self.ex, lambda: len(self.node.callback_stats['markers/pose'].durations_ms) >= self.sent_pose + 1, 2.0)
        self.sent_pose += 1

    def close(self):
        self.ex.shutdown()
        self.node.destroy_node()
        self.src.destroy_node()


def _sim(seconds):
    sched = ra.ArcSchedule.make(seconds + 1)
    t = np.arange(0, int(seconds * 1e9), 10_000_000, dtype=np.int64)
    tr = ra.truth_at(sched, t * 1e-9 + 6.0)  # start in the 64 cm/s half circle
    gyro, accel = ra.simulate_imu(tr, ra.make_imu_errors(0), 0)
    return T0 + t, tr, gyro, accel


def test_fuses_late_poses_and_survives_bad_input(ros_context):
    h = Harness(ros_context)
    try:
        t, tr, gyro, accel = _sim(2.5)
        for i in range(len(t)):
            if i % 7 == 0 and i >= 8:  # pose captured 8 samples (80 ms) ago
                h.pose(int(t[i - 8]), tr.R_enu_cam[i - 8], tr.position[i - 8])
            if i == 120:
                h.pose(int(t[i - 8]), tr.R_enu_cam[i - 8], tr.position[i - 8] + [0.6, 0, 0])   # jump: outlier
                h.pose(int(t[0]) - 2_000_000_000, tr.R_enu_cam[0], tr.position[0])           # older than the buffer
                bad = PoseWithCovarianceStamped()
                bad.header.stamp = to_stamp(int(t[i - 5]))
                bad.pose.pose.orientation.w = float('nan')
                h.pub_pose.publish(bad)
                spin_until(h.ex, lambda: False, 0.05)
                h.imu(int(t[i]) - 5_000_000, [np.nan, 0, 0], accel[i])                       # NaN IMU
            if 150 <= i < 160:
                continue                                                                      # IMU gap of 100 ms
            h.imu(int(t[i]), gyro[i], accel[i])
        assert spin_until(h.ex, lambda: len(h.odom) >= 200, 3.0)
        for msg in h.odom + [p for p in h.pred]:
            pose = msg.pose.pose if isinstance(msg, Odometry) else msg.pose
            vals = [pose.position.x, pose.position.y, pose.position.z, pose.orientation.w]
            assert np.all(np.isfinite(vals))
        # Accurate after the outlier, the NaN pose and the gap.
        idx = {int(x): k for k, x in enumerate(t)}
        errs = [np.linalg.norm(np.array([m.pose.pose.position.x, m.pose.pose.position.y, m.pose.pose.position.z]) - tr.position[idx[stamp_ns(m.header)]])
                for m in h.odom if stamp_ns(m.header) > t[200]]
        assert errs and max(errs) < 0.02
        assert h.odom[-1].child_frame_id == 'camera_optical' and h.odom[-1].header.frame_id == 'enu'
        assert stamp_ns(h.pred[-1].header) == stamp_ns(h.odom[-1].header) + 30_000_000
        assert h.node.core.rollbacks > 10
        assert np.all(np.isfinite(h.odom[-1].pose.covariance)) and h.odom[-1].pose.covariance[0] > 0
    finally:
        h.close()


def test_config_file_matches_declared_defaults(ros_context):
    params = yaml.safe_load(CONFIG.read_text())['visual_inertial_filter']['ros__parameters']
    node = VisualInertialFilterNode(context=ros_context)
    try:
        for key, value in params.items():
            assert node.has_parameter(key), key
            declared = node.get_parameter(key).value
            assert (list(declared) == value) if isinstance(value, list) else declared == pytest.approx(value), key
            assert node.describe_parameter(key).description
    finally:
        node.destroy_node()


def test_rejects_a_bad_extrinsic(ros_context):
    with pytest.raises(ValueError):
        VisualInertialFilterNode(context=ros_context, parameter_overrides=[Parameter('imu_to_camera_xyzw', value=[1.0, 1.0, 0.0, 0.0])])


def test_mount_from_tf_static_overrides_the_parameters(ros_context):
    from types import SimpleNamespace

    from ar_tracking.core.rotations import rot_z

    node = VisualInertialFilterNode(context=ros_context)   # no mount parameters: identity
    try:
        R = rot_z(0.5) @ np.diag([1.0, -1.0, -1.0])
        t = np.array([0.03, -0.05, 0.02])
        node.on_static_transforms([SimpleNamespace(parent='base', child='elsewhere', rotation=np.eye(3), translation=np.zeros(3)),
                                   SimpleNamespace(parent='imu', child='camera_optical', rotation=R, translation=t)])
        assert np.allclose(node.core.config.R_imu_cam, R) and np.allclose(node.core.config.t_imu_cam, t)
        assert node.mount_source == '/tf_static imu -> camera_optical'
        # the inverse direction (camera -> imu) gives the same mount
        node.on_static_transforms([SimpleNamespace(parent='camera_optical', child='imu', rotation=R.T, translation=-R.T @ t)])
        assert np.allclose(node.core.config.R_imu_cam, R) and np.allclose(node.core.config.t_imu_cam, t)
    finally:
        node.destroy_node()
    # Parameters that disagree: /tf_static wins (and the node says so).
    node = VisualInertialFilterNode(context=ros_context, parameter_overrides=[Parameter('imu_to_camera_xyzw', value=[1.0, 0.0, 0.0, 0.0])])
    try:
        assert node.mount_from_params
        node.on_static_transforms([SimpleNamespace(parent='imu', child='camera_optical', rotation=R, translation=t)])
        assert np.allclose(node.core.config.R_imu_cam, R)
    finally:
        node.destroy_node()
