"""imu_magnetometer: the sensor-only orientation of the IMU, a drop-in for imu_filter_madgwick.

Live mode (default): subscribes ``imu/data_raw`` (sensor_msgs/Imu) and ``imu/mag``
(sensor_msgs/MagneticField) from a driver and publishes ``imu/data``: the orientation of the IMU
body in the world frame with its covariance (REP-145), and the calibrated rates and
accelerations - the same topics and the parameters users already set for imu_filter_madgwick
(``use_mag``, ``world_frame``, ``publish_tf``, ``fixed_frame``, ``declination``, ``mag_bias_*``,
``orientation_stddev``, ``constant_dt``).

Two methods (parameter ``method``):

* ``vqf`` (default): a gyro-aided AHRS (:mod:`ar_tracking.core.ahrs`, VQF with rest and
  magnetic-disturbance handling); without a magnetometer (``use_mag: false``, or none within
  ``max_mag_age_s``) it runs 6D and the heading covariance grows.
* ``compass``: the per-sample tilt-compass of Langlotz 2011 eq. 3-4
  (:mod:`ar_tracking.core.imu_orientation`), the paper's sensor-only baseline of Fig. 8.

Each IMU sample is processed with the newest field sample that is at most ``max_mag_age_s``
from it, as soon as the field sample of its stamp has come or the next IMU sample has: at most
one sample is ever held, so a magnetometer that returns after a dropout releases no burst
downstream.

Replay mode (parameter ``bag_path``): reads those topics from a bag itself and also publishes the
calibrated ``imu/data_raw`` and ``imu/mag``.

Live parameters (``ros2 param set`` applies them from the next sample on): ``declination_rad``
and ``declination``, ``world_frame``, ``frame_id``, ``fixed_frame``, ``publish_tf``,
``max_mag_age_s``, ``reset_after_s``; the others are read-only (the filter is built from them).
"""
from __future__ import annotations

from typing import Any

import numpy as np
from sensor_msgs.msg import Imu, MagneticField

from ..core.ahrs import Ahrs, AhrsConfig, AhrsError
from ..core.imu_orientation import FieldModel, GravityFieldOrientation
from ..core.rotations import rot_z
from ..io.replay import ReplayOptions, ScheduledMessage
from ..ros.cdr_views import header_message, imu_view, magnetic_field_view, orientation_imu_cdr
from ..ros.conversions import (
    ConversionError,
    finite_vector3,
    imu_sample,
    set_vector3,
    stamp_ns,
)
from ..ros.frames import WORLD_FROM_ENU, check_world_frame
from ..ros.node_base import RELIABLE_QOS, STREAM_QOS, TrackingNode, run_node
from ..ros.param_table import IMU_CALIBRATION_PARAMS, ParamSpec, declare_params, imu_calibration
from ..ros.stamp_guard import StampGuard, StampVerdict
from ..ros.tf import TfBroadcaster, transform_stamped

METHODS = ('vqf', 'compass')
_AHRS = AhrsConfig()

#: The node's parameters (with the shared IMU calibration, param_table.IMU_CALIBRATION_PARAMS).
PARAMS = (
    ParamSpec('method', 'vqf',
              'Orientation method: vqf (gyro-aided AHRS with rest and magnetic-disturbance handling) or compass '
              "(per-sample tilt-compass, Langlotz eq. 3-4, the paper's sensor-only baseline)",
              read_only=True, choices=METHODS),
    *(ParamSpec(f'mag_bias_{axis}', 0.0,
                f'imu_filter_madgwick name: field bias along {axis}, tesla (added to hard_iron_offset)',
                min_value=-1e-3, max_value=1e-3) for axis in 'xyz'),
    *IMU_CALIBRATION_PARAMS,
    ParamSpec('declination_rad', 0.0,
              'Magnetic declination, rad, positive when magnetic north is east of true north',
              min_value=-3.1416, max_value=3.1416),
    ParamSpec('declination', 0.0,
              'imu_filter_madgwick name of the declination, rad (added to declination_rad)',
              min_value=-3.1416, max_value=3.1416),
    ParamSpec('gravity_m_s2', 9.80665, 'Local gravity, m/s^2', min_value=9.7, max_value=9.9),
    ParamSpec('expected_field_t', 0.0,
              'Local magnetic field strength, tesla (0: learn it online; compass method)',
              min_value=0.0, max_value=1e-4),
    ParamSpec('expected_dip_rad', 0.0,
              'Local inclination of the field, rad, positive down (compass method, used when expected_field_t > 0)',
              min_value=-1.5708, max_value=1.5708),
    ParamSpec('accel_noise_m_s2', 0.05,
              'Accelerometer white noise, 1-sigma per axis, m/s^2 (compass covariance floor)',
              min_value=1e-6, max_value=10.0),
    ParamSpec('mag_noise_t', 3e-7,
              'Magnetometer white noise, 1-sigma per axis, tesla (compass covariance floor)',
              min_value=1e-12, max_value=1e-4),
    ParamSpec('use_mag', True,
              'Use the magnetometer for heading (false: 6D, heading from the gyro only, arbitrary origin)',
              read_only=True),
    ParamSpec('max_mag_age_s', 0.1,
              'Oldest field sample (stamp difference to the IMU sample) still used; older: 6D update',
              min_value=0.0, max_value=10.0),
    ParamSpec('constant_dt', 0.0,
              'IMU sample period, s (imu_filter_madgwick name; 0: measured from the stamps)',
              min_value=0.0, max_value=1.0, read_only=True),
    ParamSpec('tau_acc_s', _AHRS.tau_acc_s,
              'VQF accelerometer time constant, s (larger: less tilt from hand acceleration, slower)',
              min_value=0.05, max_value=100.0, read_only=True),
    ParamSpec('tau_mag_s', _AHRS.tau_mag_s,
              'VQF magnetometer time constant, s', min_value=0.05, max_value=1000.0, read_only=True),
    ParamSpec('mag_disturbance_rejection', True,
              'VQF magnetic disturbance rejection (field norm/dip against a learnt reference)', read_only=True),
    ParamSpec('gyro_bias_estimation', True, 'VQF gyro bias estimation at rest and in motion', read_only=True),
    ParamSpec('orientation_stddev', 0.0,
              'Constant orientation 1-sigma, rad (imu_filter_madgwick name; 0: the covariance model)',
              min_value=0.0, max_value=3.2),
    ParamSpec('world_frame', 'enu',
              'World frame of the published orientation: enu, ned or nwu', validate=check_world_frame),
    ParamSpec('frame_id', '', 'Body frame id of the output (empty: the input frame_id)'),
    ParamSpec('publish_tf', False,
              'Also publish the orientation on /tf (fixed_frame -> body frame), like imu_filter_madgwick'),
    ParamSpec('fixed_frame', '', 'Parent frame of the published TF (empty: the world_frame name)'),
    ParamSpec('reset_after_s', 1.0,
              'A stamp this much older than the previous one means the clock jumped back (bag loop): reset',
              min_value=0.0, max_value=3600.0),
    ParamSpec('bag_path', '',
              'Replay mode: read imu/data_raw and imu/mag from this bag instead of subscribing', read_only=True),
    ParamSpec('rate', 1.0,
              'Replay mode: playback rate factor (0: as fast as possible)',
              min_value=0.0, max_value=1000.0, read_only=True),
    ParamSpec('loop', False, 'Replay mode: play the bag again when it ends', read_only=True),
)



class _Sample:
    """A calibrated IMU sample: what imu/data carries besides the orientation (header fields,
    calibrated rate and specific force, their covariances)."""

    __slots__ = ('sec', 'nanosec', 'frame_id', 'gyro', 'accel', 'gyro_cov', 'accel_cov')

    def __init__(self, sec: int, nanosec: int, frame_id: str, gyro: np.ndarray, accel: np.ndarray,
                 gyro_cov: Any, accel_cov: Any) -> None:
        self.sec, self.nanosec, self.frame_id = sec, nanosec, frame_id
        self.gyro, self.accel, self.gyro_cov, self.accel_cov = gyro, accel, gyro_cov, accel_cov

    def cdr(self, R: np.ndarray | None, cov: np.ndarray | None) -> bytes:
        """The sample as an Imu's CDR bytes with the orientation R and its covariance (None,
        None: no orientation, the replay's calibrated imu/data_raw): the bytes of the message
        set_quaternion / set_covariance / set_vector3 would fill (ros.cdr_views)."""
        return orientation_imu_cdr(self.sec, self.nanosec, self.frame_id, R, cov,
                                   self.gyro, self.gyro_cov, self.accel, self.accel_cov)


class ImuMagnetometerNode(TrackingNode):
    INPUTS = {'imu/data_raw': 'sensor_msgs/msg/Imu', 'imu/mag': 'sensor_msgs/msg/MagneticField'}
    #: The magnetometer is optional (6D without it).
    REQUIRED_INPUTS = ['imu/data_raw']
    OUTPUTS = {'imu/data': 'sensor_msgs/msg/Imu'}

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('imu_magnetometer', **kwargs)
        v = declare_params(self, PARAMS, live={
            'declination_rad': lambda x: self._set_declination('declination_rad', x),
            'declination': lambda x: self._set_declination('declination', x),
            'max_mag_age_s': lambda x: setattr(self, 'max_mag_age_ns', int(1e9 * x)),
            'world_frame': self._set_world_frame,
            'frame_id': lambda x: setattr(self, 'frame_id', x),
            'publish_tf': lambda x: setattr(self, 'publish_tf', x),
            'fixed_frame': lambda x: setattr(self, 'fixed_frame_param', x),
            'reset_after_s': self._set_reset_after,
        })
        self.method: str = v['method']
        calibration = imu_calibration(v, extra_hard_iron=[v[f'mag_bias_{axis}'] for axis in 'xyz'])
        self._declination_parts = {'declination_rad': v['declination_rad'], 'declination': v['declination']}
        declination = sum(self._declination_parts.values())
        #: The filter is built with the starting declination; a live change turns its output
        #: about the vertical by the difference (the cores apply the declination the same way).
        self.declination_start_rad = declination
        self.R_declination_change = np.eye(3)
        model = FieldModel(
            gravity_m_s2=v['gravity_m_s2'],
            field_t=v['expected_field_t'],
            dip_rad=v['expected_dip_rad'],
            declination_rad=declination,
            accel_noise_m_s2=v['accel_noise_m_s2'],
            mag_noise_t=v['mag_noise_t'],
        )
        self.use_mag: bool = v['use_mag']
        self.max_mag_age_ns = int(1e9 * v['max_mag_age_s'])
        try:
            config = AhrsConfig(
                sample_period_s=v['constant_dt'],
                use_mag=self.use_mag,
                max_mag_age_s=self.max_mag_age_ns * 1e-9,
                tau_acc_s=v['tau_acc_s'],
                tau_mag_s=v['tau_mag_s'],
                mag_disturbance_rejection=v['mag_disturbance_rejection'],
                bias_estimation=v['gyro_bias_estimation'],
                declination_rad=declination,
                gravity_m_s2=model.gravity_m_s2,
                constant_sigma_rad=v['orientation_stddev'],
            )
        except AhrsError as exc:
            raise ValueError(str(exc)) from exc
        self.world_frame: str = v['world_frame']
        self.frame_id: str = v['frame_id']
        self.publish_tf: bool = v['publish_tf']
        self.fixed_frame_param: str = v['fixed_frame']
        reset_s = v['reset_after_s']
        bag_path: str = v['bag_path']
        rate = v['rate']
        loop = v['loop']

        self.calibration = calibration
        self.ahrs = Ahrs(config, calibration) if self.method == 'vqf' else None
        self.compass = GravityFieldOrientation(calibration, model) if self.method == 'compass' else None
        self.R_world_enu = WORLD_FROM_ENU[self.world_frame]
        self.imu_guard = StampGuard(reset_s)
        self.mag_guard = StampGuard(reset_s)
        self.mag_raw: np.ndarray | None = None
        self.mag_ns: int | None = None
        self.held: tuple[int, np.ndarray, np.ndarray, _Sample] | None = None
        self.published = 0

        self.pub_data = self.advertise(Imu, 'imu/data', RELIABLE_QOS)
        self.tf = TfBroadcaster(self)
        if self.publish_tf and not self.tf.available:
            self.get_logger().warning('publish_tf: tf2_msgs is not installed here; no TF is published')
        self.player = None
        if bag_path:
            self.pub_raw = self.advertise(Imu, 'imu/data_raw', RELIABLE_QOS)
            self.pub_mag = self.advertise(MagneticField, 'imu/mag', RELIABLE_QOS)
            self._start_replay(bag_path, ReplayOptions(rate=rate, loop=loop, topics=[]))
        else:
            # read as views of their CDR bytes (ros.cdr_views), not deserialised
            self.subscribe(Imu, 'imu/data_raw', self.on_imu, STREAM_QOS, view=imu_view)
            self.subscribe(MagneticField, 'imu/mag', self._take_mag, STREAM_QOS, view=magnetic_field_view)
        self.get_logger().info(
            f'imu_magnetometer ({self.method}{"" if self.use_mag else ", 6D"}): '
            f'{"replaying " + bag_path if bag_path else "listening on imu/data_raw, imu/mag"}'
            f', world frame {self.world_frame}'
        )

    # -- replay mode -----------------------------------------------------------------------

    def _start_replay(self, path: str, options: ReplayOptions) -> None:
        from ..io.bags import BagError, BagReader
        from ..ros.player import BagPlayer, decode

        try:
            with BagReader(path) as bag:
                topics = bag.topics
        except BagError as exc:
            raise ValueError(str(exc)) from exc
        wanted = [t for t in ('/imu/data_raw', '/imu/mag') if t in topics]
        if not wanted:
            raise ValueError(f'{path}: no /imu/data_raw or /imu/mag topic in the bag')
        options.topics = wanted

        def on_message(item: ScheduledMessage) -> None:
            msg = decode(item.message.rawdata, item.message.msgtype)
            if item.message.topic == '/imu/mag':
                out = self.on_mag(msg)
                if out is not None:
                    self.pub_mag.publish(out)
            else:
                out = self.on_imu(msg)
                if out is not None:
                    self.pub_raw.publish(out)

        def on_done(error: str | None) -> None:
            if error:
                self.get_logger().error(error)
            else:
                self.get_logger().info(f'replay of {path} finished ({self.published} orientations)')

        self.player = BagPlayer(path, options, on_message, on_done)
        self.player.start()

    def close(self) -> None:
        if self.player is not None:
            self.player.stop()

    # -- live parameters -------------------------------------------------------------------

    @property
    def fixed_frame(self) -> str:
        return self.fixed_frame_param or self.world_frame

    def _set_declination(self, name: str, value: float) -> None:
        self._declination_parts[name] = float(value)
        if not self.use_mag:
            return  # 6D: the heading has no north to turn
        self.R_declination_change = rot_z(-(sum(self._declination_parts.values()) - self.declination_start_rad))

    def _set_world_frame(self, value: str) -> None:
        self.world_frame = value
        self.R_world_enu = WORLD_FROM_ENU[value]

    def _set_reset_after(self, value: float) -> None:
        for guard in (self.imu_guard, self.mag_guard):
            guard.reset_after_ns = int(value * 1e9)

    # -- callbacks -------------------------------------------------------------------------

    def _reset(self) -> None:
        if self.ahrs is not None:
            self.ahrs.reset()
        if self.compass is not None:
            self.compass.reset()
        self.mag_raw = None
        self.mag_ns = None
        self.held = None

    def _stamp_ok(self, guard: StampGuard, msg: Any, what: str) -> bool:
        verdict = guard.check(stamp_ns(msg.header))
        if verdict is StampVerdict.OK:
            return True
        if verdict is StampVerdict.RESET:
            self.get_logger().warning(f'{what}: {verdict.value} (bag loop?), starting over')
            self._reset()
            (self.mag_guard if guard is self.imu_guard else self.imu_guard).reset()
            return True
        self.warn_throttled(f'{what}: {verdict.value}, message dropped')
        return False

    def on_mag(self, msg: MagneticField) -> MagneticField | None:
        """Keep the newest raw field sample; returns the calibrated message (replay mode)."""
        raw = self._take_mag(msg)
        if raw is None:
            return None
        out = MagneticField()
        out.header = header_message(msg.header)
        set_vector3(out.magnetic_field, self.calibration.mag(raw))
        out.magnetic_field_covariance = msg.magnetic_field_covariance
        return out

    def _take_mag(self, msg: MagneticField) -> np.ndarray | None:
        """Keep the newest raw field sample (and process an IMU sample held for it); returns
        it, None for a dropped message. The subscription's callback: the calibrated message
        :meth:`on_mag` builds is for the replay's imu/mag only (~20 us a sample saved)."""
        try:
            raw = finite_vector3(msg.magnetic_field, 'imu/mag field')
        except ConversionError as exc:
            self.warn_throttled(f'{exc}, message dropped')
            return None
        if not self._stamp_ok(self.mag_guard, msg, 'imu/mag'):
            return None
        self.mag_raw = raw
        self.mag_ns = stamp_ns(msg.header)
        if self.held is not None and self.mag_ns >= self.held[0]:
            self._process(*self.held)
            self.held = None
        return raw

    def on_imu(self, msg: Imu) -> bytes | None:
        """Publish imu/data for one IMU sample; returns the calibrated raw sample as an Imu's
        CDR bytes (replay mode, which publishes it as imu/data_raw)."""
        try:
            accel, gyro = imu_sample(msg)
        except ConversionError as exc:
            self.warn_throttled(f'{exc}, message dropped')
            return None
        if not self._stamp_ok(self.imu_guard, msg, 'imu/data_raw'):
            return None
        # The sample's fields only (subscribed or replayed), published as CDR bytes by _publish
        stamp = msg.header.stamp
        calibrated = _Sample(int(stamp.sec), int(stamp.nanosec), self.frame_id or msg.header.frame_id,
                             self.calibration.gyro(gyro), self.calibration.accel(accel),
                             msg.angular_velocity_covariance, msg.linear_acceleration_covariance)
        t_ns = stamp_ns(msg.header)
        # A field sample with the IMU sample's stamp may come just after it: hold this one
        # sample until that field sample or the next IMU sample, whichever comes first (at
        # most one sample is ever held, so nothing queues up and nothing floods out later).
        if self.held is not None:
            self._process(*self.held)
            self.held = None
        if self.use_mag and (self.mag_ns is None or self.mag_ns < t_ns):
            self.held = (t_ns, gyro, accel, calibrated)
        else:
            self._process(t_ns, gyro, accel, calibrated)
        return None if self.player is None else calibrated.cdr(None, None)

    def _process(self, t_ns: int, gyro: np.ndarray, accel: np.ndarray, calibrated: _Sample) -> None:
        """imu/data for one IMU sample with the newest field sample within max_mag_age_s."""
        mag = None
        if self.use_mag and self.mag_ns is not None and abs(t_ns - self.mag_ns) <= self.max_mag_age_ns:
            mag = self.mag_raw
        if self.ahrs is not None:
            est = self.ahrs.update(t_ns, gyro, accel, mag, self.mag_ns)
            if isinstance(est, str):
                self.warn_throttled(f'imu/data_raw: {est}, message dropped')
                return
            if self.use_mag and not est.mag_used:
                self.warn_throttled('magnetometer missing, stale or disturbed: heading from the gyro, '
                                    'its covariance growing', 30.0)
            self._publish(calibrated, est.R_enu_body, est.covariance)
        else:
            self._emit_compass(accel, calibrated, mag)

    def _emit_compass(self, accel: np.ndarray, calibrated: _Sample, mag: np.ndarray | None) -> None:
        """Eq. 3-4 for one IMU sample and the field sample paired with it."""
        if mag is None:
            self.warn_throttled(
                f'no magnetometer sample within {self.max_mag_age_ns * 1e-9:.3g} s of the IMU; '
                'imu/data not published'
            )
            return
        assert self.compass is not None
        estimate = self.compass.estimate(accel, mag)
        if estimate is None:
            self.warn_throttled('gravity and field do not define an orientation (zero or parallel); skipped')
            return
        self._publish(calibrated, estimate.R_enu_body, estimate.covariance)

    def _publish(self, calibrated: _Sample, R_enu_body: np.ndarray, cov_enu: np.ndarray) -> None:
        R_world = self.R_world_enu @ self.R_declination_change
        R = R_world @ R_enu_body
        cov = R_world @ cov_enu @ R_world.T
        # imu/data as CDR bytes (ros.cdr_views), the same bytes as the message set_quaternion /
        # set_covariance / set_vector3 would fill, ~20 us sooner; subscribed and replayed alike
        self.pub_data.publish(calibrated.cdr(R, cov))
        self.published += 1
        if self.publish_tf and self.tf.listened:
            t_ns = calibrated.sec * 1_000_000_000 + calibrated.nanosec
            self.tf.send(transform_stamped(t_ns, self.fixed_frame, calibrated.frame_id or 'imu', R))


def main(args: list[str] | None = None) -> int:
    return run_node(ImuMagnetometerNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
