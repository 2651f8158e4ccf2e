"""Launch monocular keyframe SLAM on a bag, on a real ROS 2 install (not used by the pip install).

    ros2 launch ar_tracking slam.launch.py bag:=/path/to/desk.mcap params:=/path/to/desk.params.yaml

Plays the bag (bag_replay; it exits at the end unless loop:=true) and starts keyframe_slam_mapper
with config/keyframe_slam_mapper.yaml, then `params` (a rolling-shutter camera's readout_s; by
default the `<bag>.params.yaml` that `ar-tracking make-bag handheld_desk` writes beside the bag),
then use_sim_time. `namespace` moves everything under it with the namespace's own bag clock, as
in ar_tracking.launch.py.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

GRAPH = 'slam'


def _nodes(context, *args, **kwargs):
    from ar_tracking.ros.launch_plan import plan

    value = lambda name: LaunchConfiguration(name).perform(context)  # noqa: E731
    config = os.path.join(get_package_share_directory('ar_tracking'), 'config')
    specs = plan(GRAPH, value('bag'), config, namespace=value('namespace'), params=value('params'),
                 use_sim_time=value('use_sim_time'), rate=value('rate'), loop=value('loop'),
                 own_clock=value('own_clock'))
    return [Node(package='ar_tracking', executable=s.executable, name=s.executable, namespace=s.namespace or None,
                 parameters=s.parameters, remappings=s.remappings, output='screen') for s in specs]


def generate_launch_description() -> LaunchDescription:
    return LaunchDescription([
        DeclareLaunchArgument('bag', description='bag to play (mcap, sqlite3 or ROS 1)'),
        DeclareLaunchArgument('namespace', default_value='', description='namespace of every node and topic (one per robot)'),
        DeclareLaunchArgument('params', default_value='', description='params file (default: <bag>.params.yaml when it exists)'),
        DeclareLaunchArgument('use_sim_time', default_value='true', description='nodes take their time from the bag clock'),
        DeclareLaunchArgument('rate', default_value='1.0', description='playback rate factor'),
        DeclareLaunchArgument('loop', default_value='false', description='play the bag again at its end (else bag_replay exits)'),
        DeclareLaunchArgument('own_clock', default_value='auto', description='bag clock on /<namespace>/clock: auto (when a namespace is given), true, false'),
        OpaqueFunction(function=_nodes),
    ])
