"""quat_xyzw_to_matrix of one quaternion is the closed-form unit-quaternion matrix (normalised
first), written out instead of going through scipy per call (stacks still go through scipy): it
agrees with scipy's Rotation.from_quat(q).as_matrix() on random quaternions of any norm, one at a
time and in stacks, and rejects what scipy rejects."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ar_tracking.core.rotations import quat_xyzw_to_matrix


def scipy_matrix(q) -> np.ndarray:
    return Rotation.from_quat(np.asarray(q, dtype=float)).as_matrix()


def random_quats(seed: int, shape: tuple[int, ...]) -> np.ndarray:
    """Gaussian quaternions (uniform rotations) scaled to norms from 1e-3 to 1e3, with some
    exact unit ones and some with zero components."""
    rng = np.random.default_rng(seed)
    q = rng.normal(size=shape + (4,))
    q *= 10.0 ** rng.uniform(-3, 3, size=shape + (1,))
    flat = q.reshape(-1, 4)
    flat[::7] /= np.linalg.norm(flat[::7], axis=1, keepdims=True)
    flat[1::11, rng.integers(0, 4)] = 0.0
    return q


def test_single_quaternions_match_scipy():
    for q in random_quats(1, (400,)):
        R = quat_xyzw_to_matrix(q)
        assert R.shape == (3, 3)
        np.testing.assert_array_equal(R, scipy_matrix(q))  # scipy's own arithmetic, bit for bit
        # a rotation: orthonormal with determinant +1
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize('shape', [(1,), (1000,), (5, 7), (2, 3, 4)])
def test_stacks_match_scipy(shape):
    q = random_quats(2, shape)
    R = quat_xyzw_to_matrix(q)
    assert R.shape == shape + (3, 3)
    np.testing.assert_array_equal(R, scipy_matrix(q))  # stacks go through scipy
    # each row of a stack is its single-quaternion matrix
    np.testing.assert_allclose(R.reshape(-1, 3, 3)[3 % R.shape[0]], quat_xyzw_to_matrix(q.reshape(-1, 4)[3 % R.shape[0]]),
                               rtol=0, atol=1e-15)


def test_lists_integers_and_empty_stacks():
    np.testing.assert_allclose(quat_xyzw_to_matrix([1, 2, 3, 4]), scipy_matrix([1, 2, 3, 4]), rtol=0, atol=1e-12)
    np.testing.assert_allclose(quat_xyzw_to_matrix(np.float32([1, 2, 3, 4])), scipy_matrix(np.float32([1, 2, 3, 4])),
                               rtol=0, atol=1e-12)
    assert quat_xyzw_to_matrix(np.zeros((0, 4))).shape == (0, 3, 3)
    assert quat_xyzw_to_matrix([[0, 0, 0, 1]]).shape == (1, 3, 3)


@pytest.mark.parametrize('bad', [[0, 0, 0, 0], [[0, 0, 0, 1], [0, 0, 0, 0]], [np.nan, 0, 0, 1],
                                 [[0, 0, 0, 1], [0, np.nan, 0, 1]], [1, 2, 3], np.ones((3, 5))])
def test_rejects_what_scipy_rejects(bad):
    with pytest.raises(ValueError) as ours:
        quat_xyzw_to_matrix(bad)
    with pytest.raises(ValueError) as theirs:
        scipy_matrix(bad)
    assert str(ours.value) == str(theirs.value)
