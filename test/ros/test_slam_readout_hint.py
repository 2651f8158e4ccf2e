"""keyframe_slam_mapper says how to set the rolling-shutter readout time when it is unset."""
from __future__ import annotations

import pytest

pytest.importorskip('rclpy')

HINT = 'readout_s:=0.03'


@pytest.mark.parametrize('readout_s, hinted', [(0.0, True), (0.03, False)])
def test_readout_hint_only_when_unset(ros_context, capfd, readout_s: float, hinted: bool) -> None:
    from rclpy.parameter import Parameter

    from ar_tracking.nodes.keyframe_slam_mapper import KeyframeSlamMapperNode

    node = KeyframeSlamMapperNode(context=ros_context, parameter_overrides=[Parameter('readout_s', value=readout_s)])
    try:
        err = capfd.readouterr().err
        assert (HINT in err) is hinted
        assert 'rolling-shutter readout' in err
    finally:
        node.destroy_node()
