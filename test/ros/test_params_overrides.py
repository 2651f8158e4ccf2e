"""Params-file values become rclpy overrides a node accepts: integers where floats are declared,
alone or mixed with floats in a list (``[1.0, 0, 0]``), as people write a matrix."""
from __future__ import annotations

import pytest

pytest.importorskip('rclpy')

from rclpy.parameter import Parameter  # noqa: E402

from ar_tracking.nodes.hybrid_orientation_filter import HybridOrientationFilterNode  # noqa: E402
from ar_tracking.ros.params import to_overrides  # noqa: E402


def test_a_list_mixing_integers_and_floats_becomes_floats():
    (p,) = to_overrides({'soft_iron_matrix': [1.0, 0, 0, 0, 1, 0, 0, 0, 1.0]})
    assert p.type_ == Parameter.Type.DOUBLE_ARRAY
    assert list(p.value) == [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    (q,) = to_overrides({'topics': ['/a', '/b']})
    assert q.type_ == Parameter.Type.STRING_ARRAY  # other lists pass as they are


@pytest.mark.parametrize('matrix', [[1.0, 0, 0, 0, 1, 0, 0, 0, 2], [1, 0, 0, 0, 1, 0, 0, 0, 2]])
def test_a_node_starts_with_integers_in_its_float_array(matrix, ros_context):
    node = HybridOrientationFilterNode(context=ros_context, parameter_overrides=to_overrides(
        {'soft_iron_matrix': matrix, 'hard_iron_sigma': 1}))
    try:
        assert list(node.get_parameter('soft_iron_matrix').value) == [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 2.0]
        assert node.get_parameter('hard_iron_sigma').value == 1.0
    finally:
        node.destroy_node()
