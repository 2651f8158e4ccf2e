"""Orientation metrics on small synthetic bags whose errors are known by construction."""
from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from ar_tracking.core.rotations import (
    angle_of,
    heading_tilt_error_deg,
    matrix_to_quat_xyzw,
    rot_x,
    rot_z,
)
from ar_tracking.eval.metrics import EvaluationError, evaluate_bag
from ar_tracking.io.bags import BagError, BagWriter, msg_class, ns_to_stamp

SEC = 1_000_000_000
MS = 1_000_000
T0 = 1_700_000_000 * SEC  # epoch-sized stamps: float seconds would lose the nanoseconds
TRUTH_PERIOD_NS = 10 * MS
TRUTH_COUNT = 201  # 2 s at 100 Hz
#: Camera level and looking north: x east, y down, z north (columns are the camera axes in ENU).
R_LEVEL_NORTH = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
R_IMU_CAM = np.diag([1.0, -1.0, -1.0])
HEADING_OFFSET_DEG = 2.0
TILT_OFFSET_DEG = 1.5
#: Slerp between 10 ms truth samples of a smooth motion, plus rounding to 4 decimals.
TOL_DEG = 2e-3


def true_R_enu_cam(t_ns: int) -> np.ndarray:
    """A smooth camera motion: panning at ~29 deg/s while nodding up and down."""
    t = (t_ns - T0) * 1e-9
    return rot_z(0.3 + 0.5 * t) @ rot_x(0.2 * np.sin(1.3 * t)) @ R_LEVEL_NORTH


# --------------------------------------------------------------------------------------------
# Message builders.


def header(ns: int, frame: str) -> Any:
    return msg_class('std_msgs/msg/Header')(stamp=ns_to_stamp(ns), frame_id=frame)


def quaternion(R: np.ndarray | None = None, xyzw: Any = None) -> Any:
    q = matrix_to_quat_xyzw(R) if xyzw is None else np.asarray(xyzw, dtype=float)
    return msg_class('geometry_msgs/msg/Quaternion')(x=q[0], y=q[1], z=q[2], w=q[3])


def vector3(x: float = 0.0, y: float = 0.0, z: float = 0.0) -> Any:
    return msg_class('geometry_msgs/msg/Vector3')(x=x, y=y, z=z)


def transform_msg(ns: int, parent: str, child: str, R: np.ndarray | None = None,
                  xyzw: Any = None) -> Any:
    Transform = msg_class('geometry_msgs/msg/Transform')
    return msg_class('geometry_msgs/msg/TransformStamped')(
        header=header(ns, parent),
        child_frame_id=child,
        transform=Transform(translation=vector3(), rotation=quaternion(R, xyzw)),
    )


def imu_msg(ns: int, frame: str, R: np.ndarray | None = None, xyzw: Any = None,
            has_orientation: bool = True) -> Any:
    cov = np.zeros(9)
    cov[0] = 1e-4 if has_orientation else -1.0
    return msg_class('sensor_msgs/msg/Imu')(
        header=header(ns, frame),
        orientation=quaternion(R, xyzw),
        orientation_covariance=cov,
        angular_velocity=vector3(),
        angular_velocity_covariance=np.zeros(9),
        linear_acceleration=vector3(z=9.81),
        linear_acceleration_covariance=np.zeros(9),
    )


def pose_msg(ns: int, frame: str, R: np.ndarray) -> Any:
    Pose = msg_class('geometry_msgs/msg/Pose')
    Point = msg_class('geometry_msgs/msg/Point')
    return msg_class('geometry_msgs/msg/PoseStamped')(
        header=header(ns, frame), pose=Pose(position=Point(x=0.0, y=0.0, z=0.0),
                                            orientation=quaternion(R)),
    )


def tf_static(*transforms: Any) -> Any:
    return msg_class('tf2_msgs/msg/TFMessage')(transforms=list(transforms))


# --------------------------------------------------------------------------------------------
# Bags.

Fill = Callable[[BagWriter], None]


def truth_stamps() -> list[int]:
    return [T0 + k * TRUTH_PERIOD_NS for k in range(TRUTH_COUNT)]


def estimate_stamps() -> list[int]:
    """50 Hz, 5 ms off the truth's grid (so the truth must be interpolated), all inside."""
    return [T0 + 5 * MS + k * 20 * MS for k in range(99)]


def write_truth(w: BagWriter) -> None:
    for ns in truth_stamps():
        w.write('/ground_truth/orientation', ns, transform_msg(ns, 'enu', 'camera_optical',
                                                                true_R_enu_cam(ns)))


def write_estimate(w: BagWriter, topic: str, make: Callable[[int], Any],
                   stamps: list[int] | None = None) -> None:
    """One message per stamp; log times deliberately differ from header stamps."""
    for ns in stamps or estimate_stamps():
        w.write(topic, ns + 700 * MS, make(ns))


def make_bag(path: Path, *fills: Fill, truth: bool = True, storage: str | None = None) -> Path:
    with BagWriter(path, storage=storage) as w:  # type: ignore[arg-type]
        if truth:
            write_truth(w)
        for fill in fills:
            fill(w)
        return w.path


def offset_error() -> np.ndarray:
    """World-frame error with a known heading part and a known (horizontal-axis) tilt part."""
    return rot_z(np.radians(HEADING_OFFSET_DEG)) @ rot_x(np.radians(TILT_OFFSET_DEG))


def offset_estimate(w: BagWriter) -> None:
    write_estimate(w, '/orientation/global',
                   lambda ns: imu_msg(ns, 'camera_optical', offset_error() @ true_R_enu_cam(ns)))


def exact_estimate(topic: str = '/exact') -> Fill:
    return lambda w: write_estimate(
        w, topic, lambda ns: imu_msg(ns, 'camera_optical', true_R_enu_cam(ns)))


# --------------------------------------------------------------------------------------------
# The heading/tilt split itself.


@pytest.mark.parametrize(
    ('E', 'heading', 'tilt'),
    [
        (rot_z(np.radians(3.0)), 3.0, 0.0),
        (rot_z(np.radians(-3.0)), -3.0, 0.0),
        (rot_x(np.radians(2.0)), 0.0, 2.0),
        (rot_z(np.radians(2.0)) @ rot_x(np.radians(1.5)), 2.0, 1.5),
    ],
)
def test_heading_tilt_split_of_known_errors(E: np.ndarray, heading: float, tilt: float) -> None:
    R_true = true_R_enu_cam(T0 + 700 * MS)
    total, h, t = heading_tilt_error_deg(E @ R_true, R_true)
    assert h == pytest.approx(heading, abs=1e-9)
    assert t == pytest.approx(tilt, abs=1e-9)
    assert total == pytest.approx(np.degrees(angle_of(E)), abs=1e-9)


@settings(max_examples=60, deadline=None)
@given(
    quat=st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(
        lambda q: np.linalg.norm(q) > 0.1),
    heading=st.floats(-170.0, 170.0),
    tilt=st.floats(0.0, 60.0),
    axis_azimuth=st.floats(0.0, 2 * np.pi),
)
def test_heading_tilt_split_recovers_any_composition(
    quat: list[float], heading: float, tilt: float, axis_azimuth: float
) -> None:
    R_true = Rotation.from_quat(quat).as_matrix()
    axis = np.array([np.cos(axis_azimuth), np.sin(axis_azimuth), 0.0])
    E = rot_z(np.radians(heading)) @ Rotation.from_rotvec(np.radians(tilt) * axis).as_matrix()
    _, h, t = heading_tilt_error_deg(E @ R_true, R_true)
    assert h == pytest.approx(heading, abs=1e-6)
    assert t == pytest.approx(tilt, abs=1e-6)


# --------------------------------------------------------------------------------------------
# Bags.


def test_recovers_known_heading_and_tilt_offsets(tmp_path: Path) -> None:
    bag = make_bag(tmp_path / 'run.mcap', offset_estimate)
    result = evaluate_bag(bag)
    m = result['orientation']['orientation/global']
    total = np.degrees(angle_of(offset_error()))
    assert m['heading_rmse_deg'] == pytest.approx(HEADING_OFFSET_DEG, abs=TOL_DEG)
    assert m['tilt_rmse_deg'] == pytest.approx(TILT_OFFSET_DEG, abs=TOL_DEG)
    for key in ('rmse_deg', 'max_deg', 'mean_deg', 'p95_deg'):
        assert m[key] == pytest.approx(total, abs=TOL_DEG), key
    assert (m['n'], m['skipped']) == (len(estimate_stamps()), 0)
    # The bag's duration is that of its log times (the estimates are logged 0.7 s late).
    last_log_ns = estimate_stamps()[-1] + 700 * MS
    assert result['bag'] == {'path': str(bag), 'duration_s': (last_log_ns - T0) / SEC,
                             'topics': 2, 'world_alignment': 'none'}


def test_world_alignment_removes_a_constant_offset_and_says_so(tmp_path: Path) -> None:
    bag = make_bag(tmp_path / 'run.mcap', offset_estimate)
    rotation = evaluate_bag(bag, align='rotation')
    m = rotation['orientation']['orientation/global']
    assert m['rmse_deg'] < 1e-3
    assert m['aligned_by_deg'] == pytest.approx(np.degrees(angle_of(offset_error())), abs=TOL_DEG)
    assert rotation['bag']['world_alignment'] == 'rotation'
    heading = evaluate_bag(bag, align='heading')['orientation']['orientation/global']
    assert heading['heading_rmse_deg'] < evaluate_bag(bag)['orientation']['orientation/global']['heading_rmse_deg']
    assert heading['tilt_rmse_deg'] > 0.5 * TILT_OFFSET_DEG  # a heading alignment leaves the tilt


def test_output_is_json_with_rounded_floats(tmp_path: Path) -> None:
    result = evaluate_bag(make_bag(tmp_path / 'run.mcap', offset_estimate))
    assert json.loads(json.dumps(result)) == result
    for value in result['orientation']['orientation/global'].values():
        if isinstance(value, float):
            assert round(value, 4) == value


def test_rosbag2_sqlite3_bags_are_read_too(tmp_path: Path) -> None:
    bag = make_bag(tmp_path / 'run_db3', offset_estimate, storage='sqlite3')
    m = evaluate_bag(bag)['orientation']['orientation/global']
    assert m['heading_rmse_deg'] == pytest.approx(HEADING_OFFSET_DEG, abs=TOL_DEG)


@pytest.mark.parametrize('inverse', [False, True], ids=['imu->cam', 'cam->imu'])
def test_imu_body_frame_composed_with_static_transform(tmp_path: Path, inverse: bool) -> None:
    static = (transform_msg(T0, 'camera_optical', 'imu', R_IMU_CAM.T) if inverse
              else transform_msg(T0, 'imu', 'camera_optical', R_IMU_CAM))

    def fill(w: BagWriter) -> None:
        w.write('/tf_static', T0, tf_static(static))
        write_estimate(w, '/imu/data',
                       lambda ns: imu_msg(ns, 'imu', true_R_enu_cam(ns) @ R_IMU_CAM.T))

    m = evaluate_bag(make_bag(tmp_path / 'run.mcap', fill))['orientation']['imu/data']
    assert m['n'] == len(estimate_stamps())
    assert m['max_deg'] == pytest.approx(0.0, abs=TOL_DEG)


def test_missing_transform_gives_an_error_entry(tmp_path: Path,
                                                caplog: pytest.LogCaptureFixture) -> None:
    def fill(w: BagWriter) -> None:
        write_estimate(w, '/imu/data', lambda ns: imu_msg(ns, 'imu', true_R_enu_cam(ns)))

    with caplog.at_level(logging.WARNING):
        result = evaluate_bag(make_bag(tmp_path / 'run.mcap', fill, exact_estimate()))
    assert result['orientation']['imu/data'] == {'error': 'no transform imu -> camera_optical'}
    assert result['orientation']['exact']['n'] == len(estimate_stamps())
    assert 'no transform imu -> camera_optical' in caplog.text


def test_invalid_quaternions_are_skipped_and_counted(tmp_path: Path) -> None:
    bad = [(np.nan, 0.0, 0.0, 1.0), (0.0, np.inf, 0.0, 1.0), (0.0, 0.0, 0.0, 1.1),
           (0.0, 0.0, 0.0, 0.0)]

    def fill(w: BagWriter) -> None:
        exact_estimate('/imu/data')(w)
        for i, q in enumerate(bad):
            ns = T0 + 3 * MS + i * 100 * MS
            w.write('/imu/data', ns, imu_msg(ns, 'camera_optical', xyzw=q))

    m = evaluate_bag(make_bag(tmp_path / 'run.mcap', fill))['orientation']['imu/data']
    assert (m['n'], m['skipped']) == (len(estimate_stamps()), len(bad))
    assert m['max_deg'] == pytest.approx(0.0, abs=TOL_DEG)


def test_stamps_outside_the_truth_span_are_not_scored(tmp_path: Path) -> None:
    outside = [T0 - 50 * MS, T0 - 1 * MS, truth_stamps()[-1] + 1 * MS, T0 + 5 * SEC]
    wrong = rot_z(np.radians(90.0))  # would dominate every measure if it were scored

    def fill(w: BagWriter) -> None:
        exact_estimate('/imu/data')(w)
        write_estimate(w, '/imu/data',
                       lambda ns: imu_msg(ns, 'camera_optical', wrong @ true_R_enu_cam(ns)),
                       stamps=outside)
        write_estimate(w, '/late', lambda ns: imu_msg(ns, 'camera_optical', R_LEVEL_NORTH),
                       stamps=outside)

    result = evaluate_bag(make_bag(tmp_path / 'run.mcap', fill))['orientation']
    m = result['imu/data']
    assert (m['n'], m['outside'], m['skipped']) == (len(estimate_stamps()), len(outside), 0)
    assert m['max_deg'] == pytest.approx(0.0, abs=TOL_DEG)
    late = result['late']
    assert (late['n'], late['outside'], late['rmse_deg']) == (0, len(outside), None)


def test_which_topics_are_estimates(tmp_path: Path) -> None:
    def fill(w: BagWriter) -> None:
        write_estimate(w, '/imu/data_raw',
                       lambda ns: imu_msg(ns, 'imu', np.eye(3), has_orientation=False))
        write_estimate(w, '/panorama/orientation',
                       lambda ns: transform_msg(ns, 'panorama', 'camera_optical', np.eye(3)))
        write_estimate(w, '/vi/global', lambda ns: transform_msg(
            ns, 'enu', 'camera_optical', true_R_enu_cam(ns)))
        write_estimate(w, '/slam/pose', lambda ns: pose_msg(ns, 'enu', true_R_enu_cam(ns)))
        write_estimate(w, '/ground_truth/pose', lambda ns: pose_msg(ns, 'enu', np.eye(3)))

    result = evaluate_bag(make_bag(tmp_path / 'run.mcap', fill))['orientation']
    assert sorted(result) == ['slam/pose', 'vi/global']
    for m in result.values():
        assert m['n'] == len(estimate_stamps())
        assert m['max_deg'] == pytest.approx(0.0, abs=TOL_DEG)


def test_bag_without_ground_truth_raises_evaluation_error(tmp_path: Path) -> None:
    bag = make_bag(tmp_path / 'raw.mcap', exact_estimate(), truth=False)
    with pytest.raises(EvaluationError, match='has no /ground_truth/orientation'):
        evaluate_bag(bag)


def test_a_file_that_is_not_a_bag_raises_bag_error(tmp_path: Path) -> None:
    bogus = tmp_path / 'notes.mcap'
    bogus.write_text('not a bag\n')
    with pytest.raises(BagError):
        evaluate_bag(bogus)
    with pytest.raises(BagError):
        evaluate_bag(tmp_path / 'missing.mcap')
