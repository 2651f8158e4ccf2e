"""The parameters of hybrid_orientation_filter (nodes/hybrid_orientation_filter.py), with their
defaults from the cores' configurations (``WorldAlignmentConfig``, ``GyroBackupConfig``,
``TimeOffsetConfig``) and the shared IMU calibration (``param_table.IMU_CALIBRATION_PARAMS``).

Kept apart from the node so that the node module stays about what it does with them.
"""
from __future__ import annotations

from ..core.hybrid_orientation import GyroBackupConfig
from ..core.panorama_azimuth import AzimuthDistortionConfig
from ..core.time_offset import TimeOffsetConfig
from ..core.world_alignment_config import WorldAlignmentConfig
from .param_table import IMU_CALIBRATION_PARAMS, ParamSpec, frame_name, unit_quaternion

_ALIGN = WorldAlignmentConfig()
_GYRO = GyroBackupConfig()
_AZIMUTH = AzimuthDistortionConfig()

#: The node's parameters (with the shared IMU calibration, param_table.IMU_CALIBRATION_PARAMS).
PARAMS = (
    ParamSpec('relative_input_type', 'transform',
              'Message type of panorama/orientation: transform (TransformStamped reference -> camera) or pose '
              '(PoseStamped, orientation of the camera in header.frame_id)',
              read_only=True, validate=lambda v: None if v in ('transform', 'pose') else 'must be transform or pose'),
    ParamSpec('imu_to_camera_quat_xyzw', [1.0, 0.0, 0.0, 0.0],
              'Rotation imu -> camera_optical (R_imu_cam, x y z w), used when no /tf_static gives it; default the '
              'phone: diag(1, -1, -1)', read_only=True, validate=unit_quaternion),
    ParamSpec('camera_frame_id', 'camera_optical',
              'frame_id of orientation/global (the camera; the TF child frame)', validate=frame_name),
    ParamSpec('world_frame_id', 'enu',
              'World frame of imu/data and of the outputs (ENU; the TF parent frame)', validate=frame_name),
    ParamSpec('imu_frame_id', 'imu',
              'IMU frame of the static mount transform published with publish_mount_tf', validate=frame_name),
    ParamSpec('publish_tf', True, 'Broadcast each orientation/global on /tf (world_frame_id -> camera_frame_id)'),
    ParamSpec('publish_mount_tf', True,
              'Publish the IMU mount (imu_frame_id -> camera_frame_id) on /tf_static while it comes from '
              'imu_to_camera_quat_xyzw (not when /tf_static gave it)'),
    *IMU_CALIBRATION_PARAMS,
    ParamSpec('accel_bias_sigma_m_s2', _ALIGN.accel_bias_sigma_m_s2,
              'Prior 1-sigma of the accelerometer bias left by the calibration, m/s^2 (tight: a loose bias absorbs '
              'scale errors)', min_value=1e-6, max_value=10.0),
    ParamSpec('hard_iron_sigma', _ALIGN.hard_iron_sigma,
              'Width of the field fit\'s ridge on the residual hard iron, relative to the field strength '
              '(looser than hard_iron_prior_sigma, so that the rotations move it)',
              min_value=1e-6, max_value=10.0),
    ParamSpec('soft_iron_sigma', _ALIGN.soft_iron_sigma,
              'Width of the field fit\'s ridge on the residual soft iron (entries of a symmetric '
              'correction, relative like hard_iron_sigma); 0 leaves it out of the model',
              min_value=0.0, max_value=1.0),
    ParamSpec('window_s', _ALIGN.window_s,
              'Window of the robust field fit, s (a disturbance is judged window by window)',
              min_value=0.01, max_value=60.0),
    ParamSpec('solve_period_s', _ALIGN.solve_period_s,
              'Re-solve the field fit this often (sample stamps), s', min_value=0.01, max_value=60.0),
    ParamSpec('solve_period_share', _ALIGN.solve_period_share,
              'Early in a session re-solve the field fit every this share of its span instead (at least every 0.1 s)',
              min_value=0.0, max_value=1.0),
    ParamSpec('hand_velocity_m_s', _ALIGN.hand_velocity_m_s,
              'Typical speed of the phone in the hand, m/s (tilt covariance: the velocity term of the gravity mean)',
              min_value=0.0, max_value=10.0),
    ParamSpec('hand_period_s', _ALIGN.hand_period_s,
              'Typical period of the hand\'s sway, s (tilt covariance: how much the gravity ramps average the '
              'hand\'s velocity down)', min_value=0.01, max_value=60.0),
    ParamSpec('hard_iron_prior_sigma', _ALIGN.hard_iron_prior_sigma,
              '1-sigma of the residual hard iron the calibration leaves, relative to the field strength '
              '(heading covariance before the phone has turned)', min_value=1e-6, max_value=10.0),
    ParamSpec('soft_iron_prior_sigma', _ALIGN.soft_iron_prior_sigma,
              '1-sigma of the residual soft iron\'s entries the calibration leaves (heading covariance)',
              min_value=0.0, max_value=1.0),
    ParamSpec('correlation_s', _ALIGN.correlation_s,
              'Correlation time of field disturbances and hand motion, s (how many samples a prior carried '
              'into a new panorama is worth)', min_value=0.05, max_value=60.0),
    ParamSpec('lever_arm_sigma_m', _ALIGN.lever_arm_sigma_m,
              'Prior 1-sigma of the lever arm (the IMU from the centre the user turns about), m; 0: no lever-arm '
              'model', min_value=0.0, max_value=10.0),
    ParamSpec('cauchy_scale', _ALIGN.cauchy_scale,
              'Cauchy scale of the window weights, in robust sigmas', min_value=0.5, max_value=100.0),
    ParamSpec('tilt_floor_rad', _ALIGN.tilt_floor_rad,
              'Floor of the reported tilt 1-sigma, rad', min_value=0.0, max_value=1.0),
    ParamSpec('heading_floor_rad', _ALIGN.heading_floor_rad,
              'Floor of the reported heading 1-sigma, rad', min_value=0.0, max_value=1.0),
    ParamSpec('declination_rad', 0.0,
              'Magnetic declination, rad, positive when magnetic north is east of true north (as imu_magnetometer)',
              min_value=-3.1416, max_value=3.1416),
    ParamSpec('gyro_noise_rad_s', _GYRO.gyro_noise_rad_s,
              'Gyro rate noise, 1-sigma per sample, rad/s', min_value=0.0, max_value=10.0),
    ParamSpec('gyro_bias_sigma_rad_s', _GYRO.bias_sigma_rad_s,
              'Residual gyro bias after learning, 1-sigma rad/s (backup covariance)', min_value=0.0, max_value=10.0),
    ParamSpec('gyro_bias_window_s', _GYRO.bias_window_s,
              'Interval over which gyro and visual rotations are compared to learn the bias, s',
              min_value=0.05, max_value=10.0),
    ParamSpec('gyro_bias_gain', _GYRO.bias_gain,
              'Weight of one comparison in the running gyro bias (0: no learning)', min_value=0.0, max_value=1.0),
    ParamSpec('backup_tilt_tau_s', _GYRO.tilt_tau_s,
              'Time constant of the accelerometer pulling the gyro backup\'s tilt towards the measured up '
              'while vision is lost, s (0: gyro only)', min_value=0.0, max_value=1000.0),
    ParamSpec('visual_noise_rad', 0.001, 'Noise of the visual orientation, 1-sigma rad', min_value=0.0, max_value=1.0),
    ParamSpec('max_mag_age_s', 0.1,
              'Not used here (each field sample is paired with the visual orientation at its own stamp); kept so '
              'that a params file shared with imu_magnetometer loads', min_value=0.0, max_value=10.0),
    ParamSpec('max_pair_gap_s', 0.2,
              'Largest gap between two visual orientations that is interpolated across, s',
              min_value=0.0, max_value=10.0),
    ParamSpec('visual_timeout_s', 0.2,
              'No visual orientation for this long (in stamps) beyond the visual stream\'s usual lag behind the IMU '
              '(camera and tracker latency, measured): the tracker is lost, the gyro backup publishes; at start-up '
              'imu/data is followed after this long without a frame',
              min_value=0.0, max_value=60.0),
    ParamSpec('backup_rate_hz', 30.0,
              'Rate of orientation/global from the gyro backup, Hz', min_value=0.1, max_value=1000.0),
    ParamSpec('max_backup_s', 30.0,
              'After this long without vision the gyro backup stops and imu/data (the AHRS) is followed, s',
              min_value=0.0, max_value=3600.0),
    ParamSpec('gyro_rate_output', False,
              'Also publish at every gyro sample between camera frames (the last frame carried forward by the gyro)'),
    ParamSpec('reseed_threshold_rad', 0.1,
              'When vision returns this far from the gyro backup, its frame changed: restart the panorama-in-world '
              'estimate from the backup, rad', min_value=0.0, max_value=3.2),
    ParamSpec('imu_time_offset_s', 0.0,
              'Known camera-IMU time offset: the IMU stamp minus the camera stamp of the same instant, s '
              '(estimate_time_offset refines it)', read_only=True, min_value=-1.0, max_value=1.0),
    ParamSpec('estimate_time_offset', True,
              'Estimate the camera-IMU time offset from the gyro against the visual rotation (core/time_offset.py) '
              'and shift the IMU stamps by it once it is known to 1.5 ms', read_only=True),
    ParamSpec('max_time_offset_s', TimeOffsetConfig().max_offset_s,
              'The estimated offset is searched within +- this of imu_time_offset_s, s', read_only=True,
              min_value=0.005, max_value=1.0),
    ParamSpec('learn_panorama_distortion', True,
              'Learn the panorama\'s azimuth distortion from the gyro and remove it (core/panorama_azimuth.py: a '
              'camera turned about the user rather than about itself stretches the panorama by the near scene\'s '
              'parallax)', read_only=True),
    ParamSpec('distortion_knots', _AZIMUTH.knots,
              'Azimuths of the piecewise-linear panorama distortion over a full turn', read_only=True,
              min_value=4, max_value=720),
    ParamSpec('distortion_pair_s', _AZIMUTH.pair_s,
              'Time between the two frames whose panorama and gyro turns are compared, s', read_only=True,
              min_value=0.05, max_value=0.8),
    ParamSpec('distortion_smoothness_rad', _AZIMUTH.smoothness_rad,
              '1-sigma of the distortion\'s second difference between neighbouring knots, rad', read_only=True,
              min_value=1e-5, max_value=10.0),
    ParamSpec('gyro_scale_sigma', _AZIMUTH.scale_sigma,
              'Prior 1-sigma of the gyro\'s scale error (told from the panorama\'s stretch once a turn closes); '
              '0: taken as exact', read_only=True, min_value=0.0, max_value=0.1),
    ParamSpec('reset_after_s', 1.0,
              'A stamp this much older than the previous one means the clock jumped back (bag loop): reset',
              min_value=0.0, max_value=3600.0),
)
