"""imu_magnetometer: absolute orientation from gravity and the magnetic field (Langlotz 2011 sec. 5).

Live mode (default): subscribes ``imu/data_raw`` (sensor_msgs/Imu) and ``imu/mag``
(sensor_msgs/MagneticField) from a driver and publishes ``imu/data`` with the orientation of
the IMU body in the world frame (eq. 3-4), its covariance, and the calibrated rates and
accelerations - the same topics as imu_filter_madgwick, so it drops into graphs built for it.

Replay mode (parameter ``bag_path``): reads those topics from a bag itself and also publishes the
calibrated ``imu/data_raw`` and ``imu/mag``.
"""
from __future__ import annotations

from typing import Any

import numpy as np
from sensor_msgs.msg import Imu, MagneticField

from ..core.stamp_pairing import NearestStampPairer
from ..core.imu_orientation import FieldModel, GravityFieldOrientation, ImuCalibration
from ..io.replay import ReplayOptions, ScheduledMessage
from ..ros.conversions import (
    ConversionError,
    finite_vector3,
    set_covariance,
    set_quaternion,
    set_vector3,
    stamp_ns,
    vector3,
)
from ..ros.frames import WORLD_FROM_ENU, check_world_frame
from ..ros.node_base import RELIABLE_QOS, SENSOR_QOS, TrackingNode, run_node
from ..ros.stamp_guard import StampGuard, StampVerdict


def _length(n: int) -> Any:
    return lambda v: None if len(v) == n else f'needs {n} values, got {len(v)}'


def _matrix(v: Any) -> str | None:
    if len(v) != 9:
        return f'needs 9 values (row-major 3x3), got {len(v)}'
    if abs(np.linalg.det(np.reshape(np.asarray(v, float), (3, 3)))) < 1e-6:
        return 'matrix is singular'
    return None


class ImuMagnetometerNode(TrackingNode):
    INPUTS = {'imu/data_raw': 'sensor_msgs/msg/Imu', 'imu/mag': 'sensor_msgs/msg/MagneticField'}
    OUTPUTS = {'imu/data': 'sensor_msgs/msg/Imu'}

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('imu_magnetometer', **kwargs)
        p = self.param
        calibration = ImuCalibration(
            gyro_bias=p('gyro_bias', [0.0, 0.0, 0.0], 'Gyro bias subtracted from angular_velocity, rad/s (x, y, z)', validate=_length(3)),
            accel_bias=p('accel_bias', [0.0, 0.0, 0.0], 'Accelerometer bias subtracted from linear_acceleration, m/s^2', validate=_length(3)),
            hard_iron_offset=p('hard_iron_offset', [0.0, 0.0, 0.0], 'Hard-iron offset subtracted from the raw field, tesla', validate=_length(3)),
            soft_iron_matrix=p('soft_iron_matrix', [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0], 'Soft-iron correction, row-major 3x3: field = M (raw - hard_iron_offset)', validate=_matrix),
        )
        model = FieldModel(
            gravity_m_s2=p('gravity_m_s2', 9.80665, 'Local gravity, m/s^2', min_value=9.7, max_value=9.9),
            field_t=p('expected_field_t', 0.0, 'Local magnetic field strength, tesla (0: learn it online)', min_value=0.0, max_value=1e-4),
            dip_rad=p('expected_dip_rad', 0.0, 'Local inclination of the field, rad, positive down (used when expected_field_t > 0)', min_value=-1.5708, max_value=1.5708),
            declination_rad=p('declination_rad', 0.0, 'Magnetic declination, rad, positive when magnetic north is east of true north', min_value=-3.1416, max_value=3.1416),
            accel_noise_m_s2=p('accel_noise_m_s2', 0.05, 'Accelerometer white noise, 1-sigma per axis, m/s^2 (covariance floor)', min_value=1e-6, max_value=10.0),
            mag_noise_t=p('mag_noise_t', 3e-7, 'Magnetometer white noise, 1-sigma per axis, tesla (covariance floor)', min_value=1e-12, max_value=1e-4),
        )
        self.world_frame: str = p('world_frame', 'enu', 'World frame of the published orientation: enu, ned or nwu', validate=check_world_frame)
        self.max_mag_age_ns = int(1e9 * p('max_mag_age_s', 0.1, 'Largest stamp difference between an IMU sample and the field sample paired with it, s', min_value=0.0, max_value=10.0))
        self.frame_id: str = p('frame_id', '', 'Body frame id of the output (empty: the input frame_id)')
        reset_s = p('reset_after_s', 1.0, 'A stamp this much older than the previous one means the clock jumped back (bag loop): reset', min_value=0.0, max_value=3600.0)
        bag_path: str = p('bag_path', '', 'Replay mode: read imu/data_raw and imu/mag from this bag instead of subscribing', read_only=True)
        rate = p('rate', 1.0, 'Replay mode: playback rate factor (0: as fast as possible)', min_value=0.0, max_value=1000.0, read_only=True)
        loop = p('loop', False, 'Replay mode: play the bag again when it ends', read_only=True)

        self.core = GravityFieldOrientation(calibration, model)
        self.R_world_enu = WORLD_FROM_ENU[self.world_frame]
        self.imu_guard = StampGuard(reset_s)
        self.mag_guard = StampGuard(reset_s)
        self.pairer: NearestStampPairer[tuple[np.ndarray, Imu], np.ndarray] = NearestStampPairer(self.max_mag_age_ns)
        self.published = 0

        self.pub_data = self.advertise(Imu, 'imu/data', RELIABLE_QOS)
        self.player = None
        if bag_path:
            self.pub_raw = self.advertise(Imu, 'imu/data_raw', RELIABLE_QOS)
            self.pub_mag = self.advertise(MagneticField, 'imu/mag', RELIABLE_QOS)
            self._start_replay(bag_path, ReplayOptions(rate=rate, loop=loop, topics=[]))
        else:
            self.subscribe(Imu, 'imu/data_raw', self.on_imu, SENSOR_QOS)
            self.subscribe(MagneticField, 'imu/mag', self.on_mag, SENSOR_QOS)
        self.get_logger().info(
            f'imu_magnetometer: {"replaying " + bag_path if bag_path else "listening on imu/data_raw, imu/mag"}'
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

        from ..ros.player import BagPlayer

        self.player = BagPlayer(path, options, on_message, on_done)
        self.player.start()

    def close(self) -> None:
        if self.player is not None:
            self.player.stop()

    # -- callbacks -------------------------------------------------------------------------

    def _stamp_ok(self, guard: StampGuard, msg: Any, what: str) -> bool:
        verdict = guard.check(stamp_ns(msg.header))
        if verdict is StampVerdict.OK:
            return True
        if verdict is StampVerdict.RESET:
            self.get_logger().warning(f'{what}: {verdict.value} (bag loop?), starting over')
            self.core.reset()
            self.pairer.reset()
            (self.mag_guard if guard is self.imu_guard else self.imu_guard).reset()
            return True
        self.warn_throttled(f'{what}: {verdict.value}, message dropped')
        return False

    def on_mag(self, msg: MagneticField) -> MagneticField | None:
        """Store the calibrated field for pairing; returns the calibrated message (replay mode)."""
        try:
            raw = finite_vector3(msg.magnetic_field, 'imu/mag field')
        except ConversionError as exc:
            self.warn_throttled(f'{exc}, message dropped')
            return None
        if not self._stamp_ok(self.mag_guard, msg, 'imu/mag'):
            return None
        for _, (accel, calibrated), mag in self.pairer.add_secondary(stamp_ns(msg.header), raw):
            self._emit(accel, calibrated, mag)
        out = MagneticField()
        out.header = msg.header
        set_vector3(out.magnetic_field, self.core.calibration.mag(raw))
        out.magnetic_field_covariance = msg.magnetic_field_covariance
        return out

    def on_imu(self, msg: Imu) -> Imu | None:
        """Publish imu/data for one IMU sample; returns the calibrated raw message (replay mode)."""
        try:
            accel = finite_vector3(msg.linear_acceleration, 'imu/data_raw linear_acceleration')
            gyro = vector3(msg.angular_velocity)
            if not np.all(np.isfinite(gyro)):
                raise ConversionError('imu/data_raw angular_velocity is not finite')
        except ConversionError as exc:
            self.warn_throttled(f'{exc}, message dropped')
            return None
        if not self._stamp_ok(self.imu_guard, msg, 'imu/data_raw'):
            return None
        calibrated = Imu()
        calibrated.header = msg.header
        if self.frame_id:
            calibrated.header.frame_id = self.frame_id
        set_vector3(calibrated.angular_velocity, self.core.calibration.gyro(gyro))
        set_vector3(calibrated.linear_acceleration, self.core.calibration.accel(accel))
        calibrated.angular_velocity_covariance = msg.angular_velocity_covariance
        calibrated.linear_acceleration_covariance = msg.linear_acceleration_covariance
        set_covariance(calibrated.orientation_covariance, None)

        # Pair with the field sample nearest in stamp, whatever order the two streams arrive in.
        for _, (sample_accel, sample_msg), mag in self.pairer.add_primary(stamp_ns(msg.header), (accel, calibrated)):
            self._emit(sample_accel, sample_msg, mag)
        return calibrated

    def _emit(self, accel: np.ndarray, calibrated: Imu, mag: np.ndarray | None) -> None:
        """Publish imu/data for one IMU sample and its paired raw field sample."""
        if mag is None:
            self.warn_throttled(
                f'no magnetometer sample within {self.max_mag_age_ns * 1e-9:.3g} s of the IMU; '
                'imu/data not published'
            )
            return
        estimate = self.core.estimate(accel, mag)
        if estimate is None:
            self.warn_throttled('gravity and field do not define an orientation (zero or parallel); skipped')
            return
        out = Imu()
        out.header = calibrated.header
        out.angular_velocity = calibrated.angular_velocity
        out.linear_acceleration = calibrated.linear_acceleration
        out.angular_velocity_covariance = calibrated.angular_velocity_covariance
        out.linear_acceleration_covariance = calibrated.linear_acceleration_covariance
        R = self.R_world_enu @ estimate.R_enu_body
        set_quaternion(out.orientation, R)
        set_covariance(out.orientation_covariance, self.R_world_enu @ estimate.covariance @ self.R_world_enu.T)
        self.pub_data.publish(out)
        self.published += 1


def main(args: list[str] | None = None) -> int:
    return run_node(ImuMagnetometerNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
