"""hybrid_orientation_filter: absolute camera orientation from vision plus compass (Langlotz 2011 sec. 5).

Subscribes
  ``panorama/orientation`` geometry_msgs/TransformStamped panorama -> camera_optical (or, with
  ``relative_input_type: pose``, a PoseStamped such as ``slam/pose``: any relative orientation
  source can be remapped in), ``imu/data`` sensor_msgs/Imu (absolute orientation of the IMU body in
  ENU with covariance, from imu_magnetometer) and ``imu/data_raw`` (gyro, for the backup).
Publishes
  ``orientation/global`` sensor_msgs/Imu: the camera orientation in ENU (eq. 1 with the filtered
  R_PN), frame_id ``camera_optical``, with covariance; at the visual tracker's stamps, and from
  the integrated gyro (at ``backup_rate_hz``) while the tracker is lost;
  ``orientation/panorama_in_world`` geometry_msgs/TransformStamped enu -> panorama (R_PN^-1).

The callbacks only validate, convert, call :mod:`ar_tracking.core.hybrid_orientation` and publish.
"""
from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseStamped, TransformStamped
from sensor_msgs.msg import Imu

from ..core.hybrid_orientation import (
    GyroBackup,
    GyroBackupParams,
    HybridFilterParams,
    PanoramaWorldFilter,
    RotationBuffer,
)
from ..core.rotations import quat_xyzw_to_matrix, so3_log
from ..ros.conversions import (
    ConversionError,
    covariance_is_known,
    rotation_from_quaternion,
    set_covariance,
    set_quaternion,
    stamp_ns,
    to_stamp,
    vector3,
)
from ..ros.node_base import RELIABLE_QOS, SENSOR_QOS, TrackingNode, run_node
from ..ros.stamp_guard import StampGuard, StampVerdict

INPUT_TYPES = {'transform': TransformStamped, 'pose': PoseStamped}


def _length(n: int) -> Any:
    return lambda v: None if len(v) == n else f'needs {n} values, got {len(v)}'


def _unit_quat(v: Any) -> str | None:
    if len(v) != 4:
        return f'needs 4 values (x, y, z, w), got {len(v)}'
    norm = float(np.linalg.norm(np.asarray(v, dtype=float)))
    return None if abs(norm - 1.0) < 1e-3 else f'not a unit quaternion (norm {norm:.4g})'


class HybridOrientationFilterNode(TrackingNode):
    INPUTS = {
        'panorama/orientation': 'geometry_msgs/msg/TransformStamped',
        'imu/data': 'sensor_msgs/msg/Imu',
        'imu/data_raw': 'sensor_msgs/msg/Imu',
    }
    REQUIRED_INPUTS = ['panorama/orientation', 'imu/data']
    OUTPUTS = {
        'orientation/global': 'sensor_msgs/msg/Imu',
        'orientation/panorama_in_world': 'geometry_msgs/msg/TransformStamped',
    }

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('hybrid_orientation_filter', **kwargs)
        p = self.param
        d = HybridFilterParams()
        g = GyroBackupParams()
        input_type = p('relative_input_type', 'transform',
                       'Message type of panorama/orientation: transform (TransformStamped reference -> camera) '
                       'or pose (PoseStamped, orientation of the camera in header.frame_id)',
                       read_only=True, validate=lambda v: None if v in INPUT_TYPES else 'must be transform or pose')
        q_imu_cam = p('imu_to_camera_quat_xyzw', [1.0, 0.0, 0.0, 0.0],
                      'Rotation imu -> camera_optical (R_imu_cam, x y z w); default the phone: diag(1, -1, -1)',
                      read_only=True, validate=_unit_quat)
        self.camera_frame: str = p('camera_frame_id', 'camera_optical', 'frame_id of orientation/global (the camera)')
        self.world_frame: str = p('world_frame_id', 'enu', 'World frame of imu/data and of the outputs (ENU)')
        params = HybridFilterParams(
            process_noise_rad_sqrt_s=p('process_noise_rad_sqrt_s', d.process_noise_rad_sqrt_s, 'Random walk of the panorama-in-world rotation, rad/sqrt(s) (follows a drifting tracker)', min_value=0.0, max_value=1.0),
            visual_noise_rad=p('visual_noise_rad', d.visual_noise_rad, 'Noise of the visual orientation, 1-sigma rad', min_value=0.0, max_value=1.0),
            default_sensor_sigma_rad=p('default_sensor_sigma_rad', d.default_sensor_sigma_rad, 'Sensor orientation 1-sigma used when imu/data has no covariance (-1), rad', min_value=1e-6, max_value=3.2),
            min_sensor_sigma_rad=p('min_sensor_sigma_rad', d.min_sensor_sigma_rad, 'Floor on the sensor orientation 1-sigma, rad', min_value=0.0, max_value=3.2),
            max_sensor_heading_sigma_rad=p('max_sensor_heading_sigma_rad', d.max_sensor_heading_sigma_rad, 'Reject imu/data whose heading 1-sigma exceeds this (field magnitude/dip disturbed), rad', min_value=0.0, max_value=10.0),
            gate_chi2=p('gate_chi2', d.gate_chi2, 'Mahalanobis gate on the innovation (3 dof; 0 disables)', min_value=0.0, max_value=1e6),
            heading_gate_rad=p('heading_gate_rad', d.heading_gate_rad, 'Reject while the short-time mean heading innovation exceeds this, rad (0 disables)', min_value=0.0, max_value=3.2),
            heading_gate_window_s=p('heading_gate_window_s', d.heading_gate_window_s, 'Time constant of that mean, s', min_value=0.01, max_value=60.0),
            gate_after_sigma_rad=p('gate_after_sigma_rad', d.gate_after_sigma_rad, 'Gates apply once the heading 1-sigma of the estimate is below this, rad', min_value=0.0, max_value=3.2),
            max_reject_s=p('max_reject_s', d.max_reject_s, 'After this long with every sensor sample rejected, re-seed from the sensor, s', min_value=0.0, max_value=3600.0),
            direction_bins=p('direction_bins', d.direction_bins, 'Heading bins of the direction-spread weighting (0 disables)', min_value=0, max_value=360),
            direction_ref_count=p('direction_ref_count', d.direction_ref_count, 'Samples per heading bin at full weight; more weigh less', min_value=1.0, max_value=1e9),
            direction_memory_s=p('direction_memory_s', d.direction_memory_s, 'Forgetting time of the heading bin counts, s', min_value=0.1, max_value=1e6),
        )
        backup = GyroBackupParams(
            gyro_noise_rad_s=p('gyro_noise_rad_s', g.gyro_noise_rad_s, 'Gyro rate noise, 1-sigma per sample, rad/s', min_value=0.0, max_value=10.0),
            bias_sigma_rad_s=p('gyro_bias_sigma_rad_s', g.bias_sigma_rad_s, 'Residual gyro bias after learning, 1-sigma rad/s (backup covariance)', min_value=0.0, max_value=10.0),
            bias_window_s=p('gyro_bias_window_s', g.bias_window_s, 'Interval over which gyro and visual rotations are compared to learn the bias, s', min_value=0.05, max_value=10.0),
            bias_gain=p('gyro_bias_gain', g.bias_gain, 'Weight of one comparison in the running gyro bias (0: no learning)', min_value=0.0, max_value=1.0),
        )
        gyro_bias = np.asarray(p('gyro_bias', [0.0, 0.0, 0.0], 'Gyro bias subtracted from imu/data_raw before integration, rad/s', validate=_length(3)), dtype=float)
        self.max_pair_gap_ns = int(1e9 * p('max_pair_gap_s', 0.2, 'Largest gap between two visual orientations that is interpolated across, s', min_value=0.0, max_value=10.0))
        self.visual_timeout_ns = int(1e9 * p('visual_timeout_s', 0.2, 'No visual orientation for this long (in stamps): the tracker is lost, the gyro backup publishes', min_value=0.0, max_value=60.0))
        self.backup_period_ns = int(1e9 / p('backup_rate_hz', 30.0, 'Rate of orientation/global from the gyro backup, Hz', min_value=0.1, max_value=1000.0))
        self.max_backup_ns = int(1e9 * p('max_backup_s', 30.0, 'Stop the gyro backup after this long without vision, s', min_value=0.0, max_value=3600.0))
        self.reseed_rad: float = p('reseed_threshold_rad', 0.1, 'When vision returns this far from the gyro backup, its frame changed: re-seed the filter from the backup, rad', min_value=0.0, max_value=3.2)
        self.sensor_timeout_ns = int(1e9 * p('sensor_timeout_s', 1.0, 'Warn when imu/data has been silent this long', min_value=0.0, max_value=3600.0))
        reset_s = p('reset_after_s', 1.0, 'A stamp this much older than the previous one means the clock jumped back (bag loop): reset', min_value=0.0, max_value=3600.0)

        self.R_imu_cam = quat_xyzw_to_matrix(np.asarray(q_imu_cam, dtype=float))
        self.gyro_bias = gyro_bias
        self.filter = PanoramaWorldFilter(params)
        self.backup = GyroBackup(self.R_imu_cam, backup)
        self.visual = RotationBuffer(self.max_pair_gap_ns)
        self.pending: deque[tuple[int, np.ndarray, np.ndarray | None]] = deque()
        self.stamp_guards = {k: StampGuard(reset_s) for k in ('visual', 'sensor', 'gyro')}
        self.last_visual_ns: int | None = None
        self.last_sensor_ns: int | None = None
        self.last_backup_pub_ns: int | None = None
        self.panorama_frame = 'panorama'
        self.published = 0

        self.pub_global = self.advertise(Imu, 'orientation/global', RELIABLE_QOS)
        self.pub_frame = self.advertise(TransformStamped, 'orientation/panorama_in_world', RELIABLE_QOS)
        self.input_type = input_type
        self.subscribe(INPUT_TYPES[input_type], 'panorama/orientation', self.on_visual, SENSOR_QOS)
        self.subscribe(Imu, 'imu/data', self.on_sensor, SENSOR_QOS)
        self.subscribe(Imu, 'imu/data_raw', self.on_gyro, SENSOR_QOS)
        self.get_logger().info(f'hybrid_orientation_filter: panorama/orientation as {input_type}, imu/data, imu/data_raw')

    # -- helpers ---------------------------------------------------------------------------

    def _reset(self, why: str) -> None:
        self.get_logger().warning(f'{why}: starting over')
        self.filter.reset()
        self.backup.reset()
        self.visual.clear()
        self.pending.clear()
        for guard in self.stamp_guards.values():
            guard.reset()
        self.last_visual_ns = self.last_sensor_ns = self.last_backup_pub_ns = None

    def _stamp_ok(self, key: str, t_ns: int, what: str) -> bool:
        verdict = self.stamp_guards[key].check(t_ns)
        if verdict is StampVerdict.OK:
            return True
        if verdict is StampVerdict.RESET:
            self._reset(f'{what}: {verdict.value} (bag loop?)')
            self.stamp_guards[key].check(t_ns)
            return True
        self.warn_throttled(f'{what}: {verdict.value}, message dropped')
        return False

    def _publish(self, t_ns: int, R_enu_cam: np.ndarray, cov: np.ndarray) -> None:
        """orientation/global and orientation/panorama_in_world, never with NaN."""
        if not (np.all(np.isfinite(R_enu_cam)) and np.all(np.isfinite(cov))):
            self.warn_throttled('estimate is not finite; not published')
            return
        out = Imu()
        out.header.stamp = to_stamp(t_ns)
        out.header.frame_id = self.camera_frame
        set_quaternion(out.orientation, R_enu_cam)
        set_covariance(out.orientation_covariance, 0.5 * (cov + cov.T))
        set_covariance(out.angular_velocity_covariance, None)
        set_covariance(out.linear_acceleration_covariance, None)
        self.pub_global.publish(out)
        tf = TransformStamped()
        tf.header.stamp = out.header.stamp
        tf.header.frame_id = self.world_frame
        tf.child_frame_id = self.panorama_frame
        set_quaternion(tf.transform.rotation, self.filter.R_hat.T)
        self.pub_frame.publish(tf)
        self.published += 1

    def _resolve(self) -> None:
        """Pair pending sensor samples with the visual orientation slerped at their stamps."""
        newest_visual = self.visual.newest_ns
        while self.pending:
            t_s, R_enu_cam, cov = self.pending[0]
            if newest_visual is None or newest_visual < t_s:
                # Wait for a visual sample at or after t_s, unless vision is lost by now.
                if self.last_sensor_ns is not None and self.last_sensor_ns - t_s > self.visual_timeout_ns:
                    self.pending.popleft()
                    continue
                break
            self.pending.popleft()
            R_pano_cam = self.visual.at(t_s)
            if R_pano_cam is None:  # before the buffer, or across a lost stretch
                continue
            self.filter.update(t_s, R_pano_cam, R_enu_cam, cov)

    # -- callbacks -------------------------------------------------------------------------

    def on_visual(self, msg: Any) -> None:
        """One relative orientation R_ref_cam: pair, update, publish eq. 1."""
        try:
            if self.input_type == 'pose':
                R_pano_cam = rotation_from_quaternion(msg.pose.orientation, 'panorama/orientation')
            else:
                R_pano_cam = rotation_from_quaternion(msg.transform.rotation, 'panorama/orientation')
        except ConversionError as exc:
            self.warn_throttled(f'{exc}, message dropped')
            return
        t_v = stamp_ns(msg.header)
        if not self._stamp_ok('visual', t_v, 'panorama/orientation'):
            return
        if msg.header.frame_id:
            self.panorama_frame = msg.header.frame_id.lstrip('/')
        returning = self.last_visual_ns is not None and t_v - self.last_visual_ns > self.visual_timeout_ns
        if returning and self.filter.initialized and self.backup.R_enu_cam is not None:
            R_vis = self.filter.global_orientation(R_pano_cam)
            jump = float(np.linalg.norm(so3_log(self.backup.R_enu_cam.T @ R_vis)))
            if jump > self.reseed_rad:
                # A new visual reference frame (tracker restarted): carry the heading over from
                # the gyro backup, so the output does not jump, and let the compass refine it.
                self.get_logger().warning(
                    f'vision returned {np.degrees(jump):.1f} deg away from the gyro backup: '
                    're-seeding the panorama frame from the backup')
                R_pe = R_pano_cam @ self.backup.R_enu_cam.T
                self.filter.seed(t_v, R_pe, R_pe @ self.backup.cov @ R_pe.T)
            self.visual.clear()
            self.backup.visual.clear()
        self.last_visual_ns = t_v
        self.visual.add(t_v, R_pano_cam)
        self.backup.add_visual(t_v, R_pano_cam)
        self._resolve()
        if not self.filter.initialized:
            self.warn_throttled('waiting for imu/data to place the panorama in the world')
            return
        if self.last_sensor_ns is None or t_v - self.last_sensor_ns > self.sensor_timeout_ns:
            self.warn_throttled('imu/data is silent: publishing with the last panorama-in-world estimate, covariance growing')
        self.filter.predict(t_v)
        R_enu_cam = self.filter.global_orientation(R_pano_cam)
        vis_var = self.filter.params.visual_noise_rad ** 2
        cov = self.filter.world_covariance() + np.eye(3) * vis_var
        self.backup.anchor(t_v, R_enu_cam, cov)
        self._publish(t_v, R_enu_cam, cov)

    def on_sensor(self, msg: Imu) -> None:
        """Absolute orientation of the IMU (imu/data): queue it for pairing with vision."""
        if not covariance_is_known(msg.orientation_covariance):
            cov = None  # REP-145: unknown, the default sigma is used
        else:
            cov = np.asarray(msg.orientation_covariance, dtype=float).reshape(3, 3)
            if not np.all(np.isfinite(cov)) or np.any(np.diag(cov) < 0):
                self.warn_throttled('imu/data orientation covariance is not finite or negative, message dropped')
                return
        try:
            R_enu_imu = rotation_from_quaternion(msg.orientation, 'imu/data orientation')
        except ConversionError as exc:
            self.warn_throttled(f'{exc}, message dropped')
            return
        t_s = stamp_ns(msg.header)
        if not self._stamp_ok('sensor', t_s, 'imu/data'):
            return
        frame = msg.header.frame_id.lstrip('/')
        R_enu_cam = R_enu_imu if frame == self.camera_frame else R_enu_imu @ self.R_imu_cam
        self.last_sensor_ns = t_s
        self.pending.append((t_s, R_enu_cam, cov))
        self._resolve()

    def on_gyro(self, msg: Imu) -> None:
        """Gyro sample: integrate; while vision is lost, publish the backup orientation."""
        omega = vector3(msg.angular_velocity)
        if not np.all(np.isfinite(omega)):
            self.warn_throttled('imu/data_raw angular_velocity is not finite, message dropped')
            return
        t_g = stamp_ns(msg.header)
        if not self._stamp_ok('gyro', t_g, 'imu/data_raw'):
            return
        self.backup.add_gyro(t_g, omega - self.gyro_bias)
        if self.last_visual_ns is None or self.backup.R_enu_cam is None or not self.filter.initialized:
            return
        lost_for = t_g - self.last_visual_ns
        if lost_for <= self.visual_timeout_ns:
            return
        if lost_for > self.max_backup_ns:
            self.warn_throttled('visual tracker lost for too long: gyro backup stopped')
            return
        if self.last_backup_pub_ns is not None and t_g - self.last_backup_pub_ns < self.backup_period_ns:
            return
        self.warn_throttled('visual tracker lost: publishing the gyro backup')
        self.last_backup_pub_ns = t_g
        self._publish(t_g, self.backup.R_enu_cam, self.backup.cov)


def main(args: list[str] | None = None) -> int:
    return run_node(HybridOrientationFilterNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
