"""Sums over every P x P box of many small image windows at once, from one integral image.

Normalised cross-correlation (the panorama tracker) and zero-mean SSD (the SLAM patch search)
both need, for each of n search windows and each placement of a P x P template inside it, the
sum of the window's pixels under the template and the sum of their squares. Computed here for
all windows with one ``cv2.integral2`` of the windows stacked vertically and the differences of
its rows and columns (no per-window call, no gather).

The windows need no separator rows: a box never spans two windows, so the four integral values
of a box differ only by rows of its own window. Pixel values are integers (8-bit images, or
8-bit values held in float32), so the float64 sums are exact integers (below 2**53 for any
realistic window count): the result equals summing every box directly, whatever the stacking.
"""
from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def box_sums(integral: NDArray[np.int32 | np.float64], n: int, S: int, P: int) -> Array:
    """(n, S - P + 1, S - P + 1) sums of the P x P boxes at every offset of n (S, S) windows
    stacked vertically, whose integral image ((n S + 1), (S + 1)) is ``integral`` (int32 or
    float64 holding integers), as float64.

    The rows' difference first, over whole rows of the integral (one contiguous pass, which also
    forms the boxes that straddle two windows and are dropped), then the columns', then the
    boxes of each window picked: integer values throughout, so the same sums as adding the four
    corners in any order, at about two thirds of the time of four strided window views."""
    side = S - P + 1
    integral = np.asarray(integral)
    rows = integral[P:] - integral[:-P]
    boxes = rows[:, P:] - rows[:, :-P]
    rs, cs = boxes.strides
    return np.ndarray((n, side, side), boxes.dtype, boxes, 0, (S * rs, rs, cs)).astype(np.float64)


def window_box_sums(windows: NDArray[np.uint8 | np.float32], P: int) -> tuple[Array, Array]:
    """Sums of the values and of their squares in every P x P box of n S x S windows
    (``windows`` (n, S, S), uint8 or float32 holding integer values): two float64 arrays
    (n, S - P + 1, S - P + 1), exact (see the module docstring)."""
    n, S, S2 = windows.shape
    if S != S2 or not 0 < P <= S:
        raise ValueError(f'windows must be (n, S, S) with 0 < P <= S, got {windows.shape} and P={P}')
    if n == 0:
        empty = np.zeros((0, S - P + 1, S - P + 1))
        return empty, empty.copy()
    stacked: NDArray[np.uint8 | np.float32] = np.ascontiguousarray(windows).reshape(n * S, S)
    # uint8 windows: the sums as int32 (exact below 2**31, and OpenCV's 8u -> 32s integral is
    # vectorised: 9 us for the tracker's 60 windows against 64 us for 8u -> 64f), then float64.
    sdepth = cv2.CV_32S if stacked.dtype == np.uint8 else cv2.CV_64F
    total, squares = cv2.integral2(stacked, sdepth=sdepth, sqdepth=cv2.CV_64F)
    # np.asarray only narrows OpenCV's MatLike type (no copy); the int32 sums of uint8 windows
    # are differenced as integers and converted at the end (exact integers either way).
    return box_sums(np.asarray(total), n, S, P), box_sums(np.asarray(squares), n, S, P)
