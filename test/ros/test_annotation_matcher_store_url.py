"""annotation_matcher with ``store_url``: a PostGIS store on the session's throwaway server; a
server that is down or refuses the user is one line per attempt, the node goes on without
annotations and tries again after 1, 2, 4 ... s of bag time."""
from __future__ import annotations

import pytest

pytest.importorskip('rclpy')

from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import NavSatFix, NavSatStatus  # noqa: E402

from annotation_synth import annotation, make_case  # noqa: E402
from ar_tracking.io.stores import open_store  # noqa: E402
from ar_tracking.nodes.annotation_matcher import AnnotationMatcherNode  # noqa: E402
from ar_tracking.ros.conversions import to_stamp  # noqa: E402

T0 = 1_700_000_000_000_000_000
LAT, LON = 47.0458, 15.4251


def fix(t: int, lat: float = LAT) -> NavSatFix:
    msg = NavSatFix()
    msg.header.stamp = to_stamp(t)
    msg.status.status = NavSatStatus.STATUS_FIX
    msg.latitude, msg.longitude, msg.altitude = lat, LON, 350.0
    msg.position_covariance = [9.0, 0.0, 0.0, 0.0, 9.0, 0.0, 0.0, 0.0, 9.0]
    msg.position_covariance_type = NavSatFix.COVARIANCE_TYPE_DIAGONAL_KNOWN
    return msg


def node_with(context, url: str) -> AnnotationMatcherNode:
    return AnnotationMatcherNode(context=context, parameter_overrides=[
        Parameter('store_url', value=url), Parameter('reload_period_s', value=0.0)])


def test_postgis_store_url_loads_annotations(ros_context, pg_store_url) -> None:
    case = make_case(seed=14)
    with open_store(pg_store_url, create=True) as store:
        store.add([annotation(p, d, text=f'label {i}', lat=LAT, lon=LON)
                   for i, (p, d) in enumerate(zip(case.patches, case.dirs))])
    node = node_with(ros_context, pg_store_url)
    try:
        node.on_fix(fix(T0, lat=LAT + 0.01))  # 1.1 km away: nothing within 50 m
        assert node.detector is None
        node.on_fix(fix(T0 + 10**9))
        assert node.detector is not None and node.detector.n == 6
        assert sorted(a.text for a in node.annotations) == [f'label {i}' for i in range(6)]
    finally:
        node.destroy_node()


def test_server_down_is_one_line_and_retried_with_back_off(ros_context, tmp_path, monkeypatch) -> None:
    node = node_with(ros_context, f'postgresql://reader:s3cret@/ar?host={tmp_path}&connect_timeout=1')
    lines: list[str] = []
    monkeypatch.setattr(node.get_logger(), 'warning', lambda text, **kw: lines.append(text))
    try:
        for dt_s in (0.0, 0.5, 1.0, 2.0, 2.5, 5.0):  # tries at 0, 1 (after 1 s), 3 (2 s later): 0.5, 2.0, 2.5 wait
            node.on_fix(fix(T0 + int(dt_s * 1e9)))
        assert node.detector is None and node.store_backoff.failures == 3
        assert len(lines) == 3 and all('\n' not in x and 's3cret' not in x for x in lines)
        assert 'cannot connect' in lines[0] and 'next try in 1 s' in lines[0] and 'next try in 4 s' in lines[2]
        assert all(s.failures == 0 for s in node.callback_stats.values())
    finally:
        node.destroy_node()


def test_wrong_user_is_one_line(ros_context, pg_cluster, monkeypatch) -> None:
    node = node_with(ros_context, pg_cluster.url.replace('postgres@', 'nobody@'))
    lines: list[str] = []
    monkeypatch.setattr(node.get_logger(), 'warning', lambda text, **kw: lines.append(text))
    try:
        node.on_fix(fix(T0))
        assert node.detector is None and len(lines) == 1 and 'nobody' in lines[0]
    finally:
        node.destroy_node()
