"""A recurring warning is throttled and says how many lines it held back."""
from __future__ import annotations

import re
import time

import pytest

pytest.importorskip('rclpy')


def test_throttled_warning_counts_what_it_held_back(ros_context, capfd) -> None:
    from ar_tracking.ros.node_base import TrackingNode

    node = TrackingNode('throttle_probe', context=ros_context)
    try:
        for k in range(5):
            if k == 4:
                time.sleep(0.35)
            node.warn_throttled('marker 17 rejected', period_s=0.3)  # one call site: one throttle
        lines = [x for x in capfd.readouterr().err.splitlines() if 'marker 17 rejected' in x]
        assert len(lines) == 2
        assert lines[0].endswith('marker 17 rejected')
        assert re.search(r'\(3 more like this in the last \d+\.\d s\)$', lines[1])
    finally:
        node.destroy_node()
