"""Launch monocular keyframe SLAM on a bag on a real ROS 2 install (not used by the pip install).

    ros2 launch ar_tracking slam.launch.py bag:=/path/to/bag.mcap rate:=1.0

Plays the bag (camera topics and /clock) and starts keyframe_slam_mapper with use_sim_time and
config/keyframe_slam_mapper.yaml (set readout_s for a rolling-shutter camera:
`params:=/path/to/bag.params.yaml`, which `ar-tracking make-bag handheld_desk` writes).
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
    params = LaunchConfiguration('params')
    return LaunchDescription([
        DeclareLaunchArgument('bag', description='bag to play (mcap, sqlite3 or ROS 1)'),
        DeclareLaunchArgument('rate', default_value='1.0', description='playback rate factor'),
        DeclareLaunchArgument('params', default_value=os.path.join(config, 'keyframe_slam_mapper.yaml'),
                              description='parameters file of keyframe_slam_mapper'),
        Node(package='ar_tracking', executable='bag_replay', name='bag_replay',
             parameters=[os.path.join(config, 'bag_replay.yaml'), {'bag_path': bag, 'rate': rate}]),
        Node(package='ar_tracking', executable='keyframe_slam_mapper', name='keyframe_slam_mapper',
             parameters=[os.path.join(config, 'keyframe_slam_mapper.yaml'), params, {'use_sim_time': True}]),
    ])
