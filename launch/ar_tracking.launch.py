"""Launch the ar_tracking graph on a real ROS 2 install (not used by the pip install).

    ros2 launch ar_tracking ar_tracking.launch.py bag:=/path/to/bag.mcap rate:=1.0

Plays the bag (camera and IMU/magnetometer topics, /clock) and starts the Langlotz chain
(imu_magnetometer, panorama_mapper, hybrid_orientation_filter) with use_sim_time, each with its
config/<node>.yaml. marker_tracker and visual_inertial_filter need a marker map: start them with
`ros2 run ar_tracking marker_tracker --ros-args -p marker_map_file:=map.yaml`.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description() -> LaunchDescription:
    config = os.path.join(get_package_share_directory('ar_tracking'), 'config')
    bag = LaunchConfiguration('bag')
    rate = LaunchConfiguration('rate')
    sim_time = {'use_sim_time': True}
    return LaunchDescription([
        DeclareLaunchArgument('bag', description='bag to play (mcap, sqlite3 or ROS 1)'),
        DeclareLaunchArgument('rate', default_value='1.0', description='playback rate factor'),
        Node(package='ar_tracking', executable='bag_replay', name='bag_replay',
             parameters=[os.path.join(config, 'bag_replay.yaml'), {'bag_path': bag, 'rate': rate}]),
        Node(package='ar_tracking', executable='imu_magnetometer', name='imu_magnetometer',
             parameters=[os.path.join(config, 'imu_magnetometer.yaml'), sim_time]),
        Node(package='ar_tracking', executable='panorama_mapper', name='panorama_mapper',
             parameters=[os.path.join(config, 'panorama_mapper.yaml'), sim_time]),
        Node(package='ar_tracking', executable='hybrid_orientation_filter', name='hybrid_orientation_filter',
             parameters=[os.path.join(config, 'hybrid_orientation_filter.yaml'), sim_time]),
    ])
