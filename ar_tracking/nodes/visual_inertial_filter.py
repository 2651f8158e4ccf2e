"""visual_inertial_filter: marker camera poses fused with a 100 Hz IMU (Caarls 2009 sec. 2.5).

Subscribes ``imu/data_raw`` (sensor_msgs/Imu: rates and specific force, the time-update input
of both filters, Fig. 7) and ``markers/pose`` (PoseWithCovarianceStamped of camera_optical in the
map frame, stamped with the image capture time and arriving up to ~80 ms late: rolled back,
applied, replayed, Fig. 8). Publishes ``vi/odometry`` (nav_msgs/Odometry of camera_optical at
every IMU sample; twist in the camera frame, as REP-105 asks) and ``vi/predicted_pose``
(PoseStamped extrapolated ``render_latency_s`` ahead of the newest IMU stamp: the pose at display
time, Fig. 6), stamped with that display time.

The IMU mount - the rotation R_imu_cam and the lever arm (camera origin in the IMU frame) -
comes from ``/tf_static`` (the transform whose child, or parent, is ``child_frame_id``, the
camera frame): on a ROS install by a subscription, on the pip-only path (no tf2_msgs) from the
graph runner, which hands the bag's static transforms to :meth:`on_static_transforms` before
the first message. The parameters ``imu_to_camera_xyzw`` and ``camera_in_imu_m`` are the
fallback; a warning says when they were set and /tf_static disagrees (then /tf_static wins). A
mount arriving after the filter started re-initialises it (the state was built with the old one).
``imu/mag`` is not used (the camera is the absolute orientation reference; see the issue notes).
"""
from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from sensor_msgs.msg import Imu

from ..core.rotations import quat_xyzw_to_matrix, so3_log
from ..core.vio.eskf import FilterNoise, InitialUncertainty
from ..core.vio.rollback import FusionConfig, PoseMeasurement, RollbackFusion, Verdict
from ..ros.conversions import (
    ConversionError,
    covariance_is_known,
    rotation_from_quaternion,
    set_quaternion,
    set_vector3,
    stamp_ns,
    to_stamp,
    vector3,
)
from ..ros.node_base import (
    RELIABLE_QOS,
    STREAM_QOS,
    TrackingNode,
    run_node,
)
from ..ros.param_table import ParamSpec, declare_params, length_is, unit_quaternion
from ..ros.stamp_guard import StampGuard, StampVerdict
from ..ros.tf import subscribe_static_transforms

#: /tf_static and the parameters disagree enough for a warning (rotation rad, lever arm m).
_MOUNT_WARN_RAD = np.radians(1.0)
_MOUNT_WARN_M = 0.005


_NOISE = FilterNoise()
_INITIAL = InitialUncertainty()
_FUSION = FusionConfig()

#: The node's parameters (defaults of the filter's from its core configs).
PARAMS = (
    ParamSpec('gyro_noise_rad_s', _NOISE.gyro_noise_rad_s,
              'Gyro white noise per sample, 1-sigma, rad/s (sigma_z,w of Fig. 7)', min_value=1e-6, max_value=1.0),
    ParamSpec('angular_rate_change_rad_s', _NOISE.angular_rate_change_rad_s,
              'Process noise of the angular rate (user motion), rad/s/sqrt(s) (sigma_dw)',
              min_value=0.0, max_value=100.0),
    ParamSpec('gyro_bias_walk_rad_s', _NOISE.gyro_bias_walk_rad_s,
              'Gyro bias random walk, rad/s/sqrt(s) (sigma_db,w)', min_value=0.0, max_value=1.0),
    ParamSpec('accel_noise_m_s2', _NOISE.accel_noise_m_s2,
              'Accelerometer white noise per sample, 1-sigma, m/s^2 (sigma_z,a)', min_value=1e-6, max_value=10.0),
    ParamSpec('accel_change_m_s2', _NOISE.accel_change_m_s2,
              'Process noise of the acceleration (user motion), m/s^2/sqrt(s) (sigma_da)',
              min_value=0.0, max_value=1000.0),
    ParamSpec('accel_bias_walk_m_s2', _NOISE.accel_bias_walk_m_s2,
              'Accelerometer bias random walk, m/s^2/sqrt(s) (sigma_db,a)', min_value=0.0, max_value=10.0),
    ParamSpec('initial_velocity_sigma_m_s', _INITIAL.velocity_m_s,
              'Velocity 1-sigma at initialisation, m/s', min_value=1e-6, max_value=100.0),
    ParamSpec('initial_gyro_bias_sigma_rad_s', _INITIAL.gyro_bias_rad_s,
              'Gyro bias 1-sigma at initialisation, rad/s', min_value=1e-9, max_value=1.0),
    ParamSpec('initial_accel_bias_sigma_m_s2', _INITIAL.accel_bias_m_s2,
              'Accelerometer bias 1-sigma at initialisation, m/s^2', min_value=1e-9, max_value=10.0),
    ParamSpec('imu_to_camera_xyzw', [0.0, 0.0, 0.0, 1.0],
              'R_imu_cam as a quaternion (x, y, z, w): rotates camera_optical vectors into the IMU frame (the '
              '/tf_static imu -> camera_optical)', validate=unit_quaternion),
    ParamSpec('camera_in_imu_m', [0.0, 0.0, 0.0], 'Position of the camera origin in the IMU frame, m', validate=length_is(3)),
    ParamSpec('position_sigma_m', _FUSION.position_sigma_m,
              'Camera position noise 1-sigma when markers/pose has no covariance, and added to it, m',
              min_value=1e-6, max_value=10.0),
    ParamSpec('orientation_sigma_rad', _FUSION.orientation_sigma_rad,
              'Camera orientation noise 1-sigma when markers/pose has no covariance, and added to it, rad',
              min_value=1e-6, max_value=3.2),
    ParamSpec('gate_chi2', _FUSION.gate_chi2,
              'Innovation gate: squared Mahalanobis distance above which a pose is an outlier (0: no gate)',
              min_value=0.0, max_value=1e6),
    ParamSpec('max_consecutive_rejections', _FUSION.max_consecutive_rejections,
              'After this many poses rejected in a row, re-initialise from the camera', min_value=1, max_value=1000),
    ParamSpec('buffer_s', _FUSION.buffer_s,
              'Roll-back buffer length: poses older than this (vs the newest IMU sample) are rejected, s',
              min_value=0.05, max_value=30.0, read_only=True),
    ParamSpec('max_imu_gap_s', _FUSION.max_imu_gap_s,
              'IMU gaps longer than this are bridged with the newer sample and reported, s',
              min_value=0.001, max_value=10.0),
    ParamSpec('reset_gap_s', _FUSION.reset_gap_s,
              'IMU gaps longer than this lose the track until the next camera pose, s',
              min_value=0.001, max_value=60.0),
    ParamSpec('rollback', True,
              'Roll back to the capture time of late poses (false: apply on arrival, for comparison)'),
    ParamSpec('joint_error_state', _FUSION.joint,
              'One joint 15-state error filter (orientation-position couplings, the pose covariance in full); false: '
              'the two separate filters of Fig. 7'),
    ParamSpec('sampling_model', _FUSION.sampling_model,
              'Integrate each IMU interval with the step of the specific force placed at the kink of the angular rate '
              '(located from the gyro samples around it); false: the trapezoid'),
    ParamSpec('sampling_error_scale', _FUSION.sampling_error_scale,
              'Scale of the IMU sampling-error covariance (a step of the specific force between two samples, '
              'delta^2/12; 0: off)', min_value=0.0, max_value=100.0),
    ParamSpec('render_latency_s', 0.03,
              'Display latency: vi/predicted_pose is extrapolated this far ahead of the newest IMU sample, s',
              min_value=0.0, max_value=1.0),
    ParamSpec('world_frame_id', 'enu', 'frame_id of the outputs (the marker-map frame of markers/pose)'),
    ParamSpec('child_frame_id', 'camera_optical', 'child_frame_id of vi/odometry'),
    ParamSpec('reset_after_s', 1.0,
              'A stamp this much older than the previous one means the clock jumped back (bag loop): reset',
              min_value=0.0, max_value=3600.0),
)


class VisualInertialFilterNode(TrackingNode):
    INPUTS = {'imu/data_raw': 'sensor_msgs/msg/Imu', 'markers/pose': 'geometry_msgs/msg/PoseWithCovarianceStamped'}
    OUTPUTS = {'vi/odometry': 'nav_msgs/msg/Odometry', 'vi/predicted_pose': 'geometry_msgs/msg/PoseStamped'}
    REQUIRED_INPUTS = ['imu/data_raw', 'markers/pose']

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('visual_inertial_filter', **kwargs)
        v = declare_params(self, PARAMS)
        noise = FilterNoise(
            gyro_noise_rad_s=v['gyro_noise_rad_s'],
            angular_rate_change_rad_s=v['angular_rate_change_rad_s'],
            gyro_bias_walk_rad_s=v['gyro_bias_walk_rad_s'],
            accel_noise_m_s2=v['accel_noise_m_s2'],
            accel_change_m_s2=v['accel_change_m_s2'],
            accel_bias_walk_m_s2=v['accel_bias_walk_m_s2'],
        )
        initial = InitialUncertainty(
            velocity_m_s=v['initial_velocity_sigma_m_s'],
            gyro_bias_rad_s=v['initial_gyro_bias_sigma_rad_s'],
            accel_bias_m_s2=v['initial_accel_bias_sigma_m_s2'],
        )
        q_ic = v['imu_to_camera_xyzw']
        t_ic = v['camera_in_imu_m']
        self.config = FusionConfig(
            noise=noise, initial=initial,
            R_imu_cam=quat_xyzw_to_matrix(np.asarray(q_ic, float)),
            t_imu_cam=np.asarray(t_ic, float),
            position_sigma_m=v['position_sigma_m'],
            orientation_sigma_rad=v['orientation_sigma_rad'],
            gate_chi2=v['gate_chi2'],
            max_consecutive_rejections=v['max_consecutive_rejections'],
            buffer_s=v['buffer_s'],
            max_imu_gap_s=v['max_imu_gap_s'],
            reset_gap_s=v['reset_gap_s'],
            rollback=v['rollback'],
            joint=v['joint_error_state'],
            sampling_model=v['sampling_model'],
            sampling_error_scale=v['sampling_error_scale'],
        )
        self.render_latency_ns = int(1e9 * v['render_latency_s'])
        self.world_frame_id = v['world_frame_id']
        self.child_frame_id = v['child_frame_id']
        reset_s = v['reset_after_s']
        self.mount_from_params = bool(np.any(np.asarray(q_ic, float) != [0.0, 0.0, 0.0, 1.0]) or np.any(np.asarray(t_ic, float) != 0.0))
        self.mount_source = 'parameters' if self.mount_from_params else 'default (identity, no lever arm)'
        self.core = RollbackFusion(self.config)
        self.imu_guard = StampGuard(reset_s)
        self.gyro_var = noise.gyro_noise_rad_s ** 2
        self.published = 0
        self.pub_odom = self.advertise(Odometry, 'vi/odometry', RELIABLE_QOS)
        self.pub_pred = self.advertise(PoseStamped, 'vi/predicted_pose', RELIABLE_QOS)
        self.subscribe(Imu, 'imu/data_raw', self.on_imu, STREAM_QOS)
        self.subscribe(PoseWithCovarianceStamped, 'markers/pose', self.on_pose, RELIABLE_QOS)
        self._subscribe_tf_static()
        self.get_logger().info(f'visual_inertial_filter: roll-back {"on" if self.config.rollback else "off"}, buffer {self.config.buffer_s:g} s, '
                               f'{"joint error state" if self.config.joint else "separate orientation and position filters"}')

    # -- the IMU mount --------------------------------------------------------------------

    def _subscribe_tf_static(self) -> None:
        """/tf_static where tf2_msgs exists; on the pip-only path without it the graph runner
        hands the bag's static transforms to :meth:`on_static_transforms`."""
        subscribe_static_transforms(self, self.on_static_transforms)

    def on_static_transforms(self, transforms: list[Any]) -> None:
        """Static transforms (``parent``, ``child``, ``rotation`` rotating child vectors into the
        parent, ``translation`` the child's origin in the parent): the IMU mount from the one
        that names the camera frame (``child_frame_id``)."""
        cam = self.child_frame_id.lstrip('/')
        for tf in transforms:
            parent, child = str(tf.parent).lstrip('/'), str(tf.child).lstrip('/')
            R = np.asarray(tf.rotation, dtype=float)
            t = np.asarray(getattr(tf, 'translation', np.zeros(3)), dtype=float).reshape(3)
            if child == cam and parent != cam:
                R_imu_cam, t_imu_cam = R, t
            elif parent == cam and child != cam:
                R_imu_cam, t_imu_cam = R.T, -R.T @ t
            else:
                continue
            if not (np.all(np.isfinite(R_imu_cam)) and np.all(np.isfinite(t_imu_cam))):
                self.warn_throttled(f'/tf_static {parent} -> {child} is not finite; ignored')
                return
            d_rot = float(np.linalg.norm(so3_log(self.config.R_imu_cam.T @ R_imu_cam)))
            d_pos = float(np.linalg.norm(self.config.t_imu_cam - t_imu_cam))
            source = f'/tf_static {parent} -> {child}'
            if self.mount_from_params and (d_rot > _MOUNT_WARN_RAD or d_pos > _MOUNT_WARN_M):
                self.get_logger().warning(
                    f'{source} differs from imu_to_camera_xyzw / camera_in_imu_m by {np.degrees(d_rot):.1f} deg '
                    f'and {100 * d_pos:.1f} cm: using /tf_static')
            else:
                self.get_logger().info(f'IMU mount from {source}')
            if d_rot > 1e-9 or d_pos > 1e-9:
                self.config = replace(self.config, R_imu_cam=R_imu_cam, t_imu_cam=t_imu_cam)
                started = self.core.state is not None
                self.core.config = self.config
                if started:
                    self.get_logger().warning('IMU mount changed after the filter started: re-initialising')
                    self.core.reset()
            self.mount_source = source
            return

    def on_imu(self, msg: Imu) -> None:
        gyro, accel = vector3(msg.angular_velocity), vector3(msg.linear_acceleration)
        if not (np.all(np.isfinite(gyro)) and np.all(np.isfinite(accel))):
            self.warn_throttled('imu/data_raw: non-finite rate or acceleration; sample dropped')
            return
        t = stamp_ns(msg.header)
        verdict = self.imu_guard.check(t)
        if verdict is StampVerdict.RESET:
            self.get_logger().warning('imu/data_raw: clock jumped back (bag loop?); filter reset')
            self.core.reset()
        elif verdict is not StampVerdict.OK:
            self.warn_throttled(f'imu/data_raw: {verdict.value}; sample dropped')
            return
        result = self.core.add_imu(t, gyro, accel)
        if result in (Verdict.GAP, Verdict.RESET_GAP):
            self.warn_throttled(f'imu/data_raw: {result.value}')
        elif result is not Verdict.OK:
            self.warn_throttled(f'imu/data_raw: {result.value}; sample dropped')
            return
        self._publish(msg.header.stamp, t)

    def on_pose(self, msg: PoseWithCovarianceStamped) -> None:
        t = stamp_ns(msg.header)
        if t <= 0:
            self.warn_throttled('markers/pose: zero stamp; dropped')
            return
        try:
            R = rotation_from_quaternion(msg.pose.pose.orientation, 'markers/pose orientation')
        except ConversionError as exc:
            self.warn_throttled(f'{exc}; dropped')
            return
        p = vector3(msg.pose.pose.position)
        cov = None
        if covariance_is_known(msg.pose.covariance):
            cov = np.asarray(msg.pose.covariance, dtype=float).reshape(6, 6)
        if not np.all(np.isfinite(p)) or (cov is not None and not np.all(np.isfinite(cov))):
            self.warn_throttled('markers/pose: non-finite position or covariance; dropped')
            return
        if msg.header.frame_id and msg.header.frame_id != self.world_frame_id:
            self.warn_throttled(f'markers/pose is in {msg.header.frame_id!r}, expected {self.world_frame_id!r}; used as is')
        verdict = self.core.add_pose(PoseMeasurement(t, R, p, cov))
        if verdict in (Verdict.TOO_OLD, Verdict.OUTLIER, Verdict.INVALID, Verdict.REINITIALISED):
            self.warn_throttled(f'markers/pose at {t * 1e-9:.3f}: {verdict.value}' + ('' if verdict is Verdict.REINITIALISED else '; rejected'))

    def _publish(self, stamp: Any, t_ns: int) -> None:
        s = self.core.state
        if s is None:
            return
        R, p = self.core.camera_pose(s)
        cov = self.core.camera_covariance(s)
        v_w, w_cam = self.core.camera_velocity(s)
        R_pred, p_pred = self.core.extrapolate(s, self.render_latency_ns * 1e-9)
        if not all(np.all(np.isfinite(a)) for a in (R, p, cov, v_w, w_cam, R_pred, p_pred)):
            self.warn_throttled('filter output not finite; not published')
            return
        odom = Odometry()
        odom.header.stamp = stamp
        odom.header.frame_id = self.world_frame_id
        odom.child_frame_id = self.child_frame_id
        set_vector3(odom.pose.pose.position, p)
        set_quaternion(odom.pose.pose.orientation, R)
        odom.pose.covariance = [float(x) for x in cov.ravel()]
        set_vector3(odom.twist.twist.linear, R.T @ v_w)
        set_vector3(odom.twist.twist.angular, w_cam)
        tcov = np.zeros((6, 6))
        tcov[:3, :3] = R.T @ s.pos.P[3:6, 3:6] @ R
        tcov[3:, 3:] = np.eye(3) * self.gyro_var
        odom.twist.covariance = [float(x) for x in tcov.ravel()]
        self.pub_odom.publish(odom)
        pred = PoseStamped()
        pred.header.stamp = to_stamp(t_ns + self.render_latency_ns)
        pred.header.frame_id = self.world_frame_id
        set_vector3(pred.pose.position, p_pred)
        set_quaternion(pred.pose.orientation, R_pred)
        self.pub_pred.publish(pred)
        self.published += 1


def main(args: list[str] | None = None) -> int:
    return run_node(VisualInertialFilterNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
