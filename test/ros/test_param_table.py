"""ros/param_table: a node's parameters declared from a table of ParamSpec through TrackingNode.param."""
from __future__ import annotations

import pytest

pytest.importorskip('rclpy')

from rclpy.parameter import Parameter  # noqa: E402

from ar_tracking.ros.node_base import TrackingNode  # noqa: E402
from ar_tracking.ros.param_table import ParamSpec, declare_params, frame_name, one_of, with_defaults  # noqa: E402

TABLE = (
    ParamSpec('mode', 'a', 'Mode: a or b', choices=('a', 'b')),
    ParamSpec('gain', 1.5, 'A gain', min_value=0.0, max_value=10.0),
    ParamSpec('frame', 'map', 'A frame', validate=frame_name),
    ParamSpec('topics', ['x'], 'Topics'),
)


def _node(ros_context, overrides=(), **kwargs):
    node = TrackingNode('param_table_test', context=ros_context,
                        parameter_overrides=[Parameter(k, value=v) for k, v in overrides])
    return node, declare_params(node, TABLE, **kwargs)


def test_values_descriptors_and_live_callbacks(ros_context):
    seen = []
    node, v = _node(ros_context, [('gain', 2.0)], live={'gain': seen.append})
    try:
        assert v == {'mode': 'a', 'gain': 2.0, 'frame': 'map', 'topics': ['x']}
        d = node.describe_parameter('gain')
        assert d.description == 'A gain' and not d.read_only
        assert (d.floating_point_range[0].from_value, d.floating_point_range[0].to_value) == (0.0, 10.0)
        assert node.describe_parameter('mode').read_only  # no live callback: read-only
        assert node.set_parameters([Parameter('gain', value=3.0)])[0].successful
        assert seen == [3.0]
        assert not node.set_parameters([Parameter('mode', value='b')])[0].successful
    finally:
        node.destroy_node()


def test_choices_and_validators_check_the_initial_value(ros_context):
    with pytest.raises(ValueError, match='mode: must be one of a, b'):
        _node(ros_context, [('mode', 'c')])
    with pytest.raises(ValueError, match='frame: a frame name'):
        _node(ros_context, [('frame', '/map')])


def test_an_extra_validator_runs_after_the_table_checks(ros_context):
    node, _ = _node(ros_context, validate={'gain': lambda x: None if x != 5.0 else 'not five'},
                    live={'gain': lambda x: None})
    try:
        result = node.set_parameters([Parameter('gain', value=5.0)])[0]
        assert not result.successful and 'not five' in result.reason
        assert node.get_parameter('gain').value == 1.5
    finally:
        node.destroy_node()


def test_callbacks_for_unknown_names_are_errors(ros_context):
    with pytest.raises(KeyError, match='gian'):
        _node(ros_context, live={'gian': lambda x: None})


def test_list_defaults_are_copied_and_with_defaults_replaces(ros_context):
    node, v = _node(ros_context)
    try:
        v['topics'].append('y')
        assert TABLE[3].default == ['x']
    finally:
        node.destroy_node()
    table = with_defaults(TABLE, topics=['z'])
    assert table[3].default == ['z'] and TABLE[3].default == ['x'] and table[:3] == TABLE[:3]
    with pytest.raises(KeyError):
        with_defaults(TABLE, nope=1)


def test_one_of_reason():
    assert one_of(('a', 'b'))('a') is None
    assert one_of(('a', 'b'), 'use one of')('c') == 'use one of a, b'
