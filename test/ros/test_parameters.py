"""Every node: each parameter applies live or is read-only (a set that reports success while
nothing changes would mislead); live ones accept a valid value, read-only ones refuse with the
reason; use_sim_time (rclpy's own) stays settable."""
from __future__ import annotations

import pytest

pytest.importorskip('rclpy')

from rclpy.parameter import Parameter  # noqa: E402

from bagfactory import write_turning_imu_bag  # noqa: E402
from test_config_files import node_classes  # noqa: E402

#: Live parameters each node must offer (the ones users change at run time).
MUST_BE_LIVE = {
    'imu_magnetometer': {'declination_rad', 'declination', 'world_frame', 'publish_tf', 'fixed_frame', 'frame_id'},
    'hybrid_orientation_filter': {'world_frame_id', 'camera_frame_id', 'publish_tf', 'publish_mount_tf'},
    'keyframe_slam_mapper': {'map_frame_id', 'camera_frame_id', 'publish_tf'},
    'marker_tracker': {'publish_tf'},
}


@pytest.mark.parametrize('name', sorted(node_classes()))
def test_each_parameter_is_live_or_read_only(name, ros_context, tmp_path):
    cls = node_classes()[name]
    overrides = []
    if name in ('bag_replay', 'camera_replay'):
        bag = write_turning_imu_bag(tmp_path / 'in.mcap', seconds=0.1)
        overrides = [Parameter('bag_path', value=str(bag)), Parameter('topics', value=['/imu/mag']),
                     Parameter('rate', value=0.0), Parameter('loop', value=True)]
    node = cls(context=ros_context, parameter_overrides=overrides)
    try:
        live = set(node._live)
        assert MUST_BE_LIVE.get(name, set()) <= live
        for pname in node._parameters:
            if pname == 'use_sim_time':
                continue
            descriptor = node.describe_parameter(pname)
            value = node.get_parameter(pname).value
            result = node.set_parameters([Parameter(pname, value=value)])[0]
            if pname in live:
                assert not descriptor.read_only and result.successful, f'{name}.{pname}: {result.reason}'
            else:
                assert descriptor.read_only, f'{name}.{pname} is neither live nor read-only'
                assert not result.successful and 'read-only' in result.reason
        assert node.set_parameters([Parameter('use_sim_time', value=True)])[0].successful
    finally:
        close = getattr(node, 'close', None)
        if close:
            close()
        node.destroy_node()
