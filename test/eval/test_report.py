"""The evaluation report: a PNG figure, or one self-contained HTML page."""
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
