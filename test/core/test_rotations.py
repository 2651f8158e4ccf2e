"""Rotation helpers: quaternion orders, error decomposition, camera angles, interpolation."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ar_tracking.core.rotations import (
    align_about_axis,
    align_directions,
    angle_of,
    camera_heading_pitch_roll_deg,
    heading_tilt_error_deg,
    interpolate_rotations,
    is_valid_quat,
    matrix_to_quat_xyzw,
    quat_wxyz_to_xyzw,
    quat_xyzw_to_matrix,
    quat_xyzw_to_wxyz,
    rot_x,
    rot_y,
    rot_z,
    nearest_rotation,
    rotations_about_axis,
    trace_angle,
)

d = np.radians
#: Camera level, looking north: image x east, image y down, optical axis z north (columns in ENU).
R_LEVEL_NORTH = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def random_R(seed: int, n: int) -> np.ndarray:
    return Rotation.random(n, random_state=seed).as_matrix()


def camera(heading_deg: float, pitch_deg: float, roll_deg: float) -> np.ndarray:
    """R_enu_cam built from what a person would call heading, pitch and roll.

    Turn clockwise (seen from above) by the heading, tilt the optical axis up by the pitch
    (about the world east axis of the level camera), roll about the optical axis.
    """
    return rot_z(-d(heading_deg)) @ rot_x(d(pitch_deg)) @ R_LEVEL_NORTH @ rot_z(d(roll_deg))


# --- quaternions ------------------------------------------------------------------------------

def test_quaternion_matrix_round_trip_and_canonical_sign():
    R = random_R(1, 500)
    q = matrix_to_quat_xyzw(R)
    assert q.shape == (500, 4)
    assert np.all(q[:, 3] >= 0)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(quat_xyzw_to_matrix(q), R, atol=1e-12)
    # the negated quaternion is the same rotation, and maps back to the canonical sign
    np.testing.assert_allclose(quat_xyzw_to_matrix(-q), R, atol=1e-12)
    np.testing.assert_allclose(matrix_to_quat_xyzw(quat_xyzw_to_matrix(-q)), q, atol=1e-12)


def test_single_quaternion_canonical_sign():
    # a rotation by 270 deg about z is the quaternion (0, 0, sin 135, cos 135): w < 0 in scipy's
    # natural form; ours must flip it
    R = rot_z(d(270.0))
    q = matrix_to_quat_xyzw(R)
    assert q.shape == (4,)
    assert q[3] >= 0
    np.testing.assert_allclose(q, [0, 0, -np.sqrt(0.5), np.sqrt(0.5)], atol=1e-12)


def test_quaternion_known_values_xyzw():
    q = matrix_to_quat_xyzw(rot_x(d(90.0)))
    np.testing.assert_allclose(q, [np.sqrt(0.5), 0, 0, np.sqrt(0.5)], atol=1e-12)
    np.testing.assert_allclose(quat_xyzw_to_matrix([0, 0, 0, 1]), np.eye(3), atol=0)
    np.testing.assert_allclose(quat_xyzw_to_matrix([0, 0, 1, 0]), rot_z(np.pi), atol=1e-12)
    # un-normalised input is normalised
    np.testing.assert_allclose(quat_xyzw_to_matrix([0, 0, 0, 2.0]), np.eye(3), atol=1e-15)


def test_quaternion_order_conversions():
    q_xyzw = np.array([0.1, 0.2, 0.3, 0.9])
    q_wxyz = quat_xyzw_to_wxyz(q_xyzw)
    np.testing.assert_array_equal(q_wxyz, [0.9, 0.1, 0.2, 0.3])
    np.testing.assert_array_equal(quat_wxyz_to_xyzw(q_wxyz), q_xyzw)
    stack = matrix_to_quat_xyzw(random_R(2, 20))
    np.testing.assert_array_equal(quat_wxyz_to_xyzw(quat_xyzw_to_wxyz(stack)), stack)
    np.testing.assert_array_equal(quat_xyzw_to_wxyz(stack)[:, 0], stack[:, 3])


def test_is_valid_quat():
    assert is_valid_quat([0, 0, 0, 1])
    assert is_valid_quat([0, 0, 0, 1.0005])
    assert not is_valid_quat([0, 0, 0, 1.01])
    assert not is_valid_quat([0, 0, 0, 0])
    assert not is_valid_quat([np.nan, 0, 0, 1])
    assert not is_valid_quat([np.inf, 0, 0, 1])


def test_elementary_rotations_follow_the_right_hand_rule():
    np.testing.assert_allclose(rot_z(d(90)) @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(rot_x(d(90)) @ [0, 1, 0], [0, 0, 1], atol=1e-15)
    np.testing.assert_allclose(rot_y(d(90)) @ [0, 0, 1], [1, 0, 0], atol=1e-15)
    assert angle_of(rot_y(d(33))) == pytest.approx(d(33))
    np.testing.assert_allclose(angle_of(np.stack([np.eye(3), rot_x(np.pi)])), [0, np.pi])


# --- heading / tilt error ---------------------------------------------------------------------

@pytest.mark.parametrize(
    'E, total, heading, tilt',
    [
        (rot_z(d(3)), 3.0, 3.0, 0.0),
        (rot_z(d(-3)), 3.0, -3.0, 0.0),
        (rot_x(d(2)), 2.0, 0.0, 2.0),
        (rot_y(d(-2)), 2.0, 0.0, 2.0),
        (rot_z(d(3)) @ rot_x(d(2)), None, 3.0, 2.0),
        (rot_z(d(-170)) @ rot_y(d(5)), None, -170.0, 5.0),
        (np.eye(3), 0.0, 0.0, 0.0),
    ],
)
def test_heading_tilt_error_known_cases(E, total, heading, tilt):
    for R_true in random_R(3, 20):
        R_est = E @ R_true  # the error is in the world frame
        t, h, ti = heading_tilt_error_deg(R_est, R_true)
        assert h == pytest.approx(heading, abs=1e-9)
        assert ti == pytest.approx(tilt, abs=1e-6)
        expected_total = np.degrees(angle_of(E)) if total is None else total
        assert t == pytest.approx(expected_total, abs=1e-6)


def test_heading_tilt_error_on_stacks():
    R_true = random_R(4, 30)
    headings = np.linspace(-20, 20, 30)
    tilts = np.linspace(0, 10, 30)
    R_est = np.stack(
        [rot_z(d(h)) @ rot_x(d(t)) @ R for h, t, R in zip(headings, tilts, R_true)]
    )
    total, heading, tilt = heading_tilt_error_deg(R_est, R_true)
    assert total.shape == heading.shape == tilt.shape == (30,)
    np.testing.assert_allclose(heading, headings, atol=1e-9)
    np.testing.assert_allclose(tilt, tilts, atol=1e-6)
    assert np.all(total >= np.maximum(np.abs(heading), tilt) - 1e-9)


# --- camera heading / pitch / roll ------------------------------------------------------------

@pytest.mark.parametrize(
    'R, heading, pitch, roll',
    [
        (R_LEVEL_NORTH, 0.0, 0.0, 0.0),
        (rot_z(d(-90)) @ R_LEVEL_NORTH, 90.0, 0.0, 0.0),  # looking east
        (rot_z(d(90)) @ R_LEVEL_NORTH, 270.0, 0.0, 0.0),  # looking west
        (rot_z(d(180)) @ R_LEVEL_NORTH, 180.0, 0.0, 0.0),  # looking south
        (rot_x(d(10)) @ R_LEVEL_NORTH, 0.0, 10.0, 0.0),  # looking up 10 deg
        (rot_x(d(-25)) @ R_LEVEL_NORTH, 0.0, -25.0, 0.0),  # looking down
        # rolled about the optical axis: right side down is positive
        (R_LEVEL_NORTH @ rot_z(d(15)), 0.0, 0.0, 15.0),
        (rot_y(d(15)) @ R_LEVEL_NORTH, 0.0, 0.0, 15.0),  # same, about world north
        (R_LEVEL_NORTH @ rot_z(d(-40)), 0.0, 0.0, -40.0),
    ],
)
def test_camera_heading_pitch_roll_known_cases(R, heading, pitch, roll):
    h, p, r = camera_heading_pitch_roll_deg(R)
    assert float(h) % 360.0 == pytest.approx(heading, abs=1e-9)
    assert float(p) == pytest.approx(pitch, abs=1e-9)
    assert float(r) == pytest.approx(roll, abs=1e-9)


def test_camera_roll_right_side_down_is_positive():
    R = R_LEVEL_NORTH @ rot_z(d(15))
    image_right_in_enu = R[:, 0]
    assert image_right_in_enu[2] < 0  # the right side went down
    assert float(camera_heading_pitch_roll_deg(R)[2]) > 0


def test_camera_heading_pitch_roll_recovers_its_construction():
    """Heading, pitch and roll are independent: each reads back what built the rotation."""
    rng = np.random.default_rng(5)
    heading = rng.uniform(0, 360, 200)
    pitch = rng.uniform(-80, 80, 200)
    roll = rng.uniform(-170, 170, 200)
    R = np.stack([camera(h, p, r) for h, p, r in zip(heading, pitch, roll)])
    h, p, r = camera_heading_pitch_roll_deg(R)
    assert h.shape == (200,)
    assert np.all((h >= 0) & (h < 360))
    np.testing.assert_allclose(h, heading, atol=1e-9)
    np.testing.assert_allclose(p, pitch, atol=1e-9)
    np.testing.assert_allclose(r, roll, atol=1e-9)


def test_camera_pitched_and_rolled():
    h, p, r = camera_heading_pitch_roll_deg(camera(30.0, 45.0, 30.0))
    assert (float(h), float(p), float(r)) == pytest.approx((30.0, 45.0, 30.0), abs=1e-9)


# --- interpolation ----------------------------------------------------------------------------

def test_interpolate_at_knots_and_midway():
    times = np.array([0.0, 1.0, 3.0])
    R = np.stack([np.eye(3), rot_z(d(20)), rot_z(d(20)) @ rot_x(d(40))])
    out, inside = interpolate_rotations(times, R, times)
    assert inside.all()
    np.testing.assert_allclose(out, R, atol=1e-12)
    out, inside = interpolate_rotations(times, R, [0.5, 2.0, 2.5])
    np.testing.assert_allclose(out[0], rot_z(d(10)), atol=1e-12)
    np.testing.assert_allclose(out[1], rot_z(d(20)) @ rot_x(d(20)), atol=1e-12)
    np.testing.assert_allclose(out[2], rot_z(d(20)) @ rot_x(d(30)), atol=1e-12)


def test_interpolate_masks_queries_outside_the_span():
    times = np.array([10.0, 11.0])
    R = np.stack([np.eye(3), rot_y(d(30))])
    out, inside = interpolate_rotations(times, R, [9.0, 10.25, 11.0, 11.5])
    np.testing.assert_array_equal(inside, [False, True, True, False])
    assert out.shape == (2, 3, 3)
    np.testing.assert_allclose(out[0], rot_y(d(7.5)), atol=1e-12)
    np.testing.assert_allclose(out[1], rot_y(d(30)), atol=1e-12)


def test_interpolate_drops_duplicate_times_keeping_the_first():
    times = np.array([0.0, 1.0, 1.0, 2.0])
    R = np.stack([np.eye(3), rot_z(d(10)), rot_z(d(80)), rot_z(d(20))])
    out, inside = interpolate_rotations(times, R, [1.0, 1.5])
    assert inside.all()
    np.testing.assert_allclose(out[0], rot_z(d(10)), atol=1e-12)
    np.testing.assert_allclose(out[1], rot_z(d(15)), atol=1e-12)


def test_interpolate_single_sample():
    out, inside = interpolate_rotations([5.0], rot_x(d(3))[None], [4.0, 5.0, 6.0])
    np.testing.assert_array_equal(inside, [False, True, False])
    np.testing.assert_allclose(out, rot_x(d(3))[None], atol=0)


def test_trace_angle_agrees_with_angle_of_on_a_stack():
    Rs = Rotation.random(200, random_state=3).as_matrix()
    np.testing.assert_allclose(trace_angle(Rs), angle_of(Rs), atol=1e-9)
    assert float(trace_angle(np.eye(3))) == 0.0
    assert abs(float(trace_angle(Rotation.from_rotvec([0, 0, np.pi]).as_matrix())) - np.pi) < 1e-6


def test_rotations_about_axis_match_scipy():
    axis = np.array([0.3, -0.8, 0.5])
    angles = np.array([-2.0, -0.1, 0.0, 0.7, 3.0])
    k = axis / np.linalg.norm(axis)
    expected = Rotation.from_rotvec(angles[:, None] * k).as_matrix()
    np.testing.assert_allclose(rotations_about_axis(axis, angles), expected, atol=1e-12)


@pytest.mark.parametrize('n', [1, 2, 7])
def test_align_about_axis_recovers_the_angle_and_is_the_constrained_least_squares(n):
    rng = np.random.default_rng(n)
    axis = rng.normal(size=3)
    src = rng.normal(size=(n, 3))
    R = rotations_about_axis(axis, [0.9])[0]
    assert align_about_axis(src, src @ R.T, axis) == pytest.approx(0.9, abs=1e-12)
    # With noise: no other angle about the axis fits better, and the unconstrained (3-DoF)
    # solution fits at least as well.
    dst = src @ R.T + rng.normal(0, 0.05, (n, 3))
    psi = align_about_axis(src, dst, axis)
    def cost(Q):
        return float(np.sum((dst - src @ Q.T) ** 2))

    best = cost(rotations_about_axis(axis, [psi])[0])
    for d in (-0.01, 0.01):
        assert best < cost(rotations_about_axis(axis, [psi + d])[0])
    if n >= 2:
        assert cost(align_directions(src, dst)) <= best + 1e-12


def test_nearest_rotation_reorthonormalises_and_gives_the_chordal_mean():
    R = Rotation.from_euler('zyx', [40.0, -10.0, 5.0], degrees=True).as_matrix()
    noisy = R + np.random.default_rng(0).normal(0, 1e-3, (3, 3))
    Q = nearest_rotation(noisy)
    assert np.allclose(Q.T @ Q, np.eye(3), atol=1e-12) and np.linalg.det(Q) == pytest.approx(1.0)
    assert np.degrees(angle_of(Q.T @ R)) < 0.2
    # Samples symmetric about R: their chordal mean is R.
    d = rotations_about_axis([0.2, 1.0, -0.3], [0.03])[0]
    assert np.allclose(nearest_rotation(R @ d + R @ d.T), R, atol=1e-12)


def test_single_matrix_quaternion_equals_scipy_with_canonical_sign():
    """The fast one-matrix path agrees with scipy, 180 deg turns and the batch path included."""
    from scipy.spatial.transform import Rotation

    from ar_tracking.core.rotations import matrix_to_quat_xyzw

    Rs = list(Rotation.random(500, random_state=3).as_matrix())
    Rs += [Rotation.from_rotvec(np.pi * np.array(axis)).as_matrix() for axis in ([1, 0, 0], [0, 1, 0], [0, 0, 1])]
    for R in Rs:
        q = matrix_to_quat_xyzw(R)
        ref = Rotation.from_matrix(R).as_quat()
        ref = -ref if ref[3] < 0 else ref
        assert q[3] >= 0
        assert np.allclose(q, ref, atol=1e-12) or (abs(q[3]) < 1e-12 and np.allclose(q, -ref, atol=1e-12))
    assert np.allclose(matrix_to_quat_xyzw(np.stack(Rs[:5])), [matrix_to_quat_xyzw(R) for R in Rs[:5]])
