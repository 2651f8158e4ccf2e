"""Every key in config/<node>.yaml is a declared parameter with the same default (habit 7)."""
from __future__ import annotations

from pathlib import Path

import pytest
import yaml

pytest.importorskip('rclpy')

from rclpy.parameter import Parameter  # noqa: E402

from ar_tracking.ros.params import packaged_config  # noqa: E402
from bagfactory import write_turning_imu_bag  # noqa: E402

CONFIG = Path(__file__).resolve().parents[2] / 'config'


def node_classes():
    from ar_tracking.nodes.annotation_matcher import AnnotationMatcherNode
    from ar_tracking.nodes.ar_view import ArViewNode
    from ar_tracking.nodes.bag_replay import BagReplayNode
    from ar_tracking.nodes.camera_replay import CameraReplayNode
    from ar_tracking.nodes.imu_magnetometer import ImuMagnetometerNode
    from ar_tracking.nodes.keyframe_slam_mapper import KeyframeSlamMapperNode
    from ar_tracking.nodes.hybrid_orientation_filter import HybridOrientationFilterNode
    from ar_tracking.nodes.marker_tracker import MarkerTrackerNode
    from ar_tracking.nodes.panorama_mapper import PanoramaMapperNode
    from ar_tracking.nodes.visual_inertial_filter import VisualInertialFilterNode

    return {'imu_magnetometer': ImuMagnetometerNode, 'bag_replay': BagReplayNode, 'camera_replay': CameraReplayNode,
            'panorama_mapper': PanoramaMapperNode, 'marker_tracker': MarkerTrackerNode,
            'visual_inertial_filter': VisualInertialFilterNode,
            'hybrid_orientation_filter': HybridOrientationFilterNode,
            'annotation_matcher': AnnotationMatcherNode, 'ar_view': ArViewNode,
            'keyframe_slam_mapper': KeyframeSlamMapperNode}


def test_every_node_has_a_config_file_and_it_is_packaged():
    for name in node_classes():
        assert (CONFIG / f'{name}.yaml').is_file()
        assert packaged_config(name) is not None


@pytest.mark.parametrize('name', sorted(node_classes()))
def test_config_keys_are_declared_with_equal_defaults(name, ros_context, tmp_path):
    params = yaml.safe_load((CONFIG / f'{name}.yaml').read_text())[name]['ros__parameters']
    cls = node_classes()[name]
    needs_bag = 'bag_path' in params and name != 'imu_magnetometer'
    overrides = []
    if needs_bag:  # the replay nodes need a bag to start; their other defaults are checked
        bag = write_turning_imu_bag(tmp_path / 'in.mcap', seconds=0.1)
        overrides = [Parameter('bag_path', value=str(bag)), Parameter('topics', value=['/imu/mag']),
                     Parameter('rate', value=0.0)]
    node = cls(context=ros_context, parameter_overrides=overrides)
    try:
        for key, value in params.items():
            assert node.has_parameter(key), f'{name}: {key} in config but not declared'
            if any(o.name == key for o in overrides):
                continue
            declared = node.get_parameter(key).value
            if isinstance(value, list):
                assert list(declared) == value, key
            else:
                assert declared == value, key
            descriptor = node.describe_parameter(key)
            assert descriptor.description, f'{name}: {key} has no description'
    finally:
        close = getattr(node, 'close', None)
        if close:
            close()
        node.destroy_node()
