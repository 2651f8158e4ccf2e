"""The rolling shutter's readout estimated from tracked frames (core/panorama/readout.py)."""
from __future__ import annotations

import numpy as np
import pytest

from ar_tracking.core.panorama.readout import Painting, ReadoutConfig, ReadoutEstimator, RowFit, frame_reading
from scipy.spatial.transform import Rotation


def so3_exp(v: np.ndarray) -> np.ndarray:
    return Rotation.from_rotvec(v).as_matrix()


def _frame(rng: np.random.Generator, readout: float, used: float, omega: np.ndarray, painting: tuple | None,
           noise: float = 3e-4, n: int = 60) -> tuple[RowFit, Painting | None]:
    """Inliers of a frame fit whose rows were turned by ``used`` while the camera read them over
    ``readout`` at ``omega`` (panorama axes), against a map painted by ``painting`` = (omega_j,
    readout_j, its rows as a function of the frame's rows) or an exact one; a small error of
    the frame's rotation on top."""
    p = rng.normal(size=(n, 3)) * [0.3, 0.25, 0.0] + [0.0, 0.0, 1.0]
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    v = rng.uniform(0.0, 1.0, n)
    dtheta = rng.normal(scale=2e-3, size=3)
    d = np.einsum('nij,nj->ni', so3_exp(np.outer(v * (readout - used), omega)), p) @ so3_exp(dtheta).T
    paint = None
    if painting is not None:
        omega_j, readout_j, rows_of = painting
        rows_j = rows_of(v)
        # the map pixel was put at the direction its frame's readout said, not the true one
        d = np.einsum('nij,nj->ni', so3_exp(np.outer(-rows_j * (readout - readout_j), omega_j)), d)
        paint = Painting(np.tile(omega_j, (n, 1)), rows_j, np.full(n, readout_j))
    d += rng.normal(scale=noise, size=d.shape)
    return RowFit(p, d - p, v, np.arange(n)), paint


def test_one_frame_reads_the_readout_against_an_exact_map():
    rng = np.random.default_rng(3)
    omega = np.array([0.1, 0.9, 0.05])
    fit, _ = _frame(rng, 0.030, 0.0, omega, None)
    s, info = frame_reading(fit, omega, 0.0)
    assert s == pytest.approx(0.030, abs=3.0 / np.sqrt(info)) and 1.0 / np.sqrt(info) < 0.003


def test_a_map_painted_in_the_same_pan_hides_the_readout_unless_its_painting_is_modelled():
    """A map painted during the same pan carries the same shear: against it the frame looks
    sheared by the readout's error only through the difference of the two frames' row motions.
    With the painting modelled the reading is the true readout; left out, it is pulled to the
    readout used (what kept a first version of the estimator at a third of the truth)."""
    rng = np.random.default_rng(5)
    omega = np.array([0.05, 0.8, 0.0])
    def pan_rows(v: np.ndarray) -> np.ndarray:  # a pan keeps a point on about the same row
        return np.clip(v + rng.normal(scale=0.03, size=v.size), 0.0, 1.0)

    fit, paint = _frame(rng, 0.030, 0.0, omega, (0.7 * omega, 0.0, pan_rows))
    modelled, info = frame_reading(fit, omega, 0.0, paint)
    ignored, _ = frame_reading(fit, omega, 0.0)
    assert modelled == pytest.approx(0.030, abs=max(3.0 / np.sqrt(info), 0.002))
    assert ignored < 0.6 * 0.030


def test_the_estimator_settles_on_the_readout_and_says_zero_for_a_global_shutter():
    rng = np.random.default_rng(11)
    for truth in (0.025, 0.0):
        est, used = ReadoutEstimator(), 0.0
        for _ in range(80):
            omega = rng.normal(size=3) * [0.2, 0.8, 0.1]
            fit, paint = _frame(rng, truth, used, omega, (rng.normal(size=3) * [0.2, 0.8, 0.1], used, lambda v: v))
            est.add(used, omega, np.eye(3), fit, paint)
            used = est.readout(0.0)
        value, sigma = est.estimate()  # type: ignore[misc]
        assert used == pytest.approx(truth, abs=0.002), (truth, value, sigma)
        if truth == 0.0:
            assert used == 0.0


def test_no_reading_without_rotation_or_enough_inliers():
    rng = np.random.default_rng(2)
    est = ReadoutEstimator(ReadoutConfig(min_rate_rad_s=0.1))
    fit, _ = _frame(rng, 0.03, 0.0, np.array([0.0, 0.9, 0.0]), None)
    est.add(0.0, np.array([0.0, 0.05, 0.0]), np.eye(3), fit)  # turning too slowly
    est.add(0.0, np.array([0.0, 0.9, 0.0]), np.eye(3), RowFit(fit.rays[:5], fit.residuals[:5], fit.rows[:5],
                                                                fit.keypoints[:5]))
    est.add(0.0, np.array([np.nan, 0.9, 0.0]), np.eye(3), fit)
    assert est.frames == 0 and est.estimate() is None and est.readout(0.01) == 0.01


def test_an_estimate_in_use_is_kept_while_scattered_readings_widen_its_sigma():
    """Once used, the estimate is replaced only by a later one that passes the same test: readings
    that scatter widely for a while (a sudden stop between two frames) do not send the readout
    back to the configured 0, which would shear the frames again."""
    rng = np.random.default_rng(7)
    est, used = ReadoutEstimator(ReadoutConfig(memory_readings=10.0, apply_sigma_s=3e-4)), 0.0
    for _ in range(15):
        omega = rng.normal(size=3) * [0.2, 0.8, 0.1]
        est.add(used, omega, np.eye(3), _frame(rng, 0.025, used, omega, None)[0])
        used = est.readout(0.0)
    assert used == pytest.approx(0.025, abs=0.002)
    widened = False
    for k in range(12):
        omega = rng.normal(size=3) * [0.2, 0.8, 0.1]
        est.add(used, omega, np.eye(3), _frame(rng, (0.0, 0.05)[k % 2], used, omega, None, noise=3e-3)[0])
        widened |= est.estimate()[1] > est.config.apply_sigma_s  # type: ignore[index]
        assert est.readout(0.0) != 0.0
    assert widened
    assert ReadoutEstimator().readout(0.01) == 0.01  # nothing used yet: the configured value
