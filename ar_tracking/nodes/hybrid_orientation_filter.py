"""hybrid_orientation_filter: absolute camera orientation from vision plus the phone's sensors (Langlotz 2011 sec. 5).

Subscribes
  ``panorama/orientation`` geometry_msgs/TransformStamped panorama -> camera_optical (or, with
  ``relative_input_type: pose``, a PoseStamped such as ``slam/pose``: any relative orientation
  source can be remapped in); ``imu/data_raw`` sensor_msgs/Imu (gyro and accelerometer) and
  ``imu/mag`` sensor_msgs/MagneticField (raw, calibrated here with the same parameters as
  imu_magnetometer); ``imu/data`` (the AHRS orientation, used while there is no camera).
Publishes
  ``orientation/global`` sensor_msgs/Imu: the camera orientation in ENU with covariance - eq. 1
  with the panorama's place in the world R_PN estimated over the whole panorama session from
  gravity and field carried into the panorama frame (:mod:`ar_tracking.core.world_alignment`),
  at the visual tracker's stamps (and, with ``gyro_rate_output``, at every gyro sample between
  them); from the gyro while the tracker is lost; and from ``imu/data`` (the AHRS, turned into
  the camera frame) when there is no camera at all, so the node runs without one.
  ``orientation/panorama_in_world`` geometry_msgs/TransformStamped enu -> panorama (R_PN^-1).

The IMU -> camera rotation comes from ``/tf_static`` when the graph or the bag has it (the
parameter ``imu_to_camera_quat_xyzw`` is the fallback, with a warning when the two disagree).
IMU and field samples are paired with the visual orientation at their own stamps, moved into
the camera's clock by the camera-IMU time offset (``core/time_offset.py``, logged when known).
A field sample that only repeats the previous value (a magnetometer slower than its topic) is
skipped, with one log line.

TF (``publish_tf``): every orientation/global is also broadcast on ``/tf`` as
``world_frame_id`` -> ``camera_frame_id``, and, while the mount comes from the parameter, the
IMU mount ``imu_frame_id`` -> ``camera_frame_id`` once on ``/tf_static`` (``publish_mount_tf``).
Frame names, the TF switches and the timing/noise parameters apply live; the rest is read-only.
The callbacks only validate, convert, call the cores and publish.
"""
from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseStamped, TransformStamped
from sensor_msgs.msg import Imu, MagneticField

from ..core.hybrid_orientation import GyroBackup, GyroBackupConfig, RotationBuffer, StreamLag
from ..core.panorama_azimuth import AzimuthDistortion, AzimuthDistortionConfig
from ..core.rotations import quat_xyzw_to_matrix, so3_log
from ..core.time_offset import ImuClock, TimeOffsetConfig, TimeOffsetEstimator
from ..core.world_alignment import WorldAlignment, WorldAlignmentConfig, WorldAlignmentEstimate
from ..ros.cdr_views import (
    imu_view,
    magnetic_field_view,
    orientation_imu_cdr,
    rotation_transform_cdr,
    transform_stamped_view,
)
from ..ros.conversions import (
    ConversionError,
    covariance_is_known,
    finite_vector3,
    imu_sample,
    rotation_from_quaternion,
    stamp_ns,
)
from ..ros.node_base import RELIABLE_QOS, RELIABLE_STREAM_QOS, STREAM_QOS, TrackingNode, run_node
from ..ros.hybrid_orientation_params import PARAMS
from ..ros.param_table import declare_params, imu_calibration
from ..ros.stamp_guard import StampGuard, StampVerdict
from ..ros.tf import TfBroadcaster, subscribe_static_transforms, transform_stamped

INPUT_TYPES = {'transform': TransformStamped, 'pose': PoseStamped}
#: Disagreement between /tf_static and the parameter that is worth a warning, rad.
_EXTRINSIC_WARN_RAD = np.radians(1.0)
#: Residual hard iron worth telling the user about (once the rotations pin it), relative to the
#: field strength: 3 uT of 48, ~8 deg of heading before the phone turns.
_HARD_IRON_REPORT = 0.06
#: ... once the heading is known to this (1 sigma), rad.
_HARD_IRON_REPORT_SIGMA_RAD = np.radians(1.0)
#: The first seconds of IMU samples kept to re-pair once the time offset settles, ns.
_REPAIR_NS = 10_000_000_000
#: Before the first visual orientation arrives, IMU and field samples of this long are kept
#: (the first frame's stamp can be this much older than the IMU's newest: camera latency), ns.
_PRE_VISION_NS = 1_000_000_000
#: The orientation a tracker publishes for the first frame of a new panorama or map.
_IDENTITY = np.eye(3)
#: A visual lag worth telling the user about once, ns.
_LAG_REPORT_NS = 20_000_000


class HybridOrientationFilterNode(TrackingNode):
    INPUTS = {
        'panorama/orientation': 'geometry_msgs/msg/TransformStamped',
        'imu/data_raw': 'sensor_msgs/msg/Imu',
        'imu/mag': 'sensor_msgs/msg/MagneticField',
        'imu/data': 'sensor_msgs/msg/Imu',
    }
    #: Runs without a camera (then it follows imu/data); vision needs imu/data_raw + imu/mag.
    REQUIRED_INPUTS = [('panorama/orientation', 'imu/data')]
    OUTPUTS = {
        'orientation/global': 'sensor_msgs/msg/Imu',
        'orientation/panorama_in_world': 'geometry_msgs/msg/TransformStamped',
    }

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('hybrid_orientation_filter', **kwargs)
        def live_ns(attr: str, scale: float = 1e9) -> Any:
            return lambda v: setattr(self, attr, int(scale * v))

        v = declare_params(self, PARAMS, live={
            'camera_frame_id': lambda x: setattr(self, 'camera_frame', x),
            'world_frame_id': lambda x: setattr(self, 'world_frame', x),
            'imu_frame_id': self._set_imu_frame,
            'publish_tf': lambda x: setattr(self, 'publish_tf', x),
            'publish_mount_tf': self._set_publish_mount_tf,
            'declination_rad': lambda x: self.align.set_declination(x),
            'visual_noise_rad': lambda x: setattr(self, 'visual_noise_rad', x),
            'visual_timeout_s': live_ns('visual_timeout_ns'),
            'backup_rate_hz': lambda x: setattr(self, 'backup_period_ns', int(1e9 / x)),
            'max_backup_s': live_ns('max_backup_ns'),
            'gyro_rate_output': lambda x: setattr(self, 'gyro_rate_output', x),
            'reseed_threshold_rad': lambda x: setattr(self, 'reseed_rad', x),
            'reset_after_s': self._set_reset_after,
        })
        input_type = v['relative_input_type']
        q_imu_cam = v['imu_to_camera_quat_xyzw']
        self.camera_frame: str = v['camera_frame_id']
        self.world_frame: str = v['world_frame_id']
        self.imu_frame: str = v['imu_frame_id']
        self.publish_tf: bool = v['publish_tf']
        self.publish_mount_tf: bool = v['publish_mount_tf']
        self.calibration = imu_calibration(v)
        config = WorldAlignmentConfig(
            accel_bias_sigma_m_s2=v['accel_bias_sigma_m_s2'],
            hard_iron_sigma=v['hard_iron_sigma'],
            soft_iron_sigma=v['soft_iron_sigma'],
            window_s=v['window_s'],
            solve_period_s=v['solve_period_s'],
            solve_period_share=v['solve_period_share'],
            hand_velocity_m_s=v['hand_velocity_m_s'],
            correlation_s=v['correlation_s'],
            hand_period_s=v['hand_period_s'],
            hard_iron_prior_sigma=v['hard_iron_prior_sigma'],
            soft_iron_prior_sigma=v['soft_iron_prior_sigma'],
            lever_arm_sigma_m=v['lever_arm_sigma_m'],
            cauchy_scale=v['cauchy_scale'],
            tilt_floor_rad=v['tilt_floor_rad'],
            heading_floor_rad=v['heading_floor_rad'],
            declination_rad=v['declination_rad'],
        )
        backup = GyroBackupConfig(
            gyro_noise_rad_s=v['gyro_noise_rad_s'],
            bias_sigma_rad_s=v['gyro_bias_sigma_rad_s'],
            bias_window_s=v['gyro_bias_window_s'],
            bias_gain=v['gyro_bias_gain'],
            tilt_tau_s=v['backup_tilt_tau_s'],
        )
        self.visual_noise_rad: float = v['visual_noise_rad']
        self.max_pair_gap_ns = int(1e9 * v['max_pair_gap_s'])
        self.visual_timeout_ns = int(1e9 * v['visual_timeout_s'])
        self.backup_period_ns = int(1e9 / v['backup_rate_hz'])
        self.max_backup_ns = int(1e9 * v['max_backup_s'])
        self.gyro_rate_output: bool = v['gyro_rate_output']
        self.reseed_rad: float = v['reseed_threshold_rad']
        reset_s = v['reset_after_s']

        self.R_imu_cam_param = quat_xyzw_to_matrix(np.asarray(q_imu_cam, dtype=float))
        self.R_imu_cam = self.R_imu_cam_param
        self.extrinsic_source = 'parameter'
        self.align = WorldAlignment(config)
        self.backup = GyroBackup(self.R_imu_cam, backup)
        #: The panorama's azimuth distortion (a camera turned about the user), learnt from the gyro.
        self.distortion = AzimuthDistortion(self.R_imu_cam, AzimuthDistortionConfig(
            knots=v['distortion_knots'], pair_s=v['distortion_pair_s'],
            smoothness_rad=v['distortion_smoothness_rad'], scale_sigma=v['gyro_scale_sigma'],
        )) if v['learn_panorama_distortion'] else None
        # IMU stamps are shifted into the camera's clock: t_camera = t_imu - clock.offset_ns.
        estimator = TimeOffsetEstimator(self.R_imu_cam, TimeOffsetConfig(max_offset_s=v['max_time_offset_s'])) \
            if v['estimate_time_offset'] else None
        self.clock = ImuClock(int(round(1e9 * v['imu_time_offset_s'])), estimator, _REPAIR_NS)
        # (long enough to re-pair the samples of the first seconds once the time offset is known)
        self.visual = RotationBuffer(self.max_pair_gap_ns, keep_ns=_REPAIR_NS + 1_000_000_000)
        #: IMU samples (t, accel, omega) and field samples (t, field), camera clock, waiting for
        #: the visual orientation at their stamps.
        self.pending: deque[tuple[Any, ...]] = deque()
        #: How far panorama/orientation's stamps trail the IMU's on arrival (camera and tracker
        #: latency): vision is lost only when it is this much later than visual_timeout_s.
        self.visual_lag = StreamLag()
        self._hard_iron_reported = False
        self._lag_reported = False
        self.stamp_guards = {k: StampGuard(reset_s) for k in ('visual', 'imu', 'mag', 'ahrs')}
        #: The last raw field and how many samples repeated it exactly (a driver publishing a
        #: slower magnetometer's last value at the IMU's rate): repeats are skipped in on_mag.
        self._last_raw_field: np.ndarray | None = None
        self.repeated_fields = 0
        self.last_visual_ns: int | None = None
        self.last_imu_ns: int | None = None
        self.last_backup_pub_ns: int | None = None
        self.first_ahrs_ns: int | None = None  # the first imu/data stamp (start-up hold)
        self.last_published_ns: int | None = None
        self.panorama_frame = 'panorama'
        self._last_was_identity = False  # the last visual frame was the identity (a first frame)
        self.published = 0

        self.pub_global = self.advertise(Imu, 'orientation/global', RELIABLE_QOS)
        self.pub_frame = self.advertise(TransformStamped, 'orientation/panorama_in_world', RELIABLE_QOS)
        self.tf = TfBroadcaster(self)
        self.tf_static = TfBroadcaster(self, static=True)
        self.mount_published = False
        if (self.publish_tf or self.publish_mount_tf) and not self.tf.available:
            self.get_logger().warning('publish_tf: tf2_msgs is not installed here; no TF is published')
        self.input_type = input_type
        # The streams are read as views of their CDR bytes (ros.cdr_views), not deserialised.
        self.subscribe(INPUT_TYPES[input_type], 'panorama/orientation', self.on_visual, RELIABLE_STREAM_QOS,
                       view=transform_stamped_view if input_type == 'transform' else None)
        self.subscribe(Imu, 'imu/data_raw', self.on_imu, STREAM_QOS, view=imu_view)
        self.subscribe(MagneticField, 'imu/mag', self.on_mag, STREAM_QOS, view=magnetic_field_view)
        self.subscribe(Imu, 'imu/data', self.on_ahrs, STREAM_QOS, view=imu_view)
        self._subscribe_tf_static()
        self.get_logger().info(f'hybrid_orientation_filter: panorama/orientation as {input_type}, imu/data_raw, imu/mag, imu/data')

    # -- extrinsics ------------------------------------------------------------------------

    def _subscribe_tf_static(self) -> None:
        """/tf_static where tf2_msgs exists; on the pip-only path without it the graph runner
        hands the bag's static transforms to :meth:`on_static_transforms`."""
        subscribe_static_transforms(self, self.on_static_transforms)

    def on_static_transforms(self, transforms: list[Any]) -> None:
        """Static transforms (``parent``, ``child``, ``rotation`` rotating child vectors into
        the parent): take the IMU -> camera rotation from the one that names the camera frame."""
        cam = self.camera_frame.lstrip('/')
        for tf in transforms:
            parent, child = str(tf.parent).lstrip('/'), str(tf.child).lstrip('/')
            R = np.asarray(tf.rotation, dtype=float)
            if child == cam and parent != cam:
                R_imu_cam = R
            elif parent == cam and child != cam:
                R_imu_cam = R.T
            else:
                continue
            diff = float(np.linalg.norm(so3_log(self.R_imu_cam_param.T @ R_imu_cam)))
            if diff > _EXTRINSIC_WARN_RAD:
                self.get_logger().warning(
                    f'/tf_static {parent} -> {child} differs from imu_to_camera_quat_xyzw by '
                    f'{np.degrees(diff):.1f} deg: using /tf_static')
            self.R_imu_cam = R_imu_cam
            self.backup.R_imu_cam = R_imu_cam
            if self.distortion is not None:
                self.distortion.R_imu_cam = R_imu_cam
            if self.clock.estimator is not None:
                self.clock.estimator.R_imu_cam = R_imu_cam
            self.extrinsic_source = f'/tf_static {parent} -> {child}'
            return

    # -- TF and live parameters ------------------------------------------------------------

    def _publish_mount(self, t_ns: int) -> None:
        """The IMU mount on /tf_static, once, when it comes from the parameter."""
        if self.mount_published or not self.publish_mount_tf or self.extrinsic_source != 'parameter':
            return
        self.mount_published = True
        self.tf_static.send(transform_stamped(t_ns, self.imu_frame, self.camera_frame, self.R_imu_cam))

    def _set_imu_frame(self, value: str) -> None:
        self.imu_frame = value
        self.mount_published = False  # published again under the new name

    def _set_publish_mount_tf(self, value: bool) -> None:
        self.publish_mount_tf = value
        self.mount_published = False

    def _set_reset_after(self, value: float) -> None:
        for guard in self.stamp_guards.values():
            guard.reset_after_ns = int(value * 1e9)

    # -- helpers ---------------------------------------------------------------------------

    def _reset(self, why: str) -> None:
        self.get_logger().warning(f'{why}: starting over')
        self.align.reset()
        self.backup.reset()
        if self.distortion is not None:
            self.distortion.reset()
        self.clock.restart()  # its stamps start over; the offset applied so far is kept
        self.visual.clear()
        self.pending.clear()
        self.visual_lag.clear()
        for guard in self.stamp_guards.values():
            guard.reset()
        self.last_visual_ns = self.last_imu_ns = self.last_backup_pub_ns = self.last_published_ns = None
        self.first_ahrs_ns = None

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

    def _publish(self, t_ns: int, R_enu_cam: np.ndarray, cov: np.ndarray, R_enu_pano: np.ndarray | None) -> None:
        """orientation/global (and orientation/panorama_in_world), never with NaN."""
        if not (np.all(np.isfinite(R_enu_cam)) and np.all(np.isfinite(cov))):
            self.warn_throttled('estimate is not finite; not published')
            return
        if self.last_published_ns is not None and t_ns <= self.last_published_ns:
            return  # one output per stamp, in stamp order (a gyro sample and a frame may share one)
        self.last_published_ns = t_ns
        # As CDR bytes (ros.cdr_views): the Imu that set_quaternion / set_covariance would fill
        # (rates and accelerations zero, their covariances unknown: -1), without building it.
        sec, nanosec = divmod(int(t_ns), 1_000_000_000)
        self.pub_global.publish(orientation_imu_cdr(sec, nanosec, self.camera_frame, R_enu_cam, 0.5 * (cov + cov.T)))
        self.published += 1
        if self.publish_tf:
            if self.tf.listened:
                self.tf.send(transform_stamped(t_ns, self.world_frame, self.camera_frame, R_enu_cam))
            self._publish_mount(t_ns)
        if R_enu_pano is not None:
            self.pub_frame.publish(rotation_transform_cdr(sec, nanosec, self.world_frame, self.panorama_frame, R_enu_pano))

    def _resolve(self) -> None:
        """Feed pending IMU and field samples to the alignment, each with the visual orientation
        at its own stamp."""
        newest_visual = self.visual.newest_ns
        wait_ns = self._visual_wait_ns()
        while self.pending:
            entry = self.pending[0]
            t_s = entry[0]
            if newest_visual is None or newest_visual < t_s:
                # Wait for a visual sample at or after t_s, unless vision is lost by now.
                if self.last_imu_ns is not None and self.last_imu_ns - t_s > wait_ns:
                    self.pending.popleft()
                    continue
                break
            self.pending.popleft()
            R_pano_cam = self.visual.at(t_s)
            if R_pano_cam is None:  # before the buffer, or across a lost stretch
                continue
            if len(entry) == 2:
                self.align.add_field(t_s, R_pano_cam @ self.R_imu_cam.T, entry[1])
            else:
                self.align.add(t_s, R_pano_cam @ self.R_imu_cam.T, entry[1], None, entry[2])

    def _visual_wait_ns(self) -> int:
        """How far the IMU's stamps may run ahead of the newest visual stamp before the tracker
        counts as lost: visual_timeout_s plus the visual stream's usual lag (before the first
        frame has arrived, the pre-vision buffer's span)."""
        return self.visual_timeout_ns + (self.visual_lag.ns if self.visual_lag.known else _PRE_VISION_NS)

    # -- callbacks -------------------------------------------------------------------------

    def on_visual(self, msg: Any) -> None:
        """One relative orientation R_ref_cam: publish eq. 1 with the current R_PN."""
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
        R_raw = R_pano_cam
        # A tracker publishes the first frame of a new panorama (or map) as the identity; any
        # later frame is never exactly it. So a restart is known even when the camera happens
        # to look where the old panorama started (no jump to see). (A tracker that repeats the
        # identity until it moves restarts only once.)
        identity = bool(np.array_equal(R_raw, _IDENTITY))
        first_of_new = self.last_visual_ns is not None and identity and not self._last_was_identity
        self._last_was_identity = identity
        if self.distortion is not None and first_of_new:
            self.distortion.reset()  # a new panorama has its own (from its next frame: its up is not known yet)
        elif self.distortion is not None:
            # Learnt from the raw orientation; everything below but the time offset's estimate
            # (the gyro against the raw tracker: corrected, the two would chase each other) uses
            # the corrected one.
            up = self.align.up_in_panorama()
            self.distortion.add_visual(t_v, R_raw, up)
            R_pano_cam = self.distortion.correct(R_raw, up)
        returning = self.last_visual_ns is not None and t_v - self.last_visual_ns > self.visual_timeout_ns
        # The placement before this frame's IMU samples join it: read only when vision returns
        # (the estimate below, after _resolve, is the one published; estimate() computes only
        # when samples were added since its last call, so each state is solved once).
        # The backup at the frame's stamp: the gyro runs ahead of it by the camera's latency.
        R_backup = self.backup.at(t_v) if returning or first_of_new else None
        estimate = self.align.estimate() if R_backup is not None else None
        if estimate is not None and R_backup is not None:
            R_vis = estimate.R_pano_enu.T @ R_pano_cam
            jump = float(np.linalg.norm(so3_log(R_backup.T @ R_vis)))
            if first_of_new or jump > self.reseed_rad:
                # A new visual reference frame (tracker restarted): carry the orientation over
                # from the gyro backup as a prior of a new panorama-in-world estimate.
                self.get_logger().warning(
                    ('the first frame of a new panorama' if first_of_new else
                     f'vision returned {np.degrees(jump):.1f} deg away from the gyro backup: a new panorama frame')
                    + ', placed in the world from the backup')
                R_pe = R_pano_cam @ R_backup.T
                sigma = float(np.sqrt(max(np.trace(self.backup.cov) / 3.0, 1e-8)))
                # The old panorama's windows turned into the new frame (hard iron, field
                # clusters and gravity keep their history), weighted as the backup is known.
                self.align.reanchor(R_pe @ estimate.R_pano_enu.T, sigma)
                self.pending.clear()
                if self.distortion is not None and not first_of_new:  # (a first frame reset it above)
                    self.distortion.reset()  # a new panorama has its own distortion
            self.visual.clear()
            self.backup.visual.clear()
            self.clock.forget_kept()
        self.last_visual_ns = t_v
        if self.last_imu_ns is not None:
            self.visual_lag.add(self.last_imu_ns, t_v)
            if not self._lag_reported and self.visual_lag.settled and self.visual_lag.ns >= _LAG_REPORT_NS:
                self._lag_reported = True
                self.get_logger().info(
                    f'panorama/orientation arrives {self.visual_lag.ns * 1e-6:.0f} ms behind the IMU samples of its '
                    'time (camera and tracker latency): the tracker counts as lost only visual_timeout_s beyond that')
        self.visual.add(t_v, R_pano_cam)
        self.backup.add_visual(t_v, R_pano_cam)
        self.clock.add_visual(t_v, R_raw)
        self._resolve()
        estimate = self.align.estimate()
        if estimate is None:
            self.warn_throttled('waiting for imu/data_raw and imu/mag to place the panorama in the world')
            return
        R_enu_pano = estimate.R_pano_enu.T
        R_enu_cam = R_enu_pano @ R_pano_cam
        cov = estimate.covariance_enu + np.eye(3) * self.visual_noise_rad ** 2
        self.backup.anchor(t_v, R_enu_cam, cov)
        self._publish(t_v, R_enu_cam, cov, R_enu_pano)
        if not self._hard_iron_reported:
            self._report_hard_iron(estimate)

    def _report_hard_iron(self, estimate: WorldAlignmentEstimate) -> None:
        """Tell the user once when the magnetometer's calibration leaves a large hard iron: the
        field fit finds it against the panorama's rotations, but every session starts with it
        (the heading is off by it until the phone has turned) - the corrected offset fixes that,
        on the axes the rotations reveal."""
        if np.linalg.norm(estimate.hard_iron) < _HARD_IRON_REPORT or \
                estimate.covariance_enu[2, 2] > _HARD_IRON_REPORT_SIGMA_RAD ** 2:
            return
        self._hard_iron_reported = True
        h_t = estimate.hard_iron * estimate.field_scale  # in the field's unit (tesla by REP 145)
        size = f'{np.linalg.norm(h_t) * 1e6:.1f} uT' if 1e-5 < estimate.field_scale < 1e-4 else \
            f'{np.linalg.norm(h_t):.3g} (the field\'s unit; MagneticField is tesla)'
        cal = self.calibration
        offset = cal.hard_iron_offset + np.linalg.solve(cal.soft_iron_matrix, h_t)
        self.get_logger().warning(
            f'imu/mag: the calibration leaves {size} of hard iron (found against '
            'the panorama\'s rotations; each session starts off by it until the phone turns): '
            f'hard_iron_offset: [{", ".join(f"{x:.3e}" for x in offset)}] would remove what the rotations showed '
            '(the axis the phone turned about keeps its calibration)')

    def on_mag(self, msg: MagneticField) -> None:
        """A field sample: calibrated, to the alignment with the visual orientation at its own
        stamp (a magnetometer has its own rate and stamps; pairing it with the IMU sample next to
        it mis-pairs it by up to a sample period). A sample that repeats the previous raw value
        exactly is a driver republishing a slower magnetometer's last reading at the IMU's rate
        (sensor noise makes a genuine repeat of all three axes rare): it is skipped, since
        counted it would multiply the field windows' sample count and lag the turn."""
        try:
            raw = finite_vector3(msg.magnetic_field, 'imu/mag field')
        except ConversionError as exc:
            self.warn_throttled(f'{exc}, message dropped')
            return
        t_m = stamp_ns(msg.header)
        if not self._stamp_ok('mag', t_m, 'imu/mag'):
            return
        if self._last_raw_field is not None and np.array_equal(raw, self._last_raw_field):
            self.repeated_fields += 1
            if self.repeated_fields == 1:
                self.get_logger().info(
                    'imu/mag repeats its previous value (a magnetometer slower than its topic): '
                    'a repeat is no new measurement and is skipped')
            return
        self._last_raw_field = raw
        field = self.calibration.mag(raw)
        if float(field @ field) <= 0.0:
            self.warn_throttled('imu/mag field has zero norm, message dropped')
            return
        # Kept from the start: the first frame may arrive after samples of its own time.
        self.clock.keep((t_m, field))
        self.pending.append((t_m - self.clock.offset_ns, field))
        self._resolve()

    def on_imu(self, msg: Imu) -> None:
        """Gyro + accelerometer sample: to the alignment (paired with vision by stamp) and the
        gyro backup; while vision is lost, publish the backup."""
        try:
            accel, omega = imu_sample(msg)
        except ConversionError as exc:
            self.warn_throttled(f'{exc}, message dropped')
            return
        t_imu = stamp_ns(msg.header)
        if not self._stamp_ok('imu', t_imu, 'imu/data_raw'):
            return
        sample = (t_imu, self.calibration.accel(accel), self.calibration.gyro(omega))
        if self.clock.add(sample, sample[2]):
            self._offset_settled(self.clock.take_kept())
        if self.last_visual_ns is None:  # before vision only the last _PRE_VISION_NS are kept
            self.clock.trim_kept(t_imu - _PRE_VISION_NS)
        t_g = t_imu - self.clock.offset_ns  # in the camera's clock from here on
        self.last_imu_ns = t_g
        self.backup.add_gyro(t_g, sample[2], sample[1])
        if self.distortion is not None:
            self.distortion.add_gyro(t_g, sample[2])
        self.pending.append((t_g, *sample[1:]))
        self._resolve()
        if self.last_visual_ns is None or self.backup.R_enu_cam is None or not self.align.ready:
            return
        lost_for = t_g - self.last_visual_ns - self.visual_lag.ns
        if lost_for <= self.visual_timeout_ns:
            if self.gyro_rate_output and t_g > self.last_visual_ns:
                self._publish(t_g, self.backup.R_enu_cam, self.backup.cov, None)
            return
        if lost_for > self.max_backup_ns:
            return  # imu/data (the AHRS) takes over in on_ahrs
        if self.last_backup_pub_ns is not None and t_g - self.last_backup_pub_ns < self.backup_period_ns:
            return
        self.warn_throttled('visual tracker lost: publishing the gyro backup')
        self.last_backup_pub_ns = t_g
        self._publish(t_g, self.backup.R_enu_cam, self.backup.cov, None)

    def _offset_settled(self, kept: list[tuple[Any, ...]] | None) -> None:
        """The time offset is known: rebuild the alignment from the samples so far (when they
        are all still there), paired with the visual orientation at their corrected stamps; the
        gyro backup's chain starts over in the new clock; say so."""
        if kept is not None:
            self.align.reset()
            self.pending = deque((t - self.clock.offset_ns, *rest) for t, *rest in kept)
            self._resolve()
        self.backup.chain.clear()
        est = self.clock.estimator.estimate() if self.clock.estimator is not None else None
        self.get_logger().info(
            f'camera-IMU time offset {self.clock.offset_ns * 1e-6:.1f} +- {0.0 if est is None else est[1] * 1e3:.1f} ms '
            '(IMU stamps minus camera stamps, from the gyro against the visual rotation): IMU samples are paired with it')

    def on_ahrs(self, msg: Imu) -> None:
        """imu/data (the AHRS): without a camera (none yet, or lost beyond max_backup_s) the
        output is the AHRS orientation turned into the camera frame."""
        t_s = stamp_ns(msg.header)
        if self.last_visual_ns is not None and t_s - self.last_visual_ns <= max(self.visual_timeout_ns, self.max_backup_ns):
            return
        if covariance_is_known(msg.orientation_covariance):
            cov = np.asarray(msg.orientation_covariance, dtype=float).reshape(3, 3)
            if not np.all(np.isfinite(cov)) or np.any(np.diag(cov) < 0):
                self.warn_throttled('imu/data orientation covariance is not finite or negative, message dropped')
                return
        else:
            cov = np.eye(3) * np.pi ** 2  # REP-145 unknown
        try:
            R_enu_imu = rotation_from_quaternion(msg.orientation, 'imu/data orientation')
        except ConversionError as exc:
            self.warn_throttled(f'{exc}, message dropped')
            return
        if not self._stamp_ok('ahrs', t_s, 'imu/data'):
            return
        if self.last_visual_ns is None:
            # At start-up a camera's first frame may still be on its way (frames arrive behind the
            # IMU by the pipeline's latency): imu/data is followed once visual_timeout_s of it has
            # passed without one, so that a camera graph does not start on the AHRS and jump.
            if self.first_ahrs_ns is None:
                self.first_ahrs_ns = t_s
            if t_s - self.first_ahrs_ns < self.visual_timeout_ns:
                return
        frame = msg.header.frame_id.lstrip('/')
        R_enu_cam = R_enu_imu if frame == self.camera_frame else R_enu_imu @ self.R_imu_cam
        self._publish(t_s, R_enu_cam, cov, None)


def main(args: list[str] | None = None) -> int:
    return run_node(HybridOrientationFilterNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
