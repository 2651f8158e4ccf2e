"""core.box_sums: the box sums of the panorama tracker's NCC and the SLAM patch search's ZSSD."""
from __future__ import annotations

import numpy as np
import pytest

from ar_tracking.core.box_sums import window_box_sums


def brute_force(windows: np.ndarray, P: int) -> tuple[np.ndarray, np.ndarray]:
    n, S, _ = windows.shape
    side = S - P + 1
    s1 = np.zeros((n, side, side))
    s2 = np.zeros((n, side, side))
    w = windows.astype(np.float64)
    for y in range(side):
        for x in range(side):
            box = w[:, y:y + P, x:x + P]
            s1[:, y, x] = box.sum(axis=(1, 2))
            s2[:, y, x] = (box * box).sum(axis=(1, 2))
    return s1, s2


@pytest.mark.parametrize('dtype', [np.uint8, np.float32])
@pytest.mark.parametrize('n, S, P', [(1, 9, 9), (60, 17, 9), (80, 16, 8), (7, 12, 5)])
def test_box_sums_equal_direct_sums_exactly(dtype, n, S, P):
    rng = np.random.default_rng(n * 100 + S)
    windows = rng.integers(0, 256, size=(n, S, S)).astype(dtype)
    windows[0] = 255  # the largest values: still exact
    s1, s2 = window_box_sums(windows, P)
    e1, e2 = brute_force(windows, P)
    assert s1.shape == s2.shape == (n, S - P + 1, S - P + 1)
    assert s1.dtype == s2.dtype == np.float64
    # integers, so exactly equal (the tracker's outputs depend on every bit)
    assert np.array_equal(s1, e1) and np.array_equal(s2, e2)


def test_windows_from_a_strided_gather_and_no_windows():
    rng = np.random.default_rng(3)
    image = rng.integers(0, 256, size=(60, 80)).astype(np.uint8)
    # the tracker's windows: a gather from a sliding-window view of the frame
    windows = np.lib.stride_tricks.sliding_window_view(image, (11, 11))[[3, 20, 40], [5, 30, 60]]
    s1, s2 = window_box_sums(windows, 7)
    e1, e2 = brute_force(np.ascontiguousarray(windows), 7)
    assert np.array_equal(s1, e1) and np.array_equal(s2, e2)
    a, b = window_box_sums(np.zeros((0, 11, 11), np.uint8), 7)
    assert a.shape == b.shape == (0, 5, 5)
    with pytest.raises(ValueError):
        window_box_sums(np.zeros((2, 11, 10), np.uint8), 7)
