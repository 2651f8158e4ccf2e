"""The evaluation report (a PNG of every area's plots, or one self-contained HTML page) and the console tables of `evaluate`."""
from __future__ import annotations

import base64
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from ar_tracking.core.rotations import matrix_to_quat_xyzw, rot_x, rot_z
from ar_tracking.eval.metrics import EvaluationError, evaluate_bag
from ar_tracking.eval.report import write_report
from ar_tracking.io.bags import BagWriter, msg_class, ns_to_stamp

MS = 1_000_000
T0 = 50 * 1_000_000_000
PNG_MAGIC = b'\x89PNG\r\n\x1a\n'
R_LEVEL_NORTH = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def _R(k: int) -> np.ndarray:
    """Truth: turning a full circle and more (heading crosses 360 -> 0) while nodding."""
    t = k * 0.01
    return rot_z(-2.0 * t) @ rot_x(0.2 * np.sin(t)) @ R_LEVEL_NORTH


def _header(ns: int, frame: str) -> Any:
    return msg_class('std_msgs/msg/Header')(stamp=ns_to_stamp(ns), frame_id=frame)


def _transform(ns: int, R: np.ndarray) -> Any:
    q = matrix_to_quat_xyzw(R)
    Vector3 = msg_class('geometry_msgs/msg/Vector3')
    rotation = msg_class('geometry_msgs/msg/Quaternion')(x=q[0], y=q[1], z=q[2], w=q[3])
    return msg_class('geometry_msgs/msg/TransformStamped')(
        header=_header(ns, 'enu'), child_frame_id='camera_optical',
        transform=msg_class('geometry_msgs/msg/Transform')(
            translation=Vector3(x=0.0, y=0.0, z=0.0), rotation=rotation),
    )


def _disturbance(ns: int, deflection_rad: float) -> Any:
    return msg_class('geometry_msgs/msg/Vector3Stamped')(
        header=_header(ns, 'enu'),
        vector=msg_class('geometry_msgs/msg/Vector3')(x=deflection_rad, y=0.0, z=0.0),
    )


@pytest.fixture(scope='module')
def bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """4 s of truth at 100 Hz, an estimate whose heading error follows a disturbance, and one
    estimate topic that cannot be used (its frame has no transform)."""
    path = tmp_path_factory.mktemp('report') / 'run.mcap'
    with BagWriter(path) as w:
        for k in range(400):
            ns = T0 + k * 10 * MS
            deflection = np.radians(5.0) * np.exp(-((k - 200) / 50.0) ** 2)
            w.write('/ground_truth/orientation', ns, _transform(ns, _R(k)))
            w.write('/ground_truth/mag_disturbance', ns, _disturbance(ns, deflection))
            if k % 2:
                w.write('/orientation/global', ns, _transform(ns, rot_z(deflection) @ _R(k)))
        bad = _transform(T0, np.eye(3))
        bad.child_frame_id = 'unknown_body'
        w.write('/broken/orientation', T0, bad)
    return path


def test_png_report(bag: Path, tmp_path: Path) -> None:
    out = write_report(bag, tmp_path / 'figs' / 'report.png')
    data = out.read_bytes()
    assert out == tmp_path / 'figs' / 'report.png'
    assert data.startswith(PNG_MAGIC) and len(data) > 10_000


def test_html_report_is_self_contained(bag: Path, tmp_path: Path) -> None:
    out = write_report(bag, tmp_path / 'report.html', metrics=evaluate_bag(bag))
    page = out.read_text(encoding='utf-8')
    assert 'orientation/global' in page
    assert 'no transform unknown_body -&gt; camera_optical' in page
    match = re.search(r'src="data:image/png;base64,([A-Za-z0-9+/=]+)"', page)
    assert match is not None
    assert base64.b64decode(match.group(1)).startswith(PNG_MAGIC)
    assert 'src="http' not in page and 'src="file' not in page


def test_metrics_of_the_report_bag(bag: Path) -> None:
    m = evaluate_bag(bag)['orientation']['orientation/global']
    assert m['max_deg'] == pytest.approx(5.0, abs=0.05)
    assert m['tilt_rmse_deg'] == pytest.approx(0.0, abs=1e-3)


def test_unknown_report_kind_is_refused(bag: Path, tmp_path: Path) -> None:
    with pytest.raises(EvaluationError, match='.png or .html'):
        write_report(bag, tmp_path / 'report.pdf')


# --- every area: panorama and VI bags, the console, strict JSON -------------------------------

def _camera_info(ns: int) -> Any:
    roi = msg_class('sensor_msgs/msg/RegionOfInterest')(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return msg_class('sensor_msgs/msg/CameraInfo')(
        header=_header(ns, 'camera_optical'), height=240, width=320, distortion_model='plumb_bob',
        d=np.zeros(5), k=np.array([300.0, 0, 160, 0, 300, 120, 0, 0, 1]), r=np.eye(3).ravel(),
        p=np.zeros(12), binning_x=0, binning_y=0, roi=roi)


@pytest.fixture(scope='module')
def pano_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The report bag's truth plus a panorama tracker: 33 Hz frames, 0.05 deg off, 10 frames
    lost in the middle."""
    path = tmp_path_factory.mktemp('report') / 'pano.mcap'
    first = _R(0)
    with BagWriter(path) as w:
        for k in range(400):
            ns = T0 + k * 10 * MS
            w.write('/ground_truth/orientation', ns, _transform(ns, _R(k)))
        for i in range(133):
            k = 3 * i
            ns = T0 + k * 10 * MS
            w.write('/camera/camera_info', ns, _camera_info(ns))
            if 50 <= i < 60:
                continue
            # 0.05 deg about the optical axis, from the first frame on (which is the identity)
            msg = _transform(ns, first.T @ _R(k) @ rot_z(np.radians(0.05 if i else 0.0)))
            msg.header.frame_id, msg.child_frame_id = 'panorama', 'camera_optical'
            w.write('/panorama/orientation', ns, msg)
    return path


def test_panorama_section_is_plotted_and_missing_areas_are_named(pano_bag: Path, tmp_path: Path) -> None:
    from ar_tracking.eval.evaluate import evaluate_all

    metrics = evaluate_all(pano_bag, reference=False)
    assert metrics['panorama']['lost_frames'] == 10
    assert metrics['panorama']['tracking_rmse_deg'] == pytest.approx(0.05, abs=0.01)
    page = write_report(pano_bag, tmp_path / 'r.html', metrics).read_text(encoding='utf-8')
    assert 'Bag ' in page and ', 4.0 s, ' in page and ' topics.' in page  # never "- s, ? topics"
    assert '<h2>panorama' in page and 'Panorama tracking error over time' in page
    assert 'tracking RMSE (vs first frame)</td><td>0.050 deg</td><td>&lt;= 0.250 deg (#3)</td><td class="met">met' in page
    missing = page[page.index('Not in this bag'):]
    for area in ('annotations', 'slam', 'vi'):
        assert f'<b>{area}</b>' in missing
    assert '<pre>' not in page  # no raw JSON dumps
    images = re.findall(r'src="data:image/png;base64,([A-Za-z0-9+/=]+)"', page)
    assert len(images) == 1  # no orientation estimate here, one panorama plot (no map in the bag)


def test_panorama_tracking_figure(pano_bag: Path) -> None:
    from ar_tracking.eval.figures import panorama_tracking_png

    assert panorama_tracking_png(pano_bag).startswith(PNG_MAGIC)


def _pose(ns: int, p: np.ndarray, R: np.ndarray, frame: str = 'world') -> Any:
    q = matrix_to_quat_xyzw(R)
    return msg_class('geometry_msgs/msg/Pose')(
        position=msg_class('geometry_msgs/msg/Point')(x=float(p[0]), y=float(p[1]), z=float(p[2])),
        orientation=msg_class('geometry_msgs/msg/Quaternion')(x=q[0], y=q[1], z=q[2], w=q[3]))


@pytest.fixture(scope='module')
def vi_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A camera moving 0.3 m/s along x: truth at 100 Hz, vi/odometry 2 mm off, marker poses
    at 10 Hz arriving 80 ms late; no orientation truth (a marker bag)."""
    path = tmp_path_factory.mktemp('report') / 'vi.mcap'
    PoseStamped = msg_class('geometry_msgs/msg/PoseStamped')
    Odometry = msg_class('nav_msgs/msg/Odometry')
    PwC = msg_class('geometry_msgs/msg/PoseWithCovariance')
    PwCS = msg_class('geometry_msgs/msg/PoseWithCovarianceStamped')
    TwC = msg_class('geometry_msgs/msg/TwistWithCovariance')
    Twist = msg_class('geometry_msgs/msg/Twist')
    Vector3 = msg_class('geometry_msgs/msg/Vector3')
    R = R_LEVEL_NORTH
    with BagWriter(path) as w:
        for k in range(300):
            ns = T0 + k * 10 * MS
            p = np.array([0.003 * k, 0.0, 1.0])
            w.write('/ground_truth/pose', ns, PoseStamped(header=_header(ns, 'world'), pose=_pose(ns, p, R)))
            odom = Odometry(header=_header(ns, 'world'), child_frame_id='camera_optical',
                            pose=PwC(pose=_pose(ns, p + [0.002, 0.0, 0.0], R), covariance=np.zeros(36)),
                            twist=TwC(twist=Twist(linear=Vector3(x=0.0, y=0.0, z=0.0),
                                                  angular=Vector3(x=0.0, y=0.0, z=0.0)), covariance=np.zeros(36)))
            w.write('/vi/odometry', ns, odom)
            if k % 10 == 0:
                cam = PwCS(header=_header(ns, 'world'), pose=PwC(pose=_pose(ns, p, R), covariance=np.zeros(36)))
                w.write('/markers/pose', ns + 80 * MS, cam)
    return path


def test_vi_section_without_orientation_truth(vi_bag: Path, tmp_path: Path) -> None:
    from ar_tracking.eval.evaluate import evaluate_all
    from ar_tracking.eval.figures import vi_png

    assert vi_png(vi_bag).startswith(PNG_MAGIC)
    metrics = evaluate_all(vi_bag)
    assert metrics['vi']['position_rmse_cm'] == pytest.approx(0.2, abs=1e-3)
    page = write_report(vi_bag, tmp_path / 'vi.html', metrics).read_text(encoding='utf-8')
    assert ', 3.0 s, ' in page and '? topics' not in page
    assert 'Marker + IMU fusion against the camera alone' in page
    assert 'fused position RMSE</td><td>0.200 cm</td>' in page
    assert '<b>orientation</b>: no /ground_truth/orientation' in page


def test_console_table_for_every_area_with_targets() -> None:
    from ar_tracking.eval.console import format_console

    metrics = {
        'orientation': {'imu/data': {'rmse_deg': 1.0, 'heading_rmse_deg': 0.9, 'tilt_rmse_deg': 0.2,
                                     'max_deg': 2.0, 'n': 10},
                        'orientation/global': {'rmse_deg': 0.3, 'heading_rmse_deg': 1.2, 'tilt_rmse_deg': 0.1,
                                               'max_deg': 1.0, 'n': 10}},
        'panorama': {'tracking_rmse_deg': 0.03, 'frames': 100, 'lost_frames': 2, 'lost_frames_below_90dps': 1},
        'annotations': {'redetection_rate': 0.96, 'wrong_rate': 0.04, 'time_to_first_s': 1.0, 'n': 6, 'placed': 6},
        'slam': {'tracked_ratio': 0.9, 'ate_rmse_m': 0.002, 'ate_ratio': 0.0004, 'path_length_m': 5.0},
        'vi': {'position_rmse_cm': 0.15, 'orientation_rmse_deg': 0.08, 'camera_only': {'position_rmse_cm': 3.0}},
        'markers': {'pose': {'position_rmse_cm': 0.47, 'coverage': 0.94}, 'corner_bias_px': -0.08},
    }
    text = format_console(metrics, topics=[])
    lines = text.splitlines()

    def line(start: str) -> str:
        return next(x for x in lines if x.strip().startswith(start))

    for title in ('orientation (', 'panorama (', 'annotations (', 'slam (', 'markers (', 'vi ('):
        assert any(x.startswith(title) for x in lines), title
    assert 'not scored:' not in text
    assert line('hybrid heading RMSE ').endswith('target <= 1 deg (#16): NOT met')
    assert line('hybrid tilt RMSE').endswith(': met')
    assert 'sensor-only (imu/data)' in text
    assert line('tracking RMSE').endswith(': met')
    assert line('lost frames below 90').endswith('NOT met')
    assert line('redetection rate').endswith(': met') and line('wrong rate').endswith('NOT met')
    assert line('tracked frames').endswith('NOT met') and line('ATE / path length').endswith(': met')
    assert line('fused position RMSE').endswith(': met') and line('fused orientation RMSE').endswith('NOT met')
    assert line('fused vs camera-only hold').endswith(': met')
    assert line('camera-only position RMSE').endswith('NOT met')
    assert '-0.080 px' in line('corner bias') and line('corner bias').endswith('NOT met')  # |-0.08| > 0.05


def test_console_says_which_areas_are_not_scored_and_why() -> None:
    from ar_tracking.eval.console import format_console, unscored_areas

    metrics = {'slam': {'tracked_ratio': 0.0, 'ate_rmse_m': None, 'keyframes': 0, 'frames': 50}}
    topics = ['/camera/image_raw', '/slam/pose', '/slam/keyframes']
    why = dict(unscored_areas(metrics, topics=topics))
    assert set(why) == {'orientation', 'panorama', 'annotations', 'slam', 'markers', 'vi'}
    assert 'marker_tracker' in why['markers']
    assert '/ground_truth/orientation' in why['orientation']
    assert 'panorama_mapper' in why['panorama'] and 'annotation_matcher' in why['annotations']
    assert '/ground_truth/pose' in why['slam'] and 'visual_inertial_filter' in why['vi']
    assert 'not scored:' in format_console(metrics, topics=topics)


def test_evaluate_json_is_strict(bag: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture) -> None:
    import json

    from ar_tracking.cli import main
    from ar_tracking.eval import evaluate

    real = evaluate.evaluate_all

    def with_non_finite(path: Any, **kwargs: Any) -> dict:
        m = real(path, **kwargs)
        m['slam'] = {'ate_rmse_m': float('nan'), 'rpe_rmse': np.float64('inf'), 'keyframes': np.int64(3)}
        return m

    monkeypatch.setattr(evaluate, 'evaluate_all', with_non_finite)
    assert main(['evaluate', str(bag), '--json']) == 0

    def refuse(name: str) -> None:
        raise ValueError(f'not strict JSON: {name}')

    out = json.loads(capsys.readouterr().out, parse_constant=refuse)
    assert out['slam'] == {'ate_rmse_m': None, 'rpe_rmse': None, 'keyframes': 3}
    assert out['orientation']['orientation/global']['n'] == 200


def test_evaluate_console_names_every_area(bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    from ar_tracking.cli import main

    assert main(['evaluate', str(bag), '--report', str(tmp_path / 'r.html')]) == 0
    out = capsys.readouterr().out
    assert 'hybrid (orientation/global)' in out and 'target <= 1 deg (#16)' in out
    assert 'no transform unknown_body -> camera_optical' in out
    tail = out[out.index('not scored:'):]
    for area in ('panorama', 'annotations', 'slam', 'vi'):
        assert f'  {area} ' in tail
    assert out.rstrip().endswith(f'report: {tmp_path / "r.html"}')


def test_every_cli_option_has_help_and_scenarios_are_listed() -> None:
    import argparse

    from ar_tracking.cli import build_parser
    from ar_tracking.sim.bagmaker import SCENARIOS

    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    undocumented = [f'{name} {b.option_strings or b.dest}' for name, p in sub.choices.items()
                    for b in p._actions if not b.help]
    assert not undocumented
    text = sub.choices['make-bag'].format_help()
    assert all(s in text for s in SCENARIOS)


def test_convert_euroc_points_at_a_ground_truth_file(tmp_path: Path) -> None:
    from ar_tracking.cli import _euroc_groundtruth_hint

    (tmp_path / 'mav0' / 'cam0').mkdir(parents=True)
    assert _euroc_groundtruth_hint(tmp_path) is None  # nothing to point at
    gt = tmp_path / 'groundtruth_cam0' / 'V101_GT.txt'
    gt.parent.mkdir()
    gt.write_text('#timestamp,p_x,p_y,p_z,q_w,q_x,q_y,q_z\n')
    hint = _euroc_groundtruth_hint(tmp_path)
    assert hint is not None and len(hint.splitlines()) == 1
    assert f'--groundtruth {gt} --invert-gt-quaternion' in hint
    body = tmp_path / 'mav0' / 'state_groundtruth_estimate0' / 'data.csv'
    body.parent.mkdir()
    body.write_text('')
    assert _euroc_groundtruth_hint(tmp_path) is None  # the default one is used


def test_a_failing_area_is_named_and_does_not_hide_the_others(bag: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from ar_tracking.eval import evaluate
    from ar_tracking.eval.console import format_console

    real = evaluate._load

    def load(spec: str) -> Any:
        if 'slam' in spec:
            def broken(path: Path) -> None:
                raise RuntimeError('boom')
            return broken
        return real(spec)

    monkeypatch.setattr(evaluate, '_load', load)
    metrics = evaluate.evaluate_all(bag, reference=False)
    assert metrics['slam'] == {'error': 'evaluation failed: RuntimeError: boom'}
    assert metrics['orientation']['orientation/global']['n'] == 200
    text = format_console(metrics, bag)
    assert 'slam         evaluation failed: RuntimeError: boom' in text
    assert text.startswith('orientation (')


def test_an_all_null_area_is_not_a_section(bag: Path) -> None:
    from ar_tracking.eval.report import render_html

    metrics = evaluate_bag(bag)
    metrics['slam'] = {'ate_rmse_m': None, 'tracked_ratio': None, 'keyframes': None}
    page = render_html(bag, metrics, None, {})
    assert '<h2>slam' not in page
    assert '<li><b>slam</b>: no /slam/ topics in the bag' in page


def test_quiet_leaves_no_trace_in_process() -> None:
    """-q sets the nodes' default log level to ERROR for the command only (main() called
    in-process, as tests do, must not silence the nodes of later tests)."""
    import warnings

    rclpy_logging = pytest.importorskip('rclpy.logging')
    from ar_tracking.cli import _quiet_everything

    before = rclpy_logging.get_logger_effective_level('')
    filters = list(warnings.filters)
    restore = _quiet_everything('run')
    assert rclpy_logging.get_logger_effective_level('') == rclpy_logging.LoggingSeverity.ERROR
    restore()
    assert rclpy_logging.get_logger_effective_level('') == before
    assert warnings.filters == filters
