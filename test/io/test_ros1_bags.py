"""ROS 1 bags are read through rosbags (converted to ROS 2 CDR), and the runner runs on them."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Ros1Writer
from rosbags.typesys import Stores, get_typestore

from ar_tracking.io.bags import BagReader, deserialize
from bagfactory import T0_NS, imu_msg, mag_msg

ROS1 = get_typestore(Stores.ROS1_NOETIC)


def write_ros1_bag(path: Path, n: int = 50) -> Path:
    """The same IMU + field stream as bagfactory, but as a ROS 1 bag (as recorded on Noetic)."""
    Imu1, Mag1 = ROS1.types['sensor_msgs/msg/Imu'], ROS1.types['sensor_msgs/msg/MagneticField']
    Header1 = ROS1.types['std_msgs/msg/Header']
    Time1 = ROS1.types['builtin_interfaces/msg/Time']
    with Ros1Writer(path) as w:
        c_imu = w.add_connection('/imu/data_raw', 'sensor_msgs/msg/Imu', typestore=ROS1)
        c_mag = w.add_connection('/imu/mag', 'sensor_msgs/msg/MagneticField', typestore=ROS1)
        for i in range(n):
            t = T0_NS + i * 10_000_000
            src_imu = imu_msg(t, (0.0, 0.0, 9.81))
            src_mag = mag_msg(t, (0.0, 2.1e-5, -4.3e-5))
            header = Header1(seq=i, stamp=Time1(sec=t // 10**9, nanosec=t % 10**9), frame_id='imu')
            imu = Imu1(header=header, orientation=src_imu.orientation, orientation_covariance=src_imu.orientation_covariance,
                       angular_velocity=src_imu.angular_velocity, angular_velocity_covariance=np.zeros(9),
                       linear_acceleration=src_imu.linear_acceleration, linear_acceleration_covariance=np.zeros(9))
            mag = Mag1(header=header, magnetic_field=src_mag.magnetic_field, magnetic_field_covariance=np.zeros(9))
            w.write(c_imu, t, ROS1.serialize_ros1(imu, 'sensor_msgs/msg/Imu'))
            w.write(c_mag, t, ROS1.serialize_ros1(mag, 'sensor_msgs/msg/MagneticField'))
    return path


def test_ros1_bag_reads_as_ros2_messages(tmp_path):
    path = write_ros1_bag(tmp_path / 'noetic.bag')
    with BagReader(path) as bag:
        assert bag.topics == {'/imu/data_raw': 'sensor_msgs/msg/Imu', '/imu/mag': 'sensor_msgs/msg/MagneticField'}
        first = next(iter(bag.messages(['/imu/data_raw'])))
        msg = deserialize(first.rawdata, first.msgtype)  # ROS 2 CDR after conversion
        assert msg.linear_acceleration.z == pytest.approx(9.81)
        assert msg.header.frame_id == 'imu'


def test_runner_runs_on_a_ros1_bag(tmp_path):
    pytest.importorskip('rclpy')
    from ar_tracking.ros.runner import GraphRunner

    path = write_ros1_bag(tmp_path / 'noetic.bag')
    result = GraphRunner(path, tmp_path / 'out.mcap').run()
    with BagReader(result.out_path) as out:
        assert out.message_count(['/imu/data']) == 50
