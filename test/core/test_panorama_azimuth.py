"""The panorama's azimuth distortion learnt from the gyro (core/panorama_azimuth.py)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from ar_tracking.core.panorama_azimuth import AzimuthDistortion, AzimuthDistortionConfig
from ar_tracking.core.rotations import (quat_wxyz_conj, quat_wxyz_conj_floats, quat_wxyz_exp, quat_wxyz_log,
                                        quat_wxyz_log_along, quat_wxyz_mul, quat_wxyz_mul_floats, rot_x, rot_z,
                                        so3_exp, so3_log)

#: The phone's mount (imu -> camera_optical): diag(1, -1, -1).
R_IMU_CAM = np.diag([1.0, -1.0, -1.0])
UP = np.array([0.0, 0.0, 1.0])


def _session(stretch: float, seed: int = 0, duration_s: float = 40.0, bias_deg_s: float = 0.1
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A hand-held sweep: azimuth swinging +-120 deg then a full turn, pitch wobbling by a few
    degrees. The panorama frame is the world's (up = z), the first frame at azimuth 0; the
    tracked azimuth is the true one plus ``stretch`` times the azimuth turned from the start
    (a panorama built under parallax), wrapped where the turn closes (the seam at 180 deg).
    Returns gyro stamps, gyro rates (imu frame, with a bias and noise), frame stamps, the
    tracked R_pano_cam and the true R_pano_cam."""
    rng = np.random.default_rng(seed)
    t_imu = np.arange(0.0, duration_s, 0.01)
    turn = np.where(t_imu < 20.0, math.radians(120.0) * np.sin(2 * math.pi * t_imu / 10.0),
                    math.radians(360.0) * (t_imu - 20.0) / 20.0)
    pitch = math.radians(3.0) * np.sin(2 * math.pi * t_imu / 3.7)
    # camera looking horizontally along +y at azimuth 0: R = Rz(azimuth) Rx(-90 deg + pitch)
    R_true = np.array([rot_z(a) @ rot_x(-math.pi / 2 + p) for a, p in zip(turn, pitch)])
    R_imu = np.einsum('nij,kj->nik', R_true, R_IMU_CAM)  # R_pano_imu = R_pano_cam R_cam_imu
    # the rate at each sample (central difference), as a gyro samples it
    omega = np.array([so3_log(R_imu[max(k - 1, 0)].T @ R_imu[min(k + 1, len(t_imu) - 1)])
                      / (0.01 * (min(k + 1, len(t_imu) - 1) - max(k - 1, 0))) for k in range(len(t_imu))])
    omega += math.radians(bias_deg_s) * np.array([0.3, -0.5, 0.8]) + rng.normal(0, 0.003, omega.shape)
    frames = np.arange(0, len(t_imu), 3)  # 33 Hz
    wrapped = (turn + math.pi) % (2 * math.pi) - math.pi  # the panorama's azimuth, seam at 180
    c = stretch * wrapped
    R_tracked = np.array([so3_exp(c[k] * UP) @ R_true[k] @ so3_exp(rng.normal(0, 2e-4, 3))
                          for k in frames])
    return t_imu, omega, t_imu[frames], R_tracked, R_true[frames]


def _run(stretch: float, config: AzimuthDistortionConfig | None = None, **kw: float
         ) -> tuple[np.ndarray, np.ndarray, AzimuthDistortion]:
    """Heading errors (deg, after the best constant offset) of the raw and the corrected
    orientations, fed as a node would (each frame after the gyro samples of its time)."""
    t_imu, omega, t_frames, R_tracked, R_true = _session(stretch, **kw)
    est = AzimuthDistortion(R_IMU_CAM, config)
    raw, corrected = [], []
    k = 0
    for t, R, Rt in zip(t_frames, R_tracked, R_true):
        while k < len(t_imu) and t_imu[k] <= t + 0.05:  # the gyro runs 50 ms ahead of the frames
            est.add_gyro(int(t_imu[k] * 1e9), omega[k])
            k += 1
        est.add_visual(int(t * 1e9), R, UP)
        for out, Re in ((raw, R), (corrected, est.correct(R, UP))):
            out.append(float(so3_log(Re @ Rt.T) @ UP))
    errors = [np.degrees(np.asarray(e) - np.mean(e)) for e in (raw, corrected)]
    return errors[0], errors[1], est


def test_a_stretched_panorama_is_undone_by_the_gyro() -> None:
    raw, corrected, est = _run(0.008)  # 0.8 %: 2.9 deg over a turn, as the street with parallax
    rms = lambda e: float(np.sqrt(np.mean(e ** 2)))  # noqa: E731
    assert rms(raw) > 0.6
    # until the turn crosses the seam (30 s) the stretch is learnt as it is mapped
    before = slice(0, 950)
    assert rms(corrected[before] - corrected[before].mean()) < 0.2 * rms(raw[before] - raw[before].mean())
    # the jump at the seam is not learnt (those comparisons are left out), but the whole
    # session is still better than the raw orientation
    assert rms(corrected) < 0.85 * rms(raw)
    assert est.pairs > 1000 and 0 < est.outliers < 40


@pytest.mark.parametrize('stretch', [0.02, 0.04])
def test_a_larger_stretch_is_still_reduced_never_amplified(stretch: float) -> None:
    """Indoors (near walls) the stretch reaches several percent and the seam's jump 7-14 deg:
    the comparisons across it are left out rather than spread into the bias."""
    raw, corrected, _ = _run(stretch)
    assert float(np.sqrt(np.mean(corrected ** 2))) < 0.85 * float(np.sqrt(np.mean(raw ** 2)))


def test_an_undistorted_panorama_is_left_alone() -> None:
    raw, corrected, _ = _run(0.0)
    assert float(np.max(np.abs(corrected))) < 0.12
    assert float(np.sqrt(np.mean(corrected ** 2))) < 0.05


def test_a_gyro_bias_is_not_taken_for_a_stretch() -> None:
    """A residual gyro bias of 0.3 deg/s turns the gyro by 12 deg in 40 s: it is estimated
    beside c (the sweep back and forth separates the two), not put into the map."""
    _, corrected, est = _run(0.0, bias_deg_s=0.3)
    assert float(np.sqrt(np.mean(corrected ** 2))) < 0.06
    assert float(np.max(np.abs(corrected))) < 0.25
    assert est.outliers == 0


def test_frames_before_the_gyro_wait_for_it_and_a_reset_forgets() -> None:
    t_imu, omega, t_frames, R_tracked, _ = _session(0.01, duration_s=6.0)
    est = AzimuthDistortion(R_IMU_CAM)
    k = 0
    for t, R in zip(t_frames, R_tracked):  # every frame arrives 0.5 s before its gyro samples
        est.add_visual(int(t * 1e9), R, UP)
        while k < len(t_imu) and t_imu[k] <= t - 0.5:
            est.add_gyro(int(t_imu[k] * 1e9), omega[k])
            k += 1
    for t, w in zip(t_imu[k:], omega[k:]):
        est.add_gyro(int(t * 1e9), w)
    assert est.pairs > 100
    assert abs(est.distortion(R_tracked[-1], UP)) > 1e-3
    est.reset()
    assert est.pairs == 0 and est.distortion(R_tracked[-1], UP) == 0.0


def test_no_up_axis_no_correction() -> None:
    est = AzimuthDistortion(R_IMU_CAM)
    R = rot_x(-math.pi / 2)
    assert np.array_equal(est.correct(R, None), R)
    with pytest.raises(ValueError):
        AzimuthDistortionConfig(knots=2)


def test_the_float_quaternion_helpers_are_rotations_arithmetic() -> None:
    """The frame comparison's float quaternion algebra (rotations' *_floats and log_along, kept
    off numpy for speed) agrees with rotations' quat_wxyz_mul / conj / log, near the identity and near a half turn too."""
    rng = np.random.default_rng(3)
    u = rng.normal(size=3)
    u /= np.linalg.norm(u)
    for v in [*rng.normal(0.0, 1.0, (20, 3)), np.zeros(3), np.array([0.0, 0.0, math.pi - 1e-9])]:
        a, b = quat_wxyz_exp(v), quat_wxyz_exp(rng.normal(0.0, 1.0, 3))
        assert np.allclose(quat_wxyz_mul_floats(a.tolist(), b.tolist()), quat_wxyz_mul(a, b), rtol=0.0, atol=1e-15)
        assert np.array_equal(quat_wxyz_conj_floats(a.tolist()), quat_wxyz_conj(a))
        for q in (a, -a):
            assert math.isclose(quat_wxyz_log_along(tuple(q.tolist()), u), float(quat_wxyz_log(q) @ u),
                                rel_tol=1e-13, abs_tol=1e-15)


def test_a_stretched_panorama_keeps_a_symmetric_covariance() -> None:
    """The rank-one covariance downdates (BLAS dger in place) keep P symmetric (up to the
    rounding of the prior's inverse) and positive definite."""
    t_imu, omega, t_frames, R_tracked, _ = _session(0.01, duration_s=12.0)
    est = AzimuthDistortion(R_IMU_CAM)
    k = 0
    for t, R in zip(t_frames, R_tracked):
        while k < len(t_imu) and t_imu[k] <= t:
            est.add_gyro(int(t_imu[k] * 1e9), omega[k])
            k += 1
        est.add_visual(int(t * 1e9), R, UP)
    assert est.pairs > 300
    assert np.abs(est.P - est.P.T).max() <= 1e-12 * np.abs(est.P).max()
    assert np.all(np.linalg.eigvalsh(est.P) > 0.0)
