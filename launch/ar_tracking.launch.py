"""Launch the orientation graph on a bag, on a real ROS 2 install (not used by the pip install).

    ros2 launch ar_tracking ar_tracking.launch.py bag:=/path/to/bag.mcap
    ros2 launch ar_tracking ar_tracking.launch.py bag:=a.mcap namespace:=phone1 params:=phone1.yaml

Plays the bag (bag_replay; it exits at the end unless loop:=true) and starts imu_magnetometer,
panorama_mapper and hybrid_orientation_filter, each with its config/<node>.yaml, then `params`
(default: the calibration `<bag>.params.yaml` beside the bag, as `ar-tracking make-bag` writes
it), then use_sim_time. With a `namespace`, every topic moves under it and the bag clock is the
namespace's own (/<namespace>/clock, nodes remap /clock to it), so several phones can be
replayed side by side (own_clock:=false keeps the global /clock). What is started is decided in
ar_tracking.ros.launch_plan. marker_tracker and visual_inertial_filter need a marker map: start
them with `ros2 run ar_tracking marker_tracker --ros-args -p marker_map_file:=map.yaml`.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

GRAPH = 'orientation'


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
